"""The configuration between a failure and the switch: the gap, a closed loop like any other.

When agent f fails, its receivers hold its last estimate and propagate it for
``hold_limit`` steps, then lose it: its weight goes to their own predictions
(:func:`design.estimator.neighbour_input`). Until the monitor's new roles are in force the
network runs *that* loop: the other agents with their gains, f's row and column gone, and
each receiver's weight on f added to its own. If it is unstable, the estimates diverge
while the network waits (paper-14-live at 15-step delays with agent 3 gone: one agent ran
alone with an own loop of radius 1.40 and the MSE reached 1e32 on a stable system).

:func:`gap_report` gives, for every single failure, the exact radius and steady MSE of
that gap loop (with the delays), and each agent's own-loop radius
``rho((I - G_i H_i) A)``, the loop an agent runs on its own readings when every neighbour
weight has gone to its own prediction.

Examples
--------
>>> from design.scenario import load_scenario
>>> import numpy as np
>>> s = load_scenario("paper-14-live")
>>> G = [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure]
>>> [g.failed for g in gap_report(s, G)]
[1, 2, 3]
>>> all(g.rho < 1 for g in gap_report(s, G))
True
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .closed_loop import ClosedLoop, spectral_radius

__all__ = ["GapLoop", "gap_weights", "gap_loop", "gap_report", "own_loop_radius",
           "diverging_gaps", "gap_warnings", "gap_detectability", "own_loop_bound",
           "GAP_MARGIN", "gap_possibilities", "GAP_ANALYSIS_MAX_ORDER"]

#: The design keeps every gap's exact radius below ``1 - GAP_MARGIN`` where it can.
GAP_MARGIN = 0.01
#: :func:`gap_possibilities` runs one staircase of order n (N - 1) per agent: up to this
#: order (communities-16, order 540: 8 s on the 2-core development machine).
GAP_ANALYSIS_MAX_ORDER = 300


@dataclass(frozen=True)
class GapLoop:
    """The gap after the failure of agent ``failed`` (1-based id, row ``failed - 1``).

    ``rho``: exact radius of the delayed gap loop; ``mse_steady``: its exact steady MSE
    (None when ``rho >= 1``); ``own_radius``: agent id -> radius of its own loop
    ``(I - G_i H_i) A`` (every agent of the gap)."""

    failed: int
    rho: float
    mse_steady: float | None
    own_radius: dict

    @property
    def stable(self) -> bool:
        return bool(self.rho < 1.0)

    def to_dict(self) -> dict:
        return {"failed": self.failed, "rho_exact": self.rho, "stable": self.stable,
                "mse_steady_exact": self.mse_steady,
                "own_loop_radius": {str(a): r for a, r in self.own_radius.items()}}


def own_loop_radius(A, measured, G_i) -> float:
    """``rho((I - G_i H_i) A)``: agent i alone, on its own readings.

    >>> own_loop_radius(np.array([[1.2]]), (0,), np.array([[0.5]]))
    0.6
    """
    A = np.asarray(A, dtype=float)
    H = np.zeros((len(measured), A.shape[0]))
    H[np.arange(len(measured)), list(measured)] = 1.0
    return float(round(spectral_radius((np.eye(A.shape[0]) - np.asarray(G_i) @ H) @ A), 12))


def gap_weights(W, failed_row: int):
    """``(keep, W_gap)``: the rows that remain and their weights once ``failed_row`` is
    lost; each receiver's weight on it goes to its own prediction (rows still sum to 1).

    >>> keep, W2 = gap_weights(np.array([[0.5, 0.5, 0], [0, 0.5, 0.5], [0.5, 0, 0.5]]), 2)
    >>> keep, W2.tolist()
    ([0, 1], [[0.5, 0.5], [0.0, 1.0]])
    """
    W = np.asarray(W, dtype=float)
    keep = [r for r in range(W.shape[0]) if r != failed_row]
    W2 = W[np.ix_(keep, keep)].copy()
    for row, i in enumerate(keep):
        W2[row, row] += W[i, failed_row]
    return keep, W2


def gap_loop(scenario, G, delays, failed_row: int) -> ClosedLoop:
    """The :class:`ClosedLoop` of the other agents once ``failed_row``'s estimate is lost."""
    keep, W2 = gap_weights(scenario.W, failed_row)
    D = np.asarray(scenario.delays if delays is None else delays, dtype=int)
    return ClosedLoop(scenario.A, W2, D[np.ix_(keep, keep)],
                      [scenario.measure[r] for r in keep], [G[r] for r in keep])


