"""Zenoh authentication and access control (`gpmppi secure init`, `gpmppi launch --secrets`), on loopback: a real
router process with the generated router.json5, and sessions that join as the generated identities. Who may not
connect, what each identity receives, what it may put, the checks a launch runs on a secrets folder, TLS/mTLS,
and one secured whole-stack run."""

from __future__ import annotations

import io
import json
import os
import shutil
import stat
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh
from zenoh_helpers import REPO, ServiceProcess, endpoint, free_port, settings, wait_for, without_spares

from schemas import BaseCommand, Command, Heartbeat, decode, encode
from services.launch.launch_file import LaunchFile
from services.launch.launcher import build, main, run_launch
from services.runtime.node_settings import ZenohSettings
from services.security.secure import ROLES, SecretsError, init_secrets
from services.security.secure_check import acl_allows, check_secrets
from services.security.secure_tls import make_tls

ROBOT = "r1"
P = f"gpmppi/{ROBOT}"


def _router_process(secrets: Path, listen: list[str], tmp_path: Path) -> ServiceProcess:
    from services.launch.processes import wait_for_endpoint

    cfg = {"service": "router", "listen": listen, "router_config_file": str(secrets / "router.json5")}
    proc = ServiceProcess("router", cfg, tmp_path)
    try:
        # Every listener, the TLS one too: a client that connects over TLS before the router has bound that port
        # fails, which the tcp listener's readiness alone does not rule out under load.
        for listener in listen:
            wait_for_endpoint(listener, timeout_s=20.0)
    except TimeoutError:
        proc.stop()
        raise AssertionError(proc.log()[-2000:]) from None
    return proc


def _config(secrets: Path, identity: str, port: int, **changes: object) -> zenoh.Config:
    """The identity's client config as a service loads it (ZenohSettings.config_file), plus test changes."""
    config = ZenohSettings(connect=[endpoint(port)], config_file=str(secrets / f"{identity}.json5")).to_config()
    for path, value in changes.items():
        config.insert_json5(path.replace(".", "/"), json.dumps(value))
    return config


@pytest.fixture(scope="module")
def secured(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, int]]:
    """One secrets folder and one router process for the module's loopback tests: (secrets dir, port)."""
    tmp = tmp_path_factory.mktemp("secured")
    secrets = tmp / "secrets"
    init_secrets(secrets, robot=ROBOT)
    port = free_port()
    router = _router_process(secrets, [endpoint(port)], tmp)
    try:
        yield secrets, port
    finally:
        router.stop()


class Sessions:
    """Sessions by identity, each closed at the end."""

    def __init__(self, secrets: Path, port: int) -> None:
        self.secrets, self.port = secrets, port
        self.open: list[zenoh.Session] = []

    def __call__(self, identity: str) -> zenoh.Session:
        session = zenoh.open(_config(self.secrets, identity, self.port))
        self.open.append(session)
        return session

    def close(self) -> None:
        for s in self.open:
            s.close()


@pytest.fixture
def sessions(secured: tuple[Path, int]) -> Iterator[Sessions]:
    s = Sessions(*secured)
    try:
        yield s
    finally:
        s.close()


class Inbox:
    def __init__(self, session: zenoh.Session, key: str) -> None:
        self.got: list[tuple[str, bytes]] = []
        # remote only: a session's own puts reach its own subscribers without the router (no ACL on that path)
        self.sub = session.declare_subscriber(
            key,
            lambda s: self.got.append((str(s.key_expr), s.payload.to_bytes())),
            allowed_origin=zenoh.Locality.REMOTE,
        )

    def keys(self) -> set[str]:
        return {k for k, _ in list(self.got)}

    def payloads(self) -> list[bytes]:
        return [p for _, p in list(self.got)]


def _cmd(v: float) -> bytes:
    msg = Command(v_ref=v, omega_ref=0.0)
    msg.header.stamp_ns = time.time_ns()
    return encode(msg)


def _base(v: float) -> bytes:
    msg = BaseCommand(v=v, omega=0.0)
    msg.header.stamp_ns = time.time_ns()
    return encode(msg)


