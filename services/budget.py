"""When a run ends: after `total_timesteps` env steps or `train_for_seconds` of training,
whichever binds first, and how far along the run is (what schedules such as learning-rate
annealing and PER's β follow).

The clock is the learner's: it runs from the moment the learner starts its loop (actors
starting up, the replay filling to `learning_starts_fragments` all count) and is carried in its
checkpoints, so a learner restarted after a crash, or a run resumed later, goes on with the time
it had left. Time while no learner runs does not count.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

STEPS, SECONDS = "total_timesteps", "train_for_seconds"


def clock(seconds: float) -> str:
    """Seconds as H:MM:SS (or M:SS under an hour)."""
    seconds = max(0, int(round(seconds)))
    hours, rest = divmod(seconds, 3600)
    return f"{hours}:{rest // 60:02d}:{rest % 60:02d}" if hours else f"{rest // 60}:{rest % 60:02d}"


@dataclass
class Budget:
    """The run's two limits and the training time already spent (by earlier learner
    processes of the same run)."""

    total_timesteps: int
    train_for_seconds: float = 0.0  # 0: no time limit
    spent_before: float = 0.0
    now: Callable[[], float] = time.monotonic
    started: float = field(init=False)

    def __post_init__(self):
        self.started = self.now()

    def restart_clock(self) -> None:
        """Count from now, on top of the `spent_before` seconds (a restored checkpoint's)."""
        self.started = self.now()

    def elapsed(self) -> float:
        """Training seconds of the run so far."""
        return self.spent_before + self.now() - self.started

    def time_left(self) -> float | None:
        """Seconds before the time limit ends the run (None without one)."""
        if self.train_for_seconds <= 0:
            return None
        return max(0.0, self.train_for_seconds - self.elapsed())

    def progress(self, global_step: int) -> float:
        """The fraction of the run done: that of the limit furthest along (the one that will
        bind first, as far as anyone can tell now), in [0, 1]."""
        return self.progress_at(global_step, self.elapsed())

    def progress_at(self, global_step: int, elapsed_s: float) -> float:
        """`progress` at a given step count and training time (a learner group's rank 0's)."""
        done = global_step / self.total_timesteps
        if self.train_for_seconds > 0:
            done = max(done, elapsed_s / self.train_for_seconds)
        return min(1.0, done)

    def reached(self, global_step: int) -> str | None:
        """The limit that has ended the run (STEPS or SECONDS), or None while neither has."""
        if global_step >= self.total_timesteps:
            return STEPS
        if self.train_for_seconds > 0 and self.elapsed() >= self.train_for_seconds:
            return SECONDS
        return None

    def describe(self) -> str:
        """The limits as announced at the start of a run."""
        steps = f"{self.total_timesteps:,} steps"
        if self.train_for_seconds <= 0:
            return steps
        return (f"{steps} or {clock(self.train_for_seconds)} ({self.train_for_seconds:g} s) of "
                "training, whichever comes first")

    def shown(self) -> str:
        """The progress line's part for the time limit ("" without one)."""
        left = self.time_left()
        return "" if left is None else f" | {clock(left)} left"
