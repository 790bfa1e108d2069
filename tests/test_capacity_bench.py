"""The benches' arithmetic: the capacity plan (bench/capacity.py: medians over kept runs of each
run's best sender count, the actors one replay and one learner can feed) and how processes are
named (bench/procfs.py); made-up inputs, nothing timed."""

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
    assert row == "| HalfCheetah-v5 | 5,000 | 17.6 | 1.4 (64×64, 16) | 1.4 (8) |"


def test_the_plan_says_which_batch_growth_would_keep_and_what_it_feeds():
    result = run([88e3], 90e3, 9e3, 200, 5e3)
    result["learner"] = [  # 16 costs 1.33× an update on 8 (kept), 32 2.1× one on 16 (not)
        {"hidden": "64×64", "batch_fragments": b, "updates_per_s": u, "batch_steps": 64 * b}
        for b, u in ((8, 200.0), (16, 150.0), (32, 70.0))]
    assert capacity.grown(result["learner"], "64×64")["batch_fragments"] == 16
    combined = capacity.combine([result])
    assert [r["updates_per_s"] for r in combined["learner"]] == [200.0, 150.0, 70.0]
    row = capacity.plan_table(combined).splitlines()[-1]
    # batch 8: 200 × 512 / 16 / 5,000 = 1.3 actors; batch 16: 150 × 1,024 / 16 / 5,000 = 1.9
    assert row == "| HalfCheetah-v5 | 5,000 | 17.6 | 1.3 (64×64, 16) | 1.9 (16) |"


def test_the_plan_adds_shards_and_learner_ranks_where_ranks_were_timed():
    timed = [run([88e3], 90e3, 9e3, 220, 5e3) for _ in range(2)]
    for result, rate in zip(timed, (170.0, 190.0), strict=True):
        result["ranks"] = [{"hidden": "64×64", "ranks": 2, "batch_fragments": 8,
                            "updates_per_s": rate, "batch_steps": 512}]
    combined = capacity.combine([*timed, run([88e3], 90e3, 9e3, 220, 5e3)])  # one without
    assert combined["ranks"][0]["updates_per_s"] == 180.0
    assert combined["ranks"][0]["runs"] == [170.0, 190.0]
    header, _, row = capacity.plan_table(combined).splitlines()
    assert "2 replay shards | 2 learner ranks" in header
    # 2 shards: 2 × 88,000 / 5,000 = 35.2; 2 ranks: 2 × 180 × 512 / 16 / 5,000 = 2.3, each
    # rank 180 / 220 = 0.82 of one learner
    assert row.endswith("| 35.2 | 2.3 (0.82) |")
    assert "shards" not in capacity.plan_table(capacity.combine([run([88e3], 90e3, 9e3, 220,
                                                                      5e3)]))


def test_services_are_named_from_their_command_lines():
    import procfs

    assert procfs.service_name(["/v/bin/tpdeb-actor", "--config", "/r/config/actor-1.toml"]) \
        == "actor-1"  # as tpdeb-cluster starts them: one name per actor, not a restart
    assert procfs.service_name(["py", "-m", "tpdeb.services.actor", "--actor-id", "3"]) == \
        "actor-3"
    assert procfs.service_name(["/v/bin/tpdeb-cluster", "--config", "deploy/local.toml"]) == \
        "cluster"
    assert procfs.service_name(["/usr/bin/python3", "train.py"]) is None