# ---- what init writes -----------------------------------------------------------------------------------
def test_init_writes_private_files_one_identity_each_and_passes_its_own_check(tmp_path: Path) -> None:
    secrets = tmp_path / "s"
    init_secrets(secrets, robot=ROBOT)
    users = dict(line.split(":", 1) for line in (secrets / "users.txt").read_text().splitlines())
    assert set(users) == set(ROLES) and "monitor" in users and len(set(users.values())) == len(users)
    for path in [secrets / "users.txt", *(secrets / f"{i}.json5" for i in ROLES)]:
        assert stat.S_IMODE(path.stat().st_mode) == 0o600, path
    found = check_secrets(secrets, ROBOT)
    assert found.users == users and not found.tls
    # the rules as Zenoh evaluates them: only the owner puts cmd / base/cmd / state; monitor reads health only
    acl = json.loads(str(zenoh.Config.from_file(str(secrets / "router.json5"))))["access_control"]
    for key, owner in (("cmd", "planner"), ("base/cmd", "egress"), ("state", "ingress")):
        allowed = {u for u in users if acl_allows(acl, u, "ingress", "put", f"{P}/{key}")}
        assert allowed == {owner}, (key, allowed)
    assert acl_allows(acl, "monitor", "egress", "put", f"{P}/health/planner")
    assert not any(acl_allows(acl, "monitor", "egress", "put", f"{P}/{k}") for k in ("cmd", "state", "plan"))
    assert not acl_allows(acl, "nobody", "ingress", "put", f"{P}/health/planner")
    # a second init refuses to overwrite; --force rotates every password
    with pytest.raises(SecretsError, match="not empty"):
        init_secrets(secrets, robot=ROBOT)
    init_secrets(secrets, robot=ROBOT, force=True)
    rotated = dict(line.split(":", 1) for line in (secrets / "users.txt").read_text().splitlines())
    assert all(rotated[u] != users[u] for u in users)


# ---- authentication --------------------------------------------------------------------------------------
def test_a_session_without_credentials_or_with_a_wrong_password_cannot_connect(secured: tuple[Path, int]) -> None:
    secrets, port = secured
    zenoh.open(_config(secrets, "planner", port)).close()  # the router is up and the right password gets in
    with pytest.raises(zenoh.ZError):
        zenoh.open(ZenohSettings(connect=[endpoint(port)]).to_config())  # no credentials
    with pytest.raises(zenoh.ZError):
        zenoh.open(_config(secrets, "planner", port, **{"transport.auth.usrpwd.password": "not-the-password"}))
    with pytest.raises(zenoh.ZError):
        zenoh.open(_config(secrets, "planner", port, **{"transport.auth.usrpwd.user": "intruder"}))


# ---- access control --------------------------------------------------------------------------------------
def test_monitor_receives_health_and_liveliness_only(sessions: Sessions) -> None:
    health = Inbox(sessions("monitor"), f"{P}/health/**")
    everything = Inbox(sessions("monitor"), "gpmppi/**")  # asks for all: the router declines the subscription
    cmd_only = Inbox(sessions("monitor"), f"{P}/cmd")
    recorder = Inbox(sessions("recorder"), "gpmppi/**")  # the control: what really went over the router
    watched: list[str] = []
    monitor = sessions("monitor")
    monitor.liveliness().declare_subscriber(f"{P}/alive/**", lambda s: watched.append(str(s.key_expr)))
    planner, ingress = sessions("planner"), sessions("ingress")
    token = planner.liveliness().declare_token(f"{P}/alive/planner")
    sent = {f"{P}/health/planner", f"{P}/cmd", f"{P}/plan", f"{P}/state"}

    def publish() -> bool:
        planner.put(f"{P}/health/planner", encode(Heartbeat(service="planner")))
        planner.put(f"{P}/cmd", _cmd(0.5))
        planner.put(f"{P}/plan", b"{}")
        ingress.put(f"{P}/state", b"{}")
        return recorder.keys() >= sent and bool(health.got)

    assert wait_for(publish, 10.0, step=0.1), recorder.keys()
    time.sleep(0.5)  # anything else on its way to the monitor arrives by now
    assert health.keys() == {f"{P}/health/planner"}
    assert everything.got == [] and cmd_only.got == []
    assert wait_for(lambda: f"{P}/alive/planner" in watched, 5.0)

    def queried() -> list[str]:
        replies = monitor.liveliness().get(f"{P}/alive/**", timeout=2.0)
        return [str(r.ok.key_expr) for r in replies if r.ok is not None]

    assert wait_for(lambda: queried() == [f"{P}/alive/planner"], 10.0)  # a query (retried: a loaded machine)
    token.undeclare()


