"""The Python API: `tpdeb.train` runs a run (one process or a cluster) and returns it,
`tpdeb.load_policy` gives its policy acting with numpy alone, exactly as the trained network
does; bad settings and bad inputs raise one clear error."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import tpdeb
from tpdeb.services.evaluate import load_policy as load_torch_policy
from tpdeb.services.policy_file import POLICY_FILE, policy_bytes

ENV = "InvertedPendulum-v5"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("api") / "run"
    return tpdeb.train(ENV, total_timesteps=2048, seed=3, run_dir=out, quiet=True,
                       num_envs=2, hidden_sizes=[32, 32])


def test_train_returns_the_finished_run(run):
    assert run.ended_by == "total_timesteps" and run.global_step >= 2048
    assert run.checkpoint is not None and run.checkpoint.name.startswith("final_")
    assert (run.run_dir / POLICY_FILE).is_file()
    assert len(run.returns) > 10 and run.returns[-1][0] > 1024
    assert any("losses/policy_loss" in row for row in run.metrics)
    config = (run.run_dir / "config.toml").read_text()
    assert "hidden_sizes = [32, 32]" in config and "seed = 3" in config


def test_the_numpy_policy_acts_as_the_trained_network(run):
    model, env_id, _ = load_torch_policy(run.checkpoint, None)
    policy = tpdeb.load_policy(run.run_dir)
    from_checkpoint = tpdeb.load_policy(run.checkpoint)
    assert env_id == policy.env_id == from_checkpoint.env_id == ENV
    obs = np.random.default_rng(0).normal(0.0, 2.0, (64, 4)).astype(np.float32)
    expected = np.clip(model.act_deterministic(obs), -3.0, 3.0)
    np.testing.assert_allclose(policy.act(obs, deterministic=True), expected, rtol=0, atol=1e-5)
    np.testing.assert_allclose(from_checkpoint.act(obs, deterministic=True), expected, rtol=0,
                               atol=1e-5)
    assert policy.act(obs[0]).shape == (1,)  # one observation in, one action out
    sampled = policy.act(obs, deterministic=False, rng=np.random.default_rng(1))
    assert sampled.shape == (64, 1) and not np.allclose(sampled,
                                                        policy.act(obs, deterministic=True))
    assert np.all(np.abs(sampled) <= 3.0)


def test_loading_a_policy_file_needs_no_torch(run):
    code = (f"import sys, numpy as np, tpdeb; p = tpdeb.load_policy({str(run.run_dir)!r}); "
            "a = p.act(np.zeros(4)); print(json.dumps([float(a[0]), 'torch' in sys.modules, "
            "'gymnasium' in sys.modules]))")
    out = subprocess.run([sys.executable, "-c", "import json; " + code], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    action, torch_loaded, gym_loaded = json.loads(out.stdout)
    assert not torch_loaded and not gym_loaded and abs(action) <= 3.0


@pytest.mark.parametrize("obs, message", [
    (np.zeros(5), r"an observation of shape \(5,\), but this policy \(InvertedPendulum-v5\) "
                  r"takes \(4,\) or \(N, 4\)"),
    (np.zeros((2, 3, 4)), r"shape \(2, 3, 4\)"),
])
def test_a_wrong_observation_is_refused_in_one_line(run, obs, message):
    with pytest.raises(tpdeb.PolicyError, match=message):
        tpdeb.load_policy(run.run_dir).act(obs)


def test_bad_policy_sources_are_refused_in_one_line(run, tmp_path):
    with pytest.raises(tpdeb.PolicyError, match="was trained on InvertedPendulum-v5, not "
                                                "Hopper-v5"):
        tpdeb.load_policy(run.run_dir, env_id="Hopper-v5")
    with pytest.raises(tpdeb.PolicyError, match="no such run directory, policy file or "
                                                "checkpoint"):
        tpdeb.load_policy(tmp_path / "nothing")
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    with pytest.raises(tpdeb.PolicyError, match="junk.npz: not a policy file"):
        tpdeb.load_policy(junk)
    other = tmp_path / "other.npz"
    np.savez(other, meta=np.frombuffer(b'{"format": "something"}', np.uint8))
    with pytest.raises(tpdeb.PolicyError, match="not a policy file \\(format 'something'\\)"):
        tpdeb.load_policy(other)
    with pytest.raises(tpdeb.PolicyError, match="no checkpoints"):
        tpdeb.load_policy(tmp_path)


@pytest.mark.parametrize("kwargs, message", [
    ({"learning_rat": 3e-4}, "unknown setting 'learning_rat' \\(did you mean 'learning_rate'"),
    ({"zeta": 2}, "zeta=2.0: must be in \\[0, 1\\]"),
    ({"actors": 2}, "actors= needs cluster=True"),
    ({"env_kwargs": {"no_such_argument": 1}}, "env_kwargs .* do not fit 'InvertedPendulum-v5'"),
    ({"device": "cuda:7"}, "device='cuda:7'"),
    ({"seed": -1}, "seed=-1: must be an integer"),
])
def test_bad_settings_raise_before_anything_starts(tmp_path, kwargs, message):
    with pytest.raises(tpdeb.TrainError, match=message):
        tpdeb.train(ENV, total_timesteps=1000, run_dir=tmp_path / "run", **kwargs)
    assert not (tmp_path / "run").exists()
    with pytest.raises(tpdeb.TrainError, match="not a registered gymnasium environment"):
        tpdeb.train("NoSuchEnv-v0", total_timesteps=1000)


def test_an_unwritable_run_dir_is_one_error_before_anything_starts(tmp_path):
    (tmp_path / "file").write_text("")
    with pytest.raises(tpdeb.TrainError, match="is a file, not a directory"):
        tpdeb.train(ENV, total_timesteps=1000, run_dir=tmp_path / "file" / "run")
    with pytest.raises(tpdeb.TrainError, match="cannot write there"):
        tpdeb.train(ENV, total_timesteps=1000, run_dir="/proc/tpdeb-run")


def test_train_runs_a_cluster_that_evaluates_while_it_trains(tmp_path):
    run = tpdeb.train(ENV, total_timesteps=24_576, seed=2, cluster=True, actors=1, quiet=True,
                      run_dir=tmp_path / "run", num_envs=2, learning_rate=5e-4,
                      eval_interval=4096, eval_episodes=2)
    assert run.ended_by == "total_timesteps" and run.checkpoint is not None
    assert "learning_rate = 0.0005" in (run.run_dir / "train.toml").read_text()
    assert (run.run_dir / "logs").is_dir() and (run.run_dir / "train.log").is_file()
    assert run.policy().act(np.zeros(4)).shape == (1,)
    # the evaluator's figures, logged by the learner; the best policy and checkpoint kept
    evaluations = [r for r in run.metrics if "eval/mean_return" in r]
    assert evaluations and (run.run_dir / "best_policy.npz").is_file()
    best = json.loads((run.run_dir / "best.json").read_text())
    # (an evaluation that ends after the learner has finished is not logged)
    assert best["mean_return"] >= max(r["eval/mean_return"] for r in evaluations)
    assert (run.run_dir / "checkpoints" / "best.pt").is_file()
    assert tpdeb.evaluate(run.run_dir / "best_policy.npz", episodes=2,
                          seed=2**31 + 2).mean == pytest.approx(best["mean_return"])


def test_a_run_continues_from_python_and_a_progress_hook_stops_it(run, tmp_path):
    import shutil

    again = tmp_path / "run"
    shutil.copytree(run.run_dir, again)
    seen: list[tuple[int, dict]] = []

    def on_progress(step: int, metrics: dict) -> bool:
        seen.append((step, metrics))
        return "charts/SPS" not in metrics or step < 3000  # stop past 3,000 steps

    more = tpdeb.train(ENV, total_timesteps=100_000, seed=3, run_dir=again, quiet=True,
                       num_envs=2, hidden_sizes=[32, 32], on_progress=on_progress,
                       log_interval_s=0.2)
    assert more.ended_by == "on_progress" and more.env_id == ENV
    assert more.checkpoint.name.startswith("ckpt_") and more.global_step >= 3000
    assert seen[0][0] >= run.global_step  # the continued run's rows, not the earlier ones
    names = [p.name for p in (again / "checkpoints").glob("*.pt")]
    assert any(n.startswith("ckpt_") for n in names)  # a stopped run's checkpoint: not final
    steps = [r["global_step"] for r in tpdeb.Run.read(again).metrics]
    assert steps == sorted(steps) and 3000 <= steps[-1] < 100_000
    with pytest.raises(tpdeb.TrainError, match="holds another run"):
        tpdeb.train(ENV, total_timesteps=100_000, seed=4, run_dir=again)


def test_run_read_needs_only_the_run_dir(run):
    again = tpdeb.Run.read(run.run_dir)
    assert (again.env_id, again.global_step, again.checkpoint) == (
        ENV, run.global_step, run.checkpoint)


def test_the_onnx_export_acts_as_the_numpy_policy(run, tmp_path):
    import onnxruntime

    from tpdeb.services.export import main as export_main

    assert export_main([str(run.checkpoint), "-o", str(tmp_path / "again.npz")]) == 0
    np.testing.assert_array_equal(
        tpdeb.load_policy(tmp_path / "again.npz").act(np.ones(4), deterministic=True),
        tpdeb.load_policy(run.run_dir).act(np.ones(4), deterministic=True))
    # The run's policy with its output layer scaled up, so that some actions pass the bounds
    # and the clipping inside the graph acts.
    trained = tpdeb.load_policy(run.run_dir)
    arrays = dict(trained.file_arrays)
    arrays["policy.mean.4.weight"] = arrays["policy.mean.4.weight"] * 50.0
    (tmp_path / "loud.npz").write_bytes(policy_bytes(arrays, trained.low, trained.high,
                                                     trained.meta))
    assert export_main([str(tmp_path / "loud.npz"), "-o", str(tmp_path / "policy.onnx")]) == 0
    session = onnxruntime.InferenceSession(str(tmp_path / "policy.onnx"),
                                           providers=["CPUExecutionProvider"])
    policy = tpdeb.load_policy(tmp_path / "loud.npz")
    # far outside the normaliser's range too, where its clipping inside the graph acts
    obs = np.random.default_rng(2).normal(0.0, 30.0, (256, 4)).astype(np.float32)
    (action,) = session.run(["action"], {"obs": obs})
    np.testing.assert_allclose(action, policy.act(obs, deterministic=True), rtol=0, atol=1e-5)
    assert np.abs(action).max() == 3.0 and (np.abs(action) < 3.0).any()
    assert session.run(["action"], {"obs": obs[:1]})[0].shape == (1, 1)


def test_export_refuses_what_it_cannot_write(run, tmp_path, capsys):
    from tpdeb.services.export import main as export_main

    assert export_main([str(run.run_dir), "-o", str(tmp_path / "policy.pb")]) == 2
    assert "write a .onnx or a .npz file" in capsys.readouterr().err
    assert export_main([str(tmp_path / "missing"), "-o", str(tmp_path / "p.onnx")]) == 2
    assert "no such run directory" in capsys.readouterr().err


def test_evaluate_gives_tpdeb_evals_figures_from_any_source(run, capsys):
    import dataclasses

    from tpdeb.services.evaluate import main as eval_main

    assert eval_main([str(run.checkpoint), "--episodes", "3", "--seed", "4", "--json"]) == 0
    cli = json.loads(capsys.readouterr().out)
    policy = tpdeb.load_policy(run.run_dir)
    for source in (run.run_dir, run.checkpoint, run.run_dir / POLICY_FILE, policy):
        result = tpdeb.evaluate(source, episodes=3, seed=4)
        assert isinstance(result, tpdeb.Evaluation)
        assert result.returns == tuple(cli["returns"]) and result.lengths == tuple(cli["lengths"])
        assert (result.mean, result.std) == (cli["mean_return"], cli["std_return"])
    assert all(isinstance(n, int) for n in result.lengths)
    with pytest.raises(dataclasses.FrozenInstanceError):
        result.mean = 0.0
    sampled = tpdeb.evaluate(policy, episodes=2, seed=4, deterministic=False)
    assert sampled == tpdeb.evaluate(policy, env_id=ENV, episodes=2, seed=4, deterministic=False)
    with pytest.raises(tpdeb.PolicyError, match="trained on InvertedPendulum-v5, not Hopper-v5"):
        tpdeb.evaluate(policy, env_id="Hopper-v5")


def test_act_samples_by_default_and_the_same_way_on_every_load(run):
    obs = np.random.default_rng(0).normal(0.0, 1.0, (8, 4)).astype(np.float32)
    first, again = tpdeb.load_policy(run.run_dir), tpdeb.load_policy(run.run_dir)
    sampled = first.act(obs)
    np.testing.assert_array_equal(sampled, again.act(obs))
    assert not np.allclose(sampled, first.act(obs, deterministic=True))
    np.testing.assert_array_equal(first.act(obs, deterministic=True),
                                  again.act(obs, deterministic=True))


def test_export_checks_its_output_path_before_reading_the_policy(tmp_path, monkeypatch, capsys):
    from tpdeb.services import export
    from tpdeb.services.store.diskio import writable_path

    def never(source):
        raise AssertionError("the output path was not checked first")

    monkeypatch.setattr(export, "load_policy", never)
    (tmp_path / "file").write_text("")
    for out, reason in ((tmp_path / "file" / "p.onnx", "is a file, not a directory)"),
                        (tmp_path / "file" / "deeper" / "p.npz", "is a file, not a directory)"),
                        (Path("/proc/tpdeb/p.npz"), "cannot write there ("),
                        (tmp_path, "write a .onnx")):
        assert export.main([str(tmp_path), "-o", str(out)]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and reason in err, err
    new = tmp_path / "new" / "dirs" / "p.onnx"
    assert writable_path(new, "-o") == new and not (tmp_path / "new").exists()
