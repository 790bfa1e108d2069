"""A small TensorBoard event-file writer (scalars and text), so runs need no TensorFlow and no
tensorboard package at training time. Format: TFRecord framing of `tensorflow.Event` protos.
"""

from __future__ import annotations

import socket
import struct
import time
from pathlib import Path


def _crc32c_table() -> list[int]:
    table = []
    for n in range(256):
        c = n
        for _ in range(8):
            c = (c >> 1) ^ 0x82F63B78 if c & 1 else c >> 1
        table.append(c)
    return table


_TABLE = _crc32c_table()


def crc32c(data: bytes) -> int:
    crc = 0xFFFFFFFF
    for byte in data:
        crc = _TABLE[(crc ^ byte) & 0xFF] ^ (crc >> 8)
    return crc ^ 0xFFFFFFFF


def _masked_crc(data: bytes) -> int:
    crc = crc32c(data)
    return (((crc >> 15) | (crc << 17)) + 0xA282EAD8) & 0xFFFFFFFF


# --- protobuf wire encoding, just what Event needs ---------------------------------------------
def _varint(value: int) -> bytes:
    out = bytearray()
    value &= (1 << 64) - 1
    while True:
        bits = value & 0x7F
        value >>= 7
        if value:
            out.append(bits | 0x80)
        else:
            out.append(bits)
            return bytes(out)


def _bytes_field(number: int, payload: bytes) -> bytes:
    return _varint(number << 3 | 2) + _varint(len(payload)) + payload


def _event(step: int, **fields: bytes) -> bytes:
    body = b"\x09" + struct.pack("<d", time.time()) + b"\x10" + _varint(step)
    if "file_version" in fields:
        body += _bytes_field(3, fields["file_version"])
    if "summary" in fields:
        body += _bytes_field(5, fields["summary"])
    return body


def _scalar_value(tag: str, value: float) -> bytes:
    return _bytes_field(1, tag.encode()) + b"\x15" + struct.pack("<f", float(value))


def _text_value(tag: str, text: str) -> bytes:
    plugin = _bytes_field(1, _bytes_field(1, b"text"))  # SummaryMetadata.plugin_data.plugin_name
    tensor = b"\x08\x07" + _bytes_field(2, b"") + _bytes_field(8, text.encode())  # DT_STRING
    return _bytes_field(1, tag.encode()) + _bytes_field(9, plugin) + _bytes_field(8, tensor)


class EventWriter:
    """Appends records to `events.out.tfevents.{time}.{host}` in `log_dir`."""

    def __init__(self, log_dir: str | Path):
        log_dir = Path(log_dir)
        log_dir.mkdir(parents=True, exist_ok=True)
        name = f"events.out.tfevents.{int(time.time())}.{socket.gethostname()}"
        self.path = log_dir / name
        self._file = open(self.path, "ab")  # noqa: SIM115 - lives as long as the writer
        self._write(_event(0, file_version=b"brain.Event:2"))

    def _write(self, record: bytes) -> None:
        header = struct.pack("<Q", len(record))
        self._file.write(header + struct.pack("<I", _masked_crc(header)) + record
                         + struct.pack("<I", _masked_crc(record)))

    def add_scalars(self, values: dict[str, float], step: int) -> None:
        summary = b"".join(_bytes_field(1, _scalar_value(k, v)) for k, v in values.items())
        self._write(_event(step, summary=summary))

    def add_text(self, tag: str, text: str, step: int = 0) -> None:
        self._write(_event(step, summary=_bytes_field(1, _text_value(tag, text))))

    def flush(self) -> None:
        self._file.flush()

    def close(self) -> None:
        if not self._file.closed:
            self._file.close()