@pytest.mark.parametrize(
    ("identity", "key"),
    [
        ("monitor", "cmd"),
        ("monitor", "base/cmd"),
        ("ingress", "cmd"),  # valid identities on a key that is not theirs
        ("terrain", "cmd"),
        ("planner", "base/cmd"),
        ("sim", "state"),
        ("operator", "cmd"),
        ("recorder", "base/cmd"),
    ],
)
def test_a_put_on_a_key_that_is_not_yours_never_reaches_its_subscriber(
    sessions: Sessions, identity: str, key: str
) -> None:
    owner, reader = {"cmd": ("planner", "egress"), "base/cmd": ("egress", "sim"), "state": ("ingress", "planner")}[key]
    inbox = Inbox(sessions(reader), f"{P}/{key}")
    intruder, rightful = sessions(identity), sessions(owner)
    payload = _cmd(2.0) if key == "cmd" else _base(2.0) if key == "base/cmd" else b'{"x": 99}'
    pub = intruder.declare_publisher(f"{P}/{key}")
    for _ in range(20):
        pub.put(payload)
        intruder.put(f"{P}/{key}", payload)  # without a declared publisher too
        time.sleep(0.01)
    # the control: the owner's put on the same key does arrive (after the intruder's, on the same router)
    assert wait_for(lambda: (rightful.put(f"{P}/{key}", b"owner"), b"owner" in inbox.payloads())[1], 10.0)
    time.sleep(0.3)
    assert payload not in inbox.payloads()
    if identity == "monitor":  # it publishes nothing, so it is not even told of subscribers (the others are:
        assert not pub.matching_status.matching  # hearing of one grants no data, see services/security/secure.py)


def test_monitor_commands_never_reach_the_simulated_base(
    secured: tuple[Path, int], sessions: Sessions, tmp_path: Path
) -> None:
    secrets, port = secured
    cfg = settings("sim", port, robot=ROBOT, terrain="asphalt", lane="circle", publish_hz=10.0, heartbeat_hz=5.0)
    cfg["zenoh"]["config_file"] = str(secrets / "sim.json5")
    sim = ServiceProcess("sim", cfg, tmp_path)
    try:
        beats: list[Heartbeat] = []
        monitor = sessions("monitor")
        monitor.declare_subscriber(f"{P}/health/sim", lambda s: beats.append(decode(Heartbeat, s.payload.to_bytes())))
        assert wait_for(lambda: bool(beats), 120.0), sim.log()[-3000:]
        for _ in range(20):
            monitor.put(f"{P}/base/cmd", _base(2.0))
            monitor.put(f"{P}/cmd", _cmd(2.0))
            time.sleep(0.05)
        seen_at = len(beats)
        assert wait_for(lambda: len(beats) >= seen_at + 3, 10.0)  # heartbeats sent after the last put
        assert beats[-1].received == 0 and beats[-1].rejected == 0, beats[-1]
        egress = sessions("egress")  # the control: egress's commands reach the sim
        assert wait_for(lambda: (egress.put(f"{P}/base/cmd", _base(0.5)), beats[-1].received > 0)[1], 10.0)
        assert sim.alive()
    finally:
        assert sim.stop() == 0, sim.log()[-3000:]


