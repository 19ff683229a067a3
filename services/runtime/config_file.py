"""YAML settings files read with their line numbers, so that a mistake is reported where it is.

`read_yaml(path)` gives the data and, for every mapping key and list item, its line and column (the nodes' marks
from one parse). A YAML syntax error is one line, `FILE:LINE:COL: problem`, never a traceback or
"<unicode string>". `validation_problems` turns a pydantic `ValidationError` into `FILE:LINE:COL: where: what
(got ...)` items, located through those marks. Both raise or build a `ConfigFileError`, a `ValueError` whose
message is one line, which the CLI prints as it is (exit 2).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from gpmppi.yaml_file import yaml_error

Loc = tuple[str | int, ...]
Marks = dict[Loc, tuple[int, int]]  # key path -> (line, column), both from 1


class ConfigFileError(ValueError):
    """A settings file that cannot be used; the message is one line that names the file (and the line)."""


def _where(path: str | Path, line_col: tuple[int, int] | None) -> str:
    return f"{path}:{line_col[0]}:{line_col[1]}" if line_col else str(path)


def _one_line(text: str) -> str:
    return " ".join(text.split())


def read_yaml(path: str | Path) -> tuple[Any, Marks]:
    """(data, marks) of a YAML file; `ConfigFileError` for a missing file or a syntax error."""
    p = Path(path)
    try:
        text = p.read_text()
    except FileNotFoundError:
        raise ConfigFileError(f"{path}: no such file; give an existing YAML file") from None
    except (IsADirectoryError, UnicodeDecodeError, PermissionError) as exc:
        raise ConfigFileError(f"{path}: cannot read it as a YAML file ({_one_line(str(exc))})") from None
    loader = yaml.SafeLoader(text)
    try:
        node = loader.get_single_node()
        data = loader.construct_document(node) if node is not None else None
    except yaml.YAMLError as exc:
        raise ConfigFileError(yaml_error(path, exc)) from None
    finally:
        loader.dispose()
    marks: Marks = {}
    if node is not None:
        _collect(node, (), marks)
        marks[()] = (node.start_mark.line + 1, node.start_mark.column + 1)
    return data, marks


def _collect(node: yaml.Node, prefix: Loc, marks: Marks) -> None:
    if isinstance(node, yaml.MappingNode):
        for key, value in node.value:
            name = key.value if isinstance(key, yaml.ScalarNode) else str(key.value)
            marks[(*prefix, name)] = (key.start_mark.line + 1, key.start_mark.column + 1)
            _collect(value, (*prefix, name), marks)
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            marks[(*prefix, i)] = (item.start_mark.line + 1, item.start_mark.column + 1)
            _collect(item, (*prefix, i), marks)


def locate(marks: Marks, loc: Loc) -> tuple[int, int] | None:
    """The line and column of the longest prefix of `loc` that the file holds (a field the file does not
    name is reported at its parent)."""
    for n in range(len(loc), -1, -1):
        if tuple(loc[:n]) in marks:
            return marks[tuple(loc[:n])]
    return None


def validation_problems(
    exc: ValidationError, path: str | Path, marks: Marks, prefix: Loc = (), label: str = ""
) -> list[str]:
    """One `FILE:LINE:COL: label.field: message (got value)` item per error; `prefix` is where the validated
    mapping sits in the file (e.g. ('services', 2, 'config'))."""
    out = []
    for err in exc.errors():
        loc = tuple(err["loc"])
        field = ".".join(str(p) for p in loc)
        where = locate(marks, (*prefix, *loc))
        name = f"{label}.{field}" if label and field else label or field
        value = repr(err.get("input"))
        value = value if len(value) <= 80 else value[:77] + "..."
        got = f" (got {value})" if "input" in err and err["type"] != "missing" else ""
        out.append(_one_line(f"{_where(path, where)}: {name}: {err['msg']}{got}"))
    return out


def one_line(problems: Iterable[str]) -> str:
    """Several problems as one line: the first, then the others after '; '."""
    return "; ".join(problems)
