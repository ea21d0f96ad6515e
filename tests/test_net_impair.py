import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from broker_free_net.codec import MalformedMessage, encode
from broker_free_net.impair import (
    DELIVER,
    DROP,
    HOLD,
    InvalidImpairment,
    LinkImpairments,
    LinkParams,
    apply_impairment_message,
    decode_impairment,
    encode_impairment,
)

DETERMINISTIC = settings(derandomize=True, deadline=None)


class FakeClock:
    def __init__(self, t=0.0):
        self.t = t

    def __call__(self):
        return self.t


def test_unimpaired_link_delivers():
    table = LinkImpairments()
    assert table.offer(0, 1, "m").action == DELIVER
    assert table.release(now_step=0) == []


def test_set_merges_and_clear():
    table = LinkImpairments()
    table.set((0, 1), delay_steps=2)
    table.set((0, 1), drop=0.25)
    assert table.get((0, 1)) == LinkParams(delay_steps=2, drop=0.25)
    assert table.get((1, 0)) == LinkParams()
    table.clear((0, 1))
    assert table.get((0, 1)).is_identity
    table.set((0, 1), partition=True)
    table.set((2, 1), partition=True)
    table.clear_all()
    assert table.links() == {}


@pytest.mark.parametrize("params, field", [
    ({"drop": 1.5}, "drop"),
    ({"drop": -0.1}, "drop"),
    ({"delay_steps": -1}, "delay_steps"),
    ({"delay_steps": 1.5}, "delay_steps"),
    ({"delay_ms": math.inf}, "delay_ms"),
    ({"jitter_ms": -1}, "jitter_ms"),
    ({"burst": 0.5}, "burst"),
    ({"drop": 0.9, "burst": 2}, "burst"),
    ({"partition": 1}, "partition"),
    ({"bogus": 1}, "bogus"),
])
def test_invalid_params_name_field_and_leave_table_unchanged(params, field):
    table = LinkImpairments()
    table.set((0, 1), delay_steps=1)
    with pytest.raises(InvalidImpairment) as info:
        table.set((0, 1), **params)
    assert info.value.field == field
    assert table.get((0, 1)) == LinkParams(delay_steps=1)


def test_bad_link():
    with pytest.raises(InvalidImpairment):
        LinkImpairments().set([0, 1], drop=0.1)
    with pytest.raises(InvalidImpairment):
        LinkImpairments().set((0, 1, 2), drop=0.1)


def test_step_delay_needs_stamp():
    table = LinkImpairments()
    table.set((0, 1), delay_steps=1)
    with pytest.raises(InvalidImpairment) as info:
        table.offer(0, 1, "m")
    assert info.value.field == "stamp_step"


def test_ms_delay_with_injected_clock():
    clock = FakeClock(100.0)
    table = LinkImpairments(clock=clock)
    table.set(("a", "b"), delay_ms=50)
    d = table.offer("a", "b", "m1")
    assert d == (HOLD, None, pytest.approx(100.05))
    table.offer("a", "b", "m2", arrival=100.01)
    clock.t = 100.049
    assert table.release() == []
    clock.t = 100.05
    assert table.release() == [("a", "b", "m1")]
    assert table.release(now_time=100.07) == [("a", "b", "m2")]
    assert table.held == 0


def test_jitter_is_bounded_and_deterministic():
    def run(seed):
        table = LinkImpairments(seed=seed, clock=FakeClock())
        table.set((0, 1), delay_ms=10, jitter_ms=5)
        return [table.offer(0, 1, i, arrival=float(i)).due_time - i for i in range(200)]

    delays = run(7)
    assert all(0.010 <= d <= 0.015 + 1e-12 for d in delays)
    assert delays == run(7)
    assert delays != run(8)


def test_links_have_independent_streams():
    def outcomes(interleave):
        table = LinkImpairments(seed=3)
        table.set((0, 1), drop=0.5)
        table.set((2, 1), drop=0.5)
        out = []
        for _ in range(200):
            out.append(table.offer(0, 1, None).action)
            if interleave:
                table.offer(2, 1, None)
        return out

    assert outcomes(False) == outcomes(True)


