"""docs/MULTIHOST.md replayed across three network namespaces — a router host, a learner host
and an actor host on one LAN — command by command as the guide gives them (the test supplies
only the variables of its first block and carries out its `scp` lines as copies between the
hosts' directories): the run learns, and an actor without credentials is refused."""

from __future__ import annotations

import os
import re
import shlex
import shutil
import sys
from pathlib import Path

import pytest

from tests.netns import Hosts, unavailable
from tests.procs import ROOT
from tpdeb.services.store.metrics import read_metrics

GUIDE = ROOT / "docs" / "MULTIHOST.md"
HOSTS = ("router-host", "learner-host", "actor-host")
SECTIONS = {"1. Router host": "router-host", "3. Learner host": "learner-host",
            "4. Actor host": "actor-host"}


def guide_blocks() -> list[tuple[str, list[str]]]:
    """(section heading, command lines) of every bash block of the guide, in order."""
    blocks, heading = [], ""
    for part in re.split(r"^(## .*)$", GUIDE.read_text(), flags=re.M):
        if part.startswith("## "):
            heading = part[3:].strip()
            continue
        for body in re.findall(r"```bash\n(.*?)```", part, flags=re.S):
            blocks.append((heading, [line for line in body.splitlines() if line.strip()]))
    return blocks


@pytest.fixture
def hosts(tmp_path):
    why = unavailable()
    if why:
        pytest.skip(why)
    spaces = Hosts(tmp_path / "logs", HOSTS)
    (tmp_path / "logs").mkdir()
    try:
        spaces.create()
        yield spaces
    finally:
        problems = spaces.close()
        assert not problems, problems


def test_the_multihost_guide_runs_across_three_hosts(hosts, tmp_path):
    (_, variables), *blocks = guide_blocks()
    words = shlex.split(variables[0])
    assert words[0] == "export" and {w.split("=")[0] for w in words[1:]} == {
        "RUN", "ENV", "STEPS", "ROUTER"}
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("TPDEB_")},
           "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}", "PYTHONUNBUFFERED": "1",
           "RUN": "multihost", "ENV": "InvertedPendulum-v5", "STEPS": "20000",
           "ROUTER": hosts.address["router-host"]}
    home = {"router-host": tmp_path / "router-host"}
    for host in HOSTS[1:]:
        home[host] = tmp_path / host / "tpdeb"
    for path in home.values():
        path.mkdir(parents=True)
    running = {}
    for heading, lines in blocks:
        for line in lines:
            host = next((h for key, h in SECTIONS.items() if heading.startswith(key)), None)
            if line.startswith("scp "):  # copy between the hosts' directories
                *sources, target = shlex.split(line)[1:]
                where, _, folder = target.partition(":")
                for source in sources:
                    shutil.copy2(home["router-host"] / source,
                                 tmp_path / where / folder.rstrip("/") / Path(source).name)
                continue
            if host is None:
                continue
            name = shlex.split(line)[0]
            proc = hosts.run_on(host, f"{host}-{name}", line, home[host], env)
            if name == "tpdeb-certs":
                assert proc.wait(60) == 0, hosts.output(proc)
                continue
            running.setdefault(name, []).append(proc)
            ready = {"tpdeb-router": "tpdeb-router: routing on", "tpdeb-replay":
                     "tpdeb-replay: run multihost: serving"}.get(name)
            if ready:
                hosts.wait_for_line(proc, ready, timeout_s=60)
    router = running["tpdeb-router"][0]
    assert "with TLS, user/password, access control" in hosts.output(router)
    hosts.finish(running["tpdeb-learner"][0], timeout_s=300)
    for proc in running["tpdeb-replay"] + running["tpdeb-actor"]:
        hosts.finish(proc, timeout_s=60)
    rows = read_metrics(home["learner-host"] / "runs" / "multihost" / "metrics.jsonl")
    returns = [r["charts/episodic_return"] for r in rows if "charts/episodic_return" in r]
    assert returns and max(returns) >= 100, returns  # a random policy balances ~10 steps
    assert max(r["global_step"] for r in rows) >= 20000

    # The guide's first actor without its credentials: refused, with the reason.
    actor_line = next(line for _, lines in blocks for line in lines
                      if line.startswith("tpdeb-actor"))
    bare = re.sub(r" --user \S+ --password-file \S+", "", actor_line)
    assert bare != actor_line
    stranger = hosts.run_on("actor-host", "stranger", bare, home["actor-host"], env)
    assert stranger.wait(90) == 2, hosts.output(stranger)
    assert "refused this session: it requires a user and password" in hosts.output(stranger)
    hosts.stop(router)
