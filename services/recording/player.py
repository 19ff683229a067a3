"""The replay player: a recording back onto Zenoh with its recorded timing (what `gpmppi replay` drives).

Timing. Message i is due at `w0 + (log_time_i - log_time_0) / speed` on the monotonic clock and is put when due
(the reading runs ahead on its own thread, so decompressing a chunk never delays a put). The lateness of each
put against its due time is measured and reported. `speed = 0` puts each message as soon as the one before it
has been taken: publishers use congestion control BLOCK, so a subscriber that cannot keep up (a FIFO that is
full) slows the player down instead of losing messages.

Stamps. By default every header stamp (also nested ones, e.g. a Plan's command) is moved to replay time keeping
its recorded age: `stamp' = stamp + (due_epoch_ns - log_time_ns)`. A service that refuses stale input (ingress,
planner) therefore sees the same ages as it did live. `keep_stamps` publishes the payloads unchanged.

Keys. `keys` / `exclude` are regular expressions searched in the recorded key; quarantine channels
(`<key>/_rejected`, input the recorder found invalid) are never republished; `suppress` drops the outputs of
services that run live instead (`--replace`); `robot` republishes `gpmppi/<old>/...` as `gpmppi/<robot>/...`.
"""

from __future__ import annotations

import json
import queue
import re
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np
import zenoh

from schemas.codec import ENCODING
from services.recording.mcap_io import FOXGLOVE_SCHEMA_PREFIX
from services.recording.player_log import QUARANTINE_SUFFIX, Record


@dataclass
class PlayOptions:
    speed: float = 1.0
    start_s: float | None = None
    end_s: float | None = None
    keys: str | None = None
    exclude: str | None = None
    loop: bool = False
    robot: str | None = None
    keep_stamps: bool = False
    suppress: set[str] = field(default_factory=set)  # exact recorded keys not to publish
    # the newest message before `start_s` on these recorded keys is put first (inputs that are sent rarely,
    # e.g. the task or the terrain weights, which a live service needs from the first played state on)
    prime: set[str] = field(default_factory=set)
    track_key: str | None = None  # recorded key whose (replayed stamp -> recorded stamp) map is kept
    # only these recorded header stamps are played on `track_key` (e.g. the states a recorded planner answered)
    only_stamps: set[int] | None = None
    # after each `track_key` message, wait up to this long for `Player.answered(replayed stamp)` (a live service's
    # answer) before going on (None: recorded timing, no waiting). The wait does not move the schedule: the next
    # messages go out late (at once) until it has caught up, and every stamp stays on the schedule, so the
    # `track_key` stamps keep their recorded distances (a live planner shifts its warm start by them,
    # `Planner.catch_up`) and look older by the lateness
    lockstep_timeout_s: float | None = None
    # lockstep: a `track_key` message more than this late moves the schedule by its lateness (its stamp then follows
    # the clock: its distance to the one before grows by that much; counted in `PlayStats.lockstep_shifts`), so a
    # live service that is slower than the recorded one throughout is not fed states that grow older without end
    lockstep_max_late_s: float = 0.25

    def __post_init__(self) -> None:
        if self.speed < 0:
            raise ValueError(f"speed must be >= 0 (0: as fast as possible), got {self.speed}")
        if self.start_s is not None and self.start_s < 0:
            raise ValueError(f"start must be >= 0 seconds into the log, got {self.start_s}")
        if self.start_s is not None and self.end_s is not None and self.end_s <= self.start_s:
            raise ValueError(f"end ({self.end_s} s) must be after start ({self.start_s} s)")
        for name in ("keys", "exclude"):
            pattern = getattr(self, name)
            if pattern is not None:
                try:
                    re.compile(pattern)
                except re.error as exc:
                    raise ValueError(f"--{name} {pattern!r} is not a regular expression: {exc}") from None