# ---- TLS and mTLS ----------------------------------------------------------------------------------------
def test_tls_with_client_certificates_on_loopback(tmp_path: Path) -> None:
    secrets = tmp_path / "s"
    init_secrets(secrets, robot=ROBOT, tls=True)
    assert check_secrets(secrets, ROBOT).tls
    tcp, tls = free_port(), free_port()
    tls_ep = f"tls/127.0.0.1:{tls}"
    router = _router_process(secrets, [endpoint(tcp), tls_ep], tmp_path)
    try:

        def over_tls(identity: str, **changes: object) -> zenoh.Config:
            config = _config(secrets, identity, tcp, **changes)
            config.insert_json5("connect/endpoints", json.dumps([tls_ep]))
            return config

        got: list[bytes] = []
        egress = zenoh.open(over_tls("egress"))
        egress.declare_subscriber(f"{P}/cmd", lambda s: got.append(s.payload.to_bytes()))
        planner = zenoh.open(over_tls("planner"))
        assert wait_for(lambda: (planner.put(f"{P}/cmd", _cmd(0.1)), bool(got))[1], 10.0)
        planner.close()
        egress.close()
        # mTLS: no client certificate, no session (even with the right password)
        with pytest.raises(zenoh.ZError):
            zenoh.open(over_tls("planner", **{"transport.link.tls.enable_mtls": False}))
    finally:
        router.stop()


# ---- the checks a launch runs ------------------------------------------------------------------------------
def _launch_error(capsys: pytest.CaptureFixture[str], secrets: Path) -> str:
    code = main([str(REPO / "deploy" / "sim-secure.yaml"), "--secrets", str(secrets), "--duration", "1"])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("gpmppi launch: ") and err.count("\n") == 1, err
    return err


def test_a_missing_secrets_dir_stops_the_launch_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    err = _launch_error(capsys, tmp_path / "nowhere")
    assert str(tmp_path / "nowhere") in err and "gpmppi secure init" in err


