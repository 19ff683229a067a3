"""The GP model file: round trip, atomic writes, clear errors on bad files; predictors vs references."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from gpmppi.gp.exact import ExactPredictor
from gpmppi.gp.grid import GridPredictor, build_grid, predict_dense
from gpmppi.gp.grid_table import decode_grid_table, encode_grid_table
from gpmppi.gp.model_file import GPModel, ModelFileError, task_names
from gpmppi.gp.train import Hyperparameters, factorize


def small_model(n: int = 40, seed: int = 0) -> GPModel:
    rng = np.random.default_rng(seed)
    terrains = ["asphalt", "grass"]
    x = rng.uniform([0, -2, 0, -2], [2, 2, 2, 2], (n, 4))
    hp = Hyperparameters(rng.uniform(0.8, 2.5, (4, 4)), rng.uniform(0.01, 0.1, 4), rng.uniform(1e-4, 1e-3, 4))
    y = np.sin(x @ rng.normal(size=(4, 4))).T * 0.1
    chol, alpha = factorize(x, y, hp)
    return GPModel(terrains, task_names(terrains), np.array([0.2, 0.3, 0.05, 1.0, 0.2, 1.0]),
                   {t: np.arange(5.0) + i for i, t in enumerate(terrains)}, np.array([0, -2, 0, -2.0]),
                   np.array([2, 2, 2, 2.0]), x, hp.lengthscale, hp.outputscale, hp.noise, chol, alpha)


def test_round_trip_and_atomic_save(tmp_path: Path) -> None:
    m = small_model()
    m.set_grid(build_grid(m, 6))
    path = tmp_path / "sub" / "m.npz"
    m.save(path)
    assert [p.name for p in path.parent.iterdir()] == ["m.npz"]  # no temp file left
    r = GPModel.load(path)
    assert r.terrains == m.terrains and r.tasks == m.tasks and r.dt == m.dt
    for name in ("theta", "domain_lo", "domain_hi", "train_x", "lengthscale", "outputscale", "noise", "chol", "alpha"):
        np.testing.assert_array_equal(getattr(r, name), getattr(m, name), err_msg=name)
    for t in m.terrains:
        np.testing.assert_array_equal(r.edd5[t], m.edd5[t])
    assert r.has_stored_grid()
    span = np.ptp(m.grid().table, axis=(0, 1, 2, 3))
    assert np.all(np.abs(r.grid().table - m.grid().table) <= span / 65535 * 0.51 + 1e-18)
    np.testing.assert_array_equal(r.grid().inv_step, m.grid().inv_step)


def test_grid_codec_is_exact_on_quantized_values() -> None:
    rng = np.random.default_rng(1)
    table = rng.normal(size=(3, 4, 5, 6, 2)).cumsum(axis=3)
    enc = encode_grid_table(table)
    dec = decode_grid_table(**{"q" if k == "grid_q" else k[5:]: v for k, v in enc.items()})
    scale = enc["grid_scale"]
    assert np.all(np.abs(dec - table) <= 0.5 * scale + 1e-12)
    assert np.array_equal(encode_grid_table(dec)["grid_q"], enc["grid_q"])


def test_grid_decode_is_the_plain_cumsum_bit_for_bit() -> None:
    """The in-place decode gives the bits of the plain formula (cumsum along each axis, then offset + scale * q),
    on the shipped profile's table and on one whose sums wrap around 2^16."""
    from gpmppi.gp.model_file import DEFAULT_MODEL_PATH

    def plain(q: np.ndarray, offset: np.ndarray, scale: np.ndarray) -> np.ndarray:
        for axis in range(4):
            q = np.cumsum(q, axis=axis, dtype=np.uint16)
        return offset + scale * q

    with np.load(DEFAULT_MODEL_PATH) as z:
        shipped = (z["grid_q"], z["grid_offset"], z["grid_scale"])
    rng = np.random.default_rng(3)
    wrapping = (rng.integers(0, 2**16, (3, 4, 5, 6, 2), dtype=np.uint16), rng.normal(size=2), rng.uniform(0.1, 1, 2))
    for q, offset, scale in (shipped, wrapping):
        before = q.copy()
        got = decode_grid_table(q, offset, scale)
        assert got.dtype == np.float64 and got.flags.c_contiguous
        assert got.tobytes() == plain(q, offset, scale).tobytes()
        assert np.array_equal(q, before)  # the caller's array is left as it was


