"""Strong connectivity of a directed graph: condensation and fewest-link augmentation.

The graph is given by a square adjacency (dense or scipy-sparse) ``M`` with an edge
``u -> v`` iff ``M[u, v] != 0`` (self-loops ignored). For the agent network pass the
*flow* graph of W: information goes from agent j to agent i iff ``W[i, j] > 0``, i.e.
``M = W.T`` (see :func:`agent_flow_graph`).

:func:`strong_connectivity_augmentation` returns a smallest set of new edges that makes
the graph strongly connected, by the construction of Eswaran and Tarjan, "Augmentation
problems", SIAM J. Comput. 5(4), 1976: with ``s`` sources, ``t`` sinks and ``q``
isolated vertices in the condensation (isolated ones counted apart), the minimum is
``max(s, t) + q`` unless the graph is already strongly connected (then 0).

Examples
--------
>>> import numpy as np
>>> M = np.array([[0, 1, 0], [0, 0, 1], [0, 0, 0]])     # path 0 -> 1 -> 2
>>> strong_connectivity_augmentation(M)
[(2, 0)]
>>> M = np.array([[0, 1, 1], [0, 0, 0], [0, 0, 0]])     # 0 -> 1, 0 -> 2: two sinks
>>> len(strong_connectivity_augmentation(M))
2
"""

from __future__ import annotations

from collections import deque

import numpy as np
import scipy.sparse as sp

from .graph import as_csr_digraph, canonical_components, condensation

__all__ = [
    "agent_components",
    "is_strongly_connected",
    "strong_connectivity_augmentation",
    "agent_flow_graph",
]


def agent_flow_graph(W) -> np.ndarray:
    """Adjacency of G_W along the flow of estimates: ``M[j, i] = 1`` iff ``W[i, j] > 0``."""
    W = np.asarray(W)
    M = (W.T > 0).astype(np.int8)
    np.fill_diagonal(M, 0)
    return M


def is_strongly_connected(M) -> bool:
    """True iff the digraph ``M`` has a single SCC (an empty graph is not)."""
    G = as_csr_digraph(M)
    if G.shape[0] == 0:
        return False
    return canonical_components(G)[0] == 1


def agent_components(W) -> list:
    """Strongly connected sets of agents of ``W`` (0-based, each sorted, by smallest agent).

    >>> agent_components(np.array([[0.5, 0.5, 0], [0.5, 0.5, 0], [0, 0.5, 0.5]]))
    [[0, 1], [2]]
    """
    return list(condensation(agent_flow_graph(W)).components)


def _reachable_sink(dag: sp.csr_matrix, start: int, is_free_sink: np.ndarray):
    """First vertex with ``is_free_sink`` reachable from ``start`` (BFS), or None."""
    seen = np.zeros(dag.shape[0], dtype=bool)
    seen[start] = True
    queue = deque([start])
    while queue:
        u = queue.popleft()
        if is_free_sink[u]:
            return u
        for v in dag.indices[dag.indptr[u]: dag.indptr[u + 1]]:
            if not seen[v]:
                seen[v] = True
                queue.append(v)
    return None


def strong_connectivity_augmentation(M) -> list:
    """A smallest list of new edges ``(u, v)`` that makes the digraph ``M`` strongly connected.

    Eswaran-Tarjan construction on the condensation. Let the non-isolated sources be
    ``v_1..v_s``, the non-isolated sinks ``w_1..w_t``, the isolated SCCs ``x_1..x_q``,
    and (reversing the graph if needed) ``s <= t``. Pair sources with sinks they reach
    into a *maximal* set of disjoint pairs ``(v_i, w_i)``, ``i <= p`` (no unpaired source
    reaches an unpaired sink), ordered so that the pairs come first. Then add

    * ``w_i -> v_{i+1}`` for ``i < p``, and ``w_i -> v_i`` for ``p < i <= s``;
    * the chain ``w_p -> w_{s+1} -> ... -> w_t -> x_1 -> ... -> x_q -> v_1``.

    The pairs and the chain form one cycle through every paired vertex and every
    extra sink and isolated SCC; an unpaired source reaches a paired sink (maximality)
    and an unpaired sink is reached from a paired source, so the edge ``w_i -> v_i``
    puts both on that cycle. Every other SCC lies on a path from a source to a sink, so
    the result is strongly connected with ``t + q = max(s, t) + q`` new edges, which is
    the lower bound (every source and sink needs a new entering/leaving edge).

    Each new edge joins the smallest vertex of its two SCCs. The pairing is found by one
    BFS per source: O(s (V + E)) on the condensation, ample for agent networks.

    Parameters
    ----------
    M : (n, n) array or sparse matrix
        ``M[u, v] != 0`` iff edge u -> v.

    Returns
    -------
    list of (int, int)
        Empty iff the graph is already strongly connected (or has one vertex).
    """
    C = condensation(M)
    k = C.k
    if k <= 1:
        return []
    dag = C.dag
    indeg, outdeg = C.in_degree, C.out_degree
    isolated = [c for c in range(k) if indeg[c] == 0 and outdeg[c] == 0]
    sources = [c for c in range(k) if indeg[c] == 0 and outdeg[c] > 0]
    sinks = [c for c in range(k) if outdeg[c] == 0 and indeg[c] > 0]
    reverse = len(sources) > len(sinks)
    if reverse:  # work on the reversed DAG; flip the edges at the end
        dag = dag.T.tocsr()
        sources, sinks = sinks, sources
    edges = []
    if not sources:  # the condensation has no edges: a cycle through the isolated SCCs
        chain = isolated
        edges = [(chain[i], chain[(i + 1) % len(chain)]) for i in range(len(chain))]
    else:
        free = np.zeros(k, dtype=bool)
        free[sinks] = True
        pairs = []
        unpaired_sources = []
        for v in sources:
            w = _reachable_sink(dag, v, free)
            if w is None:
                unpaired_sources.append(v)
            else:
                free[w] = False
                pairs.append((v, w))
        paired_sinks = {w for _, w in pairs}
        unpaired_sinks = [w for w in sinks if w not in paired_sinks]
        p = len(pairs)  # >= 1: a source reaches some sink, all of them free at first
        v_ord = [v for v, _ in pairs] + unpaired_sources
        w_ord = [w for _, w in pairs] + unpaired_sinks
        s, t = len(v_ord), len(w_ord)
        for i in range(p - 1):
            edges.append((w_ord[i], v_ord[i + 1]))
        for i in range(p, s):
            edges.append((w_ord[i], v_ord[i]))
        chain = [w_ord[p - 1]] + w_ord[s:t] + isolated + [v_ord[0]]
        edges += list(zip(chain[:-1], chain[1:]))
    if reverse:
        edges = [(b, a) for a, b in edges]
    rep = [comp[0] for comp in C.components]
    return [(int(rep[a]), int(rep[b])) for a, b in edges]
