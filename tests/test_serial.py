"""The single-process runner end to end: CLI errors, run-directory contents, reproducibility,
and learning InvertedPendulum-v5."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from tpdeb.services.serial import main
from tpdeb.services.store.metrics import read_metrics

ROOT = Path(__file__).resolve().parents[1]


def train(run_dir: Path, *flags: str, timeout_s: float = 600) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "tpdeb.services.serial", "--run-dir", str(run_dir), *flags]
    # subprocess.run kills the child if the timeout expires, so nothing is left behind
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout_s)


def test_unknown_env_id_is_one_clear_line(capsys):
    assert main(["--env-id", "HalfCheeta-v5", "--total-timesteps", "10"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "HalfCheeta-v5" in err[0] and "HalfCheetah-v5" in err[0]  # names the likely fix


def test_discrete_env_is_refused(capsys):
    assert main(["--env-id", "CartPole-v1", "--total-timesteps", "10"]) == 2
    assert "continuous (Box) action spaces only" in capsys.readouterr().err


def test_short_run_writes_the_run_directory_and_is_reproducible(tmp_path):
    flags = ["--env-id", "InvertedPendulum-v5", "--total-timesteps", "4096", "--seed", "3",
             "--num-envs", "4", "--log-interval-s", "0.5"]
    first = train(tmp_path / "a", *flags)
    assert first.returncode == 0, first.stderr
    assert "[     4,096/4,096]" in first.stdout  # progress lines
    rows = read_metrics(tmp_path / "a" / "metrics.jsonl")
    keys = set().union(*rows)
    for key in ("global_step", "charts/episodic_return", "charts/SPS", "losses/policy_loss",
                "losses/value_loss", "losses/kl_behaviour", "replay/prioritized_items"):
        assert key in keys, key
    assert max(r["global_step"] for r in rows) == 4096
    assert json.loads((tmp_path / "a" / "end.json").read_text())["ended_by"] == "total_timesteps"
    assert list((tmp_path / "a").glob("events.out.tfevents.*"))
    assert 'env_id = "InvertedPendulum-v5"' in (tmp_path / "a" / "config.toml").read_text()
    (checkpoint,) = (tmp_path / "a" / "checkpoints").glob("final_*_4096.pt")
    state = torch.load(checkpoint, weights_only=False)
    assert {"model", "target_policy", "optimizer", "config", "version"} <= set(state)
    assert "obs_rms.mean" in state["model"]  # normaliser saved with the model

    # same seed, same config file: same episodes and the same losses
    second = train(tmp_path / "b", "--config", str(tmp_path / "a" / "config.toml"),
                   "--run-dir", str(tmp_path / "b"))
    assert second.returncode == 0, second.stderr

    def learning(run):
        return [{k: v for k, v in r.items() if not k.startswith(("charts/SPS", "perf/"))}
                for r in read_metrics(tmp_path / run / "metrics.jsonl")
                if "charts/episodic_return" in r]
    assert learning("a") == learning("b")


@pytest.mark.slow
def test_learns_inverted_pendulum_within_100k_steps(tmp_path):
    result = train(tmp_path / "run", "--env-id", "InvertedPendulum-v5", "--total-timesteps",
                   "100000", "--seed", "1", "--log-interval-s", "20")
    assert result.returncode == 0, result.stderr
    returns = [r["charts/episodic_return"] for r in read_metrics(tmp_path / "run" / "metrics.jsonl")
               if "charts/episodic_return" in r]
    last = returns[-20:]
    assert sum(last) / len(last) >= 900, json.dumps(returns[-40:])
