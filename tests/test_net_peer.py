"""In-process tests of Inbox and Peer (no child processes)."""

import threading
import time

import pytest

from agent.protocol import topics
from broker_free_net.config import NetConfig
from broker_free_net.keys import InvalidKey
from broker_free_net.peer import Inbox, LivelinessWatch, Peer, Received
from broker_free_net.ports import listen_port


def test_inbox_drop_oldest_and_counters():
    wake = threading.Event()
    inbox = Inbox(maxlen=3, wakeup=wake)
    assert inbox.poll() is None and inbox.get(timeout=0.01) is None
    for i in range(5):
        inbox._push(Received(bytes([i]), "k", float(i)))
    assert wake.is_set()
    assert len(inbox) == 3 and inbox.received == 5 and inbox.overflows == 2
    assert inbox.poll().payload == b"\x02"
    assert [r.payload for r in inbox.drain()] == [b"\x03", b"\x04"]
    assert inbox.drain() == []


def test_inbox_get_wakes_on_push():
    inbox = Inbox()
    timer = threading.Timer(0.05, inbox._push, args=(Received(b"x", "k", 0.0),))
    timer.start()
    try:
        assert inbox.get(timeout=30).payload == b"x"
    finally:
        timer.cancel()


def test_inbox_rejects_bad_maxlen():
    with pytest.raises(ValueError):
        Inbox(0)


class FakeSample:
    def __init__(self, key, kind):
        self.key_expr = key
        self.kind = kind


def test_liveliness_watch_tracks_alive_and_ignores_bad_keys():
    import zenoh

    watch = LivelinessWatch("socmon/r/alive")
    watch._on_sample(FakeSample("socmon/r/alive/agent/1/za", zenoh.SampleKind.PUT))
    watch._on_sample(FakeSample("socmon/r/alive/world/w/zw", zenoh.SampleKind.PUT))
    watch._on_sample(FakeSample("socmon/r/alive/agent/1", zenoh.SampleKind.PUT))
    watch._on_sample(FakeSample("socmon/r/alive/agent/1/za", zenoh.SampleKind.DELETE))
    assert watch.alive() == {("world", "w")}
    assert watch.ignored == 1
    assert [(e.role, e.id, e.alive, e.any_alive) for e in watch.drain()] == [
        ("agent", "1", True, True), ("world", "w", True, True), ("agent", "1", False, False)]
    assert watch.wait_until(lambda alive: ("world", "w") in alive, 0.01)
    assert not watch.wait_until(lambda alive: ("agent", "1") in alive, 0.01)


def test_liveliness_watch_sees_two_sessions_claiming_one_id():
    """zenoh aggregates the tokens of one key; with the session in the key, a second
    process claiming agent 1 is a second token, and the first one's end is seen."""
    import zenoh

    watch = LivelinessWatch("socmon/r/alive")
    watch._on_sample(FakeSample("socmon/r/alive/agent/1/za", zenoh.SampleKind.PUT))
    watch._on_sample(FakeSample("socmon/r/alive/agent/1/zb", zenoh.SampleKind.PUT))
    watch._on_sample(FakeSample("socmon/r/alive/agent/1/za", zenoh.SampleKind.DELETE))
    events = watch.drain()
    assert [(e.session, e.alive, e.sessions) for e in events] == [
        ("za", True, {"za"}), ("zb", True, {"za", "zb"}), ("za", False, {"zb"})]
    assert watch.alive() == {("agent", "1")} and watch.sessions("agent", 1) == {"zb"}
    for k in range(100):                   # made-up sessions for one id: bounded
        watch._on_sample(FakeSample(f"socmon/r/alive/agent/1/f{k}", zenoh.SampleKind.PUT))
    assert len(watch.sessions("agent", 1)) == 16 and watch.ignored == 85


def test_peer_rejects_bad_role_and_config():
    with pytest.raises(TypeError):
        Peer({"run": "r"}, "agent", 0, alive_prefix="socmon/r/alive")
    with pytest.raises(InvalidKey):
        Peer(NetConfig(), "a/b", 0, alive_prefix="socmon/default/alive")


def wait_for_item(inbox, predicate, timeout=20):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        item = inbox.get(timeout=0.2)
        if item is not None and predicate(item):
            return True
    return False


