"""The simulated plants: physics skid-steer plant, terrain files, the paper's residual-network plant."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gpmppi.models.dynamic_unicycle import velocity_step_exact
from gpmppi.models.identify import identify_theta, one_step_pairs
from gpmppi.plant import PhysicsPlant, Plant, ResidualNetPlant, TerrainFileError, load_terrains
from gpmppi.plant.excitation import drive
from gpmppi.plant.residual_net import NetworkFileError, load_residual_net

DT = 0.1
THETA = np.array([0.25, 0.30, 0.04, 1.0, 0.15, 1.1])  # a plausible made-up nominal model


@pytest.fixture(scope="module")
def terrains():
    return load_terrains()


def run(plant: PhysicsPlant, command: tuple[float, float], seconds: float) -> np.ndarray:
    plant.reset(np.zeros(5))
    states = [plant.step(np.array(command), DT) for _ in range(int(round(seconds / DT)))]
    return np.array(states)


def test_shipped_terrains_load(terrains) -> None:
    assert {"tile", "asphalt", "grass", "sand"} <= set(terrains.names)
    assert terrains.robot.mass == pytest.approx(17.0)
    with pytest.raises(KeyError, match="unknown terrain 'mud'"):
        terrains.get("mud")


def test_malformed_terrain_file_names_file_and_field(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        "terrains:\n  tile: {mu_long: -1.0, mu_lat: 0.5, slip_scale_long: 0.1, slip_scale_lat: 0.1, rolling: 0.01}\n"
    )
    with pytest.raises(TerrainFileError, match=r"bad\.yaml.*terrains\.tile\.mu_long"):
        load_terrains(bad)
    unknown = tmp_path / "unknown.yaml"
    unknown.write_text("terrains:\n  tile: {mu_long: 0.5, mu_lat: 0.5, slip_scale_long: 0.1, slip_scale_lat: 0.1, "
                       "rolling: 0.01, grip: 3}\n")
    with pytest.raises(TerrainFileError, match=r"unknown\.yaml.*terrains\.tile\.grip"):
        load_terrains(unknown)
    with pytest.raises(TerrainFileError, match="missing.yaml"):
        load_terrains(tmp_path / "missing.yaml")


def test_physics_plant_implements_protocol(terrains) -> None:
    assert isinstance(PhysicsPlant(terrains, "tile"), Plant)
    with pytest.raises(KeyError):
        PhysicsPlant(terrains, "mud")


def test_straight_line_reaches_command_on_high_grip(terrains) -> None:
    states = run(PhysicsPlant(terrains, "asphalt", noise=False), (1.0, 0.0), 3.0)
    assert states[-1, 3] == pytest.approx(1.0, abs=0.03)
    assert abs(states[-1, 4]) < 1e-6 and abs(states[-1, 1]) < 1e-6
    assert states[-1, 0] == pytest.approx(2.7, abs=0.3)  # ~3 s at ~1 m/s minus the start-up


def test_turning_in_place_yaws(terrains) -> None:
    plant = PhysicsPlant(terrains, "tile", noise=False)
    states = run(plant, (0.0, 1.5), 2.0)
    assert states[-1, 4] > 0.7  # yaw rate follows the command (with skid losses)
    assert np.hypot(states[-1, 0], states[-1, 1]) < 0.02  # turns about its centre
    assert abs(states[-1, 3]) < 0.02
    turned = np.unwrap(states[:, 2])[-1]
    assert turned > 1.0


def test_sand_slips_more_than_tile(terrains) -> None:
    command = (1.0, 1.0)
    finals = {name: run(PhysicsPlant(terrains, name, noise=False), command, 4.0)[-1] for name in ("tile", "sand")}
    assert finals["sand"][4] < 0.8 * finals["tile"][4]  # lower effective yaw rate
    assert finals["sand"][3] < finals["tile"][3]
    # more longitudinal slip: wheel surface speed exceeds the body speed by more on sand
    slips = {}
    for name in ("tile", "sand"):
        plant = PhysicsPlant(terrains, name, noise=False)
        run(plant, (1.0, 0.0), 4.0)
        surface = plant.wheel_speeds.mean() * terrains.robot.wheel_radius
        slips[name] = surface - plant.state()[3]
    assert slips["sand"] > 3 * slips["tile"] > 0


def test_determinism_per_seed(terrains) -> None:
    def measured(seed: int) -> np.ndarray:
        plant = PhysicsPlant(terrains, "grass", seed=seed)
        plant.reset(np.zeros(5))
        out = []
        for k in range(30):
            plant.step(np.array([1.0, np.sin(0.3 * k)]), DT)
            out.append(plant.measure())
        return np.array(out)

    a, b, c = measured(3), measured(3), measured(4)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 1e-4
    noiseless = PhysicsPlant(terrains, "grass", noise=False)
    noiseless.reset(np.zeros(5))
    noiseless.step(np.array([1.0, 0.2]), DT)
    np.testing.assert_array_equal(noiseless.measure(), noiseless.state())


def test_plant_is_not_the_nominal_model(terrains) -> None:
    """Even with theta identified from the plant's own noise-free data, one-step residuals remain."""
    runs = {n: drive(PhysicsPlant(terrains, n, seed=i, noise=False), n, 150.0, seed=i)
            for i, n in enumerate(("tile", "grass"))}
    segs = list(runs.values())
    theta = identify_theta([r.state[:, 3] for r in segs], [r.state[:, 4] for r in segs],
                           [r.command[:, 0] for r in segs], [r.command[:, 1] for r in segs], DT)
    means = {}
    for name, r in runs.items():
        v, w, cv, cw, vn, wn = one_step_pairs(r.state[:, 3], r.state[:, 4], r.command[:, 0], r.command[:, 1])
        pv, pw = velocity_step_exact(theta, v, w, cv, cw, DT)
        assert np.sqrt(np.mean((vn - pv) ** 2)) > 0.005
        assert np.sqrt(np.mean((wn - pw) ** 2)) > 0.01
        means[name] = np.mean(vn - pv)
    # terrain-dependent, not just noise: grass's drag makes the nominal model overpredict v
    assert means["grass"] < means["tile"] - 0.005


