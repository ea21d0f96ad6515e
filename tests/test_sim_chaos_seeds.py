"""Hundreds of seeded fault schedules under simulated time, each checked by the chaos
invariants: the fast subset's share of ``socmon chaos --simulated`` (docs/monitor.md).

200 schedules of 400 steps of paper-14-live with the gains ``socmon up`` designs, every
fault kind a simulated run applies but the scripted ones and the loss of every monitor
(kill, stop, hang, a quiet sensor, partition, delay, drop, a slow process, the monitor
killed or paused), 6.25 faults per 1000 steps (one or two a run: faults come at least 160
steps apart after step 80). About 0.22 s of CPU a run. The longer runs are
``scripts/sim_chaos.py`` and the ``slow`` tests of tests/test_sim_runtime.py.
"""

import pytest

from agent.run.simulated import run_schedules
from design.gain_design import design_gains
from design.scenario import load_scenario, resolve_delays

KINDS = ("kill", "stop", "hang", "sensor", "partition", "delay", "drop", "slow", "monitor",
         "monitorstop")
BATCHES, PER_BATCH, STEPS = 8, 25, 400


@pytest.fixture(scope="module")
def designed():
    s = load_scenario("paper-14-live")
    delays = resolve_delays(s, "scenario")
    return s, list(design_gains(s, delays=delays, starts=1).G), delays


def _check_batch(designed, batch):
    s, G, delays = designed
    first = 1000 + PER_BATCH * batch
    report = run_schedules(s, G, delays, range(first, first + PER_BATCH), STEPS, KINDS, 6.25)
    assert report["violations"] == [], report["violations"]
    assert report["runs"] == PER_BATCH and sum(report["faults"].values()) >= PER_BATCH
    assert sum(report["verdicts"].values()) > 0, report


# two classes: ``--dist loadscope`` gives each its own worker
class TestTheFirstHundredSeeds:
    @pytest.mark.parametrize("batch", range(BATCHES // 2))
    def test_seeded_fault_schedules_keep_the_chaos_invariants(self, designed, batch):
        """Seeds 1000 + 25 batch .. + 24: no violation of recovery, fencing, processes,
        error, convictions or alerts; the faults were drawn and answered (a batch without
        a verdict tested nothing)."""
        _check_batch(designed, batch)


class TestTheSecondHundredSeeds:
    @pytest.mark.parametrize("batch", range(BATCHES // 2, BATCHES))
    def test_seeded_fault_schedules_keep_the_chaos_invariants(self, designed, batch):
        """As the first hundred, seeds 1100 to 1199."""
        _check_batch(designed, batch)


class TestLiesAndBiases:
    @pytest.mark.slow      # about 10 s: the full suite runs it
    def test_lies_and_biases_convict_only_liars_and_keep_every_other_invariant(self):
        """Twelve schedules of 1,000 steps on paper-14-live with two receivers per agent
        (``topology = "complete"``): lies, sensor biases and kills. Every conviction of
        ``inconsistent estimates`` is of an agent that lies, and no invariant breaks but
        ``alerts``: an alert may name the wrong agent while another lies or is biased
        (the isolation's measured limit, docs/residuals.md), never otherwise."""
        import numpy as np

        from agent.run.chaos import draw_schedule
        from agent.run.simulated import SimRuntime

        s = load_scenario("paper-14-live")
        W = np.full((3, 3), 0.25)
        np.fill_diagonal(W, 0.5)
        s = s.replace(W=W)
        G = list(design_gains(s, starts=1).G)
        convicted = 0
        for seed in range(2000, 2012):
            schedule = draw_schedule(s, seed, 1000, kinds=("lie", "bias", "kill"), rate=6.25)
            r = SimRuntime(s, G, s.delays, seed=seed, faults=schedule).run(1000)
            liars = {f.agent for f in schedule if f.kind == "lie"}
            for f in r.summary["failures"]:
                if f["cause"] == "inconsistent estimates":
                    assert f["agent"] in liars, (seed, f, schedule)
                    convicted += 1
            for v in r.violations():
                assert v.invariant == "alerts", (seed, v)
                assert any(f.kind in ("lie", "bias") and f.step <= v.step for f in schedule)
        assert convicted > 0
