"""TPDEB's wire format: message types, the msgpack codec, validation and Zenoh key expressions.

Imports numpy, msgpack and zstandard, and of the core only its fragment schema
(tpdeb_core/schema.py); nothing here knows about torch, Zenoh sessions or files.
"""

from tpdeb.protocol.codec import (
    ERROR_KINDS,
    DecodeError,
    check_params_shapes,
    decode,
    encode,
    encoded_size_limit,
)
from tpdeb.protocol.keys import SCHEMA_VERSION, Keys
from tpdeb.protocol.messages import (
    MESSAGE_NAMES,
    MESSAGE_TYPES,
    Ack,
    Batch,
    Control,
    JoinReply,
    JoinRequest,
    Moments,
    Params,
    PriorityUpdate,
    RunSpec,
    SampleReply,
    SampleRequest,
    Stats,
    Trajectory,
)

__all__ = [
    "ERROR_KINDS", "MESSAGE_NAMES", "MESSAGE_TYPES", "SCHEMA_VERSION", "Ack", "Batch", "Control",
    "DecodeError", "JoinReply", "JoinRequest", "Keys", "Moments", "Params", "PriorityUpdate",
    "RunSpec", "SampleReply", "SampleRequest", "Stats", "Trajectory", "check_params_shapes",
    "decode", "encode", "encoded_size_limit",
]
