"""Two network namespaces joined by a veth pair, for tests of real links: processes started
inside them (stopped by pid, also when a test fails), the link cut and restored, and a cleanup
that deletes the namespaces and reports whatever was left. Needs root and iproute2."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from tests.procs import ROOT, pids_with


def run(*cmd: str) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=30, check=False)


def must(*cmd: str) -> str:
    done = run(*cmd)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}): {done.stderr.strip()}")
    return done.stdout


def unavailable(tools: tuple[str, ...] = ("ip",)) -> str | None:
    """Why namespaces cannot be used here (a skip reason), or None."""
    if os.geteuid() != 0:
        return "needs root to create network namespaces"
    missing = [tool for tool in tools if shutil.which(tool) is None]
    if missing:
        return f"needs {' and '.join(missing)} (iproute2)"
    done = run("ip", "netns", "list")
    if done.returncode != 0:
        return f"`ip netns` is unavailable: {done.stderr.strip()}"
    return None


class Namespaces:
    """Namespaces `a` and `b` joined by a veth pair (`dev_a` in `a`, `dev_b` in `b`); every
    process started here is recorded and stopped by `close`. `tag` keeps the names and the
    subnet apart from other tests' namespaces."""

    def __init__(self, log_dir: Path, tag: str = "", net: str = "10.231"):
        pid = os.getpid()
        infix = f"{tag}-" if tag else ""
        self.a, self.b = f"tpdeb-{infix}a-{pid}", f"tpdeb-{infix}b-{pid}"
        subnet = 10 + pid % 240
        self.addr_a, self.addr_b = f"{net}.{subnet}.1", f"{net}.{subnet}.2"
        self.dev_a, self.dev_b = "veth-a", "veth-b"  # names live inside the namespaces only
        self.log_dir = log_dir
        self.created: list[str] = []
        self.started: list[subprocess.Popen] = []
        self.logs: dict[int, Path] = {}
        self.next_port = 5001

    def create(self, mtu: int | None = None) -> None:
        for ns in (self.a, self.b):
            must("ip", "netns", "add", ns)
            self.created.append(ns)
        must("ip", "-n", self.a, "link", "add", self.dev_a, "type", "veth",
             "peer", "name", self.dev_b, "netns", self.b)
        for ns, dev, addr in ((self.a, self.dev_a, self.addr_a), (self.b, self.dev_b, self.addr_b)):
            must("ip", "-n", ns, "addr", "add", f"{addr}/24", "dev", dev)
            if mtu is not None:
                must("ip", "-n", ns, "link", "set", dev, "mtu", str(mtu))
            must("ip", "-n", ns, "link", "set", "lo", "up")
            must("ip", "-n", ns, "link", "set", dev, "up")

    def port(self) -> int:
        self.next_port += 1
        return self.next_port

    def set_link(self, ns: str, up: bool) -> None:
        """Bring this namespace's end of the veth pair up or down. The kernel on the down side
        knows (its sends fail at once: network unreachable); the other side only loses carrier
        and its packets vanish."""
        dev = self.dev_a if ns == self.a else self.dev_b
        must("ip", "-n", ns, "link", "set", "dev", dev, "up" if up else "down")

    def set_blackhole(self, on: bool) -> None:
        """Drop every packet leaving either end of the veth, telling nobody: a tbf qdisc whose
        bucket (20 bytes) is smaller than any packet. Links and routes stay up, so neither side's
        kernel learns anything (as across a cut cable between two switches); TCP just sees its
        segments go unanswered. Needs `tc` and sch_tbf."""
        for ns, dev in ((self.a, self.dev_a), (self.b, self.dev_b)):
            if on:
                must("tc", "-n", ns, "qdisc", "replace", "dev", dev, "root", "tbf", "rate", "8bit",
                     "burst", "20", "latency", "1ms")
            else:
                must("tc", "-n", ns, "qdisc", "del", "dev", dev, "root")

    # -- processes ---------------------------------------------------------------------------

    def spawn(self, ns: str, name: str, *args: str) -> subprocess.Popen:
        """`python *args` inside `ns` (`ip netns exec` execs it: the pid is Python's)."""
        log = self.log_dir / f"{name}-{len(self.started)}.log"
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        with log.open("w") as out:
            proc = subprocess.Popen(["ip", "netns", "exec", ns, sys.executable, *args], cwd=ROOT,
                                    stdout=out, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, env=env, start_new_session=True)
        self.started.append(proc)
        self.logs[proc.pid] = log
        return proc

    def output(self, proc: subprocess.Popen) -> str:
        return self.logs[proc.pid].read_text()

    def wait_for_line(self, proc: subprocess.Popen, prefix: str, timeout_s: float = 30) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if any(line.startswith(prefix) for line in self.output(proc).splitlines()):
                return
            if proc.poll() is not None:
                raise AssertionError(f"exited with {proc.returncode} before {prefix!r}:\n"
                                     f"{self.output(proc)}")
            time.sleep(0.05)
        raise AssertionError(f"no {prefix!r} within {timeout_s} s:\n{self.output(proc)}")

    def finish(self, proc: subprocess.Popen, timeout_s: float) -> str:
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"still running after {timeout_s} s:\n"
                                 f"{self.output(proc)}") from None
        assert proc.returncode == 0, f"exited with {proc.returncode}:\n{self.output(proc)}"
        return self.output(proc)

    def stop(self, proc: subprocess.Popen, timeout_s: float = 10) -> None:
        for sig in (signal.SIGTERM, signal.SIGKILL):
            if proc.poll() is not None:
                break
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, sig)
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout_s)

    # -- cleanup -----------------------------------------------------------------------------

    def close(self) -> list[str]:
        """Stop everything, delete the namespaces; returns what was found left over."""
        problems = []
        for proc in self.started:
            self.stop(proc)
        for ns in self.created:
            stray = [int(p) for p in run("ip", "netns", "pids", ns).stdout.split()]
            if stray:
                problems.append(f"processes left in {ns}: {stray}")
                for pid in stray:  # ours: nothing else runs in this run's namespaces
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(pid, signal.SIGKILL)
        for ns in self.created:
            done = run("ip", "netns", "del", ns)  # takes the veth pair with it
            if done.returncode != 0:
                problems.append(f"ip netns del {ns}: {done.stderr.strip()}")
        listed = run("ip", "netns", "list").stdout.split()
        problems += [f"namespace {ns} still listed" for ns in self.created if ns in listed]
        for ns in self.created:
            if pids := pids_with(ns):
                problems.append(f"processes mentioning {ns}: {pids}")
        return problems


