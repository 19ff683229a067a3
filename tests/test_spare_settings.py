"""A warm spare reads its settings again when it takes over: one whose settings file changed after it loaded it
does not take over with the old ones; it exits, so that its service restarts with the new ones."""

from __future__ import annotations

import os
import select
import socket
import subprocess
import sys
from pathlib import Path

from services.ingress import Settings as IngressSettings
from services.run import SETTINGS_CHANGED_EXIT
from services.runtime import role
from services.runtime.node_settings import changed_since_loaded

REPO = Path(__file__).resolve().parents[1]


def _write(path: Path, max_speed: float) -> None:
    # a router port nobody listens on: the process must not get as far as joining
    path.write_text(f"service: ingress\nrobot: r1\nmax_speed: {max_speed}\nlog_json: false\n"
                    "zenoh: {connect: ['tcp/127.0.0.1:9'], wait_for_router_s: 5.0}\n")


def test_changed_since_loaded_names_the_fields_that_differ(tmp_path: Path) -> None:
    path = tmp_path / "ingress.yaml"
    _write(path, 10.0)
    loaded = IngressSettings.load(path)
    assert changed_since_loaded(loaded) == []
    _write(path, 5.0)
    assert changed_since_loaded(loaded) == ["max_speed"]
    assert changed_since_loaded(IngressSettings()) == []  # not from a file: nothing to read again


def test_a_rewritten_model_file_counts_as_changed(tmp_path: Path) -> None:
    """The terrain service saves a learned ground over the profile: a spare that loaded the old one must not take
    over with it (planner and terrain spares load the model before they wait)."""
    from services.runtime.node_settings import NodeSettings

    class WithModel(NodeSettings):
        model_file: str | None = None

    model = tmp_path / "profile.npz"
    model.write_bytes(b"old profile")
    path = tmp_path / "planner.yaml"
    path.write_text(f"service: planner\nmodel_file: {model}\n")
    loaded = WithModel.load(path)
    assert changed_since_loaded(loaded) == []
    model.write_bytes(b"profile with a learned ground")
    assert changed_since_loaded(loaded) == ["model_file (the file was rewritten)"]
    assert changed_since_loaded(WithModel.load(path)) == []  # a process started after the save has the new one


def test_a_spare_whose_settings_changed_exits_at_its_go(tmp_path: Path) -> None:
    path = tmp_path / "ingress.yaml"
    _write(path, 10.0)
    ours, theirs = socket.socketpair()
    env = {**os.environ, role.ROLE_FD_ENV: str(theirs.fileno()), "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-m", "services.run", "ingress", "--config", str(path)], env=env,
                            pass_fds=[theirs.fileno()], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    theirs.close()
    try:
        # loaded and waiting: the spare's state, its settings read
        assert select.select([ours], [], [], 60.0)[0], "no ready from the process"
        assert ours.recv(len(role.READY)) == role.READY
        _write(path, 5.0)  # changed while it waits
        ours.sendall(role.go_message({}))
        out, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        ours.close()
    assert proc.returncode == SETTINGS_CHANGED_EXIT, out
    assert "max_speed" in out and "restarts with them" in out, out
    assert "session open" not in out  # it never joined with the old settings
