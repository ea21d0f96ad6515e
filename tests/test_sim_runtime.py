"""The whole runtime under simulated time (agent.run.simulated): what it computes equals the
design simulator through a failure, its verdict, the reassignment and the switch, and the
invariants of ``socmon chaos`` hold over random fault schedules."""

import numpy as np
import pytest

from agent.run.chaos import draw_schedule
from agent.run.local import Fault
from agent.run.summary import compare_simulator
from agent.run.simulated import SimConfig, SimRuntime
from design.scenario import load_scenario, resolve_delays


@pytest.fixture(scope="module")
def live():
    s = load_scenario("paper-14-live")
    return s, [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure]


def _run(live, faults=(), steps=500, seed=1, **config):
    s, G = live
    return SimRuntime(s, G, s.delays, seed=seed, faults=list(faults),
                      config=SimConfig(**config)).run(steps)


@pytest.mark.parametrize("faults", [
    [], pytest.param([Fault(150, "crash", 1)], marks=pytest.mark.slow),
    [Fault(150, "crash", 1), Fault(150, "crash", 2)]])
def test_the_simulated_runtime_equals_the_design_simulator(live, faults):
    r = _run(live, faults)
    diff, how = compare_simulator(r.config, r.recording, r.steps)
    assert diff <= 1e-12, how
    assert [(f["agent"], f["cause"]) for f in r.summary["failures"]] == \
        [(f.agent, "crash") for f in faults]
    if faults:
        assert r.summary["recovered"] is True
        exact = r.summary["mse_steady_exact_after_recovery"]
        assert 0.3 * exact < r.summary["mse_steady_after_recovery"] < 3 * exact


def test_a_lie_replays_in_the_simulator(live):
    """Agent 2 publishes its estimates 3 noise std-devs off from step 100 (one receiver
    each in paper-14-live: an alert at most, no reassignment): the run equals the
    simulator's replay, the liar's published estimates against the simulator's own
    estimate plus the same lie."""
    r = _run(live, [Fault(100, "lie", 2, 0.0, 3.0)], steps=300)
    diff, how = compare_simulator(r.config, r.recording, r.steps)
    assert diff <= 1e-12, how
    assert r.summary["failures"] == []


def test_a_standby_lies_only_once_it_holds_a_role_as_in_the_simulator(live):
    """Standby 4 is scripted to lie from step 100 but holds no role until agent 1's crash
    at step 150 is answered: the run up to its first step in a role is the honest run's,
    from that step it publishes its estimates 3 noise std-devs off, the simulator
    replays it the same (it refused a standby's fault before), and the summary's fault
    says that the standby lies only once it holds a role."""
    import math

    lie = Fault(100, "lie", 4, 0.0, 3.0)
    honest = _run(live, [Fault(150, "crash", 1)], steps=300)
    r = _run(live, [lie, Fault(150, "crash", 1)], steps=300)
    diff, how = compare_simulator(r.config, r.recording, r.steps)
    assert diff <= 1e-12, how
    at = r.summary["rosters"][1]["activate_at"]
    assert r.summary["rosters"][1]["ids"] == [4, 2, 3] and at > lie.step
    est, base = r.recording.est, honest.recording.est
    for a in (2, 3):
        assert all(np.array_equal(est[a][k], base[a][k]) for k in range(at + 1))
    assert min(est[4]) == at - 1 and np.array_equal(est[4][at - 1], base[4][at - 1])
    s, _ = live
    offset = 3.0 * math.sqrt(s.measurement_noise)
    assert np.allclose(est[4][at] - base[4][at], offset)
    (recorded,) = [f for f in r.summary["faults"] if f["kind"] == "lie"]
    assert recorded["note"].startswith("agent 4 is a standby (no role at the start): it "
                                       "lies only once it holds a role")
    assert all("note" not in f for f in honest.summary["faults"])


def test_the_clock_starts_once_the_monitor_foresees_every_single_failure(live):
    """Designs slow (2 s a precomputed gain): the world waits for monitor 1 as ``up``'s
    does, so a crash at the first step is answered with precomputed gains."""
    r = _run(live, [Fault(2, "crash", 3)], steps=200, precompute_s=2.0)
    (f,) = r.summary["failures"]
    assert (f["agent"], f["precomputed"]) == (3, True), f
    assert f["activate_at"] - f["detected_step"] <= 15 and r.summary["recovered"] is True


