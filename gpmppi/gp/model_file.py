"""The robot profile: the trained GP model, what else was learned about the robot, and its file format.

A model is a batch of 2M independent exact GPs (M terrains x {v, omega}) over the 4-D input
`[v_ref, omega_ref, v, omega]`, each ScaleKernel(RBF-ARD) with zero mean, plus the nominal
dynamic-unicycle parameters, the per-terrain EDD5 baselines it was trained with and the per-terrain
lateral slip coefficients (`lateral_slip`, (M, 2); optional, zeros when the file has none). A robot profile
(format version 2) also names its robot (`robot`) and holds the terrain estimator's calibration of its grounds
(`calibration`, gpmppi.profile.terrain_calibration; arrays in gpmppi.gp.profile_arrays), all fitted from the
robot's logs by `gpmppi train`. A version 1 file (a GP model only: the paper's converted models, older files) still
loads, with no calibration; whatever needs one then refuses it with the command that refits it
(`GPModel.require_calibration`).

File format: one `.npz` archive (no pickles) holding the arrays below and a `metadata` entry,
a JSON string with the format name and version, the robot, terrain and task names, input names and dt.
The grid predictor's table is stored as well when the writer built it; otherwise
`GPModel.grid()` builds it on first use (`grid_table.build_grid`, sized from the lengthscales). To
keep the file small the table is stored quantized to 16 bits per channel (offset + scale, error
<= 1/131070 of the channel's range) and difference-coded along the four axes, which the archive's
deflate then compresses ~3x (a smooth table has small differences).
"""

from __future__ import annotations

import json
import os
import tempfile
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gpmppi.gp.grid_table import GridTable, build_grid, decode_grid_table, encode_grid_table
from gpmppi.gp.profile_arrays import CALIBRATION_ARRAYS, calibration_arrays, calibration_from_arrays
from gpmppi.models.lateral_slip import N_LATERAL
from gpmppi.profile.novelty_calibration import NoveltyCalibration
from gpmppi.profile.terrain_calibration import TerrainCalibration

FORMAT_NAME = "gpmppi-gp-model"
FORMAT_VERSION = 2  # 2: a robot profile (robot name, terrain calibration); 1: the GP model alone
READABLE_VERSIONS = (1, 2)
DEFAULT_ROBOT = "jackal"  # the robot of files that do not name one (version 1)
REFIT_COMMAND = "gpmppi train LOGS -o {file}"
INPUT_NAMES = ("v_ref", "omega_ref", "v", "omega")
N_INPUT = 4
DEFAULT_MODEL_PATH = Path(__file__).resolve().parents[1] / "data" / "default_gp_model.npz"

_MODEL_ARRAYS = (
    "theta", "edd5", "domain_lo", "domain_hi", "train_x", "lengthscale", "outputscale", "noise", "chol", "alpha"
)
_GRID_ARRAYS = ("grid_q", "grid_offset", "grid_scale", "grid_lo", "grid_inv_step")


class ModelFileError(ValueError):
    """A GP model file could not be read: the message says which file and what is wrong."""


