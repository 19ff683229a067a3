"""Offline conversion of a gpmppi MCAP log to rerun (`gpmppi replay LOG.mcap --rerun save OUT.rrd | spawn |
connect URL | serve`), with no Zenoh: the same message -> rerun mapping as the live viewer service
(`services.view.rerun_map`), fed from the log. Time series go as columns (`send_columns`), so it runs far faster
than real time.

Also runnable on its own: `python -m tools.replay_rerun LOG.mcap OUT.rrd [--keys REGEX] [--exclude REGEX]`.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import sys
import time
from pathlib import Path

MCAP_MAGIC = b"\x89MCAP0\r\n"
MODES = ("save", "spawn", "connect", "serve")
FLUSH_ROWS = 50_000  # buffered time-series rows before they are sent (bounds memory on long logs)
FLUSH_LOG_S = 10.0  # and at least every this much log time: chunks come in time order, as the live viewer's do


class _Notes(logging.Handler):
    """Keeps the MCAP reader's warnings other than skipped messages (a truncated file, a linear scan)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.notes: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        if "that are not gpmppi messages" not in str(record.msg):  # those are counted through `skipped`
            self.notes.append(record.getMessage()[:300])


def _check_file(path: Path) -> None:
    if not path.exists():
        raise FileNotFoundError(f"no MCAP log at {path}: check the path")
    if not path.is_file():
        raise ValueError(f"{path} is not a file; pass a .mcap log")
    with open(path, "rb") as f:
        head = f.read(len(MCAP_MAGIC))
    if not head:
        raise ValueError(f"{path} is empty (0 bytes): nothing to convert")
    if head != MCAP_MAGIC:
        raise ValueError(f"{path} is not an MCAP file (it starts with {head[:8]!r}, not the MCAP magic)")


def _topics(path: Path) -> tuple[list[str] | None, int | None]:
    """The log's topics and first log time from its summary, or (None, None) when it has none (truncated)."""
    from mcap.reader import make_reader

    from services.recording.mcap_io import recording_files

    topics: set[str] = set()
    start: int | None = None
    for part in recording_files(path) or [path]:
        try:
            with open(part, "rb") as f:
                summary = make_reader(f).get_summary()
        except Exception:  # noqa: BLE001 - a truncated part has no summary: filter while reading instead
            return None, None
        if summary is None:
            return None, None
        topics.update(c.topic for c in summary.channels.values())
        stats = summary.statistics
        if stats is not None and stats.message_count:
            start = stats.message_start_time if start is None else min(start, stats.message_start_time)
    return sorted(topics), start


