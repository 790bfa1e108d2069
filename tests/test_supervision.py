"""Supervision in tpdeb-cluster: the restart policy as a pure class (a fake clock), the health
summary of the status line, and real clusters whose processes crash or are killed with -9."""

from __future__ import annotations

import io
import os
import re
import signal
import threading
import time
from pathlib import Path

import pytest
import zenoh

from tests.procs import pids_with, service_pid
from tests.test_faults import CLUSTER_FILE
from tpdeb.services.cluster import Cluster, parse_args
from tpdeb.services.config import ConfigError
from tpdeb.services.launcher.child import Child
from tpdeb.services.launcher.plan import hang_intervals, make_plan
from tpdeb.services.launcher.restart import (
    MAX_BACKOFF_S,
    RestartPolicy,
    RestartSettings,
    RestartTracker,
)
from tpdeb.services.launcher.status import Display, Health, ServiceView, fit

ROOT = Path(__file__).resolve().parents[1]
ENV = "InvertedPendulum-v5"


# -- the restart policy, with the clock passed in

def tracker(policy: str = "on-failure", **settings) -> RestartTracker:
    t = RestartTracker(RestartPolicy.parse(policy, "test"), RestartSettings(**settings))
    t.started(0.0)
    return t


def test_back_off_doubles_per_failure_up_to_the_cap():
    t = tracker(backoff_s=1.0, max_restarts=100, window_s=1e9)
    now, delays = 0.0, []
    for _ in range(8):
        now += 1.0  # crashes a second after each start
        verdict = t.exited(1, now)
        assert verdict.action == "restart"
        delays.append(verdict.delay_s)
        now += verdict.delay_s
        t.started(now)
    assert delays == [1, 2, 4, 8, 16, MAX_BACKOFF_S, MAX_BACKOFF_S, MAX_BACKOFF_S]
    assert t.restarts == 8


def test_back_off_starts_over_after_the_process_stayed_up():
    t = tracker(backoff_s=0.5, reset_after_s=60.0, max_restarts=100)
    assert [t.exited(1, 1.0).delay_s, t.exited(1, 2.0).delay_s] == [0.5, 1.0]
    t.started(10.0)
    assert t.exited(1, 69.0).delay_s == 2.0  # up 59 s: still consecutive
    t.started(70.0)
    assert t.exited(1, 130.0).delay_s == 0.5  # up 60 s: a fresh failure
    assert t.restarts == 4


def test_more_than_max_restarts_within_the_window_is_a_crash_loop():
    t = tracker(max_restarts=3, window_s=100.0)
    assert [t.exited(2, now).action for now in (1.0, 2.0, 3.0)] == ["restart"] * 3
    verdict = t.exited(2, 4.0)
    assert verdict.action == "crash_loop" and verdict.restarts == 3
    assert "max_restarts = 3" in verdict.reason and "crash_loop_window_s = 100 s" in verdict.reason


def test_restarts_older_than_the_window_do_not_count():
    t = tracker(max_restarts=2, window_s=100.0, reset_after_s=1e9)
    assert t.exited(1, 0.0).action == "restart"
    assert t.exited(1, 50.0).action == "restart"
    assert t.exited(1, 120.0).action == "restart"  # the one at 0 s has left the window
    assert t.exited(1, 140.0).action == "crash_loop"  # 50 s and 120 s are within it
    assert t.restarts == 3


def test_on_failure_n_allows_n_restarts_however_slow():
    t = tracker("on-failure:2", max_restarts=100, window_s=1.0)
    assert t.exited(1, 1000.0).action == "restart"
    assert t.exited(1, 2000.0).action == "restart"
    verdict = t.exited(1, 3000.0)
    assert verdict.action == "crash_loop" and verdict.restarts == 2
    assert 'restart = "on-failure:2"' in verdict.reason


@pytest.mark.parametrize("policy, code, action", [
    ("no", 1, "stay_down"), ("no", -9, "stay_down"), ("on-failure", 0, "stay_down"),
    ("on-failure", -9, "restart"), ("always", 0, "restart"), ("always", 3, "restart"),
    ("on-failure:1", 0, "stay_down"),
])
def test_which_exits_a_policy_restarts(policy, code, action):
    assert tracker(policy).exited(code, 1.0).action == action


