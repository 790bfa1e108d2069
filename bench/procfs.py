"""What the benches read about processes (through psutil): the process tree, command lines,
resident memory, and which TPDEB service a process is."""

from __future__ import annotations

import os

import psutil

SERVICES = ("router", "replay", "learner", "actor", "link", "cluster")


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
    return role
