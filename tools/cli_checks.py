"""The command line's one error path, and the checks every command gets before it does any work.

Every `gpmppi` command runs through `CheckedGroup.main`: an expected error (bad option value, a file of the wrong
kind, a domain error such as `ScenarioFileError`) prints one line, `gpmppi CMD: what was wrong; what to do`, to
stderr and exits 2, with no traceback (`--debug` or `GPMPPI_DEBUG=1` shows it). Anything else is a bug: its
traceback is printed and the exit status is 1.

Before a command's body runs, every value it received is checked by what it is, so each new option is checked
without a line of its own:
- a number must be finite (typer's `min`/`max` bound the range; NaN and +-inf are never a setting here);
- a path whose metavar is `OUT_FILE` is an output file: not a folder, its folder exists and is writable, and it is
  not an existing file unless the command's `--force` is given;
- a path whose metavar is `OUT_DIR` is an output folder: not a file, its parent folder exists;
- a path whose metavar is `RECORDING` is a recording's destination: a writable folder, or a file whose folder
  exists (an existing file is kept: the launcher records to a free name beside it);
- every other path is an input: it exists, and is a folder where the metavar says `DIR`, else a readable file.

Only typer's public names are used (`typer.TyperException` is the base of its usage errors, whichever click it
carries).
"""

from __future__ import annotations

import math
import os
import re
import sys
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import typer
from typer.core import TyperGroup

OUT_FILE = "OUT_FILE"
OUT_DIR = "OUT_DIR"
RECORDING = "OUT.mcap|DIR"  # a recording: never replaces a file (the launcher picks a free name), a folder gets one
DIR = "DIR"

# Domain errors raised on bad user input (files of the wrong kind or content, unreachable peers). Named, not
# imported: importing them would load numba, torch and zenoh before every command, even `--help`.
USER_ERRORS = frozenset({
    "tools.cli_checks.UserError",
    "gpmppi.evaluation.deployed.DeployFileError",
    "gpmppi.scenarios.ScenarioFileError",
    "gpmppi.gp.model_file.ModelFileError",
    "gpmppi.plant.residual_net.NetworkFileError",
    "gpmppi.plant.terrains.TerrainFileError",
    "gpmppi.terrain.real_data.RealDataError",
    "gpmppi.profile.terrain_calibration.CalibrationDataError",
    "services.launch.launcher.RouterUnreachable",
    "services.recording.output_files.OutputPathError",
    "services.runtime.config_file.ConfigFileError",
    "services.recording.player_log.LogError",
    "services.security.secure.SecretsError",
    "services.recording.mcap_inspect.InspectError",
    "tools.replay_live.ReplaceError",
    "tools.evaluate_ray.RayBackendError",
    "tools.log_reader.DataError",
    "yaml.error.YAMLError",
})


class UserError(ValueError):
    """Bad input from the user: the message is one line saying what was wrong and what to do."""


def fail(message: str) -> None:
    """Stop the command with one line and exit status 2 (see `CheckedGroup.main`)."""
    raise UserError(message)


def is_user_error(exc: BaseException) -> bool:
    return any(f"{c.__module__}.{c.__qualname__}" in USER_ERRORS for c in type(exc).__mro__)


def one_line(text: str) -> str:
    return " ".join(str(text).split())


def _debug(args: Sequence[str]) -> bool:
    return "--debug" in args or os.environ.get("GPMPPI_DEBUG", "") not in ("", "0")


