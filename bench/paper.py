"""The paper's comparison (its Table 2 and Fig 7): TPDEB vs IMPACT vs PPO+PER on six MuJoCo
tasks, every run a real `tpdeb-cluster` with the task's preset.

    python bench/paper.py                   # the grid: 6 tasks × 3 algorithms × seeds 11-13, 1M
    python bench/paper.py --envs Hopper-v5 --algos tpdeb --seeds 1 --steps 300000 \\
        --tag tune/hopper-lr3e-4 --set learning_rate=3e-4      # a tuning run (seeds 1-2 only)
    python bench/paper.py --report          # docs/RESULTS.md tables and docs/img/paper/*.png

Resumable run by run: each finished run leaves one small JSON in docs/data/{tag}/ (training
return, evaluation return of the final checkpoint over 10 deterministic episodes, diagnostics,
a thinned learning curve); a run whose file exists is skipped, so a stopped grid continues where
it stopped. Run dirs and logs go to bench/out/ (not kept). Reported seeds (11-13) are never used
for tuning (seeds 1-2). The order is seed-major, so every cell gets its first seed before any gets
its third.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import provenance  # noqa: E402
from runs import ROOT, read_run_metrics, run_cluster, save_json, summarize  # noqa: E402

TASKS = ("HalfCheetah-v5", "Hopper-v5", "Walker2d-v5", "Ant-v5", "Humanoid-v5", "Swimmer-v5")
ALGOS = ("tpdeb", "impact", "ppo-per")
REPORT_SEEDS = (11, 12, 13)
DATA = ROOT / "docs" / "data"
OUT = ROOT / "bench" / "out"


def result_path(tag: str, env_id: str, algo: str, steps: int, seed: int) -> Path:
    return DATA / tag / f"{env_id}__{algo}__{steps}__{seed}.json"


def evaluate(run_dir: Path, episodes: int, seed: int) -> dict | None:
    """Deterministic evaluation of the run's final checkpoint (tpdeb-eval)."""
    cmd = [sys.executable, "-m", "tpdeb.services.evaluate", str(run_dir),
           "--episodes", str(episodes), "--seed", str(seed), "--json"]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=1800)
    if proc.returncode != 0:
        print(f"[paper]   evaluation failed: {proc.stderr.strip()[-300:]}", flush=True)
        return None
    return json.loads(proc.stdout.strip().splitlines()[-1])


def finished(run_dir: Path, steps: int) -> bool:
    """The learner reached `steps` and wrote its final checkpoint."""
    from tpdeb.services.store.checkpoint import FINAL, checkpoint_dir, list_checkpoints

    return run_dir.is_dir() and any(c.tag == FINAL and c.global_step >= steps
                                    for c in list_checkpoints(checkpoint_dir(run_dir)))


def cluster_wall_s(run_dir: Path) -> float:
    """Seconds from the run dir's creation to its final checkpoint."""
    from tpdeb.services.store.checkpoint import FINAL, checkpoint_dir, list_checkpoints

    final = [c for c in list_checkpoints(checkpoint_dir(run_dir)) if c.tag == FINAL]
    return final[-1].path.stat().st_mtime - (run_dir / "cluster.json").stat().st_mtime


