"""The configuration in force: which agent id holds which row, and how it changes on failure.

A :class:`~design.scenario.Scenario` numbers its agents by row (0-based). A live run
numbers them by id (1-based): ids 1..N hold rows 0..N-1 at the start and ids
N+1..N+S are standbys. After a recovery the rows are held by other ids (a standby takes
the row of the agent it replaces), so a second failure must be planned on the
configuration *as it is now*. :class:`Roster` carries that mapping; :func:`replan`
plans a failure of ids on it with :func:`design.recovery.plan_recovery` and returns the
next roster; :func:`role_specs` says what each id does in it.

Link delays belong to the links between processes, not to roles:
:func:`link_delay_table` gives the delay of every ordered pair of ids of a run (the
scenario's delay on its links, the largest delay elsewhere: a new link is assumed as
slow as the slowest one, as :func:`design.recovery.plan_recovery` assumes).

Examples
--------
>>> from design.scenario import load_scenario
>>> s = load_scenario("paper-14")
>>> r0 = Roster.initial(s)
>>> r0.ids, r0.standby_ids
((1, 2, 3), (4,))
>>> plan, r1 = replan(r0, [1])              # agent 1 (measures node 7) fails
>>> r1.ids, r1.standby_ids, [s.labels[v] for v in r1.scenario.measure[0]]
((4, 2, 3), (), ['8'])
>>> plan2, r2 = replan(r1, [4])             # then its replacement fails: no standby left
>>> r2.ids, [[s.labels[v] for v in m] for m in r2.scenario.measure]
((2, 3), [['9', '6'], ['12']])
"""

from __future__ import annotations

import dataclasses

from dataclasses import dataclass

import numpy as np

from .errors import SocmonError
from .recovery import plan_recovery

__all__ = [
    "Roster",
    "carried_gains",
    "RoleSpec",
    "RosterError",
    "link_delay_table",
    "replan",
    "role_specs",
    "roster_from_specs",
]


class RosterError(SocmonError):
    """A failure names an id that holds no row, or a roster is inconsistent."""


def link_delay_table(scenario, delays) -> np.ndarray:
    """(M, M) int delays by 0-based id index: ``T[a-1, b-1]`` is link b -> a.

    Scenario links (both ids <= N, ``W[a-1, b-1] > 0``) keep ``delays``; every other
    pair (a standby, or agents that are not neighbours in the scenario) gets
    ``delays.max()``. The diagonal is 0.

    >>> import numpy as np
    >>> from design.scenario import load_scenario
    >>> link_delay_table(load_scenario("paper-14"), np.array([[0, 2, 0], [0, 0, 1], [3, 0, 0]]))
    array([[0, 2, 3, 3],
           [3, 0, 1, 3],
           [3, 3, 0, 3],
           [3, 3, 3, 0]])
    """
    D = np.asarray(delays, dtype=int)
    N = scenario.N
    M = N + scenario.standby
    top = int(D.max()) if D.size else 0
    T = np.full((M, M), top, dtype=int)
    W = np.asarray(scenario.W)
    link = (W > 0) & ~np.eye(N, dtype=bool)
    T[:N, :N] = np.where(link, D, top)
    np.fill_diagonal(T, 0)
    return T


@dataclass(frozen=True, eq=False)
class Roster:
    """The configuration in force: ``scenario`` row i is held by agent ``ids[i]``.

    ``standby_ids`` are the ids still available as replacements, in the order they are
    used; ``table`` is :func:`link_delay_table` of the run (by id), ``delays`` the delay
    matrix of ``scenario`` (rows), taken from ``table`` unless learned otherwise.
    """

    scenario: object
    ids: tuple
    standby_ids: tuple
    table: np.ndarray
    delays: np.ndarray

    @classmethod
    def initial(cls, scenario, delays=None) -> "Roster":
        D = scenario.delays if delays is None else np.asarray(delays, dtype=int)
        T = link_delay_table(scenario, D)
        N = scenario.N
        return cls(scenario=scenario, ids=tuple(range(1, N + 1)),
                   standby_ids=tuple(range(N + 1, N + scenario.standby + 1)), table=T,
                   delays=np.asarray(D, dtype=int).copy())

    def row_of(self, agent_id: int) -> int:
        try:
            return self.ids.index(int(agent_id))
        except ValueError:
            raise RosterError(f"agent {agent_id} holds no role in this configuration "
                              f"(active: {list(self.ids)})") from None

    def delays_for(self, ids) -> np.ndarray:
        """Delay matrix of a configuration whose rows are held by ``ids`` (from the table)."""
        idx = [int(a) - 1 for a in ids]
        return self.table[np.ix_(idx, idx)].copy()

    def with_delays(self, learned: dict) -> "Roster":
        """The same roster with learned delays ``{(receiver id, sender id): tau}`` on links."""
        D = self.delays.copy()
        for (a, b), tau in learned.items():
            if a in self.ids and b in self.ids:
                i, j = self.row_of(a), self.row_of(b)
                if i != j and self.scenario.W[i, j] > 0:
                    D[i, j] = int(tau)
        return Roster(self.scenario.replace(delays=D), self.ids, self.standby_ids,
                      self.table, D)