def test_a_crash_before_the_roles_answering_another_is_answered_with_it(live):
    """Agent 2 crashes, agent 1 seven steps later, before the roles answering agent 2 are
    in force: the pair's gains, planned on the configuration still in force, are
    precomputed (pairs for small networks), so one epoch answers both, at once, and the
    run equals the simulator's replay."""
    r = _run(live, [Fault(150, "crash", 2), Fault(157, "crash", 1)])
    diff, how = compare_simulator(r.config, r.recording, r.steps)
    assert diff <= 1e-12, how
    s = r.summary
    assert s["reissues"] == [] and s["rosters_not_in_force"] == [] and s["recovered"] is True
    assert [x["ids"] for x in s["rosters"]][:2] == [[1, 2, 3], [4, 3]]
    assert [(f["agent"], f["epoch"], f["precomputed"]) for f in s["failures"]] == \
        [(2, 2, True), (1, 2, True)]
    assert s["rosters"][1]["activate_at"] - s["failures"][1]["detected_step"] <= 15


@pytest.mark.slow
def test_a_crash_before_the_roles_answering_another_replays_in_the_simulator(live):
    """The same crashes with slow designs (2 s a precomputed gain: the pair's gains are not
    known yet): the roles answering agent 2 come into force without agent 1 (no re-issue
    to a dead agent, no roster reported not in force), the next reassignment answers it,
    and the run equals the simulator's replay. A run that ends before that second switch
    cannot be replayed, and says why."""
    faults = [Fault(150, "crash", 2), Fault(158, "crash", 1)]
    r = _run(live, faults, precompute_s=2.0)
    diff, how = compare_simulator(r.config, r.recording, r.steps)
    assert diff <= 1e-12, how
    s = r.summary
    assert s["reissues"] == [] and s["rosters_not_in_force"] == [] and s["recovered"] is True
    assert [x["ids"] for x in s["rosters"]][:3] == [[1, 2, 3], [1, 4, 3], [4, 3]]
    cut = s["rosters"][2]["activate_at"] - 2
    r = _run(live, faults, steps=cut, precompute_s=2.0)
    diff, how = compare_simulator(r.config, r.recording, r.steps)
    assert diff == float("inf") and "agent 1 was killed before the configuration" in how
    assert r.summary["recovered"] is False and (
        "agent 1 was convicted but the roles answering it were not in force by the run's "
        "end: not recovered") in r.summary["warnings"]


def test_a_hang_is_convicted_and_its_role_handed_over(live):
    r = _run(live, [Fault(150, "hang", 2)])
    (f,) = r.summary["failures"]
    assert (f["agent"], f["cause"]) == (2, "hang") and r.summary["recovered"] is True
    # the hang timeout (1 s) is 50 steps of 20 ms; statuses every 0.2 s; the failure was
    # foreseen (precomputed), so the roles follow within the lead of 10 steps
    assert 150 + 40 <= f["detected_step"] <= 150 + 60
    assert f["precomputed"] and f["activate_at"] - f["detected_step"] <= 15


def test_a_stop_shorter_than_the_hang_timeout_convicts_nobody(live):
    r = _run(live, [Fault(150, "stop", 3, 0.5)])
    assert r.summary["failures"] == [] and r.summary["late"] > 0


@pytest.mark.slow
def test_a_long_stop_is_convicted_and_the_agent_rejoins_after_probation(live):
    r = _run(live, [Fault(150, "stop", 3, 3.0)], steps=800)
    (f,) = r.summary["failures"]
    assert f["agent"] == 3 and r.summary["recovered"] is True
    assert f["rejoined_step"] > f["activate_at"] > f["detected_step"]
    assert r.violations() == []


