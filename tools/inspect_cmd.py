"""`gpmppi inspect LOG.mcap [--json] [--recover OUT.mcap]`: what is in a recording
(see services.recording.mcap_inspect)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from services.recording.mcap_inspect import InspectError, inspect_recording, recover, report_lines
from tools.cli_checks import OUT_FILE


def register(app: typer.Typer) -> None:
    """Add `gpmppi inspect`."""

    @app.command("inspect")
    def inspect_cmd(
        path: Annotated[Path, typer.Argument(metavar="LOG.mcap", help="recording (its _001, _002 ... parts too)")],
        as_json: Annotated[bool, typer.Option("--json", help="print one JSON object instead of text")] = False,
        recover_to: Annotated[
            Path | None,
            typer.Option("--recover", metavar=OUT_FILE, help="write every readable message to a complete .mcap file"),
        ] = None,
    ) -> None:
        """Channels (topic, schema, count, rate, first/last time, largest gap), duration, metadata, attachments,
        rotated parts, and truncation (a killed recorder, or one still writing). Exit 2: nothing readable."""
        try:
            if recover_to is not None:
                written, report = recover(path, recover_to)
            else:
                report = inspect_recording(path)
        except InspectError as exc:
            typer.echo(f"gpmppi inspect: {exc}", err=True)
            raise typer.Exit(code=2) from None
        except OSError as exc:
            typer.echo(f"gpmppi inspect: {exc}", err=True)
            raise typer.Exit(code=2) from None
        if as_json:
            data = report.to_json()
            if recover_to is not None:
                data["recovered_to"] = str(recover_to)
                data["recovered_written"] = written
            typer.echo(json.dumps(data))
        else:
            for line in report_lines(report):
                typer.echo(line)
            if recover_to is not None:
                typer.echo(f"recovered:   {written} messages written to {recover_to} (complete, with a summary)")
        if any(f.error for f in report.files):
            raise typer.Exit(code=1)  # partial results: part of the recording could not be read
