#!/usr/bin/env bash
# Set up (or refresh) the project's virtual environment in .venv, and warm the planner's kernel cache.
# torch is pinned to the CPU build first: an unpinned torch may pull a multi-GB CUDA build.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/python -m pip install -q --disable-pip-version-check torch==2.13.0
.venv/bin/python -m pip install -q --disable-pip-version-check -e '.[dev]'
# numba compiles the kernels on first use and caches them (per source version): compiled here, the services
# of `gpmppi demo` / `gpmppi launch` start in seconds instead of compiling at start
echo "warming the planner kernel cache (about 30 s, once)..."
.venv/bin/gpmppi warm
