"""socmon's systems and graphs in the field's libraries: python-control and networkx.

Both are optional (``pip install 'socmon[control]'``, ``'socmon[networkx]'``); they are
imported when a function here is called, and a missing one is an ImportError that says
what to install.

- :func:`closed_loop_ss`: the exact delayed error dynamics of a gain as a discrete-time
  ``control.StateSpace`` driven by unit-variance noise: its poles are the closed loop's
  eigenvalues (largest modulus: ``rho_exact``), and its squared H2 norm divided by ``nN``
  is the exact steady MSE (``mse_steady_exact``).
- :func:`influence_digraph`: the influence graph of A as an ``nx.DiGraph`` (edge j -> i
  when j influences i, ``A[i, j] != 0``). A **parent SCC** (socmon's term, the paper's) is
  a strongly connected component that no edge leaves: networkx's **attracting
  component** of this graph (``nx.attracting_components``).
- :func:`agent_digraph`: the agents' network, edge j -> i when agent i listens to agent j,
  with its weight and delay.

Examples
--------
>>> from design.scenario import load_scenario
>>> g = influence_digraph(load_scenario("paper-14"))
>>> import networkx as nx
>>> sorted(sorted(c, key=int) for c in nx.attracting_components(g))
[['12', '13', '14'], ['6', '7', '8'], ['9', '10', '11']]
"""

from __future__ import annotations

import numpy as np

from .closed_loop import ClosedLoop
from .gains import Gains, check_gains_fit

__all__ = ["closed_loop_ss", "influence_digraph", "agent_digraph"]


def _require(module: str, extra: str):
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise ImportError(f"{module} is not installed: pip install 'socmon[{extra}]' "
                          f"(or pip install {extra})") from None


def closed_loop_ss(scenario, G, delays=None, dt=True):
    """The error ``e = x - xhat`` of every agent as a discrete-time ``control.StateSpace``.

    Parameters
    ----------
    scenario : Scenario
    G : list of (n, p_i) arrays or Gains
        The agents' gains (``K^i H_i^T``), e.g. ``load_gains(path).G``.
    delays : (N, N) int array, optional
        The delay matrix (``delays[i, j]`` on link j -> i); default the scenario's.
    dt : True or float
        Sampling time of the system: True (unspecified, one step) or seconds, e.g.
        ``scenario.step_ms / 1000``.

    Returns
    -------
    control.StateSpace
        ``x_{k+1} = M x_k + B w_k``, ``y_k = e_k`` (nN outputs ``e[agent,label]``), ``w``
        white with unit variance: ``nu[label]`` (process noise of step k / sqrt(q), n
        inputs) then ``zeta[agent,label]`` (noise of the reading of step k+1 / sqrt(r), one
        per reading). Without
        delays the state is the stacked error; with delays it is augmented with the
        delay window (see :meth:`design.closed_loop.ClosedLoop.noise_state_space`).

    Examples
    --------
    >>> import numpy as np
    >>> from design.scenario import scenario_from_dict
    >>> s = scenario_from_dict({"social": {"A": [[1.1]], "process_noise": 0.04},
    ...                         "agents": {"measure": [["1"]], "measurement_noise": 0.09}})
    >>> sys = closed_loop_ss(s, [np.array([[0.5]])])      # e' = 0.55 e + 0.5 nu - 0.5 zeta
    >>> sys.A, sys.B, sys.C
    (array([[0.55]]), array([[ 0.1 , -0.15]]), array([[1.]]))
    """
    control = _require("control", "control")
    G = G.G if isinstance(G, Gains) else list(G)
    check_gains_fit(G, scenario)
    D = scenario.delays if delays is None else np.asarray(delays, dtype=int)
    loop = ClosedLoop(scenario.A, scenario.W, D, scenario.measure, G)
    M, B, C = loop.noise_state_space(scenario.process_noise, scenario.measurement_noise)
    labels = scenario.labels
    outputs = [f"e[{i + 1},{lab}]" for i in range(scenario.N) for lab in labels]
    inputs = [f"nu[{lab}]" for lab in labels] + [
        f"zeta[{i + 1},{lab}]" for i in range(scenario.N) for lab in scenario.agent_labels(i)]
    return control.ss(M, B, C, np.zeros((C.shape[0], B.shape[1])), dt,
                      inputs=inputs, outputs=outputs, name=f"{scenario.name} error")


def influence_digraph(scenario_or_A, labels=None):
    """The influence graph as an ``nx.DiGraph``: edge j -> i iff ``A[i, j] != 0``.

    Nodes are the scenario's labels (or ``labels``, or 0..n-1 for a bare matrix); each edge
    carries ``weight = A[i, j]``; self-loops are kept. Parent SCCs are its attracting
    components (``nx.attracting_components``).
    """
    nx = _require("networkx", "networkx")
    if hasattr(scenario_or_A, "A"):
        A = scenario_or_A.A
        labels = list(scenario_or_A.labels) if labels is None else list(labels)
    else:
        A = scenario_or_A
    A = A.tocoo() if hasattr(A, "tocoo") else np.asarray(A)
    n = A.shape[0]
    labels = list(range(n)) if labels is None else list(labels)
    if len(labels) != n:
        raise ValueError(f"labels: {len(labels)} labels for {n} nodes")
    g = nx.DiGraph()
    g.add_nodes_from(labels)
    if hasattr(A, "row"):
        rows, cols, vals = A.row, A.col, A.data
    else:
        rows, cols = np.nonzero(A)
        vals = A[rows, cols]
    g.add_weighted_edges_from(
        (labels[j], labels[i], float(v)) for i, j, v in zip(rows, cols, vals) if v != 0)
    return g


def agent_digraph(scenario, delays=None):
    """The agents' network as an ``nx.DiGraph`` on agents 1..N: edge j -> i iff agent i
    listens to agent j (``W[i-1, j-1] > 0``, i != j), with ``weight`` and ``delay`` (steps)."""
    nx = _require("networkx", "networkx")
    W = scenario.W
    D = scenario.delays if delays is None else np.asarray(delays, dtype=int)
    g = nx.DiGraph()
    g.add_nodes_from(range(1, scenario.N + 1))
    for i, j in zip(*np.nonzero(W > 0)):
        if i != j:
            g.add_edge(int(j) + 1, int(i) + 1, weight=float(W[i, j]), delay=int(D[i, j]))
    return g
