"""MonitorCore stepped by hand: verdicts, their guards, and the reassignment it publishes."""

import numpy as np
import pytest

from agent.monitor.core import (Assignment, GainSource, MonitorConfig, MonitorCore, RosterUpdate,
                                _gain_words, design_gains_for)


def _status(agent, step, epoch=0, active=True, pending=0, sensor_last=None):
    return {"agent": agent, "step": step, "epoch": epoch, "active": active,
            "ctl": {"pending": pending}, "sensor": {"last_step": step if sensor_last is None
                                                    else sensor_last}}


@pytest.fixture
def core(paper14):
    G = [0.5 * np.eye(14)[:, list(m)] for m in paper14.measure]
    c = MonitorCore(MonitorConfig(hang_timeout_s=1.0, settle_s=0.0, step_s=0.02), paper14,
                    G, paper14.delays)
    for a in (1, 2, 3, 4):
        c.on_liveliness("agent", a, True, 0.0)
    return c


def _advance(core, t0, t1, steps_at, skip=(), dt=0.1):
    """Statuses of every agent every dt from t0 to t1; steps follow the clock."""
    t = t0
    out = []
    while t <= t1 + 1e-9:
        for a in (1, 2, 3, 4):
            if a not in skip:
                core.on_status(_status(a, int(steps_at(t)), active=a <= 3), t)
        out += core.tick(t)
        t += dt
    return out


def test_a_healthy_run_convicts_nobody_even_when_everyone_is_slow(core):
    out = _advance(core, 0.0, 5.0, lambda t: 50 * t)
    out += _advance(core, 5.1, 10.0, lambda t: 250)          # the whole run stalls
    assert out == [] and core.verdicts == []


def test_crash_is_convicted_and_the_standby_takes_node_8(core, paper14):
    _advance(core, 0.0, 2.0, lambda t: 50 * t)
    core.on_liveliness("agent", 1, False, 2.05)
    out = core.tick(2.05)
    (v,) = core.verdicts
    assert (v.agent, v.cause) == (1, "crash")
    asg = {m.agent: m for m in out if isinstance(m, Assignment)}
    (roster,) = [m for m in out if isinstance(m, RosterUpdate)]
    assert roster.ids == (4, 2, 3) and roster.epoch == 1
    assert asg[4].spec.measure == ("8",) and asg[4].spec.take_over == 1
    # one epoch and one activate_at for everyone, ahead of the extrapolated step (102)
    assert {m.epoch for m in asg.values()} == {1}
    assert {m.activate_at for m in asg.values()} == {roster.activate_at}
    assert roster.activate_at >= 102 + core.config.lead_steps
    # W row of agent 3 now listens to 4 with agent 1's weight (renormalised rows)
    assert asg[3].spec.neighbours == {4: paper14.W[2, 0]}


def _stalling_run(core, t1, stalls, hung=None, seed=0):
    """Statuses of agents 1-4 every 0.2 s from 0 to t1, each loop stalling now and then
    (``stalls(t)``: the gaps drawn from at time t, as on a machine whose load rises);
    ``hung``: ``(agent, from)``, an agent that stops for good. Steps follow the world
    (50 a second)."""
    rng = np.random.default_rng(seed)
    due = {a: 0.0 for a in (1, 2, 3, 4)}
    t, out = 0.0, []
    while t <= t1:
        for a in due:
            if hung and a == hung[0] and t >= hung[1]:
                continue
            if t >= due[a]:
                core.on_status(_status(a, int(50 * t), active=a <= 3), t)
                due[a] = t + (float(rng.choice(stalls(t))) if rng.random() < 0.1 else 0.2)
        out += core.tick(t)
        t = round(t + 0.05, 6)
    return out


def test_the_hang_timeout_grows_with_the_statuses_pace_and_a_hang_is_still_caught(paper14):
    """Loops that stall now and then, 0.5-0.9 s, then 0.8-1.4 s as the load rises: with the
    timeout fixed at 1 s healthy agents are convicted; with the timeout following the
    statuses' pace nobody is, and an agent that stops for good is convicted within the
    ceiling."""
    G = [0.5 * np.eye(14)[:, list(m)] for m in paper14.measure]

    def core_with(**kw):
        c = MonitorCore(MonitorConfig(hang_timeout_s=1.0, settle_s=0.0, step_s=0.02, **kw),
                        paper14, G, paper14.delays)
        for a in (1, 2, 3, 4):
            c.on_liveliness("agent", a, True, 0.0)
        return c

    def stalls(t):
        return [0.5, 0.7, 0.9] if t < 15 else [0.8, 1.0, 1.2, 1.4]

    fixed = core_with(hang_timeout_max_s=1.0)
    _stalling_run(fixed, 60.0, stalls)
    assert [v.cause for v in fixed.verdicts] and fixed.hang_timeout() == 1.0
    for seed in range(4):
        adaptive = core_with()
        _stalling_run(adaptive, 60.0, stalls, seed=seed)
        assert adaptive.verdicts == [] and 1.4 < adaptive.hang_timeout() < 5.0, seed
    assert any("hang timeout" in e for e in adaptive.events)
    hung = core_with()
    _stalling_run(hung, 60.0, stalls, hung=(2, 40.0))
    [v] = hung.verdicts
    assert (v.agent, v.cause) == (2, "hang") and v.at - 40.0 <= 5.0 + 0.3
    assert "at the statuses' pace" in v.evidence


def test_a_steady_pace_keeps_the_hang_timeout_at_its_floor(core):
    _advance(core, 0.0, 30.0, lambda t: 50 * t, dt=0.2)
    assert core.hang_timeout() == core.config.hang_timeout_s


def test_a_pause_of_the_monitor_or_the_world_does_not_grow_the_hang_timeout(core):
    """The backlog a paused monitor reads after its first tick closes, for each agent, a
    gap as long as the pause: not a healthy loop's gap. Nor is the world's absence."""
    _advance(core, 0.0, 2.0, lambda t: 50 * t, dt=0.2)
    core.tick(7.0)                                     # back from a 5 s pause
    _advance(core, 7.01, 12.0, lambda t: 50 * t, dt=0.2)
    assert core.hang_timeout() == core.config.hang_timeout_s
    core.on_liveliness("world", 0, True, 12.0)
    core.on_liveliness("world", 0, False, 12.1)
    core.tick(12.2)
    core.on_liveliness("world", 0, True, 16.0)         # the world paused 4 s
    _advance(core, 16.0, 20.0, lambda t: 50 * t, dt=0.2)
    assert core.hang_timeout() == core.config.hang_timeout_s
    # the monitor ticking throughout, every loop stalls 3 s: that gap grows it
    for k in range(1, 30):
        core.tick(20.0 + 0.1 * k)
    _advance(core, 23.0, 23.0, lambda t: 50 * t)
    assert core.hang_timeout() == core.config.hang_timeout_max_s and core.verdicts == []


def test_an_agent_on_probation_does_not_grow_the_hang_timeout(core):
    """Agent 1 convicted (crash) and fenced, still running as a standby on probation,
    stalls 2.5 s: its stall is a fault's, not a healthy loop's, and the timeout stays at
    its floor, so that another agent's later 1.5 s stop is still convicted (simulated, a
    stopped standby's gaps had raised it to 3.65 s and such a stop went unconvicted)."""
    _advance(core, 0.0, 2.0, lambda t: 50 * t, dt=0.2)
    core.on_liveliness("agent", 1, False, 2.05)
    core.tick(2.05)
    assert 1 in core.failed
    core.on_liveliness("agent", 1, True, 2.3)
    _advance(core, 2.2, 4.0, lambda t: 50 * t, dt=0.2)
    _advance(core, 4.2, 6.4, lambda t: 50 * t, skip=(1,), dt=0.2)    # agent 1 stalls
    _advance(core, 6.6, 8.0, lambda t: 50 * t, dt=0.2)
    assert 1 in core.on_probation and core.hang_timeout() == core.config.hang_timeout_s
    # a healthy standby's stall (shorter than the timeout: not a hang) does grow it
    _advance(core, 8.2, 9.0, lambda t: 50 * t, skip=(4,), dt=0.2)
    _advance(core, 9.2, 9.4, lambda t: 50 * t, dt=0.2)
    assert core.hang_timeout() > 1.5 * core.config.hang_timeout_s and core.verdicts[1:] == []


def test_a_standby_stopped_past_its_lease_does_not_grow_the_hang_timeout(core):
    """Standby agent 4 stopped 3 s: its token lapses with its lease, so its stall is a
    stopped process's, not the machine's pace. The timeout stays at its floor (it went
    to its 5 s ceiling), and agent 2 hung right after is convicted at it."""
    _advance(core, 0.0, 4.0, lambda t: 50 * t, dt=0.2)
    _advance(core, 4.2, 5.2, lambda t: 50 * t, skip=(4,), dt=0.2)      # agent 4 stopped
    core.on_liveliness("agent", 4, False, 5.3)           # its lease lapsed
    _advance(core, 5.4, 7.0, lambda t: 50 * t, skip=(4,), dt=0.2)
    core.on_liveliness("agent", 4, True, 7.1)            # resumed
    _advance(core, 7.2, 9.0, lambda t: 50 * t, dt=0.2)
    assert core.hang_timeout() == core.config.hang_timeout_s and core.verdicts == []
    _advance(core, 9.2, 11.0, lambda t: 50 * t, skip=(2,), dt=0.2)     # agent 2 hangs
    [v] = core.verdicts
    assert (v.agent, v.cause) == (2, "hang") and v.at - 9.0 <= 1.0 + 0.25


def test_hang_needs_both_no_progress_and_the_others_moving_on(core):
    _advance(core, 0.0, 1.0, lambda t: 50 * t)
    out = _advance(core, 1.1, 1.9, lambda t: 50 * t, skip=(2,))
    assert core.verdicts == []                                # 0.9 s: below the timeout
    out = _advance(core, 2.0, 2.6, lambda t: 50 * t, skip=(2,))
    assert [(v.agent, v.cause) for v in core.verdicts] == [(2, "hang")]
    assert any(isinstance(m, RosterUpdate) for m in out)


def test_a_paused_monitor_suspends_its_verdicts(core):
    _advance(core, 0.0, 1.0, lambda t: 50 * t)
    # the monitor itself sleeps 3 s: agent 2's status looks 3 s old, but that is no evidence
    core.on_status(_status(1, 200), 4.0)
    core.on_status(_status(3, 200), 4.0)
    assert core.tick(4.0) == [] and core.verdicts == []
    assert any("paused" in e for e in core.events)


def test_the_head_start_counts_from_the_verdict_not_from_the_settle_window(paper14):
    """The settle window (waiting for agents killed together) ends a step and a half after
    the verdict: the precomputed roles still switch lead_steps after the verdict's step,
    not lead_steps after the moment they go out."""
    G = [0.5 * np.eye(14)[:, list(m)] for m in paper14.measure]
    c = MonitorCore(MonitorConfig(hang_timeout_s=1.0, settle_s=0.03, step_s=0.02), paper14,
                    G, paper14.delays)
    for a in (1, 2, 3, 4):
        c.on_liveliness("agent", a, True, 0.0)
    _advance(c, 0.0, 2.0, lambda t: 50 * t)
    c.on_liveliness("agent", 1, False, 2.05)
    assert c.tick(2.05) == []                       # inside the settle window
    out = c.tick(2.08)
    (v,) = c.verdicts
    assert v.step == c.current_step(2.05) and c.current_step(2.08) > v.step
    (roster,) = [m for m in out if isinstance(m, RosterUpdate)]
    assert roster.activate_at == v.step + c.config.lead_steps


def test_roles_designed_after_the_verdict_still_get_a_head_start(core):
    """A gain ready 0.5 s (25 steps) after the verdict: its roles go out lead_steps - 1
    steps ahead of the step then, never at a step already past."""
    _advance(core, 0.0, 2.0, lambda t: 50 * t)
    core.gains.ready = lambda *a, **k: False
    core.on_liveliness("agent", 1, False, 2.05)
    assert not [m for m in core.tick(2.05) if isinstance(m, RosterUpdate)]
    (v,) = core.verdicts
    del core.gains.ready
    out = core.tick(2.55)
    (roster,) = [m for m in out if isinstance(m, RosterUpdate)]
    assert roster.activate_at == core.current_step(2.55) + core.config.lead_steps - 1
    assert roster.activate_at > v.step + core.config.lead_steps


def test_unconfirmed_assignments_are_resent_then_reissued(core):
    _advance(core, 0.0, 2.0, lambda t: 50 * t)
    core.on_liveliness("agent", 1, False, 2.05)
    first = core.tick(2.05)
    at = next(m for m in first if isinstance(m, RosterUpdate)).activate_at
    assert at == 102 + core.config.lead_steps
    # before the resend period nothing; after it the same assignments again
    assert core.tick(2.10) == []
    # nobody confirmed and activate_at is reached while the agents step on: they did not
    # hear it in time; same roles, new epoch, later step
    t = 2.0 + (at - 100) * 0.02
    for a in (2, 3, 4):
        core.on_status(_status(a, at - 1, active=a <= 3), t - 0.01)
    later = core.tick(t)
    (roster,) = [m for m in later if isinstance(m, RosterUpdate)]
    assert roster.epoch == 2 and roster.activate_at > at and roster.ids == (4, 2, 3)
    # the agents heard it too late: the re-issue gives them twice the head start
    assert core.lead == 2 * core.config.lead_steps
    assert roster.activate_at - core.current_step(t) == core.lead
    # confirmations clear them
    for a in (2, 3, 4):
        core.on_status(_status(a, at, epoch=0, pending=2), t + 0.01)
    core.tick(t + 0.01)
    assert core.confirmed()
    assert core.lead == 2 * core.config.lead_steps     # kept for the next reassignment
    # the next reassignment goes out with it; confirmed in time, the lead comes back halfway
    t = 2.0 + (roster.activate_at + 5 - 100) * 0.02        # epoch 2 in force
    for a in (2, 3, 4):
        core.on_status(_status(a, roster.activate_at + 5, epoch=2), t)
    core.on_liveliness("agent", 3, False, t)
    (msg,) = [m for m in core.tick(t) if isinstance(m, RosterUpdate)]
    assert msg.activate_at - core.current_step(t) == 2 * core.config.lead_steps
    for a in msg.ids:
        core.on_status(_status(a, msg.activate_at - 5, epoch=2, pending=msg.epoch), t + 0.05)
    core.tick(t + 0.05)
    assert core.confirmed() and core.lead == (3 * core.config.lead_steps) // 2


