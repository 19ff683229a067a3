"""gpmppi: chance-constrained GP-MPPI for skid-steer robots. Pure: arrays in, arrays out."""

__version__ = "0.1.0"
