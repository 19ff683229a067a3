"""Nothing lost, nothing left running, nothing started on a bad file (issue 47).

- A recording (`--record`, the rerun `save` file) never overwrites: an existing file gets a free suffixed
  name, a folder a new file inside it, a missing folder is an error before anything starts; the writers
  themselves create their files exclusively (rotation and restarts included).
- A launcher killed by any signal takes its services with it (PR_SET_PDEATHSIG, the launcher's pid in their
  environment), and a child started from a thread that ends is not taken with that thread.
- A launch file is validated as a whole before anything starts, each problem at its line in the user's file;
  a YAML syntax error is one line FILE:LINE:COL.
- The run's numbers (duration, port) are checked by the library, not only the CLI.
"""

from __future__ import annotations

import io
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml
from zenoh_helpers import REPO, Collector, endpoint, free_port, router, wait_for

from schemas import BaseCommand, Header, Heartbeat
from services.launch import processes
from services.launch.launch_file import DEFAULT_LAUNCH, LaunchFile, LaunchFileError
from services.launch.launcher import build, main, run_launch
from services.launch.processes import wait_for_endpoint
from services.recording.mcap_io import read_messages
from services.recording.mcap_writer import McapWriter
from services.recording.output_files import OutputPathError, free_name, resolve_output
from services.run import LAUNCHER_PID_ENV
from services.runtime.config_file import ConfigFileError, read_yaml


