import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from broker_free_net.codec import (
    MAX_ERROR_CHARS,
    MAX_PAYLOAD_BYTES,
    REASONS,
    Bool,
    F64Array,
    Float,
    Ident,
    Int,
    MalformedMessage,
    MessageStats,
    Schema,
    Str,
    decode,
    encode,
    scan,
    shorten,
    try_decode,
)

SCHEMA = Schema(
    {
        "step": Int(0, 10**9),
        "sender": Ident(),
        "x": F64Array((3,)),
        "P": F64Array((3, 3)),
        "gain": Float(0.0, 10.0),
        "ok": Bool(),
        "note": Str(max_len=8, required=False),
    },
    stamp="step",
    sender="sender",
)


def good(**over):
    msg = {"step": 10, "sender": 1, "x": np.arange(3.0), "P": np.eye(3), "gain": 0.5, "ok": True}
    msg.update(over)
    return msg


def raw(obj):
    return msgpack.packb(obj, use_bin_type=True)


def arr_map(a, dtype="<f8", shape=None):
    a = np.asarray(a, dtype="<f8")
    return {"dtype": dtype, "shape": list(a.shape) if shape is None else shape, "data": a.tobytes()}


def good_raw(**over):
    msg = {"v": 1, "step": 10, "sender": 1, "x": arr_map(np.arange(3.0)), "P": arr_map(np.eye(3)),
           "gain": 0.5, "ok": True}
    msg.update(over)
    return msg


def reason_of(payload, **kw):
    with pytest.raises(MalformedMessage) as info:
        decode(payload, SCHEMA, **kw)
    assert info.value.reason in REASONS
    return info.value


def test_round_trip_and_zero_copy():
    payload = encode(good(note="hi"))
    msg = decode(payload, SCHEMA, now_step=10, window=2, senders={0, 1})
    assert msg["step"] == 10 and msg["sender"] == 1 and msg["ok"] is True and msg["note"] == "hi"
    np.testing.assert_array_equal(msg["x"], np.arange(3.0))
    np.testing.assert_array_equal(msg["P"], np.eye(3))
    assert msg["x"].dtype == np.dtype("<f8")
    assert not msg["x"].flags.writeable  # a view on the payload bytes
    assert msg["x"].base is not None


def test_encode_converts_numpy_scalars_and_non_contiguous():
    a = np.arange(9.0).reshape(3, 3).T  # not C-contiguous
    payload = encode(good(step=np.int64(4), gain=np.float32(0.25), ok=np.bool_(False), P=a))
    msg = decode(payload, SCHEMA)
    assert msg["step"] == 4 and msg["gain"] == 0.25 and msg["ok"] is False
    np.testing.assert_array_equal(msg["P"], a)


def test_encode_rejects():
    with pytest.raises(TypeError):
        encode([1, 2])
    with pytest.raises(TypeError):
        encode({1: 2})
    with pytest.raises(TypeError):
        encode({"a": object()})
    with pytest.raises(ValueError):
        encode({"v": 2})


