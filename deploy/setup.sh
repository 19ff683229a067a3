#!/usr/bin/env bash
# Set up (or refresh) the project's virtual environment in .venv, and warm the planner's kernel cache.
# torch is pinned to the CPU build first: an unpinned torch may pull a multi-GB CUDA build.
set -euo pipefail
cd "$(dirname "$0")/.."
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