@pytest.mark.slow
def test_an_agent_convicted_twice_is_paired_with_each_fault_and_reassignment(live):
    """Agent 1 stopped 2 s at step 200 (convicted, replaced by the standby 4), rejoins as
    the standby after probation, takes a role again when agent 4 is killed at 700, and is
    stopped 2.5 s at 900: two verdicts, each with its own detection time and its own,
    later, switch; the convicted agent rejoined between them."""
    r = _run(live, [Fault(200, "stop", 1, 2.0), Fault(700, "kill", 4),
                    Fault(900, "stop", 1, 2.5)], steps=1300)
    first, second = [f for f in r.summary["failures"] if f["agent"] == 1]
    for f, step in ((first, 200), (second, 900)):
        assert step < f["detected_step"] < f["activate_at"] < step + 150, f
        assert 800 < f["detection_ms"] < 1500, f
    assert first["epoch"] < second["epoch"]
    assert first["activate_at"] < first["rejoined_step"] < 700
    assert r.summary["recovered"] is True and r.violations() == []


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(8))
def test_random_fault_schedules_keep_the_chaos_invariants(live, seed):
    """kill, stop and hang drawn by agent.run.chaos.draw_schedule (3 faults per 1000 steps,
    1500 steps): recovery within its bound, fencing, error, convictions."""
    s, G = live
    schedule = draw_schedule(s, seed, 1500, kinds=("kill", "stop", "hang"), rate=3)
    r = SimRuntime(s, G, resolve_delays(s, "scenario"), seed=seed, faults=schedule).run(1500)
    assert [v.to_dict() for v in r.violations()] == []


@pytest.mark.parametrize("seed", [100] + [pytest.param(k, marks=pytest.mark.slow)
                                          for k in range(101, 105)])
def test_short_schedules_of_every_kind_keep_the_chaos_invariants(live, seed):
    """800 steps, every fault kind a simulated run applies but the scripted ones (kill,
    stop, hang, stuck sensor, partition, delay, drop, slow, the monitor's), 5 faults per
    1000 steps."""
    from agent.run.simulated import FAULT_KINDS, SCRIPTED

    s, G = live
    schedule = draw_schedule(s, seed, 800, kinds=tuple(k for k in FAULT_KINDS
                                                       if k not in SCRIPTED), rate=5)
    r = SimRuntime(s, G, resolve_delays(s, "scenario"), seed=seed, faults=schedule).run(800)
    assert [v.to_dict() for v in r.violations()] == []


@pytest.mark.parametrize("fault, kill", [(Fault(200, "monitor"), 400),
                                         (Fault(200, "monitorstop", 0, 1.0), 400),
                                         pytest.param(Fault(200, "monitorstop", 0, 5.0), 600,
                                                      marks=pytest.mark.slow),
                                         pytest.param(Fault(200, "monitorstop", 0, 30.0), 2000,
                                                      marks=pytest.mark.slow)])
def test_the_monitor_killed_or_paused_hands_over_and_a_later_crash_recovers(live, fault,
                                                                             kill):
    """Two monitors, as up starts them (agent.monitor.core.MonitorSeat): the acting one
    killed (and started again) or stopped 1, 5 or 30 s; agent 1 killed afterwards is
    convicted and replaced."""
    r = _run(live, [fault, Fault(kill, "kill", 1)], steps=kill + 300)
    assert [(f["agent"], f["cause"]) for f in r.summary["failures"]] == [(1, "crash")]
    assert r.summary["recovered"] is True and r.violations() == []


def test_a_crash_while_the_restarted_monitor_listens_is_answered_by_the_one_acting(live):
    """The acting monitor (1) killed at step 200 and started again (its token back 0.5 s
    later, then 1.5 s of listening); agent 1 killed at 240, in that listening: monitor 2,
    acting since 200, goes on acting until monitor 1 is about to, and answers the crash
    at once (it used to hand the seat over the moment monitor 1's token came back, and
    nobody acted until monitor 1 had listened: a live chaos run's stop went unanswered)."""
    r = _run(live, [Fault(200, "monitor"), Fault(240, "kill", 1)], steps=500)
    (f,) = r.summary["failures"]
    assert (f["agent"], f["cause"]) == (1, "crash") and f["detected_step"] <= 245, f
    assert r.summary["recovered"] is True and r.violations() == []


def test_with_every_monitor_gone_a_crash_is_reported_unrecovered(live):
    r = _run(live, [Fault(200, "monitorsgone"), Fault(400, "kill", 1)], steps=700)
    (f,) = r.summary["failures"]
    assert (f["agent"], f["detected"]) == (1, False) and r.summary["recovered"] is False
    assert r.recording.no_monitor_since is not None


