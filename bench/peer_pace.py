"""Which SAC runs faster here: SB3's (zoo settings) against CleanRL's single-file SAC
(bench/cleanrl_sac.py), each `bench/peers.py` run for a short wall-clock budget, alternated
A, B, A, B so a change of the machine's speed meets both. The figure is env steps per second
while learning (between the end of the random warm-up and the end of the budget, from the
episodes' (seconds, steps)), the part that decides a 15-minute race.

    python bench/peer_pace.py                      # HalfCheetah-v5, 120 s × 2 pairs
    python bench/peer_pace.py --envs Hopper-v5 --seconds 90 --pairs 3

Writes docs/data/race-pace/{env}.json (each run, and per system the median). Nothing else may
run on the machine meanwhile: these are timings.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import provenance  # noqa: I001  (bench/ is on sys.path)
from runs import ROOT, save_json

SYSTEMS = ("sb3-sac", "cleanrl-sac")
OUT = ROOT / "docs" / "data" / "race-pace"


def learning_pace(episodes: list, train_s: float, steps: int) -> float | None:
    """Env steps per second from the first episode ending after 12.5 % of the budget (past
    every warm-up: SB3's zoo waits 10,000 steps on the four large tasks, CleanRL 5,000) to the
    end of the run."""
    after = [(t, n) for t, n, _ in episodes if t >= 0.125 * train_s]
    if not after or train_s - after[0][0] < 10:
        return None
    t0, n0 = after[0]
    return (steps - n0) / (train_s - t0)


def run(system: str, env_id: str, seed: int, seconds: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "peer.json"
        cmd = [sys.executable, str(ROOT / "bench" / "peers.py"), "--system", system,
               "--env-id", env_id, "--seed", str(seed), "--seconds", str(seconds),
               "--marks", str(seconds), "--eval-episodes", "1", "--out", str(out)]
        subprocess.run(cmd, cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
        result = json.loads(out.read_text())
    pace = learning_pace(result["episodes"], result["train_s"], result["steps"])
    return {"system": system, "seed": seed, "train_s": result["train_s"],
            "steps": result["steps"], "learning_steps_per_s": pace}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=["HalfCheetah-v5"])
    parser.add_argument("--seconds", type=float, default=120.0)
    parser.add_argument("--pairs", type=int, default=2)
    args = parser.parse_args()
    for env_id in args.envs:
        record = provenance.start()
        runs = []
        for pair in range(args.pairs):
            for system in SYSTEMS:
                runs.append(run(system, env_id, 1 + pair, args.seconds))
                pace = runs[-1]["learning_steps_per_s"]
                print(f"[pace] {env_id} pair {pair + 1}: {system} "
                      f"{'n/a' if pace is None else f'{pace:,.0f}'} env steps/s while learning",
                      flush=True)
        medians = {s: statistics.median(r["learning_steps_per_s"] for r in runs
                                        if r["system"] == s and r["learning_steps_per_s"])
                   for s in SYSTEMS}
        ratio = medians["cleanrl-sac"] / medians["sb3-sac"]
        print(f"[pace] {env_id}: median {medians['sb3-sac']:,.0f} (sb3-sac) and "
              f"{medians['cleanrl-sac']:,.0f} (cleanrl-sac) env steps/s: {ratio:.2f}×", flush=True)
        save_json(OUT / f"{env_id}.json", provenance.stamp(
            {"env_id": env_id, "seconds": args.seconds, "runs": runs,
             "median_learning_steps_per_s": medians, "cleanrl_over_sb3": round(ratio, 3)},
            record))


if __name__ == "__main__":
    main()
