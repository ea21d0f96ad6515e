"""The run's record is read from what the agents did, never from what was sent."""

import math

import numpy as np
import pytest

from agent.run.recorder import Recording
from agent.run.summary import (
    DIVERGED_FACTOR,
    _failures,
    diverged_at,
    rosters_in_force,
    steady_mse,
    switch_steps,
)


def _epochs(switches, first=0, last=400):
    """{step: epoch} of one agent from {step: epoch it switches to}."""
    out, e = {}, 0
    for k in range(first, last + 1):
        e = switches.get(k, e)
        out[k] = e
    return out


def test_a_rejected_first_assignment_is_not_in_force_and_its_reissue_is():
    """Epoch 1 at step 175: agents 1 and 2 ran it, the standby 4 heard it too late and
    rejected it; the re-issue (epoch 2 at 184) is what every agent ran. The record used to
    say 175 (what was sent) and the simulator check then failed."""
    rosters = [(0, (1, 2, 3), 0), (175, (1, 2, 4), 1), (184, (1, 2, 4), 2)]
    est = {1: _epochs({175: 1, 184: 2}), 2: _epochs({175: 1, 184: 2}),
           3: _epochs({}, last=160),                     # killed
           4: {k: 2 for k in range(183, 401)}}           # standby: starts stamped 183
    assigns = {(4, 1): {}, (1, 1): {}, (2, 1): {}, (4, 2): {}, (1, 2): {}, (2, 2): {}}
    in_force, mixed = rosters_in_force(rosters, est, assigns)
    assert in_force == [(0, (1, 2, 3), 0), (184, (1, 2, 4), 2)]
    assert mixed == [{"epoch": 1, "activate_at": 175, "switched": {1: 175, 2: 175, 4: None}}]


def test_sequential_failures_and_a_same_roles_gain_change_are_all_in_force():
    rosters = [(0, (1, 2, 3), 0), (120, (4, 2, 3), 1), (200, (4, 2, 3), 2),
               (300, (2, 3), 3)]
    est = {1: _epochs({}, last=110),
           2: _epochs({120: 1, 200: 2, 300: 3}), 3: _epochs({120: 1, 200: 2, 300: 3}),
           4: {**{k: 1 for k in range(119, 200)}, **{k: 2 for k in range(200, 290)}}}
    assigns = {(a, e): {} for e, ids in ((1, (4, 2, 3)), (2, (4, 2, 3)), (3, (2, 3)))
               for a in ids}
    in_force, mixed = rosters_in_force(rosters, est, assigns)
    assert [r[0] for r in in_force] == [0, 120, 200, 300] and mixed == []


def test_a_roster_superseded_at_its_own_step_never_ran():
    rosters = [(0, (1, 2, 3), 0), (150, (4, 2, 3), 1), (150, (4, 2), 2)]
    est = {2: _epochs({150: 2}), 4: {k: 2 for k in range(149, 300)}}
    in_force, _ = rosters_in_force(rosters, est, {(4, 1): {}, (4, 2): {}, (2, 2): {}})
    assert in_force == [(0, (1, 2, 3), 0), (150, (4, 2), 2)]


def test_a_roster_superseded_at_its_own_step_too_late_was_in_force():
    """Epoch 2 was to replace epoch 1 at its own step 177, but reached agents 3 and 4 at
    step 178 (rejected): they ran epoch 1 from 177 until the re-issue, epoch 3 at 198. The
    record used to drop epoch 1 as superseded (what was sent), and the simulator's replay
    then differed from the run (1.67, a live run beside two busy loops)."""
    rosters = [(0, (1, 2, 3), 0), (177, (4, 2, 3), 1), (177, (4, 3), 2), (198, (4, 3), 3)]
    est = {1: _epochs({}, last=149), 2: _epochs({}, last=149),
           3: _epochs({177: 1, 198: 3}),
           4: {**{k: 1 for k in range(176, 198)}, **{k: 3 for k in range(198, 400)}}}
    assigns = {(a, e): {} for e, ids in ((1, (4, 2, 3)), (2, (4, 3)), (3, (4, 3)))
               for a in ids}
    in_force, mixed = rosters_in_force(rosters, est, assigns)
    assert in_force == [(0, (1, 2, 3), 0), (177, (4, 2, 3), 1), (198, (4, 3), 3)]
    assert mixed == []


def test_a_standby_that_takes_over_switches_the_step_after_its_first_estimate():
    assert switch_steps({k: 3 for k in range(99, 120)}, 3) == 100
    assert switch_steps({**{k: 1 for k in range(0, 100)}, **{k: 3 for k in range(100, 120)}},
                        3) == 100


