"""Checks a secrets directory before a launch: every error names the file and the field and says what to do.

What is checked: the directory and its files exist; the users dictionary is `user:password` lines readable by
its owner only; each identity's client config carries its own user and the dictionary's password; TLS
certificates match their keys and their CA; and the router's access control, evaluated the way Zenoh does
(per subject a deny wins, across subjects any allow wins, no subject: the default), lets every identity do
its job and lets no one but the planner put `cmd`, egress `base/cmd` and ingress `state`.
"""

from __future__ import annotations

import json
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh

from services.security.secure import (
    EXCLUSIVE_PUTS,
    MANIFEST_FILE,
    ROLES,
    ROUTER_FILE,
    SecretsError,
    role_keys,
)

Flow = str  # "ingress" (session -> router) or "egress" (router -> session)


@dataclass
class Secrets:
    """A checked secrets directory."""

    directory: Path
    robot: str
    users: dict[str, str]
    tls: bool

    def client_file(self, identity: str) -> Path:
        return self.directory / f"{identity}.json5"

    @property
    def router_file(self) -> Path:
        return self.directory / ROUTER_FILE


# ---- reading -------------------------------------------------------------------------------------------------
def load_json5(path: Path, what: str) -> dict[str, Any]:
    """A Zenoh json5 file, parsed by Zenoh itself (so its own schema errors come out), as plain JSON."""
    if not path.is_file():
        raise SecretsError(f"{what} {path} does not exist; make it with `gpmppi secure init {path.parent}`")
    try:
        config = zenoh.Config.from_file(str(path))
    except zenoh.ZError as exc:
        raise SecretsError(f"{path}: not a valid Zenoh config: {str(exc).split(' at /')[0]}") from None
    return json.loads(str(config))


def read_users(path: Path, field_name: str) -> dict[str, str]:
    """The usrpwd dictionary: `user:password` per line. `field_name` says where it was named from."""
    where = f"{path} (named by {field_name})"
    if not path.is_file():
        raise SecretsError(f"{where} does not exist; run `gpmppi secure init {path.parent}`")
    mode = stat.S_IMODE(path.stat().st_mode)
    if mode & 0o077:
        raise SecretsError(f"{where} is readable by others (mode {mode:o}); `chmod 600 {path}`")
    users: dict[str, str] = {}
    for n, raw in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        user, sep, password = line.partition(":")
        if not sep or not user or not password or ":" in password or " " in user:
            raise SecretsError(
                f"{where} line {n}: expected `user:password` (one colon, both non-empty), got "
                f"{line[:40]!r}; fix the line or re-run `gpmppi secure init`"
            )
        if user in users:
            raise SecretsError(f"{where} line {n}: user {user!r} appears twice; keep one line per user")
        users[user] = password
    if not users:
        raise SecretsError(f"{where} has no `user:password` lines; re-run `gpmppi secure init {path.parent}`")
    return users


def _get(config: dict[str, Any], dotted: str) -> Any:
    value: Any = config
    for part in dotted.split("."):
        value = value.get(part) if isinstance(value, dict) else None
    return value


# ---- the ACL, evaluated as Zenoh does -------------------------------------------------------------------------
def _includes(rule_key: str, key: str) -> bool:
    return zenoh.KeyExpr(rule_key).includes(zenoh.KeyExpr(key))


def acl_allows(acl: dict[str, Any], user: str, flow: Flow, message: str, key: str) -> bool:
    """Whether Zenoh's access control lets a session authenticated as `user` pass `message` on `key` in `flow`.
    Subjects are matched on usernames only (one that names interfaces, certificate names or protocols is taken
    to match: a check for what could get through)."""
    if not acl.get("enabled"):
        return True
    default = acl.get("default_permission", "deny") == "allow"
    rules = {r["id"]: r for r in acl.get("rules") or []}
    subjects = [s for s in acl.get("subjects") or [] if not s.get("usernames") or user in s["usernames"]]
    if not subjects:
        return default
    for subject in subjects:
        mine = [
            rules[rid]
            for p in acl.get("policies") or []
            if subject["id"] in p.get("subjects", [])
            for rid in p.get("rules", [])
            if rid in rules
        ]
        matching = [
            r
            for r in mine
            if message in r.get("messages", [])
            and flow in (r.get("flows") or ["ingress", "egress"])
            and any(_includes(k, key) for k in r.get("key_exprs", []))
        ]
        if any(r.get("permission") == "deny" for r in matching):
            continue
        if default or any(r.get("permission") == "allow" for r in matching):
            return True
    return False


def needs(identity: str, robot: str, ros2: dict[str, str] | None = None) -> list[tuple[Flow, str, str, str]]:
    """What the stack cannot run without: (flow, message, key, why) for one identity."""
    k = role_keys(identity, robot, ros2)
    out: list[tuple[Flow, str, str, str]] = []
    for key in k["puts"]:
        out += [
            ("ingress", "put", key, "publish"),
            ("egress", "declare_subscriber", key, "hear of the subscribers of what it publishes"),
        ]
    for key in k["subscribe"]:
        out.append(("ingress", "declare_subscriber", key, "subscribe"))
    for key in k["reads"]:
        out.append(("egress", "put", key, "receive"))
    for key in k["tokens"]:
        out.append(("ingress", "liveliness_token", key, "declare its liveliness token"))
    for key in k["watch"]:
        out += [
            ("ingress", "declare_liveliness_subscriber", key, "watch liveliness"),
            ("egress", "liveliness_token", key, "receive liveliness tokens"),
        ]
    return out


