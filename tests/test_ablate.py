"""The ablation grid's plan and resume (bench/ablate.py) and what each run's file keeps
(bench/runs.py), on made-up rows: nothing here trains."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import runs  # noqa: E402


def test_a_run_file_keeps_its_curves_policy_loss_and_clock():
    rows = []
    for step in range(1_000, 101_000, 1_000):
        rows.append({"global_step": step, "charts/episodic_return": step / 100})
        rows.append({"global_step": step, "losses/policy_loss": -step * 1e-7,
                     "perf/train_elapsed_s": step / 2_000})
    summary = runs.summarize(rows, 100_000)
    assert summary["final_return"] == sum(range(900, 1_001, 10)) / 11  # last 10 % of steps
    assert len(summary["policy_loss"]) == 100 and summary["policy_loss"][-1] == (100_000, -0.01)
    assert summary["clock"][0] == (1_000, 0.5) and summary["clock"][-1] == (100_000, 50.0)
    assert runs.thin(runs.series(rows, "perf/train_elapsed_s"), 10)[-1] == (100_000, 47.75)
