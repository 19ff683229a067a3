"""The rollout kernels' inputs as five bundles: model, task, sampling, cost weights, outputs.

The cost bundle's layout derives from the registered critics (`gpmppi.mppi.critics`).

Each bundle is a frozen, keyword-only dataclass; `.args()` checks every field against the bundle's
`SPECS` (dtype, number of dimensions, C-contiguous, writeable where the kernels write) and returns
the named tuple the kernels take (`ModelArgs`, `TaskArgs`, `SamplingArgs`, `OutputArgs`, made from `SPECS`:
numba compiles a named tuple as a tuple and reads its fields by name, `model.theta`, at compile time). No
kernel indexes a bundle by position. `tests/test_bundles.py` pins names, order and numba types.

The arrays a mode does not use (a grid table for the exact GP, the lane lookup for a goal task)
still have to be arrays of the right type, so that one compiled kernel serves every mode; they are
built here, by the classmethods, and nowhere else.
"""

from __future__ import annotations

from collections import namedtuple
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any, ClassVar, NamedTuple

import numpy as np

from gpmppi.costmap import NO_GRID, Costmap
from gpmppi.mppi.critics import registry
from gpmppi.mppi.critics.base import TASK_GOAL, TASK_KINDS, TASK_LANE, W_GOAL_GEODESIC
from gpmppi.mppi.goal_field import GoalField
from gpmppi.mppi.lane import LaneLookup

__all__ = [
    "CRITICS", "K_GOAL_GEODESIC", "N_COST_TERMS", "TASK_GOAL", "TASK_LANE", "CostBundle",
    "FieldSpec", "ModelArgs", "ModelBundle", "OutputArgs", "Outputs", "SamplingArgs", "SamplingBundle", "TaskArgs",
    "TaskBundle",
]

# the registered critics (`gpmppi.mppi.critics`), each with its own weight, in the kernels' order
_LAYOUT = registry.layout()
_KERNEL_TASK_KINDS = frozenset(TASK_KINDS.values())
CRITICS = _LAYOUT.names


class FieldSpec(NamedTuple):
    """What a bundle field must be: a numpy dtype and ndim (0 = a scalar of that kind), written by the kernels."""

    dtype: str
    ndim: int
    written: bool = False


_SCALAR_TYPES = {"int64": (int, np.integer), "float64": (float, int, np.floating, np.integer), "bool": (bool, np.bool_)}
_SCALAR_CAST = {"int64": np.int64, "float64": float, "bool": bool}


def _checked(bundle: str, name: str, spec: FieldSpec, value: Any) -> Any:
    """`value` as the kernels take it, or a ValueError naming the field and what it should be."""
    if spec.ndim == 0:
        kinds = _SCALAR_TYPES[spec.dtype]
        # bools are ints to Python: an int field must not take one (nor a float field)
        if isinstance(value, np.ndarray) or not isinstance(value, kinds) or (
                spec.dtype != "bool" and isinstance(value, (bool, np.bool_))):
            raise ValueError(f"{bundle}.{name} must be a {spec.dtype} scalar, got {type(value).__name__}")
        return _SCALAR_CAST[spec.dtype](value)
    if not isinstance(value, np.ndarray):
        raise ValueError(f"{bundle}.{name} must be a numpy array ({spec.dtype}, {spec.ndim}-D), got "
                         f"{type(value).__name__}")
    if value.dtype != spec.dtype or value.ndim != spec.ndim:
        raise ValueError(f"{bundle}.{name} must be {spec.dtype} with {spec.ndim} dimensions, got {value.dtype} "
                         f"with shape {value.shape}")
    if not value.flags.c_contiguous:
        raise ValueError(f"{bundle}.{name} must be C-contiguous (np.ascontiguousarray)")
    if spec.written and not value.flags.writeable:
        raise ValueError(f"{bundle}.{name} is written by the kernels but is read-only")
    return value


