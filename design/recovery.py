"""Recovery from agent failures (the paper's Theorem 2 and Remarks 5-6).

Nodes of one parent SCC of G_A are observationally equivalent: measuring any of them
keeps (A, H) (structurally) observable. When agents fail, :func:`plan_recovery` builds a
new configuration by the policy below and reports every step; the result carries a new
:class:`~design.scenario.Scenario` for which gains can be designed and certified.

Policy (deterministic)
----------------------
1. **Lost measurements.** A failed agent's measurement of node v is lost. If v lies in a
   parent SCC, its *candidates* are the other nodes of that SCC; a node of a child SCC
   has no equivalent (and is not needed for observability): it is reported and dropped.
   A parent SCC of a single node has no candidate: that measurement cannot be recovered.
2. **Replacement node.** Among the candidates, prefer a node no agent of the new
   configuration measures yet, then the one nearest to v along the influence edges
   (breadth-first distance from v inside the SCC: the node that hears v's state first),
   then the smallest index. On paper-14 this picks 8 for 7 and 10 for 9, as the paper.
3. **Who measures it.** Standby agents (ids N+1..N+standby) are used first, one per
   failed agent, in increasing order of the failed ids, for failed agents that lost at
   least one parent-SCC measurement. A standby **takes the failed agent's place in W**:
   its row and column (in- and out-links, weights and delays). When no standby is left,
   the node is added to the active agent (survivor or joined standby) that measures the
   fewest nodes at that moment, ties to the lowest id.
4. **Network.** The failed agents without a standby are removed from W and every row is
   renormalised over its remaining neighbours (self weight included). If the agent graph
   is no longer strongly connected, the fewest links that restore it are added
   (Eswaran-Tarjan, :func:`design.connectivity.strong_connectivity_augmentation`). A
   row that receives new links keeps the self weight it had in the scenario and splits
   the rest equally among all its neighbours (old and new). A new link is given the
   largest delay of the scenario (conservative: as slow as the slowest existing link).

"Recoverable" (used by :func:`failure_tolerance`): after the policy, at least one agent
is active, every parent SCC of G_A holds a node measured by an active agent, and the
agent graph is strongly connected, either as it is (``allow_new_links=False``: the
paper's Remark 5, links inherited by standbys included) or after adding links
(``allow_new_links=True``: then only the first two conditions matter). It is a
structural notion (Assumption 1); :func:`plan_recovery` also checks the new
configuration numerically.

Examples
--------
>>> from design.scenario import load_scenario
>>> s = load_scenario("paper-14")
>>> plan = plan_recovery(s, [0, 1])                 # agents 1 and 2 fail
>>> {a + 1: [s.labels[v] for v in c] for a, c in plan.candidates.items()}
{1: ['6', '8'], 2: ['10', '11']}
>>> [(r.failed + 1, s.labels[r.node_from], s.labels[r.node_to], r.by) for r in plan.replacements]
[(1, '7', '8', 4), (2, '9', '10', 3)]
>>> plan.added_links, plan.structurally_observable_after
([(3, 4)], True)
"""

from __future__ import annotations

import itertools
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from .connectivity import (
    agent_flow_graph,
    is_strongly_connected,
    strong_connectivity_augmentation,
)
from .errors import SocmonError
from .graph import condensation, influence_graph, influence_structure
from .observability import distributed_detectability, pair_observability

__all__ = [
    "RecoveryError",
    "Replacement",
    "RecoveryPlan",
    "plan_recovery",
    "is_recoverable",
    "FailureTolerance",
    "failure_tolerance",
    "redundancy_tolerance",
    "DEFAULT_MAX_SUBSETS",
]

#: Default bound on the failure sets :func:`failure_tolerance` examines.
DEFAULT_MAX_SUBSETS = 20_000


class RecoveryError(SocmonError):
    """Bad failure list (unknown or repeated agent)."""


@dataclass(frozen=True)
class Replacement:
    """Node ``node_from`` lost by failed agent ``failed`` is replaced by ``node_to``,
    measured by agent ``by``.

    ``failed`` is a 0-based row of the scenario's W; ``by`` is a 1-based agent id
    (standby ids are N+1..); nodes are 0-based indices. See :class:`RecoveryPlan`.
    """

    failed: int
    node_from: int
    node_to: int
    by: int
    by_standby: bool


