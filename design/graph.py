"""SCCs and condensation of a digraph; the influence graph's parents, classes, sensors.

One path computes strongly connected components here: :func:`canonical_components`
(SCCs numbered by their smallest vertex), :func:`condensation` on top of it (the DAG
between SCCs) and :func:`influence_structure` on top of that (the condensation of G_A and
its sinks, the parent SCCs). The agent network (:mod:`design.connectivity`), the scenario
checks, the analysis and the recovery plan all use these.

Convention for G_A: an edge j -> i (j != i) exists iff ``A[i, j] != 0`` ("j influences i"). A
measurement of node i tells about every node with a directed path to i, so a *parent
SCC* (a sink of the condensation: no edge leaves it) must hold a measured node.

Everything here runs in time linear in nodes + edges (scipy's iterative Tarjan/Pearce
SCC algorithm and numpy on the edge arrays), so graphs with millions of edges are fine.

Examples
--------
>>> import numpy as np
>>> A = np.array([[1., 1, 0], [1, 1, 0], [0, 1, 1]])   # 2 -> 3, {1, 2} strongly connected
>>> s = influence_structure(A)
>>> s.components, s.parents
([[0, 1], [2]], [1])
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

__all__ = [
    "as_csr_digraph",
    "ComponentList",
    "Condensation",
    "condensation",
    "InfluenceStructure",
    "influence_graph",
    "influence_structure",
    "canonical_components",
    "unmeasured_parents",
    "minimal_sensor_set",
]


def influence_graph(A) -> sp.csr_matrix:
    """Adjacency of G_A as a sparse matrix ``G[j, i] = 1`` iff j -> i (``A[i, j] != 0``).

    ``A`` may be dense or scipy-sparse; self-loops are dropped.
    """
    if sp.issparse(A):
        M = sp.coo_matrix(A)
        keep = (M.data != 0) & (M.row != M.col)
        rows, cols = M.row[keep], M.col[keep]
        n = M.shape[0]
    else:
        A = np.asarray(A)
        n = A.shape[0]
        rows, cols = np.nonzero(A)
        keep = rows != cols
        rows, cols = rows[keep], cols[keep]
    # edge cols -> rows
    return sp.csr_matrix((np.ones(rows.size, dtype=np.int8), (cols, rows)), shape=(n, n))


def canonical_components(G):
    """Strongly connected components of the digraph ``G``, numbered by smallest node.

    Returns ``(k, labels, first)``: the number of SCCs, ``labels[v]`` = SCC of node v, and
    ``first[c]`` = smallest node of SCC c (increasing in c). Linear time.
    """
    n = G.shape[0]
    k, raw = connected_components(G, directed=True, connection="strong")
    first = np.full(k, n, dtype=np.int64)
    np.minimum.at(first, raw, np.arange(n))
    order = np.argsort(first, kind="stable")
    rank = np.empty(k, dtype=np.int64)
    rank[order] = np.arange(k)
    return k, rank[raw], first[order]


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
    n_edges : int
        Edges of the digraph itself (self-loops excluded).
    """

    labels: np.ndarray
    components: ComponentList
    first: np.ndarray
    dag: sp.csr_matrix
    n_edges: int = 0

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


def as_csr_digraph(M) -> sp.csr_matrix:
    """``M`` (dense or sparse, square) as a 0/1 CSR adjacency without self-loops."""
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
    G = as_csr_digraph(M)
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
                        first=first, dag=dag, n_edges=int(G.nnz))


@dataclass(frozen=True)
class InfluenceStructure:
    """SCC decomposition of G_A and its condensation.

    Attributes
    ----------
    labels : ndarray of int
        ``labels[v]`` = index of the SCC holding node v.
    components : ComponentList
        Nodes of each SCC, sorted; SCCs ordered by their smallest node (a list of
        lists, built on access).
    parents : list of int
        Indices (into ``components``) of parent SCCs: no edge leaves them.
    condensation : Condensation
        The condensation of G_A these are read from (``parents`` are its sinks).
    """

    labels: np.ndarray
    components: ComponentList
    parents: list
    condensation: Condensation

    @property
    def is_parent(self) -> np.ndarray:
        flags = np.zeros(len(self.components), dtype=bool)
        flags[self.parents] = True
        return flags

    def parent_of_node(self, v: int):
        """Index of the parent SCC holding node v, or None if v is in a child SCC."""
        c = int(self.labels[v])
        return c if self.is_parent[c] else None


def influence_structure(A) -> InfluenceStructure:
    """SCCs of G_A, ordered by smallest node, and which of them are parents (sinks)."""
    C = condensation(influence_graph(A))  # G[j, i] = 1 iff j -> i: edges along influence
    return InfluenceStructure(labels=C.labels, components=C.components, parents=C.sinks,
                              condensation=C)


def unmeasured_parents(structure: InfluenceStructure, measured) -> list:
    """Parent SCC indices that hold none of the ``measured`` nodes."""
    covered = {int(structure.labels[v]) for v in measured}
    return [c for c in structure.parents if c not in covered]


def minimal_sensor_set(structure: InfluenceStructure, prefer=()) -> list:
    """One node per parent SCC: a smallest set of canonical sensors for observability.

    Nodes in ``prefer`` (e.g. the ones already measured) are taken first; otherwise the
    smallest node of each parent SCC.
    """
    first_preferred = {}
    for v in prefer:  # one pass: linear in len(prefer) + number of parents
        first_preferred.setdefault(int(structure.labels[v]), int(v))
    chosen = [first_preferred.get(c, structure.components[c][0]) for c in structure.parents]
    return sorted(int(v) for v in chosen)
