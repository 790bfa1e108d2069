"""A run's two limits: `total_timesteps` and `train_for_seconds`, whichever binds first; the
progress schedules follow; the clock survives a checkpoint; the single-process runner and the
cluster stop on time with a final checkpoint, `end.json` and exit status 0."""

from __future__ import annotations

import io
import json
import math
import subprocess
import sys

import numpy as np
import pytest

from tests.procs import ROOT, pids_with
from tests.test_checkpoint import close, service_for, spec_for
from tpdeb.services.budget import SECONDS, STEPS, Budget, clock
from tpdeb.services.config import ConfigError
from tpdeb.services.config.service import LearnerServiceConfig
from tpdeb.services.launcher.status import Display
from tpdeb.services.store import checkpoint as ckpt
from tpdeb.services.store.metrics import read_metrics

ENV = "InvertedPendulum-v5"


class FakeClock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def test_the_limit_that_binds_first_ends_the_run_and_progress_is_the_one_further_along():
    now = FakeClock()
    budget = Budget(1000, 60.0, now=now)
    assert budget.reached(0) is None and budget.progress(0) == 0.0
    now.t += 15
    assert budget.progress(100) == pytest.approx(0.25)  # time is further along than steps (0.1)
    assert budget.progress(500) == pytest.approx(0.5)  # now the steps are
    assert budget.time_left() == pytest.approx(45.0) and budget.shown() == " | 0:45 left"
    assert budget.reached(999) is None and budget.reached(1000) == STEPS
    now.t += 45
    assert budget.reached(10) == SECONDS and budget.progress(10) == 1.0


def test_without_a_time_limit_only_the_steps_count():
    now = FakeClock()
    budget = Budget(1000, now=now)
    now.t += 1e9
    assert budget.progress(250) == 0.25 and budget.reached(999) is None
    assert budget.time_left() is None and budget.shown() == ""
    assert budget.describe() == "1,000 steps"


def test_a_restarted_clock_goes_on_from_the_time_spent_before():
    now = FakeClock()
    budget = Budget(10**6, 100.0, spent_before=70.0, now=now)
    now.t += 500  # the learner waited before its loop: not training time
    budget.restart_clock()
    now.t += 20
    assert budget.elapsed() == pytest.approx(90.0) and budget.reached(0) is None
    now.t += 10
    assert budget.reached(0) == SECONDS


def test_announcement_and_clock_format():
    assert Budget(2_000_000, 900).describe() == (
        "2,000,000 steps or 15:00 (900 s) of training, whichever comes first")
    assert [clock(s) for s in (0, 59.6, 61, 3600, 3725)] == [
        "0:00", "1:00", "1:01", "1:00:00", "1:02:05"]


@pytest.mark.parametrize("value", [-1.0, math.nan, math.inf])
def test_a_bad_time_limit_is_refused_naming_it(value):
    with pytest.raises(ConfigError, match="train_for_seconds=.*finite number ≥ 0"):
        LearnerServiceConfig(train_for_seconds=value)


def test_the_training_time_is_checkpointed_and_a_restored_learner_goes_on_from_it(tmp_path):
    service, _ = service_for(tmp_path, train_for_seconds=100.0)
    try:
        now = FakeClock()
        service.budget = Budget(service.config.total_timesteps, 100.0, now=now)
        now.t += 42
        service.learner.updates, service.global_step = 3, 300
        path = service.save_checkpoint(ckpt.FINAL)
    finally:
        close(service)
    assert ckpt.load(path)["train_elapsed_s"] == pytest.approx(42.0)
    resumed, _ = service_for(tmp_path, (path, ckpt.load(path)), train_for_seconds=100.0)
    try:
        assert resumed.budget.spent_before == pytest.approx(42.0)
        resumed.budget.restart_clock()  # what run() does
        assert 57.0 < resumed.budget.time_left() <= 58.0
        assert resumed.beta() > resumed.config.beta_start  # β follows the time already spent
    finally:
        close(resumed)


def test_serial_run_stops_on_time_with_its_checkpoint_and_anneals_over_the_time(tmp_path):
    run_dir = tmp_path / "run"
    cmd = [sys.executable, "-m", "tpdeb.services.serial", "--env-id", ENV, "--run-dir",
           str(run_dir), "--total-timesteps", "100000000", "--train-for-seconds", "4",
           "--num-envs", "2", "--log-interval-s", "1", "--anneal-lr", "true"]
    result = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    out = result.stdout + result.stderr
    assert "100,000,000 steps or 0:04 (4 s) of training, whichever comes first" in out
    assert " left" in out and "(train_for_seconds reached)" in out
    end = json.loads((run_dir / "end.json").read_text())
    assert end["ended_by"] == SECONDS and 0 < end["global_step"] < 100_000_000
    assert end["train_elapsed_s"] >= 4.0
    (final,) = (run_dir / "checkpoints").glob("final_*.pt")
    assert str(final) == end["checkpoint"] and ckpt.load(final)["train_elapsed_s"] >= 4.0
    assert "train_for_seconds = 4.0" in (run_dir / "config.toml").read_text()
    rates = [r["charts/learning_rate"] for r in read_metrics(run_dir / "metrics.jsonl")
             if "charts/learning_rate" in r]
    # the steps are under 1 % of theirs: annealing by steps would have left the rate near 1e-3
    assert rates[-1] < 0.3e-3, rates


