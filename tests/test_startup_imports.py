"""No service pays at its start for a heavy library it does not use there (issue 42: the suite starts ~150 service
processes on 2 cores, and each second of a start is CPU the rest of the suite waits for).

One process does what the stack's services do before they open their sessions (their modules, settings, the
profile, the terrain estimator, the planner), and says after each group which heavy modules are loaded. Each of
these was once imported at a service's start and cost it 0.2-1 s of CPU: sklearn (the online ground fit),
scipy.signal (the planner's smoother matrix), scipy.ndimage (the costmap), cvxpy (the paper's estimator) and what
they pull in. Where one comes back, import it where it is used (as gpmppi/models/identify.py does)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

HEAVY = ("sklearn", "scipy.signal", "scipy.stats", "scipy.ndimage", "scipy.sparse", "scipy.optimize",
         "scipy.interpolate", "scipy.spatial", "cvxpy", "torch", "gpytorch")

SCRIPT = f"""
import json, sys
HEAVY = {HEAVY!r}
seen = {{}}
def snapshot(name, also=()):
    seen[name] = sorted(m for m in HEAVY + tuple(also) if m in sys.modules)

from services.run import service_module, settings_class
def start(kind):
    service_module(kind)
    return settings_class(kind).load(None)

for kind in ("router", "sim", "ingress", "egress", "recorder"):
    start(kind)
snapshot("light", also=("scipy", "numba.cuda"))

from gpmppi.gp.model_file import load_default_model
from gpmppi.terrain.estimator import make_estimator
from gpmppi.terrain.settings import profile_calibration
model = load_default_model()
terrain = start("terrain")
profile_calibration(terrain.estimator, model)
make_estimator(model, terrain.estimator)
snapshot("terrain", also=("scipy.linalg", "scipy.special"))

from gpmppi.mppi.planner import Planner
from services.planner import warm_up_scenario
planner = start("planner")
warm_up_scenario(planner.scenario)
Planner(planner.planner, model)
snapshot("planner")
print(json.dumps(seen))
"""


def test_services_start_without_heavy_imports() -> None:
    proc = subprocess.run([sys.executable, "-c", SCRIPT], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    seen = json.loads(proc.stdout.strip().splitlines()[-1])
    # sim, ingress, egress, recorder and the router need no scipy at all; the terrain service none of the above nor
    # scipy.linalg / scipy.special (its estimator is numpy); the planner scipy.special (its chance quantiles) and
    # scipy.linalg (its smoother's least squares), nothing heavier
    assert seen == {"light": [], "terrain": [], "planner": []}
