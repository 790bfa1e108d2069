"""The replay server's durability: a write-ahead log of ingested fragments plus periodic snapshots.

Every ingested fragment's wire bytes are appended to the log and the log is fsynced before the
fragment is acknowledged, so an acknowledged fragment survives a `kill -9`. A snapshot holds the
whole replay state (both buffers, priorities, the rate limiter, the de-duplication ledgers); the
log is rotated at the moment the state is captured, so restore = newest complete snapshot +
every log segment from that point on. Old segments and snapshots are deleted once a newer
snapshot is complete.

A snapshot's state is msgpack (`encode_state`): plain values, lists, maps and numpy arrays of
numeric dtypes, nothing that names a type to build, so a run dir handed over by someone else
cannot run code when it is restored; the replay server checks the decoded state's fields before
it uses them, as it checks a message from the wire.

A snapshot is written into a temporary directory and becomes valid only when its `COMPLETE`
marker (sizes and CRCs of its files) is in place and the directory renamed; anything else is
ignored and cleaned up. Capturing the state is a shallow copy on the server's loop thread; the
expensive part (encoding every item, writing, fsync) runs on a background thread, so inserts and
samples go on while it is written.

Record format (log segments and a snapshot's items file alike): u32 length, u32 CRC-32, bytes.
A torn record at the end of the last segment (a crash mid-write) ends the log there. The records
are the fragments' wire bytes, so each names its schema version; one of another version makes
the item decoder raise `Incompatible`, which ends the restore (one line, no fallback).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import struct
import threading
import time
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path

import msgpack
import numpy as np

from tpdeb.services.store.diskio import fsync_dir

_HEADER = struct.Struct("<II")
_SEGMENT = "wal-{:08d}.log"
_SNAPSHOT = "snapshot-{:08d}"
MARKER = "COMPLETE"
STATE_FILE = "state.msgpack"
_EXT_ARRAY, _EXT_BIG_INT = 1, 2
# The dtypes a state may hold: numbers and booleans, never objects.
_DTYPES = frozenset(np.dtype(t).str for t in (
    np.bool_, np.int8, np.int16, np.int32, np.int64, np.uint8, np.uint16, np.uint32, np.uint64,
    np.float16, np.float32, np.float64))


class CorruptRecord(Exception):
    pass


class Incompatible(Exception):
    """Whole stored data that this version does not read (another schema version): refused at
    load, never passed over for an older snapshot, which would be just as foreign."""


def _pack_value(value):
    if isinstance(value, np.ndarray):
        array = np.ascontiguousarray(value)
        if array.dtype.str not in _DTYPES:
            raise TypeError(f"a state array of dtype {array.dtype} cannot be stored")
        return msgpack.ExtType(_EXT_ARRAY, msgpack.packb(
            [array.dtype.str, list(array.shape), array.tobytes()]))
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, int):  # beyond 64 bits (a PCG64 generator's state)
        return msgpack.ExtType(_EXT_BIG_INT, str(value).encode())
    if isinstance(value, (set, frozenset)):
        return sorted(value)
    raise TypeError(f"a state value of type {type(value).__name__} cannot be stored")


def _unpack_ext(code: int, data: bytes):
    if code == _EXT_BIG_INT:
        text = data.decode("ascii")
        if not text.lstrip("-").isdigit():
            raise CorruptRecord(f"a big integer reads {text[:40]!r}")
        return int(text)
    if code != _EXT_ARRAY:
        raise CorruptRecord(f"unknown value type {code} in a state file")
    try:
        dtype, shape, raw = msgpack.unpackb(data)
        if dtype not in _DTYPES:
            raise CorruptRecord(f"an array of dtype {dtype!r}: only numbers are stored")
        if not all(isinstance(n, int) and n >= 0 for n in shape):
            raise CorruptRecord(f"an array of shape {shape!r}")
        return np.frombuffer(raw, dtype=np.dtype(dtype)).reshape(shape).copy()
    except (ValueError, TypeError) as exc:
        raise CorruptRecord(f"a malformed array in a state file ({exc})") from None


def encode_state(state) -> bytes:
    """Msgpack of a state tree: None, bools, ints (any size), floats, strings, bytes, lists and
    tuples (read back as lists), sets (as sorted lists), maps with string or integer keys, and
    numpy arrays of numeric dtypes. Anything else is refused."""
    return msgpack.packb(state, default=_pack_value, use_bin_type=True, strict_types=False)


def decode_state(data: bytes):
    """The tree `encode_state` wrote; builds only the types listed there."""
    try:
        return msgpack.unpackb(data, ext_hook=_unpack_ext, raw=False, strict_map_key=False)
    except (msgpack.UnpackException, ValueError, TypeError) as exc:
        raise CorruptRecord(f"the state file is not a state ({exc})") from None


def append_record(f, payload: bytes) -> None:
    f.write(_HEADER.pack(len(payload), zlib.crc32(payload)))
    f.write(payload)


def read_records(path: Path, strict: bool,
                 torn: Callable[[Path, int], None] | None = None) -> Iterator[bytes]:
    """Records of one file in order. A torn or corrupt record ends a log (`strict=False`: a crash
    can only tear the tail; `torn(path, offset)` hears where); in a snapshot file, which was
    complete, it is an error."""
    with path.open("rb") as f:
        while True:
            start = f.tell()
            header = f.read(_HEADER.size)
            if not header:
                return
            if len(header) < _HEADER.size:
                if strict:
                    raise CorruptRecord(f"{path}: truncated record header")
                if torn is not None:
                    torn(path, start)
                return
            length, crc = _HEADER.unpack(header)
            payload = f.read(length)
            if len(payload) < length or zlib.crc32(payload) != crc:
                if strict:
                    raise CorruptRecord(f"{path}: corrupt record")
                if torn is not None:
                    torn(path, start)
                return
            yield payload


def _file_crc(path: Path) -> int:
    crc = 0
    with path.open("rb") as f:
        while chunk := f.read(1 << 20):
            crc = zlib.crc32(chunk, crc)
    return crc


class ReplayPersistence:
    """Write-ahead log + snapshots in one directory (see the module docstring)."""

    def __init__(self, directory: str | Path, keep_snapshots: int = 2):
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.keep_snapshots = keep_snapshots
        self._wal = None
        self._segment = -1
        self._dirty = False
        self._writer: threading.Thread | None = None
        self.error: BaseException | None = None
        self.skipped = ""  # why the newest snapshot was passed over at load, if it was
        self.torn = ""  # where the log ended in a torn record at load, if it did
        self.last_snapshot_s = 0.0  # how long the last background write took
        self.last_capture_ms = 0.0  # how long the loop spent capturing the state
        self.snapshots_written = 0
        self.logged_records = 0
        self.sync_s_total = 0.0
        self.syncs = 0
        # A refused write or fsync (a full disk) must not leave a torn record in the middle of
        # the log: the segment is cut back to its last synced size, and the records logged since
        # are written again by the next sync.
        self._synced_size = 0
        self._since_sync: list[bytes] = []
        self._unwritten: list[bytes] = []

    # -- restore
    def complete_snapshots(self) -> list[Path]:
        """Complete snapshot directories, oldest first; leftovers of interrupted writes go."""
        found = []
        for path in sorted(self.dir.glob("snapshot-*")):
            if path.is_dir() and (path / MARKER).is_file():
                found.append(path)
        for path in self.dir.glob(".snapshot-*"):
            shutil.rmtree(path, ignore_errors=True)
        return found

    def load(self, decode_item: Callable[[bytes], object]) -> tuple[dict | None, Iterator[bytes]]:
        """(the newest complete snapshot's state or None, the log records written after it).
        A snapshot whose files fail their marker's sizes/CRCs is skipped for the one before;
        `decode_item` raising Incompatible ends the load."""
        state, first_segment = None, 0
        for path in reversed(self.complete_snapshots()):
            try:
                state, first_segment = self._read_snapshot(path, decode_item)
                break
            except Incompatible:
                raise
            except Exception as exc:  # noqa: BLE001 - any unreadable snapshot: use the one before
                self.skipped = f"{path.name}: {exc}"
        segments = [p for p in self._segments() if self._index(p) >= first_segment]
        self._segment = max([self._index(p) for p in self._segments()] + [first_segment - 1])

        def torn(path: Path, offset: int) -> None:
            self.torn = f"{path.name} at byte {offset:,} of {path.stat().st_size:,}"

        def records() -> Iterator[bytes]:
            for path in segments:
                yield from read_records(path, strict=False, torn=torn)

        return state, records()

    def _read_snapshot(self, path: Path, decode_item) -> tuple[dict, int]:
        marker = json.loads((path / MARKER).read_text())
        for name, expect in marker["files"].items():
            file = path / name
            if file.stat().st_size != expect["bytes"] or _file_crc(file) != expect["crc32"]:
                raise CorruptRecord(f"{name} does not match its marker")
        state = decode_state((path / STATE_FILE).read_bytes())
        if not isinstance(state, dict):
            raise CorruptRecord(f"{STATE_FILE} holds a {type(state).__name__}, not a map")
        items = [decode_item(r) for r in read_records(path / "items.bin", strict=True)]
        state["items"] = items
        return state, int(marker["wal_segment"])

    # -- the log
    def _segments(self) -> list[Path]:
        return sorted(self.dir.glob("wal-*.log"))

    @staticmethod
    def _index(path: Path) -> int:
        return int(path.stem.split("-")[1])

    def _open_segment(self) -> None:
        if self._wal is not None:
            self.sync()
            self._wal.close()
        self._segment += 1
        self._wal = (self.dir / _SEGMENT.format(self._segment)).open("ab")
        self._synced_size = 0
        fsync_dir(self.dir)

    def log(self, payload: bytes) -> None:
        if self._wal is None:
            self._open_segment()
        self.logged_records += 1
        if self._unwritten:  # behind what a refused write holds: the order is kept
            self._unwritten.append(payload)
            return
        self._since_sync.append(payload)
        try:
            append_record(self._wal, payload)  # a full buffer is written out here
        except OSError:
            self._cut_back()  # held with the rest since the last sync; the next sync says why
            return
        self._dirty = True

    @property
    def unwritten(self) -> int:
        """Records a refused sync left out of the log (the next sync writes them)."""
        return len(self._unwritten)

    def sync(self) -> None:
        """Make every logged record durable (one fsync for all of them). If the disk refuses
        (here, or in a write of `log`), the segment is cut back to what was synced before and
        OSError raised; the records logged since are kept and written again by the next call."""
        started = time.perf_counter()
        try:
            if self._unwritten:
                self._since_sync, self._unwritten = self._unwritten, []
                self._dirty = True
                for payload in self._since_sync:
                    append_record(self._wal, payload)
            if not self._dirty:
                return
            self._wal.flush()
            os.fsync(self._wal.fileno())
        except OSError:
            self._cut_back()
            raise
        self._dirty = False
        self._synced_size = self._wal.tell()
        self._since_sync = []
        self.sync_s_total += time.perf_counter() - started
        self.syncs += 1

    def _cut_back(self) -> None:
        path = Path(self._wal.name)
        with contextlib.suppress(OSError):
            self._wal.close()  # what its buffer still holds is dropped with it
        with contextlib.suppress(OSError):
            os.truncate(path, self._synced_size)
        self._wal = path.open("ab")
        self._unwritten, self._since_sync = self._since_sync, []
        self._dirty = False

    # -- snapshots
    @property
    def writing(self) -> bool:
        return self._writer is not None and self._writer.is_alive()

    def snapshot(self, state: dict, items: list, encode_item: Callable[[object], bytes],
                 wait: bool = False) -> bool:
        """Start writing `state` (items referenced by index into `items`) in the background; the
        log rotates now, so the snapshot covers exactly what was logged before this call.
        Returns False when a previous snapshot is still being written (nothing is started)."""
        if self.writing:
            if not wait:
                return False
            self._writer.join()
        self._open_segment()
        index = self._segment  # the first segment this snapshot does not cover
        self._writer = threading.Thread(
            target=self._write, args=(index, state, items, encode_item), daemon=True,
            name="snapshot")
        self._writer.start()
        if wait:
            self._writer.join()
        return True

    def _write(self, index: int, state: dict, items: list, encode_item) -> None:
        started = time.perf_counter()
        tmp = self.dir / f".{_SNAPSHOT.format(index)}.tmp"
        final = self.dir / _SNAPSHOT.format(index)
        try:
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir()
            files = {}
            with (tmp / "items.bin").open("wb") as f:
                for item in items:
                    append_record(f, encode_item(item))
                f.flush()
                os.fsync(f.fileno())
            with (tmp / STATE_FILE).open("wb") as f:
                f.write(encode_state(state))
                f.flush()
                os.fsync(f.fileno())
            for name in ("items.bin", STATE_FILE):
                files[name] = {"bytes": (tmp / name).stat().st_size,
                               "crc32": _file_crc(tmp / name)}
            marker = {"wal_segment": index, "items": len(items), "files": files,
                      "written_unix_s": time.time()}
            (tmp / MARKER).write_text(json.dumps(marker, indent=1))
            with (tmp / MARKER).open("rb") as f:
                os.fsync(f.fileno())
            os.replace(tmp, final)
            fsync_dir(self.dir)
            self._prune()
            self.snapshots_written += 1
            self.last_snapshot_s = time.perf_counter() - started
        except BaseException as exc:  # reported by the server; the log still holds everything
            self.error = exc
            shutil.rmtree(tmp, ignore_errors=True)

    def _prune(self) -> None:
        """Drop snapshots beyond `keep_snapshots` and log segments every kept snapshot covers."""
        snapshots = self.complete_snapshots()
        for path in snapshots[:-self.keep_snapshots]:
            shutil.rmtree(path, ignore_errors=True)
        kept = snapshots[-self.keep_snapshots:]
        if len(kept) < self.keep_snapshots:
            return  # until there are spares, the log is the fallback for a damaged snapshot
        oldest_needed = min(self._index(p) for p in kept)
        for path in self._segments():
            if self._index(path) < oldest_needed:
                path.unlink(missing_ok=True)

    def close(self) -> None:
        if self._writer is not None:
            self._writer.join()
        if self._wal is not None:
            self.sync()
            self._wal.close()
            self._wal = None
