"""Per-terrain residual GPs: the model file, training, and the exact and grid predictors."""

from gpmppi.gp.grid_table import GridTable
from gpmppi.gp.model_file import GPModel, ModelFileError, load_default_model

__all__ = ["GPModel", "GridTable", "ModelFileError", "load_default_model"]