def test_roles_are_not_reissued_to_an_agent_that_stopped_stepping(core):
    """Agent 1 crashes; agent 2 stops stepping before it confirmed the roles that answer
    it (dead, not convicted yet) while 3 and 4 confirmed: at activate_at nothing is
    re-issued (3 and 4 switch together; a re-issue would replace their pending roles
    before the step, for some of them only)."""
    _advance(core, 0.0, 2.0, lambda t: 50 * t)
    core.on_liveliness("agent", 1, False, 2.05)
    (msg,) = [m for m in core.tick(2.05) if isinstance(m, RosterUpdate)]
    t = 2.05
    while core.current_step(t) < msg.activate_at + 3:
        t = round(t + 0.05, 6)
        for a in (3, 4):
            core.on_status(_status(a, int(50 * t), epoch=0, pending=msg.epoch), t)
        # the same roles re-sent to agent 2 at most, never a new epoch
        assert {m.epoch for m in core.tick(t) if isinstance(m, RosterUpdate)} <= {msg.epoch}
    assert core.reissues == [] and core.epoch == msg.epoch


def test_no_candidate_left_is_said_loudly_and_monitoring_goes_on(core):
    _advance(core, 0.0, 1.0, lambda t: 50 * t)
    for a in (1, 2, 3):
        core.on_liveliness("agent", a, False, 1.05)
    core.on_liveliness("agent", 4, False, 1.05)
    # every token at once: no telling it from this monitor's own links lapsing, until the
    # statuses stay away for the hang timeout
    t = 1.05
    while t < 1.05 + core.config.hang_timeout_s + 0.2:
        assert core.tick(t) == []
        t = round(t + 0.05, 6)
    assert core.unrecoverable and any("IMPOSSIBLE" in e for e in core.events)


def test_an_agent_of_the_newest_epoch_whose_token_is_down_is_adopted_and_judged(core,
                                                                                 paper14):
    """A monitor that takes the seat hearing no roster (the acting one starved of CPU)
    while agent 1, active in epoch 2, is stopped and its token lapsed: agent 1 is in the
    configuration it adopts, and convicted by the evidence (a live chaos run adopted
    [4] alone, counted agent 1 failed with no verdict and never answered its stop)."""
    fresh = MonitorCore(MonitorConfig(hang_timeout_s=1.0, settle_s=0.0, step_s=0.02),
                        paper14, core.G, paper14.delays)
    W = paper14.W
    roles = {1: ({2: W[0, 1]}, ["7"]), 4: ({3: W[1, 2]}, ["9"]), 3: ({1: W[2, 0]}, ["12"])}
    for a, (nbrs, measure) in roles.items():
        fresh.on_liveliness("agent", a, True, 0.0)
        fresh.on_status({**_status(a, 300, epoch=2), "neighbours": {
            {2: 4}.get(b, b): w for b, w in nbrs.items()}, "measure": measure}, 0.0)
    fresh.on_liveliness("agent", 2, True, 0.0)
    fresh.on_status(_status(2, 300, epoch=1, active=False), 0.0)
    fresh.on_liveliness("agent", 1, False, 0.1)       # stopped: its token lapsed
    assert fresh.adopt(None, 2)
    assert fresh.roster.ids == (1, 3, 4) and 1 not in fresh.failed
    assert fresh.roster.standby_ids == (2,)
    t = 0.1
    while t < 2.0 and not fresh.verdicts:
        t = round(t + 0.05, 6)
        for a in (3, 4, 2):
            fresh.on_status({**_status(a, 300 + int(50 * t), epoch=2 if a != 2 else 1,
                                       active=a != 2)}, t)
        fresh.tick(t)
    assert [(v.agent, v.cause) for v in fresh.verdicts] == [(1, "crash")]


def test_a_restarted_monitor_adopts_the_configuration_from_statuses(core, paper14):
    fresh = MonitorCore(MonitorConfig(), paper14, core.G, paper14.delays)
    W3 = paper14.W
    for a, nbrs, measure in ((4, {2: W3[0, 1]}, ["8"]), (2, {3: W3[1, 2]}, ["9"]),
                             (3, {4: W3[2, 0]}, ["12"])):
        fresh.on_liveliness("agent", a, True, 0.0)
        fresh.on_status({**_status(a, 300, epoch=5), "neighbours": nbrs, "measure": measure},
                        0.0)
    assert fresh.adopt([4, 2, 3], epoch=5)
    assert fresh.roster.ids == (4, 2, 3) and fresh.epoch == 5 and 1 in fresh.failed
    np.testing.assert_allclose(fresh.roster.scenario.W, W3)


def test_silent_agent_is_convicted_from_its_listeners_ages(core, paper14):
    """Agent 2 advances, but from t = 1 s agent 1 (its only listener in paper-14) holds
    nothing of it fresher than step 50: once that estimate is older than 25 steps and then
    the hang timeout (75 steps at 20 ms), a 'silent' verdict."""
    assert core.detector.silent_bound() == 75
    t, ages = 0.0, []
    while t < 3.0 and not core.verdicts:
        age = 1 if t < 1.0 else round(50 * (t - 1.0)) + 1
        ages.append(age)
        _feed_ages(core, paper14, t, age)
        t = round(t + 0.1, 6)
    (v,) = core.verdicts
    assert (v.agent, v.cause) == (2, "silent") and ages[-2] <= 75 < ages[-1]
    assert f"{ages[-1]} steps (agent 1)" in v.evidence


def test_a_monitor_taking_the_seat_during_a_silence_convicts_on_the_ages_at_once(core,
                                                                                paper14):
    """A monitor that starts watching while agent 2 has been silent for 100 steps (restarted,
    or handed the seat back by a monitor that was about to convict) convicts it on its first
    look at the listeners' ages: the rule has no clock of the monitor's own to restart (a
    live chaos run lost 55 steps to a hand-over in the middle of a partition)."""
    _feed_ages(core, paper14, 0.0, 100)
    assert [(v.agent, v.cause) for v in core.verdicts] == [(2, "silent")]


def test_ages_held_below_the_bound_convict_nobody(core, paper14):
    """Estimates 40 steps old, for seconds on end (a slow link, not a silence): no verdict."""
    t = 0.0
    while t < 4.0:
        _feed_ages(core, paper14, t, 40)
        t = round(t + 0.1, 6)
    assert core.verdicts == []


def test_the_silent_bound_counts_from_the_links_delay(paper14):
    """On 15-step links an estimate 85 steps old is 70 steps late, not silent (the bound is
    75); one 95 steps old is (the bound once ignored the delay: a loaded run at 15-step
    delays convicted a healthy agent whose estimates came 10 steps later than the
    delay)."""
    G = [0.5 * np.eye(14)[:, list(m)] for m in paper14.measure]
    D = np.where(paper14.W > 0, 15, 0)
    np.fill_diagonal(D, 0)

    from agent.monitor.core import GainSource

    def run(age):
        # the verdict is the point: the gains for the roles that answer it are not designed
        c = MonitorCore(MonitorConfig(hang_timeout_s=1.0, settle_s=0.0, step_s=0.02),
                        paper14, G, D, gains=GainSource(worker=_FakeWorker()))
        for a in (1, 2, 3, 4):
            c.on_liveliness("agent", a, True, 0.0)
        t = 0.0
        while t < 3.0:
            for a in (1, 2, 3):
                nbrs = [b + 1 for b in paper14.neighbours[a - 1]]
                ages = {b: (age if b == 2 and t > 0.5 else 15) for b in nbrs}
                c.on_status({**_status(a, int(50 * t)), "ages": ages}, t)
            c.on_status(_status(4, int(50 * t), active=False), t)
            c.tick(t)
            t = round(t + 0.1, 6)
        return [(v.agent, v.cause) for v in c.verdicts]

    assert run(85) == []
    assert run(95) == [(2, "silent")]


def test_the_links_off_design_follow_each_agents_newest_status(core, paper14):
    """The links whose learned delay is off the design, kept per agent and read again only
    when its status is replaced, equal the map read from every status at every tick: a
    link reported off design, then back on it, then left out of the status."""
    rng = np.random.default_rng(3)
    D = np.asarray(core.roster.delays)
    rows = {a: i for i, a in enumerate(core.roster.ids)}
    W = np.asarray(core.roster.scenario.W)
    for k in range(40):
        for a in rng.choice([1, 2, 3], size=int(rng.integers(0, 4)), replace=False):
            a = int(a)
            delays = {b + 1: int(rng.choice([D[rows[a], rows[b + 1]], 4, 9]))
                      for b in paper14.neighbours[a - 1] if rng.random() < 0.8}
            core.on_status({**_status(a, k), "delays": delays}, 0.01 * k)
        naive = {(a, int(b)): int(t) for a in core.roster.ids
                 for b, t in core.agents[a].status.get("delays", {}).items()
                 if a != int(b) and W[rows[a], rows[int(b)]] > 0
                 and int(t) != D[rows[a], rows[int(b)]]}
        assert core._delays_off_design() == naive


def test_the_head_start_covers_the_subscriptions_the_agents_report(core):
    """An assignment's activate_at leaves the agents the time they report for a new
    link's subscription (declared, and the publisher's cache replayed into it), rounded
    up to steps plus one; a report that is not a number counts for nothing, and a huge
    one is capped at twice the hang timeout."""
    assert core.subscription_steps() == 0 and core.head_start() == core.lead == 10
    core.agents[2].status = {**_status(2, 5), "estimates_from": {
        "declare_ms_max": 3.0, "ready_ms_max": 301.0}}           # 15.05 steps of 20 ms
    core.agents[3].status = {**_status(3, 5), "estimates_from": {
        "declare_ms_max": "junk", "ready_ms_max": float("nan")}}
    assert core.subscription_steps() == 17 and core.head_start() == 17
    out = core._assign_all(core.roster, core.G, {"kind": "refined"}, 0.5, {}, "test")
    (roster,) = [m for m in out if isinstance(m, RosterUpdate)]
    assert roster.activate_at == max(core.current_step(0.5), 0) + 17
    core.agents[3].status = {**_status(3, 5), "estimates_from": {"ready_ms_max": 1e12}}
    assert core.subscription_steps() == core._lead_cap() == 100


@pytest.mark.slow
def test_learned_delays_beyond_the_certified_bound_get_new_gains(core, paper14):
    """The agents learn 9-step delays on every link: the delay-free gains are not
    stable with them (exact radius), so the monitor assigns gains designed for them,
    certified by the exact closed loop, to the same agents under a new epoch."""
    from design.closed_loop import closed_loop_for
    from design.scenario import uniform_delays

    D9 = uniform_delays(paper14.W, 9)
    assert closed_loop_for(paper14, core.G, D9).spectral_radius() >= 1
    out = []
    for k in range(5):
        t = 0.1 * k
        for a in (1, 2, 3):
            core.on_status({**_status(a, 10 * k),
                            "delays": {b + 1: 9 for b in paper14.neighbours[a - 1]}}, t)
        out = core.tick(t)
        if core.verdicts:
            break
    (v,) = core.verdicts
    assert v.cause == "delay" and "the exact loop is not stable (radius" in v.evidence
    asg = [m for m in out if isinstance(m, Assignment)]
    assert {m.agent for m in asg} == {1, 2, 3} and {m.epoch for m in asg} == {1}
    G_new = [asg_by.spec.gain for asg_by in sorted(asg, key=lambda m: m.agent)]
    assert closed_loop_for(paper14, G_new, D9).spectral_radius() < 1


def test_a_quiet_sensor_is_told_from_a_hung_loop(core):
    """Agent 2's step stops. If its statuses keep coming and say its last reading is old,
    the verdict is 'sensor'; if its statuses stop too, 'hang'."""
    _advance(core, 0.0, 1.0, lambda t: 50 * t)
    t = 1.1
    while t < 2.7:
        for a in (1, 3, 4):
            core.on_status(_status(a, int(50 * t), active=a <= 3), t)
        core.on_status(_status(2, 50, sensor_last=49), t)       # loop alive, no readings
        core.tick(t)
        t += 0.1
    assert [(v.agent, v.cause) for v in core.verdicts] == [(2, "sensor")]
    assert "its loop still reports" in core.verdicts[0].evidence


def test_agents_leaving_after_the_world_are_the_run_ending_not_failures(core):
    core.on_liveliness("world", 0, True, 0.0)
    _advance(core, 0.0, 2.0, lambda t: 50 * t)
    core.on_world_end(100)
    core.on_liveliness("world", 0, False, 2.05)
    assert not core.run_ended(2.05)
    assert any("world left after step 100" in e for e in core.events)
    out = _advance(core, 2.1, 7.0, lambda t: 100)           # the agents stop stepping
    for i, a in enumerate((1, 4, 3, 2)):                    # ... and leave one by one
        assert not core.run_ended(7.0 + i)
        core.on_liveliness("agent", a, False, 7.0 + i)
        out += core.tick(7.0 + i + 0.01)
    assert out == [] and core.verdicts == []
    assert core.run_ended(10.1)


def test_the_run_ends_world_gone_s_after_the_world_even_with_an_agent_left(core):
    core.on_liveliness("world", 0, True, 0.0)
    _advance(core, 0.0, 2.0, lambda t: 50 * t)
    core.on_world_end(100)
    core.on_liveliness("world", 0, False, 2.0)
    assert not core.run_ended(2.0 + core.config.world_gone_s - 0.1)
    assert core.run_ended(2.0 + core.config.world_gone_s)


def test_every_token_gone_at_once_without_the_worlds_end_is_not_the_run_ending(core):
    """What a monitor paused for a second sees when it resumes: its links lapsed, so the
    world's token and every agent's go together, and no end was heard. It waits for the
    network to come back (it used to exit and leave the run without a monitor)."""
    core.on_liveliness("world", 0, True, 0.0)
    _advance(core, 0.0, 2.0, lambda t: 50 * t)
    core.on_liveliness("world", 0, False, 3.2)
    for a in (1, 2, 3, 4):
        core.on_liveliness("agent", a, False, 3.2)
    assert any("went silent after step 100 without its end" in e for e in core.events)
    assert not core.run_ended(3.3)
    assert not core.run_ended(3.2 + core.config.world_silent_s - 0.1)
    core.on_liveliness("world", 0, True, 3.5)               # the links come back
    for a in (1, 2, 3, 4):
        core.on_liveliness("agent", a, True, 3.5)
    assert not core.run_ended(3.2 + core.config.world_silent_s + 1.0)
    _advance(core, 3.6, 6.0, lambda t: 100 + 50 * (t - 3.6))
    assert core.verdicts == []


