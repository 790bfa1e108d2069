"""The replay's write-ahead log and snapshots: what reads back after clean stops, crashes mid-write
and damaged files."""

from __future__ import annotations

import json
import pickle
import threading
import zlib

import msgpack
import numpy as np
import pytest

from tpdeb.services.store.persistence import (
    MARKER,
    STATE_FILE,
    CorruptRecord,
    Incompatible,
    ReplayPersistence,
    append_record,
    decode_state,
    encode_state,
    read_records,
)


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
    restored = ReplayPersistence(tmp_path)
    _, records = restored.load(decode)
    assert [r.decode() for r in records] == ["whole"]
    assert restored.torn == f"{segment.name} at byte 13 of 28"  # after 8-byte header + "whole"
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


class _Planted:
    """Unpickling this creates a file: the proof that a loader ran code."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def _replace_in_snapshot(snapshot, name: str, data: bytes) -> None:
    """Put `data` in a snapshot's file and its marker, as someone handing over a run dir could."""
    (snapshot / name).write_bytes(data)
    marker = json.loads((snapshot / MARKER).read_text())
    marker["files"][name] = {"bytes": len(data), "crc32": zlib.crc32(data)}
    (snapshot / MARKER).write_text(json.dumps(marker))


def test_state_files_round_trip_arrays_big_integers_and_integer_keys():
    state = {"slots": np.array([3, 1], np.int64), "mass": np.linspace(0, 1, 4).reshape(2, 2),
             "flags": np.array([True, False]), "rng": {"state": 2**127 + 5, "inc": -(2**70)},
             "ledgers": {7: {"windows": {2**62: (4, [6, 9])}}}, "none": None, "s": "x",
             "seen": {3, 1}, "f": np.float32(0.5)}
    back = decode_state(encode_state(state))
    assert back["slots"].dtype == np.int64 and back["slots"].tolist() == [3, 1]
    assert back["mass"].shape == (2, 2) and back["mass"][1, 1] == 1.0
    assert back["flags"].dtype == np.bool_ and back["rng"] == {"state": 2**127 + 5,
                                                                "inc": -(2**70)}
    assert back["ledgers"] == {7: {"windows": {2**62: [4, [6, 9]]}}}
    assert back["seen"] == [1, 3] and back["none"] is None and back["f"] == 0.5
    back["slots"][0] = 0  # a writable copy, not a view of the file's bytes


@pytest.mark.parametrize("value", [np.array(["a"], object), object(), _Planted("/nowhere")])
def test_state_files_refuse_what_is_not_plain_data(value):
    with pytest.raises(TypeError, match="cannot be stored"):
        encode_state({"x": value})


@pytest.mark.parametrize("data", [b"\x92\x01", b"\xc7\x03\x09abc",
                                  b"\xc7\x0f\x01" + bytes(15), b"\xd4\x02\x41"])
def test_state_files_refuse_damaged_or_foreign_bytes(data):
    with pytest.raises(CorruptRecord):
        decode_state(data)


def test_a_planted_pickle_in_a_run_dir_does_not_run(tmp_path):
    """A snapshot of someone else's run dir may hold a pickle, as state.pkl beside the state or
    in place of it (with a marker that matches): restoring reads neither as code, passes the
    snapshot over and falls back to the log."""
    run = tmp_path / "replay"
    p = ReplayPersistence(run)
    p.log(b"a")
    p.snapshot({"n": 1}, ["x"], encode, wait=True)
    p.log(b"b")
    p.close()
    snapshot = next(run.glob("snapshot-*"))
    proof = tmp_path / "ran"
    payload = pickle.dumps(_Planted(proof))
    _replace_in_snapshot(snapshot, "state.pkl", payload)
    state, _ = ReplayPersistence(run).load(decode)
    assert state == {"n": 1, "items": ["x"]} and not proof.exists()  # state.pkl is never read
    _replace_in_snapshot(snapshot, STATE_FILE, payload)
    q = ReplayPersistence(run)
    state, records = q.load(decode)
    assert not proof.exists()
    assert state is None and "not a state" in q.skipped
    assert list(records) == [b"a", b"b"]  # the log still holds everything


def _saved_state() -> dict:
    return {"format": 2, "env_id": "E", "obs_dim": 3, "act_dim": 1, "replay": {}, "limiter": {},
            "inserted_steps": 0, "samples_served": 0, "priority_updates": 0, "items": [],
            "ledgers": {0: {"ingested": 1, "duplicates": 0, "dropped_busy": 0,
                            "windows": {5: [1, [3]]}}}}


