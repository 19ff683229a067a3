#!/usr/bin/env bash
# Set up (or refresh) the project's virtual environment in .venv.
# torch is pinned to the CPU build first: an unpinned torch may pull a multi-GB CUDA build.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/python -m pip install -q --disable-pip-version-check torch==2.13.0
.venv/bin/python -m pip install -q --disable-pip-version-check -e '.[dev]'