class CheckedGroup(TyperGroup):
    """The `gpmppi` group: every command's values checked before it runs, and one error path."""

    _checks_installed = False

    def main(  # type: ignore[override]
        self,
        args: Sequence[str] | None = None,
        prog_name: str | None = None,
        complete_var: str | None = None,
        standalone_mode: bool = True,
        **extra: Any,
    ) -> Any:
        args = list(sys.argv[1:] if args is None else args)
        prog = prog_name or "gpmppi"
        install_checks(self)
        where = " ".join([prog, *command_path(self, args)])
        try:
            rv = super().main(args, prog_name=prog, complete_var=complete_var, standalone_mode=False, **extra)
            code = rv if isinstance(rv, int) else 0
        except typer.Abort:
            print(f"{where}: aborted", file=sys.stderr)
            code = 130
        except typer.TyperException as exc:  # usage: unknown option, bad value, missing argument
            if _debug(args):
                traceback.print_exc()
            message = exc.format_message() if hasattr(exc, "format_message") else str(exc)
            message = _non_finite(args, message) or message
            print(f"{where}: {one_line(message)} (see {where} --help)", file=sys.stderr)
            code = 2
        except KeyboardInterrupt:
            code = 130
        except Exception as exc:
            if not is_user_error(exc):
                raise  # a bug: its traceback, exit status 1
            if _debug(args):
                traceback.print_exc()
            print(f"{where}: {one_line(str(exc))}", file=sys.stderr)
            code = 2
        if standalone_mode:
            sys.exit(code)
        return code


def _non_finite(args: Sequence[str], message: str) -> str | None:
    """A range error whose value was NaN or inf said as such (the range check's own words, 'should be less than
    or equal to ...', would not name what was wrong)."""
    match = re.match(r"Invalid value for '(--[\w-]+)'", message)
    if match is None:
        return None
    option = match.group(1)
    for i, arg in enumerate(args):
        value = args[i + 1] if arg == option and i + 1 < len(args) else None
        if arg.startswith(option + "="):
            value = arg.split("=", 1)[1]
        if value is not None:
            try:
                number = float(value)
            except ValueError:
                continue
            if not math.isfinite(number):
                return f"{option}: must be a finite number, got {value}"
    return None


def command_path(group: Any, args: Sequence[str]) -> list[str]:
    """The subcommand names at the start of `args` (`evaluate tracking` of `evaluate tracking -t grass`)."""
    path: list[str] = []
    node = group
    for arg in args:
        if arg == "--debug":
            continue
        commands = getattr(node, "commands", None)
        if not commands or arg not in commands:
            break
        path.append(arg)
        node = commands[arg]
    return path


def leaf_commands(group: Any, path: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], Any]]:
    """Every runnable command under `group` with its path of names."""
    out: list[tuple[tuple[str, ...], Any]] = []
    for name, cmd in getattr(group, "commands", {}).items():
        if hasattr(cmd, "commands"):
            out += leaf_commands(cmd, (*path, name))
        else:
            out.append(((*path, name), cmd))
    return out


def install_checks(group: Any) -> None:
    """Wrap each command's callback so that its values are checked first (once per built command tree)."""
    if getattr(group, "_checks_installed", False):
        return
    group._checks_installed = True
    _plain_help(group)
    for _, cmd in leaf_commands(group):
        if cmd.callback is not None and not getattr(cmd.callback, "_checked", False):
            cmd.callback = _checked(cmd.callback, {p.name: p for p in cmd.params if p.name})


def _plain_help(node: Any) -> None:
    """Help as plain text: rich markup would take the units in option help ("[s]", "[m/s]") for style tags and
    drop them."""
    if hasattr(node, "rich_markup_mode"):
        node.rich_markup_mode = None
    for child in getattr(node, "commands", {}).values():
        _plain_help(child)


def _checked(callback: Callable[..., Any], params: dict[str, Any]) -> Callable[..., Any]:
    def run(**kwargs: Any) -> Any:
        force = bool(kwargs.get("force", False))
        for name, value in kwargs.items():
            param = params.get(name)
            if param is not None:
                check_value(param, value, force)
        return callback(**kwargs)

    run._checked = True  # type: ignore[attr-defined]
    return run


