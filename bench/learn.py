"""Learning benchmark: TPDEB (ζ = 0.2) against plain replay (ζ = 0), KL on, several seeds.

Runs `tpdeb-train` as subprocesses (two at a time by default, one per core), then prints a
markdown table: final return (mean ± std over seeds of each run's mean episodic return over the
last 10 % of steps), the return at the end, and steps/s. Figures, not pass/fail.

    python bench/learn.py                       # HalfCheetah-v5, 300k steps, seeds 1-3
    python bench/learn.py --env-id Hopper-v5 --total-timesteps 100000 --seeds 1 2
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import provenance

ROOT = Path(__file__).resolve().parents[1]
VARIANTS = {"TPDEB (ζ=0.2, KL on)": ["--zeta", "0.2"], "plain replay (ζ=0, KL on)": ["--zeta", "0"]}


def run_one(env_id, steps, seed, name, extra, out_dir: Path) -> dict:
    run_dir = out_dir / f"{env_id}__{name.split()[0]}{extra[1]}__{seed}"
    cmd = [sys.executable, "-m", "tpdeb.services.serial", "--env-id", env_id, "--total-timesteps",
           str(steps), "--seed", str(seed), "--run-dir", str(run_dir), "--log-interval-s", "30",
           "--preset", "none",  # the settings these results were measured with
           *extra]
    start = time.perf_counter()
    log = (out_dir / f"{run_dir.name}.log").open("w")
    subprocess.run(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, check=True)
    wall_s = time.perf_counter() - start
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").open()]
    episodes = [(r["global_step"], r["charts/episodic_return"]) for r in rows
                if "charts/episodic_return" in r]
    tail = [ret for step, ret in episodes if step >= 0.9 * steps]
    curve = [(s, r) for s, r in episodes]
    print(f"  done: {name} seed {seed}: final {statistics.mean(tail):.0f} in {wall_s:.0f} s",
          flush=True)
    return {"variant": name, "seed": seed, "final_return": statistics.mean(tail),
            "sps": steps / wall_s, "wall_s": wall_s, "curve": curve}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env-id", default="HalfCheetah-v5")
    parser.add_argument("--total-timesteps", type=int, default=300_000)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--out", default=str(ROOT / "bench" / "out" / "learn"))
    args = parser.parse_args()
    record = provenance.start()
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    jobs = [(args.env_id, args.total_timesteps, seed, name, extra, out_dir)
            for seed in args.seeds for name, extra in VARIANTS.items()]
    print(f"{len(jobs)} runs of {args.total_timesteps:,} steps on {args.env_id}, "
          f"{args.jobs} at a time; logs in {out_dir}", flush=True)
    with ThreadPoolExecutor(args.jobs) as pool:
        results = list(pool.map(lambda job: run_one(*job), jobs))
    (out_dir / "results.json").write_text(json.dumps(provenance.stamp({"runs": results},
                                                                      record)))
    print(f"\n{args.env_id}, {args.total_timesteps:,} env steps, seeds {args.seeds}\n")
    print("| variant | final return (mean ± std) | per seed | steps/s (median) |")
    print("|---|---|---|---|")
    for name in VARIANTS:
        mine = [r for r in results if r["variant"] == name]
        finals = [r["final_return"] for r in mine]
        std = statistics.stdev(finals) if len(finals) > 1 else 0.0
        print(f"| {name} | {statistics.mean(finals):,.0f} ± {std:,.0f} | "
              f"{', '.join(f'{f:,.0f}' for f in finals)} | "
              f"{statistics.median(r['sps'] for r in mine):,.0f} |")


if __name__ == "__main__":
    main()
