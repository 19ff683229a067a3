"""Zenoh authentication and access control for the stack: who may put and read which key.

`gpmppi secure init DIR` (tools/secure_cmd.py) calls `init_secrets`, which writes into DIR:

- `users.txt` (mode 600): the router's usrpwd dictionary, one `identity:password` line per identity;
- `<identity>.json5` (mode 600): a client config per identity (its user and password, TLS client files);
- `router.json5`: the router config: the dictionary, `access_control` deny by default with one policy per
  identity (built from `ROLES`), TLS listener files when made with TLS;
- `secure.json`: what was made (robot, identities, TLS) so a launch can check it matches;
- `tls/` (with TLS): a CA, a router (server) certificate and a client certificate per identity.

The ACL is seen from the router: `ingress` is what a session sends to the router, `egress` what the router sends
to it. Under deny-by-default a publication needs four allows (ingress put for the publisher, ingress
declare_subscriber for the subscriber, egress put to the subscriber, egress declare_subscriber to the publisher),
and across the subjects a session matches any allow wins, so every rule names one identity and the keys that
drive the robot (`cmd`, `base/cmd`, `state`) appear in exactly one identity's put rule.
`services/security/secure_check.py` re-checks a DIR (possibly edited by hand) before a launch.

The router's own in-process session is not subject to the ACL's ingress checks, so no service ever runs inside
the router process (services/router.py is a process of its own).
"""

from __future__ import annotations

import json
import os
import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import Any

USERS_FILE = "users.txt"
ROUTER_FILE = "router.json5"
MANIFEST_FILE = "secure.json"
TLS_DIR = "tls"


@dataclass(frozen=True)
class Role:
    """What one identity may do. Keys are relative to `gpmppi/{robot}/` (ROS 2 keys are added by options)."""

    description: str
    puts: tuple[str, ...] = ()
    reads: tuple[str, ...] = ()
    node: bool = True  # a gpmppi service: heartbeat on health/<id> and a liveliness token on alive/<id>
    watches_liveliness: bool = False  # subscribes to / queries the liveliness tokens alive/**


# the stack's processes and the people and tools around it; a service's identity is its kind
ROLES: dict[str, Role] = {
    "sim": Role("the simulated robot (plant)", puts=("odom/raw", "terrain/label"), reads=("base/cmd",)),
    "ingress": Role("state estimation ingress", puts=("state",), reads=("odom/raw",)),
    # terrain and planner also read their own last output: a standby resumes from it (services/runtime/role.py)
    "terrain": Role("terrain-weight estimator", puts=("terrain/weights",),
                    reads=("state", "base/cmd", "cmd", "terrain/weights")),
    "planner": Role("GP-MPPI planner", puts=("cmd", "plan", "task", "costmap"),
                    reads=("state", "terrain/weights", "task", "plan", "costmap")),
    "egress": Role("motor-command egress (owns safety)", puts=("base/cmd",), reads=("cmd", "estop")),
    # reads the task too: a goal keeps the scene (obstacles) of the task the planner plans for
    "nav": Role("ROS 2 paths, goals and costmaps into tasks and grids", puts=("task", "costmap"), reads=("task",)),
    "recorder": Role("MCAP recorder (reads everything)", reads=("**",)),
    "viewer": Role("rerun viewer (reads everything)", reads=("**",)),
    "launcher": Role(
        "the launcher's own monitor session (reads everything)", reads=("**",), node=False, watches_liveliness=True
    ),
    "operator": Role(
        "an operator's tool: sets the task, engages and releases the e-stop",
        puts=("task", "costmap", "estop"),
        reads=("health/**",),
        node=False,
        watches_liveliness=True,
    ),
    "monitor": Role(
        "low privilege: reads health and liveliness only", reads=("health/**",), node=False, watches_liveliness=True
    ),
}
ROS2_IDENTITY = "ros2"  # the robot's ROS 2 nodes (rmw_zenoh sessions), only with `secure init --ros2`
# the keys that move the robot: exactly one identity may put each
EXCLUSIVE_PUTS: dict[str, str] = {"cmd": "planner", "base/cmd": "egress", "state": "ingress"}


class SecretsError(ValueError):
    """A secrets directory that cannot be used: the message names the file, the field and what to do."""


# ---- the access-control section -----------------------------------------------------------------------------
def _abs(key: str, robot: str) -> str:
    return f"gpmppi/{robot}/{key}"


