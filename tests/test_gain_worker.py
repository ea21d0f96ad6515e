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
    # every foreseen failure: its fast gain first, then the polished one (a fast kind); a
    # plain fast answer may still come after it (the urgent process designs the single
    # failures too), and the monitor's GainSource keeps the polished one (or the refined)
    assert foreseen <= polished(got)
    source = GainSource()
    for r, G, info in got:
        source.put(r, G, info)
    for key in foreseen:
        seq = [i.get("polished", False) for r, _, i in got if GainSource.key(r) == key]
        assert seq[0] is False and True in seq, seq
        (r,) = {GainSource.key(r): r for r, _, _ in got if GainSource.key(r) == key}.values()
        kept = source.get(r)[1]            # the polished gain, or the refined one after it
        assert kept.get("polished") is True or kept["kind"] == "refined", kept
    assert GainSource.key(single) in foreseen and GainSource.key(other) not in foreseen
    for r, G, info in got:
        assert G is not None and info["rho"] < 1
        assert len(G) == r.scenario.N

