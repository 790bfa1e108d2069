"""What the launcher shows: service health from liveliness tokens and stats, and one status
line that fits the terminal."""

from __future__ import annotations

import math
import shutil
import sys
import threading
import time
from dataclasses import dataclass

import zenoh

from tpdeb.protocol import DecodeError, Stats, decode
from tpdeb.services.budget import clock
from tpdeb.services.launcher import PROG

STALE_INTERVALS = 3  # stats older than this many intervals mark a service stale



@dataclass
class ServiceView:
    """What the cluster knows of one process, for the status line."""

    name: str
    role: str
    ident: str | None  # stats/liveliness ident; None: publishes neither (the router)
    has_token: bool
    running: bool
    restarts: int = 0
    stats_interval_s: float = 1.0
    started_at: float = 0.0  # monotonic time its current process started


class Health:
    """Which services are alive, from their liveliness tokens (DESIGN §3) and the age of their
    stats; rendered as the `up: …` part of the status line. Thread-safe: Zenoh callbacks feed
    it, the supervisor reads it."""

    def __init__(self):
        self.alive: set[tuple[str, str]] = set()
        self.seen: set[tuple[str, str]] = set()  # had a token since its last (re)start
        self.stats_at: dict[tuple[str, str], float] = {}
        self.lock = threading.Lock()

    def on_token(self, sample) -> None:
        """Liveliness subscriber callback: …/alive/{role}/{ident} appears (PUT) or goes."""
        role, _, ident = str(sample.key_expr).rpartition("/alive/")[2].partition("/")
        self.token(role, ident, sample.kind == zenoh.SampleKind.PUT)

    def token(self, role: str, ident: str, alive: bool) -> None:
        with self.lock:
            (self.alive.add if alive else self.alive.discard)((role, ident))
            if alive:
                self.seen.add((role, ident))

    def saw_stats(self, role: str, ident: str, now: float) -> None:
        with self.lock:
            self.stats_at[(role, ident)] = now

    def restarted(self, role: str, ident: str | None) -> None:
        """A restarted process starts fresh: its predecessor's stats do not make it stale."""
        with self.lock:
            self.stats_at.pop((role, ident), None)
            self.seen.discard((role, ident))

    def silent(self, views: list[ServiceView], now: float, intervals: float,
               start_grace_s: float) -> list[tuple[ServiceView, float, float]]:
        """Running services whose stats have stopped: (view, seconds silent, bound). The bound
        is `intervals` of the service's stats interval; before a process's first stats, its
        start counts, with at least `start_grace_s` (start-up, a restore)."""
        out = []
        with self.lock:
            for v in views:
                if not v.running or v.ident is None or not intervals:
                    continue
                bound = intervals * v.stats_interval_s
                seen = self.stats_at.get((v.role, v.ident))
                if seen is None:
                    seen, bound = v.started_at, max(bound, start_grace_s)
                if now - seen > bound:
                    out.append((v, now - seen, bound))
        return out

    def summary(self, views: list[ServiceView], now: float) -> str:
        up, starting, unreachable, down, stale = [], [], [], [], []
        actors = actors_up = 0
        with self.lock:
            for v in views:
                key = (v.role, v.ident)
                # A token gone while the process runs: the network lost it, or it is stopping.
                state = ("down" if not v.running else "up" if not v.has_token or
                         key in self.alive else "unreachable" if key in self.seen else "starting")
                seen = self.stats_at.get(key)
                if state == "up" and seen is not None and \
                        now - seen > STALE_INTERVALS * v.stats_interval_s:
                    stale.append(f"{v.name} {now - seen:.0f} s")
                if v.role == "actor":
                    actors, actors_up = actors + 1, actors_up + (state == "up")
                else:
                    {"up": up, "starting": starting, "unreachable": unreachable,
                     "down": down}[state].append(v.name)
        if actors:
            up.append(f"actors {actors_up}/{actors}")
        parts = [f"up: {' '.join(up) or 'none'}"]
        parts += [f"{label}: {' '.join(names)}" for label, names in
                  (("starting", starting), ("unreachable", unreachable), ("down", down)) if names]
        if stale:
            parts.append(f"stale: {', '.join(stale)}")
        restarts = [f"{v.name} {v.restarts}" for v in views if v.restarts]
        if restarts:
            parts.append(f"restarts: {', '.join(restarts)}")
        return " | ".join(parts)


