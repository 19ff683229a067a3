"""`gpmppi replay --replace`: which recorded keys a replaced service owns, its settings (recorded, with the user's
`--config` / `--set` on top), and the comparison of its live commands with the recorded ones."""

from __future__ import annotations

import difflib
import tempfile
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from pydantic import BaseModel, ValidationError

from services.recording.player_log import RunInfo

# what each kind of service publishes (relative to gpmppi/{robot}/), besides its heartbeat health/<name>
OUTPUTS: dict[str, tuple[str, ...]] = {
    "planner": ("cmd", "plan", "task", "costmap"),
    "egress": ("base/cmd",),
    "ingress": ("state",),
    "terrain": ("terrain/weights",),
    "sim": ("odom/raw", "terrain/label"),
    "recorder": (),
    "viewer": (),
}


class ReplaceError(ValueError):
    """A --replace / --set / --config that cannot be honoured; the message says what and how to fix it."""


@dataclass
class LiveService:
    name: str
    kind: str
    config: dict[str, Any]
    from_metadata: bool


def _model_of(annotation: Any) -> type[BaseModel] | None:
    """The pydantic model an annotation holds (also inside Optional), else None."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in typing.get_args(annotation):
        if isinstance(arg, type) and issubclass(arg, BaseModel):
            return arg
    return None


def resolve_path(cls: type[BaseModel], parts: list[str], what: str) -> list[str]:
    """The full settings path of a dotted `--set` path. A first name that is not a field of the service's settings
    but of exactly one of its groups is looked up there (`planner.temperature` -> `planner.planner.temperature`)."""
    path: list[str] = []
    model: type[BaseModel] | None = cls
    for i, part in enumerate(parts):
        if model is None:
            raise ReplaceError(f"{what}: {'.'.join(path)} is a single value, it has no field {part!r}")
        fields = model.model_fields
        if part not in fields and i == 0:
            groups = [n for n, f in fields.items() if (m := _model_of(f.annotation)) and part in m.model_fields]
            if len(groups) == 1:
                path.append(groups[0])
                model = _model_of(fields[groups[0]].annotation)
                assert model is not None
                fields = model.model_fields
        if part not in fields:
            where = ".".join(path) or "the service's settings"
            # near misses, also inside the settings' groups (planner.temprature -> planner.planner.temperature)
            names = {n: n for n in fields}
            for n, f in fields.items():
                if (m := _model_of(f.annotation)) is not None:
                    names.update({sub: f"{n}.{sub}" for sub in m.model_fields if sub not in names})
            close = difflib.get_close_matches(part, list(names), n=3, cutoff=0.7)
            hint = f"; did you mean {' or '.join(repr(names[c]) for c in close)}?" if close else ""
            raise ReplaceError(f"{what}: unknown field {part!r} in {where}{hint}; valid fields: "
                               f"{', '.join(sorted(fields))}")
        path.append(part)
        if typing.get_origin(fields[part].annotation) is dict:  # a mapping (the planner's critics): its own validator
            return path + parts[i + 1:]  # checks the keys when the service starts
        model = _model_of(fields[part].annotation)
    return path


def _set_in(config: dict[str, Any], path: list[str], value: Any) -> None:
    node = config
    for part in path[:-1]:
        child = node.get(part)
        if not isinstance(child, dict):
            child = {}
            node[part] = child
        node = child
    node[path[-1]] = value


def _merge(base: dict[str, Any], top: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in top.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def parse_replace(text: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise ReplaceError("--replace needs service names, e.g. --replace planner or --replace planner,terrain")
    if len(set(names)) != len(names):
        raise ReplaceError(f"--replace {text!r} names a service twice")
    return names


def live_services(
    names: list[str], info: RunInfo, logged_services: set[str], robot: str, warn: Any
) -> list[LiveService]:
    """The settings each replaced service starts from: the recorded ones, or (a log without metadata) the
    service's defaults, with a warning."""
    from services.run import SERVICES

    out: list[LiveService] = []
    for name in names:
        if name in info.settings:
            kind, settings = info.settings[name]
            out.append(LiveService(name, kind, dict(settings), True))
            continue
        if info.settings:
            raise ReplaceError(
                f"--replace {name}: the recording has no service named {name!r}; it recorded the settings of: "
                f"{', '.join(sorted(info.settings))}"
            )
        if name not in logged_services:
            found = ", ".join(sorted(logged_services)) or "none"
            raise ReplaceError(f"--replace {name}: no service {name!r} in the recording (no health/{name} "
                               f"heartbeat); services found: {found}")
        if name not in SERVICES or name == "router":
            raise ReplaceError(f"--replace {name}: without recorded settings the kind is the name, and {name!r} is "
                               f"not a service kind ({', '.join(k for k in SERVICES if k != 'router')})")
        warn(f"warning: the recording has no settings for {name} (no gpmppi.settings.{name} metadata): starting it "
             f"with its defaults and robot {robot!r}; pass --config {name}=FILE.yaml to run what actually ran")
        out.append(LiveService(name, name, {"robot": robot}, False))
    for live in out:
        if live.kind == "router" or live.kind not in OUTPUTS:
            raise ReplaceError(f"--replace {live.name}: a {live.kind} cannot be replaced "
                               f"(replaceable kinds: {', '.join(OUTPUTS)})")
    return out


