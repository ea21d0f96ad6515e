"""AgentCore / WorldCore stepped by hand: the protocol without any socket."""

import numpy as np
import pytest

from agent.protocol import wire
from broker_free_net.codec import decode
from design import noise
from agent.node.core import AssignmentError
from tests.runtime_harness import Mesh, reference

STEPS = 40


@pytest.fixture(scope="module")
def gains14(paper14):
    rng = np.random.default_rng(5)
    return [0.4 * rng.normal(size=(paper14.n, 1)) for _ in range(paper14.N)]


def _run(mesh, steps, wait=0.0):
    for _ in range(steps + 1):
        mesh.tick()
        if wait:
            mesh.pass_time(wait)
    return mesh


@pytest.mark.parametrize("D", [None, np.array([[0, 2, 0], [0, 0, 1], [3, 0, 0]])])
def test_mesh_equals_reference_timeline(paper14, gains14, D):
    mesh = _run(Mesh(paper14, gains14, seed=3, delays=D, deadline_s=1.0), STEPS, wait=1.1)
    xs, xh = reference(paper14, gains14, STEPS, seed=3, delays=D)
    for k in range(STEPS + 1):
        np.testing.assert_array_equal(mesh.truth[k], xs[k])
        for i in range(paper14.N):
            np.testing.assert_allclose(mesh.estimates[(i + 1, k)], xh[k][i],
                                       rtol=1e-12, atol=1e-12 * np.abs(xs[k]).max())
    # the delays were learned from the stamps
    for i in range(paper14.N):
        core = mesh.agents[i + 1]
        want = {j + 1: (0 if D is None else int(D[i, j])) for j in paper14.neighbours[i]}
        assert core.learned_delays() == want
        assert core.drops == 0 and core.late == 0


def test_standby_agent_has_no_role_and_follows_the_clock(paper14, gains14):
    mesh = _run(Mesh(paper14, gains14), 5)
    standby = mesh.agents[paper14.N + 1]
    assert not standby.active and standby.step == 5
    assert not any(a == paper14.N + 1 for a, _ in mesh.estimates)


def test_the_status_carries_the_agents_heard_until_the_clock_starts(paper14, gains14):
    """The start handshake's list of agents heard is in the status before the clock
    starts (the world waits for it), and out of it afterwards (every monitor reads every
    status), as the schema allows."""
    mesh = Mesh(paper14, gains14)
    core = mesh.agents[1]
    core.note_heard(2)
    core.note_heard(3)
    before = core.status()
    assert before["heard"] == [2, 3] and core.step < 0
    _run(mesh, 2)
    after = core.status()
    assert core.step >= 0 and "heard" not in after
    for status in (before, after):
        payload = wire.encode_status({**status, "malformed": 0, "malformed_reasons": {},
                                      "overflows": 0})
        assert decode(payload, wire.STATUS_SCHEMA)["agent"] == 1


def test_lost_estimates_count_drops_and_use_the_freshest_propagated(paper14, gains14):
    # link 2 -> 1 loses stamps 10..14; agent 1 waits the deadline, then uses stamp 9 with age
    lost = lambda src, dst, stamp: src == 2 and dst == 1 and 10 <= stamp <= 14
    mesh = Mesh(paper14, gains14, seed=1, deadline_s=0.5, lost=lost)
    for _ in range(12):
        mesh.tick()
    core = mesh.agents[1]
    assert core.step == 10  # step 11 needs stamp 10 of agent 2: waiting
    mesh.pass_time(0.49)
    assert core.step == 10
    mesh.pass_time(0.02)
    assert core.step == 11 and core.drops == 1
    for _ in range(10):
        mesh.tick()
        mesh.pass_time(0.6)
    assert core.drops == 5 and core.late == 0
    assert core.learned_delays() == {2: 0}
    # replay agent 1 by hand: stamp 9 propagated by A^(k - 9) for k = 11..15
    from design.estimator import NeighbourEstimate, PowerCache, estimator_step, role_from
    from design import noise
    P = PowerCache(paper14.A)
    x1 = mesh.estimates[(1, 10)]
    for k in range(11, 17):
        stamp = 9 if k <= 15 else k - 1
        y = mesh.truth[k][[6]] + noise.measurement_noise(1, 1, k, 1, paper14.measurement_noise)[0]
        _, x1 = estimator_step(P, role_from(paper14, gains14, 0), x1,
                               [NeighbourEstimate(0.5, k - stamp, mesh.estimates[(2, stamp)])], y)
        np.testing.assert_allclose(mesh.estimates[(1, k)], x1, rtol=1e-12)


