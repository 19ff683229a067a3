"""One line for a YAML syntax error: `FILE:LINE:COL: YAML syntax error: problem (context)`, never yaml's own
multi-line text (which names "<unicode string>" when the text was read first)."""

from __future__ import annotations

from pathlib import Path

import yaml


def yaml_error(path: str | Path, exc: yaml.YAMLError) -> str:
    """The one-line message for `exc`, raised while parsing the file at `path`."""
    if isinstance(exc, yaml.MarkedYAMLError):
        mark = exc.problem_mark or exc.context_mark
        problem = " ".join((exc.problem or exc.context or "invalid YAML").split())
        if exc.context and exc.problem:
            problem = f"{problem} ({' '.join(exc.context.split())})"
        where = f"{path}:{mark.line + 1}:{mark.column + 1}" if mark is not None else str(path)
        return f"{where}: YAML syntax error: {problem}"
    return f"{path}: YAML syntax error: {' '.join(str(exc).split())}"
