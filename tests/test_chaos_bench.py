"""The chaos bench's bookkeeping (bench/chaos.py): its seeded schedule of faults, the recovery
time of a fault, the per-process version check and the fragment audit; made-up inputs, no
cluster."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import chaos  # noqa: E402

SERVICES = ["router", "replay", "learner", "actor-0", "actor-1"]


def test_the_schedule_is_seeded_spaced_and_inside_the_window():
    faults = chaos.schedule(7, 60.0, 1860.0, SERVICES)
    assert faults == chaos.schedule(7, 60.0, 1860.0, SERVICES)
    assert faults != chaos.schedule(8, 60.0, 1860.0, SERVICES)
    assert faults[0].at_s == 60.0 and faults[-1].end_s <= 1860.0
    for before, after in zip(faults, faults[1:], strict=False):
        assert 10.0 <= after.at_s - before.end_s <= 30.0 + 0.1
    for f in faults:
        assert f.kind in chaos.KINDS
        if f.kind == "kill":
            assert f.hold_s == 0 and f.target in SERVICES
        else:
            assert 5.0 <= f.hold_s <= 20.0
            assert (f.target == "link") == (f.kind == "partition")
    # half an hour holds every kind, and every service is hit
    assert {f.kind for f in faults} == set(chaos.KINDS)
    assert {f.target for f in faults} == {*SERVICES, "link"}


def test_one_fault_repeated_fills_the_window_and_bad_specs_are_refused():
    faults = chaos.repeated("hang:router:12", 45.0, 237.0, SERVICES)
    assert [f.at_s for f in faults] == [45.0, 77.0, 109.0, 141.0, 173.0, 205.0]
    assert all((f.kind, f.target, f.hold_s) == ("hang", "router", 12.0) for f in faults)
    assert {f.hold_s for f in chaos.repeated("kill:learner", 0.0, 100.0, SERVICES)} == {0.0}
    assert chaos.repeated("partition:link", 0.0, 60.0, SERVICES)[0].hold_s == 5.0
    for bad in ("hang:foo:1", "partition:router", "hang:router:x", "hang", "hang:router:1:2",
                "stop:router", "hang:link:5"):
        with pytest.raises(SystemExit, match="expected kind:target"):
            chaos.repeated(bad, 0.0, 60.0, SERVICES)


def learner(t, version):
    return (t, "learner", "0", {"param_version": version})


def test_recovery_waits_for_the_targets_acks_and_a_newer_learner_version():
    fault = chaos.Fault(at_s=10.0, kind="hang", target="actor-1", hold_s=5.0)
    stats = [learner(9.0, 40), learner(14.0, 41), learner(16.0, 41), learner(18.0, 42)]
    acks = {(0, 1, 5): 15.5, (1, 2, 7): 17.0}
    # actor 1's first ack after the end (15 s) is at 17 s; the learner's first version above
    # 41 (the newest before the end) at 18 s
    assert chaos.recovery_s(fault, acks, stats) == 3.0
    router = chaos.Fault(at_s=10.0, kind="kill", target="router")
    # anyone's ack (15.5 s) and a version above 40 (15 s): 5.5 s after the kill
    assert chaos.recovery_s(router, acks, [learner(9.0, 40), learner(15.0, 41)]) == 5.5
    assert chaos.recovery_s(fault, {(0, 1, 5): 15.5}, stats) is None  # actor 1 never came back


def test_after_a_kill_only_an_ack_the_dead_process_could_not_have_sent_counts():
    versions = [learner(9.0, 40), learner(10.5, 41)]
    replay = chaos.Fault(at_s=10.0, kind="kill", target="replay")
    # an ack the dying replay had sent lands 10 ms after the kill; the restarted one acks at 13 s
    acks = {(0, 1, 5): 10.01, (0, 1, 6): 13.0}
    assert chaos.recovery_s(replay, acks, versions) == 3.0
    # a killed actor's old incarnation still being acknowledged is not its recovery
    actor = chaos.Fault(at_s=10.0, kind="kill", target="actor-0")
    acks = {(0, 1, 5): 9.0, (0, 1, 6): 10.5, (0, 2, 0): 14.0}
    assert chaos.recovery_s(actor, acks, versions) == 4.0


def test_versions_are_judged_per_actor_process():
    stats = [learner(1, 5), learner(2, 6),
             (1, "actor", "0", {"param_version": 5, "incarnation": "a"}),
             (2, "actor", "0", {"param_version": 6, "incarnation": "a"}),
             (3, "actor", "0", {"param_version": 0, "incarnation": "b"}),  # restarted: anew
             (4, "actor", "0", {"param_version": 7, "incarnation": "b"})]
    assert chaos.versions_monotone(stats) == {"learner": True, "actor-0/a": True,
                                              "actor-0/b": True}
    stats.append((5, "actor", "0", {"param_version": 6, "incarnation": "b"}))
    stats.append(learner(6, 3))
    assert chaos.versions_monotone(stats) == {"learner": False, "actor-0/a": True,
                                              "actor-0/b": False}


def ledger(windows, ingested, duplicates=0):
    return {"windows": windows, "ingested": ingested, "duplicates": duplicates}


def test_the_audit_finds_lost_and_duplicated_fragments():
    # actor 0, incarnation 9: seqs 0-3 and 6 stored; actor 1, incarnation 4: seqs 0-1
    ledgers = {0: ledger({9: (4, [6])}, 5, duplicates=2), 1: ledger({4: (2, [])}, 2)}
    acked = {(0, 9, 0), (0, 9, 3), (0, 9, 6), (1, 4, 1)}
    clean = chaos.audit(acked, ledgers, inserted=7, logged=[])
    assert (clean["lost"], clean["duplicated"], clean["stored"]) == (0, 0, 7)
    assert clean["resends_recognised"] == 2
    # acknowledged, stored nowhere: lost, unless the log after the snapshot holds it
    missing = chaos.audit(acked | {(0, 9, 5), (1, 7, 0)}, ledgers, 7, [(1, 7, 0)])
    assert missing["lost"] == 1 and missing["lost_examples"] == [[0, 9, 5]]
    assert missing["duplicated"] == 0 and missing["stored"] == 8
    # inserted twice: the buffers took in more than the distinct fragments
    assert chaos.audit(acked, ledgers, inserted=8, logged=[])["duplicated"] == 1
    # a logged record the snapshot already holds would go in again on restore
    assert chaos.audit(acked, ledgers, 7, [(1, 4, 0)])["duplicated"] == 1


def a_run(**change) -> dict:
    """A chaos result that passes: every fault recovered quickly, nothing lost, a clear rise."""
    result = {"exit_code": 0, "versions_monotone": True,
              "audit": {"lost": 0, "duplicated": 0},
              "faults": [{"kind": "kill", "target": "replay", "at_s": 100.0, "end_s": 100.0,
                          "recovery_s": 0.7},
                         {"kind": "hang", "target": "actor-0", "at_s": 130.0, "end_s": 140.0,
                          "recovery_s": 1.2}],
              "return": {"first": 1000.0, "last": 5000.0, "first_std": 300.0,
                         "last_std": 400.0, "learned": True}}
    result.update(change)
    return result


def test_the_rule_passes_a_clean_run():
    assert chaos.judge(a_run()) == []


def test_a_fault_recovered_too_slowly_never_or_not_injected_fails_the_run():
    slow = a_run()
    slow["faults"][0]["recovery_s"] = chaos.RECOVERY_LIMIT_S + 14.2
    assert chaos.judge(slow) == ["kill replay at 100 s: recovered in 24.2 s > 10 s"]
    never = a_run()
    never["faults"][1]["recovery_s"] = None
    assert chaos.judge(never) == ["hang actor-0 at 130 s: never recovered"]
    skipped = a_run()
    skipped["faults"][1] = {"kind": "kill", "target": "learner", "at_s": 130.0,
                            "end_s": 130.0, "skipped": "not running"}
    assert chaos.judge(skipped) == ["kill learner at 130 s: not injected (not running)"]


def test_a_rise_within_the_spread_of_the_episodes_is_not_learning():
    rows = [(s, 1000.0 + (300 if s % 2 else -300)) for s in range(0, 100)]  # first 10 %
    rows += [(s, 1200.0 + (300 if s % 2 else -300)) for s in range(900, 1001)]  # last 10 %
    learned = chaos.returns_of(rows)
    assert learned["last"] > learned["first"] and learned["learned"] is False
    assert "did not rise" in chaos.judge(a_run(**{"return": learned}))[0]
    rows = [(s, r + (4000 if s >= 900 else 0)) for s, r in rows]
    assert chaos.returns_of(rows)["learned"] is True


def test_loss_duplicates_a_failed_exit_and_a_version_going_back_each_fail():
    assert chaos.judge(a_run(exit_code=1)) == ["the run exited with 1"]
    assert chaos.judge(a_run(audit={"lost": 2, "duplicated": 0})) == [
        "2 acknowledged fragments lost, 0 duplicated"]
    assert chaos.judge(a_run(versions_monotone=False)) == ["a parameter version went back"]