def test_dead_neighbour_is_not_waited_for(paper14, gains14):
    mesh = Mesh(paper14, gains14, deadline_s=100.0, lost=lambda s, d, k: s == 2 and k >= 3)
    for _ in range(5):
        mesh.tick()
    assert mesh.agents[1].step == 3  # step 4 needs stamp 3 of agent 2, lost: waiting
    mesh.agents[1].set_alive(2, False)
    mesh.pass_time(0.0)
    assert mesh.agents[1].step == 4 and mesh.agents[1].drops == 1


def _assignment(s, agent, epoch, at, measure, neighbours, self_weight, gain):
    payload = wire.encode_ctl(agent, epoch, at, measure, neighbours, self_weight, gain)
    return wire.decode(payload, wire.ctl_schema(s.n))


def test_assignment_switches_measured_node_at_the_stated_step(paper14, gains14):
    s = paper14
    mesh = Mesh(s, gains14)
    for _ in range(6):
        mesh.tick()
    core = mesh.agents[1]
    g = np.full((s.n, 1), 0.1)
    core.on_assignment(_assignment(s, 1, 1, 10, ["8"], {2: 0.5}, 0.5, g))
    assert core.wanted_labels() == ("7", "8")
    for _ in range(3):  # steps 6..8
        mesh.tick()
    assert core.status()["measure"] == ["7"] and core.step == 8
    mesh.tick()  # step 9: still the old role
    assert core.status()["measure"] == ["7"] and core.epoch == 0
    mesh.tick()  # step 10: the new one
    assert core.status()["measure"] == ["8"] and core.epoch == 1
    assert core.wanted_labels() == ("8",)


def test_assignment_activates_a_standby_agent(paper14, gains14):
    s = paper14
    mesh = Mesh(s, gains14)
    for _ in range(5):
        mesh.tick()
    sb = mesh.agents[4]
    sb.on_assignment(_assignment(s, 4, 1, 8, ["8"], {2: 0.5}, 0.5, np.full((s.n, 1), 0.1)))
    for _ in range(5):
        mesh.tick()
    # a cold start: the initial estimate of agent 4, published stamped activate_at - 1
    assert sb.active and (4, 8) in mesh.estimates and (4, 6) not in mesh.estimates
    np.testing.assert_array_equal(mesh.estimates[(4, 7)], noise.initial_estimate(0, 4, s.n)[0])


@pytest.mark.parametrize("change, match", [
    (dict(epoch=1, at=3), "activate_at"),           # already past
    (dict(measure=["99"]), "unknown node labels"),
    (dict(neighbours={9: 0.5}), "unknown agents"),
    (dict(neighbours={1: 0.5}), "its own neighbour"),
    (dict(self_weight=0.6), "must be 1"),
    (dict(gain=np.zeros((14, 2))), "gain: shape"),
    (dict(agent=2), "for agent 2"),
])
def test_invalid_assignments_are_rejected_with_a_reason(paper14, gains14, change, match):
    s = paper14
    mesh = _run(Mesh(s, gains14), 5)
    core = mesh.agents[1]
    args = dict(agent=1, epoch=1, at=20, measure=["8"], neighbours={2: 0.5}, self_weight=0.5,
                gain=np.zeros((s.n, 1)))
    args.update(change)
    msg = _assignment(s, args["agent"], args["epoch"], args["at"], args["measure"],
                      args["neighbours"], args["self_weight"], args["gain"])
    with pytest.raises(AssignmentError, match=match):
        core.on_assignment(msg)
    assert core.ctl_rejected == 1 and core.pending is None


def test_older_epochs_are_rejected(paper14, gains14):
    s = paper14
    core = _run(Mesh(s, gains14), 2).agents[1]
    g = np.zeros((s.n, 1))
    core.on_assignment(_assignment(s, 1, 5, 30, ["8"], {2: 0.5}, 0.5, g))
    with pytest.raises(AssignmentError, match="not newer"):
        core.on_assignment(_assignment(s, 1, 5, 31, ["8"], {2: 0.5}, 0.5, g))
    with pytest.raises(AssignmentError, match="not newer"):
        core.on_assignment(_assignment(s, 1, 4, 31, ["8"], {2: 0.5}, 0.5, g))
    core.on_assignment(_assignment(s, 1, 6, 31, ["9"], {2: 0.5}, 0.5, g))
    assert core.pending.epoch == 6


