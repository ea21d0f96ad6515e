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
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from .graph import canonical_components

__all__ = [
    "Condensation",
    "ComponentList",
    "condensation",
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


class ComponentList(Sequence):
    """The vertex lists of the SCCs, stored as two arrays and built on access.

    Behaves like a list of sorted lists of ints (indexing, iteration, ``len``, ``==``
    with a list) without creating one Python list per SCC up front: on a sparse graph
    with millions of singleton SCCs that would dominate the linear-time computation.

    >>> ComponentList(np.array([0, 2, 1]), np.array([0, 2, 3]))
    [[0, 2], [1]]
    """

    def __init__(self, order: np.ndarray, bounds: np.ndarray):
        self.order, self.bounds = order, bounds

    def __len__(self) -> int:
        return int(self.bounds.size - 1)

    def __getitem__(self, c):
        if isinstance(c, slice):
            return [self[i] for i in range(*c.indices(len(self)))]
        c = range(len(self))[c]
        return self.order[self.bounds[c]: self.bounds[c + 1]].tolist()

    def sizes(self) -> np.ndarray:
        return np.diff(self.bounds)

    def __eq__(self, other):
        if isinstance(other, (ComponentList, list, tuple)):
            return len(self) == len(other) and all(a == list(b) for a, b in zip(self, other))
        return NotImplemented

    def __repr__(self) -> str:
        return repr(list(self))


@dataclass(frozen=True)
class Condensation:
    """SCCs of a digraph and the DAG between them.

    Attributes
    ----------
    labels : ndarray of int
        ``labels[v]`` = SCC of vertex v (SCCs numbered by their smallest vertex).
    components : ComponentList
        Vertices of each SCC, sorted (a list of lists, built on access).
    first : ndarray of int
        Smallest vertex of each SCC.
    dag : scipy.sparse.csr_matrix (k x k)
        ``dag[a, b] != 0`` iff some edge goes from SCC a to SCC b (a != b).
    """

    labels: np.ndarray
    components: ComponentList
    first: np.ndarray
    dag: sp.csr_matrix

    @property
    def k(self) -> int:
        return len(self.components)

    @property
    def out_degree(self) -> np.ndarray:
        return np.diff(self.dag.indptr)

    @property
    def in_degree(self) -> np.ndarray:
        return np.bincount(self.dag.indices, minlength=self.k)

    @property
    def sources(self) -> list:
        """SCCs with no entering edge (isolated ones included)."""
        return np.flatnonzero(self.in_degree == 0).tolist()

    @property
    def sinks(self) -> list:
        """SCCs with no leaving edge (isolated ones included)."""
        return np.flatnonzero(self.out_degree == 0).tolist()


def _as_csr(M) -> sp.csr_matrix:
    if sp.issparse(M):
        C = sp.coo_matrix(M)
    else:
        C = sp.coo_matrix(np.asarray(M))
    if C.shape[0] != C.shape[1]:
        raise ValueError(f"adjacency: must be square, got shape {C.shape}")
    keep = (C.data != 0) & (C.row != C.col)
    n = C.shape[0]
    return sp.csr_matrix(
        (np.ones(int(keep.sum()), dtype=np.int8), (C.row[keep], C.col[keep])), shape=(n, n)
    )


def condensation(M) -> Condensation:
    """Condensation of the digraph ``M`` (edge u -> v iff ``M[u, v] != 0``), linear time."""
    G = _as_csr(M)
    k, labels, first = canonical_components(G)
    src, dst = G.nonzero()
    a, b = labels[src], labels[dst]
    cross = a != b
    dag = sp.csr_matrix(
        (np.ones(int(cross.sum()), dtype=np.int8), (a[cross], b[cross])), shape=(k, k)
    )
    dag.sum_duplicates()
    dag.data[:] = 1
    by = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[by], np.arange(k + 1))
    return Condensation(labels=labels, components=ComponentList(by, bounds),
                        first=first, dag=dag)


def is_strongly_connected(M) -> bool:
    """True iff the digraph ``M`` has a single SCC (an empty graph is not)."""
    G = _as_csr(M)
    if G.shape[0] == 0:
        return False
    k, _ = connected_components(G, directed=True, connection="strong")
    return k == 1


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
