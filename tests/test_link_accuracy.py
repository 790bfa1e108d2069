"""`tpdeb-link`'s throttle against the kernel's: in two network namespaces joined by a veth pair,
the same bulk TCP transfer (tests/traffic.py) runs once through a `tc tbf` qdisc and once through
the link with the same rate, and the link's achieved payload rate must be within 5 % of its
setting and within 5 % of what tbf delivers. Needs root, `ip` and `tc`; skips otherwise."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.procs import ROOT, pids_with

RATES = [65_536, 262_144, 1_048_576]
SECONDS = {65_536: 8.0, 262_144: 6.0, 1_048_576: 6.0}  # sending time; the slowest needs longest
TOLERANCE = 0.05
# tbf counts L2 bytes (Ethernet + IP + TCP headers included) while the link meters payload only.
# Jumbo frames keep the header share under 1 % (66 of 9,014 bytes), so both are compared on
# payload goodput without correcting for headers.
MTU = 9000
TRAFFIC = str(ROOT / "tests" / "traffic.py")


def run(*cmd: str) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=30, check=False)


def must(*cmd: str) -> str:
    done = run(*cmd)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}): {done.stderr.strip()}")
    return done.stdout


def tbf_burst(rate: int) -> int:
    """20 ms of the rate, but never less than two jumbo frames and some room: tbf drops any
    (non-GSO) packet larger than its bucket, so a bucket smaller than a 9,014-byte frame would
    pass nothing, and one of just a frame would stall back-to-back frames. The initial burst this
    allows is excluded from the measurement (traffic.py starts its slope at 20 % of the data)."""
    return max(rate // 50, 2 * (MTU + 14) + 4096)


class Namespaces:
    """Two namespaces `a` (sender side) and `b` (receiver side) joined by a veth pair; every
    process started here is recorded and stopped by `close`."""

    def __init__(self, log_dir: Path):
        pid = os.getpid()
        self.a, self.b = f"tpdeb-a-{pid}", f"tpdeb-b-{pid}"
        subnet = 10 + pid % 240
        self.addr_a, self.addr_b = f"10.231.{subnet}.1", f"10.231.{subnet}.2"
        self.dev_a, self.dev_b = "veth-a", "veth-b"  # names live inside the namespaces only
        self.log_dir = log_dir
        self.created: list[str] = []
        self.started: list[subprocess.Popen] = []
        self.logs: dict[int, Path] = {}
        self.next_port = 5001

    def create(self) -> None:
        for ns in (self.a, self.b):
            must("ip", "netns", "add", ns)
            self.created.append(ns)
        must("ip", "-n", self.a, "link", "add", self.dev_a, "type", "veth",
             "peer", "name", self.dev_b, "netns", self.b)
        for ns, dev, addr in ((self.a, self.dev_a, self.addr_a), (self.b, self.dev_b, self.addr_b)):
            must("ip", "-n", ns, "addr", "add", f"{addr}/24", "dev", dev)
            must("ip", "-n", ns, "link", "set", dev, "mtu", str(MTU))
            must("ip", "-n", ns, "link", "set", "lo", "up")
            must("ip", "-n", ns, "link", "set", dev, "up")

    def port(self) -> int:
        self.next_port += 1
        return self.next_port

    # -- processes ---------------------------------------------------------------------------

    def spawn(self, ns: str, name: str, *args: str) -> subprocess.Popen:
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

    # -- measurements ------------------------------------------------------------------------

    def transfer(self, rate: int, seconds: float, via_link: bool) -> float:
        """Payload bytes/s the receiver in `b` measured for `seconds` of bulk sending from `a`."""
        port = self.port()
        receiver = self.spawn(self.b, "recv", TRAFFIC, "recv", self.addr_b, str(port),
                              str(seconds))
        self.wait_for_line(receiver, "listening")
        target = (self.addr_b, port)
        link = None
        if via_link:
            listen = self.port()
            link = self.spawn(self.a, "link", "-m", "services.link",
                              "--listen", f"tcp/{self.addr_a}:{listen}",
                              "--connect", f"tcp/{self.addr_b}:{port}",
                              "--up-bytes-per-s", str(rate), "--publish-stats", "false")
            self.wait_for_line(link, "tpdeb-link: ")
            target = (self.addr_a, listen)
        try:
            sender = self.spawn(self.a, "send", TRAFFIC, "send", target[0], str(target[1]),
                                str(seconds))
            self.finish(sender, seconds + 30)
            out = self.finish(receiver, 30)
        finally:
            for proc in (receiver, link):
                if proc is not None:
                    self.stop(proc)
        result = json.loads([line for line in out.splitlines() if line.startswith("{")][-1])
        return result["bytes_per_s"]

    def tbf_rate(self, rate: int, seconds: float) -> float:
        must("tc", "-n", self.a, "qdisc", "replace", "dev", self.dev_a, "root", "tbf",
             "rate", f"{rate * 8}bit", "burst", str(tbf_burst(rate)), "latency", "500ms")
        try:
            return self.transfer(rate, seconds, via_link=False)
        finally:
            must("tc", "-n", self.a, "qdisc", "del", "dev", self.dev_a, "root")

    def link_rate(self, rate: int, seconds: float) -> float:
        return self.transfer(rate, seconds, via_link=True)

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
            done = run("ip", "netns", "del", ns)
            if done.returncode != 0:
                problems.append(f"ip netns del {ns}: {done.stderr.strip()}")
        listed = run("ip", "netns", "list").stdout.split()
        problems += [f"namespace {ns} still listed" for ns in self.created if ns in listed]
        for ns in (self.a, self.b):
            if pids := pids_with(ns):
                problems.append(f"processes mentioning {ns}: {pids}")
        return problems


@pytest.fixture(scope="module")
def namespaces(tmp_path_factory):
    if os.geteuid() != 0:
        pytest.skip("needs root to create network namespaces and tc qdiscs")
    missing = [tool for tool in ("ip", "tc") if shutil.which(tool) is None]
    if missing:
        pytest.skip(f"needs {' and '.join(missing)} (iproute2)")
    spaces = Namespaces(tmp_path_factory.mktemp("link-accuracy"))
    try:
        try:
            spaces.create()
        except (RuntimeError, subprocess.TimeoutExpired) as exc:
            pytest.skip(f"cannot set up network namespaces: {exc}")
        try:  # the tbf qdisc (sch_tbf) may be missing from the kernel
            must("tc", "-n", spaces.a, "qdisc", "replace", "dev", spaces.dev_a, "root", "tbf",
                 "rate", "1mbit", "burst", "32k", "latency", "500ms")
            must("tc", "-n", spaces.a, "qdisc", "del", "dev", spaces.dev_a, "root")
        except (RuntimeError, subprocess.TimeoutExpired) as exc:
            pytest.skip(f"cannot use a tbf qdisc: {exc}")
        yield spaces
    finally:
        problems = spaces.close()
        assert not problems, "cleanup left things behind: " + "; ".join(problems)


@pytest.mark.parametrize("rate", RATES, ids=[f"{r // 1024}kBps" for r in RATES])
def test_link_rate_matches_setting_and_tbf(namespaces, rate):
    seconds = SECONDS[rate]
    tbf = namespaces.tbf_rate(rate, seconds)
    shim = namespaces.link_rate(rate, seconds)
    vs_setting = (shim - rate) / rate
    vs_tbf = (shim - tbf) / tbf
    figures = (f"setting {rate:,} B/s, link {shim:,.0f} B/s ({100 * vs_setting:+.2f} %), "
               f"tbf {tbf:,.0f} B/s (link vs tbf {100 * vs_tbf:+.2f} %)")
    print(f"\nlink accuracy: {figures}")
    assert abs(vs_setting) <= TOLERANCE, f"link off its setting: {figures}"
    assert abs(vs_tbf) <= TOLERANCE, f"link off the kernel's tbf: {figures}"