def convert(
    path: Path,
    mode: str,
    target: str | None,
    *,
    start_s: float | None = None,
    end_s: float | None = None,
    keys: str | None = None,
    exclude: str | None = None,
    options: object | None = None,
) -> dict:
    """Convert the log at `path` (and its rotated parts) to rerun.

    mode: 'save' (target: the .rrd path, written whole or not at all), 'spawn' (a local viewer), 'connect'
    (target: a viewer's gRPC URL) or 'serve' (a gRPC server on port target, default 9876; blocks until Ctrl-C
    so viewers can connect).
    start_s / end_s: seconds into the log (log time). keys / exclude: regexes searched in the topic.
    options: a `services.view.rerun_map.ViewOptions` (decimation), default the viewer's defaults.
    Returns {"messages", "log_duration_s", "wall_s"} plus "skipped" (topic -> messages not converted, with a
    reason each in "skipped_reasons") and "output" (save mode)."""
    from services.recording import mcap_io
    from services.view.rerun_map import RerunMapper, ViewOptions
    from services.view.rerun_stream import open_stream

    path = Path(path)
    if mode not in MODES:
        raise ValueError(f"rerun mode {mode!r} is not one of {', '.join(MODES)}")
    if mode == "save" and not target:
        raise ValueError("--rerun save needs an output path, e.g. --rerun save out.rrd")
    if mode == "connect" and not target:
        raise ValueError("--rerun connect needs a viewer URL, e.g. rerun+http://127.0.0.1:9876/proxy")
    try:
        want = re.compile(keys) if keys else None
        drop = re.compile(exclude) if exclude else None
    except re.error as exc:
        raise ValueError(f"bad topic regex ({exc}); --keys and --exclude take Python regular expressions") from exc
    if start_s is not None and end_s is not None and end_s < start_s:
        raise ValueError(f"--end {end_s} s is before --start {start_s} s")
    serve_port = 9876
    if mode == "serve" and target:
        if not target.isdigit() or not 0 < int(target) < 65536:
            raise ValueError(f"--rerun serve takes an optional gRPC port number, not {target!r}")
        serve_port = int(target)
    _check_file(path)

    t0 = time.perf_counter()
    topics, first_ns = _topics(path)
    chosen = None
    if topics is not None:
        chosen = [t for t in topics if (want is None or want.search(t)) and not (drop and drop.search(t))]

    out_path = Path(target) if mode == "save" and target else None
    tmp_path = out_path.with_name(out_path.name + ".part") if out_path is not None else None
    rec = open_stream(mode, str(tmp_path) if tmp_path is not None else target, serve_port, batch_s=2.0)
    mapper = RerunMapper(rec, options if isinstance(options, ViewOptions) else ViewOptions())
    counter = _Notes()
    skipped: dict[str, tuple[int, str]] = {}
    io_log = logging.getLogger(mcap_io.__name__)
    io_log.addHandler(counter)
    messages = 0
    first_seen: int | None = None
    last_seen: int | None = None
    flushed_at: int | None = None
    ok = False
    try:
        for key, log_ns, msg in mcap_io.read_messages(path, chosen, skipped):
            if chosen is None and ((want is not None and not want.search(key)) or (drop and drop.search(key))):
                continue
            if first_ns is None:
                first_ns = log_ns
            if flushed_at is None:
                flushed_at = log_ns
            rel_s = (log_ns - first_ns) / 1e9
            if start_s is not None and rel_s < start_s:
                continue
            if end_s is not None and rel_s > end_s:
                continue
            mapper.log(key, msg, log_ns)
            messages += 1
            first_seen = log_ns if first_seen is None else min(first_seen, log_ns)
            last_seen = log_ns if last_seen is None else max(last_seen, log_ns)
            if mapper.buffered >= FLUSH_ROWS or log_ns - flushed_at >= FLUSH_LOG_S * 1e9:
                mapper.flush()
                flushed_at = log_ns
        mapper.flush()
        rec.flush()
        ok = True
    finally:
        io_log.removeHandler(counter)
        if mode != "serve":
            rec.disconnect()
        if tmp_path is not None:
            if ok:
                os.replace(tmp_path, out_path)  # type: ignore[arg-type]
            else:
                tmp_path.unlink(missing_ok=True)
    result: dict = {
        "messages": messages,
        "log_duration_s": round(((last_seen or 0) - (first_seen or 0)) / 1e9, 3),
        "wall_s": round(time.perf_counter() - t0, 3),
        "skipped": {topic: n for topic, (n, _) in skipped.items()},
        "skipped_reasons": {topic: reason[:200] for topic, (_, reason) in skipped.items()},
    }
    if counter.notes:
        result["notes"] = counter.notes[:10]
    if out_path is not None:
        result["output"] = str(out_path)
    if mode == "serve":
        print("rerun: serving the converted log; Ctrl-C to stop", file=sys.stderr, flush=True)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
        finally:
            rec.disconnect()
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.replay_rerun", description="Convert an MCAP log to .rrd")
    parser.add_argument("log", type=Path, help="the .mcap log (rotated parts are read after it)")
    parser.add_argument("out", help="output .rrd")
    parser.add_argument("--start", type=float, default=None, help="seconds into the log")
    parser.add_argument("--end", type=float, default=None, help="seconds into the log")
    parser.add_argument("--keys", default=None, help="only topics matching this regex")
    parser.add_argument("--exclude", default=None, help="not topics matching this regex")
    args = parser.parse_args(argv)
    try:
        result = convert(args.log, "save", args.out, start_s=args.start, end_s=args.end, keys=args.keys,
                         exclude=args.exclude)  # fmt: skip
    except (FileNotFoundError, ValueError) as exc:
        print(f"replay --rerun: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
