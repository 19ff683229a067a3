"""Chance-constraint tightening (closed form, scipy quantiles) and covariance propagation."""

from __future__ import annotations

import numpy as np
import pytest
from cached_models import synthetic_model
from scipy.stats import chi2, norm

from gpmppi.models.dynamic_unicycle import jacobian, nominal_step
from gpmppi.mppi.bundles import ModelBundle
from gpmppi.mppi.costs import ChanceQuantiles, inflate_obstacles, tighten_lane
from gpmppi.mppi.dynamics import DYN_GP, GP_GRID, propagate
from gpmppi.mppi.gp_table import TABLE_AXES, collapse_table


def _random_covs(n: int, seed: int, scale: float = 0.05) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, 5, 5)) * scale
    return a @ a.transpose(0, 2, 1)


def test_quantiles_come_from_scipy() -> None:
    q = ChanceQuantiles.for_probability(0.95)
    assert q.chi2_2 == pytest.approx(chi2.ppf(0.95, 2))
    assert q.chi2_2 == pytest.approx(-2 * np.log(0.05))  # chi2 with 2 dof has a closed-form quantile
    assert q.normal == pytest.approx(1.6448536269514722)
    with pytest.raises(ValueError, match="p_x"):
        ChanceQuantiles.for_probability(1.0)


def test_lane_tightening_equals_closed_form() -> None:
    covs = _random_covs(12, 0)
    r = 1.75
    got, clamped = tighten_lane(covs, r, chi2.ppf(0.9, 2), 0.1)
    lam = np.array([np.linalg.eigvalsh(c[:2, :2]).max() for c in covs])
    expected = np.maximum(r - np.sqrt(chi2.ppf(0.9, 2) * lam), 0.1 * r)
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)
    assert clamped == int(np.sum(r - np.sqrt(chi2.ppf(0.9, 2) * lam) < 0.1 * r))


def test_lane_tightening_clamps_and_counts() -> None:
    covs = np.zeros((3, 5, 5))
    covs[1, 0, 0] = 100.0
    covs[2, 1, 1] = 0.01
    got, clamped = tighten_lane(covs, 2.0, chi2.ppf(0.95, 2), 0.1)
    assert got[0] == 2.0
    assert got[1] == pytest.approx(0.2)  # clamped at 10 % of r, never negative
    assert got[2] == pytest.approx(2.0 - np.sqrt(chi2.ppf(0.95, 2) * 0.01))
    assert clamped == 1


def test_obstacle_inflation_equals_closed_form() -> None:
    covs = _random_covs(6, 1)
    rng = np.random.default_rng(2)
    states = rng.normal(size=(6, 5)) * 3
    obstacles = np.array([[1.0, 2.0, 0.5], [-2.0, 0.5, 0.8]])
    zq = norm.ppf(0.95)
    got, capped = inflate_obstacles(states, covs, obstacles, zq, 0.2, 10.0)
    for k in range(6):
        for j in range(2):
            n = states[k, :2] - obstacles[j, :2]
            n /= np.linalg.norm(n)
            expected = obstacles[j, 2] + 0.2 + zq * np.sqrt(n @ covs[k, :2, :2] @ n)
            assert got[k, j] == pytest.approx(expected, rel=1e-12)
    assert capped == 0
    capped_r, n_capped = inflate_obstacles(states, covs * 1e6, obstacles, zq, 0.0, 0.3)
    np.testing.assert_allclose(capped_r, np.tile(obstacles[:, 2] + 0.3, (6, 1)))
    assert n_capped == 12


def _fd_jacobian(theta: np.ndarray, x: np.ndarray, u: np.ndarray, dt: float, mv: float, mw: float) -> np.ndarray:
    jac = np.zeros((5, 5))
    for i in range(5):
        h = 1e-6
        e = np.zeros(5)
        e[i] = h
        jac[:, i] = (nominal_step(theta, x + e, u, dt, mv, mw) - nominal_step(theta, x - e, u, dt, mv, mw)) / (2 * h)
    return jac