def test_a_world_silent_for_world_silent_s_ends_the_run(core):
    core.on_liveliness("world", 0, True, 0.0)
    _advance(core, 0.0, 2.0, lambda t: 50 * t)
    core.on_liveliness("world", 0, False, 2.0)
    assert not core.run_ended(2.0 + core.config.world_silent_s - 0.1)
    assert core.run_ended(2.0 + core.config.world_silent_s)


def test_verdicts_resume_when_the_world_comes_back(core):
    core.on_liveliness("world", 0, True, 0.0)
    _advance(core, 0.0, 2.0, lambda t: 50 * t)
    core.on_liveliness("world", 0, False, 2.0)
    _advance(core, 2.1, 4.0, lambda t: 100)                 # nobody steps: no hang verdicts
    core.on_liveliness("world", 0, True, 4.05)
    assert not core.run_ended(30.0) and core.verdicts == []
    _advance(core, 4.1, 6.0, lambda t: 100 + 50 * (t - 4.1))
    assert core.verdicts == []
    core.on_liveliness("agent", 1, False, 6.05)
    core.tick(6.05)
    assert [(v.agent, v.cause) for v in core.verdicts] == [(1, "crash")]


def test_the_world_is_back_when_the_agents_step_on_though_its_token_was_missed(core):
    """A monitor whose links lapsed may never see the world's token return: the agents
    stepping well past the step reached when it went are the world back, and a crash
    after it is answered (it used to wait ``world_silent_s`` with no verdict at all)."""
    core.on_liveliness("world", 0, True, 0.0)
    _advance(core, 0.0, 2.0, lambda t: 50 * t)
    core.on_liveliness("world", 0, False, 2.0)
    _advance(core, 2.1, 3.0, lambda t: 100 + 5 * (t - 2.0))   # in flight: a few steps more
    assert core.world_gone_at is not None
    _advance(core, 3.1, 5.0, lambda t: 100 + 50 * (t - 3.0))
    assert core.world_gone_at is None
    assert any(e.startswith("the world is back (agents [1, 2") for e in core.events)
    core.on_liveliness("agent", 1, False, 5.05)
    _advance(core, 5.1, 6.5, lambda t: 100 + 50 * (t - 3.0), skip=(1,))
    assert [(v.agent, v.cause) for v in core.verdicts] == [(1, "crash")]


def test_a_standby_that_goes_is_said_with_the_standbys_left(core):
    _advance(core, 0.0, 2.0, lambda t: 50 * t)
    core.on_liveliness("agent", 4, False, 2.05)
    assert core.tick(2.05) == [] and core.verdicts == []
    assert "agent 4 gone (its token went): a standby; 0 standby left to replace a failed " \
           "agent" in core.events


def test_a_monitor_that_missed_another_monitors_epoch_acts_only_after_adopting_it(core,
                                                                                paper14):
    """A monitor paused while a standby monitor replaced agent 1 resumes with the old
    roster: the agents' statuses report an epoch it never issued, so it must not act on
    its stale view (it convicted agent 1 a second time and took the standby's new role
    away) until it has rebuilt the configuration in force from them."""
    _advance(core, 0.0, 2.0, lambda t: 50 * t)
    W = paper14.W
    statuses = {  # the configuration of epoch 1: agent 4 measures 8 in agent 1's place
        4: {"measure": ["8"], "neighbours": {2: float(W[0, 1])}},
        2: {"measure": ["9"], "neighbours": {3: float(W[1, 2])}},
        3: {"measure": ["12"], "neighbours": {4: float(W[2, 0])}},
    }
    core.on_liveliness("agent", 1, False, 2.5)          # its death, seen late
    for a, extra in statuses.items():
        core.on_status({**_status(a, 130, epoch=1), **extra}, 2.6)
    assert core.behind
    assert core.tick(2.7) == [] and core.verdicts == []
    assert core.adopt(None, core.epoch)
    assert not core.behind and core.roster.ids == (2, 3, 4) and core.epoch == 1
    for a, extra in statuses.items():
        core.on_status({**_status(a, 140, epoch=1), **extra}, 2.9)
    assert core.tick(3.0) == [] and core.verdicts == []


class _FakeWorker:
    """A gain worker stepped by hand: requests are kept, answers given by the test."""

    def __init__(self):
        self.requests = []

    def request(self, roster, kinds=("fast", "refined"), init=None):
        self.requests.append((roster, tuple(kinds)))
        self.init = init

    def assess(self, roster, G, info):
        self.requests.append((roster, ("assess",)))


def _live_core_with_worker():
    """paper-14-live's monitor core with a gain worker stepped by hand, every agent up."""
    from agent.monitor.core import GainSource
    from design.scenario import load_scenario

    s = load_scenario("paper-14-live")
    G = [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure]
    worker = _FakeWorker()
    core = MonitorCore(MonitorConfig(hang_timeout_s=1.0, settle_s=0.0, step_s=0.02), s, G,
                       s.delays, gains=GainSource(worker=worker))
    for a in (1, 2, 3, 4):
        core.on_liveliness("agent", a, True, 0.0)
    return core, worker


def test_gains_not_precomputed_are_designed_outside_the_loop_and_roles_follow_them(paper14):
    """The loop never designs: a configuration without gains is requested from the worker;
    detection goes on meanwhile; ``activate_at`` counts from when the gains came back (it
    used to be fixed before a design of seconds, and was past when sent); a fast gain in
    force is replaced by the refined one under a later epoch."""
    from agent.monitor.core import design_gains_for

    core, worker = _live_core_with_worker()
    _advance(core, 0.0, 2.0, lambda t: 50 * t)
    core.on_liveliness("agent", 1, False, 2.05)
    assert core.tick(2.05) == []                            # no gains yet: nothing sent
    assert [v.agent for v in core.verdicts] == [1]
    (roster, kinds), = worker.requests
    assert roster.ids == (4, 2, 3) and kinds == ("fast", "refined")
    assert any("designing them in the gain worker" in e for e in core.events)
    # its warm start: the survivors keep their gains, the standby 4 its reset gain H^T
    assert np.array_equal(worker.init[1], core.G[1]) and np.array_equal(worker.init[2],
                                                                         core.G[2])
    assert np.array_equal(worker.init[0], np.eye(roster.scenario.n)[:, list(
        roster.scenario.measure[0])])
    # the loop goes on ticking and detecting while the worker designs
    _advance(core, 2.1, 4.0, lambda t: 50 * t, skip=(1,))
    assert core.history == []
    fast = design_gains_for(roster, "fast")
    assert fast[0] is not None and fast[1]["kind"] == "fast" and fast[1]["rho"] < 1
    core.gains.put(roster, *fast)
    out = core.tick(4.05)
    (msg,) = [m for m in out if isinstance(m, RosterUpdate)]
    assert msg.ids == (4, 2, 3) and msg.activate_at >= 200 + core.config.lead_steps
    h = core.history[-1]
    assert h["precomputed"] is False and h["gains"] == "fast" and h["gains_rho"] < 1
    # the refined gain was asked with the fast one (not twice); the fast one's MSE after
    assert [k for _, k in worker.requests] == [("fast", "refined"), ("assess",)]
    for a in (2, 3, 4):
        core.on_status(_status(a, 215, epoch=1), 4.3)
    assert core.tick(4.3) == []                              # confirmed, no refined yet
    refined = design_gains_for(roster, "refined")
    core.gains.put(roster, *refined)
    out = core.tick(4.4)
    assert {m.epoch for m in out} == {2}
    assert core.history[-1]["gains"] == "refined" and core.history[-1]["causes"] == {
        "0": "refined"}
    assert core.roster.ids == (4, 2, 3)


def test_a_crash_is_answered_while_the_monitors_own_pause_suspends_verdicts(core):
    """The pause guard suspends the verdicts that read clocks (a status looks old because
    the monitor slept), never a deleted token: agent 2's crash during the monitor's own
    pause is convicted once its listener is past the step the token went at (the token
    went unheard: the monitor slept), not hang_timeout_s later."""
    from agent.monitor.detector import CRASH_CONFIRM_STEPS, CRASH_SETTLE_S

    _advance(core, 0.0, 1.0, lambda t: 50 * t)
    core.on_status(_status(1, 200), 4.0)                 # the monitor slept 3 s
    core.on_status(_status(3, 200), 4.0)
    core.on_liveliness("agent", 2, False, 4.0)
    assert core.tick(4.0) == [] and core.verdicts == []    # suspended; token just gone
    assert any("paused" in e for e in core.events)
    t = 4.0
    while not core.verdicts and t < 4.0 + core.config.hang_timeout_s:
        t += 0.05
        for a in (1, 3, 4):
            core.on_status(_status(a, int(50 * t), active=a <= 3), t)
        out = core.tick(t)
    assert [(v.agent, v.cause) for v in core.verdicts] == [(2, "crash")]
    confirm_s = (2 * CRASH_CONFIRM_STEPS + 2) * core.config.step_s
    assert t - 4.0 < max(CRASH_SETTLE_S, confirm_s) + 0.1 < core.config.hang_timeout_s
    assert any(isinstance(m, RosterUpdate) for m in out)


def test_a_pause_that_takes_every_token_is_no_crash(core):
    """A monitor cut off sees every token go at once: during its pause that is no crash."""
    _advance(core, 0.0, 1.0, lambda t: 50 * t)
    for a in (1, 2, 3):
        core.on_liveliness("agent", a, False, 4.0)
    assert core.tick(4.0) == []
    assert core.tick(4.3) == [] and core.verdicts == []


def test_a_failure_on_a_precomputed_fast_gain_gets_the_refined_one_later(paper14):
    """A failure before the background refined its configuration switches at once on the
    precomputed fast gain; the refined one, when the worker sends it, is put in force
    under a later epoch, and the record says which gain is in force each time."""
    from agent.monitor.gain_worker import plan_failures
    from agent.monitor.core import GainSource, design_gains_for

    from design.scenario import load_scenario

    s = load_scenario("paper-14-live")
    G = [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure]
    worker = _FakeWorker()
    core = MonitorCore(MonitorConfig(hang_timeout_s=1.0, settle_s=0.0, step_s=0.02), s, G,
                       s.delays, gains=GainSource(worker=worker))
    (roster,) = [nxt for a, nxt in plan_failures(core.roster) if a == [1]]
    fast_G, fast = design_gains_for(roster, "fast")
    assert fast_G is not None and fast["kind"] == "fast" and fast["rho"] < 1
    core.gains.put(roster, fast_G, fast)                  # the urgent process's fast pass
    for a in (1, 2, 3, 4):
        core.on_liveliness("agent", a, True, 0.0)
    _advance(core, 0.0, 2.0, lambda t: 50 * t)
    core.on_liveliness("agent", 1, False, 2.05)
    out = core.tick(2.05)
    (msg,) = [m for m in out if isinstance(m, RosterUpdate)]
    assert msg.epoch == 1 and msg.ids == roster.ids
    h = core.history[-1]
    assert h["precomputed"] is True and h["gains"] == "fast" and h["gains_rho"] == fast["rho"]
    # asked once, not designed here: the refined gain, then the fast one's exact MSE
    assert [k for _, k in worker.requests] == [("refined",), ("assess",)]
    assert all(GainSource.key(r) == GainSource.key(roster) for r, _ in worker.requests)
    assert any("fast gains" in e for e in core.events)
    for a in roster.ids:
        core.on_status(_status(a, 110, epoch=1), 2.2)
    assert core.tick(2.2) == []                           # in force; no refined gain yet
    import queue

    from agent.monitor.gain_worker import _assess

    sent = queue.Queue()
    _assess(("assess", roster, fast_G, fast), sent)       # what the worker sends back
    _, G_back, assessed = sent.get_nowait()
    mse = assessed["mse"]
    assert mse > 0 and assessed["assessed"] is True
    assert assessed["rho"] == pytest.approx(fast["rho"], rel=1e-12)
    core.gains.put(roster, G_back, assessed)
    assert core.tick(2.25) == []
    assert core.gain_notes == [{"epoch": 1, "gains": "fast", "gains_rho": fast["rho"],
                                "gains_mse": mse}]
    assert any(f"steady MSE {mse:.4g}" in e for e in core.events)
    fast = {**fast, "mse": mse}
    refined = {"kind": "refined", "rho": fast["rho"] * 0.9, "mse": fast["mse"] * 0.8}
    core.gains.put(roster, [2 * g for g in fast_G], refined)
    core.gains.put(roster, fast_G, fast)                  # a late fast answer is ignored
    out = core.tick(2.3)
    assert {m.epoch for m in out} == {2} and core.roster.ids == roster.ids
    assert {m.agent for m in out if isinstance(m, Assignment)} == set(roster.ids)
    h = core.history[-1]
    assert h["gains"] == "refined" and h["gains_rho"] == refined["rho"]
    assert h["gains_mse"] == refined["mse"] and h["activate_at"] >= 115
    assert all(np.allclose(g, 2 * f) for g, f in zip(core.G, fast_G))
    for a in roster.ids:
        core.on_status(_status(a, 130, epoch=2), 2.6)
    assert core.tick(2.6) == []                           # nothing more to upgrade


def _agent_1_replaced():
    """:func:`_live_core_with_worker` at 50 steps a second; agent 1 crashes at 2.05 s and
    the roles answering it go out at 2.06 s (fast gains). Returns the core, its worker
    and the roster message of epoch 1."""
    from agent.monitor.core import design_gains_for

    core, worker = _live_core_with_worker()
    _advance(core, 0.0, 2.0, lambda t: 50 * t)
    core.on_liveliness("agent", 1, False, 2.05)
    core.tick(2.05)
    (first, _), = worker.requests
    core.gains.put(first, *design_gains_for(first, "fast"))
    (msg,) = [m for m in core.tick(2.06) if isinstance(m, RosterUpdate)]
    return core, worker, msg