@given(
    delay_steps=st.integers(0, 5),
    delay_ms=st.floats(0, 100),
    jitter_ms=st.floats(0, 50),
    arrivals=st.lists(st.tuples(st.integers(0, 50), st.floats(0, 10)), max_size=60),
    seed=st.integers(0, 2**32),
)
@DETERMINISTIC
def test_no_loss_without_drop_or_partition(delay_steps, delay_ms, jitter_ms, arrivals, seed):
    table = LinkImpairments(seed=seed, clock=FakeClock())
    table.set((0, 1), delay_steps=delay_steps, delay_ms=delay_ms, jitter_ms=jitter_ms)
    delivered = []
    for i, (stamp, t) in enumerate(arrivals):
        d = table.offer(0, 1, i, stamp_step=stamp, arrival=t)
        assert d.action in (DELIVER, HOLD)
        if d.action == DELIVER:
            delivered.append(i)
    delivered += [m for _, _, m in table.release(now_step=10**6, now_time=math.inf)]
    assert sorted(delivered) == list(range(len(arrivals)))
    assert table.held == 0


@given(
    d=st.integers(1, 6),
    lags=st.lists(st.integers(0, 5), min_size=1, max_size=40),
    seed=st.integers(0, 1000),
)
@DETERMINISTIC
def test_step_delay_releases_exactly_at_stamp_plus_d(d, lags, seed):
    """Message i is stamped at step i and arrives at step i + lag (lag < d)."""
    table = LinkImpairments(seed=seed)
    table.set((0, 1), delay_steps=d)
    arrivals = {}
    for i, lag in enumerate(lags):
        arrivals.setdefault(i + min(lag, d - 1), []).append(i)
    released_at = {}
    for step in range(len(lags) + d + 1):
        for i in arrivals.get(step, []):
            assert table.offer(0, 1, i, stamp_step=i) == (HOLD, i + d, None)
        out = table.release(now_step=step)
        assert [m for _, _, m in out] == sorted(m for _, _, m in out)  # in stamp order
        for _, _, i in out:
            released_at[i] = step
    assert released_at == {i: i + d for i in range(len(lags))}


@given(n=st.integers(1, 300), seed=st.integers(0, 2**32), drop=st.floats(0, 1), delay=st.integers(0, 3))
@DETERMINISTIC
def test_partition_drops_everything(n, seed, drop, delay):
    table = LinkImpairments(seed=seed)
    table.set((5, 6), partition=True, drop=drop, delay_steps=delay)
    assert all(table.offer(5, 6, i, stamp_step=i).action == DROP for i in range(n))
    assert table.release(now_step=10**6) == []
    assert table.offer(6, 5, "other direction").action == DELIVER


@given(p=st.sampled_from([0.0, 0.01, 0.1, 0.3, 0.5, 0.9, 1.0]), seed=st.integers(0, 2**32))
@settings(derandomize=True, deadline=None, max_examples=15)
def test_bernoulli_drop_rate(p, seed):
    n = 20_000
    table = LinkImpairments(seed=seed)
    table.set((0, 1), drop=p)
    drops = sum(table.offer(0, 1, None).action == DROP for _ in range(n))
    tol = 5 * math.sqrt(p * (1 - p) / n) + 1e-9
    assert abs(drops / n - p) <= tol


def burst_lengths(actions):
    runs, current = [], 0
    for a in actions:
        if a == DROP:
            current += 1
        elif current:
            runs.append(current)
            current = 0
    return runs


@given(p=st.sampled_from([0.05, 0.1, 0.2]), burst=st.sampled_from([1.0, 2.0, 4.0, 8.0]),
       seed=st.integers(0, 2**32))
@settings(derandomize=True, deadline=None, max_examples=8)
def test_gilbert_elliott_mean_burst_and_rate(p, burst, seed):
    n = 100_000
    table = LinkImpairments(seed=seed)
    table.set((0, 1), drop=p, burst=burst)
    actions = [table.offer(0, 1, None).action for _ in range(n)]
    runs = burst_lengths(actions)
    mean_burst = sum(runs) / len(runs)
    assert abs(mean_burst - burst) <= 0.1 * burst
    assert abs(actions.count(DROP) / n - p) <= 0.2 * p