@dataclass
class PlayStats:
    published: int = 0
    by_key: dict[str, int] = field(default_factory=dict)
    suppressed: int = 0
    filtered: int = 0
    quarantined: int = 0
    unanswered: int = 0  # states left out because the recorded planner did not answer them (only_stamps)
    lockstep_shifts: int = 0  # lockstep: tracked messages so late that the schedule moved (lockstep_max_late_s)
    unshifted: int = 0  # payloads that are not JSON messages with a header: published as recorded
    loops: int = 0
    log_span_s: float = 0.0  # log time covered by what was played (one pass)
    wall_s: float = 0.0
    lateness_ms: list[float] = field(default_factory=list)  # put time - due time, per message (speed > 0)
    interrupted: bool = False

    def lateness_summary(self) -> dict[str, float]:
        if not self.lateness_ms:
            return {}
        a = np.asarray(self.lateness_ms)
        return {"p50_ms": float(np.percentile(a, 50)), "p99_ms": float(np.percentile(a, 99)),
                "max_ms": float(a.max()), "mean_ms": float(a.mean())}


def rename_robot(key: str, robot: str | None) -> str:
    if robot is None:
        return key
    parts = key.split("/", 2)
    if len(parts) == 3 and parts[0] == "gpmppi":
        return f"gpmppi/{robot}/{parts[2]}"
    return key


def shift_stamps(data: bytes, offset_ns: int) -> tuple[bytes, int | None] | None:
    """The payload with every header stamp moved by `offset_ns` (unset stamps, 0, stay 0), and the top header's
    original stamp; None when the payload is not a JSON object with a header (published unchanged then)."""
    try:
        obj = json.loads(data)
    except ValueError:
        return None
    if not isinstance(obj, dict) or not isinstance(obj.get("header"), dict):
        return None
    top = obj["header"].get("stamp_ns")

    def walk(node: object) -> None:
        if isinstance(node, dict):
            header = node.get("header")
            if isinstance(header, dict) and isinstance(header.get("stamp_ns"), int) and header["stamp_ns"] > 0:
                header["stamp_ns"] = max(0, header["stamp_ns"] + offset_ns)
            for k, v in node.items():
                if k != "header" and isinstance(v, dict):
                    walk(v)

    walk(obj)
    return json.dumps(obj, separators=(",", ":")).encode(), top if isinstance(top, int) else None