class _Bundle:
    """`.args()`: the fields in declaration order, each checked against `SPECS`, as the bundle's `ARGS` named tuple."""

    SPECS: ClassVar[dict[str, FieldSpec]]
    ARGS: ClassVar[type]

    def __new__(cls, *args: Any, **kwargs: Any) -> _Bundle:
        # the dataclass's own error for positional arguments names no field; this one names them
        if args:
            given = ", ".join(list(cls.SPECS)[:len(args)])
            raise TypeError(f"{cls.__name__} takes its fields by keyword only; given by position: {given}")
        return super().__new__(cls)

    def args(self) -> tuple:
        cls = type(self).__name__
        return self.ARGS(*(_checked(cls, name, spec, getattr(self, name)) for name, spec in self.SPECS.items()))

    @classmethod
    def _check_specs(cls) -> None:
        names = tuple(f.name for f in fields(cls))
        if names != tuple(cls.SPECS):
            raise TypeError(f"{cls.__name__}: SPECS {tuple(cls.SPECS)} do not list the fields {names} in order")


# ------------------------------------------------------------------------------------------------ model
@dataclass(frozen=True, kw_only=True)
class ModelBundle(_Bundle):
    """The rollout model: dynamics choice and parameters, and the GP residual (grid table or exact GP)."""

    dyn_mode: int  # `dynamics.DYN_*`
    theta: np.ndarray  # (6,) nominal dynamic unicycle parameters
    lateral: np.ndarray  # (2,) terrain-weighted lateral slip coefficients (`gpmppi.models.lateral_slip`)
    edd5: np.ndarray  # (5,) EDD5 parameters of the chosen terrain
    gp_mode: int  # `dynamics.GP_*`
    table: np.ndarray  # (nodes, 4) float32 collapsed GP table, axes in `gp_table.TABLE_AXES` order
    dims: np.ndarray  # (4,) int64 grid nodes per axis
    lo: np.ndarray  # (4,) grid lower corner, same order
    inv_step: np.ndarray  # (4,) 1 / grid step, same order
    ex_scaled_x: np.ndarray  # (2M, n, 4) exact GP: training inputs / lengthscales
    ex_inv_ls: np.ndarray  # (2M, 4) exact GP: 1 / lengthscales
    ex_outputscale: np.ndarray  # (2M,) exact GP: output scales
    ex_alpha: np.ndarray  # (2M, n) exact GP: K^-1 y
    ex_chol: np.ndarray  # (2M, n, n) exact GP: Cholesky factors of K
    terrain_w: np.ndarray  # (M,) terrain weights
    # a table collapsed lazily on the CPU (`lazy_collapse.ensure_block`): the per-terrain rows (nodes, 4M) float32, the
    # slab versions (int64; [0] = the weights' version, 0 when `table` is collapsed whole) and the factors to
    # collapse with (4 + 4M, `gp_table.collapse_weights`); a table collapsed whole carries a one-row `table_src`
    # and `lazy` = [0] (and `collapse_w` is not read). The CPU kernels write `table` and `lazy`.
    table_src: np.ndarray
    lazy: np.ndarray
    collapse_w: np.ndarray

    SPECS: ClassVar[dict[str, FieldSpec]] = {
        "dyn_mode": FieldSpec("int64", 0), "theta": FieldSpec("float64", 1), "lateral": FieldSpec("float64", 1),
        "edd5": FieldSpec("float64", 1), "gp_mode": FieldSpec("int64", 0),
        "table": FieldSpec("float32", 2, written=True),
        "dims": FieldSpec("int64", 1), "lo": FieldSpec("float64", 1), "inv_step": FieldSpec("float64", 1),
        "ex_scaled_x": FieldSpec("float64", 3), "ex_inv_ls": FieldSpec("float64", 2),
        "ex_outputscale": FieldSpec("float64", 1), "ex_alpha": FieldSpec("float64", 2),
        "ex_chol": FieldSpec("float64", 3), "terrain_w": FieldSpec("float64", 1),
        "table_src": FieldSpec("float32", 2), "lazy": FieldSpec("int64", 1, written=True),
        "collapse_w": FieldSpec("float64", 1),
    }

    @classmethod
    def no_grid(cls) -> dict[str, np.ndarray]:
        """The grid fields of a model that reads no grid table (a 2^4-node table of zeros)."""
        return {"table": np.zeros((16, 4), dtype=np.float32), "dims": np.full(4, 2, dtype=np.int64),
                "lo": np.zeros(4), "inv_step": np.ones(4), **cls.collapsed_whole()}

    @classmethod
    def collapsed_whole(cls) -> dict[str, np.ndarray]:
        """The lazy-collapse fields of a table collapsed whole (nothing left to collapse)."""
        return {"table_src": np.zeros((1, 4), dtype=np.float32), "lazy": np.zeros(1, dtype=np.int64),
                "collapse_w": np.zeros(3)}

    @classmethod
    def no_exact(cls, n_tasks: int) -> dict[str, np.ndarray]:
        """The exact-GP fields of a model that evaluates no exact GP (`n_tasks` = 2M, one training point each)."""
        return {"ex_scaled_x": np.zeros((n_tasks, 1, 4)), "ex_inv_ls": np.ones((n_tasks, 4)),
                "ex_outputscale": np.zeros(n_tasks), "ex_alpha": np.zeros((n_tasks, 1)),
                "ex_chol": np.ones((n_tasks, 1, 1))}