def test_partition_counts_drops_and_injected_delay_is_learned(paper14, gains14):
    s = paper14
    mesh = Mesh(s, gains14, deadline_s=0.1)
    for _ in range(5):
        mesh.tick()
    core = mesh.agents[1]
    core.on_impairment({"op": "set", "src": 2, "dst": 1, "partition": True})
    for _ in range(5):
        mesh.tick()
        mesh.pass_time(0.2)
    assert core.drops == 4 and core.impaired == 5  # step 5 still had stamp 4
    core.on_impairment({"op": "set", "src": 2, "dst": 1, "partition": False, "delay_steps": 3})
    for _ in range(12):
        mesh.tick()
        mesh.pass_time(0.2)
    assert core.learned_delays() == {2: 3}
    assert core.status()["links"] == {"2": {"delay_steps": 3}}


@pytest.mark.parametrize("D", [None, np.array([[0, 2, 0], [0, 0, 1], [3, 0, 0]])])
def test_mesh_equals_the_simulator(paper14, gains14, D):
    from design.simulate import simulate

    mesh = _run(Mesh(paper14, gains14, seed=4, delays=D, deadline_s=1.0), STEPS, wait=1.1)
    res = simulate(paper14, gains14, steps=STEPS, trials=1, seed=4, delays=D)
    mse = [np.mean([np.mean((mesh.estimates[(a, k)] - mesh.truth[k]) ** 2) for a in (1, 2, 3)])
           for k in range(STEPS + 1)]
    np.testing.assert_allclose(mse, res.mse, rtol=1e-9)


# -- one neighbour policy: the live protocol equals the simulator with failures ---------


def _mesh_estimates(mesh, ids, steps):
    out = np.full((steps + 1, len(ids), mesh.s.n), np.nan)
    for k in range(steps + 1):
        for c, a in enumerate(ids):
            if (a, k) in mesh.estimates:
                out[k, c] = mesh.estimates[(a, k)]
    return out


def _sim_estimates(res, ids):
    cols = [res.estimate_ids.index(a) for a in ids]
    return res.estimates[0][:, cols]


D3 = np.array([[0, 2, 0], [0, 0, 1], [3, 0, 0]])


@pytest.mark.parametrize("D", [None, D3])
def test_crashed_neighbour_is_held_then_lost_as_in_the_simulator(paper14, gains14, D):
    """Agent 2 crashes after publishing step 9: its neighbours hold its last estimates,
    propagated, until they are older than the hold limit, exactly as the simulator."""
    from design.estimator import hold_limit
    from design.simulate import simulate

    f, steps = 10, 45
    mesh = Mesh(paper14, gains14, seed=4, delays=D, deadline_s=1.0)
    for k in range(steps + 1):
        if k == f:
            mesh.crash(2)
        mesh.tick()
        mesh.pass_time(1.1)
    res = simulate(paper14, gains14, steps=steps, trials=1, seed=4, delays=D, fail=(f, [1]),
                   coordinates="absolute", record_estimates=True)
    live = _mesh_estimates(mesh, (1, 3), steps)
    np.testing.assert_allclose(live, _sim_estimates(res, (1, 3)), rtol=1e-12, atol=1e-12)
    # the hold limit was crossed: agent 1 (which listens to 2) used 'lost' inputs
    top = 0 if D is None else int(D.max())
    assert steps - f > hold_limit(top)
    assert mesh.agents[1].states["lost"] > 0 and mesh.agents[1].states["held"] > 0


def test_keyed_drops_equal_the_simulators(paper14, gains14):
    from design.simulate import simulate

    steps = 40
    mesh = Mesh(paper14, gains14, seed=6, delays=D3, deadline_s=1.0, drop=0.4)
    for _ in range(steps + 1):
        mesh.tick()
        mesh.pass_time(1.1)
    res = simulate(paper14, gains14, steps=steps, trials=1, seed=6, delays=D3, drop=0.4,
                   coordinates="absolute", record_estimates=True)
    np.testing.assert_allclose(_mesh_estimates(mesh, (1, 2, 3), steps),
                               _sim_estimates(res, (1, 2, 3)), rtol=1e-12, atol=1e-12)
    assert sum(c.states["held"] for c in mesh.agents.values()) > 0


