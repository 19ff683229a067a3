"""The nominal model's equations checked against independent references (scipy ODE, finite differences)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from gpmppi.gp.grid_interp import grid_interp
from gpmppi.models.dynamic_unicycle import jacobian, nominal_step, velocity_step_exact, wrap_angle
from gpmppi.models.edd5 import edd5_step, edd5_velocity
from gpmppi.models.kinematic_unicycle import kinematic_step

THETA = np.array([0.2155, 0.3266, 0.0514, 1.0670, 0.1660, 1.0790])  # Jackal-like values


def test_exact_velocity_step_matches_scipy_ode() -> None:
    rng = np.random.default_rng(0)
    n = 20
    v, w = rng.uniform(0, 2, n), rng.uniform(-3, 3, n)
    vr, wr = rng.uniform(0, 2, n), rng.uniform(-3, 3, n)
    v1, w1 = velocity_step_exact(THETA, v, w, vr, wr, 0.1)
    th1, th2, th3, th4, th5, th6 = THETA
    for i in range(n):

        def f(_t: float, s: np.ndarray, i: int = i) -> list[float]:
            a, b = s
            return [th3 / th1 * b * b - th4 / th1 * a + vr[i] / th1, -th5 / th2 * a * b - th6 / th2 * b + wr[i] / th2]

        ref = solve_ivp(f, (0, 0.1), [v[i], w[i]], rtol=1e-12, atol=1e-12).y[:, -1]
        assert v1[i] == pytest.approx(ref[0], abs=1e-9)
        assert w1[i] == pytest.approx(ref[1], abs=1e-9)


@pytest.mark.parametrize("with_lateral", [False, True])
def test_jacobian_matches_central_differences(with_lateral: bool) -> None:
    rng = np.random.default_rng(1)
    for _ in range(25):
        x = rng.uniform([-5, -5, -np.pi, 0, -3], [5, 5, np.pi, 2, 3])
        u = rng.uniform([0, -3], [2, 3])
        mv, mw = rng.uniform(-0.2, 0.2, 2)  # the step's GP residual, held
        lat = rng.uniform(-0.2, 0.05, 2) if with_lateral else np.zeros(2)  # sideways slide (a, b)
        J = jacobian(THETA, x, u, 0.1, mv, mw, *lat)
        eps = 1e-6
        num = np.empty((5, 5))
        for j in range(5):
            e = np.zeros(5)
            e[j] = eps
            hi, lo = nominal_step(THETA, x + e, u, 0.1, mv, mw, *lat), nominal_step(THETA, x - e, u, 0.1, mv, mw, *lat)
            num[:, j] = (hi - lo) / (2 * eps)
        np.testing.assert_allclose(J, num, atol=1e-8)


def test_nominal_step_pose_is_second_order() -> None:
    """Against the full-state ODE integrated by scipy: the step's pose error is a small fraction of an
    explicit-Euler pose step's (which drives with the start velocities) when the velocities change."""

    def f(_t: float, s: np.ndarray, u: np.ndarray) -> list[float]:
        vdot = (THETA[2] / THETA[0]) * s[4] ** 2 - (THETA[3] / THETA[0]) * s[3] + u[0] / THETA[0]
        wdot = -(THETA[4] / THETA[1]) * s[3] * s[4] - (THETA[5] / THETA[1]) * s[4] + u[1] / THETA[1]
        return [s[3] * np.cos(s[2]), s[3] * np.sin(s[2]), s[4], vdot, wdot]

    rng = np.random.default_rng(4)
    for _ in range(20):
        x = rng.uniform([-5, -5, -np.pi, 0.2, -2], [5, 5, np.pi, 2, 2])
        u = rng.uniform([0, -3], [2, 3])
        ref = solve_ivp(f, (0, 0.1), x, args=(u,), rtol=1e-11, atol=1e-12).y[:, -1]
        ours = nominal_step(THETA, x, u, 0.1)
        euler = x[:3] + 0.1 * np.array([x[3] * np.cos(x[2]), x[3] * np.sin(x[2]), x[4]])
        err, err_euler = np.linalg.norm(ours[:3] - ref[:3]), np.linalg.norm(euler - ref[:3])
        assert err < 0.2 * err_euler + 1e-9, (err, err_euler)