# ------------------------------------------------------------------------------------------------- task
@dataclass(frozen=True, kw_only=True)
class TaskBundle(_Bundle):
    """The task: a lane (lookup grid, half-widths, speed target) or a goal among obstacles (distance field, circles).

    `field`, `origin`, `inv_cell` are the lane lookup's grid for a lane and the goal-distance field's for a goal.
    """

    kind: int  # TASK_LANE or TASK_GOAL
    seg: np.ndarray  # (n, 5) lane segments
    cell_start: np.ndarray  # lane lookup: start of each cell's candidates (int64)
    candidates: np.ndarray  # lane lookup: candidate segments per cell (int32)
    field: np.ndarray  # (rows, cols, 3) lane distance and direction, or (rows, cols, 1+) goal distance [m]
    origin: np.ndarray  # (2,) the field grid's corner [m]
    inv_cell: float  # 1 / the field grid's cell [1/m]
    half_width: float  # lane half-width r [m]
    tightened_hw: np.ndarray  # (N+1,) tightened lane half-width per step [m]
    speed_target: float  # lane speed target [m/s]
    goal: np.ndarray  # (2,) goal position [m]
    obstacles: np.ndarray  # (K, 3) circles [x, y, r] [m]
    radii: np.ndarray  # (N+1, K) inflated obstacle radii per step [m]; (N+1, K+1) with a grid: its radius last
    grid: np.ndarray  # (H, W, 2) float32 occupancy grid: value / lethal, distance to the nearest lethal cell [m]
    grid_frame: np.ndarray  # (6,) the grid's frame: 1 (0: no grid), origin x, y [m], cos, sin yaw, 1 / res [1/m]

    SPECS: ClassVar[dict[str, FieldSpec]] = {
        "kind": FieldSpec("int64", 0), "seg": FieldSpec("float64", 2), "cell_start": FieldSpec("int64", 1),
        "candidates": FieldSpec("int32", 1), "field": FieldSpec("float64", 3), "origin": FieldSpec("float64", 1),
        "inv_cell": FieldSpec("float64", 0), "half_width": FieldSpec("float64", 0),
        "tightened_hw": FieldSpec("float64", 1), "speed_target": FieldSpec("float64", 0),
        "goal": FieldSpec("float64", 1), "obstacles": FieldSpec("float64", 2), "radii": FieldSpec("float64", 2),
        "grid": FieldSpec("float32", 3), "grid_frame": FieldSpec("float64", 1),
    }

    def args(self) -> tuple:
        """The fields as the kernels take them; a ValueError for a kind the kernels have no critics for (they score
        `TASK_LANE` with the lane critics and every other kind with the goal critics)."""
        if self.kind not in _KERNEL_TASK_KINDS:
            raise ValueError(f"TaskBundle.kind must be one of the kernels' task kinds {TASK_KINDS}, got {self.kind!r}; "
                             "a new task kind scores its tasks with one of these critic chains (`task_kinds.TaskKind`)")
        return super().args()

    @classmethod
    def for_lane(cls, lane: LaneLookup, half_width: float, tightened: np.ndarray, speed: float) -> TaskBundle:
        """A lane task; the goal fields are empty (no obstacles)."""
        return cls(kind=TASK_LANE, seg=lane.segments, cell_start=lane.cell_start, candidates=lane.candidates,
                   field=lane.field, origin=lane.origin, inv_cell=float(lane.inv_cell), half_width=float(half_width),
                   tightened_hw=np.ascontiguousarray(tightened, dtype=np.float64), speed_target=float(speed),
                   goal=np.zeros(2), obstacles=np.zeros((0, 3)), radii=np.zeros((tightened.shape[0], 0)),
                   grid=NO_GRID[0], grid_frame=NO_GRID[1])

    @classmethod
    def for_types(cls, horizon: int) -> TaskBundle:
        """A task with every field of its type and nothing in it (a goal with no obstacles and no field, bounds
        for `horizon` steps): the kernels compile the same code for every task bundle, and this one is built
        without compiling anything (`compile_ahead` hands it to the process that compiles the rollout kernel)."""
        return cls.for_goal(np.zeros(2), np.zeros((0, 3)), np.zeros((horizon + 1, 0)), None)

    @classmethod
    def for_goal(
        cls, goal: np.ndarray, obstacles: np.ndarray, radii: np.ndarray, goal_field: GoalField | None,
        costmap: Costmap | None = None,
    ) -> TaskBundle:
        """A goal task; `goal_field` None: no geodesic field (the cost bundle must then select the straight line);
        `costmap` an occupancy grid (its radius per step the last column of `radii`)."""
        no_seg = np.zeros((1, 5))
        no_seg[0, 4] = 1.0
        field, origin, inv_cell = (
            (np.zeros((1, 1, 3)), np.zeros(2), 1.0) if goal_field is None
            else (goal_field.field, goal_field.origin, goal_field.inv_cell)
        )
        grid, grid_frame = NO_GRID if costmap is None else costmap.kernel_arrays()
        if radii.shape[1] != obstacles.shape[0] + (costmap is not None):
            raise ValueError(f"TaskBundle radii: {radii.shape[1]} columns for {obstacles.shape[0]} circles "
                             f"{'and a grid' if costmap is not None else 'and no grid'}")
        return cls(kind=TASK_GOAL, seg=no_seg, cell_start=np.zeros(2, dtype=np.int64),
                   candidates=np.zeros(0, dtype=np.int32), field=field, origin=origin, inv_cell=float(inv_cell),
                   half_width=1.0, tightened_hw=np.ones(radii.shape[0]), speed_target=0.0,
                   goal=np.ascontiguousarray(goal, dtype=np.float64),
                   obstacles=np.ascontiguousarray(obstacles, dtype=np.float64),
                   radii=np.ascontiguousarray(radii, dtype=np.float64), grid=grid, grid_frame=grid_frame)