@pytest.mark.parametrize("D", [None, D3])
def test_role_change_after_a_crash_equals_the_simulator(paper14, gains14, D):
    """Agent 1 crashes at step 10; from step 16 standby 4 takes its place (taking over
    its last estimate), every row gets new gains: the live protocol and the simulator
    agree estimate by estimate, the replacement included."""
    from design.roster import Roster, replan, role_specs
    from design.simulate import Recovery, simulate

    f, a, steps = 10, 16, 40
    roster = Roster.initial(paper14, D)
    plan, after = replan(roster, [1])
    rng = np.random.default_rng(9)
    G_after = [0.3 * rng.normal(size=(paper14.n, len(m))) for m in after.scenario.measure]
    specs = role_specs(after, G_after, take_over={4: 1})
    mesh = Mesh(paper14, gains14, seed=2, delays=D, deadline_s=1.0)
    for k in range(steps + 1):
        if k == f:
            mesh.crash(1)
        if k == f + 2:      # the assignments arrive a few steps ahead of activate_at
            for agent, spec in specs.items():
                mesh.agents[agent].on_assignment(_spec_message(spec, epoch=1, at=a))
        mesh.tick()
        mesh.pass_time(1.1)
    rec = Recovery(after.scenario, G_after, after.ids, replaces={4: 0}, delays=after.delays,
                   activate_at=a)
    res = simulate(paper14, gains14, steps=steps, trials=1, seed=2, delays=D, fail=(f, [0]),
                   recover=rec, coordinates="absolute", record_estimates=True)
    ids = (2, 3, 4)
    live = _mesh_estimates(mesh, ids, steps)
    # the replacement published the estimate it took over, stamped a - 1:
    # agent 1's last estimate (stamp f - 1) propagated to step a - 1
    np.testing.assert_allclose(
        live[a - 1, 2], np.linalg.matrix_power(paper14.A, a - f) @ mesh.estimates[(1, f - 1)],
        rtol=1e-12)
    assert (4, a - 2) not in mesh.estimates
    live[a - 1, 2] = np.nan      # the simulator records agents from the step they compute
    np.testing.assert_allclose(live, _sim_estimates(res, ids), rtol=1e-12, atol=1e-12)
    # and the error coordinates of the simulator (another code path) agree on the MSE
    res_e = simulate(paper14, gains14, steps=steps, trials=1, seed=2, delays=D,
                     fail=(f, [0]), recover=rec)
    np.testing.assert_allclose(res_e.mse, res.mse, rtol=1e-9)


def _spec_message(spec, epoch, at):
    return {"agent": spec.agent, "epoch": epoch, "activate_at": at,
            "measure": list(spec.measure), "neighbours": dict(spec.neighbours),
            "self_weight": spec.self_weight, "gain": spec.gain,
            **({"take_over": spec.take_over} if spec.take_over else {}),
            **({"continues": dict(spec.continues)} if spec.continues else {})}


def _two_replans(scenario, first, second, seed):
    """The configurations after agent ``first`` is replaced (standby 4 takes its row) and
    then agent ``second`` removed, random gains for each (``seed``), and their role specs:
    ``(r1, r2, G1, G2, specs1, specs2)``."""
    from design.roster import Roster, replan, role_specs

    _, r1 = replan(Roster.initial(scenario, D3), [first])
    _, r2 = replan(r1, [second])
    rng = np.random.default_rng(seed)
    G1 = [0.3 * rng.normal(size=(scenario.n, len(m))) for m in r1.scenario.measure]
    G2 = [0.3 * rng.normal(size=(scenario.n, len(m))) for m in r2.scenario.measure]
    return (r1, r2, G1, G2, role_specs(r1, G1, take_over={4: first}), role_specs(r2, G2))


def _run_schedule(mesh, steps, crashes, assignments, pass_s=None):
    """Step ``mesh`` through step ``steps``: at a step of ``crashes`` ({step: agents}) those
    agents crash; at the step of each ``(step, specs, epoch, activate_at)`` of
    ``assignments`` every live agent given a spec gets its assignment; ``pass_s`` seconds
    pass after each tick when given."""
    for k in range(steps + 1):
        for agent in crashes.get(k, ()):
            mesh.crash(agent)
        for at, specs, epoch, activate_at in assignments:
            if k == at:
                for agent, spec in specs.items():
                    if agent in mesh.agents:
                        mesh.agents[agent].on_assignment(
                            _spec_message(spec, epoch=epoch, at=activate_at))
        mesh.tick()
        if pass_s is not None:
            mesh.pass_time(pass_s)


