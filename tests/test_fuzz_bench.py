"""The fuzz bench's verdict (bench/fuzz.py): made-up test runs, nothing fuzzed."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import fuzz  # noqa: E402


def run(name="test_arbitrary_bytes", cases=10_000, crashes=0, outcome="passed"):
    return fuzz.TestRun(name, cases=cases, crashes=crashes, outcome=outcome)


def test_clean_runs_pass():
    assert fuzz.judge([run(), run("test_bodies[Ack]")]) == []


def test_a_crash_a_failed_property_a_silent_test_or_nothing_run_fails():
    assert fuzz.judge([run(), run(crashes=3)]) == ["test_arbitrary_bytes: 3 crash(es)"]
    assert fuzz.judge([run(outcome="failed")]) == ["test_arbitrary_bytes: failed"]
    assert fuzz.judge([run(cases=0)]) == ["test_arbitrary_bytes: no case counted"]
    assert fuzz.judge([]) == ["no fuzz test ran"]