class Display:
    """Latest stats per service, rendered as one status line (redrawn in place on a TTY)."""

    def __init__(self, out=sys.stdout):
        self.out = out
        self.tty = out.isatty()
        self.latest: dict[tuple[str, str], dict] = {}
        self.lock = threading.Lock()
        self.last_plain = 0.0
        self.status = ""

    def on_stats(self, sample) -> Stats | None:
        try:
            stats = decode(sample.payload.to_bytes(), Stats)
        except DecodeError:
            return None
        with self.lock:
            self.latest[(stats.role, stats.ident)] = stats.values
        return stats

    def parts(self, health: str) -> list[tuple[str, int]]:
        """The status line's parts, training progress from the latest stats, then `health`
        (Health.summary), each with its rank: where the line is wider than the terminal the
        highest ranks go first (see `fit`)."""
        with self.lock:
            learner = self.latest.get(("learner", "0"), {})
            replays = [v for (role, _), v in self.latest.items() if role == "replay"]  # shards
            link = self.latest.get(("link", "0"))
        if not learner:
            return [("starting…", 0), (health, 1)]
        step, total = int(learner.get("global_step", 0)), int(learner.get("total_timesteps", 0))
        pct = f" ({100 * step / total:.0f}%)" if total else ""
        fill = (sum(int(r.get("prioritized_items", 0)) for r in replays),
                sum(int(r.get("uniform_steps", 0)) for r in replays))
        parts = [(f"{step:,}/{total:,} steps{pct}", 0),
                 (f"{learner.get('sps', 0):,.0f} SPS", 2),
                 (f"return {learner.get('mean_return', math.nan):,.1f}", 1),
                 (f"replay {fill[0]} fragments + {fill[1]:,} steps", 7),
                 (f"lag {learner.get('param_version_lag', math.nan):.1f} versions", 6),
                 (f"{int(learner.get('updates', 0)):,} updates", 5)]
        if "time_left_s" in learner:
            parts.insert(1, (f"{clock(learner['time_left_s'])} left", 0))
        if link:
            parts.append((f"link ↑{link.get('up_bytes_per_s', 0) / 1e3:,.0f} "
                          f"↓{link.get('down_bytes_per_s', 0) / 1e3:,.0f} kB/s", 4))
        return [*parts, (health, 3)]

    def echo(self, text: str) -> None:
        with self.lock:
            if self.tty and self.status:
                self.out.write("\r\033[K")
            self.out.write(text + "\n")
            if self.tty and self.status:
                self.out.write(self.status)
            self.out.flush()

    def show(self, parts: list[tuple[str, int]], plain_interval_s: float = 10.0) -> None:
        """On a terminal: redraw the line in place, fitted to the terminal's width now (a line
        that wraps cannot be redrawn: each redraw would add rows). Elsewhere (a log file): the
        whole line every `plain_interval_s`."""
        if self.tty:
            # One column spare: writing the last one moves some terminals to the next row.
            width = shutil.get_terminal_size((100, 24)).columns - 1
            with self.lock:
                self.status = fit([(f"[{PROG}]", -1), *parts], width, " ")
                self.out.write("\r\033[K" + self.status)
                self.out.flush()
        elif time.monotonic() - self.last_plain >= plain_interval_s:
            self.last_plain = time.monotonic()
            self.echo(f"[{PROG}] " + " | ".join(text for text, _ in parts))


def fit(parts: list[tuple[str, int]], width: int, first_sep: str = " | ") -> str:
    """Join (text, rank) parts with " | " (`first_sep` after the first), dropping the highest
    ranks until the line fits in `width` columns, then cutting it with "…"."""
    def join(kept):
        return (kept[0][0] + first_sep + " | ".join(t for t, _ in kept[1:])) if len(kept) > 1 \
            else kept[0][0]

    kept = list(parts)
    while len(kept) > 2 and len(join(kept)) > width:
        kept.remove(max(kept, key=lambda part: part[1]))
    line = join(kept)
    return line if len(line) <= width else line[:max(width - 1, 0)] + "…"
