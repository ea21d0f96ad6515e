"""agent.monitor.gain_worker's serving loops, run in a thread on plain queues: what a
stand-down drops (GainWorker.stand_down, sent when another monitor takes the seat)."""

import queue
import threading

import numpy as np
import pytest

from agent.monitor import gain_worker
from agent.monitor.core import GainSource, design_gains_for
from agent.monitor.gain_worker import _serve_background, _serve_precompute, plan_failures
from design.roster import Roster
from design.scenario import load_scenario, resolve_delays


@pytest.fixture(autouse=True)
def _in_a_thread(monkeypatch):
    """The loops set their signal handling as a process's main thread; not here."""
    monkeypatch.setattr(gain_worker, "_quiet_signals", lambda: None)


def _served(serve, items, *args):
    """Run ``serve(requests, results, *args)`` in a thread on ``items``; the first
    result, then the loop ended with its sentinel."""
    requests, results = queue.Queue(), queue.Queue()
    for item in items:
        requests.put(item)
    thread = threading.Thread(target=serve, args=(requests, results, *args), daemon=True)
    thread.start()
    first = results.get(timeout=60)
    requests.put(None)
    thread.join(timeout=60)
    assert not thread.is_alive()
    return first


def _small():
    s = load_scenario("paper-14-live")
    return Roster.initial(s, resolve_delays(s, "uniform:3"))


def test_the_precompute_stood_down_designs_nothing_of_the_configuration_it_had():
    big = Roster.initial(load_scenario("communities-16"))
    small = _small()
    idle = threading.Event()
    idle.set()
    roster, G, info = _served(_serve_precompute, [("precompute", big, None),
                                                  ("precompute", None, None),
                                                  ("precompute", small, None)], idle)
    first_planned = plan_failures(small)[0][1]
    assert GainSource.key(roster) == GainSource.key(first_planned)
    assert G is not None and info["kind"] == "fast"


def test_the_background_stood_down_refines_nothing_and_still_assesses():
    big = Roster.initial(load_scenario("communities-16"))
    small = _small()
    G, info = design_gains_for(small, "fast")
    roster, G_back, back = _served(_serve_background, [(1, big, None), (2, None, None),
                                                       ("assess", small, G, info)])
    assert GainSource.key(roster) == GainSource.key(small) and back["assessed"] is True
    assert all(np.array_equal(a, b) for a, b in zip(G_back, G))


def test_a_large_network_is_not_improved_ahead_a_small_one_is():
    """communities-32: each foreseen failure gets its fast gain and nothing more ahead (a
    polish and a refinement each, 300 s of CPU beside its agents); paper-14-live: fast
    gains, then each polished."""
    big = Roster.initial(load_scenario("communities-32"))
    small = _small()
    kinds = lambda queue: [kind for _, kind, _, _ in queue]        # noqa: E731
    assert kinds(gain_worker.precompute_queue(big)) == ["fast"] * 32
    planned = len(plan_failures(small))
    assert kinds(gain_worker.precompute_queue(small)) == ["fast"] * planned + \
        ["polished"] * planned


def test_the_background_refines_ahead_only_where_that_pays(monkeypatch):
    big = Roster.initial(load_scenario("communities-32"))
    small = _small()
    refined = []
    monkeypatch.setattr(gain_worker, "precompute_single_failures",
                        lambda roster, *a, **k: refined.append(roster))
    requests = queue.Queue()
    for item in [(1, big, None), (2, small, None), None]:
        requests.put(item)
    thread = threading.Thread(target=_serve_background, args=(requests, queue.Queue()))
    thread.start()                      # a thread: the loop nices the one it runs in
    thread.join(timeout=60)
    assert not thread.is_alive() and refined == [small]


def test_the_background_ends_on_a_close_read_during_a_refinement():
    """The close sentinel read while a refinement checks for newer work ends the loop (it
    was taken for "nothing read" and the loop waited for another request, until
    GainWorker.close gave up on it and terminated the process)."""
    requests = queue.Queue()
    for item in [(1, _small(), None), None]:
        requests.put(item)
    thread = threading.Thread(target=_serve_background, args=(requests, queue.Queue()),
                              daemon=True)
    thread.start()
    thread.join(timeout=60)
    assert not thread.is_alive()
