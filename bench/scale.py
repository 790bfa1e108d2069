"""The scaling curve: env steps/s and CPU per role as actors, replay shards and learners grow.

    python bench/scale.py                    # ~9 minutes, on a machine with a GPU and 16 cores
    python bench/scale.py --device cpu --cluster-seconds 15 --actors 1 2 --wide 2 \\
        --envs HalfCheetah-v5                # a smoke run on two cores

One prepared script for a lease of a bigger machine (nothing else may run meanwhile):
`tpdeb-cluster` on each task of `--envs` (its preset, unchanged: the curve is throughput at
fixed learning settings; the learner on `--device`), trained for `--cluster-seconds` each run:

- HalfCheetah-v5: 1, 2, 4, 8 and 14 actors × 4 envs with one replay and one learner, then
  `--wide` actors with 2 replay shards and 2 learner ranks;
- then `--wide` actors with one replay and one learner twice more: its batch doubled
  (`batch_fragments=16`, what two ranks learn from per update) and batch growth
  (`max_batch_fragments=64`: the learner doubles its batch while the device has headroom);
- every other task of `--envs` (Ant-v5): `--wide` actors, one replay and one learner, then 2
  and 2.

Per run: env steps/s and updates/s over the run (end.json), the CPU each role used per second
of wall-clock (/proc, every second: the replay shards together, the learner ranks together,
the actors together) and, for the first task, each run's env steps/s against linear scaling
from its 1-actor run. Writes bench/out/scale/results.json (each run as it ends) and prints the
table for BENCHMARKS ("Scaling").
"""

from __future__ import annotations

import argparse
from pathlib import Path

import provenance
from gpu import cluster_arguments, cluster_run, cpu_cells, machine, save

from tpdeb.services.device import resolve_device

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "out" / "scale"


WIDER = ("batch_fragments=16",)  # one learner, the batch two ranks learn from
GROWN = ("max_batch_fragments=64",)  # batch growth


def plan(args) -> list[tuple[str, int, int, int, tuple]]:
    """(task, actors, replay shards, learners, more settings) of every run, in order."""
    first, *others = args.envs
    runs = [(first, n, 1, 1, ()) for n in args.actors] + [
        (first, args.wide, 2, 2, ()), (first, args.wide, 1, 1, WIDER),
        (first, args.wide, 1, 1, GROWN)]
    for env_id in others:
        runs += [(env_id, args.wide, 1, 1, ()), (env_id, args.wide, 2, 2, ())]
    return runs


def table(rows: list[dict]) -> str:
    base = {r["env_id"]: r["env_steps_per_s"] for r in rows
            if (r["actors"], r["replay_shards"], r["learners"]) == (1, 1, 1)
            and not r.get("settings")}
    out = ["| task | actors × 4 envs | replay shards | learners | settings | env steps/s | "
           "of linear | updates/s | CPU/s replay | router | learner | actors |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        one = base.get(r["env_id"])
        linear = f"{r['env_steps_per_s'] / (one * r['actors']):.2f}" if one else "—"
        more = ", ".join(r.get("settings", [])) or "preset"
        out.append(f"| {r['env_id']} | {r['actors']} | {r['replay_shards']} | {r['learners']} | "
                   f"{more} | {r['env_steps_per_s']:,.0f} | {linear} | "
                   f"{r['updates_per_s']:,.0f} | "
                   f"{cpu_cells(r['cpu_per_s'])} |")
    return "\n".join(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    cluster_arguments(parser, cluster_seconds=30.0)
    parser.add_argument("--envs", nargs="+", default=["HalfCheetah-v5", "Ant-v5"],
                        help="the first task's curve over --actors; the others at --wide")
    parser.add_argument("--wide", type=int, default=14,
                        help="actors of the runs with 2 replay shards and 2 learner ranks")
    args = parser.parse_args()
    if args.wide < 2:
        parser.error("--wide must be ≥ 2 (a replay shard per actor at least)")
    record = provenance.start()
    device = resolve_device(args.device)
    OUT.mkdir(parents=True, exist_ok=True)
    result = {"machine": machine(device), "args": vars(args), "runs": []}
    print(f"[scale] {result['machine']}; {len(plan(args))} runs of "
          f"{args.cluster_seconds:g} s", flush=True)
    for env_id, actors, shards, learners, settings in plan(args):
        result["runs"].append(cluster_run(args, actors, args.device, shards, learners, env_id,
                                          out=OUT, settings=settings))
        save(result, record, OUT)
    result["table_markdown"] = table(result["runs"])
    save(result, record, OUT)
    print()
    print(result["table_markdown"])


if __name__ == "__main__":
    main()