def test_the_log_std_ceiling_falls_with_the_run_and_needs_the_global_log_std(tmp_path):
    service, _ = service_for(tmp_path, anneal_log_std=True, init_log_std=-0.5,
                             final_log_std=-2.0, total_timesteps=1000, train_for_seconds=0.0)
    try:
        assert service.learner.log_std_ceiling is None  # until the first batch
        service.global_step = 600
        service.follow_schedules()
        assert service.learner.log_std_ceiling == pytest.approx(-0.5 - 1.5 * 0.6)
        assert service.learner.optimizer.param_groups[0]["lr"] == service.config.learning_rate
    finally:
        close(service)
    with pytest.raises(ConfigError, match="anneal_log_std=true holds the global log-std"):
        LearnerServiceConfig(anneal_log_std=True, policy_std="state")


def test_schedule_steps_end_the_schedules_before_the_run_and_hold_their_end_values(tmp_path):
    service, _ = service_for(tmp_path, anneal_log_std=True, anneal_lr=True, init_log_std=0.0,
                             final_log_std=-1.0, total_timesteps=10_000, train_for_seconds=0.0,
                             schedule_steps=1000)
    lr = service.config.learning_rate
    try:
        service.global_step = 250  # the schedules' 0.25, the run's 0.025
        service.follow_schedules()
        assert service.learner.log_std_ceiling == pytest.approx(-0.25)
        assert service.learner.optimizer.param_groups[0]["lr"] == pytest.approx(0.75 * lr)
        service.global_step = 5000  # past schedule_steps: the end values, held
        service.follow_schedules()
        assert service.learner.log_std_ceiling == pytest.approx(-1.0)
        assert service.learner.optimizer.param_groups[0]["lr"] == pytest.approx(1e-3 * lr)
    finally:
        close(service)
    with pytest.raises(ConfigError, match="schedule_steps=-1: must be ≥ 0"):
        LearnerServiceConfig(schedule_steps=-1)


def test_the_observation_normaliser_holds_after_obs_norm_steps_and_the_returns_keep_going(
        tmp_path):
    from tests.test_compiled import reply
    from tests.test_learner import fragments_and_model
    from tpdeb.protocol import Moments

    fragments, _ = fragments_and_model(n=12, seed=5)
    service, _ = service_for(tmp_path, spec=spec_for(obs_dim=3, act_dim=1), compile="off",
                             obs_norm_steps=1000)
    obs, ret = service.model.obs_rms, service.model.ret_rms

    def train(step: int, seed: int) -> None:
        service.global_step = step
        batch = reply(fragments, seed)
        batch.obs_moments = Moments(64.0, np.full(3, float(seed)), np.ones(3))
        batch.ret_moments = Moments(64.0, np.array(float(seed)), np.array(1.0))
        service.train_on(batch)

    try:
        train(500, 1)
        assert (float(obs.count), float(ret.count)) == (64.0, 64.0)
        train(999, 2)  # still before obs_norm_steps
        held = (float(obs.count), obs.mean.clone(), obs.m2.clone())
        assert held[0] == 128.0
        for seed in (3, 4):
            train(1000 + seed, seed)  # from obs_norm_steps on: held; the returns' still merge
        assert float(obs.count) == held[0]
        np.testing.assert_array_equal(obs.mean, held[1])
        np.testing.assert_array_equal(obs.m2, held[2])
        assert float(ret.count) == 256.0
    finally:
        close(service)
    with pytest.raises(ConfigError, match="obs_norm_steps=-5: must be ≥ 0"):
        LearnerServiceConfig(obs_norm_steps=-5)


def test_cluster_stops_on_time_and_exits_0(procs, tmp_path):
    run_dir = tmp_path / "run"
    cluster = procs.spawn("cluster", "--env-id", ENV, "--total-timesteps", "100000000",
                          "--train-for-seconds", "6", "--num-envs", "2", "--actors", "1",
                          "--run-dir", str(run_dir))
    assert cluster.wait(180) == 0, procs.output(cluster)[-3000:]
    out = procs.output(cluster)
    assert "100,000,000 steps or 0:06 (6 s) of training, whichever comes first" in out
    end = json.loads((run_dir / "end.json").read_text())
    assert end["ended_by"] == SECONDS and end["train_elapsed_s"] >= 6.0
    assert list((run_dir / "checkpoints").glob("final_*.pt"))
    assert not pids_with(str(run_dir))  # every service is gone


def test_the_status_line_shows_the_time_left_beside_the_steps():
    display = Display(io.StringIO())
    display.latest[("learner", "0")] = {"global_step": 5000, "total_timesteps": 10000,
                                        "sps": 100.0, "mean_return": 1.0}
    texts = [text for text, _ in display.parts("up")]
    assert not any("left" in t for t in texts)  # no time limit, no clock
    display.latest[("learner", "0")]["time_left_s"] = 754.2
    texts = [text for text, _ in display.parts("up")]
    assert texts[:2] == ["5,000/10,000 steps (50%)", "12:34 left"]
