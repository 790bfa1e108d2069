"""msgpack codec (DESIGN §3): a versioned envelope, arrays as raw bytes, decode that checks all.

On the wire every message is {"v": SCHEMA_VERSION, "type": its MESSAGE_TYPES name, "body":
{field: value}}; an array is {"__nd__": True, "dtype": "<f4", "shape": [...], "data": bytes}.
Decoding builds arrays with np.frombuffer over the bytes msgpack unpacked (no further copy,
read-only) and either returns a fully valid message or raises DecodeError: never half a message,
never another error.
"""

from __future__ import annotations

import msgpack
import numpy as np
import zstandard

from tpdeb.protocol.keys import SCHEMA_VERSION
from tpdeb.protocol.messages import MESSAGE_NAMES, MESSAGE_TYPES, Params, RunSpec
from tpdeb.protocol.schema import (
    ERROR_KINDS,
    WIRE_DTYPES,
    DecodeError,
    field_rules,
    load_message,
    short,
)

__all__ = ["ERROR_KINDS", "DecodeError", "check_params_shapes", "decode", "encode",
           "encoded_size_limit"]

encoded_size_limit = 64 * 2**20  # default largest payload decode accepts, in bytes


def _array_to_wire(arr: np.ndarray, where: str) -> dict:
    if arr.dtype.byteorder == ">":
        arr = arr.astype(arr.dtype.newbyteorder("<"))
    if arr.dtype.str not in WIRE_DTYPES:
        raise ValueError(f"{where}: dtype {arr.dtype} cannot travel; use one of "
                         f"{sorted(WIRE_DTYPES)}")
    # tobytes() lays out C order whatever the strides (ascontiguousarray would turn () into (1,))
    return {"__nd__": True, "dtype": arr.dtype.str, "shape": list(arr.shape),
            "data": arr.tobytes(order="C")}


def _to_wire(value, where: str):
    if isinstance(value, np.ndarray):
        return _array_to_wire(value, where)
    if type(value) in MESSAGE_NAMES:
        return _body(value, where)
    if isinstance(value, dict):
        return {k: _to_wire(v, f"{where}[{k!r}]") for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_to_wire(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, np.generic):  # numpy scalars (np.float32 stats, np.int64 ids)
        return value.item()
    return value


def _body(msg, where: str) -> dict:
    return {name: _to_wire(getattr(msg, name), f"{where}.{name}")
            for name, _ in field_rules(type(msg))}


COMPRESSIONS = ("none", "zstd")
# zstd level 3: on HalfCheetah fragments it saves as much as level 9 (ratio 1.27) at a quarter
# of the time (~25 µs per fragment); lz4 was faster but saved less (1.21).
_ZSTD_LEVEL = 3


def encode(msg, compression: str = "none") -> bytes:
    """The wire bytes of a message. Values are not validated here; the receiver's decode is.
    With compression "zstd" the body travels compressed (envelope key `zbody`)."""
    name = MESSAGE_NAMES.get(type(msg))
    if name is None:
        raise TypeError(f"cannot encode {type(msg).__name__}: not one of {sorted(MESSAGE_TYPES)}")
    if compression not in COMPRESSIONS:
        raise ValueError(f"compression={compression!r}: use one of {COMPRESSIONS}")
    body = _body(msg, name)
    if compression == "zstd":
        packed = msgpack.packb(body, use_bin_type=True)
        envelope = {"v": SCHEMA_VERSION, "type": name,
                    "zbody": zstandard.ZstdCompressor(level=_ZSTD_LEVEL).compress(packed)}
    else:
        envelope = {"v": SCHEMA_VERSION, "type": name, "body": body}
    return msgpack.packb(envelope, use_bin_type=True)


def _unpack(data, size: int, what: str):
    try:
        # Limits scaled to the payload: a few bytes cannot claim a huge str, list or map.
        return msgpack.unpackb(data, raw=False, strict_map_key=True, max_bin_len=size,
                               max_str_len=size, max_array_len=size, max_map_len=size // 2,
                               max_ext_len=0)
    except Exception as e:  # msgpack raises several types (ValueError, ExtraData, StackError…)
        raise DecodeError("msgpack", f"{what}{type(e).__name__}: {short(str(e), 120)}") from None


def _decompress(blob, max_bytes: int):
    if type(blob) is not bytes:
        raise DecodeError("field", f"zbody is {type(blob).__name__}, expected bytes")
    try:
        reader = zstandard.ZstdDecompressor().stream_reader(blob)
        out = reader.read(max_bytes + 1)  # never inflate past the size limit
    except zstandard.ZstdError as e:
        raise DecodeError("msgpack", f"zbody does not decompress: {short(str(e), 120)}") from None
    if len(out) > max_bytes:
        raise DecodeError("size", f"zbody inflates past {max_bytes} bytes")
    return _unpack(out, len(out), "zbody: ")


def decode(data: bytes, expected: type | tuple[type, ...], spec: RunSpec | None = None,
           max_bytes: int = encoded_size_limit):
    """The message in `data`, of one of the `expected` types, checked against `spec` (its T,
    obs_dim and act_dim) when given. Raises DecodeError on any problem."""
    if not isinstance(data, bytes | bytearray | memoryview):
        raise DecodeError("msgpack", f"expected bytes, got {type(data).__name__}")
    size = data.nbytes if isinstance(data, memoryview) else len(data)
    if size > max_bytes:
        raise DecodeError("size", f"{size} bytes, at most {max_bytes}")
    top = _unpack(data, size, "")
    if type(top) is not dict:
        raise DecodeError("msgpack", f"top level is {type(top).__name__}, expected a map")
    version = top.get("v")
    if type(version) is not int or version != SCHEMA_VERSION:
        raise DecodeError("version", f"message schema version {short(version)}, this peer "
                                     f"speaks {SCHEMA_VERSION}")
    expected = expected if isinstance(expected, tuple) else (expected,)
    name = top.get("type")
    cls = MESSAGE_TYPES.get(name) if type(name) is str else None
    if cls is None or cls not in expected:
        wanted = [MESSAGE_NAMES.get(c, c.__name__) for c in expected]
        raise DecodeError("type", f"got {short(name)}, expected {' or '.join(wanted)}")
    if top.keys() not in ({"v", "type", "body"}, {"v", "type", "zbody"}):
        raise DecodeError("field", f"envelope keys {sorted(map(short, top))}, expected "
                                   "v, type and body (or zbody)")
    body = top["body"] if "body" in top else _decompress(top["zbody"], max_bytes)
    try:
        return load_message(cls, body, spec, name)
    except DecodeError:
        raise
    except Exception as e:  # a rule that trips over hostile input must still not crash a service
        raise DecodeError("field", f"{name}: internal error on hostile input, "
                                   f"{type(e).__name__}: {short(str(e), 120)}") from e


def check_params_shapes(msg: Params, expected: dict[str, tuple[int, ...]]) -> None:
    """Refuse parameters that do not fit the local model (names or shapes differ)."""
    missing = sorted(expected.keys() - msg.arrays.keys())
    extra = sorted(msg.arrays.keys() - expected.keys())
    if missing or extra:
        raise DecodeError("shape", f"Params.arrays: missing {missing[:5]}, unexpected "
                                   f"{extra[:5]}")
    wrong = [f"{k} {msg.arrays[k].shape} != {tuple(s)}" for k, s in expected.items()
             if msg.arrays[k].shape != tuple(s)]
    if wrong:
        raise DecodeError("shape", f"Params.arrays: {'; '.join(wrong[:5])}")
