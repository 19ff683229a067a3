"""Bad input on every command: exit 2, one line naming the option, no traceback, nothing written, within seconds.

The cases are generated from the command tree itself (every option and path argument of every command, with the bad
values its kind admits: NaN, inf, out of its declared range, a missing file, a folder for a file, a file for a folder,
an existing output file, an output in a missing folder), so a new option is tried without a line here. The cases the
issue measured are listed below as well, and hypothesis draws further out-of-range numbers."""

from __future__ import annotations

import math
import os
import time
from pathlib import Path
from typing import Any

import pytest
import typer
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from tools.cli import app
from tools.cli_checks import DIR, OUT_DIR, OUT_FILE, RECORDING, leaf_commands, param_label

runner = CliRunner()
CLI = typer.main.get_command(app)  # built once (0.1 s a build): the cases call it as the console script does
TREE = leaf_commands(CLI)


def annotation(param: Any) -> Any:
    return param.type_descriptor.annotation


def base_type(param: Any) -> Any:
    ann = annotation(param)
    args = getattr(ann, "__args__", None)
    if args:  # list[float], float | None
        return next((a for a in args if a is not type(None)), ann)
    return ann


def is_path(param: Any) -> bool:
    return base_type(param) is Path


def baseline(param: Any, root: Path) -> str:
    """A value that passes the checks, for the required parameters beside the one under test."""
    if is_path(param):
        if param.metavar == OUT_FILE:
            return str(root / "fresh.out")
        if param.metavar == OUT_DIR:
            return str(root / "fresh-dir")
        if param.metavar == RECORDING:
            return str(root / "run.mcap")
        if param.metavar == DIR:
            return str(root / "a-folder")
        return str(root / "an-input.txt")
    return {"name": "planner"}.get(param.name, "x")


def bad_values(param: Any, root: Path) -> list[tuple[str, str]]:
    """(what, value) pairs that must be refused for this parameter."""
    t = base_type(param)
    out: list[tuple[str, str]] = []
    if t in (float, int):
        out += [("nan", "nan"), ("inf", "inf"), ("-inf", "-inf")]
        lo, hi = getattr(param, "min", None), getattr(param, "max", None)
        step = 1 if t is int else 1.0
        if lo is not None:
            out.append(("below min", str(lo - step)))
        if hi is not None:
            out.append(("above max", str(hi + step)))
    elif is_path(param):
        if param.metavar == OUT_FILE:
            out += [("a folder", str(root / "a-folder")), ("missing folder", str(root / "nope" / "x.out")),
                    ("existing file", str(root / "an-input.txt"))]
        elif param.metavar == OUT_DIR:
            out += [("a file", str(root / "an-input.txt")), ("missing parent", str(root / "nope" / "d"))]
        elif param.metavar == RECORDING:
            out += [("missing folder", str(root / "nope" / "run.mcap"))]
        elif param.metavar == DIR:
            out += [("missing", str(root / "missing-dir")), ("a file", str(root / "an-input.txt"))]
        else:
            out += [("missing", str(root / "missing.file")), ("a folder", str(root / "a-folder")),
                    ("empty", "")]
    return out


def args_for(cmd: Any, target: Any, value: str, root: Path) -> list[str]:
    args: list[str] = []
    for p in cmd.params:
        given = p is target
        if p.param_type_name == "argument":
            if p.required or given:
                args.append(value if given else baseline(p, root))
        elif given or p.required:
            args += [p.opts[0], value if given else baseline(p, root)]
    return args


def cases() -> list[Any]:
    out = []
    root = Path("/ROOT")
    for path, cmd in TREE:
        for p in cmd.params:
            for what, _ in bad_values(p, root):
                out.append(pytest.param(path, p.name, what, id=f"{' '.join(path)} {param_label(p)} {what}"))
    return out


def snapshot(folder: Path) -> dict[str, float]:
    return {str(p.relative_to(folder)): p.stat().st_mtime for p in folder.rglob("*")}


def answer(args: list[str], root: Path) -> tuple[int, list[str], float]:
    t0 = time.perf_counter()
    result = runner.invoke(app, args)
    lines = [line for line in result.output.splitlines() if line.strip()]
    return result.exit_code, lines, time.perf_counter() - t0


def refused(args: list[str], label: str, root: Path) -> None:
    before = snapshot(root)
    code, lines, seconds = answer(args, root)
    assert code == 2, (args, lines)
    assert len(lines) == 1, (args, lines)
    assert label in lines[0], (args, lines)
    assert "Traceback" not in lines[0] and lines[0].startswith("gpmppi "), lines
    assert seconds < 5.0, (args, seconds)
    assert snapshot(root) == before, f"{args} wrote {set(snapshot(root)) - set(before)}"


