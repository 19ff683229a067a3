"""`python -m tools.startup_cpu [LAUNCH.yaml] [--runs 3]`: the CPU each process of a stack spends to start.

Runs `gpmppi launch LAUNCH --duration 0.1` `runs` times and prints, per process, its CPU seconds (user + system, its
own `getrusage`) when it told the launcher it is ready (`services.runtime.role.wait_for_role`: imports, settings,
model and kernels done, session not yet open) and when it exited, with the heavy modules loaded at ready; and the
whole run's CPU (the launcher and every process it reaped). CPU seconds, not wall time: on a shared machine they
move much less with its load. A `sitecustomize` written to a temporary directory on the children's PYTHONPATH takes
the readings (issue 42; docs/development.md, "What the suite's slowest tests cost").
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

HEAVY = ("sklearn", "scipy.signal", "scipy.stats", "scipy.ndimage", "scipy.sparse", "scipy.optimize",
         "scipy.interpolate", "scipy.linalg", "scipy.special", "cvxpy", "torch", "numba", "numba.cuda")

# runs in every Python process of the launch (the probe's directory is first on PYTHONPATH)
PROBE = '''
import importlib.abc, importlib.machinery, json, os, resource, sys
_OUT = os.environ.get("GPMPPI_STARTUP_CPU_DIR")
_HEAVY = __HEAVY__
if _OUT:
    _rec = {}
    def _cpu():
        r = resource.getrusage(resource.RUSAGE_SELF)
        return r.ru_utime + r.ru_stime
    def _name():
        argv = sys.argv
        for script, prefix in ((os.path.join("services", "run.py"), ""), (os.path.join("tools", "cli.py"), "gpmppi ")):
            if len(argv) > 1 and argv[0].endswith(script):
                return prefix + argv[1]
        return os.path.basename(argv[0]) if argv and argv[0] else "python"
    def _dump():
        if "exit_cpu" not in _rec:
            _rec.update(exit_cpu=_cpu(), name=_name())
            with open(os.path.join(_OUT, _rec["name"] + "-" + str(os.getpid()) + ".json"), "w") as f:
                json.dump(_rec, f)
    _exit = os._exit
    def _exit_after_dump(code):
        try:
            _dump()
        finally:
            _exit(code)
    os._exit = _exit_after_dump  # services leave by os._exit (services.run.exit_now): no atexit
    import atexit
    atexit.register(_dump)
    class _Ready(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path, target=None):
            if name != "services.runtime.role":
                return None
            spec = importlib.machinery.PathFinder.find_spec(name, path)
            run = spec.loader.exec_module
            def exec_module(module):
                run(module)
                wait = module.wait_for_role
                def wait_for_role(*args, **kwargs):
                    _rec.setdefault("ready_cpu", _cpu())
                    _rec.setdefault("heavy", [m for m in _HEAVY if m in sys.modules])
                    return wait(*args, **kwargs)
                module.wait_for_role = wait_for_role
            spec.loader.exec_module = exec_module
            return spec
    sys.meta_path.insert(0, _Ready())
'''.replace("__HEAVY__", repr(HEAVY))


def children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def measure(launch: Path | None, runs: int, port: int) -> None:
    per: dict[str, list[tuple[float | None, float]]] = defaultdict(list)
    heavy: dict[str, list[str]] = {}
    with tempfile.TemporaryDirectory(prefix="startup-cpu-") as tmp:
        (Path(tmp) / "sitecustomize.py").write_text(PROBE)
        for i in range(runs):
            out = Path(tmp) / f"run{i}"
            out.mkdir()
            env = {**os.environ, "GPMPPI_STARTUP_CPU_DIR": str(out),
                   "PYTHONPATH": os.pathsep.join(p for p in (tmp, os.environ.get("PYTHONPATH", "")) if p)}
            cmd = [sys.executable, "-m", "tools.cli", "launch", *([str(launch)] if launch else []),
                   "--duration", "0.1", "--port", str(port)]
            before = children_cpu()
            proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
            total = children_cpu() - before
            if proc.returncode != 0:
                sys.exit(f"run {i + 1}: `{' '.join(cmd)}` failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
            print(f"run {i + 1}: {total:.2f} CPU s in all")
            for f in sorted(out.glob("*.json")):
                rec = json.loads(f.read_text())
                per[rec["name"]].append((rec.get("ready_cpu"), rec["exit_cpu"]))
                heavy.setdefault(rec["name"], rec.get("heavy", []))
    print(f"{'process':16s} {'ready CPU s (mean)':>20s} {'exit CPU s (mean)':>19s}  heavy modules at ready")
    for name, values in sorted(per.items()):
        ready = [r for r, _ in values if r is not None]
        ready_s = f"{sum(ready) / len(ready):.2f}" if ready else "-"
        print(f"{name:16s} {ready_s:>20s} {sum(e for _, e in values) / len(values):>19.2f}  "
              f"{' '.join(heavy[name]) or '-'}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m tools.startup_cpu", description=__doc__.splitlines()[0])
    parser.add_argument("launch", nargs="?", type=Path, default=None, help="launch file (default: the shipped one)")
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--port", type=int, default=7861, help="the router's port (a free one)")
    args = parser.parse_args(argv)
    measure(args.launch, args.runs, args.port)


if __name__ == "__main__":
    main()
