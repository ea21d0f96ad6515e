"""Forged evidence on a live run (plain mode): statuses that speak for another agent or
carry an absurd epoch, and rosters without the run's control signature, are refused and
counted; the monitor that takes over after the active one is killed adopts the real
configuration, and a crash after it is recovered. Loopback, deadlines, ``up`` cleans up."""

import contextlib
import json
import threading
import time

import pytest

from tests.test_monitor_multiprocess import _up

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]


@contextlib.contextmanager
def _attached(tmp_path, gains, *flags, steps):
    """``socmon up`` in a thread; yields ``(run.json, alive, result)`` once the run folder
    names the run (``alive()``: the deadline not passed and ``up`` still running); the
    summary is ``result["s"]`` after the block."""
    out = tmp_path / "run"
    result = {}
    runner = threading.Thread(target=lambda: result.update(s=_up(tmp_path, gains, *flags,
                                                                 steps=steps)))
    runner.start()
    deadline = time.monotonic() + 180

    def alive():
        return time.monotonic() < deadline and runner.is_alive()

    try:
        while not (out / "run.json").is_file():
            assert alive()
            time.sleep(0.05)
        yield json.loads((out / "run.json").read_text()), alive, result
    finally:
        runner.join(timeout=300)


def _step_of(truth_in, stats, step):
    """The newest step of the truth heard (``step`` if none came within 0.5 s) and
    whether any came."""
    from agent.protocol import wire
    from broker_free_net.codec import try_decode

    item = truth_in.get(timeout=0.5)
    for it in ([item] if item else []) + truth_in.drain():
        m = try_decode(it.payload, wire.truth_schema(14), stats)
        if m is not None:
            step = max(step, m["step"])
    return step, item is not None


def _status(agent, step, epoch):
    """A status as agent ``agent`` would publish it (docs/runtime.md), forged."""
    return {"agent": agent, "step": step, "active": True, "epoch": epoch, "measure": ["7"],
            "neighbours": {2: 0.5}, "delays": {2: 1}, "drops": 0, "late": 0, "inputs": {},
            "ages": {}, "malformed": 0, "malformed_reasons": {}, "impaired": 0,
            "sensor": {"labels": ["7"], "last_step": step, "missed": 0}, "heard": [2, 3],
            "ctl": {"accepted": 1, "rejected": 0, "last_error": "", "pending": 0},
            "links": {}, "overflows": 0}


def test_forged_statuses_and_rosters_are_refused_and_a_later_crash_recovers(tmp_path,
                                                                            live_gains):
    from agent.protocol import wire
    from agent.protocol.control_auth import ControlSigner
    from agent.protocol import topics
    from broker_free_net.codec import MessageStats
    from broker_free_net.config import NetConfig

    with _attached(tmp_path, live_gains, "--fault", "monitor:250", "--kill", "450:1",
                   steps=650) as (run, alive, result):
        rid = run["run"]
        # a client: it brokers nobody's traffic (a slow peer in the mesh would)
        net = NetConfig(run=rid, mode="client", connect=(run["connect"],))
        with topics.open_peer(net, "attacker", 0) as peer:
            truth_in = peer.subscribe(topics.truth_key(rid), maxlen=64)
            roster_key = topics.ctl_key(rid, 0)
            for key in (roster_key, topics.status_key(rid, 1), topics.status_key(rid, 2)):
                peer.publisher(key)
            outsider = ControlSigner.generate()
            stats, step, sent = MessageStats(), -1, 0
            while step < 420:                          # past the monitor's kill at 250
                assert alive(), step
                step, heard = _step_of(truth_in, stats, step)
                if not heard or step % 5:
                    continue
                # agent 2's key, agent 1's name and an epoch far ahead
                peer.put(topics.status_key(rid, 2), wire.encode_status(
                    _status(1, step + 5, 2 ** 62)))
                # agent 1's own key, an epoch far ahead
                peer.put(topics.status_key(rid, 1), wire.encode_status(
                    _status(1, step, 2 ** 61)))
                # rosters: unsigned, and signed with a key that is not the run's
                peer.put(roster_key, wire.encode_roster(2 ** 62, 10 ** 6, [1, 2, 3]))
                peer.put(roster_key, wire.encode_roster(7, 10 ** 6, [2, 3, 4],
                                                        signer=outsider, run=rid))
                sent += 1
    assert sent > 20
    s = result["s"]
    assert [(f["agent"], f["cause"]) for f in s["failures"]] == [(1, "crash")], s["failures"]
    assert s["recovered"] is True and s["rosters"][-1]["ids"] == [4, 2, 3]
    assert max(r["epoch"] for r in s["rosters"]) < 64
    assert all(int(v["epoch"] or 0) < 64 for v in s["final_roles"].values())
    reasons = {(e["reason"], e["agent"]) for e in s["evidence_refused"]}
    assert {("sender", 2), ("epoch", 1), ("signature", 0)} <= reasons, reasons
    log = (tmp_path / "run" / "logs" / "monitor-2.log").read_text()
    assert "evidence refused (signature)" in log