@pytest.mark.parametrize("value", ["yes", "on_failure", "on-failure:", "on-failure:-1",
                                   "always:3", "unless-stopped", "", 3, False, None])
def test_restart_policy_refuses_anything_else(value):
    with pytest.raises(ConfigError, match=r"is not a restart policy; use \"no\""):
        RestartPolicy.parse(value, "[services.actor]")


# -- the health part of the status line

def views(running=True, **changes) -> list[ServiceView]:
    out = [ServiceView("router", "router", None, False, running),
           ServiceView("replay", "replay", "0", True, running),
           ServiceView("learner", "learner", "0", True, running),
           ServiceView("actor-0", "actor", "0", True, running),
           ServiceView("actor-1", "actor", "1", True, running)]
    for view in out:
        for key, value in changes.get(view.name.replace("-", "_"), {}).items():
            setattr(view, key, value)
    return out


class FakeSample:
    def __init__(self, key: str, kind):
        self.key_expr, self.kind = key, kind


def test_health_follows_liveliness_tokens():
    health = Health()
    assert health.summary(views(), 0.0) == ("up: router actors 0/2 | starting: replay learner")
    for key in ("replay/0", "learner/0", "actor/0", "actor/1"):
        health.on_token(FakeSample(f"tpdeb/r/alive/{key}", zenoh.SampleKind.PUT))
    assert health.summary(views(), 0.0) == "up: router replay learner actors 2/2"
    health.on_token(FakeSample("tpdeb/r/alive/replay/0", zenoh.SampleKind.DELETE))
    health.on_token(FakeSample("tpdeb/r/alive/actor/1", zenoh.SampleKind.DELETE))
    # running without its token: it had one, so the network lost it (or it is stopping)
    assert health.summary(views(), 0.0) == "up: router learner actors 1/2 | unreachable: replay"
    health.restarted("replay", "0")
    assert health.summary(views(), 0.0) == "up: router learner actors 1/2 | starting: replay"
    # a process that has exited is down whatever its token says (a lease takes seconds)
    line = health.summary(views(learner={"running": False}, actor_0={"running": False}), 0.0)
    assert line == "up: router actors 0/2 | starting: replay | down: learner"


def test_health_shows_restarts_and_stale_stats():
    health = Health()
    for role, ident in (("replay", "0"), ("learner", "0"), ("actor", "0"), ("actor", "1")):
        health.token(role, ident, True)
        health.saw_stats(role, ident, 100.0)
    health.saw_stats("learner", "0", 102.5)
    line = health.summary(views(replay={"restarts": 1}, actor_0={"restarts": 2},
                                actor_1={"stats_interval_s": 5.0}), 103.5)
    # replay and actor-0: 3.5 s > 3 × 1 s; actor-1: 3.5 s < 3 × 5 s; learner 1 s old
    assert line == ("up: router replay learner actors 2/2 | stale: replay 4 s, actor-0 4 s | "
                    "restarts: replay 1, actor-0 2")
    health.restarted("replay", "0")  # its predecessor's stats do not make it stale
    assert "replay" not in health.summary(views(), 103.5).split("stale:")[1]


def test_fit_drops_the_least_important_parts_first_then_cuts():
    parts = [("[c]", -1), ("10/100 steps", 0), ("return 5.0", 1), ("replay 3 fragments", 7),
             ("lag 2.0 versions", 6)]
    assert fit(parts, 200, " ") == "[c] 10/100 steps | return 5.0 | replay 3 fragments | lag " \
                                   "2.0 versions"
    assert fit(parts, 50, " ") == "[c] 10/100 steps | return 5.0 | lag 2.0 versions"
    assert fit(parts, 30, " ") == "[c] 10/100 steps | return 5.0"
    assert fit(parts, 12, " ") == "[c] 10/100 …"


class Terminal(io.StringIO):
    def isatty(self):
        return True