@pytest.mark.slow
def test_socmon_chaos_simulated_reports_every_seed(tmp_path, capsys, live_gains):
    import json

    from agent.cli.main import main

    code = main(["chaos", "paper-14-live", "--simulated", "7:9", "--duration", "600",
                 "--faults", "kill,stop,monitor", "--rate", "5", "--gains", str(live_gains),
                 "--json"])
    report = json.loads(capsys.readouterr().out)
    assert code == (1 if report["violations"] else 0)
    assert report["runs"] == 2 and report["seeds"] == [7, 9] and report["steps"] == 600
    assert report["schema_version"] == 1 and report["scenario"] == "paper-14-live"
    assert report["delays"] == [[0, 0, 0]] * 3
    assert sum(report["faults"].values()) >= 2
    assert main(["chaos", "paper-14-live", "--simulated", "0:2", "--faults", "linkdown"]) == 2
    assert "cannot be simulated" in capsys.readouterr().err
    for flags, says in ((["--rate", "-1"], "--rate: must be in [0, 6.25]"),
                        (["--rate", "nan"], "got nan"),
                        (["--duration", "50"], "--duration: must be an integer >= 100")):
        assert main(["chaos", "paper-14-live", "--simulated", "0:2", *flags]) == 2
        assert says in capsys.readouterr().err


def test_a_foreseen_crash_switches_first_to_the_precomputed_polished_gain(live):
    """The precompute's polish pass has come back 3 s into the run: the switch uses the
    polished first gain (not the fast one, whose level and transient made the error's
    peak), and the refined gain follows under the next epoch."""
    r = _run(live, [Fault(150, "crash", 2)], steps=300)
    assert r.summary["recovered"] is True
    history = [h for m in r.monitors.values()
               for h in (getattr(m, "core", None) or m[0]).history]
    first, *later = history
    assert first["precomputed"] and first["gains"] == "fast" and first.get("gains_polished")
    assert [h["gains"] for h in later] == ["refined"]


class _LateAssignment(SimRuntime):
    """Agent ``agent`` hears every assignment of ``epoch`` ``late_s`` late (a slow link)."""

    agent, epoch, late_s = 3, 1, 0.5

    def _publish(self, src, msg):
        from agent.monitor.core import Assignment

        if isinstance(msg, Assignment) and msg.agent == self.agent and msg.epoch == self.epoch:
            self.after(self.late_s, lambda: SimRuntime._publish(self, src, msg))
            return
        super()._publish(src, msg)


@pytest.mark.slow
def test_an_agent_that_hears_its_roles_too_late_is_replayed_as_it_ran(live):
    """Agent 1 crashes; standby 4 takes its role and agents 2 and 3 get new gains, but
    agent 3 hears its assignment after its step: it runs its older role (still listening
    to the dead agent 1) until the re-issue while 2 and 4 run the new ones. The record
    says so, the simulator replays that mixed configuration as the agents ran it, and the
    refined gains wait for the re-issue's step instead of superseding it (they came back
    before it: a later ``activate_at`` would have left agent 3 behind 46 steps more). Then
    agent 2 crashes: answered within the head start (15 steps, grown by the re-issue)."""
    s, G = live
    r = _LateAssignment(s, G, s.delays, seed=1,
                        faults=[Fault(150, "crash", 1), Fault(260, "crash", 2)]).run(450)
    summary = r.summary
    (reissue,) = summary["reissues"]
    assert reissue["reason"] == "activate_at passed before agents [3] confirmed"
    assert any("was not run by all its agents" in w and "agent 3 never" in w
               for w in summary["warnings"]), summary["warnings"]
    diff, how = compare_simulator(r.config, r.recording, r.steps)
    assert diff <= 1e-12, how
    in_force = [(x["epoch"], x["activate_at"]) for x in summary["rosters"]]
    assert in_force[1] == (reissue["epoch"], reissue["activate_at"]), in_force
    second = next(f for f in summary["failures"] if f["agent"] == 2)
    assert any(x["ids"] == [4, 3] and x["activate_at"] <= second["detected_step"] + 20
               for x in summary["rosters"]), (second, summary["rosters"])
    assert summary["recovered"] is True


