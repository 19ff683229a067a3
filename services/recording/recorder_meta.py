"""What the recorder writes about a run besides its messages, so a log can be re-planned years later with
exactly what ran.

Metadata records (MCAP metadata, string -> string):
- `gpmppi.run`: version, commit (git revision of the source tree, "" if not a git checkout), host, robot,
  started_ns (recorder start, Unix ns), launch_file (path, or "").
- `gpmppi.settings.<service name>`: kind, settings (JSON of that service's resolved settings: its YAML
  file with environment overrides, as the service itself loads it; secrets are masked), and error (only
  when the settings could not be resolved).

Attachments: the launch file as `launch.yaml` (application/yaml), and each planner's GP model file as
`model/<file name>` (the shipped model when the planner's `model_file` is unset). Each profile a `ModelUpdate`
announces (a ground learned during the run) as `learned/<sha256>.npz`, read when the update is recorded and checked
against its sha256: the update's message on `gpmppi/{robot}/model` says when and which version; replay finds the
file by the hash (tools/replay_live.py).
"""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from pydantic import BaseModel, ConfigDict, Field

import gpmppi

REPO_ROOT = Path(__file__).resolve().parents[2]
RUN_METADATA = "gpmppi.run"
SETTINGS_METADATA_PREFIX = "gpmppi.settings."
LAUNCH_ATTACHMENT = "launch.yaml"
MODEL_ATTACHMENT_PREFIX = "model/"
LEARNED_ATTACHMENT_PREFIX = "learned/"
MODEL_UPDATE_SUFFIX = "/model"  # the key of ModelUpdate messages, gpmppi/{robot}/model
_SECRET = re.compile(r"pass(word)?|secret|token|private|credential", re.IGNORECASE)


@dataclass
class RunRecord:
    metadata: list[tuple[str, dict[str, str]]] = field(default_factory=list)
    attachments: list[tuple[str, bytes, str]] = field(default_factory=list)  # (name, data, media type)
    warnings: list[str] = field(default_factory=list)


def learned_attachment(payload: bytes) -> tuple[str, bytes, str] | str:
    """(name, data, media type) of the profile a ModelUpdate payload announces, or the warning why it is not
    attached (the file is gone, or its bytes are not the announced ones)."""
    import hashlib

    from schemas import DecodeError, ModelUpdate, decode

    try:
        update = decode(ModelUpdate, payload)
    except DecodeError as exc:
        return f"model update not attached: {exc}"
    try:
        data = Path(update.path).read_bytes()
    except OSError as exc:
        return f"learned profile {update.path} (version {update.version}) not attached: {exc.strerror or exc}"
    if hashlib.sha256(data).hexdigest() != update.sha256:
        return (f"learned profile {update.path} (version {update.version}) not attached: its bytes are no longer the "
                "announced ones (replaced since)")
    return f"{LEARNED_ATTACHMENT_PREFIX}{update.sha256}.npz", data, "application/octet-stream"


def git_commit(root: Path = REPO_ROOT) -> str:
    """The source tree's git revision (with "-dirty" when it has local changes), or "" when unknown."""
    try:
        rev = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True, text=True, timeout=5, check=True,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""
    return f"{rev}-dirty" if rev and dirty else rev


def mask_secrets(value: Any) -> Any:
    """The settings with the value of every secret-looking field (password, token, private key...) masked."""
    if isinstance(value, dict):
        return {
            k: "***" if _SECRET.search(str(k)) and v not in (None, "") else mask_secrets(v) for k, v in value.items()
        }
    if isinstance(value, list):
        return [mask_secrets(v) for v in value]
    return value


class ServiceConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    kind: str = Field(description="service kind (sim, ingress, planner, ...)")
    config: str = Field(description="path of the YAML settings file the service was started with")


class RecorderSettings(Protocol):
    """What the run record reads from the recorder's settings (`services.recorder.Settings`)."""

    robot: str
    launch_file: str | None
    service_configs: dict[str, ServiceConfig]


def resolve_run_record(settings: RecorderSettings, started_ns: int) -> RunRecord:
    """The run's metadata and attachments; never raises (what cannot be resolved is a warning)."""
    record = RunRecord()
    try:
        _resolve(settings, started_ns, record)
    except Exception as exc:  # noqa: BLE001 - metadata must never stop a recording
        record.warnings.append(f"run metadata incomplete: {type(exc).__name__}: {exc}")
    return record


