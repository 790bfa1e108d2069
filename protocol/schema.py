"""Field rules: what each message field may hold on the wire, and the walk that checks them.

messages.py declares one rule per field (or, for a class the core declares, derives them from
its declaration: `adopt`); `load_message` runs a decoded msgpack body through them and builds the
message only when every rule and the class's cross check pass. Every problem is a DecodeError of
one of ERROR_KINDS, so a service can count bad messages by kind and drop them without catching
anything else.
"""

from __future__ import annotations

import functools
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field, fields

import numpy as np

ERROR_KINDS = ("size", "msgpack", "version", "type", "field", "dtype", "shape", "nonfinite",
               "value")

# Explicitly little-endian (or byte-order-free) dtypes: what may travel, whatever the host.
WIRE_DTYPES = {s: np.dtype(s) for s in ("<f2", "<f4", "<f8", "<i4", "<i8", "|b1", "|u1")}
ND_KEYS = frozenset({"__nd__", "dtype", "shape", "data"})
MAX_NDIM = 8
INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1


class DecodeError(ValueError):
    """A message to drop: `kind` is one of ERROR_KINDS, `detail` says what and where."""

    def __init__(self, kind: str, detail: str):
        super().__init__(f"{kind}: {detail}")
        self.kind = kind
        self.detail = detail

    def __reduce__(self):  # stays picklable despite the two-argument constructor
        return type(self), (self.kind, self.detail)


def short(value, limit: int = 60) -> str:
    """repr of a peer-controlled value, cut so a hostile message cannot flood the logs."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + "…"


class Scope:
    """Sizes of named dimensions (T, obs_dim, K, B, …) within one message and where each came
    from, so that an inconsistent shape names both sides."""

    def __init__(self, spec=None):
        self.spec = spec
        self.dims: dict[str, tuple[int, str]] = {}
        if spec is not None:
            for name, size in (("T", spec.fragment_len), ("obs_dim", spec.obs_dim),
                               ("act_dim", spec.act_dim)):
                self.dims[name] = (size, "the run spec")

    def bind(self, name: str, size: int, where: str) -> None:
        known = self.dims.setdefault(name, (size, where))
        if known[0] != size:
            raise DecodeError("shape", f"{where}: {name}={size}, but {name}={known[0]} from "
                                       f"{known[1]}")

    def get(self, name: str) -> int | None:
        return self.dims.get(name, (None, ""))[0]


def _fail_type(where: str, expected: str, raw) -> DecodeError:
    return DecodeError("field", f"{where}: expected {expected}, got {type(raw).__name__}")


@dataclass(frozen=True)
class Int:
    """An int (never a bool) in [ge, le]; `dim` makes it the size of a named dimension."""

    ge: int = 0
    le: int = INT64_MAX
    dim: str | None = None

    def load(self, raw, where: str, scope: Scope) -> int:
        if type(raw) is not int:  # msgpack yields exact ints; bool is refused on purpose
            raise _fail_type(where, "an int", raw)
        if not self.ge <= raw <= self.le:
            raise DecodeError("value", f"{where}={raw} is outside [{self.ge}, {self.le}]")
        if self.dim:
            scope.bind(self.dim, raw, where)
        return raw


@dataclass(frozen=True)
class Float:
    """A finite number (an int is accepted and becomes a float) within optional bounds."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None

    def load(self, raw, where: str, scope: Scope) -> float:
        if type(raw) not in (int, float):
            raise _fail_type(where, "a number", raw)
        value = float(raw)
        if not math.isfinite(value):
            raise DecodeError("nonfinite", f"{where}={value}")
        if ((self.ge is not None and value < self.ge) or (self.gt is not None and value <= self.gt)
                or (self.le is not None and value > self.le)):
            bounds = [f"{op} {b}" for op, b in ((">=", self.ge), (">", self.gt), ("<=", self.le))
                      if b is not None]
            raise DecodeError("value", f"{where}={value} must be {' and '.join(bounds)}")
        return value