class Player:
    """Puts the records of a recording on a Zenoh session with their recorded timing (see the module doc).

    `records` is called for each pass (a fresh iterator over the whole log, in log-time order).
    `on_progress(log_s, span_s)` is called now and then with the log time reached."""

    def __init__(
        self,
        session: zenoh.Session,
        records: Callable[[], Iterator[Record]],
        options: PlayOptions,
        on_progress: Callable[[float], None] | None = None,
        stop: threading.Event | None = None,
    ) -> None:
        self.session = session
        self.records = records
        self.o = options
        self.on_progress = on_progress
        self.stop = stop or threading.Event()
        self._pubs: dict[str, zenoh.Publisher] = {}
        self._keys_re = re.compile(options.keys) if options.keys else None
        self._exclude_re = re.compile(options.exclude) if options.exclude else None
        self.stats = PlayStats()
        # replayed stamp -> recorded stamp on `track_key` (to match a live service's outputs with the recorded ones)
        self.stamp_map: dict[int, int] = {}
        self.log_start_ns: int | None = None
        # lockstep: called with a replayed stamp and a timeout, True once the live service has answered it
        self.answered: Callable[[int, float], bool] | None = None
        self.lockstep_misses = 0

    def _publisher(self, key: str) -> zenoh.Publisher:
        pub = self._pubs.get(key)
        if pub is None:
            pub = self.session.declare_publisher(
                key, encoding=zenoh.Encoding(ENCODING), congestion_control=zenoh.CongestionControl.BLOCK
            )
            self._pubs[key] = pub
        return pub

    def _selected(self, rec: Record) -> bool:
        s = self.stats
        if rec.key.endswith(QUARANTINE_SUFFIX):
            s.quarantined += 1
            return False
        if (rec.schema or "").startswith(FOXGLOVE_SCHEMA_PREFIX):  # the Foxglove scene, a view: never put on Zenoh
            s.filtered += 1
            return False
        if rec.key in self.o.suppress:
            s.suppressed += 1
            return False
        if (self._keys_re and not self._keys_re.search(rec.key)) or (
            self._exclude_re and self._exclude_re.search(rec.key)
        ):
            s.filtered += 1
            return False
        return True

    def _window(self) -> Iterator[tuple[Record, bool]]:
        """(record, primed) of one pass: the primed records first (due at the start), then the window."""
        it = self.records()
        start_ns = end_ns = None
        primed: dict[str, Record] = {}
        for rec in it:
            if self.log_start_ns is None:
                self.log_start_ns = rec.log_time_ns
            if start_ns is None:
                start_ns = self.log_start_ns + int((self.o.start_s or 0.0) * 1e9)
                end_ns = None if self.o.end_s is None else self.log_start_ns + int(self.o.end_s * 1e9)
            if rec.log_time_ns < start_ns:
                if rec.key in self.o.prime:
                    primed[rec.key] = rec
                continue
            if end_ns is not None and rec.log_time_ns > end_ns:
                break
            if primed:
                for p in sorted(primed.values(), key=lambda r: r.log_time_ns):
                    yield p, True
                primed = {}
            yield rec, False
        # (a window that is empty yields nothing, also no primed records)

    @staticmethod
    def _offer(out: queue.Queue, item: object, done: threading.Event) -> bool:
        """Put `item` unless the pass is over first; False then."""
        while not done.is_set():
            try:
                out.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _reader(self, out: queue.Queue, done: threading.Event) -> None:
        try:
            for item in self._window():
                if not self._offer(out, item, done):
                    return
        except BaseException as exc:  # noqa: BLE001 - handed to the playing thread
            self._offer(out, exc, done)
            return
        self._offer(out, None, done)

    def play_once(self) -> None:
        q: queue.Queue = queue.Queue(maxsize=2000)
        done = threading.Event()  # the pass is over (end, stop or error): the reader thread ends too
        reader = threading.Thread(target=self._reader, args=(q, done), daemon=True, name="replay-reader")
        reader.start()
        speed = self.o.speed
        lockstep_timeout = self.o.lockstep_timeout_s
        lockstep = lockstep_timeout is not None
        first_log_ns: int | None = None
        last_log_ns: int | None = None
        w0 = e0 = 0.0
        e0_ns = 0
        next_progress = 0.0
        s = self.stats
        try:
            while not self.stop.is_set():
                item = q.get()
                if item is None:
                    break
                if isinstance(item, BaseException):
                    raise item
                rec, primed = item
                if not self._selected(rec):
                    continue
                if self.o.only_stamps is not None and rec.key == self.o.track_key:
                    try:
                        stamp = json.loads(rec.data)["header"]["stamp_ns"]
                    except (ValueError, KeyError, TypeError):
                        stamp = None
                    if stamp not in self.o.only_stamps:
                        s.unanswered += 1
                        continue
                log_ns = rec.log_time_ns
                if first_log_ns is None:
                    first_log_ns = log_ns
                    w0, e0_ns = time.monotonic(), time.time_ns()
                    e0 = w0
                if primed:
                    log_ns = first_log_ns  # due at the start, stamped as if received then
                last_log_ns = max(last_log_ns or log_ns, log_ns)
                if speed > 0:
                    due = w0 + (log_ns - first_log_ns) / 1e9 / speed
                    late = time.monotonic() - due
                    if lockstep and rec.key == self.o.track_key and late > self.o.lockstep_max_late_s:
                        w0 += late
                        due += late
                        s.lockstep_shifts += 1
                    while (wait := due - time.monotonic()) > 0:
                        if self.stop.wait(min(wait, 0.1)):
                            break
                    if self.stop.is_set():
                        break
                    due_epoch_ns = e0_ns + int((due - e0) * 1e9)
                else:
                    due, due_epoch_ns = time.monotonic(), time.time_ns()
                payload = rec.data
                if not self.o.keep_stamps:
                    # a primed record is due at the start but keeps its recorded age (as if sent again then)
                    shifted = shift_stamps(rec.data, due_epoch_ns - rec.log_time_ns)
                    if shifted is None:
                        s.unshifted += 1
                    else:
                        payload, original = shifted
                        if rec.key == self.o.track_key and original is not None:
                            self.stamp_map[original + due_epoch_ns - rec.log_time_ns] = original
                key = rename_robot(rec.key, self.o.robot)
                self._publisher(key).put(payload)
                if lockstep_timeout is not None and rec.key == self.o.track_key and self.answered:
                    # the schedule stays: what comes due during the wait goes out after it, stamped on the schedule
                    # (moving the schedule by each wait made the distance between two states' stamps grow by it,
                    # and a live planner shifts its warm start by that distance: one more step once it is dt/2)
                    answer_stamp = json.loads(payload)["header"]["stamp_ns"]
                    if not self.answered(answer_stamp, lockstep_timeout):
                        self.lockstep_misses += 1
                if speed > 0:
                    s.lateness_ms.append((time.monotonic() - due) * 1e3)
                s.published += 1
                s.by_key[key] = s.by_key.get(key, 0) + 1
                if self.on_progress is not None and time.monotonic() >= next_progress:
                    next_progress = time.monotonic() + 0.1
                    self.on_progress((log_ns - (self.log_start_ns or log_ns)) / 1e9)
        finally:
            if self.stop.is_set():
                s.interrupted = True
            done.set()
            reader.join(5.0)
        if first_log_ns is not None and last_log_ns is not None:
            s.log_span_s = max(s.log_span_s, (last_log_ns - first_log_ns) / 1e9)

    def declare(self, keys: set[str]) -> None:
        """Declare the publishers of these recorded keys now (those the filters let through), so the first put on
        each key does not pay for the declaration."""
        for key in sorted(keys):
            if not key.endswith(QUARANTINE_SUFFIX) and key not in self.o.suppress and not (
                (self._keys_re and not self._keys_re.search(key)) or (self._exclude_re and self._exclude_re.search(key))
            ):
                self._publisher(rename_robot(key, self.o.robot))

    def play(self) -> PlayStats:
        t0 = time.monotonic()
        try:
            while True:
                before = self.stats.published
                self.play_once()
                self.stats.loops += 1
                if not self.o.loop or self.stop.is_set() or self.stats.published == before:
                    break
        finally:
            self.stats.wall_s = time.monotonic() - t0
            for pub in self._pubs.values():
                pub.undeclare()
            self._pubs.clear()
        return self.stats


