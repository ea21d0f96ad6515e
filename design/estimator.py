"""The estimator step: one pure function shared by the simulator and the agent process.

Agent i at step k, with neighbour estimates ``xhat^j`` stamped ``s_j`` (normally
``s_j = k - 1 - tau_ij``):

    prediction  xhat^i_{k|k-1} = w_ii A xhat^i_{k-1|k-1} + sum_j w_ij A^(k - s_j) xhat^j_{s_j|s_j}
    update      xhat^i_{k|k}   = xhat^i_{k|k-1} + G_i (y^i_k - H_i xhat^i_{k|k-1})

with ``G_i = K^i H_i^T`` (n x p_i). ``A^(k - s_j)`` propagates a delayed estimate to the
present (``A^(1 + tau_ij)`` on a link with delay tau_ij; older when a message was dropped
and the freshest held estimate is used instead). A neighbour for which no estimate is
held at all gives its weight to the agent's own prediction, so the weights stay
row-stochastic.

Arrays may carry leading batch axes (Monte-Carlo trials): ``x`` of shape (..., n).

Examples
--------
>>> import numpy as np
>>> A = np.array([[1.0, 0.0], [0.5, 1.0]])
>>> role = AgentRole(measured=(0,), self_weight=0.5, G=np.array([[0.5], [0.0]]))
>>> prior, post = estimator_step(PowerCache(A), role, np.zeros(2),
...                              [NeighbourEstimate(0.5, 1, np.ones(2))], np.array([2.0]))
>>> prior, post
(array([0.5 , 0.75]), array([1.25, 0.75]))
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "AgentRole",
    "NeighbourEstimate",
    "PowerCache",
    "estimator_step",
    "role_from",
    "HOLD_GRACE",
    "hold_limit",
    "neighbour_input",
    "continued_stamp",
    "FRESH",
    "HELD",
    "LOST",
    "NONE",
]

#: Steps beyond the slowest link (``1 + taubar``) that a held estimate may still be used.
HOLD_GRACE = 16

# what :func:`neighbour_input` made of a neighbour at one step
FRESH = "fresh"   # the estimate stamped k - 1 - tau is held: used, age 1 + tau
HELD = "held"     # an older one is held (the needed one is late, lost or never sent,
                  # e.g. the neighbour failed): used, propagated by A^age
LOST = "lost"     # what is held is older than the hold limit: weight to self
NONE = "none"     # nothing is held (before the first estimate): weight to self


@dataclass(frozen=True, eq=False)
class AgentRole:
    """What one agent does: nodes it measures, its self weight and its gain ``G_i``."""

    measured: tuple
    self_weight: float
    G: np.ndarray  # (n, p_i)

    def __post_init__(self):
        G = np.asarray(self.G, dtype=float)
        if G.ndim != 2 or G.shape[1] != len(self.measured):
            raise ValueError(
                f"G: must be n x {len(self.measured)} (one column per measured node), "
                f"got shape {G.shape}"
            )
        if not 0 < self.self_weight <= 1:
            raise ValueError(f"self_weight: must be in (0, 1], got {self.self_weight!r}")
        object.__setattr__(self, "G", G)
        object.__setattr__(self, "measured", tuple(int(j) for j in self.measured))


@dataclass(frozen=True, eq=False)
class NeighbourEstimate:
    """``weight`` * A^``age`` applied to ``x``: a neighbour's estimate ``age`` steps old.

    ``age = k - s`` for an estimate stamped s used at step k (``1 + tau`` when on time).
    ``x=None`` means nothing is held from that neighbour: its weight goes to self.
    """

    weight: float
    age: int
    x: np.ndarray | None


class PowerCache:
    """Lazily computed and cached powers ``A^m``, ``m <= max_power`` (None: unbounded).

    The neighbour policy never uses an estimate older than :func:`hold_limit`, so a
    process keeps at most that many matrices, however long a neighbour stays silent.

    >>> import numpy as np
    >>> PowerCache(np.array([[2.0]]))[3]
    array([[8.]])
    >>> PowerCache(np.array([[2.0]]), max_power=2)[3]
    Traceback (most recent call last):
    ...
    ValueError: age: power 3 is beyond the hold limit 2
    """

    def __init__(self, A, max_power: int | None = None):
        self.A = np.asarray(A, dtype=float)
        self.max_power = None if max_power is None else int(max_power)
        self._pow = {0: np.eye(self.A.shape[0]), 1: self.A}
        self._powT = {}

    def __getitem__(self, m: int) -> np.ndarray:
        m = int(m)
        if m < 0:
            raise ValueError(f"age: an estimate cannot be from the future (power {m})")
        if self.max_power is not None and m > self.max_power:
            raise ValueError(f"age: power {m} is beyond the hold limit {self.max_power}")
        if m not in self._pow:
            k = max(p for p in self._pow if p <= m)
            P = self._pow[k]
            for j in range(k + 1, m + 1):
                P = P @ self.A
                self._pow[j] = P
        return self._pow[m]

    def transposed(self, m: int) -> np.ndarray:
        """``(A^m)^T`` as a contiguous array, for right-multiplying batches of rows."""
        if m not in self._powT:
            self._powT[m] = np.ascontiguousarray(self[m].T)
        return self._powT[m]


def estimator_step(powers: PowerCache, role: AgentRole, x_prev, neighbours, y):
    """One step of agent i: consensus prediction, then the local update.

    Parameters
    ----------
    powers : PowerCache
        Powers of the social matrix A.
    role : AgentRole
    x_prev : array (..., n)
        The agent's own estimate ``xhat^i_{k-1|k-1}``.
    neighbours : iterable of NeighbourEstimate
    y : array (..., p_i)
        The agent's measurement ``y^i_k``.

    Returns
    -------
    prior, post : arrays (..., n)
        ``xhat^i_{k|k-1}`` and ``xhat^i_{k|k}``.
    """
    w_self = role.self_weight
    terms = []
    for nb in neighbours:
        if nb.weight == 0:
            continue
        if nb.x is None:
            w_self += nb.weight
        else:
            terms.append((nb.weight, nb.age, nb.x))
    prior = w_self * (np.asarray(x_prev) @ powers.transposed(1))
    for w, age, x in terms:
        if age == 0:  # A^0 = I: no product needed
            prior = prior + w * np.asarray(x)
        else:
            prior = prior + w * (np.asarray(x) @ powers.transposed(age))
    innovation = np.asarray(y) - prior[..., list(role.measured)]
    post = prior + innovation @ role.G.T
    return prior, post


def hold_limit(taubar: int) -> int:
    """Oldest age (steps) at which a held neighbour estimate is still used.

    ``1 + taubar`` is the age of an on-time estimate over the slowest link; an estimate
    may be propagated :data:`HOLD_GRACE` steps beyond that (a late, lost or failed
    neighbour), then its weight goes to the agent's own prediction. This bounds the
    powers of A an agent ever forms, and the error a stale estimate of an unstable
    system can inject.

    >>> hold_limit(0), hold_limit(7)
    (17, 24)
    """
    return int(taubar) + 1 + HOLD_GRACE


def neighbour_input(weight: float, k: int, stamp, x, max_age: int, need=None):
    """The one neighbour policy: what an estimate stamped ``stamp`` gives at step ``k``.

    Used by the simulator (per group of trials holding the same stamp) and by
    :class:`agent.node.core.AgentCore` alike. ``stamp`` is the stamp of the estimate the agent
    uses from this neighbour (the needed one ``k - 1 - tau`` if held, else the freshest
    held, at most ``k - 1``), None or negative when it holds nothing; ``need`` is the
    needed stamp, only to tell fresh from held.

    Returns ``(NeighbourEstimate, state)``, state one of :data:`FRESH`, :data:`HELD`,
    :data:`LOST`, :data:`NONE`. A neighbour that failed or whose messages are lost is
    held and propagated until its estimate is older than ``max_age``
    (:func:`hold_limit`), then lost; a neighbour removed by a role change is simply not
    a neighbour of the new role.

    >>> import numpy as np
    >>> neighbour_input(0.5, 10, 9, np.ones(2), max_age=4, need=9)[1]
    'fresh'
    >>> neighbour_input(0.5, 10, 7, np.ones(2), max_age=4, need=9)[1]
    'held'
    >>> nb, state = neighbour_input(0.5, 10, 5, np.ones(2), max_age=4, need=9)
    >>> state, nb.x is None, nb.weight
    ('lost', True, 0.5)
    """
    if stamp is None or stamp < 0:
        return NeighbourEstimate(weight, 1, None), NONE
    age = int(k) - int(stamp)
    if age < 1:
        raise ValueError(f"stamp: an estimate stamped {stamp} cannot be used at step {k}")
    if age > max_age:
        return NeighbourEstimate(weight, 1, None), LOST
    return NeighbourEstimate(weight, age, x), FRESH if stamp == need else HELD


def continued_stamp(stamp: int, first_own: int) -> bool:
    """The continuity rule at a switch: does a link that continues a failed agent's row
    carry that agent's estimate stamped ``stamp``?

    When agent r takes over the row of a failed agent f, its first estimate is stamped
    ``first_own`` (``activate_at - 1``). Every receiver that listened to f and now listens
    to r reads, on the link from r, f's stream for the stamps before that (what f had
    already sent, arriving on f's own link schedule), then r's own: the replacement is the
    continuation of the row. The neighbour policy (:func:`neighbour_input`) then applies
    as on any link. Without it the link from r was empty for ``tau`` steps and its weight
    went to the receiver's own prediction, whose loop can be unstable (the MSE after a
    recovery at 15-step delays peaked at 1.9e5 on paper-14). The simulator
    (:func:`design.simulate.simulate`) and :class:`agent.node.core.AgentCore` both ask this.

    >>> continued_stamp(173, first_own=174), continued_stamp(174, first_own=174)
    (True, False)
    """
    return int(stamp) < int(first_own)


def role_from(scenario, gains, agent: int) -> AgentRole:
    """The :class:`AgentRole` of agent index ``agent`` (0-based) in ``scenario``."""
    return AgentRole(
        measured=scenario.measure[agent],
        self_weight=float(scenario.W[agent, agent]),
        G=gains[agent],
    )