@pytest.fixture
def no_process(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any child process the launcher would start fails the test: the check must come first."""

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError(f"a process was started: {args}")

    monkeypatch.setattr(processes.SPAWNER, "popen", refuse)


# ---- output files ---------------------------------------------------------------------------------
def test_resolve_output_never_names_an_existing_file(tmp_path: Path) -> None:
    target = tmp_path / "run.mcap"
    assert resolve_output(target) == (target, "")
    target.write_bytes(b"first")
    path, note = resolve_output(target)
    assert path == tmp_path / "run-1.mcap" and "exists and is kept" in note and str(path) in note
    path.write_bytes(b"second")
    assert resolve_output(target)[0] == tmp_path / "run-2.mcap"
    # a rotated or restarted part of an earlier recording counts as that recording
    assert free_name(tmp_path / "x.mcap") == tmp_path / "x.mcap"
    (tmp_path / "x_001.mcap").write_bytes(b"")
    assert free_name(tmp_path / "x.mcap") == tmp_path / "x-1.mcap"
    (tmp_path / "y.restart1.rrd").write_bytes(b"")
    assert free_name(tmp_path / "y.rrd") == tmp_path / "y-1.rrd"


def test_resolve_output_folder_and_missing_folder(tmp_path: Path) -> None:
    path, note = resolve_output(tmp_path, ".rrd")
    assert path.parent == tmp_path and re.fullmatch(r"run-\d{8}-\d{6}\.rrd", path.name), path
    assert "is a folder" in note
    for bad in (tmp_path / "missing" / "x.mcap", f"{tmp_path}/missing/"):
        with pytest.raises(OutputPathError, match="mkdir -p") as info:
            resolve_output(bad)
        assert "\n" not in str(info.value) and "missing" in str(info.value)
    (tmp_path / "afile").write_text("")
    with pytest.raises(ValueError, match="is not a folder"):
        resolve_output(tmp_path / "afile" / "x.mcap")
    assert not (tmp_path / "missing").exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into any folder")
def test_resolve_output_unwritable_folder(tmp_path: Path) -> None:
    folder = tmp_path / "ro"
    folder.mkdir(mode=0o500)
    with pytest.raises(OutputPathError, match="not writable"):
        resolve_output(folder / "x.mcap")


def test_mcap_writer_refuses_an_existing_file_and_part(tmp_path: Path) -> None:
    old = tmp_path / "old.mcap"
    old.write_bytes(b"precious")
    with pytest.raises(FileExistsError):
        McapWriter(old)
    assert old.read_bytes() == b"precious"
    # rotation into a part that exists: the writer stops (like a write error), naming it; the part is kept
    part = tmp_path / "r_001.mcap"
    part.write_bytes(b"earlier part")
    hb = Heartbeat(header=Header(stamp_ns=1), service="x")
    writer = McapWriter(tmp_path / "r.mcap", chunk_size=1000, max_bytes=2000)
    with pytest.raises(FileExistsError):
        for i in range(200):
            writer.write("gpmppi/r/health/x", hb, log_time_ns=i + 1)
    assert writer.failed is not None and "r_001.mcap" in writer.failed
    assert part.read_bytes() == b"earlier part"
    writer.close()
    assert len(list(read_messages(tmp_path / "r.mcap"))) > 0  # what was written before reads back


def test_recorder_failure_line_says_why() -> None:
    import errno

    from services.recorder import _write_failure

    line = _write_failure("runs/x.mcap", "File exists", 0, errno.EEXIST)
    assert "never overwrites" in line and "disk is full" not in line
    assert "is a folder" in _write_failure("runs", "Is a directory", 0, errno.EISDIR)
    assert "disk is full" in _write_failure("x.mcap", "No space left on device", 5, errno.ENOSPC)


def test_viewer_refuses_to_save_over_an_existing_file(tmp_path: Path) -> None:
    from services.viewer import Settings, run

    rrd = tmp_path / "view.rrd"
    rrd.write_bytes(b"an earlier view")
    assert run(Settings(mode="save", path=str(rrd))) == 2
    assert rrd.read_bytes() == b"an earlier view"


def test_record_into_a_missing_folder_fails_before_anything_starts(tmp_path: Path, no_process: None) -> None:
    out = io.StringIO()
    with pytest.raises(OutputPathError, match="does not exist"):
        run_launch(None, duration=1.0, record=str(tmp_path / "nope" / "x.mcap"), port=free_port(), out=out)
    with pytest.raises(OutputPathError, match="does not exist"):
        run_launch(None, duration=1.0, rerun=["save", str(tmp_path / "nope" / "v.rrd")], port=free_port(), out=out)
    assert not (tmp_path / "nope").exists() and "started" not in out.getvalue()


# ---- the run's numbers --------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("duration", "port", "setting"),
    [(float("nan"), None, "duration"), (float("inf"), None, "duration"), (-5.0, None, "duration"),
     (0.0, None, "duration"), (1.0, -1, "port"), (1.0, 0, "port"), (1.0, 70000, "port")],
)
def test_run_launch_rejects_bad_duration_and_port(
    duration: float, port: int | None, setting: str, no_process: None
) -> None:
    t0 = time.monotonic()
    with pytest.raises(ValueError, match=setting):
        run_launch(None, duration=duration, port=port, out=io.StringIO())
    assert time.monotonic() - t0 < 5.0


# ---- launch files and service configs ------------------------------------------------------------------
def test_yaml_syntax_error_is_one_line_with_the_file_and_line(tmp_path: Path, no_process: None) -> None:
    bad = tmp_path / "launch.yaml"
    bad.write_text("robot: r1\nservices:\n  - name: sim\n    config: {terrain: [asphalt, tile}\n")
    with pytest.raises(LaunchFileError) as info:
        run_launch(bad, duration=1.0, out=io.StringIO())
    message = str(info.value)
    assert message.startswith(f"{bad}:4:") and "\n" not in message and "unicode string" not in message
    with pytest.raises(LaunchFileError, match=re.escape(f"{bad}:4:")):
        LaunchFile.load(bad)
    # a service's own config file (`gpmppi service NAME --config FILE`) the same way
    from services.egress import Settings as EgressSettings

    config = tmp_path / "egress.yaml"
    config.write_text("rate_hz: 20\n  watchdog_timeout_s: 0.3\n")
    with pytest.raises(ConfigFileError) as info:
        EgressSettings.load(config)
    assert str(info.value).startswith(f"{config}:2:") and "\n" not in str(info.value)
    with pytest.raises(ConfigFileError, match=re.escape(f"{config}:2:")):
        read_yaml(config)


def test_cli_prints_one_line_and_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "launch.yaml"
    bad.write_text("services: [\n")
    assert main([str(bad), "--duration", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"gpmppi launch: {bad}:") and "\n" not in err and "Traceback" not in err
    proc = subprocess.run(
        [sys.executable, "-m", "services.run", "egress", "--config", str(bad)],
        capture_output=True, text=True, timeout=120, cwd=REPO,
    )
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert f"{bad}:2:1: YAML syntax error" in proc.stderr


def test_a_bad_field_of_any_service_is_found_before_anything_starts(tmp_path: Path, no_process: None) -> None:
    launch = yaml.safe_load(DEFAULT_LAUNCH.read_text())
    planner = next(i for i, e in enumerate(launch["services"]) if e["name"] == "planner")
    launch["services"][planner]["config"]["max_state_age_s"] = "soon"
    launch["services"][planner]["config"]["horizn"] = 40
    path = tmp_path / "typo.yaml"
    path.write_text(yaml.safe_dump(launch, sort_keys=False))
    lines = path.read_text().splitlines()
    age_line = next(n for n, line in enumerate(lines, 1) if "max_state_age_s" in line)
    typo_line = next(n for n, line in enumerate(lines, 1) if "horizn" in line)
    out = io.StringIO()
    with pytest.raises(LaunchFileError) as info:
        run_launch(path, duration=1.0, out=out)
    message = str(info.value)
    assert "\n" not in message and "gpmppi-launch-" not in message  # the user's file, not a temporary copy
    assert f"{path}:{age_line}:" in message and "max_state_age_s" in message and "(planner)" in message
    assert f"{path}:{typo_line}:" in message and "horizn" in message
    assert out.getvalue() == ""


def test_shipped_launch_files_pass_the_whole_check() -> None:
    from services.launch.launch_file import load_launch
    from services.launch.launcher import check_launch

    for path in [DEFAULT_LAUNCH, *sorted((REPO / "deploy").glob("*.yaml"))]:
        launch, marks = load_launch(path)
        check_launch(launch, path, marks)


# ---- no orphans ------------------------------------------------------------------------------------------
def test_a_service_whose_launcher_is_gone_does_not_start(tmp_path: Path) -> None:
    config = tmp_path / "router.yaml"
    config.write_text(yaml.safe_dump({"listen": [endpoint(free_port())]}))
    env = {**os.environ, "PYTHONPATH": str(REPO), LAUNCHER_PID_ENV: "1"}  # not this child's parent
    proc = subprocess.run(
        [sys.executable, "-m", "services.run", "router", "--config", str(config)],
        capture_output=True, text=True, timeout=60, env=env,
    )
    assert proc.returncode == 0 and "is gone" in proc.stderr, proc.stderr
    # it found out before a service's imports (a spare started just before its launcher's SIGKILL lived on through
    # them on a loaded machine: seconds): services.run arms PR_SET_PDEATHSIG with only the standard library loaded
    heavy = "print(sorted({'pydantic', 'numpy', 'zenoh'} & set(sys.modules)))"
    probe = subprocess.run(
        [sys.executable, "-c", f"import sys, services.run; {heavy}"],
        capture_output=True, text=True, timeout=60, env=env,
    )
    assert probe.stdout.strip() == "[]", probe.stdout + probe.stderr


def test_a_child_started_from_a_thread_outlives_the_thread(tmp_path: Path) -> None:
    """PR_SET_PDEATHSIG fires when the *thread* that forked the child ends: the launcher forks from one
    thread that lives as long as it does, so a start or restart from a passing thread is safe."""
    port = free_port()
    launch = LaunchFile.model_validate(
        {"router": {"listen": [endpoint(port)]}, "zenoh": {"connect": [endpoint(port)]}, "services": []}
    )
    launcher, _ = build(launch, None, None, None)
    launcher.out = io.StringIO()
    try:
        starter = threading.Thread(target=launcher.start_all)
        starter.start()
        starter.join(30)
        old = launcher.child("router").process

        def restart_and_wait() -> None:
            # the thread lives on until the new router has armed its PR_SET_PDEATHSIG (at the start of its main,
            # before it listens), then ends: a child forked by this thread would get SIGTERM now
            launcher.restart("router")
            wait_for_endpoint(endpoint(port), 60.0)

        restarter = threading.Thread(target=restart_and_wait)
        restarter.start()
        restarter.join(90)
        process = launcher.child("router").process
        assert process is not None and process is not old
        time.sleep(1.5)
        assert process.poll() is None, f"exit {process.returncode}: {launcher.out.getvalue()}"
    finally:
        launcher.stop_all()


def _exit_times(launcher_pid: int, since: float, timeout_s: float) -> dict[str, float]:
    """When each process of this launcher was gone, in s after `since` ('pid kind': s; inf: still running after
    `timeout_s`, then killed), so a failure names who was late and by how much."""
    names: dict[int, str] = {}
    gone: dict[str, float] = {}
    deadline = time.monotonic() + timeout_s
    while True:
        alive = set(_processes_of(launcher_pid))
        for pid in alive - set(names):
            try:
                args = (Path("/proc") / str(pid) / "cmdline").read_bytes().split(b"\0")
            except OSError:
                args = []
            kind = args[args.index(b"services.run") + 1].decode() if b"services.run" in args[:-1] else "?"
            names[pid] = f"{pid} {kind}"
        for pid, name in names.items():
            if pid not in alive and name not in gone:
                gone[name] = round(time.monotonic() - since, 3)
        if not alive or time.monotonic() > deadline:
            break
        time.sleep(0.02)
    for pid in alive:
        gone[names[pid]] = float("inf")
        os.kill(pid, signal.SIGKILL)
    return gone


def _processes_of(launcher_pid: int) -> list[int]:
    """Every process (children and theirs) whose environment names this launcher."""
    marker = f"{LAUNCHER_PID_ENV}={launcher_pid}".encode()
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            if marker in (entry / "environ").read_bytes().split(b"\0"):
                state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
                if state != "Z":
                    found.append(int(entry.name))
        except OSError:
            continue
    return found


@pytest.mark.slow(seconds=90)  # the whole simulated stack, driving, then the launcher killed
# ahead of the other tests (tests/conftest.py): it times the services' exits, and beside a compile the recorder,
# finishing its file, was out 2.38 s after the launcher's SIGKILL (2 s allowed) in a fresh-clone CI run
@pytest.mark.exclusive
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_sigkill_of_the_launcher_takes_every_service_with_it(tmp_path: Path) -> None:
    port = free_port()
    launch = yaml.safe_load(DEFAULT_LAUNCH.read_text())
    # the router is the test's own, so an outside observer still sees the robot's commands after the kill
    launch["router"] = {"enabled": False, "listen": [endpoint(port)]}
    launch["zenoh"]["connect"] = [endpoint(port)]
    path = tmp_path / "launch.yaml"
    path.write_text(yaml.safe_dump(launch))
    log_path = tmp_path / "launcher.log"
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
    with router(port) as session, open(log_path, "wb") as log:
        col = Collector(session, "gpmppi/jackal/base/cmd")
        launcher = subprocess.Popen(
            [sys.executable, "-m", "services.launch.launcher", str(path), "--duration", "600",
             "--record", str(tmp_path)],
            stdout=log, stderr=subprocess.STDOUT, env=env, cwd=tmp_path,
        )
        try:
            def driving() -> bool:
                cmds = [BaseCommand.model_validate_json(p) for _, p, _ in col.on("gpmppi/jackal/base/cmd")]
                return any(c.reason != "watchdog" and c.v > 0.2 for c in cmds[-5:])

            assert wait_for(driving, 300.0, 0.2), log_path.read_text()[-4000:]
            text = log_path.read_text()
            started = {int(pid) for pid in re.findall(r"started \w+ \(\w+\) pid (\d+)", text)}
            assert len(started) == 6, text  # sim, ingress, terrain, planner, egress and the recorder
            assert started <= set(_processes_of(launcher.pid))
            os.kill(launcher.pid, signal.SIGKILL)
            killed = time.monotonic()
            launcher.wait(10)
            exits = _exit_times(launcher.pid, killed, 10.0)
            gone_s = max(exits.values(), default=0.0)
            assert gone_s <= 2.0, f"not gone 2 s after the launcher's SIGKILL (s after it, by process): {exits}"
            # the robot is left without a command source: nothing reaches the base from then on, and its own
            # command timeout (the sim's, a Jackal's cmd_vel_timeout) stops it
            n = len(col.on("gpmppi/jackal/base/cmd"))
            time.sleep(1.0)
            assert len(col.on("gpmppi/jackal/base/cmd")) == n
            print(f"every service gone {gone_s:.2f} s after the launcher's SIGKILL: {exits}")
        finally:
            if launcher.poll() is None:
                launcher.kill()
                launcher.wait()
            for pid in _processes_of(launcher.pid):
                os.kill(pid, signal.SIGKILL)
    # the recorder stopped on its SIGTERM: its file, inside the folder given, reads back
    recordings = sorted(tmp_path.glob("run-*.mcap"))
    assert len(recordings) == 1 and len(list(read_messages(recordings[0]))) > 0


# ---- a recording never overwrites (real launches) ---------------------------------------------------------
def _sim_only(tmp_path: Path, port: int) -> Path:
    path = tmp_path / "sim.yaml"
    path.write_text(
        yaml.safe_dump(
            {
                "router": {"listen": [endpoint(port)]},
                "zenoh": {"connect": [endpoint(port)]},
                "services": [{"name": "sim", "config": {"publish_hz": 20.0}}],
            }
        )
    )
    return path


@pytest.mark.slow(seconds=40)  # two short launches (router, sim, recorder; a viewer in one)
def test_recording_twice_to_one_path_keeps_the_first(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    port = free_port()
    launch = _sim_only(tmp_path, port)
    runs = tmp_path / "runs"
    runs.mkdir()
    record, rrd = runs / "run.mcap", runs / "view.rrd"
    # an earlier run's files (what is in them does not matter: an existing file is never replaced, whatever it holds;
    # recording to a new path is what every other stack test does)
    record.write_bytes(b"an earlier recording")
    rrd.write_bytes(b"an earlier view")
    before = record.read_bytes()

    out = io.StringIO()
    code, second = run_launch(launch, duration=2.0, record=str(record), rerun=["save", str(rrd)], port=port, out=out)
    log = out.getvalue()
    assert code == 0, log[-3000:]
    assert record.read_bytes() == before  # byte-identical
    assert rrd.read_bytes() == b"an earlier view"
    assert second.recording == str(runs / "run-1.mcap") and second.rerun_file == str(runs / "view-1.rrd")
    assert f"{record} exists and is kept: writing {runs / 'run-1.mcap'}" in log  # said at the start ...
    assert any("exists and is kept" in line for line in second.lines())  # ... and in the summary
    assert len(list(read_messages(runs / "run-1.mcap"))) > 0 and (runs / "view-1.rrd").stat().st_size > 100

    # --record DIR: a new file inside it, never "recording: DIR" with nothing recorded
    code, third = run_launch(launch, duration=2.0, record=str(runs), port=port, out=io.StringIO())
    assert code == 0 and third.recording is not None
    made = Path(third.recording)
    assert made.parent == runs and re.fullmatch(r"run-\d{8}-\d{6}\.mcap", made.name)
    assert len(list(read_messages(made))) > 0
    assert record.read_bytes() == before


def test_wait_for_endpoint_probes_tcp_and_tls_ports_and_times_out_on_a_closed_one() -> None:
    import socket

    with socket.create_server(("127.0.0.1", 0)) as server:
        port = server.getsockname()[1]
        for kind in ("tcp", "tls"):
            wait_for_endpoint(f"{kind}/127.0.0.1:{port}", timeout_s=2.0)  # returns: the port accepts
    for kind in ("tcp", "tls"):  # nothing listens there now
        start = time.monotonic()
        with pytest.raises(TimeoutError, match=f"{kind}/127.0.0.1:{port}"):
            wait_for_endpoint(f"{kind}/127.0.0.1:{port}", timeout_s=0.3)
        assert time.monotonic() - start >= 0.3
