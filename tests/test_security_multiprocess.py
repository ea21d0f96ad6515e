"""Multi-process tests of the secure mode: real zenoh peers over loopback TLS.

One secured peer runs as a child process (tests/net_secure_peer.py, in its own process
group, always killed at teardown) and reports every sample and liveliness token it lets
through; the test process plays the legitimate processes, an insider holding agent 2's
credentials, and outsiders. Every wait has a deadline; nothing asserts on timing.
"""

import functools
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from broker_free_net.ports import listen_port
from tests import waiting
from broker_free_net.config import NetConfig, build_zenoh_config
from agent.protocol.topics import open_peer
from agent.protocol.topics import make_run_keys, run_identities

pytestmark = pytest.mark.multiprocess

ROOT = Path(__file__).resolve().parents[1]
CHILD = Path(__file__).with_name("net_secure_peer.py")
DEADLINE = 20.0
wait_until = functools.partial(waiting.wait_until, timeout=DEADLINE)
#: connect timeout of the outsiders' sessions (the fragment's own is 10 s)
OUTSIDER_TIMEOUT_MS = 1500


class Child:
    """A secured peer process whose stdout lines are collected by a thread."""

    def __init__(self, cmd):
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        self.proc = subprocess.Popen(cmd, env=env, cwd=ROOT, start_new_session=True, text=True,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        self.lines: list[str] = []
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self):
        for line in self.proc.stdout:
            with self._lock:
                self.lines.append(line.rstrip("\n"))

    def snapshot(self) -> list[str]:
        with self._lock:
            return list(self.lines)

    def wait_for(self, predicate, timeout=DEADLINE) -> list[str]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            lines = self.snapshot()
            if predicate(lines):
                return lines
            if self.proc.poll() is not None:
                break
            time.sleep(0.02)
        err = self.proc.stderr.read() if self.proc.poll() is not None else ""
        raise AssertionError(f"condition not met; child said {self.snapshot()[-20:]} {err[-2000:]}")

    def kill(self):
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.proc.wait(timeout=DEADLINE)
        self._thread.join(timeout=DEADLINE)
        for f in (self.proc.stdout, self.proc.stderr):
            f.close()


def received(lines, key):
    """Payloads (ints) the child received on `key`."""
    return [int(line.split()[2]) for line in lines if line.startswith(f"got {key} ")]


@pytest.fixture
def run_id():
    return f"s{os.getpid()}x{time.monotonic_ns() % 10**9}"


@pytest.fixture
def keyset(tmp_path, run_id):
    return make_run_keys(tmp_path / "keys", run_id, run_identities(3))


@pytest.fixture
def child(keyset, run_id):
    """Agent 1, secured, listening on a fresh TLS port; puts est/1 (its own) and est/2 (not)."""
    ep = f"tls/127.0.0.1:{listen_port()}"
    c = Child([sys.executable, str(CHILD), "--keys", str(keyset.dir), "--identity", "agent-1",
               "--run", run_id, "--listen", ep,
               "--put", f"socmon/{run_id}/est/1", "--put", f"socmon/{run_id}/est/2"])
    try:
        c.wait_for(lambda lines: "ready" in lines)
        yield c, ep
    finally:
        c.kill()


def secure(keyset, run_id, identity, ep):
    return NetConfig(run=run_id, listen=(f"tls/127.0.0.1:{listen_port()}",), connect=(ep,),
                     keys=keyset.dir, identity=identity)


def test_insider_with_agent2_credentials_cannot_speak_for_others(child, keyset, run_id):
    proc, ep = child
    p = f"socmon/{run_id}"
    forbidden = [f"{p}/est/1", f"{p}/status/1", f"{p}/ctl/1", f"{p}/ctl/0", f"{p}/ctl/2",
                 f"{p}/sensors", f"{p}/truth", f"{p}/impair", f"{p}/monitor/1"]
    allowed = [f"{p}/status/2", f"{p}/est/2"]  # est/2 last: the marker of a round
    with open_peer(secure(keyset, run_id, "agent-2", ep), "agent", 2) as insider:
        mine = insider.subscribe(f"{p}/**", maxlen=1 << 16, include_local=False)
        # a liveliness token in another agent's name, on the same link before the puts
        forged_token = insider.session.liveliness().declare_token(f"{p}/alive/agent/3/{insider.zid()}")
        for key in forbidden + allowed:
            insider.publisher(key, block=True)
        rounds = 0
        deadline = time.monotonic() + DEADLINE
        while time.monotonic() < deadline:
            rounds += 1
            for key in forbidden + allowed:
                insider.put(key, str(rounds).encode())
            if len(received(proc.snapshot(), f"{p}/est/2")) >= 3:
                break
            time.sleep(0.05)
        lines = proc.wait_for(lambda lines: len(received(lines, f"{p}/est/2")) >= 3)
        # the receiving peer dropped every key agent 2 may not put, and kept the others
        for key in forbidden:
            assert received(lines, key) == [], key
        assert received(lines, f"{p}/status/2")
        assert "alive agent 2" in lines
        assert "alive agent 3" not in lines
        # the other direction: agent 1's own estimate reaches agent 2, its forged est/2 does not
        got = []
        assert wait_until(lambda: got.extend(mine.drain()) or
                     sum(r.key == f"{p}/est/1" for r in got) >= 3), got[-5:]
        assert [r for r in got if r.key == f"{p}/est/2"] == []
        forged_token.undeclare()


