"""Structure of the influence graph: SCCs, parent SCCs, equivalence classes, sensors.

Convention: an edge j -> i (j != i) exists iff ``A[i, j] != 0`` ("j influences i"). A
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

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

__all__ = [
    "InfluenceStructure",
    "influence_graph",
    "influence_structure",
    "canonical_components",
    "is_structurally_observable",
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


@dataclass(frozen=True)
class InfluenceStructure:
    """SCC decomposition of G_A and its condensation.

    Attributes
    ----------
    labels : ndarray of int
        ``labels[v]`` = index of the SCC holding node v.
    components : list of list of int
        Nodes of each SCC, sorted; SCCs ordered by their smallest node.
    parents : list of int
        Indices (into ``components``) of parent SCCs: no edge leaves them.
    """

    labels: np.ndarray
    components: list
    parents: list

    @property
    def is_parent(self) -> np.ndarray:
        flags = np.zeros(len(self.components), dtype=bool)
        flags[self.parents] = True
        return flags

    def parent_of_node(self, v: int):
        """Index of the parent SCC holding node v, or None if v is in a child SCC."""
        c = int(self.labels[v])
        return c if self.is_parent[c] else None


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


def influence_structure(A) -> InfluenceStructure:
    """SCCs of G_A, ordered by smallest node, and which of them are parents."""
    G = influence_graph(A)
    k, labels, _ = canonical_components(G)
    # a component with an edge to another component is a child
    src, dst = G.nonzero()
    leaving = labels[src] != labels[dst]
    has_out = np.zeros(k, dtype=bool)
    has_out[labels[src[leaving]]] = True
    sort_nodes = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[sort_nodes], np.arange(k + 1))
    components = [sort_nodes[bounds[c] : bounds[c + 1]].tolist() for c in range(k)]
    parents = np.flatnonzero(~has_out).tolist()
    return InfluenceStructure(labels=labels, components=components, parents=parents)


def unmeasured_parents(structure: InfluenceStructure, measured) -> list:
    """Parent SCC indices that hold none of the ``measured`` nodes."""
    covered = {int(structure.labels[v]) for v in measured}
    return [c for c in structure.parents if c not in covered]


def is_structurally_observable(structure: InfluenceStructure, measured) -> bool:
    """True iff every parent SCC holds a measured node (canonical sensors, Assumption 1)."""
    return not unmeasured_parents(structure, measured)


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