@pytest.fixture(scope="module")
def long_delays(live):
    s, _ = live
    return s, [0.3 * np.eye(s.n)[:, list(m)] for m in s.measure], resolve_delays(s, "uniform:15")


@pytest.mark.slow      # the monitor's gain designs at 15-step delays: about 20 s of CPU
def test_a_switch_before_the_last_estimate_reached_the_standby_equals_the_simulator(
        long_delays):
    """15-step delays, roles in force 10 steps after the crash: the standby has not yet
    received the failed agent's last estimate (stamp 149 arrives at 164), so it takes over
    the freshest one it holds (stamp 144 at step 160), as the simulator's replacement."""
    s, G, D = long_delays
    r = SimRuntime(s, G, D, seed=1, faults=[Fault(150, "crash", 2)]).run(220)
    assert r.summary["rosters"][1]["activate_at"] < 150 + 15
    diff, how = compare_simulator(r.config, r.recording, r.steps)
    assert diff <= 1e-12, how


@pytest.mark.slow
@pytest.mark.parametrize("late", [4, 1])
def test_an_agent_or_standby_that_hears_its_roles_too_late_at_long_delays_is_replayed(
        long_delays, late):
    """15-step delays, agent 2 crashes, and one agent of the reassignment hears it after
    its step: the survivor (1) runs its older role until the re-issue; the standby (4)
    that takes agent 2's row starts nothing until then, while its receivers read agent
    2's stream on its link (the continuity rule). The simulator replays both as run."""
    s, G, D = long_delays

    class Late(_LateAssignment):
        agent = late

    r = Late(s, G, D, seed=1, faults=[Fault(150, "crash", 2)]).run(260)
    assert any(f"agent {late} never" in w for w in r.summary["warnings"]), r.summary["warnings"]
    diff, how = compare_simulator(r.config, r.recording, r.steps)
    assert diff <= 1e-12, how
    assert r.summary["recovered"] is True


def test_a_payload_shared_by_its_receivers_is_decoded_once_and_counted_for_each():
    """The simulated network decodes a payload sent to several receivers once, through the
    codec and its validation, and hands every receiver the same message; a malformed one
    is dropped for every receiver, with its reason."""
    from unittest import mock

    from agent.protocol import wire
    from agent.run import simulated
    from broker_free_net.codec import MessageStats

    stats = MessageStats()
    payload = wire.encode_est(2, 7, np.arange(3.0), epoch=1, t=0.5)
    shared = simulated._Shared(payload, wire.est_schema(3))
    with mock.patch.object(simulated, "decode", wraps=simulated.decode) as decode:
        got = [shared.decode(stats) for _ in range(3)]
    assert decode.call_count == 1 and stats.accepted == 3
    assert got[0] is got[1] is got[2] and (got[0]["agent"], got[0]["step"]) == (2, 7)
    assert not got[0]["x"].flags.writeable and list(got[0]["x"]) == [0.0, 1.0, 2.0]
    bad = simulated._Shared(payload, wire.est_schema(4))          # the wrong length
    assert [bad.decode(stats) for _ in range(2)] == [None, None]
    assert sum(stats.dropped.values()) == 2 and list(stats.dropped) == ["shape"]


def test_every_message_of_a_simulated_run_goes_through_the_codec(live):
    r = SimRuntime(live[0], live[1], live[0].delays, seed=3)
    r.run(60)
    assert r.stats.accepted > 4 * 60 and r.stats.total_dropped == 0


@pytest.mark.parametrize("seed", range(20))
def test_a_neighbour_keeps_the_newest_history_stamps_whatever_their_order(seed):
    """AgentCore's store of a neighbour's estimates (pruned as a scan of every stamp
    did): the stamps within ``history`` of the newest, in order, late, repeated."""
    from agent.node.core import _Neighbour

    rng = np.random.default_rng(seed)
    history = int(rng.integers(1, 12))
    stamps = np.arange(200) + (rng.integers(-6, 7, 200) * (rng.random(200) < 0.1))
    nb, ref = _Neighbour(8), {}
    for s in stamps.tolist():
        nb.keep(s, float(s), history)
        ref[s] = float(s)
        if len(ref) > history:
            newest = max(ref)
            for old in [old for old in ref if old <= newest - history]:
                del ref[old]
        assert nb.est == ref and nb.newest == max(ref)