def test_monitor_may_command_and_operator_may_impair(child, keyset, run_id):
    proc, ep = child
    p = f"socmon/{run_id}"
    with open_peer(secure(keyset, run_id, "monitor", ep), "monitor", 1) as monitor, \
            open_peer(secure(keyset, run_id, "operator", ep), "inject", "p1") as operator:
        for peer, key in ((monitor, f"{p}/ctl/1"), (operator, f"{p}/impair")):
            peer.publisher(key, block=True)
        assert wait_until(lambda: monitor.put(f"{p}/ctl/1", b"7") or operator.put(f"{p}/impair", b"8") or
                     (received(proc.snapshot(), f"{p}/ctl/1") and received(proc.snapshot(), f"{p}/impair")))
        # the operator may not command, the monitor may not impair or estimate
        for peer, key in ((operator, f"{p}/ctl/1"), (monitor, f"{p}/impair"), (monitor, f"{p}/est/1")):
            peer.put(key, b"99")
        monitor.put(f"{p}/ctl/1", b"100")  # marker after the forbidden ones on the monitor's link
        operator.put(f"{p}/impair", b"100")
        lines = proc.wait_for(lambda lines: 100 in received(lines, f"{p}/ctl/1")
                              and 100 in received(lines, f"{p}/impair"))
        assert 99 not in received(lines, f"{p}/ctl/1")
        assert 99 not in received(lines, f"{p}/impair")
        assert 99 not in received(lines, f"{p}/est/1")
        assert "alive monitor 1" in lines and "alive inject p1" in lines


def _outsider_configs(tmp_path, keyset, run_id, ep):
    port = ep.rsplit(":", 1)[1]
    # 1. plain tcp, no credentials, to the TLS port
    plain = zenoh.Config()
    plain.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    # 2. TLS trusting the run's CA but with no client certificate
    anon = zenoh.Config()
    anon.insert_json5("connect/endpoints", json.dumps([ep]))
    anon.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(keyset.ca)))
    anon.insert_json5("transport/link/tls/verify_name_on_connect", "false")
    # 3. a complete secured config of the same run name, from another CA
    other = make_run_keys(tmp_path / "other", run_id, run_identities(3))
    foreign = build_zenoh_config(NetConfig(run=run_id, listen=(f"tls/127.0.0.1:{listen_port()}",),
                                           connect=(ep,), keys=other.dir, identity="monitor"))
    out = {"plain-tcp": plain, "tls-no-cert": anon, "other-ca": foreign}
    for conf in out.values():
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("connect/timeout_ms", str(OUTSIDER_TIMEOUT_MS))
        conf.insert_json5("connect/exit_on_failure", "true")
    return out


def test_outsiders_deliver_nothing_and_fail_loudly(child, keyset, run_id, tmp_path):
    proc, ep = child
    p = f"socmon/{run_id}"
    opened = []
    for name, conf in _outsider_configs(tmp_path, keyset, run_id, ep).items():
        try:
            session = zenoh.open(conf)
        except zenoh.ZError:
            continue  # refused at the handshake: zenoh.open fails instead of running disconnected
        opened.append(name)
        with session:
            for key in (f"{p}/est/1", f"{p}/ctl/1", f"{p}/sensors", f"{p}/impair"):
                for _ in range(20):
                    session.put(key, b"666")
    # a legitimate peer joins after the outsiders and is heard
    with open_peer(secure(keyset, run_id, "world", ep), "world", 0) as world:
        world.publisher(f"{p}/truth", block=True)
        assert wait_until(lambda: world.put(f"{p}/truth", b"5") or received(proc.snapshot(), f"{p}/truth"))
    lines = proc.snapshot()
    assert not [line for line in lines if line.startswith("got ") and line.endswith(" 666")]
    assert opened == []


def test_secure_peer_without_valid_credentials_does_not_open(child, keyset, run_id, tmp_path):
    """A secured process that cannot complete its handshake fails, it does not run alone."""
    _, ep = child
    other = make_run_keys(tmp_path / "other", run_id, run_identities(3))
    net = NetConfig(run=run_id, connect=(ep,), keys=other.dir, identity="agent-2")
    conf = build_zenoh_config(net)
    assert json.loads(conf.get_json("connect/exit_on_failure")) is True
    conf.insert_json5("connect/timeout_ms", str(OUTSIDER_TIMEOUT_MS))
    with pytest.raises(zenoh.ZError, match="connect"):
        zenoh.open(conf)


