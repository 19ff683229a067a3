"""Identification of the nominal dynamic unicycle (theta) and of EDD5."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gpmppi.models.dynamic_unicycle import velocity_step_exact
from gpmppi.models.edd5 import edd5_velocity
from gpmppi.models.identify import identify_edd5, identify_theta, one_step_pairs

DT = 0.1
TRUE_THETA = np.array([0.25, 0.30, 0.04, 1.0, 0.15, 1.1])  # a plausible made-up nominal model


def simulate_nominal(theta: np.ndarray, n: int, seed: int, noise: float) -> tuple[np.ndarray, ...]:
    """Nominal-model data under piecewise-constant random commands, with measurement noise."""
    rng = np.random.default_rng(seed)
    holds = rng.integers(1, 15, size=n)
    cmd = np.empty((n, 2))
    k = 0
    while k < n:
        cmd[k : k + holds[k]] = [rng.uniform(0, 2), rng.uniform(-np.pi, np.pi)]
        k += holds[k]
    v, w = np.zeros(n), np.zeros(n)
    for k in range(n - 1):
        nv, nw = velocity_step_exact(theta, v[k : k + 1], w[k : k + 1], cmd[k : k + 1, 0], cmd[k : k + 1, 1], DT)
        v[k + 1], w[k + 1] = nv[0], nw[0]
    return v + rng.normal(0, noise, n), w + rng.normal(0, noise, n), cmd[:, 0], cmd[:, 1]


def test_identify_theta_recovers_nominal_parameters() -> None:
    v, w, cv, cw = simulate_nominal(TRUE_THETA, 3000, seed=0, noise=0.003)
    theta = identify_theta(v, w, cv, cw, DT)
    # the ratios are what the model's behaviour depends on; check them and the input gains
    np.testing.assert_allclose(theta[[0, 1, 3, 5]], TRUE_THETA[[0, 1, 3, 5]], rtol=0.03)
    np.testing.assert_allclose(theta[[2, 4]], TRUE_THETA[[2, 4]], atol=0.02)
    # the linear (difference-quotient) stage alone is already close
    linear = identify_theta(v, w, cv, cw, DT, refine=False)
    np.testing.assert_allclose(linear[[0, 1, 3, 5]], TRUE_THETA[[0, 1, 3, 5]], rtol=0.15)


def test_identify_theta_segments_never_straddle_a_gap() -> None:
    a = simulate_nominal(TRUE_THETA, 800, seed=1, noise=0.002)
    b = simulate_nominal(TRUE_THETA, 800, seed=2, noise=0.002)
    # shift the second segment's start far away: differencing across the gap would ruin the fit
    b = (b[0] + 1.5, b[1] - 2.0, b[2], b[3])
    as_list = identify_theta([a[0], b[0]], [a[1], b[1]], [a[2], b[2]], [a[3], b[3]], DT)
    ids = np.r_[np.zeros(800), np.ones(800)]
    as_ids = identify_theta(*(np.r_[x, y] for x, y in zip(a, b, strict=True)), DT, segment_ids=ids)
    np.testing.assert_allclose(as_list, as_ids, rtol=1e-6)
    # pairs never join the two segments
    v, *_ = one_step_pairs(*(np.r_[x, y] for x, y in zip(a, b, strict=True)), segment_ids=ids)
    assert len(v) == 2 * 799


def test_identify_theta_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="segment_ids"):
        identify_theta(np.zeros(5), np.zeros(5), np.zeros(5), np.zeros(5), DT, segment_ids=np.zeros(4))
    with pytest.raises(ValueError, match="excite"):
        identify_theta(np.zeros(50), np.zeros(50), np.zeros(50), np.zeros(50), DT, refine=False)
    with pytest.raises(ValueError, match="dt"):
        identify_theta(np.zeros(5), np.zeros(5), np.zeros(5), np.zeros(5), 0.0)


def edd5_predict(p: np.ndarray, cv: np.ndarray, cw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    out = np.array([edd5_velocity(p, a, b) for a, b in zip(cv, cw, strict=True)])
    return out[:, 0], out[:, 1]


def test_identify_edd5_recovers_parameters_despite_outliers() -> None:
    rng = np.random.default_rng(0)
    true = np.array([0.95, 0.85, 0.15, -0.28, 0.22])
    cv, cw = rng.uniform(0, 2, 400), rng.uniform(-2, 2, 400)
    v, w = edd5_predict(true, cv, cw)
    v, w = v + rng.normal(0, 0.01, 400), w + rng.normal(0, 0.01, 400)
    bad = rng.choice(400, 40, replace=False)
    v[bad] += rng.normal(0, 1.0, 40)
    w[bad] -= rng.normal(0, 1.5, 40)
    p = identify_edd5(cv, cw, v, w)
    np.testing.assert_allclose(p[[0, 1, 3, 4]], true[[0, 1, 3, 4]], rtol=0.05)
    assert p[2] == 0.0  # x_v is not observable from v, omega: kept at its initial value
    # with the lateral velocity, x_v is fitted too (EDD5: v_y = -x_v omega)
    clean = np.setdiff1d(np.arange(400), bad)
    _, w_true = edd5_predict(true, cv, cw)
    p_lat = identify_edd5(cv[clean], cw[clean], v[clean], w[clean], lateral_meas=-true[2] * w_true[clean])
    assert p_lat[2] == pytest.approx(true[2], abs=0.02)


def test_identified_edd5_matches_paper_predictions(jackal: Path) -> None:
    """Fit EDD5 to the paper's data (measured next velocity = nominal + residual) per terrain;
    its v/omega predictions must be of the same order as those of the paper's fitted EDD5."""
    data = np.genfromtxt(jackal / "gp_train.csv", delimiter=",", names=True)
    theta = np.asarray(json.loads((jackal / "theta.json").read_text())["theta"])
    paper = json.loads((jackal / "edd5.json").read_text())
    cv, cw, v, w = (data[k] for k in ("gp_ip_cmd_lin", "gp_ip_cmd_ang", "gp_ip_curr_lin", "gp_ip_curr_ang"))
    nv, nw = velocity_step_exact(theta, v, w, cv, cw, DT)
    for terrain, p_paper in paper.items():
        v_next = nv + data[f"{terrain}_Lin_Error"]
        w_next = nw + data[f"{terrain}_Ang_Error"]
        p = identify_edd5(cv, cw, v_next, w_next)
        ours = np.column_stack(edd5_predict(p, cv, cw))
        theirs = np.column_stack(edd5_predict(np.asarray(p_paper), cv, cw))
        scale = np.sqrt(np.mean(theirs**2, axis=0))
        rel = np.sqrt(np.mean((ours - theirs) ** 2, axis=0)) / scale
        assert np.all(rel < 0.15), (terrain, rel)
        assert np.all(np.isfinite(p))


def test_identify_edd5_rejects_mismatched_lengths() -> None:
    with pytest.raises(ValueError, match="lengths"):
        identify_edd5(np.zeros(10), np.zeros(10), np.zeros(9), np.zeros(10))