class Hosts(Namespaces):
    """Namespaces as hosts on one LAN: the first holds a bridge with its address, each other
    one a veth port on it. `address[name]` is each host's address on that LAN."""

    def __init__(self, log_dir: Path, names: tuple[str, ...], net: str = "10.233"):
        super().__init__(log_dir, tag="hosts", net=net)
        pid = os.getpid()
        subnet = 10 + pid % 240
        self.names = names
        self.ns = {name: f"tpdeb-{name}-{pid}" for name in names}
        self.address = {name: f"{net}.{subnet}.{i + 1}" for i, name in enumerate(names)}

    def create(self, mtu: int | None = None) -> None:
        hub, *others = self.names
        for name in self.names:
            must("ip", "netns", "add", self.ns[name])
            self.created.append(self.ns[name])
            must("ip", "-n", self.ns[name], "link", "set", "lo", "up")
        must("ip", "-n", self.ns[hub], "link", "add", "br0", "type", "bridge")
        must("ip", "-n", self.ns[hub], "addr", "add", f"{self.address[hub]}/24", "dev", "br0")
        must("ip", "-n", self.ns[hub], "link", "set", "br0", "up")
        for i, name in enumerate(others):
            port = f"port{i}"
            must("ip", "-n", self.ns[hub], "link", "add", port, "type", "veth", "peer", "name",
                 "eth0", "netns", self.ns[name])
            must("ip", "-n", self.ns[hub], "link", "set", port, "master", "br0", "up")
            must("ip", "-n", self.ns[name], "addr", "add", f"{self.address[name]}/24", "dev",
                 "eth0")
            must("ip", "-n", self.ns[name], "link", "set", "eth0", "up")

    def run_on(self, host: str, name: str, command: str, cwd: Path,
               env: dict[str, str]) -> subprocess.Popen:
        """`bash -c command` on `host`, in `cwd`, with exactly `env`."""
        log = self.log_dir / f"{name}-{len(self.started)}.log"
        with log.open("w") as out:
            proc = subprocess.Popen(["ip", "netns", "exec", self.ns[host], "bash", "-c", command],
                                    cwd=cwd, stdout=out, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, env=env, start_new_session=True)
        self.started.append(proc)
        self.logs[proc.pid] = log
        return proc