def check_acl(
    acl: dict[str, Any], robot: str, users: list[str], where: str, ros2: dict[str, str] | None = None
) -> None:
    """Raise SecretsError when an identity cannot do its job or someone else may put a key that moves the robot."""
    if not acl.get("enabled"):
        raise SecretsError(f"{where} access_control.enabled is not true: any session could drive the robot")
    if acl.get("default_permission") != "deny":
        raise SecretsError(
            f"{where} access_control.default_permission is {acl.get('default_permission')!r}; "
            'it must be "deny" (allow lets every key through unless denied)'
        )
    for identity in ROLES:
        if identity not in users:
            continue
        for flow, message, key, why in needs(identity, robot, ros2):
            if not acl_allows(acl, identity, flow, message, key):
                raise SecretsError(
                    f"{where} access_control.rules/policies lock {identity} out: it may not {why} on {key} "
                    f"({message}, flow {flow}); restore its allow rule (`gpmppi secure init` writes one) or the "
                    f"robot {'cannot be driven' if identity in ('planner', 'egress') else 'degrades'}"
                )
    for short, owner in EXCLUSIVE_PUTS.items():
        key = f"gpmppi/{robot}/{short}"
        for user in [*users, "(no username)"]:
            if user != owner and acl_allows(acl, user, "ingress", "put", key):
                raise SecretsError(
                    f"{where} access_control lets {user} put on {key}; only {owner} may "
                    "(an allow that matches every subject, or a broad key, opens it): narrow the rule"
                )


# ---- the directory -----------------------------------------------------------------------------------------
def check_secrets(directory: str | Path | None, robot: str, identities: list[str] | None = None) -> Secrets:
    """Check a secrets directory for a launch of `robot` whose sessions use `identities` (default: all)."""
    if directory is None:
        raise SecretsError("no secrets directory given; make one with `gpmppi secure init DIR`")
    path = Path(directory)
    if not path.is_dir():
        raise SecretsError(f"secrets directory {path} does not exist; make it with `gpmppi secure init {path}`")
    path = path.resolve()
    manifest_path = path / MANIFEST_FILE
    manifest: dict[str, Any] = {}
    if manifest_path.is_file():
        try:
            manifest = json.loads(manifest_path.read_text())
        except ValueError as exc:
            raise SecretsError(f"{manifest_path}: not JSON ({exc}); re-run `gpmppi secure init`") from None
        if manifest.get("robot") != robot:
            raise SecretsError(
                f"{manifest_path} robot is {manifest.get('robot')!r} but the launch drives {robot!r}; "
                f"run `gpmppi secure init {path} --robot {robot} --force`"
            )
    router_path = path / ROUTER_FILE
    router = load_json5(router_path, "router config")
    dictionary = _get(router, "transport.auth.usrpwd.dictionary_file")
    if not dictionary:
        raise SecretsError(
            f"{router_path} transport.auth.usrpwd.dictionary_file is not set: the router would "
            "accept sessions without credentials"
        )
    users = read_users(Path(dictionary), f"{router_path} transport.auth.usrpwd.dictionary_file")
    ros2 = manifest.get("ros2") or None
    check_acl(router.get("access_control") or {}, robot, list(users), str(router_path), ros2)
    tls = bool(_get(router, "transport.link.tls.listen_certificate"))
    if tls:
        _check_tls(router, router_path, "listen")
    for identity in identities or list(ROLES):
        client_path = path / f"{identity}.json5"
        client = load_json5(client_path, f"client config of identity {identity!r}")
        user = _get(client, "transport.auth.usrpwd.user")
        if user != identity:
            raise SecretsError(f"{client_path} transport.auth.usrpwd.user is {user!r}, expected {identity!r}")
        if users.get(identity) is None:
            raise SecretsError(f"{dictionary} has no line for {identity!r} (needed by {client_path})")
        if _get(client, "transport.auth.usrpwd.password") != users[identity]:
            raise SecretsError(
                f"{client_path} transport.auth.usrpwd.password does not match {identity}'s line in "
                f"{dictionary}; re-run `gpmppi secure init {path} --force` to rotate both"
            )
        if _get(client, "transport.link.tls.connect_certificate"):
            _check_tls(client, client_path, "connect")
    return Secrets(path, robot, users, tls)


def _check_tls(config: dict[str, Any], path: Path, side: str) -> None:
    from services.security.secure_tls import check_pair

    tls = _get(config, "transport.link.tls") or {}
    cert, key, ca = tls.get(f"{side}_certificate"), tls.get(f"{side}_private_key"), tls.get("root_ca_certificate")
    where = f"{path} transport.link.tls.{side}_certificate / {side}_private_key"
    if not cert or not key:
        raise SecretsError(f"{where}: both must be set (one is missing)")
    try:
        check_pair(Path(cert), Path(key), Path(ca) if ca else None, where)
    except ValueError as exc:
        raise SecretsError(str(exc)) from None


def check_launch_secrets(
    launch: Any, directory: str | Path, record: str | None, rerun: list[str] | None, foxglove: bool = False
) -> Secrets:
    """Check `directory` for a launch file (services.launch.launch_file.LaunchFile): the identities its sessions use are
    each enabled service's kind, the recorder and viewer when asked for (the Foxglove server joins as the viewer),
    and the launcher's own monitor."""
    kinds = [e.kind or e.name for e in launch.services if e.enabled]
    kinds += ["recorder"] * bool(record) + ["viewer"] * bool((rerun and rerun[0] != "off") or foxglove)
    unknown = sorted({k for k in kinds if k not in ROLES})
    if unknown:
        raise SecretsError(
            f"no identity for service kind {', '.join(unknown)} in the secrets; known: {', '.join(ROLES)}"
        )
    return check_secrets(directory, launch.robot, sorted({*kinds, "launcher"}))