@dataclass
class GPModel:
    """Batch of 2M exact GPs; task t = 2*m + (0 for v, 1 for omega) belongs to terrain m."""

    terrains: list[str]
    tasks: list[str]
    theta: np.ndarray
    edd5: dict[str, np.ndarray]
    domain_lo: np.ndarray
    domain_hi: np.ndarray
    train_x: np.ndarray
    lengthscale: np.ndarray
    outputscale: np.ndarray
    noise: np.ndarray
    chol: np.ndarray
    alpha: np.ndarray
    dt: float = 0.1
    # per terrain (a, b) of `gpmppi.models.lateral_slip` (absent: zeros, the unicycle's no sideways slide)
    lateral_slip: dict[str, np.ndarray] | None = None
    # the training fit report (`gpmppi.gp.train.FitReport.to_metadata`), when the trainer recorded one
    fit_report: dict | None = field(default=None, compare=False)
    robot: str = DEFAULT_ROBOT  # the robot the profile was fitted for: its name in the log keys gpmppi/{robot}/...
    # the terrain estimator's per-ground calibration, in this model's ground order (None: a GP model alone)
    calibration: TerrainCalibration | None = field(default=None, compare=False)
    # the novelty test's calibration ("none of these grounds", in the metadata; None: the test's stated default)
    novelty: NoveltyCalibration | None = field(default=None, compare=False)
    # how the profile was made (e.g. the command line of `gpmppi train`), when the writer recorded it
    made_by: str | None = field(default=None, compare=False)
    source: str | None = field(default=None, compare=False)  # the file it was loaded from (None: built in memory)
    file_version: int = field(default=FORMAT_VERSION, compare=False)  # the format version it was loaded from
    _grid: GridTable | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        _validate(self, "GPModel")

    @property
    def n_terrains(self) -> int:
        return len(self.terrains)

    @property
    def n_tasks(self) -> int:
        return len(self.tasks)

    def task_index(self, terrain: str, output: str) -> int:
        """Index of the task for `terrain` and output `"v"` or `"omega"`."""
        if terrain not in self.terrains:
            raise ValueError(f"unknown terrain {terrain!r}; this model has {self.terrains}")
        if output not in ("v", "omega"):
            raise ValueError(f"output must be 'v' or 'omega', got {output!r}")
        return 2 * self.terrains.index(terrain) + (0 if output == "v" else 1)

    def lateral_matrix(self) -> np.ndarray:
        """(M, 2) lateral slip coefficients in terrain order (`gpmppi.models.lateral_slip`)."""
        assert self.lateral_slip is not None
        return np.stack([self.lateral_slip[t] for t in self.terrains])

    def grid(self) -> GridTable:
        """The grid predictor's table: the stored one, else built from the exact GP once and cached.

        A built table is sized from the lengthscales (`grid_table.model_grid_dims`).
        """
        if self._grid is None:
            self._grid = build_grid(self)
        return self._grid

    def set_grid(self, grid: GridTable) -> None:
        """Attach a grid table (e.g. one just built) so `save` stores it."""
        _check_grid(grid, self.n_tasks, "GPModel")
        self._grid = grid

    def has_stored_grid(self) -> bool:
        """True when a grid table is attached (read from the file, set, or already built), so `save` writes it."""
        return self._grid is not None

    def require_calibration(self) -> TerrainCalibration:
        """The terrain calibration; ModelFileError (one line naming the file and the command that refits it) when the
        profile has none."""
        if self.calibration is not None:
            return self.calibration
        where = self.source or "this GP model"
        refit = REFIT_COMMAND.format(file=self.source or "FILE")
        if self.file_version == 1:
            raise ModelFileError(f"{where} is a v1 GP model without a terrain calibration (an older format); refit it "
                                 f"as a robot profile with `{refit}`")
        raise ModelFileError(f"{where} holds no terrain calibration (it was fitted from data without time series, "
                             f"e.g. a residual CSV); refit it from an MCAP log with `{refit}`, or set the terrain "
                             "estimator's command_change: online and response: none")

    def metadata(self) -> dict:
        return {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "robot": self.robot,
            **({} if self.made_by is None else {"made_by": self.made_by}),
            "terrains": list(self.terrains),
            "tasks": list(self.tasks),
            "inputs": list(INPUT_NAMES),
            "dt": float(self.dt),
            **({} if self.fit_report is None else {"fit": self.fit_report}),
            **({} if self.novelty is None else {"novelty": self.novelty.to_metadata()}),
        }

    def fit_warnings(self) -> list[str]:
        """One line per task whose GP was worse than the nominal model on held-out data when it was trained."""
        rows = (self.fit_report or {}).get("gp_worse_than_nominal", [])
        return [
            f"GP for {r['terrain']} {r['output']} is worse than the nominal model on {r['eval_set']} at training: "
            f"one-step RMSE {r['rmse_gp']:.4f} with the GP vs {r['rmse_nominal']:.4f} without"
            for r in rows
        ]

    def save(self, path: str | os.PathLike) -> None:
        """Write the model atomically (temp file in the same folder, then rename)."""
        path = Path(path)
        arrays: dict[str, np.ndarray] = {
            "metadata": np.array(json.dumps(self.metadata())),
            "theta": self.theta,
            "edd5": np.stack([self.edd5[t] for t in self.terrains]),
            "domain_lo": self.domain_lo,
            "domain_hi": self.domain_hi,
            "train_x": self.train_x,
            "lengthscale": self.lengthscale,
            "outputscale": self.outputscale,
            "noise": self.noise,
            "chol": self.chol,
            "alpha": self.alpha,
            "lateral_slip": self.lateral_matrix(),
        }
        if self.calibration is not None:
            arrays.update(calibration_arrays(self.calibration, self.terrains))
        if self._grid is not None:
            arrays.update(encode_grid_table(self._grid.table))
            arrays["grid_lo"] = self._grid.lo
            arrays["grid_inv_step"] = self._grid.inv_step
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                np.savez_compressed(f, **arrays)
                f.flush()
                os.fsync(f.fileno())
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the file the usual permissions
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise

    @classmethod
    def load(cls, path: str | os.PathLike) -> GPModel:
        """Read and validate a model file; raise ModelFileError naming the problem."""
        path = Path(path)
        where = str(path)
        if not path.is_file():
            raise ModelFileError(f"{where}: no such model file (train one with `gpmppi train DATA -o {path.name}`)")
        with open(path, "rb") as f:
            if f.read(4) != b"PK\x03\x04":  # an .npz is a zip archive; a truncated one is reported below
                raise ModelFileError(f"{where}: not a GP model file (an .npz written by `gpmppi train`)")
        try:
            with np.load(path, allow_pickle=False) as z:
                names = set(z.files)
                if "metadata" not in names:
                    raise ModelFileError(f"{where}: not a gpmppi GP model file (no 'metadata' entry)")
                meta = _parse_metadata(z["metadata"], where)
                missing = [n for n in _MODEL_ARRAYS if n not in names]
                if missing:
                    raise ModelFileError(f"{where}: model file is missing arrays {missing}; retrain the model")
                arr = {n: np.asarray(z[n], dtype=np.float64) for n in _MODEL_ARRAYS}
                grid_present = [n for n in _GRID_ARRAYS if n in names]
                if grid_present and len(grid_present) != len(_GRID_ARRAYS):
                    raise ModelFileError(f"{where}: model file has only part of the grid table {grid_present}")
                grid_arr = {n: z[n] for n in grid_present}
                # optional: files written before the lateral slip model load with none
                lateral = np.asarray(z["lateral_slip"], dtype=np.float64) if "lateral_slip" in names else None
                cal_arr = {n: z[n] for n in CALIBRATION_ARRAYS if n in names}
        except ModelFileError:
            raise
        except (zipfile.BadZipFile, OSError, EOFError, ValueError, KeyError) as e:
            raise ModelFileError(f"{where}: not a readable model file (corrupt or not an .npz archive: {e})") from e
        terrains, tasks = meta["terrains"], meta["tasks"]
        edd5 = arr["edd5"]
        if edd5.shape != (len(terrains), 5):
            raise ModelFileError(f"{where}: 'edd5' has shape {edd5.shape}, expected ({len(terrains)}, 5)")
        if lateral is not None and lateral.shape != (len(terrains), N_LATERAL):
            raise ModelFileError(
                f"{where}: 'lateral_slip' has shape {lateral.shape}, expected ({len(terrains)}, {N_LATERAL})"
            )
        try:
            model = cls(
                terrains=terrains, tasks=tasks, theta=arr["theta"],
                edd5={t: edd5[i].copy() for i, t in enumerate(terrains)},
                domain_lo=arr["domain_lo"], domain_hi=arr["domain_hi"], train_x=arr["train_x"],
                lengthscale=arr["lengthscale"], outputscale=arr["outputscale"], noise=arr["noise"],
                chol=arr["chol"], alpha=arr["alpha"], dt=meta["dt"], fit_report=meta.get("fit"),
                lateral_slip=None if lateral is None else {t: lateral[i].copy() for i, t in enumerate(terrains)},
                robot=meta.get("robot", DEFAULT_ROBOT), made_by=meta.get("made_by"), source=where,
                file_version=meta["version"],
            )
            if cal_arr and meta["version"] < 2:
                raise ValueError("a v1 model file cannot hold a terrain calibration; refit the profile")
            model.calibration = calibration_from_arrays(cal_arr, terrains)
            if "novelty" in meta:  # optional: profiles made before the novelty test load without it
                model.novelty = NoveltyCalibration.from_metadata(meta["novelty"])
            if grid_arr:
                table = decode_grid_table(grid_arr["grid_q"], grid_arr["grid_offset"], grid_arr["grid_scale"])
                lo = np.asarray(grid_arr["grid_lo"], dtype=np.float64)
                inv_step = np.asarray(grid_arr["grid_inv_step"], dtype=np.float64)
                model.set_grid(GridTable(table, lo, inv_step))
        except ValueError as e:
            raise ModelFileError(f"{where}: {e}") from e
        return model