def test_two_peers_in_one_process_wait_and_drain():
    run = f"inproc{listen_port()}"
    port = listen_port()
    with topics.open_peer(NetConfig(run=run, listen=(f"tcp/127.0.0.1:{port}",)), "agent", 0) as a, \
            topics.open_peer(NetConfig(run=run, connect=(f"tcp/127.0.0.1:{port}",)), "agent", 1) as b:
        inbox = b.subscribe(topics.any_agent_pattern(run, "est"))
        remote_only = b.subscribe(topics.any_agent_pattern(run, "est"), include_local=False)
        assert b.wait_for_peers(lambda alive: {("agent", "0"), ("agent", "1")} <= alive, 20)
        deadline = time.monotonic() + 20
        got, remote = [], []
        # until both subscriptions have heard a (seen once on a loaded machine: the
        # first put reached one of them and not the other)
        while not (got and remote) and time.monotonic() < deadline:
            a.put(topics.est_key(run, 0), b"hello")
            b.wait(timeout=0.2)
            got += inbox.drain()
            remote += remote_only.drain()
        assert got and got[0].payload == b"hello" and got[0].key == topics.est_key(run, 0)
        assert topics.parse_agent_key(run, "est", got[0].key) == 0
        assert a.zid() != b.zid()
        b.put(topics.est_key(run, 1), b"own")
        assert wait_for_item(inbox, lambda r: r.payload == b"own")  # local delivery
        # the local put reached `inbox`, and not the remote-only subscription
        assert {r.payload for r in remote + remote_only.drain()} == {b"hello"}
    assert a.closed and b.closed


def test_a_second_session_of_one_id_is_refused_until_the_first_lets_go():
    """``Peer.claim``: a process whose (role, id) another session holds waits for it to
    go, then is refused naming it; once the first closes, a new one of that id is
    accepted; another id is never in the way."""
    from broker_free_net.peer import IdInUse

    run = f"claim{listen_port()}"
    port = listen_port()
    said = []
    with topics.open_peer(NetConfig(run=run, listen=(f"tcp/127.0.0.1:{port}",)),
                          "agent", 3) as first:
        first.claim(wait_s=0.2)                 # alone: after waiting for a link in vain
        join = NetConfig(run=run, connect=(f"tcp/127.0.0.1:{port}",))
        with topics.open_peer(join, "agent", 4) as other:
            assert other.other_holders(timeout=2.0) == frozenset()
            other.claim(wait_s=0.0)
        with topics.open_peer(join, "agent", 3) as second:
            assert wait_until(lambda: first.zid() in second.other_holders(timeout=2.0), 20)
            t0 = time.monotonic()
            with pytest.raises(IdInUse, match=f"agent 3 of run {run} is already running "
                                              f"\\(session {first.zid()} holds"):
                second.claim(wait_s=0.3, say=said.append)
            assert time.monotonic() - t0 >= 0.3        # it waited for the first to go
            assert said == [f"another session ({first.zid()}) holds the token of agent 3; "
                            "waiting up to 0.3 s for it to go (a process just stopped holds "
                            "it for its lease)"]
            assert second.zid() in first.other_holders(timeout=2.0)
    with topics.open_peer(NetConfig(run=run, listen=(f"tcp/127.0.0.1:{port}",)),
                          "agent", 3) as again:
        again.claim(wait_s=0.0)


def wait_until(predicate, timeout):
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def _linger_of_links(port):
    """SO_LINGER on/off of this process's TCP sockets with `port` at either end."""
    import os
    import socket
    import struct

    found = []
    for name in os.listdir("/proc/self/fd"):
        try:
            s = socket.socket(fileno=os.dup(int(name)))
        except OSError:
            continue
        with s:
            if s.family != socket.AF_INET or s.type != socket.SOCK_STREAM:
                continue
            try:
                ends = {s.getsockname()[1], s.getpeername()[1]}
            except OSError:                # the listener: no peer
                continue
            if port in ends:
                found.append(struct.unpack("ii", s.getsockopt(
                    socket.SOL_SOCKET, socket.SO_LINGER, 8))[0])
    return found


@pytest.mark.skipif(not __import__("os").path.isdir("/proc/self/fd"), reason="needs /proc")
def test_links_do_not_linger_on_close():
    """zenoh opens its TCP links with SO_LINGER 10 s (a close() then sleeps until a cut-off
    host acknowledges); the peer turns it off on its links, the one zenoh opened and the
    one it accepted, within a scan period."""
    run = f"linger{listen_port()}"
    port = listen_port()
    with topics.open_peer(NetConfig(run=run, listen=(f"tcp/127.0.0.1:{port}",)), "agent", 0), \
            topics.open_peer(NetConfig(run=run, connect=(f"tcp/127.0.0.1:{port}",)), "agent", 1) as b:
        assert b.wait_for_peers(lambda alive: ("agent", "0") in alive, 20)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            states = _linger_of_links(port)
            if len(states) >= 2 and not any(states):
                break
            time.sleep(0.05)
        assert len(states) >= 2 and not any(states), states