def test_bursty_differs_from_bernoulli():
    """Same drop rate, but GE bursts are much longer than Bernoulli runs."""
    def mean_run(**params):
        table = LinkImpairments(seed=11)
        table.set((0, 1), **params)
        runs = burst_lengths([table.offer(0, 1, None).action for _ in range(50_000)])
        return sum(runs) / len(runs)

    assert mean_run(drop=0.1) < 1.5
    assert mean_run(drop=0.1, burst=6) > 4


# -- impairment messages ----------------------------------------------------


def test_impairment_message_round_trip_and_apply():
    table = LinkImpairments()
    apply_impairment_message(table, decode_impairment(encode_impairment("set", 0, 3, delay_steps=2)))
    apply_impairment_message(table, decode_impairment(encode_impairment("set", 0, 3, drop=0.2, burst=3.0)))
    apply_impairment_message(table, decode_impairment(encode_impairment("set", "world", 3, partition=True)))
    assert table.get((0, 3)) == LinkParams(delay_steps=2, drop=0.2, burst=3.0)
    assert table.get(("world", 3)).partition
    apply_impairment_message(table, decode_impairment(encode_impairment("clear", 0, 3)))
    assert table.get((0, 3)).is_identity
    apply_impairment_message(table, decode_impairment(encode_impairment("clear_all")))
    assert table.links() == {}


def test_delay_ms_int_becomes_float():
    msg = decode_impairment(encode_impairment("set", 1, 2, delay_ms=20, jitter_ms=5))
    assert msg["delay_ms"] == 20.0 and isinstance(msg["delay_ms"], float)


@pytest.mark.parametrize("msg, reason, field", [
    ({"kind": "impair", "op": "set", "dst": 1, "drop": 0.1}, "missing", "src"),
    ({"kind": "impair", "op": "clear", "src": 1}, "missing", "dst"),
    ({"kind": "impair", "op": "clear", "src": 1, "dst": 2, "drop": 0.1}, "extra", "drop"),
    ({"kind": "impair", "op": "clear_all", "partition": True}, "extra", "partition"),
    ({"kind": "impair", "op": "explode", "src": 1, "dst": 2}, "range", "op"),
    ({"kind": "est", "op": "set", "src": 1, "dst": 2}, "range", "kind"),
    ({"kind": "impair", "op": "set", "src": 1, "dst": 2, "drop": 1.5}, "range", "drop"),
    ({"kind": "impair", "op": "set", "src": 1, "dst": 2, "drop": 0.9, "burst": 2.0}, "range", "burst"),
    ({"kind": "impair", "op": "set", "src": 1, "dst": 2, "delay_steps": -1}, "range", "delay_steps"),
    ({"kind": "impair", "op": "set", "src": 1, "dst": 2, "partition": "yes"}, "type", "partition"),
    ({"kind": "impair", "op": "set", "src": 1.5, "dst": 2}, "type", "src"),
    ({"kind": "impair", "op": "set", "src": 1, "dst": 2, "mtu": 3}, "extra", "mtu"),
])
def test_bad_impairment_messages(msg, reason, field):
    with pytest.raises(MalformedMessage) as info:
        decode_impairment(encode(msg))
    assert (info.value.reason, info.value.field) == (reason, field)


def test_encode_impairment_fails_at_sender():
    with pytest.raises(MalformedMessage):
        encode_impairment("set", 0, 1, drop=2.0)
    with pytest.raises(MalformedMessage):
        encode_impairment("clear")


@given(st.binary(max_size=200))
@settings(deadline=None)
def test_random_impairment_payloads_only_raise_malformed(data):
    try:
        decode_impairment(data)
    except MalformedMessage:
        pass


def test_apply_incompatible_merge_raises_and_keeps_table():
    table = LinkImpairments()
    table.set((0, 1), burst=2.0, drop=0.3)
    msg = decode_impairment(encode_impairment("set", 0, 1, drop=0.8))  # valid alone
    with pytest.raises(InvalidImpairment):
        apply_impairment_message(table, msg)
    assert table.get((0, 1)) == LinkParams(burst=2.0, drop=0.3)