@dataclass(frozen=True, eq=False)
class RecoveryPlan:
    """Outcome of :func:`plan_recovery`.

    Agent numbering, once for all fields: an agent of the *scenario* is named by its
    0-based row of the scenario's W (``failed``, the keys of the per-failed-agent dicts,
    ``Replacement.failed``); an agent of the *new configuration* is named by its 1-based
    id (``agent_ids``, ``Replacement.by``, ``added_links``, ``components_removed``),
    because the new rows mix survivors (id = old row + 1) and standbys (ids N+1..); the
    rows of ``W_removed``, ``W_after``, ``delays_after`` and ``measure_after`` are in the
    order of ``agent_ids``. Nodes are 0-based indices everywhere. :meth:`to_dict` gives
    the JSON form with every agent as a 1-based id and every node as its label.

    Attributes
    ----------
    failed : tuple of int
        Failed agents, 0-based rows of the scenario's W, sorted.
    candidates : dict
        failed agent -> equivalent nodes (union over the parent-SCC nodes it measured).
    candidates_by_node : dict
        failed agent -> {lost node: [equivalent nodes]}.
    no_equivalent : dict
        failed agent -> lost nodes of child SCCs (no equivalent; dropped).
    unrecoverable : dict
        failed agent -> lost nodes of single-node parent SCCs (no candidate).
    unassigned : dict
        failed agent -> lost nodes that have candidates but no agent is left to take them.
    replacements : list of Replacement
    agent_ids : list of int
        1-based id of the agent in each row of the new W (survivors keep their id, a
        standby has id N+k and sits in the row of the agent it replaces).
    W_removed : ndarray
        W with failed agents removed (standbys in place) and rows renormalised.
    components_removed : list of list of int
        SCCs (agent ids) of that network.
    added_links : list of (int, int)
        New links ``(from_id, to_id)``: agent ``to_id`` listens to ``from_id``.
    W_after, delays_after : ndarray
    measure_after : tuple of tuple of int
    scenario_after : Scenario or None
        None when no agent is left or the network stays disconnected.
    """

    failed: tuple
    candidates: dict
    candidates_by_node: dict
    no_equivalent: dict
    unrecoverable: dict
    unassigned: dict
    replacements: list
    agent_ids: list
    W_removed: np.ndarray
    components_removed: list
    added_links: list
    W_after: np.ndarray
    delays_after: np.ndarray
    measure_after: tuple
    unmeasured_parents_after: list
    scenario_after: object = None
    numerical: dict = field(default_factory=dict)

    @property
    def network_strongly_connected_removed(self) -> bool:
        return len(self.components_removed) == 1

    @property
    def network_strongly_connected_after(self) -> bool:
        k = len(self.agent_ids)
        if k <= 1:
            return k == 1
        return is_strongly_connected(agent_flow_graph(self.W_after))

    @property
    def structurally_observable_after(self) -> bool:
        return bool(self.agent_ids) and not self.unmeasured_parents_after

    def is_recoverable(self, allow_new_links: bool = True) -> bool:
        """The module's definition of "recoverable" for this plan."""
        if not self.agent_ids or not self.structurally_observable_after:
            return False
        # with new links allowed, strong connectivity can always be restored
        return True if allow_new_links else self.network_strongly_connected_removed

    def to_dict(self, scenario) -> dict:
        """JSON form: agents by 1-based id, nodes by label."""
        lab = scenario.labels
        reps: dict = {}
        for r in self.replacements:
            entry = {"from": lab[r.node_from], "to": lab[r.node_to], "by": r.by,
                     "by_standby": r.by_standby}
            key = str(r.failed + 1)
            if key in reps:
                reps[key].setdefault("also", []).append(entry)
            else:
                reps[key] = dict(entry)
        out = {
            "failed": [a + 1 for a in self.failed],
            "candidates": {str(a + 1): [lab[v] for v in c] for a, c in self.candidates.items()},
            "candidates_by_node": {
                str(a + 1): {lab[v]: [lab[u] for u in c] for v, c in d.items()}
                for a, d in self.candidates_by_node.items()
            },
            "no_equivalent": {
                str(a + 1): [lab[v] for v in c] for a, c in self.no_equivalent.items() if c
            },
            "unrecoverable_nodes": {
                str(a + 1): [lab[v] for v in c] for a, c in self.unrecoverable.items() if c
            },
            "unassigned_nodes": {
                str(a + 1): [lab[v] for v in c] for a, c in self.unassigned.items() if c
            },
            "replacements": reps,
            "agents_after": list(self.agent_ids),
            "W_removed": self.W_removed,
            "network_strongly_connected_removed": self.network_strongly_connected_removed,
            "network_components_removed": self.components_removed,
            "added_links": [{"from": u, "to": v} for u, v in self.added_links],
            "network_strongly_connected_after": self.network_strongly_connected_after,
            "W_after": self.W_after,
            "delays_after": self.delays_after,
            "measure_after": [[lab[v] for v in m] for m in self.measure_after],
            "structurally_observable_after": self.structurally_observable_after,
            "unmeasured_parent_sccs_after": [
                [lab[v] for v in comp] for comp in self.unmeasured_parents_after
            ],
            "recoverable_without_new_links": self.is_recoverable(False),
            "recoverable": self.is_recoverable(True),
        }
        out.update(self.numerical)
        return out


