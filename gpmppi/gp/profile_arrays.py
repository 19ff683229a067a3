"""The terrain calibration's arrays in a robot profile file (gpmppi.gp.model_file), and reading them back.

A profile (format version 2) stores the `TerrainCalibration` of its grounds in the model's ground order as five
arrays: `cal_command_gain` (M, 2), `cal_v_ref` (A,), `cal_omega_ref` (B,), `cal_steady` (M, A, B, 2) and
`cal_rate` (M, 2). A profile fitted from data without time series (a residual CSV) has none of them.
"""

from __future__ import annotations

import numpy as np

from gpmppi.profile.response import TerrainResponse
from gpmppi.profile.terrain_calibration import TerrainCalibration

CALIBRATION_ARRAYS = ("cal_command_gain", "cal_v_ref", "cal_omega_ref", "cal_steady", "cal_rate")


def calibration_arrays(calibration: TerrainCalibration, terrains: list[str]) -> dict[str, np.ndarray]:
    """The five arrays of `calibration`, its grounds put in the model's order `terrains`."""
    cal = calibration.select(list(terrains), source="robot profile")
    return {
        "cal_command_gain": np.asarray(cal.command_gain, dtype=np.float64),
        "cal_v_ref": np.asarray(cal.response.v_ref, dtype=np.float64),
        "cal_omega_ref": np.asarray(cal.response.omega_ref, dtype=np.float64),
        "cal_steady": np.asarray(cal.response.steady, dtype=np.float64),
        "cal_rate": np.asarray(cal.response.rate, dtype=np.float64),
    }


def calibration_from_arrays(arrays: dict[str, np.ndarray], terrains: list[str]) -> TerrainCalibration | None:
    """The calibration stored in `arrays` (None when it holds none of the five); ValueError when only part of it is
    there or a shape does not fit the grounds."""
    present = [n for n in CALIBRATION_ARRAYS if n in arrays]
    if not present:
        return None
    if len(present) != len(CALIBRATION_ARRAYS):
        missing = [n for n in CALIBRATION_ARRAYS if n not in arrays]
        raise ValueError(f"the terrain calibration is incomplete (missing {missing}); refit the profile")
    a = {n: np.asarray(arrays[n], dtype=np.float64) for n in CALIBRATION_ARRAYS}
    names = tuple(terrains)
    response = TerrainResponse(a["cal_v_ref"], a["cal_omega_ref"], names, a["cal_steady"], a["cal_rate"])
    return TerrainCalibration(names, a["cal_command_gain"], response)