def load_default_model() -> GPModel:
    """The simulated Jackal's robot profile shipped with the package (`gpmppi/data/default_gp_model.npz`).

    It is regenerated from logs of the physics plant with the default settings (tile, asphalt, grass;
    2000 m each; seed 0) by (docs/training.md, "The shipped model")

        gpmppi dataset -o /tmp/default.mcap
        gpmppi train /tmp/default.mcap -o gpmppi/data/default_gp_model.npz --robot jackal
    """
    return GPModel.load(DEFAULT_MODEL_PATH)


def task_names(terrains: list[str]) -> list[str]:
    """Task names in model order: [T0_Lin, T0_Ang, T1_Lin, T1_Ang, ...]."""
    return [f"{t}_{o}" for t in terrains for o in ("Lin", "Ang")]


def _parse_metadata(raw: np.ndarray, where: str) -> dict:
    try:
        meta = json.loads(str(raw[()]))
    except (json.JSONDecodeError, TypeError, IndexError) as e:
        raise ModelFileError(f"{where}: corrupt metadata entry (not JSON: {e})") from e
    if not isinstance(meta, dict) or meta.get("format") != FORMAT_NAME:
        raise ModelFileError(f"{where}: not a gpmppi GP model file (format is not {FORMAT_NAME!r})")
    if meta.get("version") not in READABLE_VERSIONS:
        raise ModelFileError(
            f"{where}: model file format version {meta.get('version')!r}, this gpmppi reads versions "
            f"{list(READABLE_VERSIONS)}; refit it with this version (`{REFIT_COMMAND.format(file=where)}`) or "
            "update gpmppi"
        )
    for key, kind in (("terrains", list), ("tasks", list), ("dt", (int, float)), ("robot", str), ("made_by", str)):
        if key in ("robot", "made_by") and key not in meta:
            continue
        if not isinstance(meta.get(key), kind):
            raise ModelFileError(f"{where}: metadata field {key!r} is missing or has the wrong type")
    if "fit" in meta and not _fit_report_ok(meta["fit"]):
        raise ModelFileError(f"{where}: metadata field 'fit' is malformed (expected the trainer's fit report)")
    if list(meta.get("inputs", INPUT_NAMES)) != list(INPUT_NAMES):
        raise ModelFileError(f"{where}: model inputs {meta.get('inputs')} differ from {list(INPUT_NAMES)}")
    return meta