def _check_failed(scenario, failed) -> tuple:
    out = []
    for a in failed:
        if isinstance(a, bool) or not isinstance(a, (int, np.integer)):
            raise RecoveryError(f"failed: agent indices are integers, got {a!r}")
        if not 0 <= a < scenario.N:
            raise RecoveryError(f"failed: no agent {int(a) + 1} (agents are 1..{scenario.N})")
        if a in out:
            raise RecoveryError(f"failed: agent {int(a) + 1} listed twice")
        out.append(int(a))
    return tuple(sorted(out))


def _bfs_distances(G_csr, start: int, allowed: set) -> dict:
    """Distances from ``start`` along edges of ``G_csr`` (row -> columns), inside ``allowed``."""
    dist = {start: 0}
    queue = deque([start])
    while queue:
        u = queue.popleft()
        for v in G_csr.indices[G_csr.indptr[u]: G_csr.indptr[u + 1]]:
            v = int(v)
            if v in allowed and v not in dist:
                dist[v] = dist[u] + 1
                queue.append(v)
    return dist


class _Context:
    """Per-scenario data reused across many failure sets (failure_tolerance)."""

    def __init__(self, scenario):
        self.scenario = scenario
        self.structure = influence_structure(scenario.A)
        self.G = influence_graph(scenario.A)  # G[j, i] = 1 iff j -> i
        self.is_parent = self.structure.is_parent
        self._cand: dict = {}

    def candidates(self, v: int) -> list:
        """Other nodes of v's parent SCC, in the policy's order of distance (not of use)."""
        if v not in self._cand:
            c = int(self.structure.labels[v])
            members = self.structure.components[c]
            dist = _bfs_distances(self.G, v, set(members))
            others = [u for u in members if u != v]
            self._cand[v] = sorted(others, key=lambda u: (dist.get(u, len(members)), u))
        return self._cand[v]


