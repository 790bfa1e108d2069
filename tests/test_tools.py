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
        ([str(tmp_path / "nothing")], "no such run directory, policy file or checkpoint"),
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
    assert any("algo=impact | 1 run |" in line for line in lines)
    other = run("tpdeb.services.plot", str(runs["a1"]), "--metric", "losses/clipfrac", "-o",
                str(tmp_path / "c.png"))
    assert other.returncode == 0 and (tmp_path / "c.png").exists()


def test_plot_names_what_is_missing(runs, tmp_path):
    out = run("tpdeb.services.plot", str(runs["a1"]), "--metric", "charts/nothing")
    assert out.returncode == 2 and "charts/nothing" in out.stderr
    out = run("tpdeb.services.plot", str(tmp_path))
    assert out.returncode == 2 and "no metrics.jsonl" in out.stderr


def test_eval_reads_a_policy_file_with_the_checkpoints_figures(runs):
    checkpoint = run(EVAL, str(runs["a1"]), "--episodes", "3", "--seed", "4", "--json")
    policy_file = run(EVAL, str(runs["a1"] / "policy.npz"), "--episodes", "3", "--seed", "4",
                      "--json")
    assert policy_file.returncode == 0, policy_file.stderr
    a, b = json.loads(checkpoint.stdout), json.loads(policy_file.stdout)
    assert b["checkpoint"].endswith("policy.npz") and b["env_id"] == "InvertedPendulum-v5"
    assert (a["returns"], a["lengths"]) == (b["returns"], b["lengths"])
    one = run(EVAL, str(runs["a1"] / "policy.npz"), "--episodes", "1")
    assert one.returncode == 0 and "| 1 episode from seed 0" in one.stdout


def under_a_file(tmp_path: Path, name: str) -> Path:
    """A path whose parent is a regular file: unwritable even for root."""
    (tmp_path / "file").write_text("")
    return tmp_path / "file" / name


@pytest.mark.parametrize("tool", ["eval", "plot"])
@pytest.mark.parametrize("where", ["under a file", "under /proc"])
def test_an_unwritable_output_fails_first_in_one_line(tool, where, tmp_path, monkeypatch,
                                                      capsys):
    """The output path is checked before the episodes or the runs are read (those raise here)."""
    from tpdeb.services import evaluate, plot

    def never(*args, **kwargs):
        raise AssertionError("the output path was not checked first")

    name = "x.mp4" if tool == "eval" else "x.png"
    out = under_a_file(tmp_path, name) if where == "under a file" else Path("/proc/tpdeb", name)
    if tool == "eval":
        monkeypatch.setattr(evaluate, "load_numpy_policy", never)
        code, flag = evaluate.main([str(tmp_path), "--video", str(out)]), "--video"
    else:
        monkeypatch.setattr(plot, "read_run", never)
        code, flag = plot.main([str(tmp_path), "-o", str(out)]), "-o"
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert f"{flag} {out}: cannot write there (" in err
    if where == "under a file":
        assert "is a file, not a directory)" in err


def test_plot_labels_leave_out_settings_a_run_does_not_hold():
    from tpdeb.services.plot import Run, variant_labels

    runs = [Run(Path(name), "Hopper-v5", settings, [0.0], [0.0]) for name, settings in (
        ("a", {"learning_rate": 3e-4, "num_envs": 8}), ("b", {"learning_rate": 1e-4}),
        ("c", {"learning_rate": 1e-4, "num_envs": None}))]
    labels = variant_labels(runs)
    assert labels == ["learning_rate=0.0003, num_envs=8", "learning_rate=0.0001",
                      "learning_rate=0.0001"]
    assert not any("None" in label for label in labels)


def test_plot_legends_stay_inside_their_panels(tmp_path, monkeypatch):
    from tpdeb.services import plot

    figures = []
    monkeypatch.setattr(plot, "save", lambda fig, path: figures.append(fig))
    def settings(i: int) -> dict:  # variants that differ in five settings: long labels
        return {"hidden_sizes": [256] * (i + 2), "replay_capacity": 10 ** (5 + i),
                "priority_exponent": 0.5 + i / 10, "learning_rate": 3e-4 * (i + 1),
                "batch_size": 2048 * (i + 1)}

    runs = [plot.Run(Path(f"r{i}"), env, settings(i), [0.0, 1000.0], [1.0, 2.0])
            for env in ("Hopper-v5", "Walker2d-v5") for i in range(3)]
    plot.draw(runs, "charts/episodic_return", tmp_path / "c.png", 20)
    (fig,) = figures
    fig.tight_layout()
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    for ax in fig.axes:
        inside, legend = ax.get_window_extent(renderer), ax.get_legend().get_window_extent(renderer)
        assert inside.x0 <= legend.x0 and legend.x1 <= inside.x1, ax.get_title()
