"""Compiler flags shared by the planner kernels."""

from __future__ import annotations

# fastmath without 'nnan'/'ninf': the kernels rely on inf/NaN checks (infinite costs, safe controls)
FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}