def test_a_chain_of_reassignments_equals_the_simulator(paper14, gains14):
    """Agents 1 and 2 crash together, but the reassignments come one after the other
    (first 1 -> standby 4 with 2 still a row, then 2 removed): the live protocol and the
    simulator's chain of recoveries agree estimate by estimate. The standby had heard
    agent 2 before; on its new link to 2 it uses only what arrives from its activation
    on, as the simulator does."""
    from design.simulate import Recovery, simulate

    f, a1, a2, steps = 10, 14, 17, 40
    r1, r2, G1, G2, specs1, specs2 = _two_replans(paper14, 1, 2, seed=3)
    mesh = Mesh(paper14, gains14, seed=5, delays=D3, deadline_s=1.0)
    _run_schedule(mesh, steps, {f: (1, 2)}, [(f + 1, specs1, 1, a1), (a1 + 1, specs2, 2, a2)],
                  pass_s=1.1)
    chain = [Recovery(r1.scenario, G1, r1.ids, replaces={4: 0}, delays=r1.delays,
                      activate_at=a1),
             Recovery(r2.scenario, G2, r2.ids, delays=r2.delays, activate_at=a2)]
    res = simulate(paper14, gains14, steps=steps, trials=1, seed=5, delays=D3,
                   fail=(f, [0, 1]), recover=chain, coordinates="absolute",
                   record_estimates=True)
    ids = (3, 4)
    live = _mesh_estimates(mesh, ids, steps)
    live[a1 - 1, 1] = np.nan
    np.testing.assert_allclose(live, _sim_estimates(res, ids), rtol=1e-12, atol=1e-12)


def test_failures_at_different_steps_replay_in_the_simulator(paper14, gains14):
    """Agent 1 crashes at step 10 and agent 2 at step 12; the standby 4 takes over agent
    2's row at 17 (agent 1 still a row, computing nothing) and agent 1 is removed at 24.
    The standby starts from agent 2's last estimate (stamp 11) propagated over 5 steps,
    not from the first failure's step: the simulator's failures at their own steps and
    the live protocol agree estimate by estimate."""
    from design.simulate import Recovery, simulate

    f1, f2, a1, a2, steps = 10, 12, 17, 24, 40
    r1, r2, G1, G2, specs1, specs2 = _two_replans(paper14, 2, 1, seed=4)
    assert 4 in r1.ids and 1 in r1.ids and 1 not in r2.ids
    mesh = Mesh(paper14, gains14, seed=5, delays=D3, deadline_s=1.0)
    _run_schedule(mesh, steps, {f1: (1,), f2: (2,)},
                  [(f2 + 1, specs1, 1, a1), (a1 + 1, specs2, 2, a2)], pass_s=1.1)
    chain = [Recovery(r1.scenario, G1, r1.ids, replaces={4: 1}, delays=r1.delays,
                      activate_at=a1),
             Recovery(r2.scenario, G2, r2.ids, delays=r2.delays, activate_at=a2)]
    fail = [(f1, [0]), (f2, [1])]
    res = simulate(paper14, gains14, steps=steps, trials=1, seed=5, delays=D3,
                   fail=fail, recover=chain, coordinates="absolute", record_estimates=True)
    ids = (3, 4)
    live = _mesh_estimates(mesh, ids, steps)
    live[a1 - 1, 1] = np.nan
    np.testing.assert_allclose(live, _sim_estimates(res, ids), rtol=1e-12, atol=1e-12)
    res_e = simulate(paper14, gains14, steps=steps, trials=1, seed=5, delays=D3,
                     fail=fail, recover=chain)
    np.testing.assert_allclose(res_e.mse, res.mse, rtol=1e-9)


@pytest.mark.parametrize("continues", [True, False])
def test_a_replacements_link_continues_the_failed_agents_stream(paper14, gains14, continues):
    """Agent 3 listens to agent 1 over a 3-step link; 1 crashes after step 9 and the
    standby 4 takes its row at step 14 (its own first estimate, stamped 13, reaches 3 at
    step 17). With ``continues`` (the wire field), agent 3 reads 1's stream on the new
    link meanwhile: its held estimate (stamp 9), propagated. Without it the link is empty
    and the weight goes to its own prediction."""
    from design.estimator import continued_stamp

    s = paper14
    mesh = Mesh(s, gains14, seed=4, delays=D3)
    for _ in range(10):
        mesh.tick()                                  # steps 0..9
    mesh.crash(1)
    for _ in range(3):
        mesh.tick()                                  # steps 10..12
    g = np.full((s.n, 1), 0.1)
    w = float(s.W[2, 0])
    payload = wire.encode_ctl(3, 1, 14, ["12"], {4: w}, 1 - w, g,
                              continues={4: 1} if continues else None)
    msg = wire.decode(payload, wire.ctl_schema(s.n))
    assert ("continues" in msg) is continues
    mesh.agents[3].on_assignment(msg)
    mesh.agents[4].on_assignment(_assignment(s, 4, 1, 14, ["7"], {2: 0.5}, 0.5, g))
    core = mesh.agents[3]
    before = dict(core.states)
    mesh.tick()                                      # step 13: old role, 1's stamp 9 due
    mesh.tick()                                      # step 14: the new link from 4
    plan = core._plan(15, mesh.now)
    stamp, _need, src = plan[4]
    if continues:
        assert (stamp, src) == (9, 1) and continued_stamp(stamp, first_own=13)
    else:
        assert stamp is None
    held = core.states["held"] - before["held"]
    assert held == (1 if continues else 0)           # step 14 continues 1's stream