def test_a_failure_before_the_last_roles_are_in_force_is_planned_with_it_when_known(paper14):
    """Agents 1 and 2 killed together, their verdicts apart (under load): the roles
    answering agent 1 went out, not yet in force, when agent 2 is convicted. The gains of
    the pair's configuration, planned on the configuration still in force, are known (the
    precompute does pairs for small networks): that plan goes out at once under a new
    epoch, to every agent of it, instead of one planned on the roles not yet in force,
    whose gains nobody foresaw (requested from the worker: a design of seconds)."""
    import dataclasses

    from agent.monitor.core import design_gains_for
    from design.roster import replan

    core, worker, msg = _agent_1_replaced()
    assert msg.epoch == 1 and msg.ids == (4, 2, 3)
    from design.roster import Roster

    base = dataclasses.replace(Roster.initial(core.scenario, core.roster.delays),
                               standby_ids=(4,))
    _, joint = replan(base, [1, 2])
    core.gains.put(joint, *design_gains_for(joint, "fast"))
    requested = len(worker.requests)
    core.on_liveliness("agent", 2, False, 2.1)
    out = core.tick(2.1)
    (roster_msg,) = [m for m in out if isinstance(m, RosterUpdate)]
    assert roster_msg.epoch == 2 and roster_msg.ids == joint.ids
    assert roster_msg.activate_at <= msg.activate_at + core.lead
    assert sorted(m.agent for m in out if isinstance(m, Assignment)) == sorted(joint.ids)
    # no first gain designed on request (the refinement of the fast gain in force follows)
    assert all("fast" not in kinds for _, kinds in worker.requests[requested:])
    assert core.history[-1]["failed"] == [1, 2] and core.history[-1]["precomputed"]
    assert any("planned together on the configuration still in force" in e
               for e in core.events)


def test_an_agent_convicted_before_it_confirmed_is_not_waited_for(paper14):
    """Agent 1 crashes; before agent 2 confirms the roles that answer it, agent 2 crashes
    too, and the roles answering both wait for their gains. The first roles are not
    re-issued to the dead agent meanwhile (epochs churned for nothing): the next epoch
    is the reassignment that answers agent 2."""
    from agent.monitor.core import design_gains_for

    core, worker, msg = _agent_1_replaced()
    assert msg.epoch == 1 and msg.ids == (4, 2, 3)
    core.on_liveliness("agent", 2, False, 2.1)
    t = 2.1
    while t < 2.0 + (msg.activate_at - 100 + 20) * 0.02:       # well past activate_at
        for a in (3, 4):
            core.on_status(_status(a, int(50 * t), epoch=0, pending=1), t)
        assert [m for m in core.tick(t) if isinstance(m, RosterUpdate)] == []
        t += 0.05
    assert core.epoch == 1 and core.reissues == []
    assert any("agent 2 was convicted before it confirmed epoch 1" in e for e in core.events)
    second = worker.requests[-1][0]
    assert second.ids == (4, 3)
    core.gains.put(second, *design_gains_for(second, "fast"))
    (msg,) = [m for m in core.tick(t) if isinstance(m, RosterUpdate)]
    assert msg.epoch == 2 and msg.ids == (4, 3)


def test_a_precomputed_failure_switches_to_its_polished_first_gain(paper14):
    """The precompute's polish pass (a few MSE iterations from the fast gain) replaces the
    fast gain of a foreseen failure and is not replaced by a late plain fast answer; the
    switch goes out on it, said so, and its refined gain is still asked for."""
    from agent.monitor.gain_worker import plan_failures
    from agent.monitor.core import GainSource, design_gains_for
    from design.closed_loop import exact_performance

    from design.scenario import load_scenario

    s = load_scenario("paper-14-live")
    G = [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure]
    worker = _FakeWorker()
    core = MonitorCore(MonitorConfig(hang_timeout_s=1.0, settle_s=0.0, step_s=0.02), s, G,
                       s.delays, gains=GainSource(worker=worker))
    (roster,) = [nxt for a, nxt in plan_failures(core.roster) if a == [2]]
    fast_G, fast = design_gains_for(roster, "fast")
    pol_G, pol = design_gains_for(roster, "polished", init=fast_G)
    assert pol["kind"] == "fast" and pol["polished"] is True and pol["rho"] < 1
    mse = {name: exact_performance(roster.scenario, g, roster.delays).mse
           for name, g in (("fast", fast_G), ("polished", pol_G))}
    assert mse["polished"] < 0.8 * mse["fast"]
    # without init it designs the fast gain itself first: the same gain
    again = design_gains_for(roster, "polished")[0]
    assert all(np.array_equal(a, b) for a, b in zip(again, pol_G))
    core.gains.put(roster, fast_G, fast)                  # the fast pass
    core.gains.put(roster, pol_G, pol)                    # the polish pass replaces it
    core.gains.put(roster, fast_G, fast)                  # a late plain fast answer: kept out
    assert core.gains.info(roster)["polished"] is True
    for a in (1, 2, 3, 4):
        core.on_liveliness("agent", a, True, 0.0)
    _advance(core, 0.0, 2.0, lambda t: 50 * t)
    core.on_liveliness("agent", 2, False, 2.05)
    out = core.tick(2.05)
    (msg,) = [m for m in out if isinstance(m, RosterUpdate)]
    assert msg.ids == roster.ids
    h = core.history[-1]
    assert h["precomputed"] and h["gains"] == "fast" and h["gains_polished"] is True
    assert h["gains_rho"] == pol["rho"]
    assert any("fast gains (MSE-polished)" in e for e in core.events)
    assert [k for _, k in worker.requests] == [("refined",), ("assess",)]


def _standby_status(agent, step, links=None):
    return {**_status(agent, step, active=False), "links": links or {},
            "sensor": {"labels": [], "last_step": -1}}


def test_a_convicted_agent_rejoins_the_standbys_after_probation_only(core):
    """Agent 2 hangs and is convicted; it comes back fenced (a standby, advancing). It
    rejoins the pool only after rejoin_s of unbroken health: a status showing an impaired
    link into it starts the probation over. Then it can replace the next failure."""
    step = lambda t: int(50 * t)                                    # noqa: E731
    _advance(core, 0.0, 1.0, step)
    _advance(core, 1.1, 2.6, step, skip=(2,))
    assert [(v.agent, v.cause) for v in core.verdicts] == [(2, "hang")]
    assert 2 not in core.standby_pool(2.6)
    t, rejoined_at, broken = 2.7, None, False

    def others(t):
        for a in (1, 3, 4):
            core.on_status(_status(a, step(t), epoch=core.epoch), t)

    while t < 14.0 and rejoined_at is None:
        others(t)
        impaired = 4.0 <= t < 4.5                    # a partition still in force for a while
        broken |= impaired
        core.on_status(_standby_status(2, step(t), {"1": {"partition": True}} if impaired
                                       else None), t)
        core.tick(t)
        if core.rejoins:
            rejoined_at = t
        t += 0.1
    assert broken and rejoined_at is not None
    # healthy from 4.5 s on: rejoined rejoin_s later, not rejoin_s after the conviction
    assert rejoined_at >= 4.5 + core.config.rejoin_s - 1e-9
    (r,) = core.rejoins
    assert r["agent"] == 2 and r["standby"] == [2]
    assert any("rejoined as a standby" in e for e in core.events)
    # the next failure is answered by agent 2
    core.on_liveliness("agent", 4, False, t)
    out = core.tick(t + 0.01)
    (roster,) = [m for m in out if isinstance(m, RosterUpdate)]
    assert 2 in roster.ids and 4 not in roster.ids


def test_probation_forgives_a_short_slowness_not_a_lasting_one(core):
    """A standby on probation that falls behind the others for less than half the hang
    timeout (a loaded host) keeps its probation; behind for longer, it starts over. Its
    step is compared with the others' at the moment it reached it, so statuses sent a
    status period apart are not a lag."""
    step = lambda t: int(50 * t)                                    # noqa: E731
    _advance(core, 0.0, 1.0, step)
    _advance(core, 1.1, 2.6, step, skip=(2,))
    assert [v.agent for v in core.verdicts] == [2]
    t = 2.7

    def run(until, lag, offset=0.0):
        nonlocal t
        while t < until - 1e-9:
            for a in (1, 3, 4):
                core.on_status(_status(a, step(t), epoch=core.epoch), t)
            # agent 2's status arrives offset s after the others', its step then
            core.on_status(_standby_status(2, step(t + offset) - lag), t + offset)
            core.tick(t + offset)
            t += 0.1

    run(3.5, 0, offset=0.09)            # out of phase with the others: no lag
    since = core.agents[2].healthy_since
    assert since is not None and core.detector.lag_steps(2) < 1
    run(3.8, 15)                        # 15 steps behind for 0.3 s: forgiven
    assert core.agents[2].healthy_since == since
    run(4.0, 0)
    run(4.8, 15)                        # behind for 0.8 s: starts over
    assert core.agents[2].healthy_since > since
    assert any("probation starts over: 15 steps behind the others" in e for e in core.events)
    assert core.rejoins == []


def test_a_status_on_one_agents_key_naming_another_is_refused(core):
    _advance(core, 0.0, 1.0, lambda t: 50 * t)
    forged = {**_status(1, 60), "epoch": 5}
    core.on_status(forged, 1.05, sender=2)               # agent 2's key, agent 1's name
    assert core.agents[1].epoch == 0 and core.rejected == {"sender": 1}
    assert core.anomalies == [{"reason": "sender", "agent": 2,
                               "detail": "a status on agent 2's key names agent 1"}]
    core.on_status(forged, 1.06, sender=2)
    assert core.rejected == {"sender": 2} and len(core.anomalies) == 1   # one event each
    core.on_status(_status(1, 61), 1.07, sender=1)        # the genuine one still counts
    assert core.agents[1].step == 61


def test_a_dead_agent_cannot_be_hidden_behind_a_token_declared_in_its_name(paper14):
    """Tokens carry their session: the first session holding agent 1's token is agent 1's.
    An outsider's token for agent 1 is refused (``token``) and reported once; when agent
    1's own token goes, that is its crash although the outsider's token remains; the
    outsider's token going is nobody's crash."""
    G = [0.5 * np.eye(14)[:, list(m)] for m in paper14.measure]
    core = MonitorCore(MonitorConfig(hang_timeout_s=1.0, settle_s=0.0, step_s=0.02), paper14,
                       G, paper14.delays)
    for a in (1, 2, 3, 4):
        assert core.on_liveliness("agent", a, True, 0.0, session=f"z{a}") is True
    _advance(core, 0.0, 1.0, lambda t: 50 * t)
    assert core.on_liveliness("agent", 2, True, 1.01, session="evil") is None
    assert core.on_liveliness("agent", 1, True, 1.02, session="evil") is None
    assert core.rejected == {"token": 2} and [a["agent"] for a in core.anomalies] == [2, 1]
    assert "second liveliness token for agent 1" in core.anomalies[1]["detail"]
    assert core.on_liveliness("agent", 2, False, 1.03, session="evil") is None
    assert core.tick(1.03) == [] and core.verdicts == []      # the outsider leaving: nothing
    # agent 1's own token goes while the outsider's remains: judged by its estimates
    assert core.on_liveliness("agent", 1, False, 1.05, session="z1") is None
    t = 1.05
    while t < 2.0:                            # agent 2 still publishes, agent 1 does not
        core.on_estimate_seen(2, t)
        for a in (2, 3, 4):
            core.on_status(_status(a, int(50 * t), active=a <= 3), t)
        core.tick(t)
        t += 0.05
    assert [(v.agent, v.cause) for v in core.verdicts] == [(1, "crash")]
    assert "no estimate of it" in core.verdicts[0].evidence
    assert core.verdicts[0].at - 1.05 <= 25 * 0.02 + 0.1
    # a process declaring the id once every token of it is gone is agent 1 again (a restart)
    assert core.on_liveliness("agent", 1, False, 2.0, session="evil") is False
    assert core.on_liveliness("agent", 1, True, 2.1, session="z1b") is True
    assert core.rejected == {"token": 2}


def test_a_live_agent_whose_token_is_ended_by_an_impostor_leaving_is_not_convicted(paper14):
    """zenoh ended agent 2's own token when a second session holding agent 2's id left
    (seen live under --secure with agent 2's certificate). While another token for its
    id is alive, the agent is judged by its estimates: a live agent is not convicted."""
    G = [0.5 * np.eye(14)[:, list(m)] for m in paper14.measure]
    core = MonitorCore(MonitorConfig(hang_timeout_s=1.0, settle_s=0.0, step_s=0.02), paper14,
                       G, paper14.delays)
    for a in (1, 2, 3, 4):
        core.on_liveliness("agent", a, True, 0.0, session=f"z{a}")
    core.on_liveliness("agent", 2, True, 0.5, session="insider")
    core.on_liveliness("agent", 2, False, 1.0, session="z2")     # the wrong one ended
    t = 0.0
    while t < 4.0:
        for a in (1, 2, 3):
            core.on_estimate_seen(a, t)
        for a in (1, 2, 3, 4):
            core.on_status(_status(a, int(50 * t), active=a <= 3), t)
        assert core.tick(t) == [], t
        t += 0.05
    assert core.verdicts == [] and core.agents[2].alive


def test_a_step_far_ahead_of_every_other_agent_is_refused_and_moves_no_clock(core):
    """An insider reporting a step past the others' (extrapolated) plus step_ahead_s is
    refused (``step``): it cannot push ``activate_at`` of the next reassignment away, nor
    ratchet the bound up by repeating; a step inside the bound is taken."""
    _advance(core, 0.0, 2.0, lambda t: 50 * t)                      # step 100 at 2.0 s
    ceiling = core.step_ceiling(2.0, exclude=2)
    assert 100 + 100 <= ceiling <= 100 + 101                      # 2 s at 20 ms a step
    for k in range(5):                                            # the ratchet: refused
        core.on_status(_status(2, ceiling + 1 + k * 100), 2.01 + k * 0.001, sender=2)
    assert core.rejected == {"step": 5} and core.agents[2].step == 100
    assert core.current_step(2.01) < 102
    core.on_status(_status(2, 101), 2.02, sender=2)               # the genuine one counts
    assert core.agents[2].step == 101
    core.on_liveliness("agent", 1, False, 2.05)
    (roster,) = [m for m in core.tick(2.05) if isinstance(m, RosterUpdate)]
    assert roster.activate_at <= 102 + core.config.lead_steps + 1


