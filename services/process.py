"""What every service process does around its work (DESIGN §5): logging and its configuration
at start, one line and exit status 2 for a bad setting, and the stop signal its loops obey."""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import tempfile
import threading
from pathlib import Path

from tpdeb.services.config import resolve
from tpdeb.services.logs import setup_logging


def configure(cls, argv: list[str] | None, prog: str, description: str):
    """The process's configuration resolved (DESIGN §5), logging at its level: messages go
    through logging from the first line, so a refused setting prints like every other."""
    setup_logging()
    config = resolve(cls, argv, prog, description)
    setup_logging(getattr(config, "log_level", "info"))
    return config


def obey_control(sample, stop: StopSignal, log_bad) -> None:
    """A control message heard: the learner's stop broadcast sets `stop`; a bad message is
    logged through `log_bad` (rate-limited) and dropped."""
    from tpdeb.protocol import Control, DecodeError, decode

    try:
        if decode(sample.payload.to_bytes(), Control).command == "stop":
            stop.set("stop message")
    except DecodeError as exc:
        log_bad(exc.kind, f"dropped a bad control message ({exc})")


def actor_id_file(run_id: str) -> Path:
    """Where an actor with `--actor-id auto` notes the id it got, for tpdeb-health (one actor
    per container: the file is the container's)."""
    return Path(tempfile.gettempdir()) / f"tpdeb-{run_id}-actor.id"


def fail(prog: str, exc: Exception) -> int:
    """One line on stderr, exit status 2: how every service refuses bad settings."""
    logging.getLogger(prog).error(f"error: {exc}")
    return 2


class StopSignal:
    """Set by SIGINT/SIGTERM (or by a stop message); services poll or wait on it.

    The signal handler takes no lock: the main thread it interrupts may hold the one the event
    needs — inside a wait, or inside the handler of a first signal when a second comes (an
    orchestrator's SIGTERM and its runner's, a double Ctrl-C) — and would wait for itself
    forever. The handler notes the signal and writes a byte to a pipe; a thread sets the event
    (and calls `on_signal(name)`, e.g. to say so)."""

    NAMES = {signal.SIGINT: "SIGINT", signal.SIGTERM: "SIGTERM"}

    def __init__(self, on_signal=None):
        self.event = threading.Event()
        self._reason = ""
        self.signalled = ""  # the first signal's name; written by the handler only
        self.on_signal = on_signal
        self._wakeup = -1

    def install(self) -> StopSignal:
        read_fd, self._wakeup = os.pipe()
        os.set_blocking(self._wakeup, False)
        threading.Thread(target=self._deliver, args=(read_fd,), daemon=True,
                         name="signals").start()
        for sig in self.NAMES:
            signal.signal(sig, self._on_signal)
        return self

    def _on_signal(self, signum, _frame) -> None:
        if not self.signalled:
            self.signalled = self.NAMES[signum]
        with contextlib.suppress(BlockingIOError):  # a full pipe: a wake-up is pending anyway
            os.write(self._wakeup, b"\0")

    def _deliver(self, read_fd: int) -> None:
        while os.read(read_fd, 1):
            self.set(self.signalled)
            if self.on_signal is not None:
                self.on_signal(self.signalled)

    @property
    def reason(self) -> str:
        return self._reason or self.signalled

    def set(self, reason: str) -> None:
        if not self.event.is_set():
            self._reason = reason
            self.event.set()

    def __bool__(self) -> bool:
        return bool(self.signalled) or self.event.is_set()

    def wait(self, timeout_s: float) -> bool:
        return self.event.wait(timeout_s) or bool(self.signalled)
