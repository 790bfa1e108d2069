"""No training lost: `tpdeb-train` continues a run dir from its newest checkpoint as the cluster's
learner does (networks, optimiser, normalisers, KL coefficient, step count and clock), writes
periodic checkpoints by default, refuses a run dir of another configuration, and its metrics and
events go on in the same files; a stopped run's checkpoint is no final one. Evaluation while
training logs its figures and keeps the best."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import tpdeb
from tpdeb.services.config import resolve
from tpdeb.services.config.train import TrainConfig
from tpdeb.services.evaluator import Best, Schedule
from tpdeb.services.serial import SerialRunner
from tpdeb.services.store.metrics import MetricsWriter, read_metrics

ROOT = Path(__file__).resolve().parents[1]
ENV = "InvertedPendulum-v5"
FLAGS = ["--env-id", ENV, "--num-envs", "2", "--hidden-sizes", "16", "16", "--seed", "2",
         "--log-interval-s", "0.2", "--eval-interval", "0"]


def train(run_dir: Path, *flags: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "tpdeb.services.serial", "--run-dir",
                           str(run_dir), *FLAGS, *flags], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)


def test_the_same_command_continues_the_run_to_its_total(tmp_path):
    run = tmp_path / "run"
    first = train(run, "--total-timesteps", "2048")
    assert first.returncode == 0, first.stderr
    (before,) = (run / "checkpoints").glob("final_*.pt")
    saved = torch.load(before, weights_only=False)
    second = train(run, "--total-timesteps", "4096")
    assert second.returncode == 0, second.stderr
    assert f"resumed from {before}" in second.stdout
    assert "the replay is kept in memory and starts empty" in second.stdout
    (after,) = (run / "checkpoints").glob("final_*_4*.pt")
    state = torch.load(after, weights_only=False)
    assert state["updates"] > saved["updates"] and state["global_step"] >= 4096
    assert state["train_elapsed_s"] > saved["train_elapsed_s"]  # the clock goes on
    assert state["model"]["obs_rms.count"] > saved["model"]["obs_rms.count"]
    steps = [row["global_step"] for row in read_metrics(run / "metrics.jsonl")]
    assert steps == sorted(steps) and steps[-1] >= 4096  # one run, never restarted
    assert len(list(run.glob("events.out.tfevents.*"))) == 1
    third = train(run, "--total-timesteps", "4096", "--seed", "5")
    assert third.returncode == 2
    assert third.stderr.strip().count("\n") == 0 and "holds another run" in third.stderr
    assert "seed=2, this one 5" in third.stderr


def test_a_stopped_run_keeps_a_periodic_checkpoint_and_resumes_from_it(tmp_path, monkeypatch):
    monkeypatch.setenv("TPDEB_COMPILE", "off")
    config = resolve(TrainConfig, [*FLAGS, "--run-dir", str(tmp_path / "run"),
                                   "--total-timesteps", "100000",
                                   "--checkpoint-interval-s", "0.01"], "tpdeb-train", "")
    assert TrainConfig().checkpoint_interval_s > 0  # periodic checkpoints by default
    runner = SerialRunner(config)
    learn = runner.learn

    def until_updates():  # Ctrl-C once some updates are done
        learn()
        if runner.learner.learner.updates >= 20:
            raise KeyboardInterrupt

    runner.learn = until_updates
    summary = runner.run()
    assert summary["interrupted"]
    names = sorted(p.name for p in (tmp_path / "run" / "checkpoints").glob("*.pt"))
    assert names and not any(n.startswith("final_") for n in names)
    again = SerialRunner(config)
    assert again.learner.resumed and again.learner.learner.updates >= 20
    again.learner.finish(False)
    again.replay.close()
    again.actor.close()


def test_a_resumed_learner_drops_the_rows_after_its_checkpoint_and_continues_its_events(
        tmp_path):
    writer = MetricsWriter(tmp_path)
    for step in (100, 200, 300):
        writer.log(step, {"charts/SPS": float(step)})
    writer.close()
    resumed = MetricsWriter(tmp_path, resume_step=200)
    resumed.log(250, {"charts/SPS": 1.0})
    resumed.close()
    assert [r["global_step"] for r in read_metrics(tmp_path / "metrics.jsonl")] == [100, 200,
                                                                                   250]
    (events,) = tmp_path.glob("events.out.tfevents.*")
    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader

    records = list(EventFileLoader(str(events)).Load())
    starts = [e.step for e in records if e.HasField("session_log")]
    assert starts == [200]  # TensorBoard drops the orphaned step 300 at this start


def test_evaluation_is_due_by_steps_or_by_seconds():
    steps = Schedule(1000, 0.0)
    assert not steps.due(500, 0.0) and steps.due(1000, 0.0)
    steps.done(1100, 0.0)
    assert not steps.due(1999, 0.0) and steps.due(2000, 0.0)
    resumed = Schedule(1000, 0.0)
    assert not resumed.due(5500, 0.0) and resumed.due(6000, 0.0)  # the next multiple
    seconds = Schedule(0, 60.0)
    assert not seconds.due(0, 10.0) and seconds.due(0, 70.0)
    assert not Schedule(0, 0.0).due(10**9, 10**9)
    with pytest.raises(Exception, match="eval_interval='1e3x'"):
        TrainConfig(eval_interval="1e3x")


def test_the_best_evaluation_survives_a_restart(tmp_path):
    from tpdeb.services.evaluate import Evaluation

    def result(mean):
        return Evaluation(mean, 0.0, (mean,), (10,))

    best = Best(tmp_path)
    assert best.offer(result(5.0), 3, 100) and not best.offer(result(4.0), 4, 200)
    assert not Best(tmp_path).offer(result(5.0), 5, 300)
    assert json.loads((tmp_path / "best.json").read_text())["param_version"] == 3


def test_training_evaluates_inline_and_keeps_the_best(tmp_path):
    run = tmp_path / "run"
    result = train(run, "--total-timesteps", "3072", "--eval-interval", "1024",
                   "--eval-episodes", "2")
    assert result.returncode == 0, result.stderr
    rows = [r for r in read_metrics(run / "metrics.jsonl") if "eval/mean_return" in r]
    assert [r["global_step"] // 1024 for r in rows] == [1, 2, 3]
    best = json.loads((run / "best.json").read_text())
    assert best["mean_return"] == max(r["eval/mean_return"] for r in rows)
    policy = tpdeb.load_policy(run / "best_policy.npz")
    evaluation = tpdeb.evaluate(policy, episodes=2, seed=2**31 + 2)  # the evaluation's starts
    assert evaluation.mean == pytest.approx(best["mean_return"])
    state = torch.load(run / "checkpoints" / "best.pt", weights_only=False)
    assert state["eval_mean_return"] == best["mean_return"]
    np.testing.assert_allclose(state["model"]["obs_rms.mean"],
                               policy.file_arrays["obs_rms.mean"], rtol=1e-6)
    assert "evaluation took" in result.stdout  # its cost, stated
