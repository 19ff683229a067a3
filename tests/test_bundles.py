"""The kernels' five input bundles: field names, order and numba types of the named tuples the kernels take are
pinned here; the kernels read them by name; bad fields are refused by name."""

from __future__ import annotations

import numpy as np
import pytest
from numba import typeof

from gpmppi.mppi import bundles
from gpmppi.mppi.bundles import CRITICS, CostBundle, ModelBundle, Outputs, SamplingBundle, TaskBundle
from gpmppi.mppi.critics.registry import layout
from gpmppi.mppi.lane import build_lane_lookup

A1, A2, A3 = "array(float64, 1d, C)", "array(float64, 2d, C)", "array(float64, 3d, C)"

# bundle, its named tuple, fields in order with their numba types
PINNED = {
    ModelBundle: (bundles.ModelArgs, [
        ("dyn_mode", "int64"), ("theta", A1), ("lateral", A1), ("edd5", A1), ("gp_mode", "int64"),
        ("table", "array(float32, 2d, C)"), ("dims", "array(int64, 1d, C)"), ("lo", A1), ("inv_step", A1),
        ("ex_scaled_x", A3), ("ex_inv_ls", A2), ("ex_outputscale", A1), ("ex_alpha", A2), ("ex_chol", A3),
        ("terrain_w", A1), ("table_src", "array(float32, 2d, C)"), ("lazy", "array(int64, 1d, C)"),
        ("collapse_w", A1),
    ]),
    TaskBundle: (bundles.TaskArgs, [
        ("kind", "int64"), ("seg", A2), ("cell_start", "array(int64, 1d, C)"), ("candidates", "array(int32, 1d, C)"),
        ("field", A3), ("origin", A1), ("inv_cell", "float64"), ("half_width", "float64"), ("tightened_hw", A1),
        ("speed_target", "float64"), ("goal", A1), ("obstacles", A2), ("radii", A2),
        ("grid", "array(float32, 3d, C)"), ("grid_frame", A1),
    ]),
    SamplingBundle: (bundles.SamplingArgs, [
        ("x0", A1), ("nominal", A2), ("noise_std", A1), ("u_lo", A1), ("u_hi", A1), ("dt", "float64"),
        ("seed", "int64"), ("iteration", "int64"), ("noise_memory", "float64"), ("u_prev", A1), ("rate_step", A1),
    ]),
    Outputs: (bundles.OutputArgs, [("eps_out", "array(float32, 3d, C)"), ("cost_out", A1), ("xy_out", A3)]),
}


def model_bundle(**changes: object) -> ModelBundle:
    fields = dict(dyn_mode=2, theta=np.ones(6), lateral=np.zeros(2), edd5=np.ones(5), gp_mode=2,
                  **ModelBundle.no_grid(), **ModelBundle.no_exact(6), terrain_w=np.full(3, 1 / 3))
    return ModelBundle(**{**fields, **changes})


def examples() -> dict[type, object]:
    lane = build_lane_lookup(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]), False, 1.0)
    return {
        ModelBundle: model_bundle(),
        TaskBundle: TaskBundle.for_lane(lane, 1.0, np.ones(5), 1.5),
        SamplingBundle: SamplingBundle(x0=np.zeros(5), nominal=np.zeros((4, 2)), noise_std=np.ones(2), noise_memory=0.5,
                                       u_lo=np.zeros(2), u_hi=np.ones(2), dt=0.1, seed=3, iteration=2,
                                       u_prev=np.zeros(2), rate_step=np.full(2, 0.3)),
        Outputs: Outputs.allocate(8, 4, 2),
    }


@pytest.mark.parametrize("cls", list(PINNED), ids=lambda c: c.__name__)
def test_fields_order_types_and_named_tuples_are_pinned(cls: type) -> None:
    named, pinned = PINNED[cls]
    names = [name for name, _ in pinned]
    assert list(cls.SPECS) == names
    args = examples()[cls].args()
    assert type(args) is named and named._fields == tuple(names)
    assert [str(t) for t in typeof(args).types] == [t for _, t in pinned]
    assert typeof(args).fields == tuple(names)  # numba reads each field by its name


def test_the_goal_task_has_the_lane_tasks_types() -> None:
    # one compiled kernel serves both tasks: the dummies have the real fields' types
    goal = TaskBundle.for_goal(np.array([5.0, 1.0]), np.array([[1.0, 1.0, 0.5]]), np.ones((5, 1)), None)
    assert typeof(goal.args()) == typeof(examples()[TaskBundle].args())


def test_swapped_fields_are_refused_naming_the_field() -> None:
    good = model_bundle()
    with pytest.raises(ValueError, match=r"ModelBundle\.dims must be int64"):
        model_bundle(dims=good.lo, lo=good.dims).args()
    with pytest.raises(ValueError, match=r"ModelBundle\.theta must be a numpy array \(float64, 1-D\), got int"):
        model_bundle(gp_mode=good.theta, theta=2).args()
    with pytest.raises(ValueError, match=r"SamplingBundle\.seed must be a int64 scalar, got float"):
        SamplingBundle(**{**vars(examples()[SamplingBundle]), "seed": 0.1, "dt": 3}).args()


def test_non_contiguous_read_only_and_positional_fields_are_refused_naming_the_field() -> None:
    with pytest.raises(ValueError, match=r"ModelBundle\.theta must be C-contiguous"):
        model_bundle(theta=np.ones(12)[::2]).args()
    out = examples()[Outputs]
    frozen = out.cost_out.copy()
    frozen.flags.writeable = False
    with pytest.raises(ValueError, match=r"Outputs\.cost_out is written by the kernels but is read-only"):
        Outputs(eps_out=out.eps_out, cost_out=frozen, xy_out=out.xy_out).args()
    read_only = np.ones(6)
    read_only.flags.writeable = False
    assert model_bundle(theta=read_only).args().theta is read_only  # inputs may be read-only
    with pytest.raises(TypeError, match="given by position: eps_out, cost_out"):
        Outputs(out.eps_out, out.cost_out, xy_out=out.xy_out)  # type: ignore[misc]


def test_cost_bundle_takes_weights_by_critic_name() -> None:
    weights = {name: float(i + 1) for i, name in enumerate(CRITICS)}
    cost = CostBundle.from_weights(weights, {"lane_exit": {"discount": 0.8}, "speed": {"along_lane": False}}, True)
    assert cost.weights == weights and cost.params["lane_exit"] == {"discount": 0.8}
    # the cost vector: the goal switch, the weights in CRITICS order, the critics' parameters
    assert cost.args() == (1.0, *weights.values(), 0.8, 0.0, 0.01)
    assert typeof(cost.args()) == typeof((1.0,) * bundles.N_COST_TERMS)
    assert cost.args()[layout().param_index("lane_exit", "discount")] == 0.8
    assert cost.args()[bundles.K_GOAL_GEODESIC] == 1.0
    assert CostBundle.from_weights(weights).params == {**{n: {} for n in CRITICS}, "lane_exit": {"discount": 0.9},
                                                       "speed": {"along_lane": True},
                                                       "costmap": {"value_scale": 0.01}}
    with pytest.raises(ValueError, match=r"unknown \['slippage'\], missing \['slip'\]"):
        CostBundle.from_weights({**{k: v for k, v in weights.items() if k != "slip"}, "slippage": 1.0})
    with pytest.raises(ValueError, match=r"parameters of unknown critics \['slippage'\]"):
        CostBundle.from_weights(weights, {"slippage": {"x": 1.0}})