def _plan(ctx: _Context, failed: tuple, add_links: bool) -> RecoveryPlan:
    s = ctx.scenario
    N = s.N
    failed_set = set(failed)
    # 1. standbys for failed agents that lost a parent-SCC measurement
    standby_ids = list(range(N + 1, N + 1 + s.standby))
    slot_id = {i: i + 1 for i in range(N) if i not in failed_set}
    for f in failed:
        needs = any(ctx.is_parent[ctx.structure.labels[v]] for v in s.measure[f])
        if needs and standby_ids:
            slot_id[f] = standby_ids.pop(0)
    measure = {i: list(s.measure[i]) if i not in failed_set else [] for i in slot_id}
    measured = {v for m in measure.values() for v in m}
    # 2.-3. replacements
    candidates, by_node, no_eq, unrec, unassigned, reps = {}, {}, {}, {}, {}, []
    for f in failed:
        candidates[f], by_node[f], no_eq[f], unrec[f], unassigned[f] = [], {}, [], [], []
        for v in s.measure[f]:
            if not ctx.is_parent[ctx.structure.labels[v]]:
                no_eq[f].append(v)
                continue
            cands = ctx.candidates(v)
            by_node[f][v] = sorted(cands)
            candidates[f].extend(u for u in sorted(cands) if u not in candidates[f])
            if not cands:
                unrec[f].append(v)
                continue
            if not slot_id:
                unassigned[f].append(v)
                continue
            fresh = [u for u in cands if u not in measured]
            to = (fresh or cands)[0]
            if f in slot_id:
                slot = f
            else:
                slot = min(slot_id, key=lambda i: (len(measure[i]), slot_id[i]))
            if to not in measure[slot]:
                measure[slot].append(to)
            measured.add(to)
            reps.append(Replacement(f, v, to, slot_id[slot], slot_id[slot] > N))
    # a standby whose every lost node was unrecoverable does not join
    for i in [i for i in slot_id if not measure[i]]:
        del slot_id[i]
    slots = sorted(slot_id)
    ids = [slot_id[i] for i in slots]
    # 4. network: remove, renormalise, augment
    W0 = s.W[np.ix_(slots, slots)].astype(float)
    D0 = s.delays[np.ix_(slots, slots)].astype(int)
    if slots:
        W0 = W0 / W0.sum(axis=1, keepdims=True)
    flow = agent_flow_graph(W0)
    comps = condensation(flow).components if slots else []
    components_removed = [[ids[a] for a in c] for c in comps]
    W1, D1, added = W0.copy(), D0.copy(), []
    if add_links and len(comps) > 1:
        new = strong_connectivity_augmentation(flow)
        tau_new = s.taubar
        rows = {}
        for u, v in new:  # flow u -> v: agent v listens to agent u
            rows.setdefault(v, []).append(u)
            added.append((ids[u], ids[v]))
        for v, us in rows.items():
            self_w = s.W[slots[v], slots[v]]
            nbrs = sorted({j for j in range(len(slots)) if j != v and W1[v, j] > 0} | set(us))
            W1[v, :] = 0.0
            W1[v, v] = self_w
            W1[v, nbrs] = (1.0 - self_w) / len(nbrs)
            for u in us:
                D1[v, u] = tau_new
    measure_after = tuple(tuple(measure[i]) for i in slots)
    covered = {int(ctx.structure.labels[v]) for m in measure_after for v in m}
    unmeasured = [ctx.structure.components[c] for c in ctx.structure.parents if c not in covered]
    return RecoveryPlan(
        failed=failed,
        candidates=candidates,
        candidates_by_node=by_node,
        no_equivalent=no_eq,
        unrecoverable=unrec,
        unassigned=unassigned,
        replacements=reps,
        agent_ids=ids,
        W_removed=W0,
        components_removed=components_removed,
        added_links=added,
        W_after=W1,
        delays_after=D1,
        measure_after=measure_after,
        unmeasured_parents_after=unmeasured,
    )


def plan_recovery(scenario, failed, add_links: bool = True, numerical: bool = True) -> RecoveryPlan:
    """Recovery plan for the failure of ``failed`` agents (0-based) by the module's policy.

    Parameters
    ----------
    scenario : Scenario
    failed : iterable of int
        Failed agents, 0-based (CLI ids minus one).
    add_links : bool
        Add the fewest links restoring strong connectivity when needed (default True).
    numerical : bool
        Also check (A, H') and (W' (x) A, D_H') numerically: ranks, unobservable modes,
        detectability (``plan.numerical``; empty without). The new Scenario
        (``plan.scenario_after``) is built either way. The distributed check is a
        staircase of order nN: 1.2-2.8 s at communities-32, where the structural plan takes
        milliseconds.

    Raises
    ------
    RecoveryError
        Unknown or repeated agent.
    """
    failed = _check_failed(scenario, failed)
    plan = _plan(_Context(scenario), failed, add_links)
    num, new = {}, None
    if plan.agent_ids and plan.network_strongly_connected_after:
        new = scenario.replace(
            name=f"{scenario.name}-recovered",
            W=plan.W_after,
            delays=plan.delays_after,
            measure=plan.measure_after,
            standby=scenario.standby - sum(1 for a in plan.agent_ids if a > scenario.N),
        )
    if not numerical:
        return RecoveryPlan(**{**plan.__dict__, "scenario_after": new})
    if new is not None:
        central = pair_observability(new.A, new.H_all)
        distributed = distributed_detectability(new.A, new.W, new.measure)
        num = {
            "observability_rank_after": central.rank,
            "observable_after": central.observable,
            "detectable_after": central.detectable,
            "distributed_rank_after": distributed.rank,
            "distributed_order_after": distributed.order,
            "distributed_observable_after": distributed.observable,
            "distributed_detectable_after": distributed.detectable,
            "distributed_unobservable_modes_after": [
                {"re": float(np.real(v)), "im": float(np.imag(v)), "abs": float(abs(v))}
                for v in distributed.unobservable_modes
            ],
            # a singular W' only adds modes at 0 (they die in one step): said, not avoided
            "rank_W_after": int(np.linalg.matrix_rank(new.W)),
        }
    else:
        num = {"observable_after": False, "observability_rank_after": None,
               "detectable_after": None, "distributed_observable_after": False,
               "distributed_rank_after": None, "distributed_order_after": None,
               "distributed_detectable_after": None,
               "distributed_unobservable_modes_after": None, "rank_W_after": None}
    return RecoveryPlan(**{**plan.__dict__, "scenario_after": new, "numerical": num})