def run_one(args, env_id: str, algo: str, seed: int, flags: list[str] = ()) -> dict | None:
    """One run to its result file (args: tag, steps, set, timeout_s, eval_episodes; `flags`:
    cluster flags such as --actors); the result, or None where it failed."""
    path = result_path(args.tag, env_id, algo, args.steps, seed)
    if path.exists():
        return json.loads(path.read_text())
    name = path.stem
    run_dir = OUT / args.tag / "runs" / name
    record = provenance.start()
    code, wall_s = 0, float("nan")
    if finished(run_dir, args.steps):  # trained to the end, then failed to exit cleanly
        print(f"[paper] {env_id} | {algo} | seed {seed}: recording the finished run in "
              f"{run_dir}", flush=True)
        record["note"] = "recorded from a run dir that finished earlier: its start is not known"
    else:
        if run_dir.exists():  # a run cut short: start it again from nothing
            shutil.rmtree(run_dir)
        extra = ["--set", f"algo={algo}"]
        for item in args.set:
            extra += ["--set", item]
        extra += list(flags)
        print(f"[paper] {time.strftime('%H:%M')} {args.tag}: {env_id} | {algo} | seed {seed} | "
              f"{args.steps:,} steps …", flush=True)
        code, wall_s = run_cluster(env_id, args.steps, seed, run_dir, extra,
                                   OUT / args.tag / f"{name}.log", args.timeout_s)
        if code != 0 and not finished(run_dir, args.steps):
            print(f"[paper]   exit code {code} after {wall_s:.0f} s; see {OUT / args.tag}/"
                  f"{name}.log (not recorded, will be rerun)", flush=True)
            return None
    result = summarize(read_run_metrics(run_dir), args.steps)
    if wall_s != wall_s:  # recorded afterwards: the wall time from the cluster's own log
        wall_s = cluster_wall_s(run_dir)
    result.update(env_id=env_id, algo=algo, seed=seed, total_steps=args.steps,
                  overrides=list(args.set) + list(flags), wall_s=round(wall_s, 1),
                  sps=round(result["steps"] / wall_s, 1), exit_code=code, cpus=os.cpu_count())
    if args.eval_episodes:
        result["eval"] = evaluate(run_dir, args.eval_episodes, 10_000 + seed)
    save_json(path, provenance.stamp(result, record))
    ev = result.get("eval") or {}
    print(f"[paper]   → training return {result['final_return']:,.0f}"
          + (f", evaluation {ev['mean_return']:,.0f} ± {ev['std_return']:,.0f}" if ev else "")
          + f" | {result['sps']:,.0f} steps/s, {wall_s:.0f} s", flush=True)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=list(TASKS))
    parser.add_argument("--algos", nargs="+", default=list(ALGOS), choices=ALGOS)
    parser.add_argument("--seeds", type=int, nargs="+", default=list(REPORT_SEEDS))
    parser.add_argument("--steps", type=int, default=1_000_000)
    parser.add_argument("--tag", default="paper",
                        help="results go to docs/data/TAG/ (e.g. tune/NAME for tuning runs)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a training setting on top of the preset, for every run")
    parser.add_argument("--eval-episodes", type=int, default=10,
                        help="deterministic evaluation episodes of each final checkpoint (0: none)")
    parser.add_argument("--timeout-s", type=float, default=4 * 3600)
    parser.add_argument("--report", action="store_true",
                        help="no runs: write docs/RESULTS.md's tables and the figures")
    parser.add_argument("--tuning", action="store_true",
                        help="no runs: the table of every tuning run (docs/data/tune/), also "
                             "into docs/RESULTS.md")
    args = parser.parse_args()
    if args.tuning:
        from paper_report import replace_between, tuning_table

        table = tuning_table(DATA / "tune")
        print(table)
        if replace_between(ROOT / "docs" / "RESULTS.md", "<!-- tuning:begin -->",
                           "<!-- tuning:end -->", table):
            print("\nupdated docs/RESULTS.md")
        return
    if args.report:
        from paper_report import report

        report(DATA / args.tag, args.envs, args.algos, update_doc=args.tag == "paper")
        return
    jobs = [(env_id, algo, seed) for seed in args.seeds for env_id in args.envs
            for algo in args.algos]
    todo = [j for j in jobs if not result_path(args.tag, j[0], j[1], args.steps, j[2]).exists()]
    print(f"[paper] {args.tag}: {len(jobs)} runs of {args.steps:,} steps, {len(jobs) - len(todo)} "
          f"already done; results in {DATA / args.tag}", flush=True)
    for n, (env_id, algo, seed) in enumerate(todo, 1):
        print(f"[paper] run {n}/{len(todo)}", flush=True)
        run_one(args, env_id, algo, seed)


if __name__ == "__main__":
    main()
