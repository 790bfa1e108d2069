"""tpdeb-eval and tpdeb-plot on tiny real runs."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EVAL = "tpdeb.services.evaluate"


def run(*cmd: str, timeout_s: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *cmd], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout_s)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Two seeds of TPDEB and one of IMPACT, 1,024 steps of InvertedPendulum-v5 each."""
    base = tmp_path_factory.mktemp("runs")
    dirs = {}
    for name, algo, seed in (("a1", "tpdeb", 1), ("a2", "tpdeb", 2), ("b1", "impact", 1)):
        out = run("tpdeb.services.serial", "--env-id", "InvertedPendulum-v5", "--total-timesteps",
                  "1024", "--num-envs", "2", "--seed", str(seed), "--algo", algo,
                  "--learning-starts-fragments", "2", "--run-dir", str(base / name))
        assert out.returncode == 0, out.stderr
        dirs[name] = base / name
    return dirs


def test_eval_is_deterministic_for_a_seed_and_reads_run_dirs_and_files(runs):
    first = run(EVAL, str(runs["a1"]), "--episodes", "3", "--seed", "4", "--json")
    assert first.returncode == 0, first.stderr
    again = run(EVAL, str(runs["a1"]), "--episodes", "3", "--seed", "4", "--json")
    a, b = json.loads(first.stdout), json.loads(again.stdout)
    assert a["returns"] == b["returns"] and len(a["returns"]) == 3
    assert a["env_id"] == "InvertedPendulum-v5" and a["checkpoint"].endswith(".pt")
    text = run("tpdeb.services.evaluate", a["checkpoint"], "--episodes", "3", "--seed", "4")
    assert text.returncode == 0
    assert f"return {a['mean_return']:,.1f} ± {a['std_return']:,.1f}" in text.stdout


def test_eval_refuses_another_env_and_bad_targets_in_one_line(runs, tmp_path):
    for args, words in (
        ([str(runs["a1"]), "--env-id", "Hopper-v5"], "trained on InvertedPendulum-v5, not "
                                                     "Hopper-v5"),
        ([str(tmp_path / "nothing")], "no such checkpoint or run directory"),
        ([str(tmp_path)], "no checkpoints"),
        ([str(runs["a1"]), "--episodes", "0"], "--episodes 0"),
    ):
        out = run("tpdeb.services.evaluate", *args)
        assert out.returncode == 2 and words in out.stderr
        assert len(out.stderr.strip().splitlines()) == 1
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    out = run("tpdeb.services.evaluate", str(junk))
    assert out.returncode == 2 and "unreadable" in out.stderr


def test_eval_writes_a_video_or_says_why_not(runs, tmp_path):
    video = tmp_path / "v.mp4"
    out = run("tpdeb.services.evaluate", str(runs["b1"]), "--episodes", "1", "--video", str(video))
    if out.returncode == 0:
        assert video.stat().st_size > 1000 and "video:" in out.stdout
    else:
        assert out.returncode == 2 and "--video" in out.stderr and not video.exists()


def test_plot_groups_runs_by_variant_with_seeds(runs, tmp_path):
    png = tmp_path / "curves.png"
    out = run("tpdeb.services.plot", *(str(p) for p in runs.values()), "-o", str(png))
    assert out.returncode == 0, out.stderr
    assert png.stat().st_size > 5000 and png.read_bytes()[:4] == b"\x89PNG"
    lines = out.stdout.splitlines()
    assert any("algo=tpdeb | 2 runs" in line for line in lines)
    assert any("algo=impact | 1 runs" in line for line in lines)
    other = run("tpdeb.services.plot", str(runs["a1"]), "--metric", "losses/clipfrac", "-o",
                str(tmp_path / "c.png"))
    assert other.returncode == 0 and (tmp_path / "c.png").exists()


def test_plot_names_what_is_missing(runs, tmp_path):
    out = run("tpdeb.services.plot", str(runs["a1"]), "--metric", "charts/nothing")
    assert out.returncode == 2 and "charts/nothing" in out.stderr
    out = run("tpdeb.services.plot", str(tmp_path))
    assert out.returncode == 2 and "no metrics.jsonl" in out.stderr