def test_bad_commands_are_rejected(terrains) -> None:
    plant = PhysicsPlant(terrains, "tile")
    with pytest.raises(ValueError, match="finite"):
        plant.step(np.array([np.nan, 0.0]), DT)
    with pytest.raises(ValueError, match="positive"):
        plant.step(np.array([1.0, 0.0]), 0.0)
    with pytest.raises(ValueError, match="reset state"):
        plant.reset(np.zeros(4))


def _tiny_net(tmp_path: Path, with_names: bool) -> Path:
    rng = np.random.default_rng(0)
    layers = {
        "fc1.weight": rng.normal(size=(8, 4)).tolist(), "fc1.bias": rng.normal(size=8).tolist(),
        "fc2.weight": rng.normal(size=(8, 8)).tolist(), "fc2.bias": rng.normal(size=8).tolist(),
        "fc3.weight": rng.normal(size=(4, 8)).tolist(), "fc3.bias": rng.normal(size=4).tolist(),
    }
    scalers = {"input_mean": [0.5, 0.0, 0.5, 0.0], "input_scale": [0.4, 0.5, 0.4, 0.5],
               "output_mean": [0.0, 0.01, -0.01, 0.0], "output_scale": [0.02, 0.02, 0.03, 0.03]}
    raw = {"layers": layers, "scalers": scalers}
    if with_names:
        raw["terrains"] = ["Mud", "Snow"]
    path = tmp_path / "net.json"
    path.write_text(json.dumps(raw))
    return path


def test_residual_net_plant_step_is_nominal_plus_residual(tmp_path: Path) -> None:
    path = _tiny_net(tmp_path, with_names=True)
    plant = ResidualNetPlant(path, THETA, "snow", terrain_names=None)
    assert isinstance(plant, Plant)
    start = np.array([1.0, 2.0, 0.3, 0.8, 0.2])
    plant.reset(start)
    cmd = np.array([1.2, -0.4])
    out = plant.step(cmd, DT)
    res = plant.net(np.array([[1.2, -0.4, 0.8, 0.2]]))[0, 2:4]
    pv, pw = velocity_step_exact(THETA, start[3:4], start[4:5], cmd[:1], cmd[1:], DT)
    assert out[3] == pytest.approx(pv[0] + res[0], abs=1e-9)
    assert out[4] == pytest.approx(pw[0] + res[1], abs=1e-9)
    # the pose moved about v dt along the heading
    assert np.hypot(out[0] - 1.0, out[1] - 2.0) == pytest.approx(0.1 * 0.5 * (0.8 + out[3]), rel=0.05)
    np.testing.assert_array_equal(plant.measure(), out)  # noise free by default, like the paper's plant
    with pytest.raises(ValueError, match="multiple"):
        plant.step(cmd, 0.15)
    with pytest.raises(KeyError, match="unknown terrain"):
        plant.set_terrain("tile")
    with pytest.raises(ValueError, match="terrain_names"):
        ResidualNetPlant(_tiny_net(tmp_path, with_names=False), THETA, "snow")


