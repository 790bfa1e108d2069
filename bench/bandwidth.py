"""The paper's bandwidth experiment: TPDEB vs an IMPACT-like baseline behind constrained links.

    python bench/bandwidth.py                         # the whole grid (long: hours on 2 cores)
    python bench/bandwidth.py --links 0 1048576 --seeds 1 --total-timesteps 50000   # a slice

Every run is a real `tpdeb-cluster` (replay, learner, 2 actors × 4 envs, HalfCheetah-v5) with
the actors behind `tpdeb-link`, symmetric up/down rate; "unlimited" still routes through the
link (at 10^12 B/s) so its bytes are counted the same way. Variants:
  TPDEB          ζ = 0.2, KL on (λ_kl 0.01)
  IMPACT-like    ζ = 0,   KL off
each without and with compression (zstd trajectories + float16 parameters).
Runs already finished (their result file in docs/data/bandwidth exists) are skipped, so the
grid can be filled in several sittings; `--report` only prints the table and redraws the figure
from the finished runs. Prints a markdown table (final return mean ± std over seeds, env steps/s,
parameter-version lag, bytes per env step up/down) and draws docs/img/bandwidth.png.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "out" / "bandwidth"  # logs and run dirs (not committed)
RESULTS = ROOT / "docs" / "data" / "bandwidth"  # one small JSON per finished run (committed)
UNLIMITED = 1e12
VARIANTS = {
    "TPDEB": ["--set", "zeta=0.2", "--set", "kl_coef=0.01"],
    "IMPACT-like": ["--set", "zeta=0", "--set", "kl_coef=0"],
}
COMPRESSION = {
    "plain": [],
    "compressed": ["--set", "trajectory_compression=zstd", "--set", "params_dtype=float16"],
}


def link_name(rate: float) -> str:
    if rate <= 0 or rate >= UNLIMITED:
        return "unlimited"
    return f"{rate / 2**20:g} MB/s" if rate >= 2**20 else f"{rate / 2**10:g} kB/s"


def run_one(env_id: str, steps: int, seed: int, rate: float, variant: str, compression: str,
            timeout_s: float) -> dict:
    tag = f"{env_id}__{steps}__{int(rate) if rate else 0}__{variant}__{compression}__{seed}"
    result_file = RESULTS / f"{tag}.json"
    if result_file.exists():
        return json.loads(result_file.read_text())
    run_dir = OUT / "runs" / tag
    wire_rate = rate if rate > 0 else UNLIMITED
    cmd = [sys.executable, "-m", "tpdeb.services.cluster", "--env-id", env_id, "--total-timesteps",
           str(steps), "--seed", str(seed), "--run-dir", str(run_dir), "--actors", "2",
           "--num-envs", "4", "--link-up-bytes-per-s", str(wire_rate),
           "--link-down-bytes-per-s", str(wire_rate), "--set", "log_interval_s=10",
           "--set", "preset=none",  # the settings these results were measured with
           *VARIANTS[variant], *COMPRESSION[compression]]
    print(f"[bandwidth] {link_name(rate):>9} | {variant:<11} | {compression:<10} | seed {seed}"
          " …", flush=True)
    start = time.monotonic()
    with (OUT / f"{tag}.log").open("w") as log:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True)
        try:
            code = proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, 15)
            code = proc.wait(60)
    wall_s = time.monotonic() - start
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").open()]
    result = summarize(rows, steps, wall_s)
    result.update(link=rate, variant=variant, compression=compression, seed=seed,
                  exit_code=code)
    print(f"[bandwidth]   → return {result['final_return']:,.0f}, {result['sps']:,.0f} "
          f"steps/s, lag {result['lag']:.0f}, {result['up_bytes_per_step']:.0f}/"
          f"{result['down_bytes_per_step']:.0f} B per step up/down, {wall_s:.0f} s", flush=True)
    if code == 0:
        result_file.write_text(json.dumps(result))
    return result


def summarize(rows: list[dict], steps: int, wall_s: float) -> dict:
    episodes = [(r["global_step"], r["charts/episodic_return"]) for r in rows
                if "charts/episodic_return" in r]
    last = max((r["global_step"] for r in rows), default=0)
    tail = [ret for step, ret in episodes if step >= 0.9 * last] or [ret for _, ret in
                                                                     episodes[-10:]]
    lags = [r["actor/param_version_lag"] for r in rows if "actor/param_version_lag" in r]
    link = [r for r in rows if "link/up_bytes_per_env_step" in r]
    return {
        "final_return": statistics.mean(tail) if tail else float("nan"),
        "sps": last / wall_s,
        "lag": statistics.mean(lags) if lags else float("nan"),
        "up_bytes_per_step": link[-1]["link/up_bytes_per_env_step"] if link else float("nan"),
        "down_bytes_per_step": link[-1]["link/down_bytes_per_env_step"] if link
        else float("nan"),
        "steps": last, "wall_s": wall_s, "curve": episodes,
    }


def table(results: list[dict]) -> str:
    lines = ["| link | variant | compression | final return (mean ± std) | seeds | env steps/s "
             "| param lag | bytes/step up / down |", "|---|---|---|---|---|---|---|---|"]
    keys = sorted({(r["link"], r["variant"], r["compression"]) for r in results},
                  key=lambda k: (-(k[0] or UNLIMITED), k[1] != "TPDEB", k[2]))
    for rate, variant, compression in keys:
        mine = [r for r in results if (r["link"], r["variant"], r["compression"]) ==
                (rate, variant, compression)]
        finals = [r["final_return"] for r in mine]
        std = statistics.stdev(finals) if len(finals) > 1 else 0.0
        lines.append(
            f"| {link_name(rate)} | {variant} | {compression} | {statistics.mean(finals):,.0f} "
            f"± {std:,.0f} | {len(mine)} | {statistics.median(r['sps'] for r in mine):,.0f} | "
            f"{statistics.median(r['lag'] for r in mine):.0f} | "
            f"{statistics.median(r['up_bytes_per_step'] for r in mine):,.0f} / "
            f"{statistics.median(r['down_bytes_per_step'] for r in mine):,.0f} |")
    return "\n".join(lines)


def plot(results: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    rates = sorted({r["link"] for r in results}, key=lambda x: -(x or UNLIMITED))
    fig, axes = plt.subplots(1, len(rates), figsize=(4.2 * len(rates), 3.4), sharey=True,
                             squeeze=False)
    for ax, rate in zip(axes[0], rates, strict=True):
        for (variant, compression), style in {("TPDEB", "plain"): "C0-",
                                              ("TPDEB", "compressed"): "C0--",
                                              ("IMPACT-like", "plain"): "C1-",
                                              ("IMPACT-like", "compressed"): "C1--"}.items():
            runs = [r for r in results if (r["link"], r["variant"], r["compression"]) ==
                    (rate, variant, compression) and r["curve"]]
            if not runs:
                continue
            grid = np.linspace(0, max(r["steps"] for r in runs), 40)
            curves = []
            for r in runs:
                steps, returns = np.array(r["curve"]).T
                k = min(10, len(returns))  # trailing mean of the last k episodes, no edge dip
                smooth = np.convolve(returns, np.ones(k) / k, mode="valid")
                curves.append(np.interp(grid, steps[k - 1:], smooth))
            mean, std = np.mean(curves, 0), np.std(curves, 0)
            ax.plot(grid, mean, style, label=f"{variant}, {compression}")
            ax.fill_between(grid, mean - std, mean + std, color=style[:2], alpha=0.12)
        ax.set_title(f"link {link_name(rate)}")
        ax.set_xlabel("env steps")
    axes[0][0].set_ylabel("episodic return")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env-id", default="HalfCheetah-v5")
    parser.add_argument("--total-timesteps", type=int, default=100_000)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--links", type=float, nargs="+",
                        default=[0, 2**20, 256 * 2**10, 64 * 2**10],
                        help="link rates in bytes/s, 0 = unlimited")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS))
    parser.add_argument("--compression", nargs="+", default=list(COMPRESSION))
    parser.add_argument("--timeout-s", type=float, default=3600)
    parser.add_argument("--report", action="store_true",
                        help="no runs: table and figure from the finished runs")
    args = parser.parse_args()
    if args.report:
        results = [json.loads(p.read_text()) for p in sorted(RESULTS.glob("*.json"))]
        print(table(results))
        plot(results, ROOT / "docs" / "img" / "bandwidth.png")
        return
    OUT.mkdir(parents=True, exist_ok=True)
    RESULTS.mkdir(parents=True, exist_ok=True)
    jobs = [(rate, variant, compression, seed) for rate in args.links for seed in args.seeds
            for variant in args.variants for compression in args.compression]
    print(f"[bandwidth] {len(jobs)} runs of {args.total_timesteps:,} steps on {args.env_id}; "
          f"results in {OUT}", flush=True)
    results = [run_one(args.env_id, args.total_timesteps, seed, rate, variant, compression,
                       args.timeout_s) for rate, variant, compression, seed in jobs]
    results = [r for r in results if r["exit_code"] == 0]
    (OUT / "results.json").write_text(json.dumps(results))  # this invocation's runs
    print()
    print(table(results))
    plot(results, ROOT / "docs" / "img" / "bandwidth.png")
    print(f"\ncurves: {ROOT / 'docs' / 'img' / 'bandwidth.png'}")


if __name__ == "__main__":
    main()