def test_an_insider_with_agent2s_certificate_convicts_nobody(tmp_path, live_gains):
    """--secure, agent 2's own credentials: on its own key it publishes a status naming
    agent 1 (epoch 2^62), one naming agent 3 that says agent 1 is 500 steps stale, and its
    own status claiming to listen to agent 1 with the same stale age, and agent 3 (which
    it does listen to) 500 steps stale. Nothing of it is
    taken: no healthy agent is convicted and a later crash of agent 1 is recovered."""
    from agent.protocol import wire
    from agent.protocol import topics
    from broker_free_net.codec import MessageStats
    from broker_free_net.config import NetConfig

    from broker_free_net.ports import listen_port

    with _attached(tmp_path, live_gains, "--secure", "--kill", "450:1",
                   steps=650) as (run, alive, result):
        rid = run["run"]
        # joined once the real agent 2 runs: a session holding agent 2's token before it
        # starts makes it refuse to start (Peer.claim), which is not what is tested here
        log = tmp_path / "run" / "logs" / "agent-2.log"
        while not (log.is_file() and "clock started" in log.read_text()):
            assert alive()
            time.sleep(0.05)
        net = NetConfig(run=rid, listen=(f"tls/127.0.0.1:{listen_port()}",),
                        connect=(run["connect"],), keys=str(tmp_path / "run" / "keys"),
                        identity="agent-2")
        with topics.open_peer(net, "agent", 2) as peer:
            truth_in = peer.subscribe(topics.truth_key(rid), maxlen=64)
            mine = topics.status_key(rid, 2)
            peer.publisher(mine)
            stats, step, sent = MessageStats(), -1, 0
            while step < 420:
                assert alive(), step
                step, heard = _step_of(truth_in, stats, step)
                if not heard:
                    continue
                stale = {"neighbours": {1: 0.5}, "ages": {1: 500}}
                peer.put(mine, wire.encode_status(_status(1, step, 2 ** 62)))
                peer.put(mine, wire.encode_status({**_status(3, step, 0), **stale}))
                # a listener agent 1 is not (W), then the one agent 3 is (its word
                # alternates with agent 2's genuine statuses: 3 is never stale long enough)
                peer.put(mine, wire.encode_status({**_status(2, step, 0), **stale}))
                peer.put(mine, wire.encode_status({**_status(2, step, 0),
                                                   "neighbours": {3: 0.5}, "ages": {3: 500}}))
                sent += 1
    assert sent > 50
    s = result["s"]
    assert [(f["agent"], f["cause"]) for f in s["failures"]] == [(1, "crash")], s["failures"]
    assert s["recovered"] is True and max(r["epoch"] for r in s["rosters"]) < 64
    reasons = {(e["reason"], e["agent"]) for e in s["evidence_refused"]}
    assert ("sender", 2) in reasons, reasons