def test_residual_net_file_errors(tmp_path: Path) -> None:
    path = _tiny_net(tmp_path, with_names=False)
    raw = json.loads(path.read_text())
    del raw["scalers"]["input_scale"]
    path.write_text(json.dumps(raw))
    with pytest.raises(NetworkFileError, match=r"net\.json.*scalers\.input_scale"):
        load_residual_net(path)
    with pytest.raises(NetworkFileError, match="cannot read"):
        load_residual_net(tmp_path / "nope.json")


def test_residual_net_forward_matches_torch(jackal: Path) -> None:
    torch = pytest.importorskip("torch")
    path = jackal / "fcnn.json"
    raw = json.loads(path.read_text())
    model = torch.nn.Sequential(
        torch.nn.Linear(4, 32), torch.nn.Tanh(), torch.nn.Linear(32, 32), torch.nn.Tanh(), torch.nn.Linear(32, 6)
    ).double()
    state = {f"{i}.{k}": torch.tensor(raw["layers"][f"fc{j}.{k}"], dtype=torch.float64)
             for i, j in ((0, 1), (2, 2), (4, 3)) for k in ("weight", "bias")}
    model.load_state_dict(state)
    sc = {k: np.asarray(v) for k, v in raw["scalers"].items()}
    x = np.random.default_rng(1).uniform([0, -1.5, 0, -1.5], [2, 1.5, 2, 1.5], size=(200, 4))
    with torch.no_grad():
        ref = model(torch.from_numpy((x - sc["input_mean"]) / sc["input_scale"])).numpy()
    ref = ref * sc["output_scale"] + sc["output_mean"]
    net = load_residual_net(path)
    np.testing.assert_allclose(net(x), ref, rtol=1e-10, atol=1e-12)
    plant = ResidualNetPlant(path, THETA, "Grass", terrain_names=["Asphalt", "Grass", "Tile"])
    plant.reset(np.array([0.0, 0.0, 0.0, 1.0, 0.0]))
    out = plant.step(np.array([1.0, 0.0]), 1.0)
    assert np.all(np.isfinite(out)) and 0.5 < out[3] < 1.5


def test_terrain_names_must_be_lower_case_words(tmp_path: Path) -> None:
    bad = tmp_path / "names.yaml"
    bad.write_text("terrains:\n  Wet Tile: {mu_long: 0.5, mu_lat: 0.5, slip_scale_long: 0.1, slip_scale_lat: 0.1, "
                   "rolling: 0.01}\n")
    with pytest.raises(TerrainFileError, match=r"names\.yaml.*Wet Tile"):
        load_terrains(bad)


def test_straight_line_force_balance_matches_hand_calculation(terrains) -> None:
    """At steady speed on grass the motors' torque carries rolling resistance + drag (+ drivetrain damping)."""
    from gpmppi.plant.physics import GRAVITY, ROLLING_SMOOTHING, Z_IL, Z_IR, Z_WL, Z_WR, _motor_torque

    plant = PhysicsPlant(terrains, "grass", noise=False)
    run(plant, (1.2, 0.0), 6.0)
    robot, ground = terrains.robot, terrains.get("grass")
    v = plant.state()[3]
    normal = robot.mass * GRAVITY / 4
    per_side_force = 2 * (ground.rolling * normal * np.tanh(v / ROLLING_SMOOTHING) + ground.drag * v)
    z, p = plant._z, plant._params
    for w_idx, i_idx in ((Z_WL, Z_IL), (Z_WR, Z_IR)):
        tau, saturated = _motor_torque(p, z[w_idx], z[w_idx], z[i_idx])  # error ~0 at steady state
        expected = robot.wheel_radius * per_side_force + robot.drivetrain_damping * z[w_idx]
        assert not saturated
        assert tau == pytest.approx(expected, rel=0.02)