def test_the_status_line_fits_the_terminal_and_redraws_in_place(monkeypatch):
    out = Terminal()
    display = Display(out)
    display.latest[("learner", "0")] = {
        "global_step": 123456, "total_timesteps": 1000000, "sps": 4321.0, "mean_return": 1234.5,
        "param_version_lag": 12.3, "updates": 45678}
    display.latest[("replay", "0")] = {"prioritized_items": 64, "uniform_steps": 8192}
    health = "up: router replay learner actors 2/2 | restarts: actor-0 1"
    full = " | ".join(text for text, _ in display.parts(health))
    for columns in (200, 100, 80):
        monkeypatch.setattr("shutil.get_terminal_size", lambda *a, c=columns: os.terminal_size(
            (c, 24)))
        out.seek(0)
        out.truncate()
        display.show(display.parts(health))
        display.show(display.parts(health))
        written = out.getvalue()
        assert "\n" not in written  # redrawn in place, never a new row
        frames = written.split("\r\033[K")[1:]
        assert len(frames) == 2 and all(len(f) <= columns - 1 for f in frames), frames
        assert frames[0].startswith("[tpdeb-cluster] 123,456/1,000,000 steps (12%)")
        assert "return 1,234.5" in frames[0]  # the most important parts stay
    assert len(f"[tpdeb-cluster] {full}") > 79  # the 80-column case really had to fit


# -- the supervisor's decisions, on stand-in processes

class FakeProc:
    def __init__(self):
        self.returncode = None

    def poll(self):
        return self.returncode


class FakeChild(Child):
    """A Child whose processes are stand-ins the test ends by setting their exit code."""

    def start(self, now: float) -> None:
        self.proc, self.starts = FakeProc(), getattr(self, "starts", 0) + 1
        self.reader = threading.Thread(target=lambda: None)
        self.reader.start()
        self.tracker.started(now)
        self.restart_at, self.reported, self.started_at, self.hung = None, False, now, False

    def kill_hung(self) -> None:
        self.hung, self.proc.returncode = True, -9


def fake_cluster(tmp_path, **policies: str) -> tuple[Cluster, dict[str, FakeChild], io.StringIO]:
    plan = make_plan(parse_args(["--run-dir", str(tmp_path / "run")]))
    plan.restarts = RestartSettings(backoff_s=0.01, max_restarts=2)
    plan.stop_timeout_s = 0.5  # how long an exit 0 may wait for the learner's stop message
    out = io.StringIO()
    cluster = Cluster(plan, out)
    (tmp_path / "logs").mkdir()
    children = {}
    for name, role, ident in (("router", "router", None), ("replay", "replay", "0"),
                              ("learner", "learner", "0"), ("actor-0", "actor", "0"),
                              ("actor-1", "actor", "1")):
        policy = RestartPolicy.parse(policies.get(name.replace("-", "_"), "on-failure"), "test")
        child = FakeChild(name, role, [], {}, tmp_path / "logs" / f"{name}.log",
                          cluster.display.echo, RestartTracker(policy, plan.restarts), ident)
        cluster.start(child)
        children[name] = child
    return cluster, children, out


def test_an_actor_that_stays_down_leaves_the_others_until_none_is_left(tmp_path):
    cluster, children, out = fake_cluster(tmp_path, actor_0="no", actor_1="no")
    children["actor-0"].proc.returncode = -9
    assert cluster.tend() is None
    assert 'actor-0 exited with code -9; the other actors go on (restart = "no")' in out.getvalue()
    assert children["actor-0"].restart_at is None
    children["actor-1"].proc.returncode = 1
    assert cluster.tend() == 1
    assert "no actor is left: stopping the run" in out.getvalue()


def test_a_crashed_service_is_restarted_after_its_back_off(tmp_path):
    cluster, children, out = fake_cluster(tmp_path)
    children["replay"].proc.returncode = -9
    assert cluster.tend() is None
    assert "replay exited with code -9; restarting in 0.01 s (restart 1)" in out.getvalue()
    time.sleep(0.02)
    assert cluster.tend() is None
    assert children["replay"].starts == 2 and children["replay"].running


def test_a_crash_loop_stops_the_run_naming_the_process_and_its_log(tmp_path):
    cluster, children, out = fake_cluster(tmp_path)
    replay = children["replay"]
    for restart in (1, 2):
        replay.proc.returncode = 3
        assert cluster.tend() is None
        time.sleep(0.05)  # back-off 0.01 s, then 0.02 s
        assert cluster.tend() is None and replay.starts == restart + 1
    replay.log_path.write_text("one\ntwo\nthree\nfour: the reason\n")
    replay.proc.returncode = 3
    assert cluster.tend() == 1
    text = out.getvalue()
    assert (f"replay is crash looping: exited with code 3 after 2 restarts (max_restarts = 2 "
            f"within crash_loop_window_s = 120 s); stopping the run. Its log {replay.log_path} "
            "ends:\n    two\n    three\n    four: the reason\n") in text