def test_after_the_monitors_own_pause_the_agents_steps_ahead_are_taken(core):
    """A monitor paused 5 s finds every agent 250 steps further, and the world's token
    gone and back (its links lapsed): that restarts the progress clocks; the step bound
    still extrapolates from when the steps were reached, so nothing is refused (CI:
    every status refused, the clock stuck, every agent convicted)."""
    core.on_liveliness("world", "0", True, 0.0)
    _advance(core, 0.0, 2.0, lambda t: 50 * t)
    core.on_liveliness("world", "0", False, 7.0)                  # the pause: 2.0 -> 7.0
    core.on_liveliness("world", "0", True, 7.0)
    for a in (1, 2, 3, 4):             # its backlog first: statuses from before the pause
        core.on_status(_status(a, 103, active=a <= 3), 7.0)
    out = _advance(core, 7.0, 10.0, lambda t: 50 * t)
    assert core.rejected == {} and core.verdicts == [] and out == []
    assert core.agents[1].step >= 495


def test_epochs_far_above_the_highest_seen_are_refused_from_statuses_and_rosters(core):
    _advance(core, 0.0, 1.0, lambda t: 50 * t)
    bound = core.epoch_ceiling()
    assert bound == core.config.epoch_jump_max
    core.on_status({**_status(1, 60), "epoch": 2 ** 62}, 1.05, sender=1)
    assert core.epoch == 0 and not core.behind and core.rejected == {"epoch": 1}
    assert not core.accept_roster({"epoch": 2 ** 62, "activate_at": 10, "ids": [1, 2, 3]})
    assert core.rejected == {"epoch": 2}
    # a genuine epoch a few above this monitor's (another monitor acted) is taken
    core.on_status({**_status(1, 61), "epoch": 3}, 1.06, sender=1)
    assert core.epoch == 3 and core.behind
    assert core.accept_roster({"epoch": 3 + core.config.epoch_jump_max, "activate_at": 10,
                               "ids": [1, 2, 3]})


def _feed_ages(core, paper14, t, age_of_2, links_of_1=None, monitor_hears_2=False):
    step = int(50 * t)
    for a in (1, 2, 3):
        nbrs = {b + 1: float(paper14.W[a - 1, b]) for b in paper14.neighbours[a - 1]}
        ages = {b: (age_of_2 if b == 2 else 1) for b in nbrs}
        core.on_status({**_status(a, step), "neighbours": nbrs, "ages": ages,
                        "links": (links_of_1 or {}) if a == 1 else {}}, t)
    core.on_status(_status(4, step, active=False), t)
    if monitor_hears_2:
        core.on_estimate_seen(2, t)
    return core.tick(t)


def test_one_listeners_word_against_the_monitors_own_observation_convicts_nobody(core,
                                                                                 paper14):
    """Agent 1, agent 2's only listener, reports it 100 steps stale while the monitor keeps
    hearing agent 2's estimates: no verdict, agent 1's hearsay is an anomaly."""
    t = 0.0
    while t < 4.0:
        _feed_ages(core, paper14, t, 1 if t < 1.0 else 100, monitor_hears_2=True)
        t += 0.1
    assert core.verdicts == []
    assert core.rejected.get("hearsay", 0) > 0
    assert [x["agent"] for x in core.anomalies if x["reason"] == "hearsay"] == [1]


def test_one_listener_with_an_impaired_link_still_convicts_a_partitioned_agent(core, paper14):
    """A partition cut at the receivers (socmon's impairment): the monitor still hears
    agent 2, but agent 1's status shows the link from 2 cut, so its word stands."""
    t = 0.0
    while t < 4.0 and not core.verdicts:
        late = t >= 1.0
        _feed_ages(core, paper14, t, 100 if late else 1,
                   links_of_1={"2": {"partition": True}} if late else None,
                   monitor_hears_2=True)
        t += 0.1
    assert [(v.agent, v.cause) for v in core.verdicts] == [(2, "silent")]


def test_a_failure_without_a_standby_is_recovered_once_an_agent_rejoins(core):
    """Agents 1, 4, 2 and 3 crash one after the other: the standby takes 1's role, the
    others cover 4's and 2's, and 3's cannot be recovered (nobody left to take it). When
    agent 1 comes back and passes probation, 3's role is handed to it."""
    step = lambda t: int(50 * t)                                    # noqa: E731
    _advance(core, 0.0, 1.0, step)
    t, gone = 1.0, set()

    def run(until, back=()):
        nonlocal t
        while t < until:
            t += 0.1
            for a in core.roster.ids:
                if a not in gone:
                    core.on_status(_status(a, step(t), epoch=core.epoch), t)
            for a in back:
                core.on_status(_standby_status(a, step(t)), t)
            core.tick(t)

    for a in (1, 4, 2, 3):
        core.on_liveliness("agent", a, False, t)
        gone.add(a)
        run(t + 1.5)
    assert core.unrecoverable and core.roster.ids == (3,)
    core.on_liveliness("agent", 1, True, t)                         # agent 1 is back
    gone.discard(1)
    run(t + core.config.rejoin_s + 2.0, back=(1,))
    assert [r["agent"] for r in core.rejoins] == [1]
    assert core.roster.ids == (1,) and not core.unrecoverable
    assert any("planning the recovery of [3]" in e for e in core.events)


def test_the_failure_detector_judges_without_the_controller(paper14):
    """FailureDetector alone: a stuck loop is a hang, a deleted token a crash, a status on
    another agent's key refused; it reassigns nothing."""
    from agent.monitor.detector import FailureDetector
    from design.roster import Roster

    d = FailureDetector(MonitorConfig(hang_timeout_s=1.0, step_s=0.02),
                        Roster.initial(paper14, paper14.delays))
    assert sorted(d.agents) == [1, 2, 3, 4]
    for a in (1, 2, 3):
        d.on_liveliness("agent", a, True, 0.0)
    t = 0.0
    while t <= 3.0:
        d.observe(t)
        for a in (1, 2, 3):
            if a != 2 or t < 0.8:                      # agent 2's loop hangs at step 40
                d.on_status(_status(a, int(50 * t)), t, sender=a)
        t += 0.1
    found = d.verdicts(t)
    assert [(v.agent, v.cause) for v in found] == [(2, "hang")]
    assert "step 40 for" in found[0].evidence and "no status either" in found[0].evidence
    d.on_liveliness("agent", 3, False, t)
    d.observe(t + 0.2)
    assert sorted((v.agent, v.cause) for v in d.verdicts(t + 0.2)) == [(2, "hang"), (3, "crash")]
    d.failed.add(2)                                    # the controller convicted it
    assert [(v.agent, v.cause) for v in d.verdicts(t + 0.2)] == [(3, "crash")]
    assert d.on_status(_status(1, 200), t + 0.2, sender=3) is None
    assert d.rejected == {"sender": 1}


def test_residual_alarms_are_isolated_into_an_alert_that_convicts_nobody(core):
    """Statuses whose residual tests alarm: agent 1's own innovation far above its
    threshold is a sensor bias alert on agent 1 (once), an event and a record; nobody is
    convicted. Malformed levels (a string, NaN, a foreign name) are ignored."""
    out = _advance(core, 0.0, 1.0, lambda t: 50 * t)
    quiet = {"innovation 1": 0.2, "link 2->1": 0.3}

    def status(a, step, levels):
        first = {k: [step - 2, v] for k, v in levels.items()
                 if isinstance(v, float) and v >= 1}
        return {**_status(a, step), "residuals": {"levels": levels, "first": first,
                                                  "alarms": 0}}

    core.on_status(status(1, 60, {"innovation 1": 9.0, "link 2->1": 0.4,
                                  "link 9->1": "x", "innovation 2": float("nan")}), 1.1)
    out += core.tick(1.1)
    assert core.residual_alerts == []        # agents 2 and 3 have not reported step 60
    core.on_status(status(2, 60, {"innovation 2": 0.3, "link 3->2": 0.2}), 1.1)
    core.on_status(status(3, 60, {"innovation 3": 0.1, "link 1->3": 0.5}), 1.1)
    out += core.tick(1.2)
    assert [(r["agent"], r["fault"]) for r in core.residual_alerts] == [(1, "sensor bias")]
    assert any("residual alert: agent 1 sensor bias" in e for e in core.events)
    assert core.verdicts == [] and out == []
    assert ("residual_alert", core.residual_alerts[0]) in core.new_records()
    core.on_status(status(1, 61, quiet), 1.3)
    core.tick(1.3)
    assert len(core.residual_alerts) == 1


def test_residual_alarms_wait_while_an_agent_was_disturbed_lately(core):
    """An agent that used a held estimate lately (``disturbed`` within ``settle`` steps of
    the newest step) puts the whole network's tests on hold: what alarmed meanwhile is
    dropped; an alarm once it settled is isolated."""
    _advance(core, 0.0, 1.0, lambda t: 50 * t)

    def status(a, levels, disturbed=-1):
        first = {k: [58, v] for k, v in levels.items() if v >= 1}
        return {**_status(a, 60), "residuals": {"levels": levels, "first": first, "alarms": 0,
                                                "disturbed": disturbed, "settle": 40}}

    core.on_status(status(1, {"innovation 1": 9.0}), 1.1)
    core.on_status(status(2, {"innovation 2": 0.3}, disturbed=40), 1.1)
    core.on_status(status(3, {"innovation 3": 0.1}), 1.1)
    core.tick(1.1)
    assert core.residual_alerts == []
    core.on_status(status(2, {"innovation 2": 0.3}, disturbed=10), 1.2)
    core.tick(1.2)
    assert core.residual_alerts == []         # what alarmed while unsettled is dropped
    core.on_status(status(1, {"innovation 1": 9.0}), 1.3)
    core.tick(1.3)
    assert [(r["agent"], r["fault"]) for r in core.residual_alerts] == [(1, "sensor bias")]



def test_residual_isolation_takes_the_picture_at_the_first_alarm(core):
    """Agent 2 lies: agent 1 (its receiver) alarms first on link 2->1; the lie then goes
    round the loop (1 -> 3 -> 2) and alarms later on links 1->3 and 3->2, at larger
    levels. The alert names agent 2, not a consequence."""
    _advance(core, 0.0, 1.0, lambda t: 50 * t)

    def status(a, levels, first):
        return {**_status(a, 70), "residuals": {"levels": levels, "first": first,
                                                "alarms": 1, "disturbed": -1, "settle": 40}}

    core.on_status(status(3, {"innovation 3": 0.2, "link 1->3": 900.0},
                          {"link 1->3": [63, 40.0]}), 1.1)
    core.on_status(status(2, {"innovation 2": 0.1, "link 3->2": 5000.0},
                          {"link 3->2": [66, 12.0]}), 1.1)
    core.tick(1.1)
    assert core.residual_alerts == []                       # agent 1 not heard since
    core.on_status(status(1, {"innovation 1": 0.3, "link 2->1": 80.0},
                          {"link 2->1": [61, 6.0]}), 1.2)
    core.tick(1.2)
    assert [(r["agent"], r["fault"], r["step"]) for r in core.residual_alerts] == \
        [(2, "inconsistent estimates", 61)]


class _ScriptedWorker:
    """Answers ``poll`` with the results given, one per call, then nothing."""

    def __init__(self, results):
        self.results = list(results)

    def poll(self, timeout=0.0):
        return [self.results.pop(0)] if self.results else []


def _single_failures(delays="uniform:3"):
    from agent.monitor.gain_worker import plan_failures
    from design.roster import Roster
    from design.scenario import load_scenario, resolve_delays

    s = load_scenario("paper-14-live")
    roster = Roster.initial(s, resolve_delays(s, delays))
    return roster, [(a, nxt) for a, nxt in plan_failures(roster) if len(a) == 1]


class _Never:
    flag = False


@pytest.mark.parametrize("answered, foreseen", [(3, [1, 2, 3]), (2, [1, 2])])
def test_the_monitor_joins_once_every_single_failure_is_foreseen_or_after_its_bound(
        answered, foreseen):
    """foresee_single_failures returns when every single failure has gains (a failure with
    no stabilising gain counts as known), else after its bound, saying which it foresees."""
    from agent.monitor.core import GainSource
    from agent.monitor.process import foresee_single_failures

    roster, singles = _single_failures()
    results = [(nxt, [[0.0]] if a != [2] else None, {"kind": "fast"})
               for a, nxt in singles[:answered]]
    gains = GainSource(worker=_ScriptedWorker(results))
    out = foresee_single_failures(gains.worker, gains, roster, _Never(), limit=0.3)
    assert out["planned"] == [1, 2, 3] and out["foreseen"] == foreseen
    if answered == 3:
        assert "every agent ([1, 2, 3])" in out["line"]
    else:
        assert out["seconds"] >= 0.3 and "of [1, 2, 3] (after 0.3 s" in out["line"]


def test_a_standby_is_in_the_pool_before_the_clock_starts_not_once_it_stops_advancing(core):
    """Before the clock starts nobody's step moves: the standby is available however long
    the wait (a world waiting for its monitor). Once the others advance and the standby's
    step does not for the hang timeout, it is not."""
    _advance(core, 0.0, 6.0, lambda t: -1)                   # the clock has not started
    assert core.standby_pool(6.0) == (4,)
    _advance(core, 6.1, 7.0, lambda t: 50 * (t - 6.1))       # every step moves
    assert core.standby_pool(7.0) == (4,)
    _advance(core, 7.1, 9.0, lambda t: 50 * (t - 6.1), skip=(4,))
    stuck = core.agents[4].step
    core.on_status(_status(4, stuck, active=False), 9.0)    # still reporting its step
    assert core.standby_pool(9.0) == ()


