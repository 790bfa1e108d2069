"""Restart policies of the launcher's services and the crash-loop rule (DESIGN §5)."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from tpdeb.services.config import ConfigError

RESTART_KEYS = ("restart_backoff_s", "restart_reset_s", "max_restarts", "crash_loop_window_s")
RESTART_MODES = ("no", "on-failure", "always")
MAX_BACKOFF_S = 30.0



@dataclass(frozen=True)
class RestartPolicy:
    """Compose's vocabulary: "no", "on-failure" (a non-zero exit), "on-failure:N" (at most N
    restarts), "always" (any exit, unless the run is ending)."""

    mode: str = "on-failure"
    limit: int | None = None

    @classmethod
    def parse(cls, value, where: str) -> RestartPolicy:
        mode, sep, count = value.partition(":") if isinstance(value, str) else ("", "", "")
        if mode in RESTART_MODES and not sep:
            return cls(mode)
        if mode == "on-failure" and count.isdigit():
            return cls(mode, int(count))
        raise ConfigError(f"{where}: restart={value!r} is not a restart policy; use \"no\", "
                          "\"on-failure\", \"on-failure:N\" (at most N restarts) or \"always\"")

    def restarts_after(self, code: int) -> bool:
        return self.mode == "always" or (self.mode == "on-failure" and code != 0)

    def __str__(self) -> str:
        return self.mode if self.limit is None else f"{self.mode}:{self.limit}"


@dataclass(frozen=True)
class RestartSettings:
    """[cluster] back-off and crash-loop limits, shared by every service."""

    backoff_s: float = 1.0  # first delay; doubles per consecutive failure up to MAX_BACKOFF_S
    reset_after_s: float = 60.0  # a process up this long starts again from `backoff_s`
    max_restarts: int = 5  # more restarts of one process within `window_s` is a crash loop
    window_s: float = 120.0
    max_backoff_s: float = MAX_BACKOFF_S

    @classmethod
    def from_section(cls, cluster: dict, path) -> RestartSettings:
        values = {}
        for key, name in zip(RESTART_KEYS, ("backoff_s", "reset_after_s", "max_restarts",
                                            "window_s"), strict=True):
            if key not in cluster:
                continue
            value, integral = cluster[key], name == "max_restarts"
            number = not isinstance(value, bool) and isinstance(value, (int, float))
            if not number or (integral and not (value >= 0 and float(value).is_integer())) or (
                    not integral and not 0 < value < math.inf):
                raise ConfigError(f"{path} [cluster] {key}={value!r}: expected "
                                  f"{'an integer ≥ 0' if integral else 'a number of seconds > 0'}")
            values[name] = int(value) if integral else float(value)
        return cls(**values)


@dataclass
class Verdict:
    """What to do about one exit: "restart" after `delay_s`, "stay_down", or "crash_loop"."""

    action: str
    restarts: int  # restarts so far, this one included
    delay_s: float = 0.0
    reason: str = ""


class RestartTracker:
    """When one service process starts again after it exits. Pure: the clock is passed in.

    Back-off doubles per consecutive failure from `backoff_s` up to `max_backoff_s`, and starts
    over once the process has stayed up `reset_after_s`. More than `max_restarts` restarts within
    `window_s`, or an on-failure:N limit reached, is a crash loop: restarting again would only
    hide a fault that needs a person."""

    def __init__(self, policy: RestartPolicy, settings: RestartSettings):
        self.policy, self.settings = policy, settings
        self.restarts = 0
        self.consecutive = 0
        self.recent: deque[float] = deque()  # times of restarts within the window
        self.started_at: float | None = None

    def started(self, now: float) -> None:
        self.started_at = now

    def exited(self, code: int, now: float) -> Verdict:
        s = self.settings
        if not self.policy.restarts_after(code):
            return Verdict("stay_down", self.restarts)
        if self.started_at is not None and now - self.started_at >= s.reset_after_s:
            self.consecutive = 0
        while self.recent and now - self.recent[0] > s.window_s:
            self.recent.popleft()
        if self.policy.limit is not None and self.restarts >= self.policy.limit:
            return Verdict("crash_loop", self.restarts, reason=f'restart = "{self.policy}"')
        if len(self.recent) >= s.max_restarts:
            return Verdict("crash_loop", self.restarts,
                           reason=f"max_restarts = {s.max_restarts} within crash_loop_window_s "
                                  f"= {s.window_s:g} s")
        delay_s = min(s.backoff_s * 2 ** self.consecutive, s.max_backoff_s)
        self.consecutive += 1
        self.restarts += 1
        self.recent.append(now)
        return Verdict("restart", self.restarts, delay_s)
