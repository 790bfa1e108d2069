"""The soak's verdict (bench/soak.py): a series is judged by the median of the minute after
warm-up against the median of the last minute; made-up series, nothing timed."""

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
