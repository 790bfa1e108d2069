"""What the learning benches share: run one `tpdeb-cluster` training run in its own process
group, and reduce a run directory's metrics.jsonl to the protocol's figures."""

from __future__ import annotations

import json
import os
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

import provenance  # noqa: I001  (bench/ is on sys.path)

from tpdeb.services.store.metrics import read_metrics

ROOT = Path(__file__).resolve().parents[1]

# Learner metrics averaged over the last 10 % of steps: the diagnostics of a run.
DIAGNOSTICS = ("losses/clipfrac", "losses/kl_behaviour", "losses/approx_kl",
               "losses/explained_variance", "losses/entropy", "actor/param_version_lag",
               "replay/sample_age_updates", "perf/update_ms")
# The learner's state over the run, kept thinned in each result (what a plateau is made of).
OVER_TIME = ("losses/entropy", "losses/kl_behaviour", "losses/approx_kl", "losses/clipfrac",
             "losses/explained_variance", "losses/value_loss", "losses/kl_coef",
             "losses/grad_norm")


def run_cluster(env_id: str, steps: int, seed: int, run_dir: Path, extra: list[str],
                log_path: Path, timeout_s: float, env: dict | None = None) -> tuple[int, float]:
    """One cluster run to `steps` env steps; returns (exit code, wall seconds). The whole
    process group is stopped on timeout or when this process is interrupted. `env`: variables
    added to the cluster's environment (a service setting as TPDEB_*)."""
    cmd = [sys.executable, "-m", "tpdeb.services.cluster", "--env-id", env_id, "--total-timesteps",
           str(steps), "--seed", str(seed), "--run-dir", str(run_dir), "--set",
           "log_interval_s=10", *extra]
    log_path.parent.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    # A SIGTERM to this script (kill PID) raises here like Ctrl-C, so the cluster, which runs in
    # its own session, is stopped with it instead of left running.
    previous = signal.signal(signal.SIGTERM, _exit_on_sigterm)
    try:
        with log_path.open("w") as log:
            proc = subprocess.Popen(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT,
                                    start_new_session=True, env={**os.environ, **(env or {})})
            try:
                code = proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGTERM)
                code = proc.wait(60)
            except BaseException:
                os.killpg(proc.pid, signal.SIGTERM)
                proc.wait(60)
                raise
    finally:
        signal.signal(signal.SIGTERM, previous)
    return code, time.monotonic() - start


def save_json(path: Path, result: dict) -> None:
    """Write a result file whole or not at all (a stopped bench leaves no half file that
    would count as a finished run)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(result))
    tmp.replace(path)
    provenance.written(path)


def save_result(path: Path | None, result: dict, record: dict) -> None:
    """`result` stamped with the run's provenance, and written to `path` where one is given."""
    provenance.stamp(result, record)
    if path:
        save_json(path, result)


def _exit_on_sigterm(signum, frame):
    raise SystemExit(128 + signum)


def read_run_metrics(run_dir: Path) -> list[dict]:
    path = Path(run_dir) / "metrics.jsonl"
    return read_metrics(path) if path.exists() else []


def episodes(rows: list[dict]) -> list[tuple[int, float]]:
    return [(r["global_step"], r["charts/episodic_return"]) for r in rows
            if "charts/episodic_return" in r]


def training_return(curve: list[tuple[int, float]], total_steps: int) -> float:
    """Mean episodic return over the last 10 % of the steps (the protocol's training return)."""
    tail = [ret for step, ret in curve if step >= 0.9 * total_steps]
    tail = tail or [ret for _, ret in curve[-10:]]
    return statistics.mean(tail) if tail else float("nan")


def summarize(rows: list[dict], total_steps: int) -> dict:
    curve = episodes(rows)
    last = max((r["global_step"] for r in rows), default=0)
    diagnostics = {}
    for tag in DIAGNOSTICS:
        values = [r[tag] for r in rows if tag in r and r["global_step"] >= 0.9 * last]
        if values:
            diagnostics[tag] = statistics.mean(values)
    return {"final_return": training_return(curve, total_steps), "steps": last,
            "episodes": len(curve), "diagnostics": diagnostics, "curve": thin(curve, 400),
            "policy_loss": thin(series(rows, "losses/policy_loss"), 200, digits=5),
            "clock": thin(series(rows, "perf/train_elapsed_s"), 200),
            "diagnostic_curves": {tag: thin(series(rows, tag), 50, digits=4)
                                  for tag in OVER_TIME if any(tag in r for r in rows)}}


def series(rows: list[dict], tag: str) -> list[tuple[int, float]]:
    """(step, value) of one logged metric, in step order."""
    return sorted((r["global_step"], r[tag]) for r in rows if tag in r)


def thin(curve: list[tuple[int, float]], points: int,
         digits: int = 2) -> list[tuple[int, float]]:
    """At most `points` (step, value) pairs, each the mean of a run of consecutive points (of
    episodes, of logged rows): keeps result files small without changing the curve's shape."""
    if len(curve) <= points:
        return [(int(s), round(float(r), digits)) for s, r in curve]
    size = len(curve) / points
    out = []
    for i in range(points):
        chunk = curve[int(i * size):int((i + 1) * size)]
        out.append((int(chunk[-1][0]), round(statistics.mean(r for _, r in chunk), digits)))
    return out


def alternation_arguments(parser, cluster_seconds: float) -> None:
    """The options of a bench that alternates cluster runs of two variants (`alternated`): the
    task, each run's training seconds, the rounds, the seed."""
    parser.add_argument("--env-id", default="HalfCheetah-v5", help="the cluster's task")
    parser.add_argument("--cluster-seconds", type=float, default=cluster_seconds,
                        help="training seconds of each cluster run")
    parser.add_argument("--pairs", type=int, default=2, help="cluster runs each way")
    parser.add_argument("--seed", type=int, default=1)
