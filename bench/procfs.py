"""What the benches read about processes (through psutil): the process tree, command lines,
resident memory, and which TPDEB service a process is."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Hashable
from pathlib import Path

import psutil

SERVICES = ("router", "replay", "learner", "actor", "link", "evaluator", "cluster")


def proc_table() -> dict[int, tuple[int, float]]:
    """pid -> (ppid, start time) of every live process (zombies left out)."""
    table = {}
    for proc in psutil.process_iter(["ppid", "create_time", "status"]):
        info = proc.info
        if info["status"] != psutil.STATUS_ZOMBIE and info["ppid"] is not None:
            table[proc.pid] = (info["ppid"], info["create_time"])
    return table


def descendants(root: int, table: dict[int, tuple[int, float]] | None = None) -> list[int]:
    """Every live process below `root` (not `root` itself)."""
    if table is None:
        try:
            return [p.pid for p in psutil.Process(root).children(recursive=True)]
        except psutil.Error:
            return []
    children: dict[int, list[int]] = {}
    for pid, (ppid, _) in table.items():
        children.setdefault(ppid, []).append(pid)
    out, todo = [], list(children.get(root, []))
    while todo:
        pid = todo.pop()
        out.append(pid)
        todo.extend(children.get(pid, []))
    return out


def cmdline(pid: int) -> list[str]:
    try:
        return psutil.Process(pid).cmdline()
    except psutil.Error:
        return []


def rss_kib(pid: int) -> int | None:
    try:
        return psutil.Process(pid).memory_info().rss // 1024
    except psutil.Error:
        return None


def service_name(argv: list[str]) -> str | None:
    """`actor-0`, `replay`, … from a command line (`tpdeb-x` script or `-m tpdeb.services.x`)."""
    role = None
    for i, arg in enumerate(argv):
        base = os.path.basename(arg)
        if base.startswith("tpdeb-") and base[6:] in SERVICES:
            role = base[6:]
            break
        if arg == "-m" and i + 1 < len(argv) and argv[i + 1].startswith("tpdeb.services."):
            role = argv[i + 1].rsplit(".", 1)[1]
            break
    if role is None:
        return None
    if role == "actor" and "--actor-id" in argv:
        index = argv.index("--actor-id")
        if index + 1 < len(argv):
            return f"actor-{argv[index + 1]}"
    if "--config" in argv[:-1]:  # tpdeb-cluster starts each with run/config/{name}.toml
        stem = Path(argv[argv.index("--config") + 1]).stem
        if stem.startswith(role):
            return stem
    return role


class CpuSampler(threading.Thread):
    """CPU seconds (user + system) of a changing set of processes, read every `period_s`:
    `targets()` names them ({key: pid}) at each reading. `last` keeps each key's latest reading
    (it stands once the process has exited); `per_second` gives rates over a window."""

    def __init__(self, targets: Callable[[], dict[Hashable, int]], period_s: float):
        super().__init__(daemon=True)
        self.targets, self.period_s, self.done = targets, period_s, threading.Event()
        self.samples: list[tuple[float, dict]] = []
        self.last: dict = {}

    def run(self) -> None:
        while not self.done.wait(self.period_s):
            row = {}
            for key, pid in self.targets().items():
                try:
                    times = psutil.Process(pid).cpu_times()
                except psutil.Error:
                    continue
                row[key] = times.user + times.system
            self.last.update(row)
            self.samples.append((time.time(), row))

    def stop(self) -> None:
        self.done.set()
        self.join(5)

    def per_second(self, start: float, end: float) -> dict:
        """Each key's CPU seconds per second between the first and last readings inside
        [start, end] (wall-clock), for the keys read at both."""
        inside = [s for s in self.samples if start <= s[0] <= end]
        if len(inside) < 2:
            return {}
        (t0, c0), (t1, c1) = inside[0], inside[-1]
        return {k: (c1[k] - c0[k]) / (t1 - t0) for k in c0.keys() & c1.keys()}
