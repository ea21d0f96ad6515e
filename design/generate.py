"""Generated scenarios: any number of agents on a social graph of communities.

:func:`communities_scenario` builds the scenario dict (the TOML tables, for
:func:`design.scenario.scenario_from_dict`) of N communities and a public of ``public``
individuals (one child SCC): one member of every community listens to one individual of
the public, and nothing a community thinks leaves it, so each community is a parent SCC.
Agent i measures one member of community i, so every parent SCC is measured and the
system is observable; every node has a self-loop (``a_ii != 0``), so the
distributed pair meets the premise of the paper's Lemma 3. The agents talk on a cycle.
The built-in scenarios ``communities-16`` and ``communities-32`` are this with 16 and 32
agents (``scripts/make_scale_scenarios.py`` writes them); they serve the scale benchmark
(``scripts/bench_scale.py``).

Examples
--------
>>> from design.scenario import scenario_from_dict
>>> s = scenario_from_dict(communities_scenario(4, seed=1))
>>> s.n, s.N, [s.agent_labels(i) for i in range(s.N)]
(12, 4, [['c1a'], ['c2a'], ['c3a'], ['c4a']])
>>> round(s.rho_A, 6)
0.95
"""

from __future__ import annotations

import numpy as np

__all__ = ["communities_scenario"]


def communities_scenario(N: int, *, size: int = 2, public: int = 4, seed: int = 0,
                         spectral_radius: float = 0.95, standby: int = 0,
                         self_weight: float = 0.6, step_ms: int = 10,
                         noise: float = 0.05) -> dict:
    """The scenario dict of N communities of `size` members and a public of `public`.

    Parameters
    ----------
    N : int
        Agents and communities (>= 1).
    size : int
        Members per community (>= 1; with >= 2 a standby agent can take over a
        community by measuring another member).
    public : int
        Individuals of the public (>= 1), on a directed cycle.
    seed : int
        Seed of the weights (uniform in [0.2, 1)).
    spectral_radius : float
        A is rescaled to this radius.
    standby : int
        Standby agents (the monitor gives a failed agent's community to one of them,
        measuring another member).
    self_weight : float
        The agents' own weight on the cycle (0.5 would make W singular for even N).
    step_ms : int
        The runtime step in ms.
    noise : float
        Standard deviation of the process and the measurement noise.

    Returns
    -------
    dict
        The tables of a scenario TOML file (name ``communities-<N>``).
    """
    for name, value, lo in (("N", N, 1), ("size", size, 1), ("public", public, 1),
                            ("standby", standby, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < lo:
            raise ValueError(f"{name}: expected an int >= {lo}, got {value!r}")
    if size > 26:                         # members are labelled a..z within a community
        raise ValueError(f"size: at most 26 members a community, got {size}")
    if standby > N or (standby and size < 2):
        raise ValueError(f"standby: at most N = {N} standby agents, and only with size >= 2, "
                         f"got {standby} with size {size}")
    rng = np.random.default_rng(seed)
    labels = [f"c{c + 1}{chr(ord('a') + m)}" for c in range(N) for m in range(size)]
    labels += [f"p{k + 1}" for k in range(public)]
    n = len(labels)
    A = np.zeros((n, n))

    def w():
        return float(rng.uniform(0.2, 1.0))

    for c in range(N):
        members = [c * size + m for m in range(size)]
        for m, i in enumerate(members):
            A[i, i] = w()
            if size > 1:                       # a directed cycle inside the community
                A[i, members[(m + 1) % size]] = w()
    first = N * size
    for k in range(public):
        i = first + k
        A[i, i] = w()
        if public > 1:
            A[i, first + (k + 1) % public] = w()
    for c in range(N):                          # community c listens to one of the public
        A[c * size, first + c % public] = w()
    measure = [[labels[c * size]] for c in range(N)]
    return {
        "name": f"communities-{N}",
        "social": {"A": A.tolist(), "labels": labels, "spectral_radius": spectral_radius,
                   "process_noise": noise},
        "agents": {"measure": measure, "measurement_noise": noise, "standby": standby},
        "network": {"topology": "cycle", "self_weight": self_weight},
        "runtime": {"step_ms": step_ms},
    }