def test_a_service_other_than_an_actor_staying_down_stops_the_run(tmp_path):
    cluster, children, out = fake_cluster(tmp_path, learner="no")
    children["learner"].proc.returncode = 1
    assert cluster.tend() == 1
    assert 'learner exited with code 1: stopping the run (restart = "no"; see' in out.getvalue()


def test_nothing_is_restarted_once_the_learner_has_finished(tmp_path):
    cluster, children, out = fake_cluster(tmp_path, actor_0="always", replay="always")
    cluster.finishing.set()  # the learner's stop message
    children["actor-0"].proc.returncode = 0
    children["actor-1"].proc.returncode = -15
    children["replay"].proc.returncode = 1
    assert cluster.tend() is None
    assert all(c.restart_at is None for c in children.values())
    assert "restarting" not in out.getvalue() and "no actor is left" not in out.getvalue()
    children["learner"].proc.returncode = 0
    assert cluster.tend() == 0


def test_an_exit_0_before_the_stop_message_arrives_is_not_a_failure(tmp_path):
    cluster, children, out = fake_cluster(tmp_path)
    threading.Timer(0.1, cluster.finishing.set).start()  # the message comes a little later
    children["replay"].proc.returncode = 0
    assert cluster.tend() is None
    assert "stopping the run" not in out.getvalue()


def test_nothing_is_restarted_after_ctrl_c(tmp_path):
    cluster, children, out = fake_cluster(tmp_path)
    children["actor-0"].proc.returncode = -9
    assert cluster.tend() is None  # restart scheduled
    cluster.stopping.set()
    time.sleep(0.02)
    assert cluster.tend() is None and children["actor-0"].starts == 1


# -- real clusters

def cluster_file(tmp_path, actor_args: str = "[]", actor_env: str = "{}") -> Path:
    """deploy/local.toml with quick restarts (and `args` and `env` for the actors)."""
    text = (ROOT / "deploy" / "local.toml").read_text()
    section = text[text.index("[services.actor]"):]
    text = text.replace(section, section.replace("args = []", f"args = {actor_args}", 1)
                        .replace("env = {}", f"env = {actor_env}", 1))
    for old, new in (("restart_backoff_s = 1", "restart_backoff_s = 0.2"),
                     ("max_restarts = 5", "max_restarts = 2"),
                     ("crash_loop_window_s = 120", "crash_loop_window_s = 300")):
        assert old in text
        text = text.replace(old, new)
    path = tmp_path / "cluster.toml"
    path.write_text(text)
    return path


def start_cluster(procs, tmp_path, total_timesteps: int, actor_args: str = "[]",
                  actor_env: str = "{}"):
    run_dir = tmp_path / "run"
    proc = procs.spawn("cluster", "--cluster-file",
                       str(cluster_file(tmp_path, actor_args, actor_env)),
                       "--env-id", ENV, "--total-timesteps", str(total_timesteps),
                       "--num-envs", "2", "--run-dir", str(run_dir), "--set", "log_interval_s=1")
    return proc, run_dir