def apply_overrides(services: list[LiveService], configs: list[str], sets: list[str]) -> None:
    """--config NAME=FILE.yaml (merged onto the settings), then --set NAME.PATH=VALUE (VALUE read as YAML)."""
    from services.run import settings_class

    by_name = {s.name: s for s in services}

    def target(name: str, option: str) -> LiveService:
        if name not in by_name:
            raise ReplaceError(f"{option} names service {name!r}, which is not replaced; replaced: "
                               f"{', '.join(by_name) or 'none (use --replace)'}")
        return by_name[name]

    for item in configs:
        name, sep, file = item.partition("=")
        if not sep or not file:
            raise ReplaceError(f"--config {item!r}: expected SERVICE=FILE.yaml, e.g. --config planner=planner.yaml")
        live = target(name, f"--config {item}")
        path = Path(file)
        if not path.is_file():
            raise ReplaceError(f"--config {item}: file {path} does not exist")
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise ReplaceError(f"--config {item}: {path} is not valid YAML: {exc}") from None
        if not isinstance(data, dict):
            raise ReplaceError(f"--config {item}: {path} must hold a mapping of settings, not {type(data).__name__}")
        live.config = _merge(live.config, data)
    for item in sets:
        lhs, sep, raw = item.partition("=")
        name, dot, rest = lhs.partition(".")
        if not sep or not dot or not rest:
            raise ReplaceError(f"--set {item!r}: expected SERVICE.FIELD=VALUE, e.g. --set planner.temperature=0.5")
        live = target(name, f"--set {item}")
        path = resolve_path(settings_class(live.kind), rest.split("."), f"--set {item}")
        try:
            value = yaml.safe_load(raw) if raw.strip() else raw
        except yaml.YAMLError:
            value = raw
        _set_in(live.config, path, value)


def finalize(
    services: list[LiveService], info: RunInfo, robot: str, endpoint: str, tmp: Path, profile: Path | None = None
) -> None:
    """Point each service at the replay's router and robot, give the planner and terrain services `profile` (a
    robot profile; None: the planner the attached model), validate."""
    from gpmppi.gp.model_file import GPModel
    from services.run import settings_class

    if profile is not None:
        GPModel.load(profile)  # ModelFileError (one line) before any service starts

    models = {name.split("/", 1)[1]: data for name, data in info.attachments.items() if name.startswith("model/")}
    learned = {name.split("/", 1)[1]: data for name, data in info.attachments.items() if name.startswith("learned/")}
    if learned:  # the profiles learned during the run: the replayed ModelUpdates find them by their sha256
        (tmp / "learned").mkdir(exist_ok=True)
        for name, data in learned.items():
            (tmp / "learned" / Path(name).name).write_bytes(data)
    for live in services:
        c = live.config
        c.update(service=live.name, robot=robot, zenoh={"mode": "client", "connect": [endpoint]})
        if profile is not None and live.kind in ("planner", "terrain"):
            c["model_file"] = str(Path(profile).resolve())
        elif live.kind == "planner":
            if learned:
                c["learned_dir"] = str(tmp / "learned")
            recorded = c.get("model_file")
            name = Path(recorded).name if recorded else None
            data = models.get(name) if name else (next(iter(models.values())) if len(models) == 1 else None)
            if data is not None:
                path = tmp / (name or "model.npz")
                path.write_bytes(data)
                c["model_file"] = str(path)
            elif recorded and not Path(recorded).is_file():
                raise ReplaceError(
                    f"--replace {live.name}: the recording ran with model_file {recorded}, which is neither attached "
                    f"to the log nor on this machine; pass --set {live.name}.model_file=PATH"
                )
        try:
            settings_class(live.kind).model_validate(c)
        except ValidationError as exc:
            lines = [f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors()]
            raise ReplaceError(f"settings of {live.name} ({live.kind}) do not validate: {'; '.join(lines)}; fix them "
                               f"with --set {live.name}.FIELD=VALUE or --config {live.name}=FILE.yaml") from None


def temp_dir() -> Path:
    return Path(tempfile.mkdtemp(prefix="gpmppi-replay-"))


def compare(
    live: list[tuple[int, float, float]], recorded: dict[int, tuple[float, float]], stamp_map: dict[int, int] | None
) -> dict[str, float | int]:
    """Live commands matched with the recorded ones by the state stamp they answer (a command carries its state's
    stamp): count, RMS and max of the v_ref and omega_ref differences. `stamp_map` maps replayed stamps back to
    recorded ones (None: stamps were kept)."""
    dv: list[float] = []
    dw: list[float] = []
    for stamp, v, w in live:
        original = stamp if stamp_map is None else stamp_map.get(stamp)
        if original is None or original not in recorded:
            continue
        rv, rw = recorded[original]
        dv.append(v - rv)
        dw.append(w - rw)
    if not dv:
        return {"compared": 0, "exact": 0, "v_rmse": float("nan"), "omega_rmse": float("nan"), "v_max": float("nan"),
                "omega_max": float("nan")}
    a, b = np.asarray(dv), np.asarray(dw)
    return {
        "compared": len(dv),
        # bit for bit the same (a seeded planner given the same states in the same order reproduces exactly)
        "exact": int(np.sum((np.abs(a) < 1e-12) & (np.abs(b) < 1e-12))),
        "v_rmse": float(np.sqrt(np.mean(a * a))),
        "omega_rmse": float(np.sqrt(np.mean(b * b))),
        "v_max": float(np.abs(a).max()),
        "omega_max": float(np.abs(b).max()),
    }
