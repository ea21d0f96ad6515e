"""An in-memory network of AgentCore/WorldCore for unit tests: time is stepped by hand."""

import numpy as np

from agent.node.core import AgentCore, agent_config
from agent.world.core import WorldCore
from design import noise
from design.estimator import NeighbourEstimate, PowerCache, estimator_step, role_from


class Mesh:
    """World + agents wired in memory; ``lost(src, dst, stamp)`` drops estimates in transit.

    ``neighbour_only``: each agent receives the estimates of
    :func:`agent.node.subscriptions.estimate_sources` only, followed as the agent process
    follows them; a sender added to its sources delivers its last ``history`` estimates
    (its publisher's cache) and then its live ones, both held back for ``history_lag``
    ticks (a history query answered late: zenoh's advanced subscriber holds the live
    samples until the history has come)."""

    def __init__(self, scenario, G, seed=0, delays=None, deadline_s=1.0, lost=None, drop=0.0,
                 residuals=False, neighbour_only=False, history_lag=0):
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
        self.neighbour_only = neighbour_only
        self.history_lag = int(history_lag)
        self.ticks = 0
        # receiver -> the senders it follows (None: every agent); those of the start are
        # subscribed before the clock runs (the start handshake)
        self.sources = {a: None for a in self.agents}
        if neighbour_only:
            from agent.node.subscriptions import estimate_sources

            self.sources = {a: estimate_sources(c) for a, c in self.agents.items()}
        self.joining = {}    # (receiver, sender) -> [tick it comes, queued (stamp, x)]

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
        self.ticks += 1

    def settle(self):
        moved = True
        while moved:
            moved = False
            for a, core in list(self.agents.items()):
                self._follow(a)
                for step, x, _epoch in core.poll(self.now):
                    moved = True
                    self.estimates[(a, step)] = x.copy()
                    for b, other in self.agents.items():
                        if b != a and not self.lost(a, b, step):
                            self._send(a, b, step, x)
                moved |= self._follow(a)

    def _send(self, a, b, step, x):
        """Estimate ``step`` of agent ``a`` to agent ``b``, as its subscriptions let it."""
        wanted = self.sources.get(b)
        if wanted is not None and a not in wanted:
            return
        queued = self.joining.get((b, a))
        if queued is not None:
            queued[1].append((step, x))
        else:
            self.agents[b].on_estimate(a, step, x, self.now)

    def _follow(self, b) -> bool:
        """Agent ``b`` follows its estimate sources (neighbour-only), and gets each new
        source's history and held-back estimates once due. True if any came."""
        if self.neighbour_only:
            self._subscribe(b)
        came = False
        for (r, a), (at, items) in list(self.joining.items()):
            if r == b and at <= self.ticks:
                del self.joining[(r, a)]
                for step, x in items:
                    self.agents[b].on_estimate(a, step, x, self.now)
                came = True
        return came

    def _subscribe(self, b) -> None:
        from agent.node.subscriptions import estimate_sources

        core = self.agents[b]
        wanted = estimate_sources(core)
        old = self.sources.get(b)
        if wanted == old:
            return
        self.sources[b] = wanted
        if wanted is None:
            return
        for key in [k for k in self.joining if k[0] == b and k[1] not in wanted]:
            del self.joining[key]
        # est/* -> est/<j> declares each est/<j> anew (with its history), as the process does
        for a in sorted(set(wanted) - (set() if old is None else set(old))):
            if a not in self.agents:
                continue                       # a dead agent's cache is gone with it
            stamps = sorted(s for (who, s) in self.estimates if who == a)[-core.history:]
            cache = [(s, self.estimates[(a, s)]) for s in stamps]
            self.joining[(b, a)] = [self.ticks + self.history_lag, cache]

    def crash(self, agent):
        """Agent ``agent`` stops (after what it published); the others see its token go."""
        del self.agents[agent]
        for key in [k for k in self.joining if agent in k]:
            del self.joining[key]
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