def test_propagation_matches_finite_difference_jacobians() -> None:
    model = synthetic_model()
    w = np.array([0.5, 0.3, 0.2])
    g = model.grid()
    table = collapse_table(np.ascontiguousarray(g.table, dtype=np.float32), w)
    rng = np.random.default_rng(3)
    controls = np.column_stack([rng.uniform(0.5, 2.0, 15), rng.uniform(-2, 2, 15)])
    x0 = np.array([1.0, -2.0, 0.4, 0.8, 0.3])
    bundle = ModelBundle(dyn_mode=DYN_GP, theta=model.theta, lateral=np.zeros(2), edd5=model.edd5["grass"],
                         gp_mode=GP_GRID, table=table.reshape(-1, 4), dims=np.array(table.shape[:4], dtype=np.int64),
                         lo=g.lo[TABLE_AXES], inv_step=g.inv_step[TABLE_AXES],
                         **ModelBundle.no_exact(2 * len(model.terrains)), terrain_w=w,
                         **ModelBundle.collapsed_whole())
    states, covs, step_var = propagate(bundle.args(), x0, controls, 0.1)
    sigma = np.zeros((5, 5))
    for k in range(15):
        # the step's GP residual mean: what the mean step added to the nominal velocities
        nominal = nominal_step(model.theta, states[k], controls[k], 0.1)
        mv, mw = states[k + 1, 3] - nominal[3], states[k + 1, 4] - nominal[4]
        np.testing.assert_allclose(states[k + 1], nominal_step(model.theta, states[k], controls[k], 0.1, mv, mw),
                                   atol=1e-6)  # the kernels' cos/sin are single precision
        jac_fd = _fd_jacobian(model.theta, states[k], controls[k], 0.1, mv, mw)
        np.testing.assert_allclose(jacobian(model.theta, states[k], controls[k], 0.1, mv, mw), jac_fd, atol=1e-7)
        sigma = jac_fd @ sigma @ jac_fd.T + np.diag([0, 0, 0, step_var[k, 0], step_var[k, 1]])
        np.testing.assert_allclose(covs[k + 1], sigma, rtol=1e-6, atol=1e-12)
    assert np.all(step_var > 0)
    assert covs[-1][0, 0] > 0 and covs[-1][1, 1] > 0  # velocity noise reaches the position


def test_collapsed_table_interpolates_like_the_weighted_model_grid() -> None:
    from gpmppi.gp.grid_interp import grid_interp
    from gpmppi.mppi.gp_table import interp4

    model = synthetic_model()
    g = model.grid()
    w = np.array([0.6, 0.1, 0.3])
    packed = collapse_table(np.ascontiguousarray(g.table, dtype=np.float32), w)
    rng = np.random.default_rng(4)
    full = np.empty(g.table.shape[4])
    for _ in range(200):
        x = model.domain_lo - 0.3 + (model.domain_hi - model.domain_lo + 0.6) * rng.uniform(size=4)  # some outside
        grid_interp(g.table, g.lo, g.inv_step, x, full)
        t = len(model.terrains) * 2
        expected = [w @ full[0:t:2], w @ full[1:t:2], w**2 @ full[t::2], w**2 @ full[t + 1 :: 2]]
        got = interp4(packed.reshape(-1, 4), np.array(packed.shape[:4]), g.lo[TABLE_AXES], g.inv_step[TABLE_AXES],
                      *x[TABLE_AXES])
        np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-8)


def test_simplex_interpolation_is_exact_on_linear_data_and_as_accurate_as_multilinear() -> None:
    from gpmppi.gp.grid import predict_dense
    from gpmppi.mppi.gp_table import interp4, interp4_simplex

    g_n = 7
    dims = np.array([g_n] * 4)
    lo = np.array([0.0, -1.0, 0.5, 2.0])
    inv = np.array([3.0, 1.5, 2.0, 4.0])
    idx = np.indices((g_n,) * 4).reshape(4, -1).T
    coords = lo + idx / inv
    lin = np.stack([coords @ np.array(c) for c in ([1, 2, -1, 0.5], [0, 0, 0, 1], [3, -1, 0, 0], [1, 1, 1, 1])], 1)
    table = lin.astype(np.float32)
    rng = np.random.default_rng(5)
    for _ in range(100):
        x = lo + rng.uniform(size=4) * (g_n - 1) / inv
        want = np.array([x @ np.array(c) for c in ([1, 2, -1, 0.5], [0, 0, 0, 1], [3, -1, 0, 0], [1, 1, 1, 1])])
        np.testing.assert_allclose(interp4_simplex(table, dims, lo, inv, *x), want, rtol=1e-5, atol=1e-5)
    # on the GP itself: errors against the exact GP comparable to the multilinear interpolation's
    model = synthetic_model(nodes=9)
    g = model.grid()
    w = np.array([0.2, 0.5, 0.3])
    t = collapse_table(np.ascontiguousarray(g.table, dtype=np.float32), w)
    flat, tdims = t.reshape(-1, 4), np.array(t.shape[:4])
    pts = model.domain_lo + rng.uniform(size=(300, 4)) * (model.domain_hi - model.domain_lo)
    mean, var = predict_dense(model, pts)
    exact = np.stack([mean[:, 0::2] @ w, mean[:, 1::2] @ w, var[:, 0::2] @ w**2, var[:, 1::2] @ w**2], 1)
    args = (flat, tdims, g.lo[TABLE_AXES], g.inv_step[TABLE_AXES])
    err_s = np.array([interp4_simplex(*args, *p[TABLE_AXES]) for p in pts]) - exact
    err_m = np.array([interp4(*args, *p[TABLE_AXES]) for p in pts]) - exact
    rms_s, rms_m = np.sqrt((err_s**2).mean(0)), np.sqrt((err_m**2).mean(0))
    assert np.all(rms_s < 2.0 * rms_m + 1e-7), (rms_s, rms_m)
    assert np.all(rms_s[:2] < 0.1 * np.abs(exact[:, :2]).max(0))
