"""Fuzzing benchmark: every hypothesis fuzz test of the wire format at bench scale.

    python bench/fuzz.py                     # 10,000 cases per fuzz test and message type
    python bench/fuzz.py --examples 100000   # longer
    python bench/fuzz.py --out docs/data/fuzz.json   # the counts kept, with their provenance

The fuzz tests of `tests/test_protocol.py` (every `@given` test there) run through pytest with
`TPDEB_FUZZ_EXAMPLES` set to `--examples`, so the strategies and properties are exactly the
suite's. The tests that run once per message type get the full count for each type, so every
message decoder sees at least `--examples` cases of its own. Every case goes through the tests'
`decode_or_error`; this script wraps it to count the cases and to record crashes instead of
letting the first one end the test, so the crash count covers all cases (hypothesis does not
shrink them then; the smallest crashing input of each kind is printed to reproduce it). A crash is
any exception from `decode` other than `DecodeError`, including one caught by the codec's own
safety net (a `DecodeError` saying "internal error", raised from another exception): a service
would survive it, but a rule tripped over its input.

Prints, per fuzz test, the cases, crashes and seconds, with the total, and then how many cases
reached each message type's body decoder (the rest stopped at the envelope: msgpack, version,
type). Exit status 1 on any crash or failed property, 2 when a fuzz test counted no cases.
`--out` keeps every count (per test, per message type) and that verdict in a JSON file.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import provenance
import pytest

ROOT = Path(__file__).resolve().parents[1]
TARGET = "tests/test_protocol.py"
ENVELOPE = "(envelope only)"  # cases refused before any message type's body decoder ran
MAX_CRASHES_SHOWN = 10  # kinds of crash printed with a reproducing input, most frequent first


def say(text: str) -> None:
    print(f"[fuzz] {text}", flush=True)


@dataclass
class TestRun:
    name: str
    cases: int = 0
    crashes: int = 0
    seconds: float = 0.0
    outcome: str = "not run"
    by_type: Counter = field(default_factory=Counter)
    crashes_by_type: Counter = field(default_factory=Counter)


@dataclass
class Crash:
    test: str
    kind: str  # exception type and where the codec's safety net saw it
    data: bytes
    count: int = 1


class FuzzCounter:
    """A pytest plugin: keeps only the hypothesis tests of TARGET, wraps their decode path to
    count cases and crashes, and shows progress while each runs."""

    def __init__(self, examples: int, out=sys.stdout):
        self.examples = examples
        self.out = out
        self.tty = out.isatty()
        self.runs: dict[str, TestRun] = {}
        self.crashes: dict[tuple[str, str], Crash] = {}
        self.current: TestRun | None = None
        self.reached: str | None = None
        self.started = 0.0
        self.last_shown = 0.0
        self.total_tests = 0
        self.problems: list[str] = []  # failure reports (pytest's own terminal output is off)

    # -- pytest hooks
    def pytest_collection_modifyitems(self, config, items):
        keep = [item for item in items if getattr(item.obj, "is_hypothesis_test", False)]
        config.hook.pytest_deselected(items=[item for item in items if item not in keep])
        items[:] = keep

    def pytest_collection_finish(self, session):
        # After every deselection (-k included): the tests that will run.
        self.runs = {item.name: TestRun(item.name) for item in session.items}
        self.total_tests = len(self.runs)

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_call(self, item):
        import tpdeb.protocol.codec as codec

        module = item.module
        original_check = module.decode_or_error
        # Only for the by-type breakdown: without it every case counts as "envelope only".
        original_load = getattr(codec, "load_message", None)
        self.current = self.runs[item.name]
        module.decode_or_error = self._counting(original_check)
        if original_load is not None:
            codec.load_message = self._noting_type(original_load)
        self.started = self.last_shown = time.monotonic()
        self._show(force=True)
        try:
            yield
        finally:
            module.decode_or_error = original_check
            if original_load is not None:
                codec.load_message = original_load
            self._show(force=True, done=True)
            self.current = None

    def pytest_runtest_logreport(self, report):
        name = report.nodeid.split("::")[-1]
        if report.when == "call" and name in self.runs:
            self.runs[name].seconds, self.runs[name].outcome = report.duration, report.outcome
        if report.failed:
            self.problems.append(f"{report.nodeid} ({report.when}):\n{report.longreprtext}")

    def pytest_collectreport(self, report):
        if report.failed:
            self.problems.append(f"collecting {report.nodeid}:\n{report.longreprtext}")

    # -- wrappers
    def _noting_type(self, load_message):
        def wrapped(cls, body, spec, *args, **kwargs):
            if self.reached is None:  # the outermost message of this case
                self.reached = cls.__name__
            return load_message(cls, body, spec, *args, **kwargs)
        return wrapped

    def _counting(self, decode_or_error):
        from tpdeb.protocol import DecodeError

        def wrapped(data, *args, **kwargs):
            run = self.current
            run.cases += 1
            self.reached = None
            try:
                return decode_or_error(data, *args, **kwargs)
            except Exception as exc:
                # decode_or_error lets anything but a DecodeError through, and asserts on a
                # DecodeError from the codec's safety net: both are crashes.
                cause = exc.__context__ if isinstance(exc.__context__, DecodeError) else None
                inner = cause.__cause__ if cause is not None else None
                kind = (f"{type(inner).__name__} behind the codec's safety net ({cause.detail})"
                        if inner is not None else
                        f"{type(cause).__name__}: {cause}" if cause is not None else
                        f"{type(exc).__name__}: {exc}")
                self._record(run, kind[:200], bytes(data))
                # The rest of the test sees a refusal; the crash is counted here.
                return DecodeError("field", f"crash recorded by bench/fuzz.py: {kind[:200]}")
            finally:
                run.by_type[self.reached or ENVELOPE] += 1
                self._show()
        return wrapped

    def _record(self, run: TestRun, kind: str, data: bytes) -> None:
        run.crashes += 1
        run.crashes_by_type[self.reached or ENVELOPE] += 1
        key = (run.name, kind)
        crash = self.crashes.get(key)
        if crash is None:
            self.crashes[key] = Crash(run.name, kind, data)
        else:
            crash.count += 1
            if len(data) < len(crash.data):
                crash.data = data

    # -- progress
    def _show(self, force: bool = False, done: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self.last_shown < (0.5 if self.tty else 10.0):
            return
        self.last_shown = now
        run = self.current
        index = list(self.runs).index(run.name) + 1
        pct = min(100, 100 * run.cases // max(self.examples, 1))
        text = (f"[fuzz] {index}/{self.total_tests} {run.name}: {run.cases:,} cases"
                f"{'' if done else f' (~{pct} %)'}, {run.crashes} crashes, "
                f"{now - self.started:.1f} s")
        if self.tty:
            self.out.write("\r\033[K" + text + ("\n" if done else ""))
        elif done or not force:
            self.out.write(text + "\n")
        self.out.flush()


def render(counter: FuzzCounter) -> str:
    runs = list(counter.runs.values())
    lines = ["| decoder (fuzz test) | cases | crashes | seconds | result |",
             "|---|---:|---:|---:|---|"]
    for r in runs:
        reached = [t for t in r.by_type if t != ENVELOPE]
        what = ("envelope" if not reached else reached[0] if len(reached) == 1
                else f"{len(reached)} message types")
        lines.append(f"| {r.name} ({what}) | {r.cases:,} | {r.crashes} | {r.seconds:.1f} | "
                     f"{r.outcome} |")
    lines.append(f"| **total** | **{sum(r.cases for r in runs):,}** | "
                 f"**{sum(r.crashes for r in runs)}** | **{sum(r.seconds for r in runs):.1f}** | "
                 f"{'passed' if all(r.outcome == 'passed' for r in runs) else 'FAILED'} |")
    by_type, crashes = Counter(), Counter()
    for r in runs:
        by_type.update(r.by_type)
        crashes.update(r.crashes_by_type)
    lines += ["", "Cases by the message type whose body decoder they reached (all fuzz tests):",
              "", "| message type | cases | crashes |", "|---|---:|---:|"]
    for name in sorted(by_type, key=lambda t: (t == ENVELOPE, t)):
        lines.append(f"| {name} | {by_type[name]:,} | {crashes[name]} |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--examples", type=int, default=10_000,
                        help="hypothesis examples per fuzz test (TPDEB_FUZZ_EXAMPLES)")
    parser.add_argument("-k", dest="select", help="only fuzz tests matching this pytest -k")
    parser.add_argument("--out", type=Path, help="keep the counts and the verdict here (JSON)")
    args = parser.parse_args()
    record = provenance.start()
    if args.examples < 1:
        parser.error(f"--examples {args.examples}: must be ≥ 1")
    # Read by tests/test_protocol.py when pytest imports it below.
    os.environ["TPDEB_FUZZ_EXAMPLES"] = str(args.examples)
    os.chdir(ROOT)
    counter = FuzzCounter(args.examples)
    say(f"{args.examples:,} examples per fuzz test of {TARGET}")
    # Progress and failures are reported here, so pytest's terminal reporter is off.
    pytest_args = [TARGET, "-s", "-o", "addopts=", "-p", "no:terminal", "-p", "no:cacheprovider",
                   "--timeout=0"]
    if args.select:
        pytest_args += ["-k", args.select]
    code = pytest.main(pytest_args, plugins=[counter])
    for problem in counter.problems:
        print(f"\n{problem}")
    if not counter.runs:
        say(f"no fuzz test was collected (pytest exit {int(code)})")
        return 2
    print()
    print(render(counter))
    crashes = sorted(counter.crashes.values(), key=lambda c: -c.count)
    for crash in crashes[:MAX_CRASHES_SHOWN]:
        print(f"\ncrash in {crash.test} ({crash.count}×): {crash.kind}\n"
              f"  smallest input ({len(crash.data)} bytes): {crash.data[:256].hex()}"
              f"{'…' if len(crash.data) > 256 else ''}")
    if len(crashes) > MAX_CRASHES_SHOWN:
        say(f"{len(crashes) - MAX_CRASHES_SHOWN} more kinds of crash not shown")
    silent = [r.name for r in counter.runs.values() if r.outcome == "passed" and r.cases == 0]
    if silent:
        say(f"counted no cases in {silent}: they no longer call decode_or_error")
        return 2
    short = [r.name for r in counter.runs.values()
             if r.outcome == "passed" and 0 < r.cases < args.examples]
    if short:
        say(f"fewer than {args.examples:,} cases in {short} (hypothesis ran out of examples)")
    crashed = sum(r.crashes for r in counter.runs.values())
    if args.out is not None:
        keep(args.out, counter, record, code, short)
    if crashed or code != 0:
        say(f"{crashed} crash(es); pytest exit {int(code)}")
        return 1
    return 0


def judge(runs: list[TestRun]) -> list[str]:
    """Why a fuzz run fails (empty: it passes), by the rule fixed before it: no fuzz test
    crashed a decoder, every one passed (its properties held), and every one counted cases
    (one that counts none no longer reaches the decoders)."""
    if not runs:
        return ["no fuzz test ran"]
    why = [f"{r.name}: {r.crashes} crash(es)" for r in runs if r.crashes]
    why += [f"{r.name}: {r.outcome}" for r in runs if r.outcome != "passed"]
    why += [f"{r.name}: no case counted" for r in runs if r.outcome == "passed" and not r.cases]
    return why


def keep(path: Path, counter: FuzzCounter, record: dict, code: int, short: list[str]) -> None:
    """The counts, the crashes' kinds and the verdict (no crash and every property held) to
    `path`."""
    runs = list(counter.runs.values())
    by_type = Counter()
    for r in runs:
        by_type.update(r.by_type)
    why = judge(runs)
    result = {"examples_per_test": counter.examples, "pytest_exit": int(code),
              "tests": [{"name": r.name, "cases": r.cases, "crashes": r.crashes,
                         "seconds": round(r.seconds, 1), "outcome": r.outcome,
                         "by_type": dict(r.by_type)} for r in runs],
              "cases": sum(r.cases for r in runs), "crashes": sum(r.crashes for r in runs),
              "by_type": dict(by_type), "short_of_examples": short,
              "crash_kinds": [{"test": c.test, "kind": c.kind, "count": c.count,
                               "smallest_input_hex": c.data[:256].hex()}
                              for c in counter.crashes.values()],
              "table_markdown": render(counter)}
    provenance.stamp(result, record)
    provenance.add_verdict(result, "bench/fuzz.py:judge", 1, not why, why)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=1))
    provenance.written(path)
    say(f"counts in {path}")


if __name__ == "__main__":
    sys.exit(main())
