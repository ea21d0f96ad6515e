"""Chaos runs: the seeded schedule, the invariant checker, and live runs under faults.

The schedule and the checker are tested without processes; a few fixed seeds run live
(multi-process, loopback, about 20 s each). The longer suite is marked ``chaos`` and
deselected by default: ``python -m pytest -m chaos`` runs it.
"""

import json

import numpy as np
import pytest

from agent.run.chaos import Bounds, check_invariants, draw_schedule
from agent.run.local import Fault, Recording, RunConfig
from design.scenario import load_scenario
from tests.test_runtime_multiprocess import _socmon


@pytest.fixture(scope="module")
def live():
    return load_scenario("paper-14-live")


def test_the_same_seed_gives_the_same_schedule_and_faults_keep_their_distance(live):
    a = draw_schedule(live, seed=11, duration=3000, rate=5)
    assert a == draw_schedule(live, seed=11, duration=3000, rate=5)
    assert a != draw_schedule(live, seed=12, duration=3000, rate=5)
    steps = [f.step for f in a]
    assert steps == sorted(steps) and steps[0] >= Bounds().warmup
    assert all(b - s >= Bounds().gap - Bounds().gap // 4 for s, b in zip(steps, steps[1:]))


@pytest.mark.parametrize("seed", range(20))
def test_a_schedule_never_kills_the_last_two_agents(live, seed):
    killed = [f.agent for f in draw_schedule(live, seed=seed, duration=5000, kinds=("kill",),
                                             rate=6)]
    assert len(set(killed)) == len(killed) <= live.N + live.standby - 2


def _config(live, faults=(), tmp_path=None):
    G = [0.5 * np.eye(live.n)[:, list(m)] for m in live.measure]
    return RunConfig(scenario=live, scenario_arg="paper-14-live", G=G, gains_path=None,
                     delays=live.delays, delays_spec="scenario", steps=300, seed=0,
                     step_ms=20.0, deadline_ms=20.0, out=tmp_path, faults=tuple(faults))


def _recording(live, rosters, est_epochs):
    rec = Recording(run_id="t", ports=[])
    rec.rosters = rosters
    rec.est = {a: {k: np.zeros(live.n) for k in ks} for a, ks in est_epochs.items()}
    rec.est_epoch = {a: dict(ks) for a, ks in est_epochs.items()}
    rec.truth = {k: np.zeros(live.n) for k in range(301)}
    return rec


def _assignments(live, failed, epoch):
    """The assignments a monitor publishes for the failure of ``failed`` (by id)."""
    from design.roster import Roster, replan, role_specs

    _, nxt = replan(Roster.initial(live), failed)
    G = [0.5 * np.eye(live.n)[:, list(m)] for m in nxt.scenario.measure]
    return {(a, epoch): {"measure": list(sp.measure), "neighbours": sp.neighbours,
                         "self_weight": sp.self_weight, "gain": sp.gain,
                         "take_over": sp.take_over}
            for a, sp in role_specs(nxt, G).items()}


def _summary(failures=(), exit_status=None):
    return {"failures": list(failures), "orphans": [],
            "exit_status": exit_status or {"world": 0, "agent-1": 0, "agent-2": 0,
                                           "agent-3": 0, "agent-4": 0, "monitor": 0}}


def test_the_checker_flags_an_outsider_publishing_under_the_current_epoch(live, tmp_path):
    """Agent 1 was replaced from step 120 (epoch 1) but publishes step 130 under epoch 1:
    receivers would accept it, a split brain. Under epoch 0 it would be fenced: fine."""
    rosters = [(0, (1, 2, 3), 0), (120, (4, 2, 3), 1)]
    steps = list(range(301))
    mse = [0.1] * 301
    for epoch, expected in ((1, 1), (0, 0)):
        est = {1: {k: (0 if k < 120 else epoch) for k in range(131)},
               4: {k: 1 for k in range(119, 301)}}
        rec = _recording(live, rosters, est)
        rec.assigns = _assignments(live, [1], epoch=1)
        v = [x for x in check_invariants(_config(live, [Fault(110, "kill", 1)], tmp_path), rec,
                                         _summary(), steps, mse) if x.invariant == "fencing"]
        assert len(v) == expected, v


def test_the_checker_flags_a_conviction_without_a_fault(live, tmp_path):
    rosters = [(0, (1, 2, 3), 0)]
    rec = _recording(live, rosters, {a: {k: 0 for k in range(301)} for a in (1, 2, 3)})
    fails = [{"agent": 2, "cause": "hang", "evidence": "step 10", "detected_step": 50}]
    v = check_invariants(_config(live, [], tmp_path), rec, _summary(fails), list(range(301)),
                         [0.1] * 301)
    assert [x.invariant for x in v] == ["convictions"]


def test_lies_and_biases_are_drawn_once_per_agent_within_their_sizes(live):
    """``lie`` and ``bias`` come only when asked for (the default kinds are those before
    them), at most one of either per agent, 2 to 8 noise std-devs."""
    for seed in range(10):
        assert not {f.kind for f in draw_schedule(live, seed=seed, duration=3000, rate=6)} \
            & {"lie", "bias"}
        skewed = [f for f in draw_schedule(live, seed=seed, duration=5000,
                                           kinds=("lie", "bias"), rate=6)]
        assert skewed and len({f.agent for f in skewed}) == len(skewed)
        assert all(f.kind in ("lie", "bias") and 2.0 <= f.value <= 8.0 for f in skewed)


def test_the_checker_flags_an_alert_on_an_agent_without_a_fault(live, tmp_path):
    """A residual alert that names a fault on an agent nothing was injected into breaks
    ``alerts``; on the biased agent (from its step), or ``unexplained``, it does not. While
    a liar holds its role the error is not judged (its lie goes on until convicted)."""
    rosters = [(0, (1, 2, 3), 0)]
    rec = _recording(live, rosters, {a: {k: 0 for k in range(301)} for a in (1, 2, 3)})
    faults = [Fault(100, "bias", 2, 0.0, 5.0), Fault(90, "lie", 3, 0.0, 5.0)]
    alerts = [{"agent": 1, "fault": "sensor bias", "step": 105, "score": 2.0},
              {"agent": 2, "fault": "sensor bias", "step": 104, "score": 9.0},
              {"agent": 2, "fault": "sensor bias", "step": 99, "score": 9.0},
              {"agent": 1, "fault": "unexplained", "step": 130, "score": 1.1}]
    v = check_invariants(_config(live, faults, tmp_path), rec,
                         {**_summary(), "residual_alerts": alerts}, list(range(301)),
                         [0.1] * 150 + [50.0] * 151)
    assert [(x.invariant, x.step) for x in v] == [("alerts", 105), ("alerts", 99)], v


def test_the_checker_flags_a_missing_recovery_and_a_dead_process(live, tmp_path):
    rosters = [(0, (1, 2, 3), 0)]
    rec = _recording(live, rosters, {a: {k: 0 for k in range(301)} for a in (1, 2, 3)})
    status = {"world": 0, "agent-1": -9, "agent-2": 1, "agent-3": 0, "agent-4": 0,
              "monitor": 0}
    v = check_invariants(_config(live, [Fault(100, "kill", 1)], tmp_path), rec,
                         _summary(exit_status=status), list(range(301)), [0.1] * 301)
    kinds = sorted(x.invariant for x in v)
    assert kinds == ["processes", "recovery"], v
    assert "agent-2 exited with status 1" in next(x.evidence for x in v
                                                   if x.invariant == "processes")


def _chaos(tmp_path, seed, faults, duration=900, rate=4.0):
    code, out, err = _socmon("chaos", "paper-14-live", "--seed", str(seed), "--duration",
                             str(duration), "--faults", faults, "--rate", str(rate), "--out",
                             str(tmp_path / "chaos"), "--json", "--quiet")
    report = json.loads(out) if out.strip() else {}
    assert code == 0, (err, report.get("violations"), report.get("replay"))
    return report


@pytest.mark.multiprocess
@pytest.mark.slow
# seeds whose schedules hit agents of the configuration with several kinds each:
# 0: stop 3, kill 2, kill 3, stop 1, stop 1; 6: sensor 2, partition 2, monitor
@pytest.mark.parametrize("seed, faults", [(0, "kill,stop"),
                                          (6, "partition,monitor,hang,sensor")])
def test_fixed_chaos_seeds_keep_every_invariant(tmp_path, seed, faults):
    report = _chaos(tmp_path, seed, faults)
    assert report["violations"] == [] and report["faults"]
    for name in ("schedule.json", "timeline.json", "timeline.png", "invariants.json",
                 "summary.json", "mse.png", "estimates.npz", "assignments.json"):
        assert (tmp_path / "chaos" / name).is_file()     # up's files and its own


@pytest.mark.multiprocess
@pytest.mark.chaos
@pytest.mark.parametrize("seed", range(100, 110))
def test_longer_chaos_runs_keep_every_invariant(tmp_path, seed):
    report = _chaos(tmp_path, seed, "kill,stop,monitor,partition,delay,drop", duration=2500,
                    rate=4.0)
    assert report["violations"] == []


def test_the_timeline_places_a_failure_no_verdict_answered_where_the_agent_died(tmp_path):
    """A standby killed with no verdict (``detected_step`` None) once made ``socmon chaos``
    die writing its timeline (chaos seed 105): it is placed at the step it died."""
    from agent.run.chaos import write_timeline

    summary = {"scenario": "paper-14-live", "seed": 105, "agents": 3, "standby": 1,
               "step_ms": 20.0, "failures": [
                   {"agent": 1, "cause": "crash", "detected_step": 120},
                   {"agent": 4, "cause": "crash", "detected_step": None, "died_step": 300},
                   {"agent": 2, "cause": "crash", "detected_step": None}]}
    schedule = [Fault(100, "kill", 1), Fault(290, "kill", 4)]
    steps = list(range(400))
    write_timeline(tmp_path, summary, steps, [1.0] * 400, schedule,
                   [(0, (1, 2, 3), 0), (130, (4, 2, 3), 1)])
    items = json.loads((tmp_path / "timeline.json").read_text())
    assert [(i["step"], i["what"]) for i in items] == [
        (100, "fault"), (120, "verdict"), (130, "activation"), (290, "fault"),
        (300, "undetected")]