def test_crash_looping_actors_stop_the_cluster_with_a_clear_message(procs, tmp_path):
    # Actors that crash at start (exit status 3, before any work): a fault a restart may cure,
    # so they are restarted until the crash-loop rule stops the run.
    crashing = tmp_path / "crashing"
    crashing.mkdir()
    (crashing / "sitecustomize.py").write_text(
        "import os, sys\nsys.stderr.write('tpdeb-actor: crashed on purpose\\n')\n"
        "sys.stderr.flush()\nos._exit(3)\n")
    started = time.monotonic()
    cluster, run_dir = start_cluster(procs, tmp_path, 1_000_000,
                                     actor_env=f'{{PYTHONPATH = "{crashing}"}}')
    assert cluster.wait(180) == 1, procs.output(cluster)[-3000:]
    out = procs.output(cluster)
    assert time.monotonic() - started < 180
    lines = [line for line in out.splitlines() if "is crash looping" in line]
    assert len(lines) == 1, out[-3000:]
    name = lines[0].split("] ")[1].split()[0]
    assert name in ("actor-0", "actor-1")
    log = run_dir / "logs" / f"{name}.log"
    assert "exited with code 3 after 2 restarts" in lines[0], lines[0]
    assert "max_restarts = 2 within crash_loop_window_s = 300 s" in lines[0]
    assert str(log) in lines[0]
    # the log's last lines follow the message: the actor's own reason
    after = out.splitlines()[out.splitlines().index(lines[0]) + 1:]
    assert any("crashed on purpose" in line and line.startswith("    ")
               for line in after[:3]), after[:3]
    assert f"[tpdeb-cluster] {name} exited with code 3; restarting in 0.2 s (restart 1)" in out
    assert f"[tpdeb-cluster] {name} exited with code 3; restarting in 0.4 s (restart 2)" in out
    text = log.read_text()
    assert "--- restart #1 (exit code 3) ---" in text and "--- restart #2 (exit code 3) ---" in text
    assert text.count("crashed on purpose") == 3  # started 3 times, crashed each time
    assert "tpdeb-cluster: stopped" in out
    assert not pids_with(str(run_dir))


def test_actors_that_refuse_their_configuration_stop_the_cluster_at_once(procs, tmp_path):
    cluster, run_dir = start_cluster(procs, tmp_path, 1_000_000, '["--env-id", "Nope-v0"]')
    assert cluster.wait(120) == 2, procs.output(cluster)[-3000:]
    out = procs.output(cluster)
    assert "refused its configuration (exit status 2), so the run stops" in out
    assert "Nope-v0" in out and "restarting" not in out
    assert not pids_with(str(run_dir))