def test_exact_predictors_agree_with_direct_formula() -> None:
    m = small_model()
    rng = np.random.default_rng(2)
    q = rng.uniform(-0.5, 2.5, (30, 4))
    mean, var = ExactPredictor(m).predict(q)
    dmean, dvar = predict_dense(m, q)
    for t in range(m.n_tasks):  # textbook GP equations with explicit inverses
        def k(a, b, t=t):
            d = (a[:, None, :] - b[None, :, :]) / m.lengthscale[t]
            return m.outputscale[t] * np.exp(-0.5 * (d**2).sum(-1))
        kxx = k(m.train_x, m.train_x) + m.noise[t] * np.eye(len(m.train_x))
        ks = k(q, m.train_x)
        y = kxx @ m.alpha[t]
        ref_mean = ks @ np.linalg.solve(kxx, y)
        ref_var = m.outputscale[t] - np.einsum("ij,ji->i", ks, np.linalg.solve(kxx, ks.T))
        np.testing.assert_allclose(mean[:, t], ref_mean, rtol=1e-8, atol=1e-12)
        np.testing.assert_allclose(var[:, t], ref_var, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(mean, dmean, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(var, dvar, rtol=1e-8, atol=1e-14)


def test_grid_predictor_exact_at_nodes_and_close_between() -> None:
    m = small_model()
    g = build_grid(m, 12)
    m.set_grid(g)
    axes = [np.linspace(m.domain_lo[d], m.domain_hi[d], 12) for d in range(4)]
    nodes = np.array([[axes[0][i], axes[1][j], axes[2][k], axes[3][l]] for i, j, k, l in
                      [(0, 0, 0, 0), (3, 5, 7, 11), (11, 11, 11, 11), (6, 2, 9, 1)]])
    gm, gv = GridPredictor(m).predict(nodes)
    em, ev = ExactPredictor(m).predict(nodes)
    np.testing.assert_allclose(gm, em, rtol=1e-9, atol=1e-14)
    np.testing.assert_allclose(gv, ev, rtol=1e-9, atol=1e-14)
    q = np.random.default_rng(5).uniform(m.domain_lo, m.domain_hi, (2000, 4))
    gm, _ = GridPredictor(m).predict(q)
    em, _ = ExactPredictor(m).predict(q)
    rel = np.sqrt(((gm - em) ** 2).mean(0)) / np.sqrt((em**2).mean(0))
    assert np.all(rel < 0.05), rel  # 12 nodes over lengthscales >= 0.8: a few percent at most
    assert np.all(rel > 1e-6)  # and it is an interpolation, not the exact predictor again


def _rewrite(src: Path, dst: Path, change) -> None:
    with np.load(src) as z:
        arrays = {k: z[k] for k in z.files}
    change(arrays)
    np.savez(dst, **arrays)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda a: a.pop("metadata"), "not a gpmppi GP model file"),
        (lambda a: a.update(metadata=np.array("{not json")), "corrupt metadata"),
        (lambda a: a.update(metadata=np.array(json.dumps({"format": "other"}))), "not a gpmppi GP model file"),
        (lambda a: a.update(metadata=np.array(json.dumps(
            {**json.loads(str(a["metadata"][()])), "version": 99}))), "format version 99"),
        (lambda a: a.pop("chol"), "missing arrays ['chol']"),
        (lambda a: a.update(alpha=a["alpha"][:, :-1]), "'alpha' has shape"),
        (lambda a: a.update(edd5=a["edd5"][:1]), "'edd5' has shape"),
        (lambda a: a["train_x"].__setitem__((0, 0), np.nan), "non-finite"),
        (lambda a: a.update(noise=-a["noise"]), "'noise' must be positive"),
        (lambda a: a.pop("grid_scale"), "only part of the grid table"),
    ],
)
def test_load_rejects_bad_files(tmp_path: Path, change, message: str) -> None:
    m = small_model()
    m.set_grid(build_grid(m, 4))
    good = tmp_path / "good.npz"
    m.save(good)
    bad = tmp_path / "bad.npz"
    _rewrite(good, bad, change)
    with pytest.raises(ModelFileError, match=message.replace("[", r"\[").replace("]", r"\]")) as e:
        GPModel.load(bad)
    assert str(bad) in str(e.value)


def test_load_rejects_non_model_files(tmp_path: Path) -> None:
    with pytest.raises(ModelFileError, match="no such model file"):
        GPModel.load(tmp_path / "absent.npz")
    text = tmp_path / "text.npz"
    text.write_text("hello")
    with pytest.raises(ModelFileError, match="not a GP model file"):
        GPModel.load(text)
    m = small_model()
    good = tmp_path / "good.npz"
    m.save(good)
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(ModelFileError, match="not a readable model file"):
        GPModel.load(truncated)
    assert isinstance(ModelFileError("x"), ValueError)
    assert zipfile.is_zipfile(good)


def test_constructor_validates_shapes() -> None:
    m = small_model()
    with pytest.raises(ValueError, match="'chol' has shape"):
        GPModel(m.terrains, m.tasks, m.theta, m.edd5, m.domain_lo, m.domain_hi, m.train_x, m.lengthscale,
                m.outputscale, m.noise, m.chol[:, :-1], m.alpha)
    with pytest.raises(ValueError, match="task names"):
        GPModel(m.terrains, m.tasks[:-1], m.theta, m.edd5, m.domain_lo, m.domain_hi, m.train_x, m.lengthscale,
                m.outputscale, m.noise, m.chol, m.alpha)