def copy_payloads(config: zenoh.Config) -> zenoh.Config:
    """`config` with Zenoh's shared-memory transport optimization off, for the player's session.

    With it on (the default), a payload above its threshold (3 kB) that goes to a session on the same host is
    placed in this session's shared-memory pool and only a reference is sent. The player exits as soon as it has
    put the last message, and a backlog still waiting for a slow subscriber then refers to memory that is gone:
    it is lost (measured at --speed 0, 1000 x 20 kB to a subscriber taking 2 ms each: about 190 of 1000
    arrived). Copied payloads outlive the player."""
    config.insert_json5("transport/shared_memory/transport_optimization/enabled", "false")
    return config


def drain(session: zenoh.Session, helper: zenoh.Session, timeout_s: float = 60.0) -> bool:
    """Wait until the router has received everything `session` has put (True), so closing it loses nothing in flight.

    A query from `session` to a queryable on a second session `helper` goes through the router on the same link
    and at the same priority as the data, after it: its reply means the router has read everything before it.
    Towards a slow subscriber that backlog then waits in the router and the subscriber; it survives the player only
    because the player's session sends copies, not shared-memory references (`copy_payloads`)."""
    key = f"gpmppi/_replay/drain/{helper.zid()}"
    queryable = helper.declare_queryable(key, lambda query: query.reply(key, b""))
    try:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            replies = session.get(key, timeout=min(5.0, max(0.1, deadline - time.monotonic())),
                                  congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.DATA)
            if any(r.ok is not None for r in replies):
                return True
        return False
    finally:
        queryable.undeclare()