# --------------------------------------------------------------------------------------------- sampling
@dataclass(frozen=True, kw_only=True)
class SamplingBundle(_Bundle):
    """Where the rollouts start and how their commands are drawn: nominal + noise, clipped to the limits, the first
    command also to the rate limits from the command in effect (`rng.sampled_command`)."""

    x0: np.ndarray  # (5,) start state [x m, y m, yaw rad, v m/s, omega rad/s]
    nominal: np.ndarray  # (N, 2) nominal sequence [v_ref m/s, omega_ref rad/s]
    noise_std: np.ndarray  # (2,) control noise std [m/s, rad/s]
    u_lo: np.ndarray  # (2,) lower control limits
    u_hi: np.ndarray  # (2,) upper control limits
    dt: float  # rollout step [s]
    seed: int  # noise seed
    iteration: int  # planner iteration (part of the noise counter)
    noise_memory: float  # AR(1) memory of the unit noise from step to step (0 = white; `rng.sampled_command`)
    u_prev: np.ndarray  # (2,) the command in effect before the sequence's first step [m/s, rad/s]
    rate_step: np.ndarray  # (2,) largest change of the first command from `u_prev` [m/s, rad/s]; inf: none

    SPECS: ClassVar[dict[str, FieldSpec]] = {
        "x0": FieldSpec("float64", 1), "nominal": FieldSpec("float64", 2), "noise_std": FieldSpec("float64", 1),
        "u_lo": FieldSpec("float64", 1), "u_hi": FieldSpec("float64", 1), "dt": FieldSpec("float64", 0),
        "seed": FieldSpec("int64", 0), "iteration": FieldSpec("int64", 0),
        "noise_memory": FieldSpec("float64", 0), "u_prev": FieldSpec("float64", 1),
        "rate_step": FieldSpec("float64", 1),
    }


# ------------------------------------------------------------------------------------------------- cost
# the cost vector the kernels read (`registry.CriticLayout`): the goal-distance switch, each critic's weight, each
# critic's parameters
K_GOAL_GEODESIC = W_GOAL_GEODESIC
N_COST_TERMS = _LAYOUT.size