def replan(roster: Roster, failed_ids, add_links: bool = True, numerical: bool = True):
    """Plan the failure of agents ``failed_ids`` (1-based ids) on the roster in force.

    ``numerical``: also check the next configuration's observability and distributed
    detectability numerically (``plan.numerical``, :func:`design.recovery.plan_recovery`);
    the monitor, which acts on the structural plan and leaves the numbers to the gain
    design, passes False.

    Returns ``(plan, next_roster)``: ``plan`` is the :class:`design.recovery.RecoveryPlan`
    on ``roster.scenario`` (rows), whose ``agent_ids`` are translated to run ids;
    ``next_roster`` is None when no configuration is left (``plan.scenario_after`` None).
    The next configuration's delays come from the run's link delay table.
    """
    rows = sorted(roster.row_of(a) for a in failed_ids)
    s = roster.scenario
    # plan_recovery numbers standbys N+1.. after the rows of the scenario it is given
    local = s.replace(standby=len(roster.standby_ids), delays=roster.delays)
    plan = plan_recovery(local, rows, add_links=add_links, numerical=numerical)
    to_run = {i + 1: roster.ids[i] for i in range(s.N)}
    to_run.update({s.N + 1 + k: a for k, a in enumerate(roster.standby_ids)})
    ids_after = tuple(to_run[a] for a in plan.agent_ids)
    plan = _translate(plan, to_run)
    if plan.scenario_after is None:
        return plan, None
    used = set(ids_after)
    left = tuple(a for a in roster.standby_ids if a not in used)
    D_after = roster.delays_for(ids_after)
    W_after = plan.scenario_after.W
    D_after = np.where((W_after > 0) & ~np.eye(len(ids_after), dtype=bool), D_after, 0)
    new = plan.scenario_after.replace(delays=D_after, standby=len(left))
    plan = plan.__class__(**{**plan.__dict__, "scenario_after": new, "delays_after": D_after})
    return plan, Roster(new, ids_after, left, roster.table, D_after)


def _translate(plan, to_run):
    from .recovery import Replacement

    reps = [Replacement(r.failed, r.node_from, r.node_to, to_run[r.by], r.by_standby)
            for r in plan.replacements]
    return plan.__class__(**{
        **plan.__dict__,
        "agent_ids": [to_run[a] for a in plan.agent_ids],
        "replacements": reps,
        "components_removed": [[to_run[a] for a in c] for c in plan.components_removed],
        "added_links": [(to_run[u], to_run[v]) for u, v in plan.added_links],
    })


@dataclass(frozen=True, eq=False)
class RoleSpec:
    """What agent ``agent`` does in a configuration (labels, neighbour ids, gain)."""

    agent: int
    measure: tuple            # node labels, order = columns of gain
    neighbours: dict          # neighbour id -> weight
    self_weight: float
    gain: np.ndarray          # (n, len(measure))
    take_over: int | None = None
    #: new neighbour id -> the failed agent id whose estimate stream it continues
    continues: dict | None = None

    def same_as(self, other) -> bool:
        """True iff ``other`` (a RoleSpec) describes the same role."""
        return (other is not None and self.measure == other.measure
                and self.neighbours == other.neighbours
                and self.self_weight == other.self_weight
                and self.gain.shape == other.gain.shape
                and bool(np.array_equal(self.gain, other.gain)))


