"""agent.monitor.gain_worker: the design processes answer requests and precompute every single
failure of the configuration in force (real spawned processes, no network)."""

import queue
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



def test_a_newer_precompute_goes_before_a_refinement_and_starts_from_the_gains_in_force():
    """A refinement (seconds at T = 7) asked just before the precompute of a new
    configuration gives way to it: every single failure's fast gain comes back before the
    refined gain, each designed from the gains in force (carried: below the fast design's
    target already, so no iteration was needed).

    The precompute process alone, fed what :meth:`GainWorker.request` and
    :meth:`GainWorker.precompute` send it: beside it, the background process refines the
    same single failures, and under load its refined gain of the first one came back
    before the precompute's last fast gain (CI, stop 39)."""
    import multiprocessing

    import numpy as np

    from agent.monitor.gain_worker import _serve_precompute
    from design.closed_loop import closed_loop_for
    from design.gain_design import design_gains
    from design.reconfigure import FAST_TARGET
    from design.roster import carried_gains

    s = load_scenario("paper-14-live")
    roster = Roster.initial(s, resolve_delays(s, "uniform:7"))
    G = design_gains(s, delays=roster.delays, starts=1, max_iter=30).G
    _, in_force = replan(roster, [3])
    singles = [GainSource.key(nxt) for a, nxt in plan_failures(roster) if len(a) == 1]
    ctx = multiprocessing.get_context("spawn")
    requests, results, idle = ctx.Queue(), ctx.Queue(), ctx.Event()
    idle.set()
    proc = ctx.Process(target=_serve_precompute, args=(requests, results, idle), daemon=True)
    proc.start()
    got = []
    refined = lambda: [i for r, _, i in got if i.get("kind") == "refined"]  # noqa: E731
    try:
        requests.put(("refine", in_force))
        requests.put(("precompute", roster, [list(g) for g in G]))
        deadline = time.monotonic() + 600.0
        while not refined() and time.monotonic() < deadline and proc.is_alive():
            try:
                got.append(results.get(timeout=0.5))
            except queue.Empty:
                pass
    finally:
        requests.put(None)
        proc.join(timeout=10.0)
        if proc.is_alive():
            proc.terminate()
            proc.join(timeout=5.0)
    assert refined(), "no refined gain within 600 s"
    order = [GainSource.key(r) for r, _, i in got]
    first_refined = next(k for k, (_, _, i) in enumerate(got) if i.get("kind") == "refined")
    assert GainSource.key(got[first_refined][0]) == GainSource.key(in_force)
    assert set(singles) <= set(order[:first_refined]), [i for _, _, i in got]
    kept = 0
    for r, Gr, info in got[:first_refined]:
        if info.get("kind") != "fast" or info.get("polished"):
            continue
        warm = carried_gains(roster, G, r)
        if closed_loop_for(r.scenario, warm, r.delays).spectral_radius() < FAST_TARGET:
            assert all(np.array_equal(a, b) for a, b in zip(Gr, warm))
            kept += 1
    assert kept >= 1


def test_a_refinement_asked_alone_comes_back_refined_and_nothing_else():
    """``request(roster, kinds=("refined",))``, what the monitor asks for a configuration
    put in force on a fast gain: the precompute process designs its refined gain, and no
    first gain is designed for it (the urgent process is not asked)."""
    s = load_scenario("paper-14-live")
    _, in_force = replan(Roster.initial(s, resolve_delays(s, "uniform:3")), [2])
    worker = GainWorker(start=True)
    try:
        worker.request(in_force, kinds=("refined",))
        got = _collect(worker, lambda g: any(i.get("kind") == "refined" for _, _, i in g))
    finally:
        worker.close()
    assert [(GainSource.key(r), i["kind"]) for r, _, i in got] == \
        [(GainSource.key(in_force), "refined")]
    (_, G, info), = got
    assert G is not None and info["rho"] < 1 and info["mse"] > 0


def test_a_refined_gain_from_the_gains_in_force_is_as_good_as_from_the_reset_gain():
    """The monitor's refined precompute starts each single failure's MSE design from the
    gains in force carried over (a shorter stop rule): certified, and its exact steady MSE
    within a fraction of a percent of the design from the reset gain."""
    from agent.monitor.core import design_gains_for
    from agent.monitor.gain_worker import refined_gains_from
    from design.gain_design import design_gains
    from design.roster import carried_gains

    s = load_scenario("paper-14-live")
    roster = Roster.initial(s, resolve_delays(s, "uniform:2"))
    G = design_gains(s, delays=roster.delays, objective="mse").G
    nxt = next(r for a, r in plan_failures(roster) if a == [2])
    warm, warm_info = refined_gains_from(nxt, carried_gains(roster, G, nxt))
    cold, cold_info = design_gains_for(nxt, "refined")
    assert warm is not None and warm_info["kind"] == "refined" and warm_info["rho"] < 1
    assert len(warm) == nxt.scenario.N
    assert warm_info["mse"] <= cold_info["mse"] * 1.005, (warm_info, cold_info)