def _fit_report_ok(fit: object) -> bool:
    if not isinstance(fit, dict) or not isinstance(fit.get("gp_worse_than_nominal", []), list):
        return False
    text, num = ("terrain", "output", "eval_set"), ("rmse_gp", "rmse_nominal")
    return all(
        isinstance(r, dict) and all(isinstance(r.get(k), str) for k in text)
        and all(isinstance(r.get(k), (int, float)) for k in num)
        for r in fit.get("gp_worse_than_nominal", [])
    )


def _shape(name: str, a: np.ndarray, expected: tuple[int, ...], where: str) -> None:
    if a.shape != expected:
        raise ValueError(f"{where}: {name!r} has shape {a.shape}, expected {expected}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{where}: {name!r} holds non-finite values (NaN or inf)")


def _check_grid(grid: GridTable, n_tasks: int, where: str) -> None:
    t = np.asarray(grid.table)
    if t.ndim != 5 or t.shape[4] != 2 * n_tasks or min(t.shape[:4]) < 2:
        raise ValueError(
            f"{where}: grid table has shape {t.shape}, expected (G0, G1, G2, G3, {2 * n_tasks}) with every G >= 2"
        )
    _shape("grid_table", t, t.shape, where)
    _shape("grid_lo", np.asarray(grid.lo), (N_INPUT,), where)
    _shape("grid_inv_step", np.asarray(grid.inv_step), (N_INPUT,), where)
    if np.any(np.asarray(grid.inv_step) <= 0):
        raise ValueError(f"{where}: grid_inv_step must be positive")