def test_internal_step_is_converged(terrains) -> None:
    """Halving the integration step barely changes a demanding manoeuvre (fast turn on high grip)."""
    fine = terrains.model_copy(update={"robot": terrains.robot.model_copy(update={"internal_dt": 0.00025})})
    commands = [(2.0, 2.5)] * 10 + [(0.5, -3.0)] * 10 + [(1.5, 0.0)] * 10
    finals = []
    for ts in (terrains, fine):
        plant = PhysicsPlant(ts, "asphalt", noise=False)
        plant.reset(np.zeros(5))
        traj = np.array([plant.step(np.array(c), DT) for c in commands])
        finals.append(traj)
    np.testing.assert_allclose(finals[0][:, 3:], finals[1][:, 3:], atol=0.01)
    np.testing.assert_allclose(finals[0][:, :2], finals[1][:, :2], atol=0.01)


def test_residual_net_reproduces_the_paper_residuals_in_csv_order(jackal: Path) -> None:
    """The network was fit to gp_train.csv: its outputs follow the CSV's column order (Asphalt, Grass, Tile)."""
    data = np.genfromtxt(jackal / "gp_train.csv", delimiter=",", names=True)
    theta = np.asarray(json.loads((jackal / "theta.json").read_text())["theta"])
    x = np.column_stack([data[k] for k in data.dtype.names[:4]])
    targets = np.column_stack([data[k] for k in data.dtype.names[4:]])
    err = load_residual_net(jackal / "fcnn.json")(x) - targets
    assert np.all(np.sqrt(np.mean(err**2, axis=0)) < 0.3 * np.sqrt(np.mean(targets**2, axis=0)))
    plant = ResidualNetPlant(jackal / "fcnn.json", theta, "tile", ["Asphalt", "Grass", "Tile"])
    k = 7
    plant.reset(np.array([0.0, 0.0, 0.0, x[k, 2], x[k, 3]]))
    out = plant.step(x[k, :2], DT)
    pv, pw = velocity_step_exact(theta, x[k, 2:3], x[k, 3:4], x[k, 0:1], x[k, 1:2], DT)
    assert out[3] - pv[0] == pytest.approx(targets[k, 4], abs=0.02)
    assert out[4] - pw[0] == pytest.approx(targets[k, 5], abs=0.02)


def test_residual_net_plant_runs_the_deployed_command_path(tmp_path: Path) -> None:
    """Egress sends at 20 Hz, the network steps at 0.1 s: the plant holds, per step, the command active at its start
    (a base sampling its input at its own rate), and every egress output is still scored as the base's command."""
    from cached_models import synthetic_model

    from gpmppi.evaluation.closed_loop import ClosedLoopConfig, run_closed_loop
    from gpmppi.mppi.planner import Planner, PlannerConfig
    from gpmppi.safety import SafetyConfig
    from gpmppi.scenarios import circle_lane

    net = _tiny_net(tmp_path, with_names=False)
    plant = ResidualNetPlant(net, THETA, "grass", terrain_names=["asphalt", "grass"])
    applied: list[np.ndarray] = []
    step = plant.step

    def recording_step(command: np.ndarray, duration: float) -> np.ndarray:
        applied.append(np.array(command, dtype=float))
        assert duration == pytest.approx(0.1)  # whole network steps only
        return step(command, duration)

    plant.step = recording_step  # type: ignore[method-assign]
    sc = circle_lane()
    planner = Planner(PlannerConfig(dynamics="unicycle", backend="cpu", samples=64, seed=1), synthetic_model())
    cfg = ClosedLoopConfig(time_limit_s=2.0, safety=SafetyConfig(accel_limit=2.0, yaw_accel_limit=3.0))
    traj = run_closed_loop(planner, plant, sc.task, sc.start, 3, cfg)
    assert traj.status == "time_limit" and len(traj.commands) == 20 and len(applied) == 20
    # egress sent twice per planner cycle (its 20 Hz), and the plant applied the first output of each cycle
    assert len(traj.base_times) >= 38
    for k, u in enumerate(applied):
        first = np.flatnonzero(np.isclose(traj.base_times, 0.1 * k))
        assert first.size and np.allclose(u, traj.base_commands[first[-1]]), k
