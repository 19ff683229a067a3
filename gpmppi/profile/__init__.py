"""What a robot profile holds beside the GP, as plain data both the model file (gpmppi.gp) and the terrain
estimator (gpmppi.terrain) read: each ground's velocity response (`response`) and the terrain calibration
(`terrain_calibration`). Imports nothing of ours, so neither package depends on the other through it.
"""
