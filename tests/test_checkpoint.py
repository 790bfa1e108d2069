"""Learner checkpoints: rotation and naming, atomicity, a full state round trip, `--resume`
refusals, monotone parameter versions across restarts, and a real learner killed with SIGKILL
and resumed while an actor keeps running."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest
import torch

from tests.procs import Procs, free_port, pids_with
from tests.test_learner import fragments_and_model
from tpdeb.protocol import Keys, Params, Stats, decode
from tpdeb.services.config import ConfigError
from tpdeb.services.config.service import LearnerServiceConfig
from tpdeb.services.learner import LearnerService
from tpdeb.services.net.memory import MemoryBus
from tpdeb.services.net.session import open_session
from tpdeb.services.net.wire import run_spec
from tpdeb.services.process import StopSignal
from tpdeb.services.store import checkpoint as ckpt
from tpdeb.services.store.metrics import MetricsWriter, read_metrics
from tpdeb.tpdeb_core.fragments import stack_fragments
from tpdeb.tpdeb_core.learner import Learner, LossConfig
from tpdeb.tpdeb_core.model import ActorCritic

ENV = "InvertedPendulum-v5"


# -- a LearnerService on the in-memory bus, with a monitor recording its parameter puts ------
class Watched:
    def __init__(self):
        self.bus = MemoryBus()
        self.params: list[bytes] = []
        self.bus.session().declare_subscriber(
            Keys("t").params, lambda sample: self.params.append(sample.payload.to_bytes()))

    def session(self):
        return self.bus.session()

    def published_versions(self) -> list[int]:
        return [decode(data, Params).version for data in self.params]


def config_for(run_dir, **extra) -> LearnerServiceConfig:
    """A learner's settings for a test: its update eager unless the test asks to compile."""
    return LearnerServiceConfig(run_id="t", env_id=ENV, run_dir=str(run_dir),
                                **{"compile": "off", **extra})


def spec_for(obs_dim=4, act_dim=1, env_id=ENV, hidden_sizes=(64, 64), policy_std="global"):
    config = LearnerServiceConfig(env_id=env_id, hidden_sizes=hidden_sizes,
                                  policy_std=policy_std)
    return run_spec(config, obs_dim, act_dim, -np.ones(act_dim), np.ones(act_dim))


def service_for(run_dir, resume_from=None, spec=None,
                **extra) -> tuple[LearnerService, Watched]:
    watched = Watched()
    service = LearnerService(config_for(run_dir, **extra), spec or spec_for(), watched.session(),
                             StopSignal(), resume_from)
    return service, watched


def close(service: LearnerService) -> None:
    service.metrics.close()