@pytest.mark.parametrize(
    "payload, reason, field",
    [
        (b"\xc1", "bad_msgpack", None),
        (b"", "bad_msgpack", None),
        (raw(good_raw()) + b"\x00", "bad_msgpack", None),
        (raw(good_raw())[:-3], "bad_msgpack", None),
        (b"\x91" * 5000, "too_deep", None),
        (msgpack.packb(msgpack.ExtType(5, b"abc")), "bad_msgpack", None),
        (raw([1, 2]), "not_map", None),
        (raw(3), "not_map", None),
        (raw({k: v for k, v in good_raw().items() if k != "v"}), "version", "v"),
        (raw(good_raw(v=2)), "version", "v"),
        (raw(good_raw(v=True)), "version", "v"),
        (raw({k: v for k, v in good_raw().items() if k != "gain"}), "missing", "gain"),
        (raw(good_raw(extra=1)), "extra", "extra"),
        (raw(good_raw(step="10")), "type", "step"),
        (raw(good_raw(step=True)), "type", "step"),
        (raw(good_raw(step=-1)), "range", "step"),
        (raw(good_raw(step=2**64 - 1)), "range", "step"),
        (raw(good_raw(gain=float("nan"))), "nonfinite", "gain"),
        (raw(good_raw(gain=float("inf"))), "nonfinite", "gain"),
        (raw(good_raw(gain=11.0)), "range", "gain"),
        (raw(good_raw(ok=1)), "type", "ok"),
        (raw(good_raw(note="x" * 9)), "range", "note"),
        (raw(good_raw(sender=1.5)), "type", "sender"),
        (raw(good_raw(sender=-3)), "range", "sender"),
        (raw(good_raw(x=[0.0, 1.0, 2.0])), "type", "x"),
        (raw(good_raw(x={"dtype": "<f8", "shape": [3]})), "type", "x"),
        (raw(good_raw(x=arr_map(np.zeros(3), dtype=">f8"))), "dtype", "x"),
        (raw(good_raw(x=arr_map(np.zeros(3), dtype="<f4"))), "dtype", "x"),
        (raw(good_raw(x=arr_map(np.zeros(4)))), "shape", "x"),
        (raw(good_raw(x=arr_map(np.zeros(3), shape=[4]))), "shape", "x"),
        (raw(good_raw(x=arr_map(np.zeros(3), shape=[3, 1]))), "shape", "x"),
        (raw(good_raw(x=arr_map(np.zeros(3), shape=[-3]))), "shape", "x"),
        (raw(good_raw(x=arr_map(np.zeros(3), shape="3"))), "shape", "x"),
        (raw(good_raw(x={"dtype": "<f8", "shape": [3], "data": "abc"})), "type", "x"),
        (raw(good_raw(P=arr_map(np.zeros((3, 2))))), "shape", "P"),
        (raw(good_raw(x=arr_map([0.0, np.nan, 1.0]))), "nonfinite", "x"),
        (raw(good_raw(x=arr_map([0.0, -np.inf, 1.0]))), "nonfinite", "x"),
        (b"\xc6\xff\xff\xff\xf0" + b"x" * 10, "bad_msgpack", None),  # bin32 claiming ~4 GiB
        (b"\xdd\xff\xff\xff\xf0", "bad_msgpack", None),  # array32 claiming 4G items
        (b"\xdf\xff\xff\xff\xf0", "bad_msgpack", None),  # map32 claiming 4G items
        (raw({1: 2}), "bad_msgpack", None),  # non-str key (strict_map_key)
        (raw({"v": 1, b"step": 1}), "missing", "step"),  # bytes key is not the str field
        (b"\x00" * (MAX_PAYLOAD_BYTES + 1), "too_large", None),
        ("not bytes", "type", None),
    ],
)
def test_malformed(payload, reason, field):
    exc = reason_of(payload)
    assert exc.reason == reason, exc
    assert exc.field == field
    if field is not None:
        assert repr(field) in str(exc)


def test_sender_and_stamp_checks():
    payload = encode(good(step=10, sender=5))
    assert reason_of(payload, senders={0, 1}).reason == "sender"
    assert decode(payload, SCHEMA, senders={5})["sender"] == 5
    assert reason_of(payload, now_step=20, window=5).reason == "stale"
    assert reason_of(payload, now_step=2, window=5).reason == "future"
    assert decode(payload, SCHEMA, now_step=15, window=5)["step"] == 10  # window is inclusive
    assert decode(payload, SCHEMA, now_step=5, window=5)["step"] == 10


def test_schema_validation():
    with pytest.raises(ValueError):
        Schema({"v": Int()})
    with pytest.raises(ValueError):
        Schema({"a": Int()}, stamp="b")
    with pytest.raises(TypeError):
        Schema({"a": int})


def test_stats_and_try_decode():
    stats = MessageStats()
    assert try_decode(b"\xc1", SCHEMA, stats) is None
    assert try_decode(encode(good(step=-1)), SCHEMA, stats) is None
    assert try_decode(encode(good()), SCHEMA, stats) is not None
    assert stats.as_dict() == {"accepted": 1, "dropped": {"bad_msgpack": 1, "range": 1}}
    assert stats.total_dropped == 2


finite = st.floats(allow_nan=False, allow_infinity=False)