def is_recoverable(scenario, failed, allow_new_links: bool = False) -> bool:
    """True iff the failure of ``failed`` (0-based) leaves a recoverable configuration."""
    failed = _check_failed(scenario, failed)
    return _plan(_Context(scenario), failed, add_links=False).is_recoverable(allow_new_links)


@dataclass(frozen=True)
class FailureTolerance:
    """Result of :func:`failure_tolerance`.

    ``p`` is None when even the intact configuration is not recoverable (a parent SCC
    without sensor). ``exact`` is False when the subset bound stopped the search: then
    ``p`` is a lower bound. ``witness`` is a smallest failing set found (0-based) or None.
    """

    p: object
    exact: bool
    witness: object
    subsets_checked: int
    max_subsets: int


def failure_tolerance(scenario, allow_new_links: bool = False,
                      max_subsets: int = DEFAULT_MAX_SUBSETS) -> FailureTolerance:
    """Largest p such that ANY p failures among the N active agents are recoverable.

    "Recoverable" is the module's definition (standby agents are spares that take a
    failed agent's place; ``allow_new_links`` says whether links may be added to restore
    strong connectivity). The search examines every subset of size 0, 1, 2, ... and
    stops at the first size with a non-recoverable subset: p is that size minus one
    (so p failures *or fewer* are always recoverable), or N when every subset passes.

    Cost: sum over sizes of C(N, size) plans, each O(N^2 + n + m) (m = edges of G_A),
    i.e. up to 2^N plans. At most ``max_subsets`` subsets are examined; past that the
    result is a lower bound with ``exact = False`` (the default 20 000 covers any N <= 14
    exhaustively and larger N up to the first few sizes).

    Examples
    --------
    >>> from design.scenario import load_scenario
    >>> s = load_scenario("paper-14")
    >>> failure_tolerance(s).p, failure_tolerance(s, allow_new_links=True).p
    (1, 3)
    """
    ctx = _Context(scenario)
    return _tolerance_search(
        scenario.N, max_subsets,
        lambda subset: _plan(ctx, subset, add_links=False).is_recoverable(allow_new_links))


def redundancy_tolerance(scenario, max_subsets: int = DEFAULT_MAX_SUBSETS) -> FailureTolerance:
    """The paper's Remark 5 notion: tolerance WITHOUT replacement or standby agents.

    Largest p such that after ANY p failures the surviving agents alone still measure
    every parent SCC and their network (W restricted and renormalised) is strongly
    connected. Same search and bound as :func:`failure_tolerance`.

    Examples
    --------
    >>> from design.scenario import load_scenario
    >>> redundancy_tolerance(load_scenario("paper-14")).p     # one sensor per parent SCC
    0
    """
    structure = influence_structure(scenario.A)
    comp_of = structure.labels
    parents = set(structure.parents)

    def survives(subset) -> bool:
        alive = [i for i in range(scenario.N) if i not in subset]
        covered = {int(comp_of[v]) for i in alive for v in scenario.measure[i]}
        if not alive or not parents <= covered:
            return False
        return len(alive) == 1 or is_strongly_connected(
            agent_flow_graph(scenario.W[np.ix_(alive, alive)]))

    return _tolerance_search(scenario.N, max_subsets, survives)


def _tolerance_search(N: int, max_subsets: int, survives) -> FailureTolerance:
    """Smallest failure set (by size, then lexicographic) that ``survives`` rejects."""
    checked = 0
    for size in range(0, N + 1):
        for subset in itertools.combinations(range(N), size):
            if checked >= max_subsets:
                return FailureTolerance(size - 1 if size else None, False, None, checked,
                                        max_subsets)
            checked += 1
            if not survives(subset):
                return FailureTolerance(size - 1 if size else None, True, subset, checked,
                                        max_subsets)
    return FailureTolerance(N, True, None, checked, max_subsets)
