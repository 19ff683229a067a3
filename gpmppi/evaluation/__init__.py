"""Closed-loop evaluation: run planner + terrain estimator + plant in one process, and score the runs."""
