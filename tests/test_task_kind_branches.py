"""Counted in the code: no branch on the task kind outside the kind objects.

What differs between a lane and a goal lives in the kinds: the task types (`gpmppi/tasks.py`: the plain part, e.g.
`outline`, `start_problems`), the planner's `TaskKind`s (`gpmppi/mppi/task_kinds.py`) and the evaluation's `TaskRun`s
(`gpmppi/evaluation/task_runs.py`); the kernels pick a kind's critics through chains built from the registered kinds
(`critics.registry.ByKind`), the message codecs and the message's own field checks are tables keyed by the kind's
name. Everywhere else a branch on which kind a task is (an `isinstance` of a task type, a comparison of a `kind` with
a kind's name or number) is a place a new kind would have to be added by hand: this test fails on each.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCANNED = ("gpmppi", "services", "tools", "schemas")
# the kind objects themselves: they may name their own kinds
KIND_OBJECTS = {"gpmppi/tasks.py", "gpmppi/mppi/task_kinds.py", "gpmppi/evaluation/task_runs.py"}

_KIND_NAME = r"""["'](?:lane|goal)["']"""
BRANCHES = [
    re.compile(r"isinstance\([^)]*\b(?:LaneTask|GoalTask)\b"),  # an isinstance of a task type
    re.compile(r"type\([^)]*\)\s+(?:is|==)\s+(?:LaneTask|GoalTask)\b"),
    re.compile(rf"kind\s*(?:==|!=)\s*{_KIND_NAME}"),  # msg.kind == "lane", task_kind != "goal"
    re.compile(rf"{_KIND_NAME}\s*(?:==|!=)\s*[\w.]*kind\b"),
    re.compile(rf"\bkind\s+(?:not\s+)?in\s+[(\[{{]\s*{_KIND_NAME}"),
    re.compile(r"\bkind\s*(?:==|!=)\s*TASK_(?:LANE|GOAL)\b"),  # a kernel kind by number
    re.compile(rf"^\s*case\s+{_KIND_NAME}"),
]


def branches(text: str) -> list[tuple[int, str]]:
    """(line number, line) of each branch on the task kind in `text`."""
    return [(n, line.strip()) for n, line in enumerate(text.splitlines(), 1)
            if not line.lstrip().startswith("#") and any(p.search(line) for p in BRANCHES)]


def test_the_count_finds_each_form_of_branch() -> None:
    """The patterns catch the branches this issue moved into the kinds (so a clean count means something)."""
    found = branches(
        "    if isinstance(task, LaneTask):\n"
        "    if task is not None and task.kind == \"lane\":\n"
        "        if self.task_kind == 'goal':\n"
        "    if task is None or task.kind != \"lane\" or not states:\n"
        "    lane = task.kind == TASK_LANE\n"
        "    if not isinstance(task, (GoalTask, Foo)) or x:\n"
        "    if \"lane\" == msg.kind:\n"
        "    if msg.kind in (\"lane\", \"goal\"):\n"
        "        case \"goal\":\n"
        "    # if isinstance(task, LaneTask): a comment\n"
        "    kind: Literal[\"lane\", \"goal\"]\n"
        "    if task.kind == other.kind:\n"
    )
    assert [n for n, _ in found] == [1, 2, 3, 4, 5, 6, 7, 8, 9]


def test_no_branch_on_the_task_kind_outside_the_kind_objects() -> None:
    found = []
    for top in SCANNED:
        for path in sorted((ROOT / top).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            if rel in KIND_OBJECTS:
                continue
            found += [f"{rel}:{n}: {line}" for n, line in branches(path.read_text())]
    assert not found, ("branches on the task kind outside the kind objects (give the kinds a method or attribute "
                       "for it, gpmppi/tasks.py, task_kinds.py, task_runs.py):\n" + "\n".join(found))
