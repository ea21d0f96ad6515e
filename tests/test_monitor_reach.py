"""The monitor reaches every agent of the configuration before it judges any
(agent.monitor.process.reach_every_agent): a link not up yet is no death."""

import io
import threading
import time

import agent.monitor.process as mp


class _Watch:
    """A liveliness watch whose agents appear at given times (seconds from creation)."""

    def __init__(self, appear):
        self.t0 = time.monotonic()
        self.appear = appear

    def alive(self):
        now = time.monotonic() - self.t0
        return {("agent", str(a)) for a, t in self.appear.items() if t <= now}

    def wait_until(self, pred, timeout):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if pred(self.alive()):
                return True
            time.sleep(0.01)
        return pred(self.alive())


class _Stop:
    flag = False


def test_it_waits_for_late_links_and_not_for_the_dead(monkeypatch):
    log = io.StringIO()
    # links up one by one over 0.6 s: every agent is waited for
    assert mp.reach_every_agent(_Watch({1: 0.0, 2: 0.3, 3: 0.6}), [1, 2, 3], 1, _Stop(),
                                log, limit=5.0) == []
    # agent 3 dead (a restarted monitor): no new token for the settle time, then it judges
    monkeypatch.setattr(mp, "REACH_SETTLE_S", 0.3)
    t = time.monotonic()
    assert mp.reach_every_agent(_Watch({1: 0.0, 2: 0.1}), [1, 2, 3], 1, _Stop(), log,
                                limit=5.0) == [3]
    assert time.monotonic() - t < 2.0
    assert "agents [3] not seen" in log.getvalue()
    # nobody at all: the limit
    assert mp.reach_every_agent(_Watch({}), [1, 2], 1, _Stop(), log, limit=0.3) == [1, 2]
    # a stop ends the wait
    stop = _Stop()
    threading.Timer(0.1, lambda: setattr(stop, "flag", True)).start()
    assert mp.reach_every_agent(_Watch({}), [1], 1, stop, log, limit=30.0) == [1]