def test_absurd_estimates_and_readings_are_refused_and_the_run_holds(tmp_path, live_gains):
    """Plain mode: an outsider publishes, as agent 1, estimates of 1e300 and 1e30 at the
    run's current step, readings of 1e300 for the next step, and plausible readings
    stamped 99,998 and 99,999 steps ahead, for 150 steps. Every agent refuses them
    (counted ``implausible`` and ``sensor_future``), nobody is convicted, the agents do
    not race ahead, and the run's steady MSE stays within 3x of the exact prediction."""
    from agent.protocol import wire
    from agent.protocol import topics
    from broker_free_net.codec import MessageStats
    from broker_free_net.config import NetConfig

    with _attached(tmp_path, live_gains, steps=500) as (run, alive, result):
        rid = run["run"]
        net = NetConfig(run=rid, mode="client", connect=(run["connect"],))
        with topics.open_peer(net, "attacker", 0) as peer:
            truth_in = peer.subscribe(topics.truth_key(rid), maxlen=64)
            for key in (topics.est_key(rid, 1), topics.sensors_key(rid)):
                peer.publisher(key)
            stats, step, sent = MessageStats(), -1, 0
            while step < 250:
                assert alive(), step
                step, heard = _step_of(truth_in, stats, step)
                if not heard or step < 100:
                    continue
                for value in (1e300, -1e30):
                    peer.put(topics.est_key(rid, 1), wire.encode_est(
                        1, step + 1, [value] * 14, 0, time.time()))
                peer.put(topics.sensors_key(rid), wire.encode_sensors(step + 1, [1e300] * 14))
                for ahead in (99_998, 99_999):    # plausible values, stamps from the future
                    peer.put(topics.sensors_key(rid), wire.encode_sensors(step + ahead,
                                                                        [1.0] * 14))
                sent += 1
    assert sent > 50
    s = result["s"]
    assert s["failures"] == [], s["failures"]
    assert s["implausible"]["estimates"] > 50 and s["implausible"]["readings"] > 50, s
    assert s["sensor_future"] > 50 and s["steps"] == 500, s
    assert s["mse_steady"] < 3 * s["mse_steady_exact"], (s["mse_steady"], s["mse_steady_exact"])


def test_a_dead_agent_is_not_hidden_behind_a_token_and_statuses_in_its_name(tmp_path,
                                                                             live_gains):
    """Plain mode: an outsider declares agent 1's liveliness token (in its own session)
    and publishes statuses on agent 1's key that keep advancing; agent 1 is then killed.
    Tokens carry the declaring session, so the monitor sees a second token for agent 1
    (refused, ``token``) and the end of agent 1's own token: the crash is convicted and
    recovered although the outsider's token and statuses go on."""
    from agent.protocol import wire
    from agent.protocol import topics
    from broker_free_net.codec import MessageStats
    from broker_free_net.config import NetConfig

    with _attached(tmp_path, live_gains, "--kill", "300:1", steps=600) as (run, alive, result):
        rid = run["run"]
        net = NetConfig(run=rid, mode="client", connect=(run["connect"],))
        with topics.open_peer(net, "attacker", 0) as peer:
            truth_in = peer.subscribe(topics.truth_key(rid), maxlen=64)
            peer.publisher(topics.status_key(rid, 1))
            stats, step, sent, token = MessageStats(), -1, 0, None
            while step < 450:
                assert alive(), step
                step, heard = _step_of(truth_in, stats, step)
                if not heard or step < 150:
                    continue
                if token is None:          # agent 1's id, in the outsider's own session
                    token = peer.session.liveliness().declare_token(
                        topics.alive_key(rid, "agent", 1, peer.zid()))
                peer.put(topics.status_key(rid, 1), wire.encode_status(_status(1, step, 0)))
                sent += 1
            token.undeclare()
    assert sent > 100
    s = result["s"]
    assert [(f["agent"], f["cause"]) for f in s["failures"]] == [(1, "crash")], s["failures"]
    assert s["recovered"] is True and s["rosters"][-1]["ids"] == [4, 2, 3], s["rosters"]
    reasons = {(e["reason"], e["agent"]) for e in s["evidence_refused"]}
    assert ("token", 1) in reasons, reasons