@pytest.mark.skipif(not __import__("os").path.isdir("/proc/self/fd"), reason="needs /proc")
def test_the_linger_guard_finds_sockets_opened_after_it_started():
    import socket
    import struct

    from broker_free_net.linger import LingerGuard

    guard = LingerGuard(period=0.02)
    try:
        with socket.socket() as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 10))
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline and guard.cleared == 0:
                time.sleep(0.02)
            onoff, _ = struct.unpack("ii", s.getsockopt(socket.SOL_SOCKET, socket.SO_LINGER, 8))
            assert onoff == 0
        with socket.socket(socket.AF_UNIX) as u:    # not TCP: left alone
            before = guard.cleared
            guard.scan()
            assert guard.cleared == before and u.fileno() >= 0
    finally:
        guard.stop()


def test_start_order_does_not_matter():
    """A peer whose seed is not up yet keeps retrying and joins when it starts."""
    run = f"late{listen_port()}"
    port = listen_port()
    with topics.open_peer(NetConfig(run=run, connect=(f"tcp/127.0.0.1:{port}",)), "agent", 1) as early:
        with topics.open_peer(NetConfig(run=run, listen=(f"tcp/127.0.0.1:{port}",)), "agent", 0):
            assert early.wait_for_peers(lambda alive: ("agent", "0") in alive, 30)


def test_inbox_is_bounded_by_bytes_and_refuses_oversized_payloads():
    inbox = Inbox(maxlen=100, max_bytes=1000, max_payload=400)
    for i in range(5):
        inbox._push(Received(bytes([i]) * 300, "k", float(i)))
    # 5 x 300 bytes into 1000: the two oldest go
    assert [r.payload[0] for r in inbox.drain()] == [2, 3, 4]
    assert inbox.overflows == 2 and inbox.nbytes == 0
    inbox._push(Received(b"x" * 401, "k", 0.0))
    inbox._push(Received(b"y" * 400, "k", 0.0))
    assert inbox.oversized == 1 and len(inbox) == 1 and inbox.nbytes == 400
    assert inbox.poll().payload == b"y" * 400 and inbox.nbytes == 0
    # count bound still applies to tiny items
    small = Inbox(maxlen=3, max_bytes=1 << 20)
    for i in range(10):
        small._push(Received(b"z", "k", 0.0))
    assert len(small) == 3 and small.overflows == 7 and small.nbytes == 3


@pytest.mark.parametrize("kwargs, field", [
    ({"max_bytes": 0}, "max_bytes"), ({"max_payload": -1}, "max_payload"),
    ({"max_bytes": 10, "max_payload": 11}, "max_bytes"), ({"max_bytes": True}, "max_bytes")])
def test_inbox_rejects_bad_bounds(kwargs, field):
    with pytest.raises(ValueError, match=field):
        Inbox(**kwargs)