def gap_report(scenario, G, delays=None, mse: bool = True, radii=None) -> list:
    """A :class:`GapLoop` for the failure of each agent of ``scenario`` (N >= 2);
    ``mse=False`` skips the steady MSE (a Lyapunov solve each: the radii alone are what a
    start-up check needs); ``radii`` (failed id -> exact radius of its gap loop with these
    gains and delays) skips the radii already known."""
    out = []
    N = len(scenario.measure)
    if N < 2:
        return out
    own = {i + 1: own_loop_radius(scenario.A, scenario.measure[i], G[i]) for i in range(N)}
    for f in range(N):
        loop = gap_loop(scenario, G, delays, f)
        rho = radii[f + 1] if radii is not None and f + 1 in radii else loop.spectral_radius()
        value = loop.mse_steady(scenario.process_noise, scenario.measurement_noise) \
            if mse and rho < 1 else None
        out.append(GapLoop(failed=f + 1, rho=float(rho), mse_steady=value,
                           own_radius={a: r for a, r in own.items() if a != f + 1}))
    return out


def diverging_gaps(report) -> list:
    """The gaps of ``report`` whose loop is unstable, in words (empty when none).

    >>> diverging_gaps([GapLoop(2, 1.4, None, {1: 1.403, 3: 0.5})])
    ['agent 2 fails: the others run a loop of exact radius 1.4 until the switch (own loops above 1: agent 1 1.403)']
    """
    lines = []
    for g in report:
        if g.stable:
            continue
        above = [f"agent {a} {r:.4g}" for a, r in sorted(g.own_radius.items()) if r >= 1]
        lines.append(f"agent {g.failed} fails: the others run a loop of exact radius "
                     f"{g.rho:.4g} until the switch"
                     + (f" (own loops above 1: {', '.join(above)})" if above else ""))
    return lines


def gap_warnings(scenario, G, delays=None) -> list:
    """The start-up warnings of a run: one line per single failure whose gap diverges."""
    return [f"{line}: the estimates diverge if the switch comes later than the hold "
            "window" for line in diverging_gaps(gap_report(scenario, G, delays, mse=False))]


def gap_detectability(scenario, failed_row: int):
    """Detectability of the gap's distributed pair (:class:`PairObservability`): when it
    is not detectable no gain makes that gap stable (its unobservable modes stay)."""
    from .observability import distributed_detectability

    keep, W2 = gap_weights(scenario.W, failed_row)
    return distributed_detectability(scenario.A, W2, [scenario.measure[r] for r in keep])


def own_loop_bound(A, measured) -> float:
    """The largest unobservable modulus of ``(A, H_i)``: no ``G_i`` brings agent i's own
    loop below it (0 when agent i alone observes everything).

    >>> own_loop_bound(np.array([[0.5, 0.0], [1.0, 2.0]]), (0,))
    2.0
    """
    from .observability import pair_observability

    A = np.asarray(A, dtype=float)
    H = np.zeros((len(measured), A.shape[0]))
    H[np.arange(len(measured)), list(measured)] = 1.0
    return pair_observability(A, H).max_unobservable_modulus


def gap_possibilities(scenario):
    """What any gain can do in the gaps, from the scenario alone.

    Returns ``(gaps, own)``: ``gaps`` a list of dicts, for the failure of each agent,
    ``failed`` (id), ``detectable`` (some gain makes that gap loop stable only if so) and
    ``max_unobservable_modulus`` of the gap's distributed pair; ``own`` agent id ->
    :func:`own_loop_bound`, the lowest radius any gain gives that agent's own loop.
    ``gaps`` is None when ``n (N - 1)`` is above :data:`GAP_ANALYSIS_MAX_ORDER`.

    >>> from design.scenario import load_scenario
    >>> gaps, own = gap_possibilities(load_scenario("paper-14-live"))
    >>> [g["detectable"] for g in gaps], sorted(own)
    ([True, True, True], [1, 2, 3])
    """
    N = len(scenario.measure)
    own = {i + 1: own_loop_bound(scenario.A, scenario.measure[i]) for i in range(N)}
    if N < 2:
        return [], own
    if scenario.n * (N - 1) > GAP_ANALYSIS_MAX_ORDER:
        return None, own
    gaps = []
    for f in range(N):
        d = gap_detectability(scenario, f)
        gaps.append({"failed": f + 1, "detectable": bool(d.detectable),
                     "max_unobservable_modulus": float(d.max_unobservable_modulus)})
    return gaps, own