@dataclass(frozen=True)
class Str:
    """A str of bounded length, optionally one of `choices` or matching `pattern`."""

    max_len: int = 256
    min_len: int = 0
    choices: tuple[str, ...] | None = None
    pattern: str | None = None

    def load(self, raw, where: str, scope: Scope) -> str:
        if type(raw) is not str:
            raise _fail_type(where, "a str", raw)
        if not self.min_len <= len(raw) <= self.max_len:
            raise DecodeError("value", f"{where}: length {len(raw)} is outside "
                                       f"[{self.min_len}, {self.max_len}]")
        if self.choices is not None and raw not in self.choices:
            raise DecodeError("value", f"{where}={short(raw)} is not one of {self.choices}")
        if self.pattern is not None and not re.fullmatch(self.pattern, raw):
            raise DecodeError("value", f"{where}={short(raw)} does not match {self.pattern}")
        return raw


@dataclass(frozen=True)
class Bool:
    def load(self, raw, where: str, scope: Scope) -> bool:
        if type(raw) is not bool:
            raise _fail_type(where, "a bool", raw)
        return raw


@dataclass(frozen=True)
class Scalar:
    """An int, float or str (free-form stats values)."""

    def load(self, raw, where: str, scope: Scope):
        rule = {int: Int(ge=INT64_MIN), float: Float(), str: Str()}.get(type(raw))
        if rule is None:
            raise _fail_type(where, "an int, float or str", raw)
        return rule.load(raw, where, scope)


@dataclass(frozen=True)
class ListOf:
    """A list of items under one rule; `dim` makes its length a named dimension."""

    item: object
    max_len: int | None = None
    dim: str | None = None

    def load(self, raw, where: str, scope: Scope) -> list:
        if type(raw) is not list:
            raise _fail_type(where, "a list", raw)
        if self.max_len is not None and len(raw) > self.max_len:
            raise DecodeError("value", f"{where}: {len(raw)} items, at most {self.max_len}")
        if self.dim:
            scope.bind(self.dim, len(raw), f"{where} (length)")
        return [self.item.load(x, f"{where}[{i}]", scope) for i, x in enumerate(raw)]


@dataclass(frozen=True)
class DictOf:
    """A map with str keys under `key` and values under `value`."""

    key: Str
    value: object

    def load(self, raw, where: str, scope: Scope) -> dict:
        if type(raw) is not dict:
            raise _fail_type(where, "a map", raw)
        out = {}
        for k, v in raw.items():
            name = self.key.load(k, f"{where} key", scope)
            out[name] = self.value.load(v, f"{where}[{name!r}]", scope)
        return out


@dataclass(frozen=True)
class OrNone:
    inner: object

    def load(self, raw, where: str, scope: Scope):
        return None if raw is None else self.inner.load(raw, where, scope)


@dataclass(frozen=True)
class Nested:
    """Another message's body; it sizes its own dimensions (from the same run spec)."""

    cls: type

    def load(self, raw, where: str, scope: Scope):
        return load_message(self.cls, raw, scope.spec, where)


def _parse_shape(text: str):
    """'T+1 obs_dim' → (('T', 1), ('obs_dim', 0)); '*' → None, any shape."""
    if text.strip() == "*":
        return None
    return tuple((name, int(offset or 0)) for name, _, offset in
                 (token.partition("+") for token in text.split()))


@dataclass
class Array:
    """An n-d array. `dtypes` lists allowed dtypes separated by spaces, `shapes` alternative
    shapes separated by '|', e.g. Array("<f4 <f8", "n | n T"); dimension names bind within the
    message (and to the run spec)."""

    dtypes: str
    shapes: str
    ge: float | None = None  # lower bound on every element
    _allowed: tuple[str, ...] = field(init=False, repr=False)
    _patterns: tuple = field(init=False, repr=False)

    def __post_init__(self):
        self._allowed = tuple(self.dtypes.split())
        self._patterns = tuple(_parse_shape(s) for s in self.shapes.split("|"))

    def load(self, raw, where: str, scope: Scope) -> np.ndarray:
        arr = array_from_wire(raw, where)
        if arr.dtype.str not in self._allowed:
            raise DecodeError("dtype", f"{where}: {arr.dtype.str}, expected "
                                       f"{' or '.join(self._allowed)}")
        self._bind_shape(arr.shape, where, scope)
        if arr.dtype.kind == "b" and (arr.view(np.uint8) > 1).any():
            raise DecodeError("value", f"{where}: bool bytes must be 0 or 1")
        if arr.dtype.kind == "f" and not np.isfinite(arr).all():
            raise DecodeError("nonfinite", f"{where}: {int((~np.isfinite(arr)).sum())} NaN/inf")
        if self.ge is not None and arr.size and arr.min() < self.ge:
            raise DecodeError("value", f"{where}: minimum {arr.min()} is below {self.ge}")
        return arr

    def _bind_shape(self, shape: tuple[int, ...], where: str, scope: Scope) -> None:
        fitting = [p for p in self._patterns if p is None or len(p) == len(shape)]
        if not fitting:
            raise DecodeError("shape", f"{where}: shape {shape}, expected {self.shapes}")
        if fitting[0] is None:
            return
        for (name, offset), size in zip(fitting[0], shape, strict=True):
            if size < offset:
                raise DecodeError("shape", f"{where}: shape {shape}, expected {self.shapes}")
            scope.bind(name, size - offset, f"{where} of shape {shape}")