def test_payloads_over_the_limit_are_not_delivered():
    """Messages over MAX_PAYLOAD_BYTES never reach an inbox (refused before the copy)."""
    from broker_free_net.codec import MAX_PAYLOAD_BYTES

    run = f"big{listen_port()}"
    port = listen_port()
    with topics.open_peer(NetConfig(run=run, listen=(f"tcp/127.0.0.1:{port}",)), "agent", 0) as a, \
            topics.open_peer(NetConfig(run=run, connect=(f"tcp/127.0.0.1:{port}",)), "agent", 1) as b:
        inbox = b.subscribe(topics.est_key(run, 0), include_local=False)
        assert b.wait_for_peers(lambda alive: ("agent", "0") in alive, 20)
        key = topics.est_key(run, 0)
        a.publisher(key, block=True)
        got = []
        deadline = time.monotonic() + 20
        while not any(r.payload == b"ready" for r in got) and time.monotonic() < deadline:
            a.put(key, b"ready")  # the route exists once one small message went through
            b.wait(timeout=0.2)
            got += inbox.drain()
        assert got, "no route from a to b"
        sizes = [MAX_PAYLOAD_BYTES + 1, MAX_PAYLOAD_BYTES + 4096, 3 * MAX_PAYLOAD_BYTES // 2]
        for size in sizes * 4:
            a.put(key, b"\x00" * size)
        a.put(key, b"end")  # same publisher, same key: arrives after the big ones
        after = []
        while not any(r.payload == b"end" for r in after) and time.monotonic() < deadline + 20:
            b.wait(timeout=0.2)
            after += inbox.drain()
        assert [r.payload for r in after if r.payload != b"ready"] == [b"end"]
        # zenoh's max_message_size drops them before any callback (through shared memory,
        # now off, they used to bypass it and reached the inbox, which refused them)
        assert inbox.oversized == 0


def test_publisher_latency_options_are_checked_and_delivered():
    """An express, high-priority publisher delivers; an unknown priority is refused."""
    run = f"prio{listen_port()}"
    port = listen_port()
    with topics.open_peer(NetConfig(run=run, listen=(f"tcp/127.0.0.1:{port}",)), "agent", 0) as a, \
            topics.open_peer(NetConfig(run=run, connect=(f"tcp/127.0.0.1:{port}",)), "agent", 1) as b:
        key = topics.est_key(run, 0)
        with pytest.raises(ValueError, match="priority"):
            a.publisher(topics.status_key(run, 0), priority="URGENT")
        inbox = b.subscribe(key, include_local=False)
        assert b.wait_for_peers(lambda alive: ("agent", "0") in alive, 20)
        a.publisher(key, express=True, priority="DATA_HIGH")
        got = []
        deadline = time.monotonic() + 20
        while not got and time.monotonic() < deadline:
            a.put(key, b"x")
            b.wait(timeout=0.2)
            got += inbox.drain()
        assert got and got[0].payload == b"x" and got[0].key == key


def test_inbox_wakes_only_for_the_items_asked_for():
    """Items are always queued; only those asked for set the wake-up event."""
    event = threading.Event()
    inbox = Inbox(wakeup=event)
    inbox._push(Received(b"1", "k/a", 0.0))
    assert event.is_set()
    event.clear()
    inbox.wakes = False
    inbox._push(Received(b"2", "k/a", 0.0))
    assert not event.is_set()
    inbox.wakes = frozenset({"k/b"})
    inbox._push(Received(b"3", "k/a", 0.0))
    assert not event.is_set()
    inbox._push(Received(b"4", "k/b", 0.0))
    assert event.is_set()
    assert [r.payload for r in inbox.drain()] == [b"1", b"2", b"3", b"4"]


def test_a_key_set_inbox_follows_its_keys_and_gets_a_late_publishers_cache():
    """An agent's estimate subscriptions (agent.node.subscriptions): a key subscribed late
    with history gets the publisher's cached samples in order, then the live ones; a key
    dropped from the set is no longer delivered; the pattern of a standby hears all."""
    run = f"keyset{listen_port()}"
    port = listen_port()
    with topics.open_peer(NetConfig(run=run, listen=(f"tcp/127.0.0.1:{port}",)), "agent", 1) as a, \
            topics.open_peer(NetConfig(run=run, connect=(f"tcp/127.0.0.1:{port}",)), "agent", 2) as b:
        assert b.wait_for_peers(lambda alive: {("agent", "1"), ("agent", "2")} <= alive, 20)
        k1, k2 = topics.est_key(run, 1), topics.est_key(run, 2)
        a.publisher(k1, cache=4)
        # first without history, until a live sample shows that b knows a's publisher
        inbox = b.subscribe_keys([k1], include_local=False)
        assert inbox.keys == {k1: 0}
        deadline = time.monotonic() + 20
        while not inbox.drain() and time.monotonic() < deadline:
            a.put(k1, b"ping")
            b.wait(timeout=0.2)
        for i in range(6):
            a.put(k1, bytes([i]))
        assert wait_for_item(inbox, lambda r: r.payload == b"\x05")
        inbox.drain()
        # the same key with history: declared again, the cache's samples come
        assert inbox.follow({k1: 4}) == ((k1,), ())
        assert inbox.keys == {k1: 4}
        got = []
        deadline = time.monotonic() + 20
        while b"\x05" not in got and time.monotonic() < deadline:
            item = inbox.get(timeout=0.2)
            if item is not None:
                got.append(item.payload)
        # the cache's last 4, oldest first
        assert got == [b"\x02", b"\x03", b"\x04", b"\x05"], got
        # live samples after it
        deadline = time.monotonic() + 20
        live = []
        while b"\x06" not in live and time.monotonic() < deadline:
            a.put(k1, b"\x06")
            b.wait(timeout=0.2)
            live += [r.payload for r in inbox.drain()]
        assert b"\x06" in live
        # a standby's pattern instead: a's other key is heard, k1 still, b's own is not
        added, removed = inbox.follow(topics.estimate_subscriptions(run, None, 4))
        assert added == (topics.any_agent_pattern(run, "est"),) and removed == (k1,)
        b.put(k2, b"own")
        heard = set()
        deadline = time.monotonic() + 20
        while b"x" not in heard and time.monotonic() < deadline:
            a.put(k1, b"x")
            b.wait(timeout=0.2)
            heard |= {r.payload for r in inbox.drain()}
        assert b"x" in heard and b"own" not in heard
        # back to no key at all: nothing more is delivered
        inbox.follow({})
        assert inbox.keys == {}
        inbox.drain()
        a.put(k1, b"late")       # (an "x" sent before may still be on its way)
        assert not wait_for_item(inbox, lambda r: r.payload == b"late", timeout=0.5)
        with pytest.raises(ValueError, match="history"):
            inbox.follow({k1: -1})