def trained_learner(steps=3, seed=0) -> tuple[Learner, list]:
    fragments, model = fragments_and_model(n=6, seed=seed)
    learner = Learner(model, LossConfig(kl_target=0.01))  # adaptive: kl_coef becomes state
    for fragment in fragments:
        learner.observe(fragment)
    n = len(fragments)
    for _ in range(steps):
        learner.step(stack_fragments(fragments), np.arange(n), np.ones(n, np.float32),
                     np.array([True, False] * (n // 2)))
    return learner, fragments


# -- files ----------------------------------------------------------------------------------
def test_periodic_checkpoints_are_named_rotated_and_the_final_one_stays(tmp_path):
    service, _ = service_for(tmp_path, keep_checkpoints=2)
    try:
        written = []
        for step in range(1, 6):
            service.learner.updates = 10 * step
            service.global_step = 1000 * step
            written.append(service.periodic_checkpoint())
        final = service.save_checkpoint(ckpt.FINAL)
    finally:
        close(service)
    names = sorted(p.name for p in (tmp_path / "checkpoints").glob("*.pt"))
    assert names == ["ckpt_40_4000.pt", "ckpt_50_5000.pt", "final_50_5000.pt"]
    assert [p.name for p in written][-1] == "ckpt_50_5000.pt" and final.name == names[-1]
    state = ckpt.load(final)
    assert state["updates"] == 50 and state["global_step"] == 5000
    assert state["version"] == 50  # fresh run: versions are the update count
    assert state["spec"] == {"env_id": ENV, "obs_dim": 4, "act_dim": 1, "hidden_sizes": [64, 64],
                             "policy_std": "global", "action_low": [-1.0], "action_high": [1.0]}
    assert state["config"]["env_id"] == ENV and state["config"]["keep_checkpoints"] == 2
    assert service.checkpoints_written == 5 and service.checkpoint_s > 0


def test_a_full_disk_costs_periodic_checkpoints_one_line_and_keeps_the_last_one(
        tmp_path, monkeypatch, capsys):
    service, _ = service_for(tmp_path)
    real, full = ckpt.save_training, [False]

    def save_training(*args, **kw):
        if full[0]:
            raise OSError(28, "No space left on device")
        return real(*args, **kw)

    monkeypatch.setattr("tpdeb.services.learner.save_training", save_training)
    try:
        service.learner.updates, service.global_step = 10, 1000
        first = service.periodic_checkpoint()
        full[0] = True
        service.learner.updates, service.global_step = 20, 2000
        assert service.periodic_checkpoint() is None
        assert service.periodic_checkpoint() is None  # still full: no second line
        full[0] = False
        service.learner.updates, service.global_step = 30, 3000
        assert service.periodic_checkpoint().name == "ckpt_30_3000.pt"
    finally:
        close(service)
    assert ckpt.load(first)["updates"] == 10  # the previous one stayed valid throughout
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "No space left on device" in err[0] and "goes on" in err[0], err
    assert "stays valid" in err[0]


def test_a_version_mark_the_disk_refuses_holds_the_parameters_back(tmp_path, monkeypatch):
    service, _ = service_for(tmp_path)
    service.mark_guard.retry_s = 0.0  # the next publish tries the disk again
    try:
        service.learner.updates = 1
        service.publish_params()
        published = service.current_version
        service.learner.updates = 5 * ckpt.VERSION_BLOCK  # past the mark: a new one is needed

        def full(*_args, **_kw):
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(ckpt, "write_atomic", full)
        service.publish_params()
        assert service.current_version == published  # never above the mark on disk
        monkeypatch.undo()
        service.publish_params()
        assert service.current_version == 5 * ckpt.VERSION_BLOCK
        assert service.versions.reserved >= service.current_version
    finally:
        close(service)


def test_auto_skips_temp_files_and_a_truncated_newest_checkpoint(tmp_path):
    learner, _ = trained_learner(steps=1)
    config = config_for(tmp_path)
    for updates in (1, 2, 3):
        learner.updates = updates
        good = ckpt.save_training(tmp_path, learner, config, 100 * updates, ckpt.PERIODIC)
    directory = tmp_path / "checkpoints"
    data = good.read_bytes()
    good.write_bytes(data[: len(data) // 2])  # ckpt_3: torn (as if the rename had not been atomic)
    (directory / "final_4_400.pt").write_bytes(b"")  # empty
    # a crash mid-write leaves a temp file; it is complete here, and still never read
    (directory / ".ckpt_9_900.pt.k2j4h5g6").write_bytes(data)
    skipped: list[str] = []
    path, state = ckpt.choose_resume("auto", tmp_path, skipped.append)
    assert path.name == "ckpt_2_200.pt" and state["updates"] == 2
    assert len(skipped) == 2 and all(line.count("\n") == 0 for line in skipped), skipped
    assert "final_4_400.pt" in skipped[0] and "ckpt_3_300.pt" in skipped[1]
    assert "unreadable" in skipped[1]
    assert ckpt.choose_resume("never", tmp_path, skipped.append) is None
    assert ckpt.choose_resume("auto", tmp_path / "elsewhere", skipped.append) is None
    # the next rotation removes the leftover temp file
    ckpt.rotate(directory, keep=3)
    assert not list(directory.glob(".*"))


def test_learner_state_round_trips_through_a_checkpoint(tmp_path):
    learner, fragments = trained_learner(steps=3)
    assert learner.kl_coef != 0.01 and learner.model.obs_rms.count.item() > 0
    path = ckpt.save_training(tmp_path, learner, config_for(tmp_path), 1234, ckpt.PERIODIC,
                              version=1003)
    state = ckpt.read_checkpoint(path)
    assert (state["updates"], state["global_step"], state["version"]) == (3, 1234, 1003)

    torch.manual_seed(99)  # different initial weights: everything must come from the file
    fresh = Learner(ActorCritic(3, 1), LossConfig(kl_target=0.01))
    fresh.load_state_dict(state)
    for name, tensor in learner.model.state_dict().items():  # weights and both normalisers
        assert torch.equal(tensor, fresh.model.state_dict()[name]), name
    for name, tensor in learner.target_policy.state_dict().items():
        assert torch.equal(tensor, fresh.target_policy.state_dict()[name]), name
    saved, loaded = learner.optimizer.state_dict(), fresh.optimizer.state_dict()
    assert saved["param_groups"] == loaded["param_groups"]
    assert saved["state"].keys() == loaded["state"].keys()
    for key, moments in saved["state"].items():
        for name, value in moments.items():
            assert torch.equal(torch.as_tensor(value), torch.as_tensor(loaded["state"][key][name]))
    assert (fresh.kl_coef, fresh.updates) == (learner.kl_coef, learner.updates)

    # complete state: the next update is the same for the original and the restored learner
    n = len(fragments)
    args = (stack_fragments(fragments), np.arange(n), np.ones(n, np.float32),
            np.array([True, False] * (n // 2)))
    a, b = learner.step(*args), fresh.step(*args)
    assert a.metrics == b.metrics
    for x, y in zip(learner.model.parameters(), fresh.model.parameters(), strict=True):
        assert torch.equal(x, y)


def test_a_checkpoint_from_before_the_compiled_learner_loads_its_optimiser_converted(tmp_path):
    """Checkpoints written by the learner's earlier Adam kept torch.optim.Adam's layout with
    plain floats (the learning rate, one step count copied per parameter, no fused or
    capturable flags): they load, the moments and step count kept, this learner's options
    put back, and training goes on."""
    learner, fragments = trained_learner(steps=3)
    state = learner.state_dict()
    groups = state["optimizer"]["param_groups"]
    old = {"state": {k: {"step": torch.tensor(3.0), "exp_avg": v["exp_avg"].clone(),
                         "exp_avg_sq": v["exp_avg_sq"].clone()}
                     for k, v in state["optimizer"]["state"].items()},
           "param_groups": [{"lr": 1e-3, "betas": (0.9, 0.999), "eps": 1e-5, "weight_decay": 0,
                             "amsgrad": False, "maximize": False, "foreach": None,
                             "capturable": False, "differentiable": False, "fused": None,
                             "decoupled_weight_decay": False, "params": groups[0]["params"]}]}
    path = tmp_path / "old.pt"
    torch.save({**state, "optimizer": old, "global_step": 1234, "version": 3}, path)
    fresh = Learner(ActorCritic(3, 1), LossConfig(kl_target=0.01, adam_eps=1e-6))
    fresh.load_state_dict(ckpt.read_checkpoint(path))
    group = fresh.optimizer.param_groups[0]
    assert group["fused"] and isinstance(group["lr"], torch.Tensor) and group["eps"] == 1e-6
    assert fresh.learning_rate() == pytest.approx(1e-3)
    for p, q in zip(learner.params, fresh.params, strict=True):
        for name in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(learner.optimizer.state[p][name], fresh.optimizer.state[q][name])
        assert int(fresh.optimizer.state[q]["step"]) == 3
    n = len(fragments)
    fresh.step(stack_fragments(fragments), np.arange(n), np.ones(n, np.float32), np.ones(n, bool))
    assert fresh.updates == 4 and int(fresh.optimizer.state[fresh.params[0]]["step"]) == 4


def test_metrics_append_after_a_torn_last_line(tmp_path):
    (tmp_path / "metrics.jsonl").write_text('{"global_step": 1, "a": 1.0}\n{"global_st')
    writer = MetricsWriter(tmp_path)
    writer.log(2, {"a": 2.0})
    writer.close()
    assert read_metrics(tmp_path / "metrics.jsonl") == [
        {"global_step": 1, "a": 1.0}, {"global_step": 2, "a": 2.0}]


# -- refusals --------------------------------------------------------------------------------
def test_resume_path_that_is_missing_or_unreadable_is_one_line_and_exit_2(tmp_path):
    procs = Procs(tmp_path)
    missing = tmp_path / "missing.pt"
    try:
        # nothing listens at --connect: the refusal comes before any network wait
        learner = procs.spawn("learner", "--env-id", ENV, "--run-dir", str(tmp_path / "r"),
                              "--resume", str(missing), "--connect",
                              f"tcp/127.0.0.1:{free_port()}", "--connect-timeout-s", "60")
        assert learner.wait(60) == 2
        lines = procs.output(learner).strip().splitlines()
        assert len(lines) == 1 and f"--resume {missing}: no such checkpoint file" in lines[0], \
            lines
    finally:
        procs.stop_all()
    bad = tmp_path / "garbage.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ConfigError) as refused:
        ckpt.choose_resume(str(bad), tmp_path, print)
    line = str(refused.value)
    assert "\n" not in line and f"--resume {bad}: unreadable" in line, line


def test_a_checkpoint_of_another_env_is_refused(tmp_path):
    service, _ = service_for(tmp_path, spec=spec_for(11, 3, "Hopper-v5"))
    service.learner.updates = 7
    service.save_checkpoint(ckpt.FINAL)
    close(service)
    resume = ckpt.choose_resume("auto", tmp_path, print)
    with pytest.raises(ConfigError) as refused:
        service_for(tmp_path, resume_from=resume)  # the run trains InvertedPendulum (4, 1)
    line = str(refused.value)
    assert "\n" not in line and "Hopper-v5" in line and ENV in line and "obs_dim 11" in line
    assert "--resume never" in line
    # same env, other network sizes: refused too, before torch's size-mismatch error
    with pytest.raises(ConfigError, match="hidden sizes"):
        service_for(tmp_path, resume_from=resume, spec=spec_for(11, 3, "Hopper-v5", (32,)))


def test_a_checkpoint_from_before_the_policy_setting_loads_and_another_policy_is_refused(tmp_path):
    """Checkpoints written before `policy_std` existed record no such field and hold the
    global log-std's weights under the same names: they resume; a run whose policy has the
    other standard deviation refuses them in one line naming the setting."""
    service, _ = service_for(tmp_path)
    service.learner.updates = 5
    path = service.save_checkpoint(ckpt.FINAL)
    close(service)
    state = ckpt.read_checkpoint(path)
    del state["spec"]["policy_std"]  # as the earlier layout wrote it
    ckpt.save_atomic(state, path)
    resume = ckpt.choose_resume("auto", tmp_path, print)
    restored, _ = service_for(tmp_path, resume_from=resume)
    assert restored.learner.updates == 5
    close(restored)
    with pytest.raises(ConfigError) as refused:
        service_for(tmp_path, resume_from=resume, spec=spec_for(policy_std="state"))
    line = str(refused.value)
    assert "\n" not in line and "global log-std" in line and "--policy-std global" in line


# -- versions --------------------------------------------------------------------------------
def test_version_mark_reserves_blocks_and_survives_a_bad_file(tmp_path):
    mark = ckpt.VersionMark(tmp_path, block=10)
    assert mark.reserved == -1 and mark.offset(0) == 0
    mark.reserve(0)
    assert ckpt.VersionMark(tmp_path).reserved == 10
    mark.reserve(10)  # within the block: no write
    assert ckpt.VersionMark(tmp_path).reserved == 10
    mark.reserve(11)
    assert ckpt.VersionMark(tmp_path).reserved == 21
    # a restart from a checkpoint at 5 updates publishes 22 first; from 30 updates, 30
    assert ckpt.VersionMark(tmp_path).offset(5) == 17
    assert ckpt.VersionMark(tmp_path).offset(30) == 0
    assert ckpt.VersionMark(tmp_path).offset(5, restored_version=40) == 36  # mark deleted
    (tmp_path / ckpt.VersionMark.FILE).write_text("{oops")
    with pytest.raises(ConfigError, match="params_version.json") as bad:
        ckpt.VersionMark(tmp_path)
    assert "\n" not in str(bad.value)


def test_versions_stay_monotone_when_the_learner_dies_after_its_checkpoint(tmp_path,
                                                                          monkeypatch):
    monkeypatch.setattr(ckpt, "VERSION_BLOCK", 100)
    published: list[int] = []
    resume = None
    for restart in range(3):
        service, session = service_for(tmp_path, resume_from=resume)
        try:
            service.publish_params()
            for i in range(1, 241):  # beyond a reserved block
                service.learner.updates += 1
                service.publish_params()
                if i == 15:
                    service.periodic_checkpoint()  # then 225 more versions go out: lost
        finally:
            close(service)  # a crash: no final checkpoint
        versions = session.published_versions()
        assert versions == sorted(set(versions)), "versions within one run must increase"
        if published:
            assert versions[0] > max(published), (restart, versions[0], max(published))
        published += versions
        resume = ckpt.choose_resume("auto", tmp_path, print)
        assert resume[1]["updates"] == 15 * (restart + 1)
    # the restored learner counts updates from its checkpoint, versions from the mark
    assert service.learner.updates == 15 * 2 + 240
    assert published == sorted(set(published))


def test_resume_never_sets_earlier_checkpoints_aside(tmp_path, capsys):
    service, _ = service_for(tmp_path)
    service.learner.updates = 50
    service.publish_params()
    service.save_checkpoint(ckpt.FINAL)
    close(service)
    service, session = service_for(tmp_path, resume="never")
    try:
        service.publish_params()
    finally:
        close(service)
    assert service.learner.updates == 0 and session.published_versions()[0] > 50
    assert not list((tmp_path / "checkpoints").glob("*.pt"))
    assert list((tmp_path / "checkpoints").glob("before_*/final_50_0.pt"))
    assert "moved to" in capsys.readouterr().out


# -- a real learner killed and resumed -------------------------------------------------------
def test_killed_learner_resumes_and_actor_versions_never_go_down(tmp_path):
    procs = Procs(tmp_path)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    run_dir = tmp_path / "run"
    # long enough that the learner is still training at its first periodic checkpoint however
    # fast the machine is
    common = ["--run-id", "ck", "--env-id", ENV, "--num-envs", "2", "--total-timesteps", "40000",
              "--run-dir", str(run_dir)]
    learner_args = [*common, "--connect", endpoint, "--checkpoint-interval-s", "1",
                    "--log-interval-s", "1"]
    session = None
    try:
        replay = procs.spawn("replay", *common, "--listen", endpoint)
        procs.wait_for_line(replay, "serving")
        session = open_session("client", [], [endpoint], connect_timeout_s=30)
        seen: list = []  # (time, param_version) of actor 0 in arrival order (append: atomic)
        session.declare_subscriber(Keys("ck").stats("actor", 0), lambda s: seen.append(
            (time.monotonic(), decode(s.payload.to_bytes(), Stats).values["param_version"])))
        learner = procs.spawn("learner", *learner_args)
        procs.spawn("actor", *common, "--connect", endpoint, "--actor-id", "0")

        deadline = time.monotonic() + 90
        while not (list((run_dir / "checkpoints").glob("ckpt_*.pt")) and seen):
            assert time.monotonic() < deadline, procs.output(learner)
            assert learner.poll() is None, procs.output(learner)
            time.sleep(0.2)
        os.kill(learner.pid, signal.SIGKILL)
        assert learner.wait(10) == -signal.SIGKILL
        killed_at = time.monotonic()

        again = procs.spawn("learner", *learner_args, name="learner-again")
        procs.wait_for_line(again, "resumed from", timeout_s=60)
        assert again.wait(120) == 0, procs.output(again)[-3000:]
        line = next(x for x in procs.output(again).splitlines() if "resumed from" in x)
        assert str(run_dir / "checkpoints" / "ckpt_") in line, line
        versions = list(seen)
        before = [v for t, v in versions if t < killed_at]
        after = [v for t, v in versions if t > killed_at]
        assert before and after, versions
        values = [v for _, v in versions]
        assert values == sorted(values), f"the actor's version went down: {values}"
        assert max(after) > max(before)  # it took the resumed learner's parameters
        steps = [r["global_step"] for r in read_metrics(run_dir / "metrics.jsonl")]
        assert max(steps) >= 40000
    finally:
        if session is not None:
            session.close()
        procs.stop_all()
    assert not procs.leftovers(), "a service outlived its test"
    assert not pids_with(str(tmp_path)), "a service process outlived its test"
