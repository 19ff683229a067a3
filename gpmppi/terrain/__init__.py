"""Terrain identification: which mixture of the trained terrains is under the robot, and its calibration.

- `estimate`: what an estimator publishes (`TerrainEstimate`) and what every estimator is (`EstimatorLike`);
- `settings`: the estimator's settings (`EstimatorConfig`) and its command-change gains file;
- `estimator`: the estimators (the Bayesian filter, the paper's convex problem) and `make_estimator`;
- `cycle`: the terrain service's cycle, free of any transport (pairing, gating, timing, clean-up);
- (gpmppi.profile holds the data the estimator learns per ground besides the GP: the velocity response, the
  filter's second evidence, and the gains, both stored in the robot profile);
- `calibration`: fitting the command-change gains and the responses on drives of a plant;
- `log_calibration`: fitting the same calibration from a robot's logs alone (held commands, every step);
- `separability`: how well the terrains can be told apart on recorded transitions, and replaying estimators.

Services and tools call into these modules; nothing outside the package computes the evidence. This module imports
nothing, so a service can validate its settings (`settings`, `cycle`) without importing the solver (cvxpy).
"""