def test_steady_mse_and_divergence_are_one_definition():
    # the last quarter, steps nobody estimated left out: the live record and the simulator
    assert steady_mse([9.0] * 6 + [math.nan, 3.0]) == 3.0
    assert steady_mse([9.0] * 6 + [1.0, math.inf]) == math.inf
    from agent.run import summary as run_summary
    from design import metrics
    assert run_summary.steady_mse is metrics.steady_mse
    mse = [0.3, 0.4, 0.28 * DIVERGED_FACTOR * 1.01, 1e30]
    assert diverged_at([0, 1, 2, 3], mse, [0.27, 0.28, None]) == 2
    assert diverged_at([0, 1], [0.3, math.nan], [0.27]) == 1


def _recording(rosters, est_epoch, assigns, steps=400):
    rec = Recording(run_id="t", ports=[])
    rec.rosters, rec.est_epoch, rec.assigns = rosters, est_epoch, assigns
    return rec


@pytest.mark.parametrize("after, recovered", [(0.30, True), (5.0, False)])
def test_recovered_needs_the_roles_in_force_and_the_error_near_its_prediction(after,
                                                                                recovered):
    """A run whose roles are in force but whose error after them is 18x the exact level
    (a network that diverges while it recovers) is not recovered."""
    from design.roster import Roster, role_specs
    from design.scenario import load_scenario

    s = load_scenario("paper-14-live")
    G = [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure]
    specs = role_specs(Roster.initial(s), G)
    rosters = [(0, (1, 2, 3), 0), (100, (1, 2, 3), 1)]
    assigns = {(a, 1): {"measure": list(sp.measure), "neighbours": sp.neighbours,
                        "self_weight": sp.self_weight, "gain": sp.gain}
               for a, sp in specs.items()}
    est = {a: _epochs({100: 1}) for a in (1, 2, 3)}
    steps = list(range(0, 401))
    from design.closed_loop import closed_loop_for

    exact = closed_loop_for(s, G, s.delays).mse_steady(s.process_noise, s.measurement_noise)
    mse = [exact] * 100 + [after / 0.30 * exact] * 301
    out = _failures(None, _recording(rosters, est, assigns), s, s.delays, steps, mse, G)
    assert out["mse_steady_exact_after_recovery"] == pytest.approx(exact)
    assert out["recovered"] is recovered
    if not recovered:
        assert any("not recovered" in w for w in out["warnings"])


def _same_roles_new_gains(scales, switches, last):
    """paper-14-live's roles throughout, with gains ``scale * I`` from each switch on."""
    from design.closed_loop import closed_loop_for
    from design.roster import Roster, role_specs
    from design.scenario import load_scenario

    s = load_scenario("paper-14-live")
    rosters, assigns, exact = [(0, (1, 2, 3), 0)], {}, []
    for epoch, (scale, at) in enumerate(zip(scales, switches), start=1):
        G = [scale * np.eye(s.n)[:, list(m)] for m in s.measure]
        for a, sp in role_specs(Roster.initial(s), G).items():
            assigns[(a, epoch)] = {"measure": list(sp.measure), "neighbours": sp.neighbours,
                                   "self_weight": sp.self_weight, "gain": sp.gain}
        rosters.append((at, (1, 2, 3), epoch))
        exact.append(closed_loop_for(s, G, s.delays).mse_steady(s.process_noise,
                                                                 s.measurement_noise))
    est = {a: _epochs({at: e for at, _, e in rosters[1:]}, last=last) for a in (1, 2, 3)}
    G0 = [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure]
    return s, rosters, assigns, est, exact, G0


def test_refined_gains_late_in_a_run_do_not_shrink_the_window_after_recovery():
    """Roles in force from step 224, refined gains (same roles, a new epoch) from 346, the
    run ends at 350: the window after recovery was step 350 alone ("too few for a
    standard error"). It is the last quarter since the roles, and its prediction the mean
    of the two gains' exact levels over its steps."""
    s, rosters, assigns, est, (fast, refined), G0 = _same_roles_new_gains(
        (0.5, 0.4), (224, 346), 350)
    steps = list(range(351))
    mse = [fast if k < 346 else refined for k in steps]
    out = _failures(None, _recording(rosters, est, assigns), s, s.delays, steps, mse, G0)
    assert out["mse_steady_after_recovery_window"] == [320, 350]
    assert out["mse_steady_after_recovery_se"] is not None
    assert [(g["epoch"], g["from"], g["steps"]) for g in out["after_recovery_gains"]] == [
        (1, 320, 26), (2, 346, 5)]
    mean = (26 * fast + 5 * refined) / 31
    assert out["mse_steady_exact_over_after_recovery_window"] == pytest.approx(mean)
    assert out["mse_steady_after_recovery"] == pytest.approx(mean)
    assert out["mse_steady_exact_after_recovery"] == pytest.approx(refined)
    assert out["recovered"] is True


