"""One supervised service process: started in its own process group, logged line by line with
a prefix, stopped by SIGTERM then SIGKILL, restarted by its policy."""

from __future__ import annotations

import contextlib
import ctypes
import os
import shutil
import signal
import subprocess
import sys
import threading
from pathlib import Path

from tpdeb.services.config import ConfigError
from tpdeb.services.launcher.restart import RestartTracker
from tpdeb.services.launcher.status import ServiceView


def resolve_command(command: str) -> list[str]:
    """`tpdeb-x` next to this interpreter first (a venv needs no activation), then PATH."""
    local = Path(sys.executable).parent / command
    if local.exists():
        return [str(local)]
    found = shutil.which(command)
    if found is None:
        raise ConfigError(f"command {command!r} not found (is the package installed?)")
    return [found]


def _die_with_parent() -> None:
    # Children must not outlive a cluster that is killed with SIGKILL.
    with contextlib.suppress(Exception):
        ctypes.CDLL("libc.so.6").prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


class RunEnded(Exception):
    """The run must end with this exit status (the reason has been shown already)."""

    def __init__(self, code: int):
        super().__init__(code)
        self.code = code


class Child:
    """One service process slot: its command, log file and restart book-keeping, the current
    process, and the thread that prefixes its output. A restart starts a new process with the
    same argv that appends to the same log."""

    def __init__(self, name: str, role: str, argv: list[str], env: dict, log_path: Path, echo,
                 tracker: RestartTracker, ident: str | None = None, has_token: bool = True,
                 stats_interval_s: float = 1.0):
        self.name, self.role, self.argv, self.env = name, role, argv, env
        self.log_path, self.echo, self.tracker = log_path, echo, tracker
        self.ident = ident  # its stats (and liveliness token) are {role}/{ident}; None: none
        self.has_token = has_token
        self.stats_interval_s = stats_interval_s
        self.proc: subprocess.Popen | None = None
        self.reader: threading.Thread | None = None
        self.restart_at: float | None = None  # monotonic time a scheduled restart is due
        self.last_code: int | None = None
        self.reported = False  # the current process's exit was handed to the supervisor
        self.started_at = 0.0
        self.hung = False  # the current process was killed as hung

    def start(self, now: float) -> None:
        log = self.log_path.open("a", buffering=1)
        if self.tracker.restarts:
            log.write(f"--- restart #{self.tracker.restarts} (exit code {self.last_code}) ---\n")
        self.proc = subprocess.Popen(
            self.argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL, env=self.env, start_new_session=True,
            preexec_fn=_die_with_parent, text=True, bufsize=1)
        self.reader = threading.Thread(target=self._pump, args=(self.proc, log), daemon=True)
        self.reader.start()
        self.tracker.started(now)
        self.restart_at, self.reported, self.started_at, self.hung = None, False, now, False

    def _pump(self, proc: subprocess.Popen, log) -> None:
        for line in proc.stdout:
            log.write(line)
            self.echo(f"[{self.name}] {line.rstrip()}")
        log.close()

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def poll_exit(self) -> int | None:
        """The current process's exit code, returned once, when it has ended."""
        if self.proc is None or self.reported or self.proc.poll() is None:
            return None
        self.reported, self.last_code = True, self.proc.returncode
        self.reader.join(timeout=5)  # its last words are in the log before anyone reads it
        return self.last_code

    def tail(self, lines: int = 3) -> list[str]:
        """The last lines of the log (read from its end: logs of long runs are large)."""
        try:
            with self.log_path.open("rb") as f:
                f.seek(max(0, f.seek(0, os.SEEK_END) - 16384))
                return f.read().decode(errors="replace").splitlines()[-lines:]
        except OSError:
            return []

    def view(self) -> ServiceView:
        return ServiceView(self.name, self.role, self.ident, self.has_token, self.running,
                           self.tracker.restarts, self.stats_interval_s, self.started_at)

    def kill_hung(self) -> None:
        """SIGKILL to its process group: a hung process handles nothing gentler."""
        self.hung = True
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, signal.SIGKILL)

    def stop(self, timeout_s: float) -> int | None:
        self.restart_at = None
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            with contextlib.suppress(ProcessLookupError):  # a stopped one handles it when resumed
                os.kill(self.proc.pid, signal.SIGCONT)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.reader.join(timeout=5)
        return self.proc.returncode
