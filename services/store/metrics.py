"""Run-directory metrics: one JSON object per line in metrics.jsonl plus TensorBoard events
(tensorboardX), both keyed by `global_step` (environment steps), with CleanRL's tag names."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import socket
import struct
import time
from pathlib import Path

from tpdeb.services.store.diskio import AppendFile, DiskGuard, write_atomic

FLUSH_ROWS = 256  # rows held in memory at most between two flushes


def hyperparameter_table(config) -> str:
    """The configuration as a markdown table (TensorBoard's text tab), as CleanRL logs it."""
    rows = "\n".join(f"|{k}|{v}|" for k, v in dataclasses.asdict(config).items())
    return f"|param|value|\n|-|-|\n{rows}"


class MetricsWriter:
    """Writes metrics.jsonl and TensorBoard events. Only the processes that train write them
    (the learner, tpdeb-train): tensorboardX is imported here, not at module level, because it
    loads torch, and tools that only read metrics (tpdeb-plot) must not.

    Rows and events are held in memory and appended at `flush` (and every `FLUSH_ROWS` rows),
    each file by whole writes (`AppendFile`): a full disk leaves no half line or half record,
    and costs the rows written meanwhile, said once per outage (`DiskGuard`), never the run.
    The events are written here, not by tensorboardX's writer thread, which dies on the first
    refused write and then blocks its caller for good once its queue is full."""

    def __init__(self, run_dir: str | Path, log: logging.Logger | None = None,
                 resume_step: int | None = None):
        """`resume_step`: the global step a resumed run continues from. The rows its
        predecessor logged after that step (training lost with it) are dropped, the events go on
        in the run's newest events file, and a session-start event at that step tells
        TensorBoard to drop its later ones: both files rise monotonically, as one run."""
        from tensorboardX.crc32c import crc32c
        from tensorboardX.proto.event_pb2 import Event, SessionLog
        from tensorboardX.proto.summary_pb2 import Summary

        self._crc32c, self._Event, self._Summary = crc32c, Event, Summary
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        log = log or logging.getLogger("tpdeb")
        path = self.run_dir / "metrics.jsonl"
        _drop_torn_line(path)
        if resume_step is not None:
            _drop_rows_after(path, resume_step)
        # Append: a restarted (resumed) process continues the file its predecessor wrote.
        self._jsonl = AppendFile(path)
        earlier = sorted(self.run_dir.glob("events.out.tfevents.*"), key=os.path.getmtime)
        self._events_path = earlier[-1] if resume_step is not None and earlier else (
            self.run_dir / f"events.out.tfevents.{int(time.time())}.{socket.gethostname()}."
                           f"{os.getpid()}")
        self._events_file: AppendFile | None = None
        self._rows: list[str] = []
        self._events: list[bytes] = []
        if resume_step is not None:
            self._events.append(self._record(Event(
                wall_time=time.time(), step=int(resume_step),
                session_log=SessionLog(status=SessionLog.START))))
        self.rows_guard = DiskGuard("metrics rows", path, log)
        self.events_guard = DiskGuard("TensorBoard events", self._events_path, log)

    def log(self, global_step: int, values: dict[str, float]) -> None:
        clean = {k: float(v) for k, v in values.items() if v is not None and math.isfinite(v)}
        if not clean:
            return
        self._rows.append(json.dumps({"global_step": int(global_step), **clean}) + "\n")
        summary = self._Summary(value=[self._Summary.Value(tag=tag, simple_value=value)
                                       for tag, value in clean.items()])
        self._events.append(self._record(self._Event(wall_time=time.time(),
                                                     step=int(global_step), summary=summary)))
        if len(self._rows) >= FLUSH_ROWS:
            self.flush()

    def text(self, tag: str, text: str) -> None:
        from tensorboardX.summary import text as text_summary

        self._events.append(self._record(self._Event(wall_time=time.time(),
                                                     summary=text_summary(tag, text))))

    def _record(self, event) -> bytes:
        """One TFRecord: length, its masked CRC-32C, the event, the event's masked CRC-32C."""
        data = event.SerializeToString()
        header = struct.pack("<Q", len(data))
        return (header + struct.pack("<I", _masked(self._crc32c(header))) + data
                + struct.pack("<I", _masked(self._crc32c(data))))

    def flush(self) -> None:
        rows, self._rows = "".join(self._rows).encode(), []
        events, self._events = b"".join(self._events), []
        if rows:
            self.rows_guard.attempt(lambda: self._jsonl.append(rows))
        if events:
            self.events_guard.attempt(lambda: self._append_events(events))

    def _append_events(self, data: bytes) -> None:
        if self._events_file is None:
            self._events_file = AppendFile(self._events_path)
        if self._events_file.path.stat().st_size == 0:  # a new file starts with its version
            data = self._record(self._Event(wall_time=time.time(),
                                            file_version="brain.Event:2")) + data
        self._events_file.append(data)

    def close(self) -> None:
        self.flush()
        self._jsonl.close()
        if self._events_file is not None:
            self._events_file.close()


def _masked(crc: int) -> int:
    return (((crc >> 15) | (crc << 17)) + 0xA282EAD8) & 0xFFFFFFFF


def _drop_torn_line(path: Path) -> None:
    """A process killed mid-write can leave half a line at the end (the buffer flushes in
    blocks, not lines); cut it so the next process's first line starts on a line of its own."""
    if not path.is_file():
        return
    with open(path, "rb+") as f:
        size = f.seek(0, 2)
        if size == 0:
            return
        f.seek(size - 1)
        if f.read(1) == b"\n":
            return
        tail = min(size, 1 << 20)
        f.seek(size - tail)
        end = f.read(tail).rfind(b"\n")
        f.truncate(size - tail + end + 1 if end >= 0 else (0 if tail == size else size))


def _drop_rows_after(path: Path, step: int) -> None:
    """Rewrite metrics.jsonl without the rows past `step` (atomically; untouched if none)."""
    if not path.is_file():
        return
    def step_of(row: bytes) -> int:
        try:
            return int(json.loads(row).get("global_step", 0))
        except (ValueError, AttributeError):
            return 0

    rows = path.read_bytes().splitlines(keepends=True)
    kept = [r for r in rows if step_of(r) <= step]
    if len(kept) < len(rows):
        write_atomic(path, lambda f: f.write(b"".join(kept)))


def read_metrics(path: str | Path) -> list[dict]:
    """The rows of a metrics.jsonl; a torn last line (a run killed mid-write) ends the list."""
    rows = []
    with open(path) as f:
        for line in f:
            if not line.strip():
                continue
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:
                break
    return rows