@pytest.fixture
def root(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setattr("typer.testing._get_command", lambda _app: CLI)  # the tree built once, not per case
    (tmp_path / "an-input.txt").write_text("not what any command reads\n")
    (tmp_path / "a-folder").mkdir()
    monkeypatch.chdir(tmp_path)  # outputs with defaults (evaluate table's evaluation/) land here if anywhere
    return tmp_path


def test_the_generated_cases_cover_every_command() -> None:
    commands_with_cases = {c.values[0] for c in cases()}
    assert len(commands_with_cases) == len(TREE) - 1, set(p for p, _ in TREE) - commands_with_cases  # warm: none
    assert len(cases()) > 300


@pytest.mark.timeout(60)
@pytest.mark.parametrize(("path", "name", "what"), cases())
def test_every_option_refuses_bad_values(path: tuple[str, ...], name: str, what: str, root: Path) -> None:
    cmd = dict(TREE)[path]
    param = next(p for p in cmd.params if p.name == name)
    value = dict(bad_values(param, root))[what]
    refused([*path, *args_for(cmd, param, value, root)], param_label(param), root)


NUMERIC = [(path, p) for path, cmd in TREE for p in cmd.params if base_type(p) is float
           and (getattr(p, "min", None) is not None or getattr(p, "max", None) is not None)]


@pytest.mark.timeout(120)
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_out_of_range_numbers_are_refused(data: st.DataObject, root: Path) -> None:
    path, param = data.draw(st.sampled_from(NUMERIC), label="option")
    lo, hi = getattr(param, "min", None), getattr(param, "max", None)
    value = data.draw(st.floats(allow_nan=True, allow_infinity=True).filter(
        lambda x: not math.isfinite(x) or (lo is not None and x < lo) or (hi is not None and x > hi)), label="value")
    cmd = dict(TREE)[path]
    refused([*path, *args_for(cmd, param, repr(value), root)], param_label(param), root)


# The cases measured on main before this checking (each was exit 0, a hang, a traceback, or an answer after the work)
ISSUE_CASES = [
    (["launch", "--duration", "nan"], "--duration"),
    (["launch", "--duration", "-5"], "--duration"),
    (["launch", "--port", "-1"], "--port"),
    (["replay", "{input}", "--speed", "nan"], "--speed"),
    (["replay", "{input}", "--end", "inf"], "--end"),
    (["evaluate", "terrain-gains", "--distance", "inf"], "--distance"),
    (["evaluate", "tracking", "--distance", "inf"], "--distance"),
    (["dataset", "-o", "{root}/d.mcap", "--distance", "inf"], "--distance"),
    (["evaluate", "avoidance", "--lane-file", "{input}"], "--lane-file"),
    (["evaluate", "tracking", "--scene-file", "{input}"], "--scene-file"),
    (["bench", "zenoh", "--launch-file", "{root}/missing.yaml"], "--launch-file"),
    (["train", "{input}", "-o", "{root}/a-folder"], "--output"),
    (["evaluate", "tracking", "-o", "{input}"], "--output"),
    (["replay", "{input}", "--rerun", "save", "--rerun-target", "{root}/a-folder"], "--rerun-target"),
    (["dataset", "-o", "{root}/a-folder"], "--output"),
    (["gp", "predict", "{input}", "--profile", "{input}", "-o", "{root}/a-folder"], "--output"),
    (["schemas", "export", "{input}"], "OUT_DIR"),
    (["launch", "--record", "{root}/nonexistent/dir/x.mcap"], "--record"),
    (["evaluate", "tracking", "--profile", "{input}"], "--profile"),
    (["evaluate", "tracking", "--estimator", "bogus=1"], "bogus"),
    (["evaluate", "tracking", "--estimator", "nokeyvalue"], "KEY=VALUE"),
    (["train", "{input}", "-o", "{root}/m.npz"], "not an MCAP file"),
    (["train", "{root}/text.mcap", "-o", "{root}/m.npz"], "not an MCAP file"),
    (["replay", "{input}", "--rerun", "save", "--rerun-target", "{root}/v.rrd", "--speed", "2"], "--speed"),
    (["launch", "{root}/view.rrd"], "--rerun-target"),
    # further cases of ours: a file of the wrong kind or content is named with its line where it has one
    (["launch", "{root}/bad.yaml"], "bad.yaml:2:1: YAML syntax error"),
    (["service", "planner", "--config", "{root}/bad.yaml"], "bad.yaml:2:1: YAML syntax error"),
    (["evaluate", "tracking", "--lane-file", "{root}/bad.yaml"], "bad.yaml:2:1: YAML syntax error"),
    (["evaluate", "tracking", "--terrain-file", "{root}/bad.yaml"], "bad.yaml:2:1: YAML syntax error"),
    (["evaluate", "tracking", "--launch-file", "{root}/bad.yaml"], "bad.yaml:2:1: YAML syntax error"),
    (["evaluate", "tracking", "--plant", "residual-net", "--plant-file", "{input}"], "--plant-file"),
    (["evaluate", "tracking", "--plant", "residual-net"], "--plant-file"),
    (["evaluate", "table", "-o", "{root}/a-folder"], "--force"),
    (["replay", "{input}"], "not an MCAP file"),
    (["inspect", "{input}"], "not an MCAP file"),
    (["replay", "{input}", "--start", "5", "--end", "2"], "--end"),
    (["launch", "--rerun", "save"], "--rerun-target"),
    (["launch", "--rerun-target", "{root}/v.rrd"], "--rerun-target"),
    (["service", "bogus"], "unknown service"),
    (["bench", "view", "--minutes", "abc"], "--minutes"),
    (["evaluate", "tracking", "--switch", "abc"], "--switch"),
    (["evaluate", "tracking", "--set", "bogus=1"], "--set"),
    (["secure", "init", "{root}/nope/secrets"], "does not exist"),
    # an option that only applies with another is an error without it, not ignored
    (["bench", "planner", "--collapse-in-plan"], "--collapse-in-plan"),
    (["bench", "planner", "-m", "edd5", "--gp", "exact"], "--gp"),
    (["bench", "viewer-stall", "--mode", "stack", "--rate", "5"], "--rate"),
    (["replay", "{input}", "--lockstep"], "--lockstep"),
    (["replay", "{input}", "--set", "planner.samples=64"], "--set"),
    (["secure", "init", "{root}/secrets", "--tls-endpoint", "tls/127.0.0.1:9"], "--tls-endpoint"),
    (["secure", "init", "{root}/secrets", "--ros2-cmd-key", "a/b"], "--ros2-cmd-key"),
    (["evaluate", "tracking", "--plant-file", "{input}"], "--plant-file"),
]


@pytest.mark.timeout(60)
@pytest.mark.parametrize(("args", "named"), ISSUE_CASES, ids=[" ".join(a) for a, _ in ISSUE_CASES])
def test_the_measured_cases_answer_at_once(args: list[str], named: str, root: Path) -> None:
    (root / "text.mcap").write_text("a text file named like a log\n")
    (root / "view.rrd").write_text("")
    (root / "bad.yaml").write_text("a: [1, 2\n")
    (root / "a-folder" / "table.md").write_text("an earlier table\n")
    filled = [a.format(input=root / "an-input.txt", root=root) for a in args]
    refused(filled, named, root)


def test_an_existing_output_is_replaced_only_with_force(root: Path) -> None:
    out = root / "schemas"
    assert runner.invoke(app, ["schemas", "export", str(out)]).exit_code == 0
    first = {p.name: p.read_text() for p in out.iterdir()}
    (out / "keys.json").write_text("mine\n")
    refused(["schemas", "export", str(out)], "--force", root)
    assert (out / "keys.json").read_text() == "mine\n"
    assert runner.invoke(app, ["schemas", "export", str(out), "--force"]).exit_code == 0
    assert {p.name: p.read_text() for p in out.iterdir()} == first
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary file left


def test_a_bug_is_not_dressed_as_user_error(monkeypatch: pytest.MonkeyPatch) -> None:
    """Only expected errors become one line: any other exception keeps its traceback (and exit status 1)."""
    import tools.service_cmd as service_cmd

    def broken(*_: Any, **__: Any) -> int:
        raise KeyError("a bug")

    monkeypatch.setattr(service_cmd, "_launch", broken)
    result = runner.invoke(app, ["launch", "--duration", "1"])
    assert result.exit_code == 1 and isinstance(result.exception, KeyError)


def test_debug_shows_the_traceback_of_a_user_error() -> None:
    env = {**os.environ, "GPMPPI_DEBUG": "1"}
    result = runner.invoke(app, ["launch", "--duration", "nan"], env=env)
    assert result.exit_code == 2 and "Traceback" in result.output


def test_the_user_errors_named_by_the_error_path_exist() -> None:
    """The error path names its expected errors (importing them would load numba before `--help`): each name must
    still be a class where it says, or that error would come out as a traceback."""
    import importlib

    from tools.cli_checks import USER_ERRORS

    for dotted in USER_ERRORS:
        module, _, name = dotted.rpartition(".")
        cls = getattr(importlib.import_module(module), name)
        assert isinstance(cls, type) and issubclass(cls, Exception), dotted