def _validate(m: GPModel, where: str) -> None:
    """Coerce arrays to float64 and check every shape, value range and name list."""
    if len(m.terrains) == 0 or len(set(m.terrains)) != len(m.terrains):
        raise ValueError(f"{where}: terrains must be a non-empty list of distinct names, got {m.terrains}")
    n_tasks = 2 * len(m.terrains)
    if len(m.tasks) != n_tasks:
        raise ValueError(f"{where}: {len(m.tasks)} task names for {len(m.terrains)} terrains (expected {n_tasks})")
    if set(m.edd5) != set(m.terrains):
        raise ValueError(f"{where}: EDD5 terrains {sorted(m.edd5)} differ from model terrains {m.terrains}")
    if not (isinstance(m.dt, (int, float)) and np.isfinite(m.dt) and m.dt > 0):
        raise ValueError(f"{where}: dt must be a positive number, got {m.dt!r}")
    m.dt = float(m.dt)
    for name in ("theta", "domain_lo", "domain_hi", "train_x", "lengthscale", "outputscale", "noise", "chol", "alpha"):
        setattr(m, name, np.ascontiguousarray(getattr(m, name), dtype=np.float64))
    m.edd5 = {k: np.ascontiguousarray(v, dtype=np.float64) for k, v in m.edd5.items()}
    if m.lateral_slip is None:
        m.lateral_slip = {t: np.zeros(N_LATERAL) for t in m.terrains}
    if set(m.lateral_slip) != set(m.terrains):
        raise ValueError(
            f"{where}: lateral slip terrains {sorted(m.lateral_slip)} differ from model terrains {m.terrains}"
        )
    m.lateral_slip = {k: np.ascontiguousarray(v, dtype=np.float64) for k, v in m.lateral_slip.items()}
    if not (isinstance(m.robot, str) and m.robot.strip()):
        raise ValueError(f"{where}: robot must be a non-empty name, got {m.robot!r}")
    if m.calibration is not None:  # held in the model's ground order; an error names a ground it lacks
        m.calibration = m.calibration.select(list(m.terrains), source=f"{where} terrain calibration")
    for t, p in m.lateral_slip.items():
        _shape(f"lateral_slip[{t}]", p, (N_LATERAL,), where)
        if not np.all(np.isfinite(p)):
            raise ValueError(f"{where}: lateral_slip[{t}] must be finite, got {p.tolist()}")
    if m.train_x.ndim != 2 or m.train_x.shape[0] < 1:
        raise ValueError(f"{where}: 'train_x' has shape {m.train_x.shape}, expected (n, {N_INPUT}) with n >= 1")
    n = m.train_x.shape[0]
    _shape("theta", m.theta, (6,), where)
    for t, p in m.edd5.items():
        _shape(f"edd5[{t}]", p, (5,), where)
    _shape("domain_lo", m.domain_lo, (N_INPUT,), where)
    _shape("domain_hi", m.domain_hi, (N_INPUT,), where)
    _shape("train_x", m.train_x, (n, N_INPUT), where)
    _shape("lengthscale", m.lengthscale, (n_tasks, N_INPUT), where)
    _shape("outputscale", m.outputscale, (n_tasks,), where)
    _shape("noise", m.noise, (n_tasks,), where)
    _shape("chol", m.chol, (n_tasks, n, n), where)
    _shape("alpha", m.alpha, (n_tasks, n), where)
    if np.any(m.theta[:2] <= 0):
        raise ValueError(f"{where}: theta1 and theta2 (inertia terms) must be positive, got {m.theta[:2]}")
    if np.any(m.domain_hi <= m.domain_lo):
        raise ValueError(f"{where}: domain_hi must exceed domain_lo on every axis ({m.domain_lo} vs {m.domain_hi})")
    for name in ("lengthscale", "outputscale", "noise"):
        if np.any(getattr(m, name) <= 0):
            raise ValueError(f"{where}: {name!r} must be positive")
    if np.any(np.diagonal(m.chol, axis1=1, axis2=2) <= 0):
        raise ValueError(f"{where}: 'chol' is not a valid Cholesky factor (non-positive diagonal)")
