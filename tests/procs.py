"""Real service processes for integration tests: free ports, spawning by pid, guaranteed stop,
and a Zenoh client session to watch a run from outside."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from tpdeb.services.launcher.plan import free_port  # noqa: F401 (the tests take it from here)

ROOT = Path(__file__).resolve().parents[1]
MODULES = {**{name: f"tpdeb.services.{name}"
              for name in ("replay", "learner", "actor", "cluster", "router", "link", "health")},
           "certs": "tpdeb.services.net.certs"}


class Procs:
    """Starts service CLIs as subprocesses (own process group each) and stops every one of them,
    with their children, when the test ends — also when it fails."""

    def __init__(self, log_dir: Path):
        self.log_dir = log_dir
        self.started: list[subprocess.Popen] = []
        self.logs: dict[int, Path] = {}

    def spawn(self, role: str, *args: str, name: str | None = None,
              env: dict[str, str] | None = None) -> subprocess.Popen:
        """`env`: extra variables (e.g. TPDEB_PASSWORD, which must not appear in argv)."""
        return self.spawn_command([sys.executable, "-m", MODULES[role], *args], name or role,
                                  {**os.environ, **(env or {})})

    def spawn_command(self, argv: list[str], name: str, env: dict[str, str]) -> subprocess.Popen:
        """`argv` in its own process group with exactly `env`, its output in {name}.log."""
        log = self.log_dir / f"{name}.log"
        with log.open("w") as out:
            proc = subprocess.Popen(
                argv, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                env={**env, "PYTHONUNBUFFERED": "1"}, start_new_session=True)
        self.started.append(proc)
        self.logs[proc.pid] = log
        return proc

    def output(self, proc: subprocess.Popen) -> str:
        return self.logs[proc.pid].read_text()

    def wait_for_line(self, proc: subprocess.Popen, text: str, timeout_s: float = 60) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if text in self.output(proc):
                return
            if proc.poll() is not None:
                raise AssertionError(f"exited with {proc.returncode} before {text!r}:\n"
                                     f"{self.output(proc)}")
            time.sleep(0.1)
        raise AssertionError(f"no {text!r} within {timeout_s} s:\n{self.output(proc)}")

    def stop_all(self, timeout_s: float = 15) -> None:
        for proc in self.started:
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGTERM)
        deadline = time.monotonic() + timeout_s
        for proc in self.started:
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(max(0.1, deadline - time.monotonic()))
        for proc in self.started:  # whatever is left, and any grandchildren, by group
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(5)

    def leftovers(self) -> list[int]:
        """Pids of started processes or members of their groups still alive."""
        alive = []
        for proc in self.started:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(proc.pid, 0)
                alive.append(proc.pid)
        return alive


def pids_with(text: str) -> list[int]:
    """Live processes whose command line mentions `text` (e.g. a test's unique run dir)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
            state = (entry / "stat").read_text().split(") ")[-1][:1]
        except OSError:
            continue
        if text in cmdline and state != "Z":
            found.append(int(entry.name))
    return found


def maps_torch(pid: int) -> bool:
    """Whether the process has torch's shared library mapped (it imported torch, even lazily)."""
    return "libtorch" in (Path("/proc") / str(pid) / "maps").read_text()


def python_c(code: str) -> subprocess.CompletedProcess:
    """`python -c code` in the repository root, its output captured; fails on a non-zero exit."""
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                          check=True)


def service_pid(run_dir: Path, name: str) -> int:
    """The pid of the cluster's service `name` (router, replay, learner, actor-0, …): the
    process started with its configuration file, {run_dir}/config/{name}.toml."""
    path = str(Path(run_dir) / "config" / f"{name}.toml")
    for pid in pids_with(path):
        try:
            argv = Path(f"/proc/{pid}/cmdline").read_bytes().decode().split("\0")
        except OSError:
            continue
        if path in argv and not any(a.endswith("pytest") for a in argv):
            return pid
    raise AssertionError(f"no process runs by {path}")