def test_a_malformed_users_file_names_the_file_line_and_field(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    secrets = tmp_path / "s"
    init_secrets(secrets, robot="jackal")
    users = secrets / "users.txt"
    lines = users.read_text().splitlines()
    lines.insert(2, "planner-without-a-password")
    users.write_text("\n".join(lines) + "\n")
    err = _launch_error(capsys, secrets)
    assert str(users) in err and "line 3" in err and "dictionary_file" in err and "user:password" in err
    users.chmod(0o644)
    with pytest.raises(SecretsError, match="readable by others"):
        check_secrets(secrets, "jackal")


def test_a_certificate_that_does_not_match_its_key_names_the_config_and_fields(tmp_path: Path) -> None:
    secrets = tmp_path / "s"
    init_secrets(secrets, robot="jackal", tls=True)
    shutil.copy(secrets / "tls" / "egress.key", secrets / "tls" / "planner.key")  # planner's cert, egress's key
    with pytest.raises(SecretsError) as err:
        check_secrets(secrets, "jackal")
    text = str(err.value)
    assert str(secrets / "planner.json5") in text and "connect_certificate" in text and "connect_private_key" in text
    assert "does not match" in text
    # the router's own pair, and a certificate from another CA
    init_secrets(secrets, robot="jackal", tls=True, force=True)
    shutil.copy(secrets / "tls" / "sim.key", secrets / "tls" / "router.key")
    with pytest.raises(SecretsError, match=r"router\.json5 transport\.link\.tls\.listen_certificate"):
        check_secrets(secrets, "jackal")
    init_secrets(secrets, robot="jackal", tls=True, force=True)
    other = make_tls(tmp_path / "other", ["planner"], ["localhost"])
    for i, name in enumerate(("planner.pem", "planner.key")):
        shutil.copy(other["planner"][i], secrets / "tls" / name)
    with pytest.raises(SecretsError, match="is not signed by the root_ca_certificate"):
        check_secrets(secrets, "jackal")


def _edit_acl(secrets: Path, edit) -> None:  # noqa: ANN001 - a callable on the access_control dict
    path = secrets / "router.json5"
    router = json.loads(str(zenoh.Config.from_file(str(path))))
    edit(router["access_control"])
    path.write_text(json.dumps(router))
    os.chmod(path, 0o600)


def _delivered(secrets: Path, tmp_path: Path, sender: str, key: str, reader: str, timeout_s: float = 3.0) -> bool:
    """Whether a real router running DIR/router.json5 delivers `sender`'s put on `key` to `reader` within
    `timeout_s` (a refusal waits it out: short; a delivery ends the wait: allow for a loaded machine)."""
    port = free_port()
    router = _router_process(secrets, [endpoint(port)], tmp_path)
    s = Sessions(secrets, port)
    try:
        inbox = Inbox(s(reader), key)
        src = s(sender)
        return wait_for(lambda: (src.put(key, _cmd(0.3)), bool(inbox.got))[1], timeout_s)
    finally:
        s.close()
        router.stop()


def test_an_acl_that_locks_the_planner_out_of_cmd_is_refused_at_start(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    secrets = tmp_path / "s"
    init_secrets(secrets, robot="jackal")

    def lock_out(acl: dict) -> None:
        next(r for r in acl["rules"] if r["id"] == "planner:put")["key_exprs"].remove("gpmppi/jackal/cmd")

    _edit_acl(secrets, lock_out)
    err = _launch_error(capsys, secrets)
    assert str(secrets / "router.json5") in err and "access_control" in err
    assert "planner" in err and "gpmppi/jackal/cmd" in err and "cannot be driven" in err
    # the check says what Zenoh does: under that ACL a real router drops the planner's commands
    assert not _delivered(secrets, tmp_path, "planner", "gpmppi/jackal/cmd", "egress")
    # a broad allow (a subject with no usernames matches every session) opens cmd to everyone: refused too
    init_secrets(secrets, robot="jackal", force=True)

    def broad(acl: dict) -> None:
        acl["rules"].append(
            {"id": "all", "messages": ["put"], "flows": ["ingress"], "permission": "allow", "key_exprs": ["gpmppi/**"]}
        )
        acl["subjects"].append({"id": "anyone"})
        acl["policies"].append({"rules": ["all"], "subjects": ["anyone"]})

    _edit_acl(secrets, broad)
    with pytest.raises(SecretsError, match="lets sim put on gpmppi/jackal/cmd; only planner may"):
        check_secrets(secrets, "jackal")
    assert _delivered(secrets, tmp_path, "sim", "gpmppi/jackal/cmd", "egress", 15.0)  # and Zenoh lets it through


def test_a_client_config_with_the_wrong_password_or_robot_is_refused(tmp_path: Path) -> None:
    secrets = tmp_path / "s"
    init_secrets(secrets, robot="jackal")
    with pytest.raises(SecretsError, match="robot is 'jackal' but the launch drives 'other'"):
        check_secrets(secrets, "other")
    path = secrets / "egress.json5"
    path.write_text(path.read_text().replace('"password": "', '"password": "x'))
    with pytest.raises(SecretsError, match=r"egress\.json5 transport\.auth\.usrpwd\.password does not match"):
        check_secrets(secrets, "jackal")


def test_the_secured_build_gives_each_session_its_identity_and_the_default_is_unchanged(tmp_path: Path) -> None:
    secrets = tmp_path / "s"
    init_secrets(secrets, robot="jackal")
    path = REPO / "deploy" / "sim-secure.yaml"
    plain, _ = build(LaunchFile.load(path), None, None, free_port())
    import yaml

    for child in plain.children:  # no secrets: nothing points at a secrets folder (as before this option)
        config = yaml.safe_load(child.config_path.read_text())
        assert "router_config_file" not in config and config.get("zenoh", {}).get("config_file") is None
    launch = LaunchFile.load(path)
    secure, _ = build(launch, str(tmp_path / "rec.mcap"), None, free_port(), secrets=str(secrets))
    for child in secure.children:
        config = yaml.safe_load(child.config_path.read_text())
        if child.kind == "router":
            assert config["router_config_file"] == str(secrets.resolve() / "router.json5")
        else:
            assert config["zenoh"]["config_file"] == str(secrets.resolve() / f"{child.kind}.json5")
    assert launch.zenoh.config_file == str(secrets.resolve() / "launcher.json5")


# ---- the whole stack, secured ---------------------------------------------------------------------------------
@pytest.mark.slow(seconds=13)
def test_secured_stack_drives(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    secrets = tmp_path / "secrets"
    init_secrets(secrets, robot="jackal")
    port = free_port()
    out = io.StringIO()
    checks: dict[str, object] = {}

    def intruders(launcher, monitor) -> None:  # noqa: ANN001 - the launcher's hook signature
        # while the robot drives: no credentials, no session; the monitor identity's commands go nowhere; and
        # what egress sends the base follows the planner (reason "planner"), seen by a reader identity
        try:
            zenoh.open(ZenohSettings(connect=[endpoint(port)]).to_config()).close()
            checks["anonymous"] = "connected"
        except zenoh.ZError:
            checks["anonymous"] = "refused"
        reader, intruder = zenoh.open(_config(secrets, "recorder", port)), zenoh.open(_config(secrets, "monitor", port))
        base: list[BaseCommand] = []
        reader.declare_subscriber(
            "gpmppi/jackal/base/cmd", lambda s: base.append(decode(BaseCommand, s.payload.to_bytes()))
        )
        try:
            deadline = time.monotonic() + 6.0
            while time.monotonic() < deadline and not launcher.stop_event.is_set():
                intruder.put("gpmppi/jackal/cmd", _cmd(1.9))
                time.sleep(0.1)
            with monitor.lock:
                checks["egress_received"] = (
                    monitor.heartbeats["egress"].received if "egress" in monitor.heartbeats else 0
                )
        finally:
            intruder.close()
            reader.close()
        checks["base"] = list(base)

    code, summary = run_launch(
        REPO / "deploy" / "sim-secure.yaml", port=port, out=out, secrets=str(secrets), then=intruders,
        edit=without_spares,
    )
    log = out.getvalue()
    assert code == 0, log[-4000:]
    assert checks["anonymous"] == "refused"
    assert {"sim", "ingress", "terrain", "planner", "egress"} <= set(summary.heartbeats_from), log[-3000:]
    base = checks["base"]
    assert isinstance(base, list) and len(base) > 30, log[-3000:]  # egress: 20 Hz
    driven = [b for b in base if b.reason in ("planner", "limit") and b.v > 0.1]
    assert len(driven) > 0.5 * len(base), [b.reason for b in base]
    assert isinstance(checks["egress_received"], int) and checks["egress_received"] > 10
    assert summary.messages.get("gpmppi/jackal/cmd", 0) > 20 and summary.messages.get("gpmppi/jackal/base/cmd", 0) > 30
    assert summary.planner_rate_hz is not None and summary.planner_rate_hz > 2.0, log[-3000:]
    assert summary.distance_driven_m > 1.0


# ---- the robot: ROS 2 nodes on the same (rmw_zenoh) router -----------------------------------------------------
def test_ros2_identity_shares_the_router_but_cannot_command_the_base(tmp_path: Path) -> None:
    from tools.secure_cmd import ROS2_CMD_KEY, ROS2_NAV_KEYS, ROS2_ODOM_KEY

    secrets = tmp_path / "s"
    init_secrets(secrets, robot=ROBOT, ros2={"cmd": ROS2_CMD_KEY, "odom": ROS2_ODOM_KEY, **ROS2_NAV_KEYS})
    assert "ros2" in check_secrets(secrets, ROBOT).users
    port = free_port()
    router = _router_process(secrets, [endpoint(port)], tmp_path)
    s = Sessions(secrets, port)
    try:
        cmd_vel = "0/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_0123"
        odom = "0/odometry/filtered/nav_msgs::msg::dds_::Odometry_/RIHS01_4567"
        base_driver, teleop, egress, ingress = s("ros2"), s("ros2"), s("egress"), s("ingress")
        at_base, at_ingress, at_egress = Inbox(base_driver, cmd_vel), Inbox(ingress, odom), Inbox(egress, f"{P}/cmd")
        graph: list[str] = []
        base_driver.liveliness().declare_subscriber("@ros2_lv/**", lambda x: graph.append(str(x.key_expr)))
        tokens = [teleop.liveliness().declare_token("@ros2_lv/0/teleop/NN/%/%/teleop")]  # the ROS graph still works
        for _ in range(10):
            teleop.put(cmd_vel, b"teleop")  # only egress commands the base
            teleop.put(f"{P}/cmd", _cmd(2.0))  # and no ROS node puts on gpmppi keys
            time.sleep(0.01)
        assert wait_for(lambda: (egress.put(cmd_vel, b"egress"), b"egress" in at_base.payloads())[1], 10.0)
        assert wait_for(lambda: (base_driver.put(odom, b"odom"), b"odom" in at_ingress.payloads())[1], 10.0)
        # Nav2's path reaches the nav service, and the planner's plan reaches the ROS 2 nodes
        path = "0/plan/nav_msgs::msg::dds_::Path_/RIHS01_89ab"
        plan = "0/local_plan/nav_msgs::msg::dds_::Path_/RIHS01_89ab"
        nav, planner = s("nav"), s("planner")
        at_nav, at_ros = Inbox(nav, path), Inbox(teleop, plan)
        assert wait_for(lambda: (teleop.put(path, b"path"), b"path" in at_nav.payloads())[1], 10.0)
        assert wait_for(lambda: (planner.put(plan, b"plan"), b"plan" in at_ros.payloads())[1], 10.0)
        # a token declared before the subscription reached the router is not replayed to it: declare another
        # (same node, next id) until one is seen
        def seen() -> bool:
            if not graph:
                tokens.append(teleop.liveliness().declare_token(f"@ros2_lv/0/teleop/N{len(tokens)}/%/%/teleop"))
            return bool(graph)

        assert wait_for(seen, 10.0)
        time.sleep(0.3)
        assert b"teleop" not in at_base.payloads() and at_egress.got == []
    finally:
        s.close()
        router.stop()


@pytest.mark.parametrize("launch", ["robot.yaml", "ros2_nav2.yaml"])
def test_the_robot_launch_file_runs_secured_without_a_router_of_its_own(tmp_path: Path, launch: str) -> None:
    import yaml

    from tools.secure_cmd import ROS2_NAV_KEYS

    secrets = tmp_path / "s"
    init_secrets(secrets, robot="jackal",
                 ros2={"cmd": "0/cmd_vel/*/*", "odom": "0/odometry/filtered/*/*", **ROS2_NAV_KEYS})
    launcher, _ = build(LaunchFile.load(REPO / "deploy" / launch), None, None, None, secrets=str(secrets))
    kinds = {c.kind for c in launcher.children}
    assert "router" not in kinds and {"ingress", "planner", "egress", "recorder"} <= kinds
    assert ("nav" in kinds) == (launch == "ros2_nav2.yaml")
    for child in launcher.children:
        config = yaml.safe_load(child.config_path.read_text())
        assert config["zenoh"]["config_file"] == str(secrets.resolve() / f"{child.kind}.json5")
        assert config["zenoh"]["connect"] == ["tcp/127.0.0.1:7447"]  # the launch file's endpoint still applies


def test_the_cli_init_and_check(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from tools.cli import app

    runner = CliRunner()
    done = runner.invoke(app, ["secure", "init", str(tmp_path / "s"), "--robot", "r7", "--tls"])
    assert done.exit_code == 0 and "monitor.json5" in done.output, done.output
    assert json.loads((tmp_path / "s" / "secure.json").read_text())["robot"] == "r7"
    ok = runner.invoke(app, ["secure", "check", str(tmp_path / "s"), "--robot", "r7"])
    assert ok.exit_code == 0 and "TLS on; ok" in ok.output, ok.output
    again = runner.invoke(app, ["secure", "init", str(tmp_path / "s")])
    assert again.exit_code == 2 and "--force" in again.output
    missing = runner.invoke(app, ["secure", "check", str(tmp_path / "nowhere")])
    assert missing.exit_code == 2 and "does not exist" in missing.output
