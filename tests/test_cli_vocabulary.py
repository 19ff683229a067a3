"""One vocabulary: every command's help read, and docs/cli.md's table checked against the code.

The table's rows name a concept and its flags; here each concept is found in the code by what the parameter is
(its name, its type), and the flags every command gives it must be the table's."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
import typer
from typer.testing import CliRunner

from tools.choices import ModelName
from tools.cli import app
from tools.cli_checks import leaf_commands

REPO = Path(__file__).resolve().parents[1]
CLI = typer.main.get_command(app)
TREE = leaf_commands(CLI)
runner = CliRunner()


def _ann(p: Any) -> Any:
    ann = p.type_descriptor.annotation
    args = getattr(ann, "__args__", None)
    return next((a for a in args if a is not type(None)), ann) if args else ann


# docs/cli.md row ("what") -> how the code shows that a parameter is that concept
CONCEPTS = {
    "terrain (a ground name)": lambda p: p.name == "terrain",
    "planner model (gp, edd5, unicycle)": lambda p: _ann(p) is ModelName,
    "output file or folder": lambda p: p.param_type_name == "option" and p.name in ("output", "out", "out_dir"),
    "worker processes": lambda p: p.name == "workers",
    "robot profile (.npz from `gpmppi train`: GP, nominal model, terrain calibration)": lambda p: p.name in (
        "gp_model", "model_path", "profile")
    or (_ann(p) is Path and p.name == "model"),
    "launch file (YAML)": lambda p: p.param_type_name == "option" and p.name in ("launch_file", "launch", "deploy"),
    "terrain estimator setting": lambda p: p.name == "estimator" and "KEY=VALUE" in (p.help or "")
    and "METHOD" not in (p.help or ""),
    "an estimator to compare": lambda p: p.name == "estimator" and "METHOD" in (p.help or ""),
    "replace an existing output": lambda p: p.name == "force",
    "router port on 127.0.0.1": lambda p: p.name == "port",
    "seed": lambda p: p.name == "seed",
}


def table() -> dict[str, set[str]]:
    """docs/cli.md's vocabulary table: what -> the flags in its flag column."""
    rows: dict[str, set[str]] = {}
    text = (REPO / "docs" / "cli.md").read_text()
    section = text.split("## Vocabulary", 1)[1]
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 3 or cells[0] in ("what", "---"):
            continue
        rows[cells[0]] = set(re.findall(r"(?<![\w-])(--?[a-z][\w-]*)", cells[1]))
    return rows


def test_the_table_names_every_concept_checked_here() -> None:
    assert set(CONCEPTS) <= set(table()), set(CONCEPTS) - set(table())


@pytest.mark.parametrize("concept", list(CONCEPTS))
def test_each_concept_has_the_tables_flags_in_every_command(concept: str) -> None:
    want = table()[concept]
    found = []
    for path, cmd in TREE:
        for p in cmd.params:
            if p.param_type_name == "option" and CONCEPTS[concept](p):
                flags = {o for o in [*p.opts, *p.secondary_opts]}
                found.append(" ".join(path))
                assert flags <= want, f"{' '.join(path)}: {concept} is {sorted(flags)}, docs/cli.md says {sorted(want)}"
                assert any(f.startswith("--") for f in flags & want)
    assert found, f"no command has {concept}"


def test_the_short_flags_mean_one_thing() -> None:
    """-t is always the terrain, -m the planner model, -o the output, -j the workers (and -n the trials)."""
    meaning = {"-t": "terrain", "-m": "model", "-o": ("output", "out", "out_dir"), "-j": "workers", "-n": "trials"}
    for path, cmd in TREE:
        for p in cmd.params:
            for flag in p.opts:
                if len(flag) == 2 and flag in meaning:
                    names = meaning[flag] if isinstance(meaning[flag], tuple) else (meaning[flag],)
                    assert p.name in names, f"{' '.join(path)}: {flag} is {p.name}"


def test_no_path_option_is_called_model() -> None:
    """--model is the planner model everywhere; a robot profile (the GP model file) is --profile."""
    for path, cmd in TREE:
        for p in cmd.params:
            if "--model" in p.opts:
                assert _ann(p) is ModelName, f"{' '.join(path)}: --model is {_ann(p)}"


@pytest.mark.parametrize("path", [p for p, _ in TREE], ids=[" ".join(p) for p, _ in TREE])
def test_every_command_has_help_with_h_and_shows_its_defaults(path: tuple[str, ...], monkeypatch) -> None:
    monkeypatch.setenv("COLUMNS", "200")
    long = runner.invoke(app, [*path, "--help"])
    short = runner.invoke(app, [*path, "-h"])
    assert long.exit_code == 0 and short.exit_code == 0, (long.output, short.output)
    assert long.output == short.output and "Usage:" in long.output
    cmd = dict(TREE)[path]
    shown = [p for p in cmd.params if p.param_type_name == "option" and p.default not in (None, False, [], ())]
    assert long.output.count("[default:") >= len(shown), (path, [p.name for p in shown], long.output)
