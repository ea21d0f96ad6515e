"""Hostile input to an agent: far-future stamps, deep nesting, large payloads, floods.

The agent must keep stepping exactly as the reference timeline says, hold a bounded amount
of memory (measured with tracemalloc, which counts Python allocations exactly), and the
codec must never raise anything but its own error.
"""

import gc
import io
import tracemalloc

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.protocol import wire
from agent.node.core import (
    MAX_POLL_STEPS,
    SENSOR_GAP,
    SENSOR_HELD,
    SENSOR_WINDOW,
    AgentConfig,
    AgentCore,
    AssignmentError,
    Role,
)
from agent.shell.ratelimit import LogLimiter
from broker_free_net.codec import (
    MAX_DEPTH,
    MAX_ERROR_CHARS,
    MAX_OBJECTS,
    MAX_PAYLOAD_BYTES,
    REASONS,
    MalformedMessage,
    MessageStats,
    decode,
    try_decode,
)
from broker_free_net.impair import DELIVER
from broker_free_net.peer import DEFAULT_INBOX_BYTES, Inbox, Received
from design.plausibility import ESTIMATE_MULTIPLE
from tests.runtime_harness import Mesh, reference

STEPS = 30


@pytest.fixture(scope="module")
def gains14(paper14):
    rng = np.random.default_rng(5)
    return [0.4 * rng.normal(size=(paper14.n, 1)) for _ in range(paper14.N)]


# ---------------------------------------------------------------------------------
# sensor stamps


def test_far_future_sensor_stamps_leave_the_timeline_exact(paper14, gains14):
    """Every step, every agent also gets readings stamped 2^38, just past the window and
    1000+ steps ahead (never adjacent): the estimates stay those of the reference."""
    mesh = Mesh(paper14, gains14, seed=3, deadline_s=1.0)
    for t in range(STEPS + 1):
        for core in mesh.agents.values():
            label = core.wanted_labels()[0]
            base = max(core.step, 0)
            assert not core.on_sensor(label, wire.MAX_STEP, 1e6)
            assert not core.on_sensor(label, base + SENSOR_WINDOW + 1, 1e6)
            assert core.on_sensor(label, 1000 + 4 * t, 1e6)  # held aside, never believed
        mesh.tick()
        mesh.pass_time(1.1)
    xs, xh = reference(paper14, gains14, STEPS, seed=3)
    for k in range(STEPS + 1):
        for i in range(paper14.N):
            np.testing.assert_allclose(mesh.estimates[(i + 1, k)], xh[k][i],
                                       rtol=1e-12, atol=1e-12 * np.abs(xs[k]).max())
    for core in mesh.agents.values():
        assert core.step == STEPS and core.sensor_missed == 0
        assert not core.sensor                       # nothing left to use: it could exit
        assert len(core.sensor_aside) <= SENSOR_GAP


def _lone_agent(n=2):
    """An active agent with no neighbours on an n-node system (A = 0.5 I)."""
    role = Role(epoch=0, activate_at=0, measure=("a",), neighbours={}, self_weight=1.0,
                gain=np.full((n, 1), 0.5))
    labels = ("a",) + tuple(f"n{i}" for i in range(1, n))
    return AgentCore(AgentConfig(agent=1, A=0.5 * np.eye(n), labels=labels, agents=(1,),
                                 seed=0, measurement_noise=0.0, role=role))


def _drive(core, now=0.0):
    """Poll until the agent stops moving; return the steps computed, in order."""
    steps = []
    while True:
        out = core.poll(now)
        steps += [k for k, *_ in out]
        if len(out) < MAX_POLL_STEPS:
            return steps


def test_readings_resume_after_a_long_silence():
    """The world was silent (or cut off) for 100 steps: the first reading after the gap is
    held aside until the next one confirms it, then the 100 lost steps are computed."""
    core = _lone_agent()
    for k in range(11):
        core.on_sensor("a", k, 1.0)
    assert _drive(core) == list(range(11))
    core.on_sensor("a", 111, 1.0)
    assert _drive(core) == [] and list(core.sensor_aside) == [111]
    core.on_sensor("a", 112, 1.0)
    assert _drive(core) == list(range(11, 113))
    assert core.sensor_missed == 100 and not core.sensor and not core.sensor_aside


def test_a_stray_stamp_is_never_believed():
    core = _lone_agent()
    for k in range(5):
        core.on_sensor("a", k, 1.0)
    _drive(core)
    core.on_sensor("a", 500, -1e6)                     # one stray stamp, 496 steps ahead
    for k in range(5, 600):
        core.on_sensor("a", k, 1.0)
        assert _drive(core) == [k]                     # no reading is skipped
        assert 0 < core.x[0] < 1                       # the stray value is never used
    assert core.sensor_missed == 0 and not core.sensor and not core.sensor_aside


