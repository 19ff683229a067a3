"""Simulated robots: the physics skid-steer plant (default) and the paper's residual-network plant."""

from gpmppi.plant.base import Plant
from gpmppi.plant.physics import PhysicsPlant
from gpmppi.plant.residual_net import ResidualNetPlant
from gpmppi.plant.terrains import TerrainFileError, TerrainParams, TerrainSet, load_terrains

__all__ = [
    "Plant",
    "PhysicsPlant",
    "ResidualNetPlant",
    "TerrainFileError",
    "TerrainParams",
    "TerrainSet",
    "load_terrains",
]