def _resolve(settings: RecorderSettings, started_ns: int, record: RunRecord) -> None:
    launch = str(Path(settings.launch_file).resolve()) if settings.launch_file else ""
    record.metadata.append(
        (
            RUN_METADATA,
            {
                "version": gpmppi.__version__,
                "commit": git_commit(),
                "host": socket.gethostname(),
                "robot": settings.robot,
                "started_ns": str(started_ns),
                "launch_file": launch,
            },
        )
    )
    if launch:
        try:
            record.attachments.append((LAUNCH_ATTACHMENT, Path(launch).read_bytes(), "application/yaml"))
        except OSError as exc:
            record.warnings.append(f"launch file {launch} not attached: {exc}")
    configs = {name: {"kind": c.kind, "config": c.config} for name, c in settings.service_configs.items()}
    resolved = _settings_in_subprocess(configs) if configs else {"metadata": [], "models": [], "warnings": []}
    record.metadata += [(name, dict(entry)) for name, entry in resolved["metadata"]]
    record.warnings += resolved["warnings"]
    for path in dict.fromkeys(Path(p).resolve() for p in resolved["models"]):  # each distinct file once
        try:
            data = path.read_bytes()
            record.attachments.append((MODEL_ATTACHMENT_PREFIX + path.name, data, "application/octet-stream"))
        except OSError as exc:
            record.warnings.append(f"GP model {path} not attached: {exc}")


def _settings_in_subprocess(configs: dict[str, dict[str, str]]) -> dict[str, Any]:
    """`resolve_settings` in a child process: loading a service's settings imports its module (the planner's
    pulls in numba), which the recorder itself need not carry (memory, start-up, shutdown)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO_ROOT), os.environ.get("PYTHONPATH", "")])}
    try:
        out = subprocess.run(
            [sys.executable, "-m", "services.recording.recorder_meta"], input=json.dumps(configs), capture_output=True,
            text=True, timeout=300, env=env, check=True,
        )
        return json.loads(out.stdout.strip().splitlines()[-1])
    except (OSError, subprocess.SubprocessError, ValueError, IndexError) as exc:
        detail = getattr(exc, "stderr", "") or ""
        return {"metadata": [], "models": [], "warnings": [f"service settings not recorded: {exc} {detail[-500:]}"]}


def resolve_settings(configs: dict[str, dict[str, str]]) -> dict[str, Any]:
    """{"metadata": [(gpmppi.settings.<name>, entry)], "models": [GP model paths], "warnings": [...]} for
    service name -> {"kind", "config"}; one bad entry does not cost the others."""
    from services.run import settings_class

    metadata: list[tuple[str, dict[str, str]]] = []
    models: list[str] = []
    warnings: list[str] = []
    for name, service in configs.items():
        kind = service["kind"]
        entry = {"kind": kind, "settings": ""}
        try:
            resolved = settings_class(kind).load(service["config"])
            entry["settings"] = json.dumps(mask_secrets(resolved.model_dump(mode="json")), sort_keys=True)
            if kind in ("planner", "terrain"):  # the robot profile they run with (attached once per file)
                models.append(str(_model_path(getattr(resolved, "model_file", None))))
        except Exception as exc:  # noqa: BLE001 - one bad entry must not cost the others
            entry["error"] = f"{type(exc).__name__}: {exc}"[:2000]
            warnings.append(f"settings of {name} ({kind}) not recorded: {entry['error']}")
        metadata.append((SETTINGS_METADATA_PREFIX + name, entry))
    return {"metadata": metadata, "models": models, "warnings": warnings}


def _model_path(model_file: str | None) -> Path:
    if model_file:
        return Path(model_file)
    from gpmppi.gp.model_file import DEFAULT_MODEL_PATH

    return Path(DEFAULT_MODEL_PATH)


if __name__ == "__main__":  # the child of _settings_in_subprocess: configs as JSON on stdin, one JSON line out
    print(json.dumps(resolve_settings(json.loads(sys.stdin.read()))))
