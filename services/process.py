"""What every service process does around its work (DESIGN §5): logging and its configuration
at start, one line and exit status 2 for a bad setting, and the stop signal its loops obey."""

from __future__ import annotations

import logging
import signal
import threading

from tpdeb.services.config import resolve
from tpdeb.services.logs import setup_logging


def configure(cls, argv: list[str] | None, prog: str, description: str):
    """The process's configuration resolved (DESIGN §5), logging at its level: messages go
    through logging from the first line, so a refused setting prints like every other."""
    setup_logging()
    config = resolve(cls, argv, prog, description)
    setup_logging(getattr(config, "log_level", "info"))
    return config


def fail(prog: str, exc: Exception) -> int:
    """One line on stderr, exit status 2: how every service refuses bad settings."""
    logging.getLogger(prog).error(f"error: {exc}")
    return 2


class StopSignal:
    """Set by SIGINT/SIGTERM (or by a stop message); services poll or wait on it."""

    def __init__(self):
        self.event = threading.Event()
        self.reason = ""

    def install(self) -> StopSignal:
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._on_signal)
        return self

    def _on_signal(self, signum, _frame) -> None:
        self.set(signal.Signals(signum).name)

    def set(self, reason: str) -> None:
        if not self.event.is_set():
            self.reason = reason
            self.event.set()

    def __bool__(self) -> bool:
        return self.event.is_set()

    def wait(self, timeout_s: float) -> bool:
        return self.event.wait(timeout_s)
