"""`tpdeb-link`'s throttle against the kernel's: in two network namespaces joined by a veth pair,
the same bulk TCP transfer (tests/traffic.py) runs once through a `tc tbf` qdisc and once through
the link with the same rate, and the link's achieved payload rate must be within 5 % of its
setting and within 5 % of what tbf delivers. Needs root, `ip` and `tc`; skips otherwise."""

from __future__ import annotations

import json
import subprocess

import pytest

from tests.netns import Namespaces, must, unavailable
from tests.procs import ROOT

RATES = [65_536, 262_144, 1_048_576]
SECONDS = {65_536: 8.0, 262_144: 6.0, 1_048_576: 6.0}  # sending time; the slowest needs longest
TOLERANCE = 0.05
# tbf counts L2 bytes (Ethernet + IP + TCP headers included) while the link meters payload only.
# Jumbo frames keep the header share under 1 % (66 of 9,014 bytes), so both are compared on
# payload goodput without correcting for headers.
MTU = 9000
TRAFFIC = str(ROOT / "tests" / "traffic.py")


def tbf_burst(rate: int) -> int:
    """20 ms of the rate, but never less than two jumbo frames and some room: tbf drops any
    (non-GSO) packet larger than its bucket, so a bucket smaller than a 9,014-byte frame would
    pass nothing, and one of just a frame would stall back-to-back frames. The initial burst this
    allows is excluded from the measurement (traffic.py starts its slope at 20 % of the data)."""
    return max(rate // 50, 2 * (MTU + 14) + 4096)


class LinkNamespaces(Namespaces):
    """The shared namespaces (tests/netns.py) plus the two transfers this test compares."""

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
            link = self.spawn(self.a, "link", "-m", "tpdeb.services.link",
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


@pytest.fixture(scope="module")
def namespaces(tmp_path_factory):
    if reason := unavailable(("ip", "tc")):
        pytest.skip(reason)
    spaces = LinkNamespaces(tmp_path_factory.mktemp("link-accuracy"))
    try:
        try:
            spaces.create(mtu=MTU)
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
