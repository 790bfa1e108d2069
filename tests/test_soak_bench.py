"""The soak's verdict (bench/soak.py): a series is judged by the median of the minute after
warm-up against the median of the last minute; made-up series, nothing timed."""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import soak  # noqa: E402


def series(values_by_minute: list[float]) -> list[tuple[float, float]]:
    return [(60.0 * m + s, v) for m, v in enumerate(values_by_minute) for s in range(0, 60, 5)]


def test_a_flat_series_passes_and_the_warm_up_is_not_judged():
    verdict = soak.judge(series([50.0, 90.0, 100.0, 101.0, 102.0, 103.0]), 120.0, 360.0, 5.0)
    assert verdict["result"] == "PASS"
    assert verdict["warmup_mib"] == 100.0 and verdict["final_mib"] == 103.0
    assert round(verdict["drift_pct"], 6) == 3.0 and verdict["min_mib"] == 100.0


def test_growth_or_shrinkage_past_the_tolerance_fails():
    assert soak.judge(series([100.0, 100.0, 103.0, 106.0]), 60.0, 240.0, 5.0)["result"] == "FAIL"
    assert soak.judge(series([100.0, 100.0, 97.0, 94.0]), 60.0, 240.0, 5.0)["result"] == "FAIL"


def test_a_soak_too_short_to_judge_fails_with_the_reason():
    verdict = soak.judge(series([100.0, 100.0]), 120.0, 120.0, 5.0)
    assert verdict["result"] == "FAIL" and "no samples" in verdict["why"]


def test_a_gauge_is_judged_over_minutes_enough_to_hold_its_sawtooth():
    # the replay's disk: its log grows for 70 s and is cut at a snapshot; no trend at all
    tooth = [(float(t), 80.0 + 80.0 * (t % 70) / 70) for t in range(0, 3600, 5)]
    minute = soak.judge(tooth, 120.0, 3600.0, 5.0)
    assert minute["result"] == "FAIL"  # one minute's median depends on where the minute falls
    results = {"meta": {"warmup_minutes": 2.0, "soak_s": 3600.0, "tolerance_pct": 5.0},
               "series": {"replay disk (MiB)": tooth, "replay": series([90.0] * 60)},
               "problems": [], "restarts": {}}
    judged = soak.verdict(results)
    assert judged["summary"]["replay disk (MiB)"]["window_s"] == 300.0
    assert judged["summary"]["replay"]["window_s"] == 60.0
    assert judged["result"] == "PASS", judged["table_markdown"]


def test_a_failing_series_or_a_problem_fails_the_verdict_with_its_reason():
    results = {"meta": {"warmup_minutes": 2.0, "soak_s": 3600.0, "tolerance_pct": 5.0},
               "series": {"replay": series([90.0] * 30 + [99.0] * 30)},
               "problems": [], "restarts": {}}
    judged = soak.verdict(results)
    assert judged["result"] == "FAIL" and judged["reasons"] == [
        "replay: drift +10.0 % beyond ±5 %"]
    results["series"]["replay"] = series([90.0] * 60)
    results["problems"] = ["services restarted during the soak: {'actor-0': 1}"]
    assert soak.verdict(results)["reasons"] == results["problems"]


def test_rejudging_adds_a_verdict_beside_the_first_and_never_rewrites_it(tmp_path, capsys):
    results = {"meta": {"warmup_minutes": 2.0, "soak_s": 3600.0, "tolerance_pct": 5.0},
               "series": {"replay": series([90.0] * 60)}, "problems": [], "restarts": {},
               "summary": {}, "result": "FAIL", "table_markdown": "as the run judged it",
               "verdicts": [{"rule": soak.RULE, "rule_version": 1, "verdict": "FAIL",
                             "reasons": ["a rule of old"]}]}
    path = tmp_path / "soak.json"
    path.write_text(json.dumps(results))
    assert soak.rejudge(path, None, None) == 0
    after = json.loads(path.read_text())
    assert [(v["rule_version"], v["verdict"]) for v in after["verdicts"]] == [
        (1, "FAIL"), (soak.RULE_VERSION, "PASS")]
    assert after["result"] == "FAIL" and after["table_markdown"] == "as the run judged it"
    assert soak.rejudge(path, None, None) == 0  # the same rule again: nothing added
    assert len(json.loads(path.read_text())["verdicts"]) == 2
