"""Whose estimates an agent subscribes to (agent.node.subscriptions), on a real AgentCore
through an assignment: in-neighbours only, the pending role's from its acceptance, the
failed agent a new neighbour continues, every agent while a standby."""

import numpy as np

from agent.node.subscriptions import estimate_sources
from agent.protocol import topics, wire
from tests.runtime_harness import Mesh


def _assignment(s, agent, epoch, at, measure, neighbours, self_weight, gain, **extra):
    payload = wire.encode_ctl(agent, epoch, at, measure, neighbours, self_weight, gain,
                              **extra)
    return wire.decode(payload, wire.ctl_schema(s.n))


def test_an_agent_hears_its_in_neighbours_and_follows_its_role(paper14):
    s = paper14
    G = [np.full((s.n, len(m)), 0.1) for m in s.measure]
    mesh = Mesh(s, G)
    for _ in range(5):
        mesh.tick()
    core, standby = mesh.agents[1], mesh.agents[s.N + 1]
    ins = {j + 1 for j in s.neighbours[0]}
    assert estimate_sources(core) == ins and 1 not in ins
    assert estimate_sources(standby) is None          # may take over anyone
    # agent 1 is told to listen to agent 3 instead, continuing agent 2's stream (2 failed
    # and 3 took over its row): from the acceptance it hears the old and the new ones
    msg = _assignment(s, 1, 1, 12, [s.labels[s.measure[0][0]]], {3: 0.5}, 0.5, G[0],
                      continues={3: 2})
    core.on_assignment(msg)
    assert estimate_sources(core) == ins | {3, 2}
    for _ in range(9):
        mesh.tick()
    assert core.epoch == 1
    # in force: agent 3, and agent 2 whose stream the link from 3 continues
    assert estimate_sources(core) == {3, 2}
    # the standby told to take over agent 2 keeps hearing everyone until the role is in
    # force, then only its in-neighbours
    standby.on_assignment(_assignment(s, s.N + 1, 1, 20, [s.labels[s.measure[1][0]]],
                                      {1: 0.5}, 0.5, G[1], take_over=2))
    assert estimate_sources(standby) is None
    for _ in range(8):
        mesh.tick()
    assert standby.active and estimate_sources(standby) == {1}
    subs = topics.estimate_subscriptions("r", estimate_sources(standby), core.history)
    assert subs == {"socmon/r/est/1": core.history}
