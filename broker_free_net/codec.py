"""msgpack wire format with declarative validation.

A message is a msgpack map with str keys and a version field ``"v": 1``.
float64 arrays are encoded as a nested map::

    {"dtype": "<f8", "shape": [n, ...], "data": <bin: little-endian raw bytes>}

and decoded with a zero-copy, read-only ``np.frombuffer`` view. No pickle,
no msgpack ext types. Before any object is built, the payload's size is
checked against :data:`MAX_PAYLOAD_BYTES` and its msgpack headers are walked
(no object built) to refuse nesting deeper than :data:`MAX_DEPTH` or more
than :data:`MAX_OBJECTS` values, so a hostile payload costs at most a bounded
amount of memory and time. Every failure raises :class:`MalformedMessage`
with a short reason code and a message of at most :data:`MAX_ERROR_CHARS`
characters.

Example
-------
>>> schema = Schema({"step": Int(0, 10**9), "sender": Ident(), "x": F64Array((3,))},
...                 stamp="step", sender="sender")
>>> payload = encode({"step": 4, "sender": 1, "x": np.zeros(3)})
>>> msg = decode(payload, schema, now_step=5, window=10, senders={0, 1, 2})
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field

import msgpack
import numpy as np

__all__ = [
    "MAX_DEPTH",
    "MAX_ERROR_CHARS",
    "MAX_OBJECTS",
    "MAX_PAYLOAD_BYTES",
    "REASONS",
    "VERSION",
    "Bool",
    "F64Array",
    "Float",
    "Ident",
    "Int",
    "MalformedMessage",
    "MessageStats",
    "Schema",
    "Str",
    "check_context",
    "decode",
    "encode",
    "scan",
    "shorten",
    "try_decode",
]

VERSION = 1
#: Payloads larger than this are rejected before unpacking (reason "too_large").
MAX_PAYLOAD_BYTES = 1 << 20
#: Containers (maps, arrays) nested deeper than this are rejected before unpacking ("too_deep").
#: The deepest socmon message (a status: top map -> links -> link parameters) has depth 3.
MAX_DEPTH = 16
#: Payloads holding more msgpack values than this (every key, value and container counts)
#: are rejected before unpacking ("too_many"): it bounds the Python objects one message can
#: build (~1 MB) whatever its bytes. A 14-node estimate holds 19 values.
MAX_OBJECTS = 1 << 14
#: Error messages (and so logs and statuses that quote them) are cut to this many characters.
MAX_ERROR_CHARS = 200
#: A payload of a flat schema up to this size is unpacked without the header walk first:
#: it builds at most this many objects, and what passes the schema nests at most
#: MAX_DEPTH deep (scalars and arrays: 3; a field spec with ``bounded_depth`` bounds its
#: own values), so the walk cannot refuse it. Anything refused is decoded again with the
#: walk, which names the reason: the result and the reason are the same either way.
UNSCANNED_MAX_BYTES = 4096
_MAX_CONTAINER = 4096
_ARRAY_KEYS = frozenset({"dtype", "shape", "data"})

#: Every reason code :class:`MalformedMessage` can carry.
REASONS = (
    "too_large",    # payload over MAX_PAYLOAD_BYTES
    "bad_msgpack",  # not decodable msgpack (truncated, trailing bytes, ext type, bad header)
    "too_deep",     # containers nested deeper than MAX_DEPTH
    "too_many",     # more than MAX_OBJECTS msgpack values
    "not_map",      # top level is not a map
    "version",      # "v" missing or not VERSION
    "missing",      # a required field is absent
    "extra",        # a field not in the schema
    "type",         # wrong python type
    "dtype",        # array dtype other than "<f8"
    "shape",        # array shape does not match / data length mismatch
    "nonfinite",    # NaN or inf
    "range",        # number / string out of range or not in the allowed set
    "sender",       # sender field not among the known senders
    "stale",        # stamp older than now_step - window
    "future",       # stamp newer than now_step + window
)


class MalformedMessage(ValueError):
    """A received payload is invalid.

    Attributes
    ----------
    reason : str
        Short reason code, one of :data:`REASONS`.
    field : str or None
        The offending field, if any.
    """

    def __init__(self, reason: str, message: str, field: str | None = None):
        self.reason = reason
        self.field = shorten(field, 64) if isinstance(field, str) else field
        where = f"field {self.field!r}: " if self.field is not None else ""
        super().__init__(shorten(f"[{reason}] {where}{message}"))


def shorten(text: str, limit: int = MAX_ERROR_CHARS) -> str:
    """Return `text` cut to at most `limit` characters (an ellipsis marks the cut).

    Used for every message that can quote received data (errors, logs, statuses).

    >>> shorten("x" * 10, 6)
    'xxx...'
    >>> shorten("short")
    'short'
    """
    text = str(text)
    if len(text) <= limit:
        return text
    return text[:max(0, limit - 3)] + "..."


# --------------------------------------------------------------------------
# field specs


@dataclass(frozen=True)
class Int:
    """An int (not bool) in ``[lo, hi]``, optionally restricted to `allowed`."""

    lo: int | None = None
    hi: int | None = None
    allowed: frozenset | None = None
    required: bool = True

    def check(self, name, value):
        if isinstance(value, bool) or not isinstance(value, int):
            raise MalformedMessage("type", f"expected int, got {type(value).__name__}", name)
        if (self.lo is not None and value < self.lo) or (self.hi is not None and value > self.hi):
            raise MalformedMessage("range", f"{value} outside [{self.lo}, {self.hi}]", name)
        if self.allowed is not None and value not in self.allowed:
            raise MalformedMessage("range", f"{value} not in the allowed set", name)
        return value


@dataclass(frozen=True)
class Float:
    """A finite float (ints accepted and converted) in ``[lo, hi]``."""

    lo: float | None = None
    hi: float | None = None
    required: bool = True

    def check(self, name, value):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise MalformedMessage("type", f"expected float, got {type(value).__name__}", name)
        value = float(value)
        if not math.isfinite(value):
            raise MalformedMessage("nonfinite", f"{value} is not finite", name)
        if (self.lo is not None and value < self.lo) or (self.hi is not None and value > self.hi):
            raise MalformedMessage("range", f"{value} outside [{self.lo}, {self.hi}]", name)
        return value


@dataclass(frozen=True)
class Bool:
    """A bool."""

    required: bool = True

    def check(self, name, value):
        if not isinstance(value, bool):
            raise MalformedMessage("type", f"expected bool, got {type(value).__name__}", name)
        return value


@dataclass(frozen=True)
class Str:
    """A str of at most `max_len` characters, optionally one of `choices`."""

    max_len: int = 256
    choices: frozenset | None = None
    required: bool = True

    def check(self, name, value):
        if not isinstance(value, str):
            raise MalformedMessage("type", f"expected str, got {type(value).__name__}", name)
        if len(value) > self.max_len:
            raise MalformedMessage("range", f"longer than {self.max_len} characters", name)
        if self.choices is not None and value not in self.choices:
            raise MalformedMessage("range", f"{value!r} not in {sorted(self.choices)}", name)
        return value


@dataclass(frozen=True)
class Ident:
    """A process id: a non-negative int or a short non-empty str.

    `allowed`, if given, restricts the values (reason ``"range"``); to check
    a *sender* against the known peers prefer ``Schema(sender=...)`` and
    ``decode(..., senders=...)`` (reason ``"sender"``).
    """

    allowed: frozenset | None = None
    required: bool = True

    def check(self, name, value):
        if isinstance(value, bool) or not isinstance(value, (int, str)):
            raise MalformedMessage("type", f"expected int or str id, got {type(value).__name__}", name)
        if isinstance(value, int) and not 0 <= value < 2**31:
            raise MalformedMessage("range", f"id {value} outside [0, 2**31)", name)
        if isinstance(value, str) and not 0 < len(value) <= 64:
            raise MalformedMessage("range", "str id must have 1..64 characters", name)
        if self.allowed is not None and value not in self.allowed:
            raise MalformedMessage("range", f"{value!r} not in the allowed set", name)
        return value


@dataclass(frozen=True)
class Bytes:
    """Raw bytes of an exact ``length`` (e.g. a signature); opaque to the transport."""

    length: int
    required: bool = True

    def check(self, name, value):
        if not isinstance(value, (bytes, bytearray)) or len(value) != self.length:
            raise MalformedMessage("type", f"expected {self.length} bytes", name)
        return bytes(value)


@dataclass(frozen=True)
class F64Array:
    """A float64 array of the given shape; ``None`` in `shape` matches any length.

    Decodes to a read-only ``np.ndarray`` sharing memory with the payload.
    """

    shape: tuple = (None,)
    finite: bool = True
    max_size: int = 1 << 16
    required: bool = True

    def check(self, name, value):
        if not isinstance(value, dict):
            raise MalformedMessage("type", f"expected array map, got {type(value).__name__}", name)
        if value.keys() != _ARRAY_KEYS:
            raise MalformedMessage("type", f"array map must have keys {sorted(_ARRAY_KEYS)}", name)
        if value["dtype"] != "<f8":
            raise MalformedMessage("dtype", f"dtype {value['dtype']!r}, expected '<f8'", name)
        shape, data = value["shape"], value["data"]
        if not isinstance(shape, list) or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0
                                                  for s in shape):
            raise MalformedMessage("shape", f"bad shape {shape!r}", name)
        if len(shape) != len(self.shape) or any(e is not None and e != s for e, s in zip(self.shape, shape)):
            raise MalformedMessage("shape", f"shape {tuple(shape)}, expected {self.shape}", name)
        if not isinstance(data, bytes):
            raise MalformedMessage("type", f"array data must be bin, got {type(data).__name__}", name)
        size = math.prod(shape)
        if size > self.max_size:
            raise MalformedMessage("shape", f"{size} elements > max {self.max_size}", name)
        if len(data) != 8 * size:
            raise MalformedMessage("shape", f"{len(data)} data bytes for shape {tuple(shape)}", name)
        arr = np.frombuffer(data, dtype="<f8").reshape(shape)
        if self.finite and not np.isfinite(arr).all():
            raise MalformedMessage("nonfinite", "array contains NaN or inf", name)
        return arr


@dataclass(frozen=True)
class Schema:
    """Declarative message schema.

    Parameters
    ----------
    fields : mapping of str to spec
        Field name -> one of :class:`Int`, :class:`Float`, :class:`Bool`,
        :class:`Str`, :class:`Ident`, :class:`F64Array`. Fields are required
        unless the spec has ``required=False``; unknown fields are rejected.
    stamp : str, optional
        Name of an int field holding the sender's step; checked against
        ``now_step`` and ``window`` in :func:`decode`.
    sender : str, optional
        Name of the field holding the sender id; checked against ``senders``
        in :func:`decode`.
    """

    fields: Mapping
    stamp: str | None = None
    sender: str | None = None
    #: every field a scalar, a float64 array or of a spec with ``bounded_depth`` (set from
    #: `fields`): a message that passes such a schema nests at most MAX_DEPTH deep (see
    #: :data:`UNSCANNED_MAX_BYTES`)
    flat: bool = field(init=False, default=False)

    def __post_init__(self):
        object.__setattr__(self, "fields", dict(self.fields))
        object.__setattr__(self, "flat", all(type(spec) in _FLAT_SPECS
                                             or getattr(spec, "bounded_depth", False)
                                             for spec in self.fields.values()))
        if "v" in self.fields:
            raise ValueError("fields: 'v' is reserved for the version")
        for name, spec in self.fields.items():
            if not hasattr(spec, "check"):
                raise TypeError(f"fields[{name!r}]: not a field spec: {spec!r}")
        for role in ("stamp", "sender"):
            name = getattr(self, role)
            if name is not None and name not in self.fields:
                raise ValueError(f"{role}: {name!r} is not a field of the schema")


_FLAT_SPECS = (Int, Float, Bool, Str, Ident, Bytes, F64Array)

# --------------------------------------------------------------------------
# encode / decode


def _pack_default(obj):
    if isinstance(obj, np.ndarray):
        return pack_array(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    raise TypeError(f"cannot encode {type(obj).__name__}")


def pack_array(arr) -> dict:
    """Return the wire map of a float64 array (little-endian, C order)."""
    a = np.ascontiguousarray(arr, dtype="<f8")
    return {"dtype": "<f8", "shape": list(a.shape), "data": a.tobytes()}


def encode(message: Mapping) -> bytes:
    """Encode a message (a mapping with str keys) to msgpack bytes.

    Adds ``"v": VERSION``. numpy arrays become float64 array maps; numpy
    scalars become python scalars.

    Raises
    ------
    TypeError
        If a key is not a str or a value cannot be encoded.
    """
    if not isinstance(message, Mapping):
        raise TypeError(f"message: expected a mapping, got {type(message).__name__}")
    out = {"v": VERSION}
    for key, value in message.items():
        if not isinstance(key, str):
            raise TypeError(f"message: key {key!r} is not a str")
        if key == "v":
            raise ValueError("message: 'v' is reserved for the version")
        out[key] = value
    return msgpack.packb(out, default=_pack_default, use_bin_type=True)


# --------------------------------------------------------------------------
# header walk: depth and value count, before any object is built

_FIXED = {0xc0: 0, 0xc2: 0, 0xc3: 0, 0xca: 4, 0xcb: 8, 0xcc: 1, 0xcd: 2, 0xce: 4, 0xcf: 8,
          0xd0: 1, 0xd1: 2, 0xd2: 4, 0xd3: 8}


def _scalar_skip(b: int) -> int:
    if b <= 0x7f or b >= 0xe0:   # positive / negative fixint
        return 0
    if 0xa0 <= b <= 0xbf:        # fixstr
        return b & 0x1f
    return _FIXED.get(b, 255)    # nil, bool, float, int; 255: not a fixed-size scalar


# _STEP[b]: for a scalar first byte b, the bytes that follow it; 255 for anything else
_STEP = bytes(_scalar_skip(b) for b in range(256))
# length-prefixed str/bin: first byte -> bytes of the big-endian length
_SIZED = {0xc4: 1, 0xc5: 2, 0xc6: 4, 0xd9: 1, 0xda: 2, 0xdb: 4}
# containers with a length prefix: first byte -> (bytes of the count, values per item)
_COUNTED = {0xdc: (2, 1), 0xdd: (4, 1), 0xde: (2, 2), 0xdf: (4, 2)}


def scan(payload, max_depth: int = MAX_DEPTH, max_objects: int = MAX_OBJECTS) -> tuple:
    """Walk the msgpack headers of `payload` without building anything.

    Returns ``(values, depth)``: the number of msgpack values (map keys, map values, array
    items and containers all count; the top level is one) and the deepest container
    nesting (0 for a scalar). Stops as soon as a limit is passed, so the cost is at most
    ``max_objects`` header reads whatever the payload's size.

    Raises
    ------
    MalformedMessage
        ``"too_deep"`` beyond `max_depth`, ``"too_many"`` beyond `max_objects`,
        ``"bad_msgpack"`` for a truncated payload, trailing bytes, an ext type or the
        reserved byte 0xc1.

    >>> import msgpack
    >>> scan(msgpack.packb({"a": [1, 2, {"b": None}]}))
    (8, 3)
    """
    buf = payload if isinstance(payload, (bytes, bytearray)) else memoryview(payload).cast("B")
    n = len(buf)
    pos = values = depth = 0
    remaining = 1         # values still to read in the innermost open container
    stack = []            # remaining counts of the enclosing containers
    step, sized, counted = _STEP, _SIZED, _COUNTED
    while True:
        if not remaining:
            if not stack:
                break
            remaining = stack.pop()
            continue
        if pos >= n:
            raise MalformedMessage("bad_msgpack", f"truncated at byte {pos}")
        b = buf[pos]
        pos += 1
        remaining -= 1
        values += 1
        if values > max_objects:
            raise MalformedMessage("too_many", f"more than {max_objects} msgpack values")
        skip = step[b]
        if skip != 255:
            pos += skip
            continue
        if 0x80 <= b <= 0x9f:
            count = (b & 0x0f) * 2 if b <= 0x8f else b & 0x0f
        elif b in counted:
            width, per = counted[b]
            if pos + width > n:
                raise MalformedMessage("bad_msgpack", f"truncated at byte {pos}")
            count = int.from_bytes(buf[pos:pos + width], "big") * per
            pos += width
        elif b in sized:
            width = sized[b]
            if pos + width > n:
                raise MalformedMessage("bad_msgpack", f"truncated at byte {pos}")
            pos += width + int.from_bytes(buf[pos:pos + width], "big")
            continue
        else:  # 0xc1 (never used), ext and fixext types
            raise MalformedMessage("bad_msgpack", f"byte 0x{b:02x} at {pos - 1}: not allowed")
        level = len(stack) + 1
        if level > max_depth:
            raise MalformedMessage("too_deep", f"containers nested deeper than {max_depth}")
        depth = max(depth, level)
        if count:
            stack.append(remaining)
            remaining = count
    if pos > n:
        raise MalformedMessage("bad_msgpack", f"truncated: {pos - n} bytes missing")
    if pos < n:
        raise MalformedMessage("bad_msgpack", f"{n - pos} trailing bytes")
    return values, depth


def _no_ext(code, data):
    raise ValueError(f"msgpack ext type {code} not allowed")


def _unpack(payload, walk: bool = True) -> object:
    """The unpacked payload; ``walk=False`` skips the header walk (see
    :data:`UNSCANNED_MAX_BYTES`)."""
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise MalformedMessage("type", f"payload must be bytes, got {type(payload).__name__}")
    n = len(payload)
    if n > MAX_PAYLOAD_BYTES:
        raise MalformedMessage("too_large", f"{n} bytes > {MAX_PAYLOAD_BYTES}")
    if walk:
        scan(payload)
    try:
        return msgpack.unpackb(
            payload, raw=False, strict_map_key=True, use_list=True, timestamp=0, ext_hook=_no_ext,
            max_bin_len=n, max_str_len=min(n, 1 << 16), max_array_len=min(n, _MAX_CONTAINER),
            max_map_len=min(n, _MAX_CONTAINER), max_ext_len=0,
        )
    except Exception as exc:  # ExtraData, FormatError, StackError, UnicodeDecodeError, ...
        raise MalformedMessage("bad_msgpack", f"{type(exc).__name__}: {exc}") from None


def decode(payload, schema: Schema, *, now_step: int | None = None, window: int | None = None,
           senders=None) -> dict:
    """Decode and validate a payload.

    Parameters
    ----------
    payload : bytes
    schema : Schema
    now_step : int, optional
        The receiver's current step. With `window`, a message whose
        ``schema.stamp`` is older than ``now_step - window`` is rejected as
        ``"stale"`` and one newer than ``now_step + window`` as ``"future"``.
    window : int, optional
    senders : container, optional
        Known sender ids; ``schema.sender`` not in it -> ``"sender"``.

    Returns
    -------
    dict
        The fields (without ``"v"``); arrays are read-only numpy views.

    Raises
    ------
    MalformedMessage
        On any problem; nothing else is raised for bad input.
    """
    if schema.flat and isinstance(payload, bytes) and len(payload) <= UNSCANNED_MAX_BYTES:
        try:
            return _checked(_unpack(payload, walk=False), schema, now_step, window, senders)
        except MalformedMessage:
            pass                       # decoded again below, to name the reason
    return _checked(_unpack(payload), schema, now_step, window, senders)


def _checked(obj, schema: Schema, now_step, window, senders) -> dict:
    """The fields of the unpacked message `obj` checked against `schema` (see decode)."""
    if not isinstance(obj, dict):
        raise MalformedMessage("not_map", f"top level is {type(obj).__name__}, expected map")
    version = obj.pop("v", None)
    if version is None:
        raise MalformedMessage("version", "no version field", "v")
    if isinstance(version, bool) or version != VERSION:
        raise MalformedMessage("version", f"version {version!r}, expected {VERSION}", "v")
    out = {}
    for name, spec in schema.fields.items():
        if name in obj:
            out[name] = spec.check(name, obj.pop(name))
        elif spec.required:
            raise MalformedMessage("missing", "required field absent", name)
    if obj:
        extra = sorted(map(str, obj))[0]
        raise MalformedMessage("extra", "unknown field", extra)
    return check_context(out, schema, now_step=now_step, window=window, senders=senders)


def check_context(msg: dict, schema: Schema, *, now_step: int | None = None,
                  window: int | None = None, senders=None) -> dict:
    """The receiver's checks of :func:`decode` (``senders``, ``now_step`` and ``window``)
    on a message decoded with `schema` already: ``msg``, or MalformedMessage. A payload
    that several receivers get is decoded once and checked by each.

    >>> s = Schema({"k": Int()}, stamp="k")
    >>> check_context({"k": 5}, s, now_step=10, window=2)
    Traceback (most recent call last):
    ...
    broker_free_net.codec.MalformedMessage: [stale] field 'k': stamp 5 older than 10 - 2
    """
    if schema.sender is not None and senders is not None and schema.sender in msg:
        if msg[schema.sender] not in senders:
            raise MalformedMessage("sender", f"unknown sender {msg[schema.sender]!r}", schema.sender)
    if schema.stamp is not None and now_step is not None and window is not None and schema.stamp in msg:
        stamp = msg[schema.stamp]
        if stamp < now_step - window:
            raise MalformedMessage("stale", f"stamp {stamp} older than {now_step} - {window}", schema.stamp)
        if stamp > now_step + window:
            raise MalformedMessage("future", f"stamp {stamp} newer than {now_step} + {window}", schema.stamp)
    return msg


@dataclass
class MessageStats:
    """Counts accepted messages and drops by reason code.

    Not thread-safe: use it from the thread that decodes.
    """

    accepted: int = 0
    dropped: Counter = field(default_factory=Counter)

    def count_accepted(self) -> None:
        """Count one accepted message."""
        self.accepted += 1

    def count_dropped(self, reason: str) -> None:
        """Count one dropped message with the given reason code."""
        self.dropped[reason] += 1

    @property
    def total_dropped(self) -> int:
        """Number of dropped messages, all reasons."""
        return sum(self.dropped.values())

    def as_dict(self) -> dict:
        """Return ``{"accepted": n, "dropped": {reason: n}}``."""
        return {"accepted": self.accepted, "dropped": dict(self.dropped)}


def try_decode(payload, schema: Schema, stats: MessageStats, **kwargs) -> dict | None:
    """Decode like :func:`decode`, counting the outcome in `stats`.

    Returns the message, or ``None`` if it was malformed (and counted).
    """
    try:
        msg = decode(payload, schema, **kwargs)
    except MalformedMessage as exc:
        stats.count_dropped(exc.reason)
        return None
    stats.count_accepted()
    return msg