@given(
    step=st.integers(0, 10**9),
    sender=st.one_of(st.integers(0, 2**31 - 1), st.text(min_size=1, max_size=64)),
    x=st.lists(finite, min_size=3, max_size=3),
    P=st.lists(finite, min_size=9, max_size=9),
    gain=st.floats(0.0, 10.0),
    ok=st.booleans(),
    note=st.one_of(st.none(), st.text(max_size=8)),
)
@settings(deadline=None)
def test_round_trip_property(step, sender, x, P, gain, ok, note):
    msg = good(step=step, sender=sender, x=np.array(x), P=np.array(P).reshape(3, 3), gain=gain, ok=ok)
    if note is not None:
        msg["note"] = note
    out = decode(encode(msg), SCHEMA)
    assert out.keys() == msg.keys()
    for k, v in msg.items():
        if isinstance(v, np.ndarray):
            assert np.array_equal(out[k], v) and out[k].shape == v.shape
        else:
            assert out[k] == v


@given(st.binary(max_size=512))
@settings(max_examples=500, deadline=None)
def test_random_bytes_only_raise_malformed(data):
    try:
        decode(data, SCHEMA)
    except MalformedMessage as exc:
        assert exc.reason in REASONS


msgpack_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats() | st.text(max_size=10)
    | st.binary(max_size=40),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=6), children, max_size=4),
    max_leaves=12,
)


@pytest.mark.slow
@given(st.dictionaries(st.sampled_from(["v", "step", "sender", "x", "P", "gain", "ok", "note", "zz"]),
                       msgpack_values | st.builds(lambda a: arr_map(a), st.lists(st.floats(), max_size=10))))
@settings(max_examples=500, deadline=None)
def test_random_structures_only_raise_malformed(obj):
    try:
        msg = decode(raw(obj), SCHEMA)
    except MalformedMessage as exc:
        assert exc.reason in REASONS
    else:
        assert msg.keys() <= set(SCHEMA.fields)
        assert all(np.isfinite(msg[k]).all() for k in ("x", "P"))
        assert math.isfinite(msg["gain"])


@given(st.binary(min_size=1, max_size=200), st.integers(0, 199))
@settings(deadline=None)
def test_corrupted_good_payload_only_raises_malformed(noise, pos):
    payload = bytearray(encode(good()))
    pos %= len(payload)
    payload[pos:pos + len(noise)] = noise
    try:
        decode(bytes(payload), SCHEMA)
    except MalformedMessage:
        pass


def _walk(obj, level=0):
    """(values, depth) of an unpacked msgpack object: the reference for scan()."""
    if isinstance(obj, dict):
        parts = [_walk(v, level + 1) for kv in obj.items() for v in kv]
    elif isinstance(obj, list):
        parts = [_walk(v, level + 1) for v in obj]
    else:
        return 1, level
    return 1 + sum(p[0] for p in parts), max([level + 1] + [p[1] for p in parts])


@given(msgpack_values)
@settings(max_examples=300, deadline=None)
def test_scan_counts_like_a_walk_of_the_unpacked_object(obj):
    payload = raw(obj)
    assert scan(payload) == _walk(msgpack.unpackb(payload, strict_map_key=False))


def test_scan_limits_and_hand_counted_examples():
    assert scan(raw(5)) == (1, 0)
    assert scan(raw([])) == (1, 1)
    assert scan(raw({"a": [1, {"b": None}]})) == (7, 3)
    assert scan(raw([[]] * 3)) == (4, 2)
    assert scan(b"\x91" * 16 + b"\xc0") == (17, 16)
    with pytest.raises(MalformedMessage, match="too_deep"):
        scan(b"\x91" * 17 + b"\xc0")
    assert scan(raw(list(range(10))), max_objects=11) == (11, 1)
    with pytest.raises(MalformedMessage, match="too_many"):
        scan(raw(list(range(11))), max_objects=11)
    for bad in (b"\xc1", b"\xd4\x01\x00", b"\x92\x01", b"\xc4\x05ab", b"\x01\x02", b""):
        with pytest.raises(MalformedMessage, match="bad_msgpack"):
            scan(bad)


def test_error_messages_are_short():
    long_value = "y" * 60_000
    schema = Schema({"s": Str(max_len=10**6, choices=frozenset({"a"}))})
    with pytest.raises(MalformedMessage) as info:
        decode(raw({"v": 1, "s": long_value}), schema)
    assert info.value.reason == "range" and len(str(info.value)) <= MAX_ERROR_CHARS
    assert str(info.value).endswith("...")
    assert shorten("abcdef", 5) == "ab..." and shorten("abcde", 5) == "abcde"


def _outcome(decoder):
    try:
        msg = decoder()
    except MalformedMessage as exc:
        return ("refused", exc.reason, str(exc))
    return ("accepted", {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                         for k, v in msg.items()})