def wait_for_count(procs, proc, text: str, count: int, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while procs.output(proc).count(text) < count:
        assert proc.poll() is None and time.monotonic() < deadline, (
            f"{text!r} not {count} times:\n{procs.output(proc)[-4000:]}")
        time.sleep(0.2)


def kill_and_finish(procs, tmp_path, total_timesteps: int, ready: str, name: str, back: str):
    """Kill the service `name` once the cluster printed `ready`; it must be restarted, print
    `back` a second time, and the run finish with exit 0."""
    cluster, run_dir = start_cluster(procs, tmp_path, total_timesteps)
    procs.wait_for_line(cluster, ready, timeout_s=150)
    os.kill(service_pid(run_dir, name), signal.SIGKILL)
    wait_for_count(procs, cluster, back, 2, timeout_s=120)  # the new process is in the run
    assert cluster.wait(240) == 0, procs.output(cluster)[-4000:]
    out = procs.output(cluster)
    assert f"[tpdeb-cluster] {name} exited with code -9; restarting in 0.2 s (restart 1)" in out
    assert out.count("exited with code -9") == 1
    assert "--- restart #1 (exit code -9) ---" in (run_dir / "logs" / f"{name}.log").read_text()
    assert list((run_dir / "checkpoints").glob("final_*.pt"))
    assert "tpdeb-cluster: finished" in out
    assert not pids_with(str(run_dir))


def test_a_killed_actor_is_restarted_and_the_run_finishes(procs, tmp_path):
    # Killed as soon as it acts; the run is long enough for its successor to rejoin.
    kill_and_finish(procs, tmp_path, 40_000, "[actor-0] tpdeb-actor: actor 0:", "actor-0",
                    "[actor-0] tpdeb-actor: actor 0:")


def test_a_killed_router_is_restarted_and_the_run_finishes(procs, tmp_path):
    # Every other service is a client of the router: they reconnect when it comes back.
    kill_and_finish(procs, tmp_path, 16_000, "[learner] tpdeb-learner: [", "router",
                    "[router] tpdeb-router: routing on")


def stats_from_all(cluster: Cluster, children: dict) -> float:
    """Every service's stats arrive now; returns now."""
    now = time.monotonic()
    for child in children.values():
        if child.ident is not None:
            cluster.health.saw_stats(child.role, child.ident, now)
    return now


def test_a_service_silent_past_its_bound_is_killed_and_restarted_like_a_crash(tmp_path):
    cluster, children, out = fake_cluster(tmp_path)
    t0 = stats_from_all(cluster, children)
    late = t0 + 31.0  # 30 intervals of 1 s: the default bound
    for name in ("learner", "actor-0", "actor-1"):
        cluster.health.saw_stats(children[name].role, children[name].ident, late)
    cluster.check_hangs(late)
    assert children["replay"].hung and not children["learner"].hung
    assert "replay is hung: no stats for 31 s (bound 30 s); killing it" in out.getvalue()
    cluster.check_hangs(late + 1)  # killed once, said once
    assert out.getvalue().count("is hung") == 1
    assert cluster.tend() is None  # its exit goes to the restart policy, as a crash would
    replay = children["replay"]
    assert replay.tracker.restarts == 1 and replay.restart_at is not None  # toward a crash loop
    assert "replay exited with code -9; restarting" in out.getvalue()


def test_before_its_first_stats_a_service_has_the_start_timeout(tmp_path):
    cluster, children, _ = fake_cluster(tmp_path)
    started = children["learner"].started_at
    cluster.check_hangs(started + cluster.plan.start_timeout_s - 1)
    assert not any(c.hung for c in children.values())


def test_when_every_service_is_silent_the_router_is_the_one_killed(tmp_path):
    cluster, children, out = fake_cluster(tmp_path)
    cluster.check_hangs(stats_from_all(cluster, children) + 40)
    assert [name for name, c in children.items() if c.hung] == ["router"]
    assert "router is hung: nobody's stats arrive" in out.getvalue()


def test_hang_intervals_0_turns_it_off_and_bad_values_are_refused(tmp_path):
    cluster, children, _ = fake_cluster(tmp_path)
    cluster.plan.hang_intervals = 0
    cluster.check_hangs(time.monotonic() + 10_000)
    assert not any(c.hung for c in children.values())
    with pytest.raises(ConfigError, match="hang_intervals=-1 must be a number >= 0"):
        hang_intervals({"hang_intervals": -1}, "cluster.toml")


# the fault tests' cluster, told to take 5 silent stats intervals for a hang
HUNG_FILE = CLUSTER_FILE.replace("restart_backoff_s = 0.5\n", "restart_backoff_s = 0.5\n"
                                 "hang_intervals = 5\nstop_timeout_s = 10\n")


def hung_cluster(procs, tmp_path, endpoint, steps: int):
    run_dir = tmp_path / "run"
    cluster_file = tmp_path / "cluster.toml"
    assert "hang_intervals" in HUNG_FILE
    cluster_file.write_text(HUNG_FILE.format(endpoint=endpoint, env="InvertedPendulum-v5",
                                             steps=steps))
    cluster = procs.spawn("cluster", "--cluster-file", str(cluster_file), "--run-dir", str(run_dir))
    procs.wait_for_line(cluster, "[learner] tpdeb-learner: [", timeout_s=120)
    return cluster, run_dir


def test_a_hung_replay_is_restarted_and_sigterm_stops_a_wedged_run_within_a_bound(
        procs, tmp_path, endpoint):
    cluster, run_dir = hung_cluster(procs, tmp_path, endpoint, steps=10**7)
    os.kill(service_pid(run_dir, "replay"), signal.SIGSTOP)  # alive, silent
    procs.wait_for_line(cluster, "replay is hung: no stats for", timeout_s=60)
    procs.wait_for_line(cluster, "replay exited with code -9; restarting", timeout_s=30)
    procs.wait_for_line(cluster, "[replay] tpdeb-replay: restored", timeout_s=60)
    def steps() -> int:
        found = re.findall(r"\[learner\] tpdeb-learner: \[\s*([\d,]+)/", procs.output(cluster))
        return int(found[-1].replace(",", ""))

    restored_at, deadline = steps(), time.monotonic() + 60  # and training goes on
    while steps() < restored_at + 5000:
        assert time.monotonic() < deadline, procs.output(cluster)[-3000:]
        time.sleep(0.5)
    assert procs.output(cluster).count("is hung") == 1  # the others went on publishing

    for name in ("learner", "replay", "actor-0", "actor-1"):  # now everything is wedged
        os.kill(service_pid(run_dir, name), signal.SIGSTOP)
    started = time.monotonic()
    cluster.send_signal(signal.SIGTERM)
    code = cluster.wait(90)
    assert code == 130 and time.monotonic() - started < 60, procs.output(cluster)[-3000:]
    assert "SIGTERM: stopping the services" in procs.output(cluster)
    assert not pids_with(str(run_dir))  # every service is gone
