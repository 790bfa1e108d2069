"""Logging for every process: the standard library's, one line per record as `prog: message`,
information on stdout, warnings and errors on stderr, the level from `--log-level` (or
`TPDEB_LOG_LEVEL`). What a hostile or broken peer can make a service say many times a second —
a bad message dropped, a resend — goes through `rate_limited`: at most one line per kind and
interval, with a count of what was held back.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections.abc import Callable

LEVELS = ("debug", "info", "warning", "error")
_FORMAT = "%(name)s: %(message)s"


class _Below(logging.Filter):
    def __init__(self, level: int):
        super().__init__()
        self.level = level

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno < self.level


class _Console(logging.StreamHandler):
    """A handler on sys.stdout or sys.stderr as they are when a record is written (not when the
    handler was made), so that a redirected stream still gets the lines."""

    def __init__(self, which: str):
        self.which = which
        super().__init__()

    @property
    def stream(self):
        return getattr(sys, self.which)

    @stream.setter
    def stream(self, _value) -> None:
        pass


def setup_logging(level: str = "info") -> None:
    """This process's handlers (from main; again to change the level): INFO and DEBUG to
    stdout, WARNING and above to stderr, each record flushed as it is written. Handlers others
    installed on the root logger stay."""
    if level not in LEVELS:
        raise ValueError(f"log level {level!r}: expected one of {', '.join(LEVELS)}")
    root = logging.getLogger()
    for handler in [h for h in root.handlers if isinstance(h, _Console)]:
        root.removeHandler(handler)
    out = _Console("stdout")
    out.addFilter(_Below(logging.WARNING))
    err = _Console("stderr")
    err.setLevel(logging.WARNING)
    for handler in (out, err):
        handler.setFormatter(logging.Formatter(_FORMAT))
        root.addHandler(handler)
    root.setLevel(level.upper())


class RateLimit(logging.Filter):
    """Passes a record that carries `extra={"kind": …}` at most once per `interval_s` per kind;
    the next one that passes says how many were held back. Records without a kind pass."""

    def __init__(self, interval_s: float = 5.0, clock: Callable[[], float] = time.monotonic):
        super().__init__()
        self.interval_s, self.clock = interval_s, clock
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}
        self._lock = threading.Lock()

    def filter(self, record: logging.LogRecord) -> bool:
        kind = getattr(record, "kind", None)
        if kind is None:
            return True
        now = self.clock()
        with self._lock:
            if now - self._last.get(kind, -1e18) < self.interval_s:
                self._held[kind] = self._held.get(kind, 0) + 1
                return False
            self._last[kind] = now
            held = self._held.pop(kind, 0)
        if held:
            record.msg = f"{record.getMessage()} (+{held} more since the last report)"
            record.args = ()
        return True


def rate_limited(log: logging.Logger, interval_s: float = 5.0) -> Callable[[str, str], None]:
    """A `warn(kind, line)` for `log` whose lines pass `RateLimit` (one filter per call)."""
    limit = RateLimit(interval_s)

    def warn(kind: str, line: str) -> None:
        record = log.makeRecord(log.name, logging.WARNING, "", 0, line, (), None,
                                extra={"kind": kind})
        if log.isEnabledFor(logging.WARNING) and limit.filter(record):
            log.handle(record)

    return warn