@dataclass(frozen=True)
class CostBundle:
    """Each critic's weight and parameters, by name (every registered critic, `CRITICS`), and whether the goal
    critics measure the distance around the obstacles. `.args()`: the cost vector as a tuple of floats (a bool as
    1.0 / 0.0), in `registry.CriticLayout` order."""

    weights: Mapping[str, float]
    params: Mapping[str, Mapping[str, float | bool]]
    goal_geodesic: bool

    def __post_init__(self) -> None:
        unknown = sorted(set(self.weights) - set(CRITICS))
        missing = [name for name in CRITICS if name not in self.weights]
        if unknown or missing:
            raise ValueError(f"critic weights: unknown {unknown}, missing {missing}; the critics are {list(CRITICS)}")
        for c in _LAYOUT.critics:
            given = dict(self.params.get(c.name, {}))
            if set(given) != set(c.params):
                raise ValueError(f"critic {c.name!r} parameters: given {sorted(given)}, expected {sorted(c.params)}")
        extra = sorted(set(self.params) - set(CRITICS))
        if extra:
            raise ValueError(f"parameters of unknown critics {extra}; the critics are {list(CRITICS)}")

    @classmethod
    def from_weights(
        cls, weights: Mapping[str, float], params: Mapping[str, Mapping[str, float | bool]] | None = None,
        goal_geodesic: bool = True,
    ) -> CostBundle:
        """Weights by critic name; parameters by critic and name, each critic's defaults where not given."""
        given = params or {}
        full = {c.name: {p: given.get(c.name, {}).get(p, spec.default) for p, spec in c.params.items()}
                for c in _LAYOUT.critics}
        extra = sorted(set(given) - set(CRITICS))
        if extra:
            raise ValueError(f"parameters of unknown critics {extra}; the critics are {list(CRITICS)}")
        return cls({name: float(weights[name]) for name in weights}, full, bool(goal_geodesic))

    def with_weight(self, name: str, weight: float) -> CostBundle:
        """This bundle with critic `name`'s weight replaced."""
        return CostBundle({**self.weights, name: float(weight)}, self.params, self.goal_geodesic)

    def args(self) -> tuple[float, ...]:
        values = [0.0] * N_COST_TERMS
        values[K_GOAL_GEODESIC] = 1.0 if self.goal_geodesic else 0.0
        for c in _LAYOUT.critics:
            values[_LAYOUT.weight_index(c.name)] = float(self.weights[c.name])
            for p in c.params:
                values[_LAYOUT.param_index(c.name, p)] = float(self.params[c.name][p])
        return tuple(values)


# ---------------------------------------------------------------------------------------------- outputs
@dataclass(frozen=True, kw_only=True)
class Outputs(_Bundle):
    """What the rollout kernels write: per sample the applied perturbation, the total cost, and some XY."""

    eps_out: np.ndarray  # (S, N, 2) float32 clipped command minus nominal
    cost_out: np.ndarray  # (S,) total cost
    xy_out: np.ndarray  # (n_xy, N+1, 2) XY of the first n_xy rollouts [m]

    SPECS: ClassVar[dict[str, FieldSpec]] = {
        "eps_out": FieldSpec("float32", 3, written=True), "cost_out": FieldSpec("float64", 1, written=True),
        "xy_out": FieldSpec("float64", 3, written=True),
    }

    @classmethod
    def allocate(cls, samples: int, horizon: int, n_xy: int) -> Outputs:
        return cls(eps_out=np.empty((samples, horizon, 2), dtype=np.float32), cost_out=np.empty(samples),
                   xy_out=np.empty((n_xy, horizon + 1, 2)))


for _cls in (ModelBundle, TaskBundle, SamplingBundle, Outputs):
    _cls._check_specs()

# the kernels' inputs: each bundle's fields by name (module-level names, so that they pickle for `compile_ahead`)
ModelArgs = ModelBundle.ARGS = namedtuple("ModelArgs", list(ModelBundle.SPECS))
TaskArgs = TaskBundle.ARGS = namedtuple("TaskArgs", list(TaskBundle.SPECS))
SamplingArgs = SamplingBundle.ARGS = namedtuple("SamplingArgs", list(SamplingBundle.SPECS))
OutputArgs = Outputs.ARGS = namedtuple("OutputArgs", list(Outputs.SPECS))
