"""agent.monitor.gain_worker: the design processes answer requests and precompute every single
failure of the configuration in force (real spawned processes, no network)."""

import time

import pytest

from agent.monitor.gain_worker import GainWorker, plan_failures
from agent.monitor.core import GainSource
from design.roster import Roster, replan
from design.scenario import load_scenario, resolve_delays

pytestmark = pytest.mark.slow


def _collect(worker, want, deadline_s=120.0):
    got = []
    deadline = time.monotonic() + deadline_s
    while not want(got) and time.monotonic() < deadline:
        got += worker.poll()
        time.sleep(0.05)
    return got


def test_a_request_and_the_precompute_both_come_back_certified():
    s = load_scenario("paper-14-live")
    roster = Roster.initial(s, resolve_delays(s, "uniform:3"))
    foreseen = {GainSource.key(nxt) for _, nxt in plan_failures(roster)}
    _, single = replan(roster, [1])
    # not in the precompute: other delays
    _, other = replan(Roster.initial(s, resolve_delays(s, "uniform:4")), [3])
    worker = GainWorker(start=True)
    try:
        worker.precompute(roster)
        worker.request(other)
        kinds = lambda got: [i.get("kind") for r, G, i in got   # noqa: E731
                             if GainSource.key(r) == GainSource.key(other)]
        polished = lambda got: {GainSource.key(r) for r, _, i in got   # noqa: E731
                                if i.get("polished")}
        got = _collect(worker, lambda g: kinds(g) == ["fast", "refined"] and foreseen
                       <= polished(g))
    finally:
        worker.close()
    assert kinds(got) == ["fast", "refined"]
    assert foreseen <= {GainSource.key(r) for r, _, _ in got}
    # every foreseen failure: its fast gain first, then the polished one (a fast kind)
    assert foreseen <= polished(got)
    for key in foreseen:
        seq = [i.get("polished", False) for r, _, i in got if GainSource.key(r) == key]
        assert seq == [False, True]
    assert GainSource.key(single) in foreseen and GainSource.key(other) not in foreseen
    for r, G, info in got:
        assert G is not None and info["rho"] < 1
        assert len(G) == r.scenario.N
