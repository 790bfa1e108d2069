"""What the benches read from /proc: the process tree, command lines, resident memory, and which
TPDEB service a process is."""

from __future__ import annotations

import os

SERVICES = ("router", "replay", "learner", "actor", "link", "cluster")


def proc_table() -> dict[int, tuple[int, int]]:
    """pid -> (ppid, start time in clock ticks) of every live process."""
    table = {}
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            with open(f"/proc/{entry.name}/stat") as f:
                stat = f.read()
        except OSError:
            continue
        fields = stat[stat.rfind(")") + 2:].split()
        if fields[0] == "Z":
            continue
        table[int(entry.name)] = (int(fields[1]), int(fields[19]))
    return table


def descendants(root: int, table: dict[int, tuple[int, int]] | None = None) -> list[int]:
    """Every live process below `root` (not `root` itself)."""
    table = proc_table() if table is None else table
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
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().decode(errors="replace").split("\0")
    except OSError:
        return []


def rss_kib(pid: int) -> int | None:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def service_name(argv: list[str]) -> str | None:
    """`actor-0`, `replay`, … from a command line (`tpdeb-x` script or `-m tpdeb.services.x`)."""
    role = None
    for i, arg in enumerate(argv):
        base = os.path.basename(arg)
        if base.startswith("tpdeb-") and base[6:] in SERVICES:
            role = base[6:]
            break
        if arg == "-m" and i + 1 < len(argv) and argv[i + 1].startswith("services."):
            role = argv[i + 1].split(".", 1)[1]
            break
    if role is None:
        return None
    if role == "actor" and "--actor-id" in argv:
        index = argv.index("--actor-id")
        if index + 1 < len(argv):
            return f"actor-{argv[index + 1]}"
    return role
