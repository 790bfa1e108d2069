"""The replay's write-ahead log and snapshots: what reads back after clean stops, crashes mid-write
and damaged files."""

from __future__ import annotations

import threading

import pytest

from services.persistence import MARKER, ReplayPersistence, append_record, read_records


def decode(payload: bytes) -> str:
    return payload.decode()


def encode(item: str) -> bytes:
    return item.encode()


def test_log_and_snapshot_restore_everything_in_order(tmp_path):
    p = ReplayPersistence(tmp_path)
    for i in range(5):
        p.log(f"a{i}".encode())
    p.snapshot({"n": 5}, ["x", "y"], encode, wait=True)
    for i in range(3):
        p.log(f"b{i}".encode())
    p.sync()
    p.close()
    state, records = ReplayPersistence(tmp_path).load(decode)
    assert state["n"] == 5 and state["items"] == ["x", "y"]
    assert [r.decode() for r in records] == ["b0", "b1", "b2"]  # only what came after


def test_no_snapshot_means_the_whole_log(tmp_path):
    p = ReplayPersistence(tmp_path)
    for i in range(4):
        p.log(f"a{i}".encode())
    p.sync()  # a kill -9 now: no close
    state, records = ReplayPersistence(tmp_path).load(decode)
    assert state is None and [r.decode() for r in records] == ["a0", "a1", "a2", "a3"]


def test_a_torn_record_ends_the_log(tmp_path):
    p = ReplayPersistence(tmp_path)
    p.log(b"whole")
    p.log(b"torn-record")
    p.close()
    segment = next(tmp_path.glob("wal-*.log"))
    segment.write_bytes(segment.read_bytes()[:-4])  # the crash hit mid-write
    _, records = ReplayPersistence(tmp_path).load(decode)
    assert [r.decode() for r in records] == ["whole"]
    with pytest.raises(Exception, match="corrupt"):
        list(read_records(segment, strict=True))


def test_a_restarted_log_never_appends_to_an_old_segment(tmp_path):
    p = ReplayPersistence(tmp_path)
    p.log(b"one")
    p.close()
    q = ReplayPersistence(tmp_path)
    _, records = q.load(decode)
    assert list(records) == [b"one"]
    q.log(b"two")
    q.close()
    assert len(list(tmp_path.glob("wal-*.log"))) == 2
    _, records = ReplayPersistence(tmp_path).load(decode)
    assert list(records) == [b"one", b"two"]


def test_incomplete_and_damaged_snapshots_are_passed_over(tmp_path):
    p = ReplayPersistence(tmp_path, keep_snapshots=2)
    p.log(b"before-first")
    p.snapshot({"n": 1}, ["x"], encode, wait=True)
    p.log(b"between")
    p.snapshot({"n": 2}, ["x", "y"], encode, wait=True)
    p.log(b"after-second")
    p.close()
    newest = sorted(tmp_path.glob("snapshot-*"))[-1]
    items = newest / "items.bin"
    items.write_bytes(items.read_bytes()[:-1] + b"?")  # damaged: the CRC in the marker fails
    (tmp_path / ".snapshot-00000099.tmp").mkdir()  # an interrupted write
    q = ReplayPersistence(tmp_path)
    state, records = q.load(decode)
    assert state["n"] == 1 and "does not match" in q.skipped
    assert [r.decode() for r in records] == ["between", "after-second"]
    assert not (tmp_path / ".snapshot-00000099.tmp").exists()


def test_a_snapshot_without_its_marker_does_not_count(tmp_path):
    p = ReplayPersistence(tmp_path)
    p.log(b"a")
    p.snapshot({"n": 1}, [], encode, wait=True)
    p.close()
    (next(tmp_path.glob("snapshot-*")) / MARKER).unlink()
    state, records = ReplayPersistence(tmp_path).load(decode)
    assert state is None and list(records) == [b"a"]  # the log it covered is still there


def test_old_snapshots_and_covered_log_segments_are_pruned(tmp_path):
    p = ReplayPersistence(tmp_path, keep_snapshots=2)
    for n in range(5):
        p.log(f"r{n}".encode())
        p.snapshot({"n": n}, [], encode, wait=True)
    p.close()
    assert len(list(tmp_path.glob("snapshot-*"))) == 2
    oldest_kept = min(int(s.name.split("-")[1]) for s in tmp_path.glob("snapshot-*"))
    assert all(int(w.stem.split("-")[1]) >= oldest_kept for w in tmp_path.glob("wal-*.log"))


def test_a_snapshot_in_progress_is_not_started_twice(tmp_path):
    p = ReplayPersistence(tmp_path)
    release = threading.Event()

    def held_encode(item):  # the first snapshot's writer waits here until released
        release.wait(10)
        return item.encode()

    assert p.snapshot({"n": 1}, ["x"], held_encode)
    assert p.writing
    assert not p.snapshot({"n": 2}, [], encode)  # refused, not queued
    release.set()
    p.close()
    assert p.snapshots_written == 1


def test_records_round_trip(tmp_path):
    path = tmp_path / "f.bin"
    with path.open("wb") as f:
        for payload in (b"", b"x" * 70000, b"\x00\xff"):
            append_record(f, payload)
    assert list(read_records(path, strict=True)) == [b"", b"x" * 70000, b"\x00\xff"]