def array_from_wire(raw, where: str) -> np.ndarray:
    """{__nd__, dtype, shape, data} → a read-only array viewing `data` (np.frombuffer, no copy)."""
    if type(raw) is not dict or raw.keys() != ND_KEYS or raw["__nd__"] is not True:
        raise DecodeError("field", f"{where}: expected an array map with keys {sorted(ND_KEYS)}")
    dtype = WIRE_DTYPES.get(raw["dtype"]) if type(raw["dtype"]) is str else None
    if dtype is None:
        raise DecodeError("dtype", f"{where}: dtype {short(raw['dtype'])} is not one of "
                                   f"{sorted(WIRE_DTYPES)}")
    shape = raw["shape"]
    if (type(shape) is not list or len(shape) > MAX_NDIM
            or any(type(d) is not int or d < 0 for d in shape)):
        raise DecodeError("shape", f"{where}: shape {short(shape)} is not a list of at most "
                                   f"{MAX_NDIM} sizes >= 0")
    data = raw["data"]
    if type(data) is not bytes:
        raise _fail_type(where + ".data", "bytes", data)
    needed = math.prod(shape) * dtype.itemsize
    if needed != len(data):
        raise DecodeError("shape", f"{where}: shape {tuple(shape)} of {dtype.str} needs {needed} "
                                   f"bytes, the data has {len(data)}")
    return np.frombuffer(data, dtype=dtype).reshape(shape)


# Classes declared outside this package (the core's Fragment, FragmentBatch) that travel as
# messages: their rules and cross checks, given by `adopt`.
_ADOPTED: dict[type, tuple[tuple[tuple[str, object], ...], Callable | None]] = {}


def adopt(cls: type, rules: dict[str, object], cross_check: Callable | None = None) -> type:
    """Make `cls`, a dataclass declared elsewhere, a message: `rules` holds one rule for each of
    its fields (a missing or unknown name raises at import), `cross_check(message, scope,
    where)` the rules spanning several fields."""
    names = [f.name for f in fields(cls)]
    if sorted(rules) != sorted(names):
        raise TypeError(f"{cls.__name__}: rules for {sorted(rules)}, fields {sorted(names)}")
    _ADOPTED[cls] = (tuple((name, rules[name]) for name in names), cross_check)
    return cls


@functools.cache
def field_rules(cls: type) -> tuple[tuple[str, object], ...]:
    """(name, rule) of every field of a message class, in declaration order (looked up once:
    `dataclasses.fields` per message costs more than most rules)."""
    if cls in _ADOPTED:
        return _ADOPTED[cls][0]
    return tuple((f.name, f.metadata["rule"]) for f in fields(cls))


def cross_check_of(cls: type) -> Callable | None:
    """The rules of `cls` spanning several fields, called as check(message, scope, where)."""
    return _ADOPTED[cls][1] if cls in _ADOPTED else getattr(cls, "cross_check", None)


def load_message(cls: type, body, spec, where: str | None = None):
    """Build `cls` from a decoded body, checking every field's rule, then `cls.cross_check`."""
    where = where or cls.__name__
    if type(body) is not dict:
        raise _fail_type(where, "a map body", body)
    rules = field_rules(cls)
    names = [name for name, _ in rules]
    missing = [n for n in names if n not in body]
    extra = [short(k, 40) for k in body if k not in names]
    if missing or extra:
        problems = ([f"missing {', '.join(missing)}"] if missing else []) + (
            [f"unknown {', '.join(extra[:5])}"] if extra else [])
        raise DecodeError("field", f"{where}: {'; '.join(problems)}")
    scope = Scope(spec)
    values = {name: rule.load(body[name], f"{where}.{name}", scope) for name, rule in rules}
    message = cls(**values)
    check = cross_check_of(cls)
    if check is not None:
        check(message, scope, where)
    return message
