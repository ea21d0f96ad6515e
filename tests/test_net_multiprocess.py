"""Multi-process tests: real zenoh peers on loopback, one per OS process.

Every wait has a generous deadline (the machine is small and shared); no
test asserts on timing. Children run in their own process group, which is
always killed at teardown.
"""

import functools
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from agent.protocol import topics
from broker_free_net.codec import MessageStats, decode, encode, try_decode
from broker_free_net.config import NetConfig
from broker_free_net.ports import listen_port
from tests import waiting

pytestmark = pytest.mark.multiprocess

ROOT = Path(__file__).resolve().parents[1]
ECHO = Path(__file__).with_name("net_echo_peer.py")
sys.path.insert(0, str(Path(__file__).parent))
from net_echo_peer import REPLY, REQUEST  # noqa: E402

DEADLINE = 20.0  # seconds; generous for a loaded 2-core machine
wait_until = functools.partial(waiting.wait_until, timeout=DEADLINE)


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"




@pytest.fixture
def run_id():
    return f"t{os.getpid()}x{random.randrange(10**9)}"


@pytest.fixture
def spawn(run_id):
    """Start echo peers; kill their process groups at teardown."""
    procs = []

    def start(id_, connect=()):
        port = listen_port()
        cmd = [sys.executable, str(ECHO), "--run", run_id, "--id", str(id_), "--listen", endpoint(port)]
        for ep in connect:
            cmd += ["--connect", ep]
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        proc = subprocess.Popen(cmd, env=env, cwd=ROOT, start_new_session=True,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        procs.append(proc)
        return proc, endpoint(port)

    yield start
    for proc in procs:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait(timeout=DEADLINE)
        if proc.stderr:
            proc.stderr.close()


def handshake(peer, inbox, run, id_, timeout=DEADLINE):
    """Ping until the echo answers: routes are declared both ways afterwards."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        peer.put(topics.ctl_key(run, id_), encode({"seq": 0}))
        item = inbox.get(timeout=0.25)
        if item is not None:
            inbox.drain()
            return decode(item.payload, REPLY)
    raise AssertionError(f"echo peer {id_} never answered")


def test_echo_round_trip(spawn, run_id):
    _, ep = spawn(1)
    with topics.open_peer(NetConfig(run=run_id, connect=(ep,)), "monitor", 0) as me:
        inbox = me.subscribe(topics.status_key(run_id, 1))
        me.publisher(topics.ctl_key(run_id, 1), block=True)
        assert me.wait_for_peers(lambda alive: ("echo", "1") in alive, DEADLINE)
        handshake(me, inbox, run_id, 1)
        n = 300
        xs = [np.random.default_rng(i).normal(size=14) for i in range(n)]
        for i, x in enumerate(xs, start=1):
            me.put(topics.ctl_key(run_id, 1), encode({"seq": i, "x": x}))
        replies = []
        assert wait_until(lambda: replies.extend(inbox.drain()) or len(replies) >= n), len(replies)
        msgs = [decode(r.payload, REPLY, senders={1}) for r in replies]
        assert [m["seq"] for m in msgs] == list(range(1, n + 1))  # in order, none lost
        for m, x in zip(msgs, xs):
            np.testing.assert_array_equal(m["x"], x)
        assert all(r.key == topics.status_key(run_id, 1) for r in replies)
        assert inbox.overflows == 0


def test_malformed_flood_is_counted_and_good_message_gets_through(spawn, run_id):
    _, ep = spawn(1)
    with topics.open_peer(NetConfig(run=run_id, connect=(ep,)), "monitor", 0) as me:
        inbox = me.subscribe(topics.status_key(run_id, 1))
        key = topics.ctl_key(run_id, 1)
        me.publisher(key, block=True)
        first = handshake(me, inbox, run_id, 1)
        rng = random.Random(1)
        bad = [
            lambda: rng.randbytes(rng.randrange(0, 64)),
            lambda: b"\xc1",
            lambda: encode({"seq": -5}),
            lambda: encode({"seq": 1, "x": np.array([np.nan])}),
            lambda: encode({"seq": 1, "bogus": 1}),
            lambda: b"\xc6\xff\xff\xff\xf0",  # bin32 header claiming 4 GiB
            lambda: b"\x91" * 3000,  # deep nesting
        ]
        n_bad = 1000
        for i in range(n_bad):
            payload = bad[i % len(bad)]()
            if try_decode(payload, REQUEST, MessageStats()) is not None:
                payload = b"\xc1"  # random bytes that happen to be valid (never in practice)
            me.put(key, payload)
        me.put(key, encode({"seq": 7}))
        item = inbox.get(timeout=DEADLINE)
        assert item is not None
        reply = decode(item.payload, REPLY)
        assert reply["seq"] == 7
        assert reply["dropped"] == n_bad
        assert reply["accepted"] == first["accepted"] + 1


def test_sigkill_withdraws_liveliness(spawn, run_id):
    proc, ep = spawn(1)
    with topics.open_peer(NetConfig(run=run_id, connect=(ep,)), "monitor", 0) as me:
        watch = me.watch_liveliness()
        assert watch.wait_until(lambda alive: ("echo", "1") in alive, DEADLINE)
        assert ("monitor", "0") in watch.alive()  # own token, through history
        os.killpg(proc.pid, signal.SIGKILL)
        assert watch.wait_until(lambda alive: ("echo", "1") not in alive, 10.0)
        events = [(e.role, e.id, e.alive) for e in watch.drain()]
        assert ("echo", "1", True) in events
        assert events.index(("echo", "1", False)) > events.index(("echo", "1", True))


def test_hung_peer_expires_by_lease(spawn, run_id):
    """SIGSTOP keeps the socket open: only the link lease (1 s) can detect it."""
    proc, ep = spawn(1)
    with topics.open_peer(NetConfig(run=run_id, connect=(ep,)), "monitor", 0) as me:
        assert me.wait_for_peers(lambda alive: ("echo", "1") in alive, DEADLINE)
        os.killpg(proc.pid, signal.SIGSTOP)
        try:
            assert me.wait_for_peers(lambda alive: ("echo", "1") not in alive, 10.0)
        finally:
            # A stopped peer stalls the reconnect handshake, and with it
            # session.close() for ~10 s (eclipse-zenoh/zenoh#2675).
            os.killpg(proc.pid, signal.SIGKILL)


def test_gossip_finds_peers_through_one_seed(spawn, run_id):
    _, seed = spawn(1)
    spawn(2, connect=(seed,))
    with topics.open_peer(NetConfig(run=run_id, connect=(seed,)), "monitor", 0) as me:
        inbox = me.subscribe(topics.any_agent_pattern(run_id, "status"))
        assert me.wait_for_peers(lambda alive: {("echo", "1"), ("echo", "2")} <= alive, DEADLINE)
        assert handshake(me, inbox, run_id, 2)["from"] == 2
        assert wait_until(lambda: len(me.connected_peers()) == 2)


def test_peer_close_is_idempotent_and_withdraws_token(run_id):
    port = listen_port()
    a = topics.open_peer(NetConfig(run=run_id, listen=(endpoint(port),)), "agent", 0)
    with topics.open_peer(NetConfig(run=run_id, connect=(endpoint(port),)), "agent", 1) as b:
        assert b.wait_for_peers(lambda alive: ("agent", "0") in alive, DEADLINE)
        a.close()
        a.close()
        assert a.closed
        with pytest.raises(RuntimeError):
            a.put(topics.est_key(run_id, 0), b"x")
        with pytest.raises(ValueError):
            b.publisher(topics.est_key(run_id, 1), block=True)
            b.publisher(topics.est_key(run_id, 1), block=False)
        assert b.wait_for_peers(lambda alive: ("agent", "0") not in alive, DEADLINE)
