"""Run-directory metrics: one JSON object per line in metrics.jsonl plus TensorBoard events
(tensorboardX), both keyed by `global_step` (environment steps), with CleanRL's tag names."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

FLUSH_S = 10.0  # TensorBoard events reach the disk at least this often


def hyperparameter_table(config) -> str:
    """The configuration as a markdown table (TensorBoard's text tab), as CleanRL logs it."""
    rows = "\n".join(f"|{k}|{v}|" for k, v in dataclasses.asdict(config).items())
    return f"|param|value|\n|-|-|\n{rows}"


class MetricsWriter:
    """Writes metrics.jsonl and TensorBoard events. Only the processes that train write them
    (the learner, tpdeb-train): tensorboardX is imported here, not at module level, because it
    loads torch, and tools that only read metrics (tpdeb-plot) must not."""

    def __init__(self, run_dir: str | Path):
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        path = self.run_dir / "metrics.jsonl"
        _drop_torn_line(path)
        # Append: a restarted (resumed) process continues the file its predecessor wrote.
        self._jsonl = open(path, "a")  # noqa: SIM115
        from tensorboardX import SummaryWriter

        self._events = SummaryWriter(str(self.run_dir), flush_secs=FLUSH_S)

    def log(self, global_step: int, values: dict[str, float]) -> None:
        clean = {k: float(v) for k, v in values.items() if v is not None and math.isfinite(v)}
        if not clean:
            return
        self._jsonl.write(json.dumps({"global_step": int(global_step), **clean}) + "\n")
        for tag, value in clean.items():
            self._events.add_scalar(tag, value, int(global_step))

    def text(self, tag: str, text: str) -> None:
        self._events.add_text(tag, text)

    def flush(self) -> None:
        self._jsonl.flush()
        self._events.flush()

    def close(self) -> None:
        self.flush()
        self._jsonl.close()
        self._events.close()


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