def carried_gains(roster: Roster, G, nxt: Roster) -> list:
    """A warm start for the gains of ``nxt`` from the gains ``G`` (by row) in force on
    ``roster``: an agent that keeps its measurements keeps its gain, any other row gets the
    reset gain ``H_i^T`` (it replaces its measured states by the measurement).

    Why: the configuration after one failure differs from the one in force by a row or
    two, and the gains in force usually stabilise it already (paper-14-live, each single
    failure at T = 3 and 15: exact radius 0.76-0.91 from this start, below the fast
    design's target, against 0.89-0.95 from the reset gain alone), so that a first
    certified gain costs one eigenvalue problem instead of a few BFGS iterations.

    >>> from design.scenario import load_scenario
    >>> s = load_scenario("paper-14")
    >>> r = Roster.initial(s)
    >>> G = [np.full((s.n, len(m)), float(i)) for i, m in enumerate(s.measure, start=1)]
    >>> _, nxt = replan(r, [1])
    >>> nxt.ids
    (4, 2, 3)
    >>> [float(g[0, 0]) for g in carried_gains(r, G, nxt)]   # 4 is new: its reset gain
    [0.0, 2.0, 3.0]
    """
    out = []
    for i, a in enumerate(nxt.ids):
        m = tuple(nxt.scenario.measure[i])
        j = roster.ids.index(a) if a in roster.ids else None
        if j is not None and tuple(roster.scenario.measure[j]) == m:
            out.append(np.array(G[j], dtype=float))
        else:
            out.append(np.eye(nxt.scenario.n)[:, list(m)])
    return out


def role_specs(roster: Roster, G, take_over=None) -> dict:
    """``{id: RoleSpec}`` of every agent of ``roster`` with gains ``G`` (by row).

    ``take_over`` maps a new id to the id whose estimate it starts from; a neighbour that
    takes over in this way *continues* that agent's stream (``continues``, the continuity
    rule of :class:`design.estimator.NeighbourLink`).
    """
    s = roster.scenario
    take_over = take_over or {}
    out = {}
    for i, a in enumerate(roster.ids):
        neighbours = {roster.ids[j]: float(s.W[i, j]) for j in range(s.N)
                      if j != i and s.W[i, j] > 0}
        out[a] = RoleSpec(
            agent=a, measure=tuple(s.labels[v] for v in s.measure[i]),
            neighbours=neighbours,
            self_weight=float(s.W[i, i]), gain=np.asarray(G[i], dtype=float),
            take_over=take_over.get(a),
            continues={b: take_over[b] for b in neighbours if b in take_over} or None)
    return out


def roster_from_specs(scenario, table, ids, specs: dict, transient: bool = False):
    """The configuration held by ``ids`` whose roles are ``specs`` ({id: RoleSpec}).

    Returns ``(Scenario, G, delays)`` by row (row i = ``ids[i]``), delays from the run's
    link delay ``table``: what a recorder rebuilds from the assignments it saw, to predict
    the new configuration's error exactly and to replay it in the simulator.
    ``transient``: the roles some agents ran for a few steps while others still ran older
    ones (an assignment heard too late), replayed as the agents ran them: not validated as
    a network (it need not be strongly connected).
    """
    ids = [int(a) for a in ids]
    n = len(ids)
    W = np.zeros((n, n))
    measure, G = [], []
    for i, a in enumerate(ids):
        sp = specs.get(a)
        if sp is None:
            raise RosterError(f"no role recorded for agent {a}")
        for b, w in sp.neighbours.items():
            if b not in ids:
                raise RosterError(f"agent {a} listens to {b}, which holds no role")
            W[i, ids.index(b)] = w
        W[i, i] = sp.self_weight
        measure.append(tuple(scenario.index_of(label) for label in sp.measure))
        G.append(np.asarray(sp.gain, dtype=float))
    idx = [a - 1 for a in ids]
    D = np.asarray(table)[np.ix_(idx, idx)]
    D = np.where((W > 0) & ~np.eye(n, dtype=bool), D, 0)
    if transient:
        new = dataclasses.replace(scenario, W=W, measure=tuple(measure), delays=D, standby=0)
    else:
        new = scenario.replace(W=W, measure=tuple(measure), delays=D, standby=0)
    return new, G, D
