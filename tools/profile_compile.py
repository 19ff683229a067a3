"""Where a cold compile's time goes: `python -m tools.profile_compile [--top N] [--json]`.

Runs the bench's GP planner (`tools.bench_planner`, CPU, S=1024, N=40) for a few plans in one process
(`GPMPPI_COMPILE_AHEAD=0`) in an empty numba cache of its own (a temporary folder, removed after), with numba's
compile events ("numba:compile", `numba.core.event`) recorded: for each compiled function its own compile time (the
event's time less the compiles nested in it), its time including them, and how many type signatures
(specializations) it compiled. For measuring, not for a plan.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--top", type=int, default=25, help="functions listed, by their own compile time")
    p.add_argument("--plans", type=int, default=3)
    p.add_argument("--json", action="store_true")
    a = p.parse_args()
    cache = tempfile.mkdtemp(prefix="gpmppi-cold-")
    os.environ["NUMBA_CACHE_DIR"] = cache
    os.environ["GPMPPI_COMPILE_AHEAD"] = "0"
    try:
        print(json.dumps(_profile(a.plans, a.top)) if a.json else _text(_profile(a.plans, a.top)))
    finally:
        shutil.rmtree(cache, ignore_errors=True)


def _profile(plans: int, top: int) -> dict:
    t_start = time.perf_counter()
    c_start = time.process_time()
    from numba.core import event

    stack: list[list] = []  # [name, start, nested seconds]
    own: dict[str, float] = {}
    incl: dict[str, float] = {}
    sigs: dict[str, int] = {}

    class _Listener(event.Listener):
        def on_start(self, ev: event.Event) -> None:
            d = ev.data["dispatcher"]
            name = f"{d.py_func.__module__}.{d.py_func.__qualname__}"
            stack.append([name, time.perf_counter(), 0.0])

        def on_end(self, ev: event.Event) -> None:
            name, t0, nested = stack.pop()
            dt = time.perf_counter() - t0
            own[name] = own.get(name, 0.0) + dt - nested
            incl[name] = incl.get(name, 0.0) + dt
            sigs[name] = sigs.get(name, 0) + 1
            if stack:
                stack[-1][2] += dt

    event.register("numba:compile", _Listener())
    import numpy as np

    from gpmppi.mppi.planner import PlannerConfig
    from tools.bench_planner import _load_model, _Ours

    t_import = time.perf_counter() - t_start
    model, _ = _load_model()
    weights = np.linspace(1.0, 2.0, len(model.terrains))
    weights /= weights.sum()
    ours = _Ours(PlannerConfig(samples=1024, horizon=40, backend="cpu"), model, weights)
    t0 = time.perf_counter()
    ours.step()
    first_plan = time.perf_counter() - t0
    for _ in range(plans - 1):
        ours.step()
    wall = time.perf_counter() - t_start
    order = sorted(own, key=own.get, reverse=True)  # type: ignore[arg-type]
    return {"wall_s": wall, "cpu_s": time.process_time() - c_start, "import_s": t_import, "first_plan_s": first_plan,
            "compiled_s": sum(own.values()), "functions": len(own), "signatures": sum(sigs.values()),
            "top": [{"function": n, "own_s": own[n], "with_nested_s": incl[n], "signatures": sigs[n]}
                    for n in order[:top]]}


def _text(res: dict) -> str:
    lines = [f"cold process: {res['wall_s']:.1f} s wall, {res['cpu_s']:.1f} s CPU (imports {res['import_s']:.1f} s, "
             f"first plan {res['first_plan_s']:.1f} s); numba compiled {res['functions']} functions, "
             f"{res['signatures']} signatures, {res['compiled_s']:.1f} s",
             f"{'own s':>7} {'incl s':>7} {'sigs':>4}  function"]
    lines += [f"{t['own_s']:7.2f} {t['with_nested_s']:7.2f} {t['signatures']:4d}  {t['function']}" for t in res["top"]]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