def test_nominal_step_moves_along_heading() -> None:
    x = np.array([1.0, 2.0, np.pi / 2, 1.0, 0.0])
    out = nominal_step(THETA, x, np.array([1.0, 0.0]), 0.1)
    assert out[0] == pytest.approx(1.0, abs=1e-12)
    assert out[1] == pytest.approx(2.0 + 0.1 * 0.5 * (1.0 + out[3]))  # at the mean of start and end speeds
    # steady state of vdot = 0 with w = 0: v = v_ref / th4
    assert out[3] == pytest.approx(1.0 + 0.1 * (-THETA[3] + 1.0) / THETA[0])


def test_wrap_angle_half_open_interval() -> None:
    assert wrap_angle(np.pi) == pytest.approx(np.pi)
    assert wrap_angle(-np.pi) == pytest.approx(np.pi)
    assert wrap_angle(3 * np.pi / 2) == pytest.approx(-np.pi / 2)


def test_kinematic_step_takes_command_velocity() -> None:
    out = kinematic_step(np.array([0.0, 0.0, 0.0, 0.0, 0.0]), np.array([2.0, 1.0]), 0.1)
    np.testing.assert_allclose(out, [0.2, 0.0, 0.1, 2.0, 1.0])


def test_edd5_matches_readme_formula_and_ideal_case() -> None:
    b, r = 0.377, 0.09
    p = np.array([0.93, 0.92, 0.25, -0.31, 0.19])
    vr, wr = 1.2, 0.7
    w_r, w_l = (vr + 0.5 * wr * b) / r, (vr - 0.5 * wr * b) / r
    k = r / (p[4] - p[3])
    expected = (k * (-p[3] * p[1] * w_l + p[4] * p[0] * w_r), k * (-p[1] * w_l + p[0] * w_r))
    assert edd5_velocity(p, vr, wr) == pytest.approx(expected)
    # no slip, ICR on the wheels (y_r = -b/2, y_l = b/2): EDD5 reduces to the command
    ideal = np.array([1.0, 1.0, 0.0, -b / 2, b / 2])
    assert edd5_velocity(ideal, vr, wr) == pytest.approx((vr, wr))
    out = edd5_step(ideal, np.zeros(5), np.array([vr, wr]), 0.1)
    assert out[3:] == pytest.approx([vr, wr])


def test_grid_interp_is_exact_for_multilinear_functions_and_clamps() -> None:
    g = np.linspace(0, 1, 5)
    A, B, C, D = np.meshgrid(g * 2 - 1, g * 4, g, g * 3 + 1, indexing="ij")
    table = np.stack([1 + 2 * A - B + 0.5 * C * D, A * B * C * D], axis=-1)
    lo = np.array([-1.0, 0.0, 0.0, 1.0])
    inv = 1.0 / np.array([0.5, 1.0, 0.25, 0.75])
    rng = np.random.default_rng(2)
    out = np.empty(2)
    for _ in range(50):
        x = lo + rng.uniform(0, 1, 4) * np.array([2.0, 4.0, 1.0, 3.0])
        grid_interp(table, lo, inv, x, out)
        # multilinear within a cell: exact for these (products of one power per axis)
        assert out[0] == pytest.approx(1 + 2 * x[0] - x[1] + 0.5 * x[2] * x[3], abs=1e-12)
        assert out[1] == pytest.approx(x[0] * x[1] * x[2] * x[3], abs=1e-12)
    grid_interp(table, lo, inv, np.array([-9.0, -9.0, -9.0, -9.0]), out)
    assert out[0] == pytest.approx(table[0, 0, 0, 0, 0])