def test_a_pending_reassignment_superseded_too_close_to_its_step_goes_to_every_agent():
    """Agent 1 crashes and its roles go out for step A; agent 2 crashes a few steps before
    A, too close to reuse A, and its gains come at once. Every agent of the new
    configuration gets the new epoch, the ones whose role did not change too: none runs
    the pending roles from A while the others wait for the new step."""
    core, worker, msg = _agent_1_replaced()
    role_of_3 = core.specs[3]                    # agent 3's role in the pending epoch 1
    t = 2.06
    while 50 * t < msg.activate_at - 3:                      # 3 steps before A
        t += 0.02
        for a in (2, 3, 4):
            core.on_status(_status(a, int(50 * t), epoch=1 if a != 2 else 0), t)
        core.tick(t)
    core.on_liveliness("agent", 2, False, t)
    out = []
    for k in range(1, 40):
        for a in (3, 4):
            core.on_status(_status(a, int(50 * (t + 0.01 * k)), epoch=1), t + 0.01 * k)
        if len(worker.requests) > 1 and not core.gains.has(worker.requests[-1][0]):
            # the gains in force carried over (what a warm-started fast design returns
            # when they stabilise the new configuration): agent 3's role is unchanged
            second = worker.requests[-1][0]
            core.gains.put(second, core.warm_start(second), {"kind": "fast", "rho": 0.9})
        out = core.tick(t + 0.01 * k)
        if any(isinstance(m, RosterUpdate) for m in out):
            break
    (new,) = [m for m in out if isinstance(m, RosterUpdate)]
    assert new.epoch == 2 and new.activate_at > msg.activate_at and new.ids == (4, 3)
    sent = {m.agent: m.spec for m in out if isinstance(m, Assignment)}
    assert set(sent) == {4, 3} and sent[3].same_as(role_of_3)    # unchanged, sent anyway


def test_a_monitor_that_stood_by_takes_the_seat_without_suspending_its_verdicts(paper14):
    """Monitor 2 acts while monitor 1 is away, stands by for 5 s once monitor 1 is back,
    then monitor 1's token goes: monitor 2 acts at once with its evidence as it stands
    (its detector's clock moved while it stood by: no 'monitor paused' and no suspended
    verdicts, which used to cost every hand-over the hang timeout)."""
    from agent.monitor.core import MonitorSeat

    G = [0.5 * np.eye(14)[:, list(m)] for m in paper14.measure]
    c = MonitorCore(MonitorConfig(hang_timeout_s=1.0, settle_s=0.0, step_s=0.02), paper14,
                    G, paper14.delays)
    seat = MonitorSeat(c, 2, 0.0, listen_s=1.5)
    for a in (1, 2, 3, 4):
        c.on_liveliness("agent", a, True, 0.0)
    t, states = 0.0, []
    while t < 8.0:
        for a in (1, 2, 3):
            c.on_status(_status(a, int(50 * t)), t)
        c.on_status(_status(4, int(50 * t), active=False), t)
        state = seat.decide(t, [2] if t < 2.0 else [1, 2])
        states.append(state)
        if state == "act":
            c.tick(t)
        t = round(t + 0.05, 6)
    assert states[35] == states[39] == "act" and states[-1] == "idle"
    assert seat.decide(t, [2]) == "act"
    c.tick(t)
    assert not c.detector.suspended(t)
    assert not any("paused" in e for e in c.events)


def test_an_acting_monitor_hands_over_only_when_the_smaller_id_is_about_to_act(paper14):
    """Monitor 1 restarted (its token back): monitor 2 goes on acting for its listening
    less HANDOVER_S, then stands by."""
    from agent.monitor.core import HANDOVER_S, MonitorSeat

    G = [0.5 * np.eye(14)[:, list(m)] for m in paper14.measure]
    c = MonitorCore(MonitorConfig(), paper14, G, paper14.delays)
    seat = MonitorSeat(c, 2, 0.0, listen_s=1.5)
    assert seat.decide(2.0, [2]) == "act"
    assert seat.decide(3.0, [1, 2]) == "act"           # monitor 1's token is back
    assert seat.decide(3.0 + 1.5 - HANDOVER_S - 0.01, [1, 2]) == "act"
    assert seat.decide(3.0 + 1.5 - HANDOVER_S, [1, 2]) == "idle"


# -- residual convictions: a corroborated lie, on a network where agents have two receivers


@pytest.fixture
def complete_core(paper14):
    """paper-14 with every agent listening to both others (W complete, self weight 0.5):
    each agent has two receivers, so a lie can be corroborated."""
    W = np.full((3, 3), 0.25)
    np.fill_diagonal(W, 0.5)
    s = paper14.replace(W=W)
    G = [0.5 * np.eye(14)[:, list(m)] for m in s.measure]
    c = MonitorCore(MonitorConfig(hang_timeout_s=1.0, settle_s=0.0, step_s=0.02), s, G,
                    s.delays)
    for a in (1, 2, 3, 4):
        c.on_liveliness("agent", a, True, 0.0)
    return c


def _residual_status(agent, step, levels, first_at, epoch=0, tests_epoch=None):
    """A status whose residual tests (of the configuration of ``tests_epoch``; unsaid:
    the initial one's) reached ``levels``; those >= 1 first alarmed at ``first_at``."""
    return {**_status(agent, step, epoch=epoch),
            "residuals": {"levels": levels, "first": {k: [first_at, v] for k, v in levels.items()
                                                      if v >= 1},
                          "alarms": int(any(v >= 1 for v in levels.values())),
                          "disturbed": -1, "settle": 40,
                          **({} if tests_epoch is None else {"epoch": tests_epoch})}}


#: Agent 1 lies from step 61 (levels as the simulator gives them on this network): both
#: its receivers flag it, and their links from each other alarm too, far weaker (the lie
#: entered their priors with weight 0.25); agent 1's own tests are quiet.
LIE_OF_1 = {1: {"innovation 1": 0.01, "link 2->1": 0.15, "link 3->1": 0.2},
            2: {"innovation 2": 0.01, "link 1->2": 3.8e5, "link 3->2": 5.1e3},
            3: {"innovation 3": 0.001, "link 1->3": 1.3e5, "link 2->3": 8.6e3}}


def test_a_corroborated_lie_is_convicted_and_its_role_reassigned(complete_core):
    """Both receivers of agent 1 single it out at its first alarm and nothing else
    alarms: a verdict ``inconsistent estimates`` naming the receivers and their levels,
    answered like a crash (the standby takes agent 1's node), recorded as a verdict, not
    as an alert."""
    core = complete_core
    out = _advance(core, 0.0, 1.0, lambda t: 50 * t)
    core.new_records()
    for a in (1, 2, 3):
        core.on_status(_residual_status(a, 62, LIE_OF_1[a], 61), 1.1)
    out += core.tick(1.1)
    (v,) = core.verdicts
    assert (v.agent, v.cause) == (1, "inconsistent estimates")
    assert "first alarm at step 61" in v.evidence
    assert "agent 2 (link 1->2 at 3.8e+05 x threshold)" in v.evidence
    assert "agent 3 (link 1->3 at 1.3e+05 x threshold)" in v.evidence
    asg = {m.agent: m for m in out if isinstance(m, Assignment)}
    (roster,) = [m for m in out if isinstance(m, RosterUpdate)]
    assert roster.ids == (4, 2, 3) and roster.epoch == 1 and asg[4].spec.take_over == 1
    assert core.failed == {1} and core.residual_alerts == []
    kinds = [k for k, _ in core.new_records()]
    assert "verdict" in kinds and "reassign" in kinds and "residual_alert" not in kinds
    # the isolation is not taken again (the tests are the initial configuration's)
    core.on_status(_residual_status(2, 70, LIE_OF_1[2], 68), 1.2)
    core.tick(1.2)
    assert len(core.verdicts) == 1


def test_a_liars_quiet_status_read_before_its_receivers_alarms_still_counts(complete_core):
    """Agent 1's status covering the lie's first step (its own tests quiet) is read one
    tick before its receivers' alarms. The picture at the first alarm keeps it: a
    corroborated conviction. (Before: the monitor cleared what it had heard at every quiet
    tick, so agent 1 counted as reporting no test at all, as if agents 2 and 3 did not
    send to it, and the lie stayed an alert: the live liar test failed that way in about
    a third of its runs.)"""
    core = complete_core
    _advance(core, 0.0, 1.0, lambda t: 50 * t)
    core.on_status(_residual_status(1, 62, LIE_OF_1[1], 61), 1.05)
    core.tick(1.05)
    for a in (2, 3):
        core.on_status(_residual_status(a, 62, LIE_OF_1[a], 61), 1.1)
    core.tick(1.1)
    assert [(v.agent, v.cause) for v in core.verdicts] == [(1, "inconsistent estimates")]
    assert core.residual_alerts == []


@pytest.mark.parametrize("levels, why", [
    # agent 2's own innovation alarms nearly as strongly: a near-tie (here broken in
    # favour of a sensor bias of agent 2), never corroborated
    ({**LIE_OF_1, 2: {"innovation 2": 1.0e5, "link 1->2": 3.8e5, "link 3->2": 5.1e3}},
     "near-tie"),
    # both receivers flag agent 1, but barely above their thresholds: not clear
    ({**LIE_OF_1, 2: {"innovation 2": 0.01, "link 1->2": 1.2, "link 3->2": 0.5},
      3: {"innovation 3": 0.01, "link 1->3": 1.1, "link 2->3": 0.6}}, "not clear"),
    # agent 3's estimate is off too: an alarm at agent 1 on link 3->1 (not quiet enough
    # for a lie: an absorbed bias, or two faults)
    ({**LIE_OF_1, 1: {"innovation 1": 0.01, "link 2->1": 0.15, "link 3->1": 2.0e5}},
     None),
    # agent 1's own innovation alarms: a sensor bias read from one report only
    ({**LIE_OF_1, 1: {"innovation 1": 50.0, "link 2->1": 0.15, "link 3->1": 0.2},
      2: {"innovation 2": 0.1, "link 1->2": 0.3, "link 3->2": 0.2},
      3: {"innovation 3": 0.1, "link 1->3": 0.4, "link 2->3": 0.2}}, "innovation of agent 1"),
])
def test_an_uncorroborated_isolation_stays_an_alert(complete_core, levels, why):
    """What is not corroborated convicts nobody: an alert, as before."""
    core = complete_core
    _advance(core, 0.0, 1.0, lambda t: 50 * t)
    for a in (1, 2, 3):
        core.on_status(_residual_status(a, 62, levels[a], 61), 1.1)
    out = core.tick(1.1)
    out += _advance(core, 1.2, 2.0, lambda t: 50 * t)
    assert core.verdicts == [] and out == []
    (alert,) = core.residual_alerts
    assert why is None or any(why in e for e in alert["evidence"])


def test_a_lie_seen_by_a_single_receiver_is_an_alert_only(core):
    """On paper-14's cycle agent 2 has one receiver (agent 1): its lie, however large,
    cannot be told from a fault of that link or receiver. An alert, no verdict."""
    _advance(core, 0.0, 1.0, lambda t: 50 * t)
    levels = {1: {"innovation 1": 0.02, "link 2->1": 4.0e5},
              2: {"innovation 2": 0.01, "link 3->2": 0.2},
              3: {"innovation 3": 0.03, "link 1->3": 0.3}}
    for a in (1, 2, 3):
        core.on_status(_residual_status(a, 62, levels[a], 61), 1.1)
    out = core.tick(1.1)
    out += _advance(core, 1.2, 2.0, lambda t: 50 * t)
    assert core.verdicts == [] and out == []
    (alert,) = core.residual_alerts
    assert (alert["agent"], alert["fault"]) == (2, "inconsistent estimates")
    assert any("single receiver: not corroborated" in e for e in alert["evidence"])


def _convict_the_liar(core):
    """``core`` after agent 1's lie of LIE_OF_1 at step 61, reported at t = 1.1."""
    _advance(core, 0.0, 1.0, lambda t: int(50 * t))
    for a in (1, 2, 3):
        core.on_status(_residual_status(a, 62, LIE_OF_1[a], 61), 1.1)
    core.tick(1.1)
    return core


def test_a_convicted_liar_is_not_taken_back_after_probation(complete_core):
    """Agent 1 is convicted for lying and fenced into a standby; it then looks as healthy
    as a standby can (up, advancing with the others, no impaired link) for three times
    rejoin_s: it stays on probation and out of the pool, so the next failure (agent 2's
    crash) finds no standby, where a hung agent would have rejoined
    (test_a_convicted_agent_rejoins_the_standbys_after_probation_only)."""
    core = _convict_the_liar(complete_core)
    step = lambda t: int(50 * t)                                    # noqa: E731
    assert [(v.agent, v.cause) for v in core.verdicts] == [(1, "inconsistent estimates")]
    t = 1.2
    while t < 1.2 + 3 * core.config.rejoin_s:
        for a in (2, 3, 4):
            core.on_status(_status(a, step(t), epoch=core.epoch), t)
        core.on_status(_standby_status(1, step(t)), t)
        core.tick(t)
        t += 0.1
    assert core.healthy_standby(1, t - 0.1)          # healthy by every probation check
    assert core.rejoins == [] and 1 in core.on_probation
    assert 1 not in core.standby_pool(t)
    assert not any("rejoined as a standby" in e for e in core.events)
    core.on_liveliness("agent", 2, False, t)
    core.tick(t + 0.01)
    roster = core.roster
    assert 1 not in roster.ids


def test_a_monitor_that_adopts_keeps_the_convicted_liar_out_of_the_standbys(complete_core):
    """Monitor 1 convicts agent 1 of lying and dies; monitor 2 takes the seat and adopts
    the configuration from the roster it heard (signed fields on the wire: ``probation``,
    ``barred``). Agent 1, fenced into a healthy-looking standby, stays on probation for
    good there too: the next failure finds no standby. (Before: the adopting monitor
    knew nothing of the conviction and took the liar back as a standby at once.)"""
    from agent.monitor.core import MonitorSeat
    from agent.protocol import wire

    core = _convict_the_liar(complete_core)
    step = lambda t: int(50 * t)                                    # noqa: E731
    m = core.roster_message
    assert (m.ids, m.probation, m.barred) == ((4, 2, 3), (1,), (1,))
    heard = wire.decode(wire.encode_roster(m.epoch, m.activate_at, m.ids,
                                           probation=m.probation, barred=m.barred),
                        wire.roster_schema())
    s = complete_core.scenario
    G = [0.5 * np.eye(14)[:, list(x)] for x in s.measure]
    c2 = MonitorCore(MonitorConfig(hang_timeout_s=1.0, settle_s=0.0, step_s=0.02), s, G,
                     s.delays)
    seat = MonitorSeat(c2, 2, 1.2, listen_s=0.5)
    seat.on_roster(heard)

    def statuses(t):
        for a, spec in core.specs.items():
            c2.on_status({**_status(a, step(t), epoch=m.epoch), "measure": list(spec.measure),
                          "neighbours": dict(spec.neighbours)}, t)
        c2.on_status(_standby_status(1, step(t)), t)

    for a in (1, 2, 3, 4):
        c2.on_liveliness("agent", a, True, 1.2)
    t = 1.2
    while t < 1.8:
        statuses(t)
        seat.decide(t, [2])
        t = round(t + 0.1, 6)
    assert seat.active and c2.roster.ids == (4, 2, 3)
    assert 1 in c2.on_probation and 1 in c2.barred and 1 not in c2.roster.standby_ids
    assert any("on probation (convicted before): [1], never to rejoin: [1]" in e
               for e in c2.events)
    while t < 1.8 + 3 * c2.config.rejoin_s:
        statuses(t)
        seat.decide(t, [2])
        c2.tick(t)
        t = round(t + 0.1, 6)
    assert c2.rejoins == [] and 1 not in c2.standby_pool(t)
    assert c2.roster_message.probation == (1,)       # and it tells the next monitor