_EST = Schema({"kind": Str(choices=frozenset({"est"})), "agent": Int(1, 99),
               "step": Int(0, 10**9), "t": Float(0.0, 1e12), "x": F64Array((3,))},
              stamp="step", sender="agent")


def _mutated(data, valid: bytes, kind: str) -> bytes:
    """``valid`` with a byte changed (``flip``), cut short (``cut``) or extended."""
    if kind == "flip":
        i = data.draw(st.integers(0, len(valid) - 1))
        return valid[:i] + bytes([data.draw(st.integers(0, 255))]) + valid[i + 1:]
    if kind == "cut":
        return valid[:data.draw(st.integers(0, len(valid) - 1))]
    return valid + data.draw(st.binary(min_size=1, max_size=8))


@given(st.data())
@settings(max_examples=300, deadline=None)
def test_small_flat_messages_decode_alike_with_and_without_the_header_walk(data):
    """A small payload of a flat schema skips the header walk; whatever it holds (a valid
    message, one with a byte changed, cut or extended, nested junk), the outcome (the
    message, or the reason and text of the refusal) is the walk's."""
    from broker_free_net import codec

    valid = encode({"kind": "est", "agent": 2, "step": 40, "t": 1.5,
                    "x": np.array([1.0, -2.0, 3.0])})
    kind = data.draw(st.sampled_from(["flip", "cut", "extend", "nest"]))
    if kind == "nest":
        payload = b"\x91" * data.draw(st.integers(1, 40)) + b"\xc0"
    else:
        payload = _mutated(data, valid, kind)
    assert _EST.flat and len(payload) <= codec.UNSCANNED_MAX_BYTES
    kwargs = {"now_step": 50, "window": 100, "senders": {1, 2, 3}}
    fast = _outcome(lambda: decode(payload, _EST, **kwargs))
    walked = _outcome(lambda: codec._checked(codec._unpack(payload), _EST,
                                              kwargs["now_step"], kwargs["window"],
                                              kwargs["senders"]))
    assert fast == walked


def _a_status() -> dict:
    return {"agent": 2, "step": 40, "active": True, "epoch": 1, "measure": ["n3"],
            "neighbours": {1: 0.4}, "delays": {1: 2}, "drops": 0, "late": 3,
            "inputs": {"fresh": 40}, "ages": {1: 2}, "malformed": 0,
            "malformed_reasons": {}, "impaired": 0, "heard": [1, 3], "overflows": 0,
            "sensor": {"labels": ["n3"], "last_step": 40, "missed": 0},
            "ctl": {"accepted": 1, "pending": 0}, "links": {"1": {"delay": 2, "drop": 0.0}},
            "estimates_from": {"ids": [1], "changes": 1, "received": {"1": 40}},
            "hop_ms": {"n": 4, "median": 0.5, "p99": 1.0}}


@given(st.data())
@settings(max_examples=300, deadline=None)
def test_small_statuses_decode_alike_with_and_without_the_header_walk(data):
    """A status's free-form fields bound their own nesting (``Loose``), so a small status
    skips the header walk too; whatever it holds (a byte changed, cut or extended, a
    free-form field nested up to 40 deep), the outcome is the walk's."""
    from agent.protocol import wire
    from broker_free_net import codec

    schema = wire.STATUS_SCHEMA
    status = _a_status()
    kind = data.draw(st.sampled_from(["flip", "cut", "extend", "nest"]))
    if kind == "nest":
        depth = data.draw(st.integers(1, 40))
        field = data.draw(st.sampled_from(["sensor", "links", "ctl", "hop_ms"]))
        nested = 0
        for _ in range(depth):
            nested = data.draw(st.sampled_from([[nested], {"k": nested}]))
        status[field] = nested
    valid = wire.encode_status(status)
    payload = valid if kind == "nest" else _mutated(data, valid, kind)
    assert schema.flat and len(payload) <= codec.UNSCANNED_MAX_BYTES
    fast = _outcome(lambda: decode(payload, schema))
    walked = _outcome(lambda: codec._checked(codec._unpack(payload), schema, None, None, None))
    assert fast == walked
    if kind == "nest":
        assert (fast[0] == "accepted") == (depth <= wire.LOOSE_MAX_DEPTH), (depth, fast)
