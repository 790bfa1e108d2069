"""Two learner ranks, compiled or eager: what compiling the update gives data-parallel learners.

    python bench/ranks_compile.py                 # HalfCheetah-v5, 2 pairs of 90 s (~9 minutes)
    python bench/ranks_compile.py --out docs/data/capacity/ranks-compile.json

`tpdeb-cluster` on `--env-id` (its preset, 2 actors × 4 envs, the learners on the CPU) with 2
replay shards and 2 learner ranks, trained for `--cluster-seconds`, with the ranks' update
compiled (`compile = auto`, the default: each rank compiles in the background and the group
switches together once both are ready) and eager (`compile = off`), `--pairs` times each, the
order turned each round. A first compiled run, not counted, fills the compiler's cache, as any
earlier run on the machine would have. Prints env steps/s and updates/s of each run and the
medians' ratio; `--out` keeps them with the run's provenance.

The machine must be otherwise idle: these are timings.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import provenance
from gpu import alternated, cluster_run
from runs import alternation_arguments, save_result

OUT = Path(__file__).resolve().parents[1] / "bench" / "out" / "ranks_compile"
GROUP = {"shards": 2, "learners": 2}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    alternation_arguments(parser, 90.0)
    parser.add_argument("--out", type=Path, help="write the figures here as JSON")
    args = parser.parse_args()
    record = provenance.start()
    warm = cluster_run(args, 2, "cpu", out=OUT, **GROUP)  # the compiler's cache, filled
    print(f"warm-up run (not counted): {warm['env_steps_per_s']:,.0f} env steps/s", flush=True)
    result = alternated(args, {"compiled": GROUP,
                               "eager": {**GROUP, "settings": ("compile=off",)}},
                        args.pairs, 2, OUT)
    save_result(args.out, result, record)
    return 0


if __name__ == "__main__":
    sys.exit(main())