def role_keys(identity: str, robot: str, ros2: dict[str, str] | None = None) -> dict[str, list[str]]:
    """The concrete key expressions of one identity: puts, reads (what it may subscribe to and receive),
    tokens (its liveliness token) and watch (liveliness it may subscribe to and query)."""
    role = ROLES[identity]
    puts = [_abs(k, robot) for k in role.puts]
    reads = [_abs(k, robot) for k in role.reads]
    if role.node:
        # `$*` lets a renamed instance (planner_gpu) keep its heartbeat; no identity is a prefix of another
        puts.append(f"gpmppi/{robot}/health/{identity}$*")
    ros2 = ros2 or {}
    if identity == "egress" and ros2.get("cmd"):
        puts.append(ros2["cmd"])
    if identity == "ingress" and ros2.get("odom"):
        reads.append(ros2["odom"])
    if identity == "nav":  # Nav2's path, goal and local costmap
        reads += [ros2[k] for k in ("path", "goal", "costmap") if ros2.get(k)]
    if identity == "planner" and ros2.get("plan"):  # the plan as nav_msgs/Path
        puts.append(ros2["plan"])
    if "**" in role.reads:
        # readers of everything subscribe with `gpmppi/**` (the recorder's and viewer's default); what reaches
        # them is still only this robot's keys (the egress put rule)
        subscribe = ["gpmppi/**"]
    else:
        subscribe = list(reads)
    return {
        "puts": puts,
        "reads": reads,
        "subscribe": subscribe,
        "tokens": [f"gpmppi/{robot}/alive/{identity}$*"] if role.node else [],
        # a service may ask whether another process of itself is alive (a spare taking over waits until none is)
        "watch": [f"gpmppi/{robot}/alive/**"] if role.watches_liveliness
        else [f"gpmppi/{robot}/alive/{identity}$*"] if role.node else [],
    }


def _hear(puts: list[str]) -> list[str]:
    # gpmppi/** covers every gpmppi subscription (the recorder's is that wide); a ROS 2 key is outside it
    return ["gpmppi/**", *(p for p in puts if not p.startswith("gpmppi/"))] if puts else []


def acl_section(robot: str, identities: list[str] | None = None, ros2: dict[str, str] | None = None) -> dict:
    """The router's `access_control`: deny by default; per identity, its rules under one subject (its username).

    A publisher is told about subscriptions anywhere under `gpmppi/**` (the recorder subscribes to all of it,
    and a publisher that hears of no subscriber sends nothing): hearing of a subscription grants no data."""
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for identity in identities or list(ROLES):
        k = role_keys(identity, robot, ros2)
        wants = [
            ("put", ["put"], "ingress", k["puts"]),
            ("hear-subscribers", ["declare_subscriber"], "egress", _hear(k["puts"])),
            ("subscribe", ["declare_subscriber"], "ingress", k["subscribe"]),
            ("receive", ["put"], "egress", k["reads"]),
            ("token", ["liveliness_token"], "ingress", k["tokens"]),
            ("watch", ["declare_liveliness_subscriber", "liveliness_query"], "ingress", k["watch"]),
            ("watch-tokens", ["liveliness_token", "reply"], "egress", k["watch"]),
        ]
        mine = [
            {
                "id": f"{identity}:{name}",
                "messages": messages,
                "flows": [flow],
                "permission": "allow",
                "key_exprs": keys,
            }
            for name, messages, flow, keys in wants
            if keys
        ]
        rules += mine
        subjects.append({"id": identity, "usernames": [identity]})
        policies.append({"id": identity, "rules": [r["id"] for r in mine], "subjects": [identity]})
    if ros2:
        rules += ros2_rules(robot, ros2)
        subjects.append({"id": ROS2_IDENTITY, "usernames": [ROS2_IDENTITY]})
        policies.append(
            {"id": ROS2_IDENTITY, "rules": [r["id"] for r in ros2_rules(robot, ros2)], "subjects": [ROS2_IDENTITY]}
        )
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def ros2_rules(robot: str, ros2: dict[str, str]) -> list[dict[str, Any]]:
    """The ROS 2 nodes sharing the robot's rmw_zenoh router (one identity for all of them): anything outside
    gpmppi, except putting on the base's command topic (egress's) or on gpmppi keys. Within one subject a deny
    wins over an allow, which is what keeps the broad allow from opening those keys."""
    everything = [
        "put",
        "delete",
        "declare_subscriber",
        "query",
        "reply",
        "declare_queryable",
        "liveliness_token",
        "declare_liveliness_subscriber",
        "liveliness_query",
    ]
    keys = ["**", "@ros2_lv/**"]  # `**` does not reach `@`-chunks (rmw_zenoh's graph tokens)
    denied = [f"gpmppi/{robot}/**", *([ros2["cmd"]] if ros2.get("cmd") else [])]
    return [
        {
            "id": "ros2:ros-graph",
            "messages": everything,
            "flows": ["ingress", "egress"],
            "permission": "allow",
            "key_exprs": keys,
        },
        {
            "id": "ros2:not-the-base-command",
            "messages": ["put", "delete"],
            "flows": ["ingress"],
            "permission": "deny",
            "key_exprs": denied,
        },
    ]


