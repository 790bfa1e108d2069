"""The capacity plan's arithmetic (bench/capacity.py): medians over kept runs of each run's best
sender count, and the actors one replay and one learner can feed; made-up runs, nothing timed."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import capacity  # noqa: E402


def run(wal_on: list[float], wal_off: float, forwarded: float, updates: float, acting: float):
    ingest = [{"persist": True, "actors": i + 1, "env_steps_per_s": x}
              for i, x in enumerate(wal_on)] + [{"persist": False, "actors": 1,
                                                 "env_steps_per_s": wal_off}]
    return {"ingest": ingest, "forwarding": [{"senders": 1, "forwarded_per_s": forwarded}],
            "learner": [{"hidden": "64×64", "updates_per_s": updates, "batch_steps": 512}],
            "acting": {"HalfCheetah-v5": {"env_steps_per_s": acting, "replay_ratio": 16.0,
                                          "hidden": "64×64"}}}


def test_the_plan_takes_medians_of_each_runs_best_sender_count():
    combined = capacity.combine([run([50e3, 80e3], 90e3, 9e3, 200, 5e3),
                                 run([95e3, 60e3], 99e3, 12e3, 250, 6e3),
                                 run([70e3, 88e3], 97e3, 15e3, 220, 4e3)])
    wal_on = next(r for r in combined["ingest"] if r["persist"])
    assert wal_on["runs"] == [80e3, 95e3, 88e3] and wal_on["env_steps_per_s"] == 88e3
    assert combined["forwarding"]["per_s"] == 12e3
    assert combined["learner"][0]["updates_per_s"] == 220
    assert combined["acting"]["HalfCheetah-v5"]["env_steps_per_s"] == 5e3
    row = capacity.plan_table(combined).splitlines()[-1]
    # one replay: 88,000 / 5,000 = 17.6 actors; one learner: 220 × 512 / 16 / 5,000 = 1.4
    assert row == "| HalfCheetah-v5 | 5,000 | 17.6 | 1.4 (64×64, 16) |"