def test_a_replay_of_old_estimates_does_not_change_the_learned_delay(paper14, gains14):
    """A publisher's cache answers a subscription declared again (a standby taking a
    role): the agent gets again, at once, estimates it already holds. Their ages say
    nothing of the link: the delay learned from the fresh ones stays, and so does the
    step computed next."""
    D = np.array([[0, 2, 0], [0, 0, 1], [3, 0, 0]])
    mesh = _run(Mesh(paper14, gains14, seed=3, delays=D, deadline_s=1.0), 30, wait=1.1)
    core = mesh.agents[1]
    assert core.learned_delays() == {2: 2}
    held = {s: x for s, x in core.nbrs[2].est.items()}
    # the cache's replay comes after newer estimates of the live stream: stamps 9..23
    # while 28 is held (their ages, 7 to 21 steps, filled the 8-sample window: tau 7)
    for stamp in sorted(held)[-20:-5]:
        core.on_estimate(2, stamp, held[stamp], mesh.now)
    core.poll(mesh.now)
    assert core.learned_delays() == {2: 2}


@pytest.mark.parametrize("lag", [0, 3, 12])
def test_neighbour_only_a_new_link_from_an_agent_never_heard_equals_the_simulator(
        paper14, gains14, lag):
    """Neighbour-only subscriptions (tests.runtime_harness.Mesh): agent 2 crashes at step
    12 and the standby 4 takes its row at 17; agent 1 crashes at 10 and is removed at
    24, when agent 3 listens to agent 4 over a 3-step link, an agent it never heard before
    (it subscribes at the assignment, at 18). Agent 4's cache gives it 4's last estimates,
    the one stamped 24 - 1 - 3 among them; answered ``lag`` ticks late (a loaded machine),
    that history and the live estimates held back with it come only after step 24 began,
    when the link's delay is not learned yet. The estimates equal the simulator's, which
    reads stamp 20 on the new link at step 24, whatever the lag."""
    from design.simulate import Recovery, simulate

    f1, f2, a1, a2, steps = 10, 12, 17, 24, 40
    r1, r2, G1, G2, specs1, specs2 = _two_replans(paper14, 2, 1, seed=4)
    assert 4 in specs2[3].neighbours and 4 not in specs1[3].neighbours
    mesh = Mesh(paper14, gains14, seed=5, delays=D3, deadline_s=1e6, neighbour_only=True,
                history_lag=lag)
    _run_schedule(mesh, steps, {f1: (1,), f2: (2,)},
                  [(f2 + 1, specs1, 1, a1), (a1 + 1, specs2, 2, a2)])
    for _ in range(lag):                   # the last held-back estimates come
        mesh.pass_time(0.001)
        mesh.ticks += 1
    core = mesh.agents[3]
    assert 4 not in core.nbrs or core.nbrs[4].heard       # heard at last, never before 18
    assert mesh.sources[3] == {4}
    chain = [Recovery(r1.scenario, G1, r1.ids, replaces={4: 1}, delays=r1.delays,
                      activate_at=a1),
             Recovery(r2.scenario, G2, r2.ids, delays=r2.delays, activate_at=a2)]
    res = simulate(paper14, gains14, steps=steps, trials=1, seed=5, delays=D3,
                   fail=[(f1, [0]), (f2, [1])], recover=chain, coordinates="absolute",
                   record_estimates=True)
    ids = (3, 4)
    live = _mesh_estimates(mesh, ids, steps)
    live[a1 - 1, 1] = np.nan
    np.testing.assert_allclose(live, _sim_estimates(res, ids), rtol=1e-12, atol=1e-12)