# ---- files --------------------------------------------------------------------------------------------------
def _write_private(path: Path, text: str) -> None:
    """Write a file only its owner can read (created 600, not chmod-ed after the fact)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.chmod(path, 0o600)  # an existing file keeps its mode through O_CREAT


def _json5(header: str, body: dict) -> str:
    # JSON is json5; the header says what the file is for whoever opens it
    return "".join(f"// {line}\n" for line in header.splitlines()) + json.dumps(body, indent=2) + "\n"


def client_config(identity: str, password: str, endpoint: str, tls: dict[str, str] | None) -> dict:
    config: dict[str, Any] = {
        "mode": "client",
        "connect": {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"auth": {"usrpwd": {"user": identity, "password": password}}},
    }
    if tls:
        config["transport"]["link"] = {"tls": tls}
    return config


def router_config(
    directory: Path, robot: str, listen: list[str], tls: dict[str, Any] | None, ros2: dict[str, str] | None = None
) -> dict:
    config: dict[str, Any] = {
        "mode": "router",
        "listen": {"endpoints": listen},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"auth": {"usrpwd": {"dictionary_file": str(directory / USERS_FILE)}}},
        "access_control": acl_section(robot, ros2=ros2),
    }
    if tls:
        config["transport"]["link"] = {"tls": tls}
    return config


def init_secrets(
    directory: str | Path,
    robot: str = "jackal",
    tls: bool = False,
    endpoint: str = "tcp/127.0.0.1:7447",
    tls_endpoint: str = "tls/127.0.0.1:7448",
    hosts: list[str] | None = None,
    ros2: dict[str, str] | None = None,
    force: bool = False,
) -> list[Path]:
    """Write a new secrets directory (see the module docstring); the written paths. Fresh passwords (and keys)
    every call: re-running it rotates every identity at once."""
    directory = Path(directory).resolve()
    if directory.exists() and any(directory.iterdir()) and not force:
        raise SecretsError(f"{directory} is not empty; pass --force to replace its secrets (rotates them all)")
    directory.mkdir(parents=True, exist_ok=True)
    os.chmod(directory, 0o700)
    written: list[Path] = []
    identities = [*ROLES, *([ROS2_IDENTITY] if ros2 else [])]
    passwords = {identity: secrets.token_urlsafe(24) for identity in identities}  # [A-Za-z0-9_-]: never a ':'
    users = directory / USERS_FILE
    _write_private(users, "".join(f"{i}:{p}\n" for i, p in passwords.items()))
    written.append(users)
    router_tls: dict[str, Any] | None = None
    client_tls: dict[str, dict[str, str]] = {}
    listen = [endpoint]
    if tls:
        from services.security.secure_tls import make_tls

        files = make_tls(directory / TLS_DIR, identities, hosts or ["localhost", "127.0.0.1"])
        written += [p for pair in files.values() for p in pair]
        ca = str(files["ca"][0])
        router_tls = {
            "root_ca_certificate": ca,
            "listen_certificate": str(files["router"][0]),
            "listen_private_key": str(files["router"][1]),
            "enable_mtls": True,
        }
        for identity in identities:
            client_tls[identity] = {
                "root_ca_certificate": ca,
                "connect_certificate": str(files[identity][0]),
                "connect_private_key": str(files[identity][1]),
                "enable_mtls": True,
            }  # without it the client sends no certificate
        listen.append(tls_endpoint)
    for identity, password in passwords.items():
        path = directory / f"{identity}.json5"
        what = ROLES[identity].description if identity in ROLES else "the robot's ROS 2 nodes (rmw_zenoh)"
        header = (
            f"gpmppi identity '{identity}': {what}.\n"
            "Secret (holds a password): readable by the service's user only. Made by `gpmppi secure init`."
        )
        _write_private(path, _json5(header, client_config(identity, password, endpoint, client_tls.get(identity))))
        written.append(path)
    router = directory / ROUTER_FILE
    header = (
        "gpmppi router: usrpwd against users.txt, access control deny by default (gpmppi secure init).\n"
        "The launcher's router (`router_config_file`) or zenohd/rmw_zenohd (`-c`) loads it."
    )
    _write_private(router, _json5(header, router_config(directory, robot, listen, router_tls, ros2)))
    written.append(router)
    manifest = directory / MANIFEST_FILE
    manifest.write_text(
        json.dumps(
            {
                "robot": robot,
                "identities": identities,
                "tls": tls,
                "endpoint": endpoint,
                "tls_endpoint": tls_endpoint if tls else None,
                "ros2": ros2 or {},
            },
            indent=2,
        )
        + "\n"
    )
    written.append(manifest)
    return written