def test_a_restarted_monitor_adopts_what_the_agents_run_over_an_older_roster_heard(paper14):
    """Monitor 1, restarted, heard only the roster of epoch 1 ([1, 2, 3]) while it
    listened; the agents have since switched to epoch 2 (agent 4 replaced agent 2, which
    is fenced): it adopts epoch 2 from the statuses and acts (it used to wait on the old
    roster for the rest of the run, holding the seat without acting)."""
    from agent.monitor.core import MonitorSeat

    G = [0.5 * np.eye(14)[:, list(m)] for m in paper14.measure]
    c = MonitorCore(MonitorConfig(), paper14, G, paper14.delays)
    seat = MonitorSeat(c, 1, 0.0, listen_s=1.5)
    seat.heard_roster = {"kind": "roster", "epoch": 1, "activate_at": 100, "ids": [1, 2, 3]}
    W = paper14.W
    roles = {1: ({4: W[0, 1]}, ["7"]), 4: ({3: W[1, 2]}, ["9"]), 3: ({1: W[2, 0]}, ["12"])}
    for a, (nbrs, measure) in roles.items():
        c.on_liveliness("agent", a, True, 0.0)
        c.on_status({**_status(a, 300, epoch=2), "neighbours": nbrs, "measure": measure}, 0.0)
    c.on_liveliness("agent", 2, True, 0.0)
    c.on_status({**_status(2, 300, epoch=1, active=True), "neighbours": {1: W[1, 0]},
                 "measure": ["9"]}, 0.0)
    assert seat.decide(2.0, [1]) == "act"
    assert c.roster.ids == (1, 3, 4) and c.epoch == 2 and 2 in c.failed


def test_a_passive_monitor_does_not_take_the_seat_once_the_world_has_ended(paper14):
    """Monitor 1 leaves once the world's end is heard; monitor 2, which heard it too, stays
    passive (before: it took the seat after the run and raised monitor 1's residual alert
    again from the same last statuses)."""
    from agent.monitor.core import MonitorSeat

    G = [0.5 * np.eye(14)[:, list(m)] for m in paper14.measure]
    seat = MonitorSeat(MonitorCore(MonitorConfig(), paper14, G, paper14.delays), 2, 0.0,
                       listen_s=1.5)
    seat.decide(0.5, [(1, "a"), (2, "z")])
    assert seat.decide(2.0, [(1, "a"), (2, "z")]) == "idle"
    seat.core.on_world_end(500)
    assert seat.decide(3.0, [(2, "z")]) == "idle" and not seat.active
    other = MonitorSeat(MonitorCore(MonitorConfig(), paper14, G, paper14.delays), 2, 0.0,
                        listen_s=1.5)
    other.decide(0.5, [(1, "a"), (2, "z")])
    assert other.decide(2.0, [(1, "a"), (2, "z")]) == "idle"
    assert other.decide(3.0, [(2, "z")]) == "act"          # the run going on: it acts


def test_the_seat_goes_at_once_to_a_monitor_back_from_a_pause_not_to_a_restarted_one(paper14):
    """Monitor 1's token goes (paused past the lease) and comes back with the same
    session: it acts at once, so monitor 2 stands by at once (two monitors never act
    together). Back with a new session (restarted, listening first): monitor 2 goes on
    acting until monitor 1 is about to act."""
    from agent.monitor.core import HANDOVER_S, MonitorSeat

    G = [0.5 * np.eye(14)[:, list(m)] for m in paper14.measure]
    seat = MonitorSeat(MonitorCore(MonitorConfig(), paper14, G, paper14.delays), 2, 0.0,
                       listen_s=1.5)
    seat.decide(0.5, [(1, "a"), (2, "z")])
    assert seat.decide(2.0, [(1, "a"), (2, "z")]) == "idle"
    assert seat.decide(3.0, [(2, "z")]) == "act"              # monitor 1 paused
    assert seat.decide(4.0, [(1, "a"), (2, "z")]) == "idle"   # back: same session
    assert seat.decide(5.0, [(2, "z")]) == "act"              # killed
    assert seat.decide(6.0, [(1, "b"), (2, "z")]) == "act"    # restarted: it listens
    assert seat.decide(6.0 + 1.5 - HANDOVER_S, [(1, "b"), (2, "z")]) == "idle"


def test_after_a_pause_that_took_most_tokens_a_token_back_last_is_no_crash(core):
    """The monitor was SIGSTOPped past the link lease: every token went at once, then the
    links came back one by one, agent 3's last: during the suspension that follows no
    crash verdict (a live run convicted a healthy agent 0.1 s after the others' tokens
    were back); a token still gone once the suspension is over is a crash."""
    _advance(core, 0.0, 2.0, lambda t: 50 * t)
    t = 3.2
    for a in (1, 2, 3):
        core.on_liveliness("agent", a, False, t)
    for a in (1, 2, 3, 4):
        core.on_status(_status(a, 160, active=a <= 3), t)
    assert core.tick(t) == []
    for a in (1, 2):
        core.on_liveliness("agent", a, True, t + 0.05)
    while t < 4.1:
        t = round(t + 0.05, 6)
        for a in (1, 2, 4):
            core.on_status(_status(a, int(50 * (t - 1.2)), active=a <= 3), t)
        core.tick(t)
        assert core.verdicts == [], t
    while t < 4.6 and not core.verdicts:
        t = round(t + 0.05, 6)
        core.tick(t)
    assert [(v.agent, v.cause) for v in core.verdicts] == [(3, "crash")]


def test_the_wait_for_the_clock_is_not_a_hang_but_staying_behind_after_it_is(core):
    # every agent up and waiting (step -1) for 5 s: the world starts its clock at t = 5
    _advance(core, 0.0, 5.0, lambda t: -1)

    def steps(t, late=None):
        return lambda a: -1 if a == late else int(50 * (t - 5))

    def advance(t0, t1, late=None):
        t = t0
        while t <= t1 + 1e-9:
            for a in (1, 2, 3, 4):
                core.on_status(_status(a, steps(t, late)(a), active=a <= 3), t)
            core.tick(t)
            t = round(t + 0.1, 6)

    # agent 3 still reports -1 for half a second after the others started (its loop was
    # slow to hear the clock): the 5 s it waited before the clock started are no evidence
    advance(5.1, 5.6, late=3)
    assert core.verdicts == []
    # ... but staying at -1 for the hang timeout (1 s) once the clock runs is a hang
    advance(5.7, 6.3, late=3)
    assert [(v.agent, v.cause) for v in core.verdicts] == [(3, "hang")]
    assert core.verdicts[0].evidence.startswith("step -1 for 1.10 s")


def _feed_lapse(core, paper14, t, age_of_2, statuses_of_2=True):
    """Statuses at t (50 steps/s) with agent 1 (agent 2's only listener in paper-14)
    holding agent 2's estimate ``age_of_2`` steps old; agent 2's own status reaches the
    monitor only with ``statuses_of_2``."""
    step = int(50 * t)
    for a in (1, 2, 3):
        if a == 2 and not statuses_of_2:
            continue
        nbrs = {b + 1: float(paper14.W[a - 1, b]) for b in paper14.neighbours[a - 1]}
        ages = {b: (age_of_2 if b == 2 else 1) for b in nbrs}
        core.on_status({**_status(a, step), "neighbours": nbrs, "ages": ages}, t)
    core.on_status(_status(4, step, active=False), t)
    return core.tick(t)


def test_a_link_to_the_monitor_that_lapses_convicts_nobody_its_listener_hears(core,
                                                                             paper14):
    """Agent 2's link to the monitor lapses at t = 1 s (nothing of it arrives), its token
    goes a lease later (t = 2 s), while agent 1, its listener, goes on holding its fresh
    estimates: neither a crash (the token went by its lease, not with its process) nor a
    hang (its estimates carry steps past its last status). The link comes back at 3.5 s.
    (Before: 'crash' at 2 s, a healthy agent replaced.)"""
    t = 0.0
    while t < 4.5:
        if t == 2.0:
            core.on_liveliness("agent", 2, False, t)
        if t == 3.5:
            core.on_liveliness("agent", 2, True, t)
        _feed_lapse(core, paper14, t, age_of_2=1, statuses_of_2=not 1.0 <= t < 3.5)
        t = round(t + 0.05, 6)
    assert core.verdicts == []
    assert core.detector.rejected.get("lapse") == 2, core.detector.rejected
    assert [x["agent"] for x in core.detector.anomalies if x["reason"] == "lapse"] == [2]


@pytest.mark.parametrize("lease_s, convicted", [(1.0, True), (0.4, False)])
def test_a_recent_word_is_measured_against_the_monitors_lease(paper14, lease_s, convicted):
    """Agent 2's statuses stop reaching the monitor at t = 1 s and its token goes at
    1.5 s while agent 1 still holds its fresh estimates. Under a 1 s lease the token
    went 0.5 s after a word, too soon for a lapse: an exit, 'crash' at once. Under a
    0.4 s lease (``--lease-ms 400``) a lapse is that quick: the listener decides, and
    it hears agent 2 (refused as ``lapse``, nobody convicted)."""
    G = [0.5 * np.eye(14)[:, list(m)] for m in paper14.measure]
    core = MonitorCore(MonitorConfig(hang_timeout_s=1.0, settle_s=0.0, step_s=0.02,
                                     lease_s=lease_s), paper14, G, paper14.delays)
    for a in (1, 2, 3, 4):
        core.on_liveliness("agent", a, True, 0.0)
    t = 0.0
    while t < 2.5:
        if t == 1.5:
            core.on_liveliness("agent", 2, False, t)
        _feed_lapse(core, paper14, t, age_of_2=1, statuses_of_2=t < 1.0)
        t = round(t + 0.05, 6)
    assert [(v.agent, v.cause) for v in core.verdicts] == ([(2, "crash")] if convicted
                                                             else [])
    assert ("lapse" in core.detector.rejected) is not convicted


def test_a_token_gone_by_its_lease_with_no_listener_hearing_it_is_a_crash(core, paper14):
    """The monitor paused 3 s; agent 2's token is gone when it resumes (the monitor heard
    nothing of it for the pause: no telling an exit from a lapse by the token alone).
    Agent 1, its listener, reports from then on nothing newer than the step before the
    pause: convicted 'crash' once agent 1 is CRASH_CONFIRM_STEPS past the step the token
    went at, well before the hang timeout."""
    from agent.monitor.detector import CRASH_CONFIRM_STEPS

    t = 0.0
    while t < 1.0:
        _feed_lapse(core, paper14, t, age_of_2=1)
        t = round(t + 0.05, 6)
    last_of_2 = int(50 * 0.95) - 1
    t = 4.0                                      # the monitor slept 3 s
    core.on_liveliness("agent", 2, False, t)
    gone_step = core.detector.agents[2].gone_step
    while not core.verdicts and t < 6.0:
        _feed_lapse(core, paper14, t, age_of_2=int(50 * t) - last_of_2, statuses_of_2=False)
        t = round(t + 0.05, 6)
    assert [(v.agent, v.cause) for v in core.verdicts] == [(2, "crash")]
    assert gone_step + CRASH_CONFIRM_STEPS <= core.verdicts[0].step <= gone_step + 15
    assert "lapse" not in core.detector.rejected


def test_most_tokens_gone_at_once_after_fresh_statuses_is_the_monitors_own_lapse(core,
                                                                                paper14):
    """The monitor's loop stalls past the lease with the agents' statuses queued: they are
    read just before the tokens of agents 1 and 3 (two of three) go together. Freshly
    read statuses are no recent word then: the listeners, still hearing both, decide,
    and nobody is convicted; the tokens come back. (Before: both 'crash' at once, in a
    run beside two busy loops.)"""
    t = 0.0
    while t < 3.0:
        if t == 1.0:
            core.on_liveliness("agent", 1, False, t)
            core.on_liveliness("agent", 3, False, t)
        if t == 1.5:
            core.on_liveliness("agent", 1, True, t)
            core.on_liveliness("agent", 3, True, t)
        _feed_lapse(core, paper14, t, age_of_2=1)
        t = round(t + 0.05, 6)
    assert core.verdicts == []


def test_the_token_that_comes_back_last_after_the_monitors_pause_is_no_crash(core, paper14):
    """The monitor is stopped 5 s: when it resumes, every token goes at once (its links
    lapsed: agents 2, 3, the world, 4, then 1); before its next tick the world's comes
    back, and those of 2, 3 and 4, and agent 1's 0.3 s after them. Agent 1, then the only one gone, was
    heard just before its token went; but it went with half the configuration's, so that
    is no crash: nobody is convicted. (CI: agent 1 'crash' 0.1 s after the others came
    back, a healthy agent replaced.)"""
    core.on_liveliness("world", 0, True, 0.0)
    t = 0.0
    while t < 2.0:
        _feed_lapse(core, paper14, t, age_of_2=1)
        t = round(t + 0.05, 6)
    t = 7.0                                        # the monitor was stopped 5 s
    _feed_lapse(core, paper14, t, age_of_2=1)
    for a in (2, 3):
        core.on_liveliness("agent", a, False, t)
    core.on_liveliness("world", 0, False, t)
    for a in (4, 1):
        core.on_liveliness("agent", a, False, t)
    # before the monitor's next tick: the world's and the links of 2, 3 and 4 are back
    core.on_liveliness("world", 0, True, 7.01)
    for a in (2, 3, 4):
        core.on_liveliness("agent", a, True, 7.02)
    while t < 10.0:
        t = round(t + 0.05, 6)
        if t == 7.3:
            core.on_liveliness("agent", 1, True, t)
        _feed_lapse(core, paper14, t, age_of_2=1)
    assert core.verdicts == []