def test_poll_is_bounded_and_resumes():
    core = _lone_agent()
    for k in range(1001):
        core.on_sensor("a", k, 1.0)
    first = core.poll(0.0)
    assert [k for k, *_ in first] == list(range(MAX_POLL_STEPS))
    assert _drive(core) == list(range(MAX_POLL_STEPS, 1001))


def test_sensor_buffers_are_bounded_under_a_flood():
    core = _lone_agent()
    core.on_sensor("a", 0, 1.0)
    _drive(core)
    rng = np.random.default_rng(0)
    stamps = rng.integers(1, 2 * SENSOR_WINDOW, size=20_000)
    gc.collect()
    tracemalloc.start()
    try:
        for s in stamps[:10_000]:
            core.on_sensor("a", int(s), 1.0)
        warm = tracemalloc.get_traced_memory()[0]
        for s in stamps[10_000:]:
            core.on_sensor("a", int(s), 1.0)
        gc.collect()
        grown = tracemalloc.get_traced_memory()[0] - warm
    finally:
        tracemalloc.stop()
    assert len(core.sensor) <= SENSOR_HELD and len(core.sensor_aside) <= SENSOR_GAP
    assert min(core.sensor) >= 1 and max(core.sensor) <= SENSOR_WINDOW
    assert grown < 64 * 1024, grown  # a full buffer does not grow


def test_rejected_assignment_error_is_short():
    core = _lone_agent()
    msg = {"agent": 1, "epoch": 1, "activate_at": 5, "measure": [f"x{i:0>250}" for i in range(4096)],
           "neighbours": {a: 0.0 for a in range(2, 4098)}, "self_weight": 1.0,
           "gain": np.zeros((2, 4096))}
    with pytest.raises(AssignmentError):
        core.on_assignment(msg)
    assert core.ctl_rejected == 1
    assert 0 < len(core.ctl_last_error) <= MAX_ERROR_CHARS
    assert core.ctl_last_error.startswith("measure: unknown node labels")
    st = core.status()
    st.update(malformed=0, malformed_reasons={}, overflows=0)
    assert len(wire.encode_status(st)) < 2000


def test_log_lines_are_shortened_and_rate_limited():
    out, t = io.StringIO(), [0.0]
    log = LogLimiter(out, burst=3, rate=2.0, max_chars=50, clock=lambda: t[0])
    written = [log.say("rejected " + "x" * 10_000) for _ in range(741)]
    assert written == [True] * 3 + [False] * 738
    t[0] = 1.0  # two more lines' worth of budget
    assert log.say("a") and log.say("b") and not log.say("c")
    lines = out.getvalue().splitlines()
    assert len(lines) == 5 and all(len(line) <= 50 for line in lines[:3])
    assert lines[3] == "a (738 similar lines suppressed)" and lines[4] == "b"
    assert log.suppressed_total == 739


# ---------------------------------------------------------------------------------
# decoding: depth and size refused before objects are built


def _nested_list(depth):
    obj = []
    for _ in range(depth - 1):
        obj = [obj]
    return obj


