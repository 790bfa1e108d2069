"""Writing to a disk that may refuse: files that grow only by whole writes, and a guard that turns
a refused write (ENOSPC, EDQUOT, EIO, ...) into one line and a later retry instead of a dead
writer.

A long run meets a full disk sooner or later (a neighbour's job, a forgotten dump). What the
run writes besides its checkpoints — metrics rows, TensorBoard events — is worth less than the
training, so a writer that cannot write says so once with the path, goes on without writing,
tries again after `retry_s`, and says so when the disk takes writes again.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path


class AppendFile:
    """A file that grows only by whole writes: a write the disk refuses part-way is cut back
    off, so the file never ends in half a line or half a record."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)

    def append(self, data: bytes, sync: bool = False) -> None:
        size = os.fstat(self._fd).st_size
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(self._fd, view):]
            if sync:
                os.fsync(self._fd)
        except OSError:
            with contextlib.suppress(OSError):
                os.ftruncate(self._fd, size)
            raise

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


class DiskGuard:
    """Runs a write; if the disk refuses it, says so once (what, the path, why), skips the
    writes that come for `retry_s`, then tries again; says when a write works again and how
    many were skipped. `clock` is injectable for tests."""

    def __init__(self, what: str, path: str | Path, log: logging.Logger, retry_s: float = 5.0,
                 consequence: str = "training goes on without it",
                 clock: Callable[[], float] = time.monotonic):
        self.what, self.path, self.log, self.retry_s, self.clock = what, path, log, retry_s, clock
        self.consequence = consequence
        self.failing = False
        self.skipped = 0
        self.failures = 0
        self._next_try = 0.0

    def attempt(self, write: Callable[[], None]) -> bool:
        """True when `write` ran and succeeded; False when it was refused or skipped."""
        if self.failing and self.clock() < self._next_try:
            self.skipped += 1
            return False
        try:
            write()
        except OSError as exc:
            self.failures += 1
            self.skipped += 1
            if not self.failing:
                retry = f", trying again every {self.retry_s:g} s" if self.retry_s else ""
                self.log.warning(f"{self.what} not written: {self.path}: "
                                 f"{exc.strerror or exc}; {self.consequence}{retry}")
            self.failing = True
            self._next_try = self.clock() + self.retry_s
            return False
        if self.failing:
            self.log.info(f"{self.what}: {self.path} takes writes again ({self.skipped} "
                          f"skipped meanwhile)")
            self.failing, self.skipped = False, 0
        return True


def fsync_dir(path: Path) -> None:
    """Make a rename or a new file in `path` durable: the directory entry must reach the disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomic(path: str | Path, write: Callable) -> Path:
    """`write(file)` fills a temp file beside `path`, which then replaces `path` in one rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)
    return path


class OutputError(ValueError):
    """A path that cannot be written: one line with the flag or setting, the path and why."""

    @classmethod
    def of(cls, what: str, path: str | Path, exc: OSError) -> OutputError:
        return cls(f"{what} {path}: cannot write there ({exc.strerror or exc})")


def writable_path(path: str | Path, what: str, directory: bool = False) -> Path:
    """`path` once it can be written — a file (`directory` False) or a directory to write in —
    its missing directories made in the nearest one that exists, which must take a new file;
    else OutputError naming `what`. Commands check before their work, so a bad path costs no
    run, rollout or read and ends in one line; nothing is left behind."""
    path = Path(path)
    nearest = next(p for p in (path, *path.parents) if p.exists() or p == p.parent)
    try:
        if nearest == path and path.is_dir() != directory:
            code = errno.EISDIR if path.is_dir() else errno.ENOTDIR
            raise OSError(code, os.strerror(code))
        if not nearest.is_dir():
            raise OutputError(f"{what} {path}: cannot write there ({nearest} is a file, not a "
                              "directory)")
        if nearest == path and not directory:
            with path.open("r+b"):
                pass
        else:  # writing in a directory is the one test that holds for permissions, read-only
            with tempfile.TemporaryFile(dir=nearest):  # mounts and root alike
                pass
    except OSError as exc:
        where = "" if nearest in (path, path.parent) else f" (in {nearest})"
        raise OutputError(f"{what} {path}: cannot write there{where} "
                          f"({exc.strerror or exc})") from None
    return path