def test_a_lie_after_a_recovery_is_convicted_on_the_new_configurations_tests(complete_core):
    """After agent 1's conviction (standby 4 in its row, epoch 1), agent 2 lies: reports of
    the tests of another configuration (the initial one's, an agent that did not switch
    them) are no evidence; once agents 4, 2 and 3 report tests of epoch 1, both receivers
    of agent 2 single it out and it is convicted on those tests."""
    core = _convict_the_liar(complete_core)
    step = lambda t: int(50 * t)                                    # noqa: E731
    assert core.roster.ids == (4, 2, 3) and core.epoch == 1
    at = core.history[-1]["activate_at"]
    t = 1.2
    while step(t) < at + 5:
        for a in (4, 2, 3):
            core.on_status(_status(a, step(t), epoch=1), t)
        core.tick(t)
        t += 0.1
    lie = {4: {"innovation 4": 0.01, "link 2->4": 3.8e5, "link 3->4": 5.1e3},
           3: {"innovation 3": 0.001, "link 2->3": 1.3e5, "link 4->3": 8.6e3},
           2: {"innovation 2": 0.01, "link 4->2": 0.15, "link 3->2": 0.2}}
    k = step(t)
    for a in (4, 2, 3):          # stale tests: those of the initial configuration
        core.on_status(_residual_status(a, k, lie[a], k - 1, epoch=1, tests_epoch=0), t)
    core.tick(t)
    assert [v.agent for v in core.verdicts] == [1] and core.residual_alerts == []
    t += 0.1
    k = step(t)
    for a in (4, 2, 3):
        core.on_status(_residual_status(a, k, lie[a], k - 1, epoch=1, tests_epoch=1), t)
    core.tick(t)
    core.tick(t + 0.05)
    assert [(v.agent, v.cause) for v in core.verdicts] == \
        [(1, "inconsistent estimates"), (2, "inconsistent estimates")], core.events
    assert "residual tests of the configuration of epoch 1" in core.verdicts[1].evidence
    assert "agent 4 (link 2->4" in core.verdicts[1].evidence


def test_an_earlier_alert_on_an_agent_does_not_stop_its_conviction_for_a_lie(complete_core):
    """Agent 1 is first flagged by both receivers but one only just (1.2 x its threshold:
    an alert, not corroborated); once that episode is over, both flag it clearly: it is
    convicted (the alert, raised once per agent and kind, used to swallow the conviction
    too)."""
    core = complete_core
    step = lambda t: int(50 * t)                                    # noqa: E731
    _advance(core, 0.0, 1.0, step)
    weak = {1: {"innovation 1": 0.01, "link 2->1": 0.15, "link 3->1": 0.2},
            2: {"innovation 2": 0.01, "link 1->2": 3.0e4, "link 3->2": 0.1},
            3: {"innovation 3": 0.001, "link 1->3": 1.2, "link 2->3": 0.1}}
    for a in (1, 2, 3):
        core.on_status(_residual_status(a, 52, weak[a], 51), 1.05)
    core.tick(1.05)
    assert [(r["agent"], r["fault"]) for r in core.residual_alerts] == \
        [(1, "inconsistent estimates")] and core.verdicts == []
    t = 1.1
    quiet = {a: {k: 0.1 for k in levels} for a, levels in weak.items()}
    while step(t) < 52 + 45:                   # the episode ends after its settle window
        for a in (1, 2, 3):
            core.on_status(_residual_status(a, step(t), quiet[a], 0), t)
        core.tick(t)
        t += 0.1
    k = step(t)
    for a in (1, 2, 3):
        core.on_status(_residual_status(a, k + 1, LIE_OF_1[a], k), t)
    core.tick(t)
    core.tick(t + 0.05)
    assert [(v.agent, v.cause) for v in core.verdicts] == [(1, "inconsistent estimates")], \
        core.events


@pytest.mark.parametrize("disturbed, convicted", [(20, True), (21, False)])
def test_an_alarm_at_the_tests_first_formed_step_is_not_isolated(complete_core, disturbed,
                                                                 convicted):
    """The agents' tests started over at step ``disturbed`` (a switch, a late input) and
    settle in 40 steps. A lie whose first alarm comes after their first formed step
    (``disturbed + 40``) began while they were running: convicted. One that alarms at
    that very step may have been there before they started (a standby that lied before
    it took a row; seen in a live chaos run): the picture of a fault already going on is
    not its onset's, and isolating it named a healthy agent (`sensor bias` on one of the
    liar's receivers), so it is logged as not isolated."""
    core = complete_core
    _advance(core, 0.0, 1.0, lambda t: int(50 * t))
    for a in (1, 2, 3):
        st = _residual_status(a, 62, LIE_OF_1[a], 61)
        st["residuals"]["disturbed"] = disturbed
        core.on_status(st, 1.1)
    core.tick(1.1)
    core.tick(1.15)
    assert [(v.agent, v.cause) for v in core.verdicts] == \
        ([(1, "inconsistent estimates")] if convicted else []), core.events
    assert convicted or any("not isolated" in e for e in core.events)


def test_a_first_gain_counted_below_its_target_is_the_exact_designs_and_its_radius_follows(
        monkeypatch):
    """A foreseen or unforeseen failure's first gain from the gains in force: when the
    start's eigenvalues are counted below the fast target, no eigenvalue problem of the
    delayed loop is solved; the gain is the one the exact radius picks, and the worker's
    assessment brings the exact radius (with the steady MSE) into the monitor's record."""
    from design.closed_loop import ClosedLoop
    from design.reconfigure import FAST_TARGET, fast_recovery_gains
    from design.roster import Roster, carried_gains
    from design.scenario import load_scenario, uniform_delays

    from agent.monitor.gain_worker import performance_of, plan_failures

    s = load_scenario("paper-14-live")
    r0 = Roster.initial(s, uniform_delays(s.W, 7))
    G0, _ = design_gains_for(r0, "fast")
    (roster,) = [nxt for a, nxt in plan_failures(r0) if a == [2]]
    init = carried_gains(r0, G0, roster)
    exact = fast_recovery_gains(roster.scenario, roster.delays, init=init, starts=2)
    assert exact.rho < FAST_TARGET and exact.iterations == 0        # the start, as it is
    with monkeypatch.context() as m:
        m.setattr(ClosedLoop, "companion",
                  lambda *a, **k: pytest.fail("a companion eigenvalue problem was solved"))
        G, info = design_gains_for(roster, "fast", init=init)
    assert info["rho"] is None and info["rho_below"] == (1 + FAST_TARGET) / 2
    assert all(np.array_equal(g, h) for g, h in zip(G, exact.G))
    assert f"radius below {info['rho_below']:g} (counted; exact to follow)" in _gain_words(info)
    perf = performance_of(roster, G)
    assert perf.rho == pytest.approx(exact.rho, rel=1e-12) and perf.rho < info["rho_below"]

    # in force on that gain, then the worker's assessment: the record gets both figures
    worker = _FakeWorker()
    core = MonitorCore(MonitorConfig(hang_timeout_s=1.0, settle_s=0.0, step_s=0.02),
                       s.replace(delays=r0.delays), G0, r0.delays,
                       gains=GainSource(worker=worker))
    core.gains.put(roster, G, info)
    for a in (1, 2, 3, 4):
        core.on_liveliness("agent", a, True, 0.0)
    _advance(core, 0.0, 2.0, lambda t: 50 * t)
    core.on_liveliness("agent", 2, False, 2.05)
    core.tick(2.05)
    assert core.history[-1]["gains_rho"] is None
    assert core.history[-1]["gains_rho_below"] == info["rho_below"]
    for a in roster.ids:
        core.on_status(_status(a, 110, epoch=1), 2.2)
    core.tick(2.2)
    assert ("assess",) in [k for _, k in worker.requests]     # asked for, once in force
    core.gains.put(roster, G, {**info, "rho": perf.rho, "mse": perf.mse, "assessed": True})
    core.tick(2.25)
    assert core.gain_notes == [{"epoch": 1, "gains": "fast", "gains_rho": perf.rho,
                                "gains_mse": perf.mse}]
    assert any(f"exact radius {perf.rho:.4f}, steady MSE {perf.mse:.4g}" in e
               for e in core.events)


def test_the_stability_of_learned_delays_is_counted_in_the_loop_not_solved_for(monkeypatch):
    """The delay verdict's check runs in the monitor's loop: at long delays a stable
    loop's eigenvalues are counted inside the unit circle, with no eigenvalue problem of
    order (T+1) nN; an unstable one (whose eigenvalues crowd the circle, where the count
    does not settle) gets its exact radius."""
    from design.closed_loop import ClosedLoop, closed_loop_for
    from design.roster import Roster
    from design.scenario import load_scenario, uniform_delays

    from agent.monitor.core import _stability

    s = load_scenario("paper-14-live")
    D = uniform_delays(s.W, 9)
    G, _ = design_gains_for(Roster.initial(s, D), "fast")
    unstable = closed_loop_for(s, [6.0 * g for g in G], D)
    rho = float(np.max(np.abs(np.linalg.eigvals(unstable.companion(sparse=False)))))
    assert rho > 1.01
    assert _stability(unstable) == (False, f"radius {rho:.4f}")
    monkeypatch.setattr(ClosedLoop, "spectral_radius",
                        lambda *a: pytest.fail("an eigenvalue problem was solved"))
    assert _stability(closed_loop_for(s, G, D)) == (
        True, "every eigenvalue counted inside the unit circle: radius < 1")


def test_an_assessment_is_kept_apart_and_completes_only_its_own_gain(paper14):
    """The worker's assessment of a fast gain (its exact radius and MSE) is kept whatever
    came for the configuration meanwhile: a polished gain in the cache is not replaced
    by it, and the fast gain's entry, when still there, gets its figures."""
    from design.roster import Roster

    roster = Roster.initial(paper14)
    fast = [np.ones((paper14.n, len(m))) for m in paper14.measure]
    polished = [2 * g for g in fast]
    gains = GainSource()
    gains.put(roster, fast, {"kind": "fast", "rho": None, "rho_below": 0.975, "mse": None})
    figures = {"kind": "fast", "rho": 0.93, "mse": 0.5, "assessed": True}
    gains.put(roster, fast, figures)
    G, info = gains.get(roster)
    assert np.array_equal(G[0], fast[0]) and (info["rho"], info["mse"]) == (0.93, 0.5)
    gains.put(roster, polished, {"kind": "fast", "polished": True, "rho": 0.9, "mse": None})
    gains.put(roster, fast, {**figures, "rho": 0.94})
    G, info = gains.get(roster)
    assert np.array_equal(G[0], polished[0]) and info == {
        "kind": "fast", "polished": True, "rho": 0.9, "mse": None}
    G, info = gains.assessment(roster)
    assert np.array_equal(G[0], fast[0]) and info["rho"] == 0.94


def test_an_exact_radius_not_below_the_counted_bound_is_said(core):
    """The assessment of a counted gain in force whose exact radius is not below the
    bound its count gave: the figures are recorded and a WARNING says so."""
    core.gain_info = {"kind": "fast", "rho": None, "rho_below": 0.975, "mse": None}
    core.gains.put(core.roster, core.G, {"kind": "fast", "rho": 0.99, "mse": 0.7,
                                         "assessed": True})
    core.tick(0.1)
    assert core.gain_info["rho"] == 0.99 and "rho_below" not in core.gain_info
    assert core.gain_notes[-1]["gains_rho"] == 0.99
    assert any(e.startswith("WARNING: epoch 0: the fast gain's exact radius 0.9900 is not "
                            "below 0.975") for e in core.events)


def test_a_second_monitor_precomputes_once_the_clock_started_and_stands_down_when_passive(
        paper14):
    """Monitor 2 acting while monitor 1 prepares (the clock waits for monitor 1) does not
    precompute: that duplicated monitor 1's work beside the starting agents. It does once
    an agent reports a step, and stands down when monitor 1 takes the seat. Monitor 1
    precomputes when it acts, clock or not (the clock waits for its precompute)."""
    from agent.monitor.core import MonitorSeat

    G = [0.5 * np.eye(14)[:, list(m)] for m in paper14.measure]
    c = MonitorCore(MonitorConfig(), paper14, G, paper14.delays)
    seat = MonitorSeat(c, 2, 0.0, listen_s=1.5)
    for a in (1, 2, 3, 4):
        c.on_liveliness("agent", a, True, 0.0)
        c.on_status(_status(a, -1, active=a <= 3), 0.0)
    assert seat.decide(2.0, [(2, "z")]) == "act"
    assert not seat.precompute and not seat.stand_down
    assert seat.decide(2.5, [(2, "z")]) == "act" and not seat.precompute
    c.on_status(_status(1, 0), 2.6)                    # the clock started
    assert seat.decide(2.6, [(2, "z")]) == "act" and seat.precompute
    seat.precompute = False
    seat.decide(2.7, [(1, "a"), (2, "z")])
    assert seat.decide(2.7 + 1.5, [(1, "a"), (2, "z")]) == "idle"
    assert seat.stand_down and not seat.precompute
    # its record says it took the seat and handed it over, not only that it acted
    assert [k for k, _ in seat.records] == ["active", "passive"]
    assert seat.records[-1][1] == {"monitor": 2, "to": 1, "epoch": 0}

    first = MonitorSeat(MonitorCore(MonitorConfig(), paper14, G, paper14.delays), 1, 0.0,
                        listen_s=1.5)
    assert first.decide(2.0, [(1, "a")]) == "act" and first.precompute


def test_an_agent_started_with_another_gain_is_named_once(core):
    """Its statuses carry the digest of the gain it started with: the monitor names an
    agent whose gain is not its own, once, and nobody whose gain is."""
    from design.gains import gain_digest

    for a in (1, 2, 3):
        g = core.G[a - 1] * (1.1 if a == 3 else 1.0)
        for t in (0.0, 0.2):
            core.on_status({**_status(a, -1), "gains": gain_digest(g)}, t)
    warned = [e for e in core.events if "warning" in e]
    assert len(warned) == 1 and warned[0].startswith(
        "warning: agent 3 was started with another gain than this monitor's (digest "
        f"{gain_digest(core.G[2] * 1.1)}, here {gain_digest(core.G[2])})")
    core.G = None                  # as after an adoption: the initial digests still serve
    core.on_status({**_status(2, 5), "gains": gain_digest(np.ones((14, 1)))}, 0.4)
    assert [e for e in core.events if "warning" in e][1].startswith("warning: agent 2 ")