HOSTILE = {
    "deep": msgpack.packb({"v": 1, "x": _nested_list(MAX_DEPTH + 5)}),
    "deep_max": b"\x91" * (MAX_PAYLOAD_BYTES - 1) + b"\xc0",
    "wide": msgpack.packb({"v": 1, "x": [[0] * 4000] * (MAX_OBJECTS // 4000 + 1)}),
    "empty_lists": b"\xdd\x00\x0f\xff\xff" + b"\x90" * (MAX_PAYLOAD_BYTES - 5),
    "junk_250k": np.random.default_rng(1).bytes(250_000),
    "big_bin": msgpack.packb({"v": 1, "kind": "est", "x": b"\x00" * (MAX_PAYLOAD_BYTES - 100)}),
    "over_limit": b"\x00" * (MAX_PAYLOAD_BYTES + 1),
    "future": wire.encode_sensors(wire.MAX_STEP, np.ones(14)),
}


@pytest.mark.parametrize("name, reason", [
    ("deep", "too_deep"), ("deep_max", "too_deep"), ("wide", "too_many"),
    ("empty_lists", "too_many"), ("over_limit", "too_large"), ("future", "future")])
def test_hostile_payloads_are_refused_with_their_reason(name, reason):
    schema = wire.sensors_schema(14) if name == "future" else wire.est_schema(14)
    with pytest.raises(MalformedMessage) as info:
        decode(HOSTILE[name], schema, now_step=10, window=100_000)
    assert info.value.reason == reason
    assert len(str(info.value)) <= MAX_ERROR_CHARS


@pytest.mark.parametrize("name", [pytest.param(k, marks=pytest.mark.slow)
                                  if k in ("empty_lists", "wide") else k for k in sorted(HOSTILE)])
def test_decoding_hostile_payloads_allocates_little_and_keeps_nothing(name):
    """Peak Python allocation of one decode stays far below what the payload could build
    (a 1 MiB payload of empty lists builds ~1M lists, ~60 MB, without the header walk)."""
    payload, schema, stats = HOSTILE[name], wire.est_schema(14), MessageStats()
    try_decode(payload, schema, stats)  # warm caches
    gc.collect()
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        for _ in range(20):
            assert try_decode(payload, schema, stats) is None
        current, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    limit = 3 * len(payload) if name in ("big_bin", "junk_250k") else 2 << 20
    assert peak - before < limit, (peak - before)
    assert current - before < 16 * 1024
    assert stats.accepted == 0 and stats.total_dropped == 21


def test_inbox_holds_bounded_bytes_under_a_flood_of_large_payloads():
    inbox = Inbox()
    junk = HOSTILE["junk_250k"]
    for _ in range(400):
        inbox._push(Received(junk, "k", 0.0))
    assert inbox.nbytes <= DEFAULT_INBOX_BYTES and len(inbox) == DEFAULT_INBOX_BYTES // len(junk)
    inbox._push(Received(HOSTILE["over_limit"], "k", 0.0))
    assert inbox.oversized == 1 and inbox.nbytes <= DEFAULT_INBOX_BYTES


# ---------------------------------------------------------------------------------
# property-based fuzz: only the codec's own error, on every wire schema

SCHEMAS = [wire.sensors_schema(3), wire.truth_schema(3), wire.est_schema(3), wire.ctl_schema(3),
           wire.STATUS_SCHEMA]
GOOD = [wire.encode_sensors(5, [1.5, 0.0, -2.0]), wire.encode_truth(5, np.ones(3)),
        wire.encode_est(2, 5, np.ones(3), 0, 1.0),
        wire.encode_ctl(1, 2, 9, ["a"], {2: 0.5}, 0.5, np.ones((3, 1)), take_over=3)]

leaf = (st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats()
        | st.text(max_size=8) | st.binary(max_size=24))
values = st.recursive(
    leaf, lambda c: st.lists(c, max_size=5) | st.dictionaries(st.text(max_size=6), c, max_size=5),
    max_leaves=20)
field_names = st.sampled_from(sorted({f for s in SCHEMAS for f in s.fields} | {"v", "zz"}))


def _only_malformed(payload, schema):
    try:
        decode(payload, schema, now_step=5, window=10, senders={1, 2, 3})
    except MalformedMessage as exc:
        assert exc.reason in REASONS
        assert len(str(exc)) <= MAX_ERROR_CHARS


@pytest.mark.slow
@given(st.sampled_from(SCHEMAS), st.dictionaries(field_names, values, max_size=8))
@settings(max_examples=300, deadline=None)
def test_fuzz_structures_only_raise_malformed(schema, obj):
    _only_malformed(msgpack.packb({"v": 1, **obj}, use_bin_type=True), schema)


@given(st.sampled_from(SCHEMAS), st.sampled_from(GOOD), st.binary(min_size=1, max_size=16),
       st.integers(0, 10**6), st.booleans())
@settings(max_examples=300, deadline=None)
def test_fuzz_corrupted_messages_only_raise_malformed(schema, good, noise, pos, insert):
    data = bytearray(good)
    pos %= len(data)
    if insert:
        data[pos:pos] = noise
    else:
        data[pos:pos + len(noise)] = noise
    _only_malformed(bytes(data), schema)


@given(st.sampled_from(SCHEMAS), st.integers(1, 3 * MAX_DEPTH), st.sampled_from([b"\x91", b"\x81\xa1k"]))
@settings(max_examples=50, deadline=None)
def test_fuzz_nesting_only_raises_malformed(schema, depth, opener):
    # {"v": 1, "x": [[[... None]]]} or {"v": 1, "x": {"k": {"k": ... None}}}
    _only_malformed(b"\x82\xa1v\x01\xa1x" + opener * depth + b"\xc0", schema)


def test_rosters_heard_together_each_take_effect_at_their_step():
    """An agent far behind the run (resumed after a pause) hears two rosters at once: the
    first removes it from step 10, the second (a later failure) from step 20. It drops its
    role at step 10, not 20, and every estimate of the catch-up batch carries the epoch it
    was computed under (seen in a chaos run: the batch went out stamped with the epoch of
    the drop, and the later roster had replaced the earlier one)."""
    core = _lone_agent()
    core.on_roster({"epoch": 1, "activate_at": 10, "ids": [2]})
    core.on_roster({"epoch": 2, "activate_at": 20, "ids": [3]})
    assert not core.on_roster({"epoch": 2, "activate_at": 25, "ids": [3]})   # not newer
    for k in range(31):
        core.on_sensor("a", k, 1.0)
    out = core.poll(0.0)                                # one batch: steps 0..30
    assert [(k, e) for k, _, e in out] == [(k, 0) for k in range(10)]
    assert not core.active and core.epoch == 1 and core.roster_epoch == 2 and core.step == 30


def test_a_newer_roster_supersedes_pending_ones_that_start_later():
    core = _lone_agent()
    core.on_roster({"epoch": 1, "activate_at": 20, "ids": [2]})
    core.on_roster({"epoch": 2, "activate_at": 10, "ids": [1]})   # in force first: keeps it
    for k in range(31):
        core.on_sensor("a", k, 1.0)
    assert [k for k, *_ in core.poll(0.0)] == list(range(31))
    assert core.active and core.roster_epoch == 2 and core.roster_pending == []


def test_readings_from_beyond_the_worlds_pace_are_refused():
    """Readings every 20 ms: two adjacent forged stamps 99,998 and 99,999 steps ahead,
    0.1 s later, are refused (a world cannot have run that far) and the agent keeps
    stepping; after the agent itself was stopped 5 s, the readings of those 5 s (250
    steps ahead, from its inbox) are taken."""
    core = _lone_agent()
    t = 0.0
    for k in range(20):
        assert core.on_sensor("a", k, 1.0, now=t)
        t += 0.02
    assert _drive(core) == list(range(20))
    assert not core.on_sensor("a", 19 + 99_998, -1e6, now=t + 0.1)
    assert not core.on_sensor("a", 19 + 99_999, -1e6, now=t + 0.1)
    assert core.sensor_future == 2 and not core.sensor_aside
    for k in range(20, 40):
        assert core.on_sensor("a", k, 1.0, now=t)
        t += 0.02
    assert _drive(core) == list(range(20, 40)) and 0 < core.x[0] < 1
    t += 5.0                                       # the agent was stopped
    for k in range(290, 300):                      # what its inbox kept of those 5 s
        assert core.on_sensor("a", k, 1.0, now=t)
    assert _drive(core) == list(range(40, 300))
    assert core.sensor_future == 2 and core.status()["sensor"]["future"] == 2


def test_absurd_readings_and_estimates_are_refused_and_counted():
    """A reading of 1e300, and estimates of 1e300 or 1e30 from a neighbour, are refused
    (counted under ``implausible``) and never reach the agent's state; values on the
    model's scale pass."""
    core = _lone_agent()
    assert not core.on_sensor("a", 0, 1e300)
    assert core.implausible == {"estimates": 0, "readings": 1}
    assert core.on_sensor("a", 0, 2.5)
    assert core.on_estimate(2, 0, [1e300, 0.0], now=0.0) == "implausible"
    assert core.on_estimate(2, 0, [0.0, -1e30], now=0.0) == "implausible"
    assert core.on_estimate(2, 0, [3.0, -4.0], now=0.0) == DELIVER
    assert core.status()["implausible"] == {"estimates": 2, "readings": 1}
    status = {**core.status(), "malformed": 0, "malformed_reasons": {}, "overflows": 0}
    assert try_decode(wire.encode_status(status), wire.STATUS_SCHEMA, MessageStats())
    assert 2 not in core.nbrs or list(core.nbrs[2].est) == [0]
    assert _drive(core) == [0] and np.all(np.abs(core.x) < 10)


def test_an_estimate_is_judged_at_its_stamp():
    """On an unstable system the scale grows with the step: 1e10 is absurd at step 0
    and on the model's scale 200 steps later (1.2^200 ~ 7e15), where it is used."""
    role = Role(epoch=0, activate_at=0, measure=("a",), neighbours={2: 0.5}, self_weight=0.5,
                gain=np.full((1, 1), 0.5))
    core = AgentCore(AgentConfig(agent=1, A=np.array([[1.2]]), labels=("a",), agents=(1, 2),
                                 seed=0, measurement_noise=0.0, role=role))
    assert core.on_estimate(2, 0, [1e10], now=0.0) == "implausible"
    assert core.on_estimate(2, 200, [1e10], now=0.0) != "implausible"
    assert not core.scale.plausible([1e10], 0, ESTIMATE_MULTIPLE)
