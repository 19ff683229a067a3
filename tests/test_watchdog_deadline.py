"""Egress's watchdog fires at its deadline (last accepted command + `watchdog_timeout_s`), not at the next steady
output tick: `SafetyCycle` with explicit times, then egress's own event loop (`services.egress.serve`) in this
process over real loopback Zenoh sessions, 20 trials measured from the last command's put to the zero's arrival."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest
from zenoh_helpers import Collector, client, free_port, matched_publisher, router, settings, wait_for

from gpmppi.safety import SafetyConfig, SafetyCycle
from schemas import BaseCommand, Command, Header, decode, encode
from services.egress import Settings, serve
from services.runtime.node import Node

NS = 1_000_000_000
T0_NS = 1_700_000_000 * NS


def _drive(cycle: SafetyCycle, until: float, now: float = 0.0) -> list[tuple[float, str]]:
    """Run the cycle as the loop does: sleep `wait_s`, then `step`; (time, reason) of every output."""
    sent = []
    while now < until:
        out = cycle.step(now)
        if out is not None:
            sent.append((now, out.output.reason))
        now += max(cycle.wait_s(now), 1e-6)
    return sent


@pytest.mark.parametrize("timeout_s", [0.25, 0.22, 0.13])
def test_the_cycle_sends_zero_at_the_deadline_between_steady_ticks(timeout_s: float) -> None:
    cycle = SafetyCycle(SafetyConfig(watchdog_timeout_s=timeout_s, rate_hz=20.0))
    assert cycle.on_command(0.5, 0.1, T0_NS, 0.0, T0_NS) is None
    sent = _drive(cycle, 1.0)
    assert sent[0] == (0.0, "planner")  # the accepted command goes out at once
    zero = next(t for t, r in sent if r == "watchdog")
    assert zero == pytest.approx(timeout_s, abs=1e-9)  # at the deadline, not the next multiple of 50 ms
    driving = [t for t, r in sent if r == "planner"]
    assert np.allclose(np.diff(driving), 0.05)  # steady repeats until then
    assert all(r == "watchdog" for t, r in sent if t >= timeout_s)


def test_a_refused_command_changes_nothing_and_sends_nothing_new() -> None:
    cycle = SafetyCycle(SafetyConfig(max_command_age_s=0.3))
    cycle.on_command(0.5, 0.0, T0_NS, 0.0, T0_NS)
    assert cycle.step(0.0) is not None and cycle.step(0.01) is None
    assert cycle.on_command(1.0, 0.0, T0_NS, 0.02, T0_NS + int(0.4 * NS)) is not None  # 0.4 s old: refused
    assert cycle.step(0.02) is None
    out = cycle.step(0.05)
    assert out is not None and out.output.v == 0.5 and out.command_stamp_ns is None  # a repeat


def _egress_thread(port: int, **config: object) -> tuple[Node, threading.Thread, SafetyCycle]:
    s = Settings(**settings("egress", port, **config))
    node = Node(s, install_signals=False).open()
    cycle = SafetyCycle(SafetyConfig.from_settings(s))
    thread = threading.Thread(target=serve, args=(node, s, cycle), daemon=True)
    thread.start()
    return node, thread, cycle


def _cpu_wait_s() -> float:
    """How long the calling thread has waited for a CPU, runnable but not running, since it started [s] (Linux
    schedstat; 0 where there is none)."""
    try:
        return int(Path("/proc/thread-self/schedstat").read_text().split()[1]) / 1e9
    except (OSError, IndexError, ValueError):
        return 0.0


class _Timeline:
    """The egress loop's own view, recorded on its thread by wrapping its cycle: each `wait_s` (when it asked to
    wake next) and each `step` that sent a zero (when it woke and sent it, and the command it timed out on), with
    the thread's CPU wait at each."""

    def __init__(self, cycle: SafetyCycle) -> None:
        self.lock = threading.Lock()
        self.waits: list[tuple[float, float, float]] = []  # (now, asked wake time, cpu wait so far)
        # (now, cpu wait so far, when the last command was accepted) of each step that sent a watchdog zero
        self.zeros: list[tuple[float, float, float]] = []
        wait_s, step = cycle.wait_s, cycle.step

        def recorded_wait_s(now: float) -> float:
            w = wait_s(now)
            with self.lock:
                self.waits.append((now, now + w, _cpu_wait_s()))
            return w

        def recorded_step(now: float):  # noqa: ANN202 - SafetyCycle.step's own type
            sent = step(now)
            if sent is not None and sent.output.reason == "watchdog":
                with self.lock:
                    self.zeros.append((now, _cpu_wait_s(), cycle.safety.command_time))
            return sent

        cycle.wait_s = recorded_wait_s  # type: ignore[method-assign]
        cycle.step = recorded_step  # type: ignore[method-assign]

    def zero_after(self, t: float) -> tuple[float, float, float, float] | None:
        """(accepted, asked wake time, sent, CPU waited during that sleep) of the first zero sent after `t`: when
        the command it timed out on was accepted, when the loop asked to wake before sending it, when it did."""
        with self.lock:
            zero = next((z for z in self.zeros if z[0] > t), None)
            if zero is None:
                return None
            now, cpu, accepted = zero
            _, asked, cpu_before = max((w for w in self.waits if w[0] < now), key=lambda w: w[0])
        return accepted, asked, now, cpu - cpu_before


