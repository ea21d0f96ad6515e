"""Structural and numerical analysis of a scenario (what ``socmon analyze`` reports).

Two layers:

* :func:`structural_analysis` works on the influence graph alone (dense or scipy-sparse
  ``A``, never made dense) in time linear in nodes + edges: SCCs, condensation, parent
  and child SCCs, which parents lack a sensor, a minimal sensor set, nodes without a
  self-loop. It is what the paper's graph-theoretic results use.
* :func:`analyze` adds the numbers for one scenario: rank and spectral radius of A, the
  observability rank of (A, H) and of the distributed pair (W (x) A, D_H) by the
  orthogonal staircase, their unobservable modes and detectability, whether the
  structural and numerical verdicts agree (and why not), the agent network's strong
  connectivity and the failure tolerance of :mod:`design.recovery`.

Structural verdicts. (A, H) with canonical sensors is *structurally* observable iff every
parent SCC holds a measured node; the paper proves the numerical statement only under
Assumption 1 (A full rank, and self-loops ``a_ii != 0``: without them a node set can
"contract" and the generic rank drops). The paper's Lemma 3 (distributed observability
of (W (x) A, D_H)) additionally needs G_W strongly connected and self-damped
(``w_ii > 0``). When a premise fails the structural verdict can be wrong: the numerical
one is the truth, and ``reasons`` says which premise failed.

Examples
--------
>>> from design.scenario import load_scenario
>>> r = analyze(load_scenario("paper-14"))
>>> r.observability_rank, r.distributed_rank, r.distributed_detectable
(14, 33, True)
>>> [[r.labels[v] for v in c] for c in r.equivalence_classes]
[['6', '7', '8'], ['9', '10', '11'], ['12', '13', '14']]
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from .connectivity import agent_components
from .graph import InfluenceStructure, influence_structure
from .observability import distributed_detectability, pair_observability
from .recovery import DEFAULT_MAX_SUBSETS, failure_tolerance, redundancy_tolerance

__all__ = [
    "StructuralAnalysis",
    "structural_analysis",
    "Analysis",
    "analyze",
]


@dataclass(frozen=True, eq=False)
class StructuralAnalysis:
    """Graph-only facts about G_A and a sensor set (see :func:`structural_analysis`).

    Attributes
    ----------
    structure : InfluenceStructure
        SCC labels, components (sorted by smallest node) and parent SCC indices.
    n_edges : int
        Edges of G_A (self-loops excluded).
    condensation_edges : int
        Edges of the condensation DAG (between distinct SCCs, without duplicates).
    measured : list of int
        The measured nodes, sorted and unique.
    unmeasured_parents : list of int
        Parent SCCs (indices into ``structure.components``) without a measured node.
    minimal_sensor_set : list of int
        One node per parent SCC, preferring measured nodes: a smallest sensor set.
    missing_self_loops : ndarray of int
        Nodes with ``a_ii == 0`` (Assumption 1's self-loop premise fails there).
    """

    structure: InfluenceStructure
    n_edges: int
    condensation_edges: int
    measured: list
    unmeasured_parents: list
    minimal_sensor_set: list
    missing_self_loops: np.ndarray

    @property
    def n(self) -> int:
        return int(self.structure.labels.size)

    @property
    def n_sccs(self) -> int:
        return len(self.structure.components)

    @property
    def parents(self) -> list:
        return list(self.structure.parents)

    @property
    def children(self) -> list:
        flags = self.structure.is_parent
        return np.flatnonzero(~flags).tolist()

    @property
    def structurally_observable(self) -> bool:
        """Every parent SCC holds a measured node."""
        return not self.unmeasured_parents


def structural_analysis(A, measured=()) -> StructuralAnalysis:
    """SCCs, condensation, parents, minimal sensor set of G_A, in linear time.

    Parameters
    ----------
    A : (n, n) array or scipy.sparse matrix
        Edge j -> i iff ``A[i, j] != 0``. A sparse matrix is never made dense.
    measured : iterable of int
        Measured node indices (0-based).

    Examples
    --------
    >>> import scipy.sparse as sp
    >>> A = sp.csr_matrix(([1., 1, 1, 1], ([0, 1, 2, 2], [1, 0, 1, 2])), shape=(3, 3))
    >>> s = structural_analysis(A, measured=[0])     # node 2 listens to 1: {2} is the parent
    >>> s.structure.components, s.parents, s.unmeasured_parents, s.minimal_sensor_set
    ([[0, 1], [2]], [1], [1], [2])
    >>> s.missing_self_loops.tolist()
    [0, 1]
    """
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise ValueError(f"A: must be square, got shape {A.shape}")
    n = A.shape[0]
    measured = np.unique(np.asarray(list(measured), dtype=np.int64)).tolist()
    bad = [v for v in measured if not 0 <= v < n]
    if bad:
        raise ValueError(f"measured: node indices {bad[:5]} out of range 0..{n - 1}")
    structure = influence_structure(A)
    C = structure.condensation
    parents = structure.parents
    # vectorised (no Python loop over SCCs): a sensor per parent, the smallest measured
    # node of it if any, else its smallest node (the rule of graph.minimal_sensor_set)
    pick = C.first.copy()
    covered = np.zeros(C.k, dtype=bool)
    if measured:
        m = np.asarray(measured, dtype=np.int64)
        comp = C.labels[m]
        covered[comp] = True
        first_idx = np.unique(comp, return_index=True)
        pick[first_idx[0]] = m[first_idx[1]]
    par = np.asarray(parents, dtype=np.int64)
    unmeasured = par[~covered[par]].tolist()
    diag = A.diagonal() if sp.issparse(A) else np.diagonal(np.asarray(A))
    return StructuralAnalysis(
        structure=structure,
        n_edges=int(C.n_edges),
        condensation_edges=int(C.dag.nnz),
        measured=measured,
        unmeasured_parents=unmeasured,
        minimal_sensor_set=np.sort(pick[par]).tolist(),
        missing_self_loops=np.flatnonzero(np.asarray(diag) == 0),
    )


@dataclass(frozen=True, eq=False)
class Analysis:
    """Everything ``socmon analyze`` reports about one scenario (0-based inside).

    Use :meth:`to_dict` for the JSON form (labels for nodes, ids 1..N for agents).
    """

    scenario: object
    structural: StructuralAnalysis
    rank_A: int
    rho_A: float
    observability_rank: int
    unobservable_modes: np.ndarray
    distributed_rank: int
    distributed_unobservable_modes: np.ndarray
    network_components: list
    failure_tolerance: object
    failure_tolerance_with_links: object
    redundancy_tolerance: object = None
    tolerance: dict = field(default_factory=dict)

    # -- convenience ------------------------------------------------------------------
    @property
    def labels(self):
        return self.scenario.labels

    @property
    def n(self) -> int:
        return self.scenario.n

    @property
    def full_rank(self) -> bool:
        return self.rank_A == self.n

    @property
    def equivalence_classes(self) -> list:
        """Parent SCCs (node indices): nodes in one are observationally equivalent."""
        s = self.structural.structure
        return [s.components[c] for c in s.parents]

    @property
    def observable(self) -> bool:
        return self.observability_rank == self.n

    @property
    def detectable(self) -> bool:
        return bool(np.all(np.abs(self.unobservable_modes) < 1.0))

    @property
    def distributed_order(self) -> int:
        return self.n * self.scenario.N

    @property
    def distributed_observable(self) -> bool:
        return self.distributed_rank == self.distributed_order

    @property
    def distributed_detectable(self) -> bool:
        return bool(np.all(np.abs(self.distributed_unobservable_modes) < 1.0))

    @property
    def network_strongly_connected(self) -> bool:
        return len(self.network_components) == 1

    @property
    def structurally_observable(self) -> bool:
        return self.structural.structurally_observable

    @property
    def distributed_structurally_observable(self) -> bool:
        """Lemma 3's verdict: (A, H) structurally observable, G_W strongly connected, w_ii > 0."""
        W = self.scenario.W
        return (
            self.structurally_observable
            and self.network_strongly_connected
            and bool(np.all(np.diag(W) > 0))
        )

    @property
    def verdicts_agree(self) -> bool:
        return self.structurally_observable == self.observable

    @property
    def distributed_verdicts_agree(self) -> bool:
        return self.distributed_structurally_observable == self.distributed_observable

    def reasons(self) -> list:
        """Why a structural verdict differs from the numerical one (empty if they agree)."""
        out = []
        lab = self.labels
        missing = [lab[v] for v in self.structural.missing_self_loops]
        premise = []
        if not self.full_rank:
            premise.append(f"A has rank {self.rank_A} < n = {self.n} (Assumption 1)")
        if missing:
            premise.append(
                f"nodes without self-loop (a_ii = 0): {_label_ranges(missing)} "
                "(Assumption 1 / Lemma 3 premise)"
            )
        rank_W = int(np.linalg.matrix_rank(self.scenario.W))
        dist_premise = list(premise)
        if rank_W < self.scenario.N:
            dist_premise.append(
                f"W has rank {rank_W} < N = {self.scenario.N}, so W (x) A has eigenvalue 0 "
                f"with multiplicity >= {(self.scenario.N - rank_W) * self.n}, mostly unseen by "
                "D_H (Kronecker premise of Lemma 3; such modes at 0 do not harm detectability)"
            )
        for name, s_ok, n_ok, rank, order, why_list in (
            ("(A, H)", self.structurally_observable, self.observable,
             self.observability_rank, self.n, premise),
            ("(W (x) A, D_H)", self.distributed_structurally_observable,
             self.distributed_observable, self.distributed_rank, self.distributed_order,
             dist_premise),
        ):
            if s_ok == n_ok:
                continue
            if s_ok:
                why = "; ".join(why_list) if why_list else (
                    "non-generic weights: the entries of A cancel numerically"
                )
                out.append(
                    f"{name}: structurally observable but numerical rank {rank} of {order}: "
                    f"{why}"
                )
            else:
                out.append(
                    f"{name}: numerically observable although the structural test fails "
                    "(the structural test is only sufficient here)"
                )
        return out

    # -- JSON -------------------------------------------------------------------------
    def to_dict(self) -> dict:
        s = self.scenario
        lab = self.labels
        st = self.structural.structure
        parents = set(st.parents)
        ft, ftl = self.failure_tolerance, self.failure_tolerance_with_links
        return {
            "scenario": s.name,
            "n": s.n,
            "N": s.N,
            "standby": s.standby,
            "labels": list(lab),
            "rho_A": self.rho_A,
            "rank_A": self.rank_A,
            "full_rank": self.full_rank,
            "sccs": [
                {"nodes": [lab[v] for v in comp], "parent": c in parents}
                for c, comp in enumerate(st.components)
            ],
            "equivalence_classes": [[lab[v] for v in c] for c in self.equivalence_classes],
            "minimal_sensor_set": [lab[v] for v in self.structural.minimal_sensor_set],
            "measured_nodes": [lab[v] for v in self.structural.measured],
            "unmeasured_parent_sccs": [
                [lab[v] for v in st.components[c]] for c in self.structural.unmeasured_parents
            ],
            "missing_self_loops": [lab[v] for v in self.structural.missing_self_loops],
            "structurally_observable": self.structurally_observable,
            "observable": self.observable,
            "observability_rank": self.observability_rank,
            "unobservable_modes": _modes(self.unobservable_modes),
            "detectable": self.detectable,
            "distributed_structurally_observable": self.distributed_structurally_observable,
            "distributed_observable": self.distributed_observable,
            "distributed_rank": self.distributed_rank,
            "distributed_order": self.distributed_order,
            "distributed_unobservable_modes": _modes(self.distributed_unobservable_modes),
            "distributed_detectable": self.distributed_detectable,
            "verdicts_agree": self.verdicts_agree,
            "distributed_verdicts_agree": self.distributed_verdicts_agree,
            "disagreement_reasons": self.reasons(),
            "network_strongly_connected": self.network_strongly_connected,
            "network_components": [[a + 1 for a in c] for c in self.network_components],
            "failure_tolerance": ft.p,
            "failure_tolerance_exact": ft.exact,
            "failure_tolerance_witness": (
                [a + 1 for a in ft.witness] if ft.witness is not None else None
            ),
            "failure_tolerance_with_new_links": ftl.p,
            "failure_tolerance_with_new_links_exact": ftl.exact,
            "failure_tolerance_with_new_links_witness": (
                [a + 1 for a in ftl.witness] if ftl.witness is not None else None
            ),
            "failure_tolerance_without_replacement": (
                self.redundancy_tolerance.p if self.redundancy_tolerance else None
            ),
            "A": s.A,
            "W": s.W,
            "delays": s.delays,
            "measure": [s.agent_labels(i) for i in range(s.N)],
            "warnings": list(s.warnings),
        }


def analyze(scenario, tol=None, max_subsets=None) -> Analysis:
    """Structural and numerical analysis of ``scenario`` (see the module docstring).

    Parameters
    ----------
    scenario : Scenario
    tol : float, optional
        Rank tolerance of the staircase (default :func:`default_tolerance` per pair).
    max_subsets : int, optional
        Bound on the failure sets :func:`design.recovery.failure_tolerance` examines.
    """
    s = scenario
    A, H = s.A, s.H_all
    structural = structural_analysis(A, [v for m in s.measure for v in m])
    rank_A = int(np.linalg.matrix_rank(A))
    central = pair_observability(A, H, tol)
    distributed = distributed_detectability(A, s.W, s.measure, tol)
    kw = {} if max_subsets is None else {"max_subsets": max_subsets}
    limit = DEFAULT_MAX_SUBSETS if max_subsets is None else max_subsets
    return Analysis(
        scenario=s,
        structural=structural,
        rank_A=rank_A,
        rho_A=s.rho_A,
        observability_rank=central.rank,
        unobservable_modes=central.unobservable_modes,
        distributed_rank=distributed.rank,
        distributed_unobservable_modes=distributed.unobservable_modes,
        network_components=agent_components(s.W),
        failure_tolerance=failure_tolerance(s, allow_new_links=False, **kw),
        failure_tolerance_with_links=failure_tolerance(s, allow_new_links=True, **kw),
        redundancy_tolerance=redundancy_tolerance(s, **kw),
        tolerance={"max_subsets": limit},
    )


def _modes(vals) -> list:
    return [
        {"re": float(np.real(v)), "im": float(np.imag(v)), "abs": float(abs(v))}
        for v in np.atleast_1d(vals)
    ]


def _label_ranges(labels) -> str:
    """Compact list of labels: consecutive integer labels as ``a..b``."""
    if not labels or not all(str(x).isdigit() for x in labels):
        return ", ".join(map(str, labels))
    nums = [int(x) for x in labels]
    parts, start, prev = [], nums[0], nums[0]
    for x in nums[1:] + [None]:
        if x is not None and x == prev + 1:
            prev = x
            continue
        parts.append(f"{start}..{prev}" if prev > start else f"{start}")
        if x is not None:
            start = prev = x
    return ", ".join(parts)