def test_refined_gains_with_room_after_them_have_the_window_to_themselves():
    s, rosters, assigns, est, (fast, refined), G0 = _same_roles_new_gains(
        (0.5, 0.4), (224, 346), 699)
    steps = list(range(700))
    mse = [fast if k < 346 else refined for k in steps]
    out = _failures(None, _recording(rosters, est, assigns), s, s.delays, steps, mse, G0)
    assert out["mse_steady_after_recovery_window"] == [612, 699]      # 354 // 4 = 88
    assert "after_recovery_gains" not in out
    assert out["mse_steady_after_recovery"] == pytest.approx(refined)


def test_a_roster_that_would_activate_after_the_run_ended_is_simply_not_in_force():
    rosters = [(0, (1, 2, 3), 0), (192, (1, 4, 3), 1), (457, (1, 4, 3), 2)]
    est = {1: _epochs({192: 1}, last=450), 3: _epochs({192: 1}, last=450),
           4: {k: 1 for k in range(191, 451)}}
    assigns = {(a, e): {} for a in (1, 3, 4) for e in (1, 2)}
    assert rosters_in_force(rosters, est, assigns) == ([(0, (1, 2, 3), 0),
                                                         (192, (1, 4, 3), 1)], [])


def test_final_roles_mark_killed_and_fenced_agents():
    """A killed agent's last status still says active: the record says dead, not active;
    an agent that dropped its role and lives is fenced; tokens that go at the run's end
    are no death."""
    from agent.run.summary import final_roles

    last = {1: {"active": True, "epoch": 0, "measure": ["1"]},
            2: {"active": False, "epoch": 2, "measure": ["2"]},
            3: {"active": True, "epoch": 2, "measure": ["3"]},
            4: {"active": True, "epoch": 2, "measure": ["1"]}}
    events = [{"process": "agent-1", "exit_status": -9, "step": 150},
              {"process": "agent-2", "role": "dropped", "epoch": 2, "step": 180},
              {"process": "agent-3", "liveliness": False, "step": 400},
              {"process": "agent-4", "liveliness": False, "step": 400}]
    roles = final_roles(last, events, 400)
    assert roles["1"] == {"active": False, "epoch": 0, "measure": ["1"], "dead": True,
                          "fenced": False}
    assert roles["2"]["fenced"] and not roles["2"]["dead"] and not roles["2"]["active"]
    assert roles["3"]["active"] and roles["4"]["active"]
    assert not any(roles[a]["dead"] or roles[a]["fenced"] for a in ("3", "4"))
    # a token gone before the last step (a watched run: no exit status) is a death
    events.append({"process": "agent-3", "liveliness": False, "step": 260})
    assert final_roles(last, events, 400)["3"]["dead"]


def test_failures_at_different_steps_are_named_each_once():
    from design.scenario import load_scenario
    from design.simulate import SimulationError, simulate

    s = load_scenario("paper-14")
    G = [np.zeros((s.n, len(m))) for m in s.measure]
    with pytest.raises(SimulationError, match="distinct agent rows"):
        simulate(s, G, steps=20, trials=1, seed=0, fail=[(5, [0]), (8, [0])])
    res = simulate(s, G, steps=20, trials=1, seed=0, fail=[(5, [0]), (8, [1])])
    assert res.fail_step == 5 and res.failed == (1, 2)


@pytest.mark.parametrize("rejoined", [False, True])
def test_an_agent_convicted_again_before_it_rejoined_is_one_failure(tmp_path, rejoined):
    """Two verdicts against agent 2 (a second monitor's, or one written again by a monitor
    that took the seat) with no rejoin between them are one failure, the verdicts counted;
    with a rejoin between, two (it came back, rejoined, failed again)."""
    import json

    from design.scenario import load_scenario

    s = load_scenario("paper-14-live")
    records = [{"kind": "verdict", "agent": 2, "cause": "crash", "evidence": "token",
                "step": 160, "t": 10.0, "mono": 1.0},
               {"kind": "verdict", "agent": 2, "cause": "crash", "evidence": "token",
                "step": 170, "t": 10.2, "mono": 1.2}]
    if rejoined:
        records.insert(1, {"kind": "rejoin", "agent": 2, "step": 165, "t": 10.1,
                           "healthy_s": 1.0, "standby": [2]})
    path = tmp_path / "events.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in records))
    out = _failures(path, _recording([(0, (1, 2, 3), 0)], {}, {}), s, s.delays,
                    list(range(300)), [0.3] * 300, None)
    mine = [(f["agent"], f["detected_step"], f.get("verdicts")) for f in out["failures"]]
    assert mine == ([(2, 160, None), (2, 170, None)] if rejoined else [(2, 160, 2)])