def param_label(param: Any) -> str:
    opts = [o for o in getattr(param, "opts", []) if o.startswith("--")] or list(getattr(param, "opts", []))
    if getattr(param, "param_type_name", "") == "argument":
        return (param.metavar or param.name or "argument").upper()
    return opts[0] if opts else str(param.name)


def check_value(param: Any, value: Any, force: bool = False) -> None:
    """UserError naming the option where `value` is not a finite number or not a usable path (module doc)."""
    if isinstance(value, list | tuple):
        for item in value:
            check_value(param, item, force)
        return
    label = param_label(param)
    if isinstance(value, float) and not math.isfinite(value):
        fail(f"{label}: must be a finite number, got {value}")
    if isinstance(value, Path):
        kind = param.metavar or ""
        if kind == OUT_FILE:
            check_output_file(label, value, force)
        elif kind == OUT_DIR:
            check_output_dir(label, value)
        elif kind == RECORDING:
            check_recording(label, value)
        else:
            check_input(label, value, want_dir=kind == DIR)


def check_input(label: str, path: Path, want_dir: bool = False) -> None:
    if str(path) == "":
        fail(f"{label}: empty path; give a {'folder' if want_dir else 'file'}")
    if not path.exists():
        fail(f"{label} {path}: does not exist (no such {'folder' if want_dir else 'file'})")
    if want_dir and not path.is_dir():
        fail(f"{label} {path}: is a file, not a folder; give a folder")
    if not want_dir:
        if path.is_dir():
            fail(f"{label} {path}: is a folder, not a file; give a file")
        if not os.access(path, os.R_OK):
            fail(f"{label} {path}: not readable")


def check_output_file(label: str, path: Path, force: bool = False) -> None:
    if str(path) == "":
        fail(f"{label}: empty path; give a file to write")
    if path.is_dir():
        fail(f"{label} {path}: is a folder; give a file name to write (for example {path / 'out'}...)")
    _check_parent(label, path)
    if path.exists() and not force:
        fail(f"{label} {path}: exists; choose another path, or add --force to replace it")


def check_output_dir(label: str, path: Path) -> None:
    if str(path) == "":
        fail(f"{label}: empty path; give a folder to write into")
    if path.exists() and not path.is_dir():
        fail(f"{label} {path}: is a file; give a folder")
    if not path.exists():
        _check_parent(label, path)
    elif not os.access(path, os.W_OK):
        fail(f"{label} {path}: folder not writable")


def check_recording(label: str, path: Path) -> None:
    if str(path) == "":
        fail(f"{label}: empty path; give an .mcap file or a folder")
    if path.is_dir():
        if not os.access(path, os.W_OK):
            fail(f"{label} {path}: folder not writable")
        return
    _check_parent(label, path)


def _check_parent(label: str, path: Path) -> None:
    parent = path.absolute().parent
    if not parent.is_dir():
        fail(f"{label} {path}: folder {parent} does not exist; create it first")
    if not os.access(parent, os.W_OK):
        fail(f"{label} {path}: folder {parent} is not writable")


class AtomicOutput:
    """`with AtomicOutput(path) as tmp:` write `tmp`; on success it is renamed onto `path` (readers never see half
    a file), on failure it is removed (nothing half-written stays behind)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.tmp = self.path.with_name(f".{self.path.name}.part-{os.getpid()}{self.path.suffix}")

    def __enter__(self) -> Path:
        return self.tmp

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is None and self.tmp.exists():
            os.replace(self.tmp, self.path)
        else:
            self.tmp.unlink(missing_ok=True)


def write_text_atomic(path: Path, text: str) -> None:
    """Write `text` to `path` through a temporary file renamed when complete."""
    with AtomicOutput(path) as tmp:
        tmp.write_text(text)


def only_with(condition: bool, needs: str, given: dict[str, bool]) -> None:
    """UserError naming the options of `given` that were set although they apply only with `needs`."""
    named = [name for name, on in given.items() if on]
    if named and not condition:
        fail(f"{', '.join(named)}: only with {needs}")
