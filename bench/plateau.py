"""What a plateau is made of: the learner's state over the runs of a tag (bench/paper.py result
files), step by step, for the runs that sat low and those that did not.

    python bench/paper.py --envs Walker2d-v5 --algos tpdeb --seeds 1 2 3 --tag tune/plateau-w2d
    python bench/plateau.py --tag tune/plateau-w2d --envs Walker2d-v5 [--threshold 1500]

For each run, at every tenth of its steps: the training return (the mean of the episodes ending
in that tenth), the policy's entropy, its KL to the behaviour policies, the approximate KL to
the target policy, the clip fraction, the value function's explained variance and loss, the
gradients' norm before clipping (`max_grad_norm`) and the adaptive KL coefficient, each the
mean of the learner's rows in that tenth (`diagnostic_curves`, kept in each result by
bench/runs.py). Then the step at which the return first passes `--threshold`: a run is on a
plateau until then. Prints markdown; nothing is run or written.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from runs import ROOT  # noqa: E402

COLUMNS = (("losses/entropy", "entropy", 2), ("losses/kl_behaviour", "KL(μ‖π)", 3),
           ("losses/approx_kl", "KL to target", 3), ("losses/clipfrac", "clip frac", 2),
           ("losses/explained_variance", "expl. var", 2), ("losses/value_loss", "value loss", 3),
           ("losses/grad_norm", "grad norm", 2), ("losses/kl_coef", "λ_kl", 3))
TENTHS = 10


def window_mean(points: list, low: float, high: float) -> float | None:
    values = [v for step, v in points if low < step <= high]
    return statistics.mean(values) if values else None


def first_passing(curve: list, threshold: float, span: int = 5) -> int | None:
    """The step at which the mean of `span` consecutive episodes first reaches `threshold`."""
    for i in range(len(curve) - span + 1):
        if statistics.mean(r for _, r in curve[i:i + span]) >= threshold:
            return int(curve[i + span - 1][0])
    return None


def run_table(result: dict, threshold: float) -> str:
    total = result.get("total_steps") or result["steps"]
    curves = result.get("diagnostic_curves") or {}
    head = ("| steps | return | " + " | ".join(name for _, name, _ in COLUMNS) + " |\n"
            + "|---|---|" + "---|" * len(COLUMNS))
    lines = [head]
    for k in range(1, TENTHS + 1):
        low, high = total * (k - 1) / TENTHS, total * k / TENTHS
        ret = window_mean(result["curve"], low, high)
        cells = [f"{high / 1e3:,.0f}k", "—" if ret is None else f"{ret:,.0f}"]
        for tag, _, digits in COLUMNS:
            value = window_mean(curves.get(tag, []), low, high)
            cells.append("—" if value is None else f"{value:.{digits}f}")
        lines.append("| " + " | ".join(cells) + " |")
    passed = first_passing(result["curve"], threshold)
    where = (f"first at or above {threshold:,.0f} after {passed / 1e3:,.0f}k steps"
             if passed is not None else f"never at or above {threshold:,.0f}")
    return (f"**{result['env_id']}, seed {result['seed']}** ({result['algo']}; training return "
            f"{result['final_return']:,.0f}; {where})\n\n" + "\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tag", required=True, help="a docs/data/ folder of bench/paper.py runs")
    parser.add_argument("--envs", nargs="+", default=None)
    parser.add_argument("--algos", nargs="+", default=None)
    parser.add_argument("--threshold", type=float, default=1000.0,
                        help="the return a run is on a plateau below")
    args = parser.parse_args()
    folder = ROOT / "docs" / "data" / args.tag
    results = [json.loads(p.read_text()) for p in sorted(folder.glob("*.json"))]
    results = [r for r in results if (args.envs is None or r["env_id"] in args.envs)
               and (args.algos is None or r["algo"] in args.algos)]
    if not results:
        raise SystemExit(f"plateau: no runs in {folder}"
                         + (f" for {' '.join(args.envs)}" if args.envs else ""))
    missing = [f"{r['env_id']} seed {r['seed']}" for r in results if "diagnostic_curves" not in r]
    if missing:
        print(f"(no learner state over time in: {', '.join(missing)}; made before it was kept)\n")
    for result in results:
        print(run_table(result, args.threshold) + "\n")


if __name__ == "__main__":
    main()