@pytest.mark.exclusive
@pytest.mark.parametrize("timeout_s", [0.25, 0.22])
def test_egress_loop_zeroes_within_20_ms_of_its_deadline_over_10_trials(timeout_s: float) -> None:
    """10 trials per timeout (20 in all): 0.25 s is the default, 0.22 s is off the 50 ms output grid (a loop that
    waited for the next steady tick would send 30 ms late there). Measured from when egress accepted the last
    command (its cycle's own record, as of the zero) to when it sent the zero (the zero's stamp), on this process's
    clocks; the zero's arrival at a subscriber is printed beside it.

    What a loaded machine adds is told apart from what the loop does: the loop must ask to wake at the deadline
    (never later), every trial; and the zero must go out within 20 ms of the deadline once the time its thread
    waited for a CPU during that sleep is taken off (Linux schedstat), in the median trial: a wait that ignores its
    timeout, or a loop that sleeps to the next tick, is late in every trial; a thread that found both cores busy
    (other tests, other users) in one or two."""
    port = free_port()
    with router(port):
        node, thread, cycle = _egress_thread(port, watchdog_timeout_s=timeout_s, rate_hz=20.0)
        timeline = _Timeline(cycle)
        observer = client(port)
        try:
            col = Collector(observer, "gpmppi/r1/base/cmd")
            pub = matched_publisher(observer, "gpmppi/r1/cmd")
            delays: list[float] = []  # last accepted command -> zero sent by egress
            arrivals: list[float] = []  # -> zero arrived at the subscriber (Zenoh and this process's scheduling)
            asked: list[float] = []  # the wake time the loop asked for before sending the zero - the deadline
            cpu_waits: list[float] = []  # how long egress's thread waited for a CPU in that sleep
            for trial in range(10):
                for _ in range(3):
                    t_last = time.monotonic()
                    pub.put(encode(Command(v_ref=0.5, omega_ref=0.1 * trial, header=Header(stamp_ns=time.time_ns()))))
                    time.sleep(0.1)

                def zero_after(t: float = t_last) -> tuple[float, BaseCommand] | None:
                    return next(((ta, b) for ta, p, _ in col.on("gpmppi/r1/base/cmd")
                                 if ta > t and (b := decode(BaseCommand, p)).reason == "watchdog"), None)

                assert wait_for(lambda: zero_after() is not None, 2.0), "no watchdog zero"
                # egress's own record of it: the deadline is the command it timed out on, when egress accepted it
                # (the last one put, however late it was delivered: 0.2 s once under load; or, if it came after the
                # zero, the one before, on which the zero then rightly timed out)
                seen = timeline.zero_after(t_last)
                assert seen is not None, "the loop's record holds no zero after the last command"
                accepted, asked_at, woke, cpu_wait = seen
                assert t_last - 0.25 < accepted < woke
                arrived, zero = zero_after()  # type: ignore[misc]
                # sent: the zero's stamp is egress's wall clock when it went out, on this process's monotonic clock
                sent = (zero.header.stamp_ns - (time.time_ns() - time.monotonic_ns())) / 1e9
                delays.append(sent - accepted)
                arrivals.append(arrived - accepted)
                asked.append(asked_at - (accepted + timeout_s))
                cpu_waits.append(cpu_wait)
                time.sleep(0.1)
            ms = {name: np.round(np.array(v) * 1e3, 1).tolist() for name, v in (
                ("sent", delays), ("arrived", arrivals), ("asked wake - deadline", asked), ("CPU wait", cpu_waits))}
            print(f"timeout {timeout_s} s: last accepted command -> zero [ms]", ms)
            assert min(delays) >= timeout_s - 0.002, delays  # never before the deadline
            assert max(asked) <= 0.001, asked  # the loop asks to wake at the deadline, not at the next tick
            late = np.array(delays) - timeout_s - np.array(cpu_waits)
            assert np.median(late) <= 0.020, (delays, cpu_waits)
        finally:
            node.stop()
            thread.join(5.0)
            assert not thread.is_alive()
            node.close()
            observer.close()
