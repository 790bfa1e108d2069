"""What evaluation while training costs the cluster: env steps/s with the evaluator at the
default interval against the same cluster without it.

    python bench/eval_cost.py                        # HalfCheetah-v5, 3 pairs × 120 s each
    python bench/eval_cost.py --seconds 60 --pairs 2 --env-id Hopper-v5

Each pair runs `tpdeb-cluster` (deploy/local.toml, the task's preset, seed 11) for `--seconds`
of training twice, alternating which goes first: once with the defaults (`eval_interval`
100,000 env steps, 5 episodes: the evaluator process) and once with `--eval-interval 0` (no
evaluator). The figure is the run's env steps per second of training (`end.json`: global step
over training seconds), and the cost is 1 − with/without per pair, reported as the median over
pairs. Nothing else should run meanwhile. Each run is written as it ends to
`docs/data/eval/cost.json` (`--out`) with its provenance, and a finished pair is not run again.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import provenance

ROOT = Path(__file__).resolve().parents[1]
VARIANTS = {"with": [], "without": ["--eval-interval", "0"]}


def run_cluster(args, variant: str, run_dir: Path) -> dict:
    cmd = [sys.executable, "-m", "tpdeb.services.cluster", "--env-id", args.env_id,
           "--seed", str(args.seed), "--train-for-seconds", str(args.seconds),
           "--total-timesteps", "100000000", "--run-dir", str(run_dir), *VARIANTS[variant]]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True,
                          timeout=args.seconds + 300)
    if proc.returncode != 0:
        raise SystemExit(f"{variant}: tpdeb-cluster exited {proc.returncode}:\n"
                         f"{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
    end = json.loads((run_dir / "end.json").read_text())
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    evaluations = [r for r in rows if "eval/mean_return" in r]
    return {"variant": variant, "global_step": end["global_step"],
            "train_elapsed_s": end["train_elapsed_s"],
            "env_steps_per_s": end["global_step"] / end["train_elapsed_s"],
            "evaluations": len(evaluations),
            "eval_returns": [r["eval/mean_return"] for r in evaluations]}


def summary(runs: list[dict]) -> dict:
    pairs: dict[int, dict] = {}
    for run in runs:
        pairs.setdefault(run["pair"], {})[run["variant"]] = run["env_steps_per_s"]
    costs = [1 - p["with"] / p["without"] for p in pairs.values() if len(p) == 2]

    def median(values):
        values = list(values)
        return statistics.median(values) if values else None

    return {"pairs": len(costs), "costs": costs, "median_cost": median(costs),
            "median_with": median(p["with"] for p in pairs.values() if "with" in p),
            "median_without": median(p["without"] for p in pairs.values() if "without" in p)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env-id", default="HalfCheetah-v5")
    p.add_argument("--seed", type=int, default=11)
    p.add_argument("--seconds", type=float, default=120.0)
    p.add_argument("--pairs", type=int, default=3)
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "data" / "eval" / "cost.json")
    args = p.parse_args()
    data = json.loads(args.out.read_text()) if args.out.is_file() else {"runs": []}
    record = data.get(provenance.FIELD) or provenance.start()
    for pair in range(args.pairs):
        order = ["with", "without"] if pair % 2 == 0 else ["without", "with"]
        for variant in order:
            if any(r["pair"] == pair and r["variant"] == variant for r in data["runs"]):
                continue
            with tempfile.TemporaryDirectory(prefix="tpdeb-evalcost-") as tmp:
                result = run_cluster(args, variant, Path(tmp) / "run")
            data["runs"].append({"pair": pair, **result})
            data.update(env_id=args.env_id, seconds=args.seconds, summary=summary(data["runs"]))
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps(provenance.stamp(data, record), indent=1) + "\n")
            provenance.written(args.out)
            print(f"pair {pair} {variant:>7}: {result['env_steps_per_s']:,.0f} env steps/s, "
                  f"{result['evaluations']} evaluations", flush=True)
    s = summary(data["runs"])
    print(f"median env steps/s: with the evaluator {s['median_with']:,.0f}, without "
          f"{s['median_without']:,.0f}; cost per pair {[f'{c:.1%}' for c in s['costs']]}, "
          f"median {s['median_cost']:.1%}")


if __name__ == "__main__":
    main()
