#!/usr/bin/env bash
# Set up (or refresh) the project's virtual environment in .venv, and warm the planner's kernel cache.
# torch is pinned to the CPU build first: an unpinned torch may pull a multi-GB CUDA build.
set -euo pipefail
cd "$(dirname "$0")/.."
# Python's byte-code cache: where the environment sets PYTHONDONTWRITEBYTECODE (some images do), no process ever
# writes a .pyc and each one compiles every module it imports from source (with the --no-compile below, numpy's and
# torch's too: 0.65 -> 2.0 CPU s for the planner's imports). Unset here, the warm-up below writes them for what the
# services import, and later processes read them whatever the environment says.
unset PYTHONDONTWRITEBYTECODE
python3 -m venv .venv
# --no-compile: pip would byte-compile every installed module (~15,000 files, ~50 s of CPU on a small machine, most
# of them never imported); Python compiles those a process imports on first use instead, and keeps them
PIP=(.venv/bin/python -m pip install -q --disable-pip-version-check --no-compile)
"${PIP[@]}" torch==2.13.0
"${PIP[@]}" -e '.[dev]'
# numba compiles the kernels on first use and caches them (per source version): compiled here, the services
# of `gpmppi demo` / `gpmppi launch` start in seconds instead of compiling at start
echo "warming the planner kernel cache (about 30 s, once)..."
.venv/bin/gpmppi warm