def test_a_seat_decides_the_same_when_the_monitors_alive_repeat():
    """MonitorSeat keeps what it made of the monitors alive while they are the same: the
    decisions over a run of ticks equal those of a seat asked afresh every tick."""
    from agent.monitor.core import MonitorConfig, MonitorCore, MonitorSeat

    s = load_scenario("paper-14-live")
    G = [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure]
    ticks = [(0.01 * k, [(1, "a"), (2, "b")] if k < 150 or k > 180 else [(2, "b")])
             for k in range(400)] + [(4.0 + 0.01 * k, [(1, "c"), (2, "b")]) for k in range(300)]

    def states(fresh: bool):
        core = MonitorCore(MonitorConfig(), s, G, s.delays)
        seat = MonitorSeat(core, 2, 0.0, listen_s=0.5)
        out = []
        for now, alive in ticks:
            if fresh:
                seat._alive_in = None
            out.append((seat.decide(now, alive), dict(seat.seen_since)))
        return out

    assert states(fresh=False) == states(fresh=True)


@pytest.fixture(scope="module")
def complete():
    """paper-14-live with every agent listening to both others (two receivers each, so a
    lie can be corroborated) and short-designed gains (its residual tests need a stable
    loop)."""
    from design.gain_design import design_gains

    s = load_scenario("paper-14-live")
    W = np.full((3, 3), 0.25)
    np.fill_diagonal(W, 0.5)
    s = s.replace(W=W)
    return s, list(design_gains(s, exact_mse=False, starts=1, max_iter=30, gaps=False).G)


def test_a_lie_after_a_recovery_is_convicted_on_the_new_configurations_tests(complete):
    """Agent 3 crashes at step 200 (standby 4 takes its row under epoch 1, its assignment
    carrying each agent's residual tests of the new configuration); agent 2 lies by 5
    noise std-devs from step 450: convicted ``inconsistent estimates`` on the tests of
    the configuration in force (epoch 1's, or 2's once the refined gain is in force),
    replaced, and nobody else accused; the invariants hold."""
    r = _run(complete, [Fault(200, "crash", 3), Fault(450, "lie", 2, 0.0, 5.0)], steps=700)
    s = r.summary
    assert [(f["agent"], f["cause"]) for f in s["failures"]] == \
        [(3, "crash"), (2, "inconsistent estimates")], s["failures"]
    f = s["failures"][1]
    assert "residual tests of the configuration of epoch " in f["evidence"], f
    assert 450 <= f["detected_step"] <= 470 and s["residual_alerts"] == []
    assert s["recovered"] is True and r.violations() == []


def test_without_the_precompute_a_crash_is_answered_by_a_counted_first_gain(live):
    """As ``up --no-precompute`` at 7-step delays: the crash's first gain is requested when
    it comes; the gains in force, carried, are counted below halfway from the fast target
    to 1 and go out without an eigenvalue problem; the refined gain follows; the run
    recovers and equals the simulator's replay."""
    from agent.monitor.core import design_gains_for
    from design.reconfigure import FAST_TARGET
    from design.roster import Roster

    s, _ = live
    delays = resolve_delays(s, "uniform:7")
    G, _ = design_gains_for(Roster.initial(s, delays), "fast")
    r = SimRuntime(s, G, delays, seed=1, faults=[Fault(150, "crash", 2)],
                   config=SimConfig(precompute=False, design_s=0.2)).run(300)
    assert r.summary["recovered"] is True
    diff, how = compare_simulator(r.config, r.recording, r.steps)
    assert diff <= 1e-12, how
    first, *later = [h for m in r.monitors.values()
                     for h in (getattr(m, "core", None) or m[0]).history]
    assert first["precomputed"] is False and first["gains"] == "fast"
    assert first["gains_rho"] is None and first["gains_rho_below"] == (1 + FAST_TARGET) / 2
    assert [h["gains"] for h in later] == ["refined"]
