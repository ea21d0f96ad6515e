"""An in-memory network of AgentCore/WorldCore for unit tests: time is stepped by hand."""

import numpy as np

from agent.node.core import AgentCore, agent_config
from agent.world.core import WorldCore
from design import noise
from design.estimator import NeighbourEstimate, PowerCache, estimator_step, role_from


class Mesh:
    """World + agents wired in memory; ``lost(src, dst, stamp)`` drops estimates in transit."""

    def __init__(self, scenario, G, seed=0, delays=None, deadline_s=1.0, lost=None, drop=0.0,
                 residuals=False):
        self.s = scenario
        delays = np.zeros((scenario.N, scenario.N), int) if delays is None else delays
        M = scenario.N + scenario.standby
        self.world = WorldCore(scenario.A, seed, scenario.process_noise)
        self.agents = {a: AgentCore(agent_config(scenario, a, G, seed, delays, deadline_s,
                                                 drop=drop, residuals=residuals))
                       for a in range(1, M + 1)}
        self.lost = lost or (lambda src, dst, stamp: False)
        self.now = 0.0
        self.estimates = {}  # (agent, step) -> x
        self.truth = {}

    def tick(self, dt=0.001):
        """Publish the world's step k to every agent and let the agents run; advance."""
        k = self.world.step
        self.truth[k] = self.world.x.copy()
        for core in self.agents.values():
            for label in core.wanted_labels():
                core.on_sensor(label, k, self.world.x[self.s.index_of(label)])
        self.settle()
        self.world.advance()
        self.now += dt

    def settle(self):
        moved = True
        while moved:
            moved = False
            for a, core in self.agents.items():
                for step, x, _epoch in core.poll(self.now):
                    moved = True
                    self.estimates[(a, step)] = x.copy()
                    for b, other in self.agents.items():
                        if b != a and not self.lost(a, b, step):
                            other.on_estimate(a, step, x, self.now)

    def crash(self, agent):
        """Agent ``agent`` stops (after what it published); the others see its token go."""
        del self.agents[agent]
        for core in self.agents.values():
            core.set_alive(agent, False)

    def pass_time(self, dt):
        self.now += dt
        self.settle()


def reference(scenario, G, steps, seed=0, delays=None):
    """The estimator timeline of design/noise + design/estimator, written out directly."""
    s = scenario
    n, N = s.n, s.N
    D = np.zeros((N, N), int) if delays is None else delays
    P = PowerCache(s.A)
    x = noise.initial_state(seed, n)[0]
    xs = [x]
    xh = [np.array([noise.initial_estimate(seed, i + 1, n)[0] for i in range(N)])]
    for k in range(1, steps + 1):
        x = s.A @ x + noise.process_noise(seed, k - 1, n, s.process_noise)[0]
        xs.append(x)
        cur = np.zeros((N, n))
        for i in range(N):
            nbs = []
            for j in s.neighbours[i]:
                stamp = k - 1 - D[i, j]  # nothing exists before step 0
                x_j = xh[stamp][j] if stamp >= 0 else None
                nbs.append(NeighbourEstimate(s.W[i, j], k - stamp, x_j))
            p = len(s.measure[i])
            y = x[list(s.measure[i])] + noise.measurement_noise(seed, i + 1, k, p,
                                                                 s.measurement_noise)[0]
            _, cur[i] = estimator_step(P, role_from(s, G, i), xh[k - 1][i], nbs, y)
        xh.append(cur)
    return np.array(xs), np.array(xh)