@pytest.mark.parametrize("damage, match", [
    (lambda s: s.pop("limiter"), "lacks 'limiter'"),
    (lambda s: s.update(inserted_steps="12"), "inserted_steps is str, not int"),
    (lambda s: s.update(inserted_steps=True), "inserted_steps is bool"),
    (lambda s: s.update(ledgers={"0": {}}), "ledger for actor '0'"),
    (lambda s: s["ledgers"][0].update(windows={5: [1, 3]}), "is not \\[low, \\[seq"),
])
def test_a_saved_replay_state_is_checked_field_by_field(damage, match):
    from tpdeb.services.config import ConfigError
    from tpdeb.services.replay import _check_saved

    _check_saved(_saved_state())
    state = _saved_state()
    damage(state)
    with pytest.raises(ConfigError, match=match):
        _check_saved(state)


def test_a_snapshot_of_another_version_ends_the_load_instead_of_being_passed_over(tmp_path):
    """Damage falls back to an older snapshot; another version's data does not (the older one is
    just as foreign, and the log no longer covers what the snapshot held)."""
    p = ReplayPersistence(tmp_path)
    p.snapshot({"n": 1}, ["x"], encode, wait=True)
    p.close()

    def refuse(payload: bytes):
        raise Incompatible(f"{payload!r} is of another version")

    with pytest.raises(Incompatible, match="another version"):
        ReplayPersistence(tmp_path).load(refuse)


def _of_version(payload: bytes, version: int) -> bytes:
    wire = msgpack.unpackb(payload, raw=False)
    wire["v"] = version
    return msgpack.packb(wire, use_bin_type=True)


@pytest.mark.parametrize("where", ["log", "snapshot"])
def test_a_run_dir_written_under_another_schema_version_is_refused_in_one_line(tmp_path, where):
    from tests.test_protocol import ACT_DIM, OBS_DIM, T, make_traj
    from tpdeb.protocol import SCHEMA_VERSION
    from tpdeb.protocol import encode as encode_message
    from tpdeb.services.config.service import ReplayServiceConfig
    from tpdeb.services.net.memory import MemoryBus
    from tpdeb.services.net.wire import run_spec
    from tpdeb.services.process import StopSignal
    from tpdeb.services.replay import ReplayServer

    old = _of_version(encode_message(make_traj()), SCHEMA_VERSION - 1)
    p = ReplayPersistence(tmp_path / "replay")
    if where == "log":
        p.log(old)
    else:  # nothing logged after it: passing it over would silently start afresh
        p.snapshot({"format": 2}, [old], lambda item: item, wait=True)
    p.close()
    config = ReplayServiceConfig(run_id="r", connect=("tcp/127.0.0.1:1",), env_id="Hopper-v5",
                                 fragment_len=T, batch_fragments=2, persist=True)
    spec = run_spec(config, OBS_DIM, ACT_DIM, -np.ones(ACT_DIM), np.ones(ACT_DIM))
    server = ReplayServer(config, spec, MemoryBus().session(), StopSignal())
    with pytest.raises(Incompatible) as err:
        server.enable_persistence(tmp_path / "replay")
    line = str(err.value)
    assert f"schema version {SCHEMA_VERSION - 1}" in line and "--restore never" in line
    assert "\n" not in line and server.persistence is None and len(server.replay) == 0
    server.close()


def test_a_refused_sync_leaves_no_torn_record_and_the_next_one_writes_what_it_held(
        tmp_path, monkeypatch):
    from tests.test_disk_full import refused_fsyncs

    p = ReplayPersistence(tmp_path)
    p.log(b"a")
    p.sync()
    full = refused_fsyncs(monkeypatch, full=True)
    p.log(b"b")
    p.log(b"c")
    with pytest.raises(OSError, match="No space"):
        p.sync()
    assert p.unwritten == 2
    segment = next(tmp_path.glob("wal-*.log"))
    _, records = ReplayPersistence(tmp_path).load(decode)
    assert [r.decode() for r in records] == ["a"]  # cut back to what was synced
    with pytest.raises(OSError):
        p.sync()  # still full: still held
    full[0] = False
    p.log(b"d")
    p.sync()
    assert p.unwritten == 0
    assert [r.decode() for r in read_records(segment, strict=True)] == ["a", "b", "c", "d"]


def test_a_write_the_disk_refuses_inside_log_is_held_for_the_next_sync(tmp_path, monkeypatch):
    import errno

    import tpdeb.services.store.persistence as persistence

    p = ReplayPersistence(tmp_path)
    p.log(b"a")
    p.sync()
    real, full = persistence.append_record, [True]

    def append_record(f, payload):
        if full[0]:  # the buffer was written out part-way, then the disk was full
            f.write(b"\x07" * 3)
            f.flush()
            raise OSError(errno.ENOSPC, "No space left on device")
        real(f, payload)

    monkeypatch.setattr(persistence, "append_record", append_record)
    p.log(b"b")  # nothing raised: the server goes on, the next sync says why
    p.log(b"c")
    assert p.unwritten == 2
    with pytest.raises(OSError, match="No space"):
        p.sync()
    full[0] = False
    p.sync()
    segment = next(tmp_path.glob("wal-*.log"))
    assert [r.decode() for r in read_records(segment, strict=True)] == ["a", "b", "c"]
