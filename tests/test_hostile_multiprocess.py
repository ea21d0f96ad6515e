"""A live agent under hostile input: it keeps stepping, reports short errors, honours SIGTERM."""

import signal
import subprocess

import numpy as np
import pytest

from agent.protocol import wire
from agent.protocol import topics
from broker_free_net.codec import MAX_ERROR_CHARS, MAX_PAYLOAD_BYTES
from design.gains import save_gains
from design.scenario import load_scenario
from tests.runtime_procs import DEADLINE, Deployment

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]


def test_hostile_flood_leaves_the_agent_stepping_and_sigterm_stops_it(tmp_path):
    s = load_scenario("paper-14-live")
    gains = tmp_path / "g.npz"
    save_gains(gains, [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure], {"method": "test"})
    dep = Deployment(tmp_path, "paper-14-live", gains, n=s.n)
    try:
        dep.wait_for(lambda: dep.step_of(1) >= 5, "5 steps")
        run = dep.run
        bad_ctl = wire.encode_ctl(1, 1, 10, [f"no-such-node-{i:0>60}" for i in range(400)],
                                  {2: 0.5}, 0.5, np.zeros((s.n, 400)))
        flood = [
            (topics.sensors_key(run), wire.encode_sensors(wire.MAX_STEP, np.full(s.n, 1e9)), 20),
            (topics.sensors_key(run), wire.encode_sensors(dep.step_of(1) + 500, np.full(s.n, 1e9)),
             1),
            # nested deeper than the codec's limit, small enough to reach the decoder
            (topics.est_key(run, 2), b"\x82\xa1v\x01\xa1x" + b"\x91" * 200 + b"\xc0", 50),
            # larger than any estimate: refused by the inbox before it is copied
            (topics.est_key(run, 2), b"\x82\xa1v\x01\xa1x" + b"\x91" * 5000 + b"\xc0", 50),
            (topics.sensors_key(run), bytes(250_000), 50),
            (topics.ctl_key(run, 1), bytes(MAX_PAYLOAD_BYTES + 1024), 20),
            (topics.ctl_key(run, 1), bad_ctl, 50),
        ]
        for key, payload, count in flood:
            dep.peer.publisher(key, block=True)
            for _ in range(count):
                dep.peer.put(key, payload)
        base = dep.status[1]["sensor"]["missed"]
        reasons = lambda: dep.status[1]["malformed_reasons"]
        dep.wait_for(lambda: dep.status[1]["ctl"]["rejected"] >= 50
                     and {"future", "too_deep", "too_large"} <= set(reasons()),
                     "agent 1 counts the flood")
        k = dep.step_of(1)
        dep.wait_for(lambda: dep.step_of(1) >= k + 20, "agent 1 keeps stepping")
        st = dep.status[1]
        assert 0 < len(st["ctl"]["last_error"]) <= MAX_ERROR_CHARS
        assert st["sensor"]["missed"] - base <= 2  # no reading skipped for a forged stamp
        assert st["sensor"]["last_step"] < wire.MAX_STEP
        proc = dep.children.children["agent-1"].proc
        proc.send_signal(signal.SIGTERM)
        try:
            assert proc.wait(timeout=DEADLINE) == 0
        except subprocess.TimeoutExpired:
            pytest.fail("agent 1 ignored SIGTERM")
    finally:
        dep.close()
