"""Gains for a new configuration after failures: plan -> warm start -> design -> certify.

Pure (no I/O). The pipeline the simulator, ``socmon simulate --recover`` and the monitor
share:

1. :func:`design.recovery.plan_recovery` (failed rows 0-based) builds the new
   configuration ``plan.scenario_after`` (``plan.agent_ids`` = 1-based id per row);
2. :func:`initial_gains` builds a warm start for it from the gains before the failure:
   survivors keep their ``G_i``; an agent that takes a failed agent's place starts from
   that agent's columns for the nodes both measure, and from the reset gain ``H_i^T``
   (the column ``e_v``) for a node it measures anew;
3. :func:`fast_recovery_gains` (a first stabilising gain: objective rho, a target radius,
   a small iteration budget), :func:`polished_recovery_gains` (a few MSE iterations from
   the fast gain: what a precomputed failure switches to first) and
   :func:`refined_recovery_gains` (the MSE-optimised one) design from there; all are
   deterministic (bounded by iterations, no wall clock) and certified by the exact
   radius of the delayed loop (a fast design with ``exact_rho=False``: by its
   eigenvalues counted below a bound, :func:`design.gain_design.counted_bound`);
4. :func:`build_recovery` returns the simulator's :class:`design.simulate.Recovery`;
   :func:`precompute_failures` does steps 1-3 for every failure set of a kind.

Cost (2-core machine, see docs/gain-design.md): one fast gain is one eigenvalue
computation of the companion matrix when the warm start is already stable, a few
BFGS iterations otherwise; a refined gain is one BFGS run on the MSE (one product per
lag and impulse-response step per evaluation) plus one dense Lyapunov solve to certify
the MSE. ``precompute_failures`` costs one fast (+ one refined) design per failure set:
N sets for ``"single"``, N(N-1)/2 for ``"pairs"``.

Examples
--------
>>> from design.scenario import load_scenario
>>> s = load_scenario("paper-14")
>>> from design.gain_design import design_gains
>>> G = design_gains(s, delays="uniform:2", starts=1, max_iter=10).G
>>> rec, info = build_recovery(s, [0], "uniform:2", objective="rho", previous=G, max_iter=5)
>>> rec.ids, info["rho_exact_after_recovery"] < 1
((4, 2, 3), True)
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field

import numpy as np

from .errors import SocmonError

__all__ = [
    "RecoveryDesignError",
    "PrecomputedRecovery",
    "initial_gains",
    "fast_recovery_gains",
    "refined_recovery_gains",
    "polished_recovery_gains",
    "build_recovery",
    "precompute_failures",
    "FAST_TARGET",
    "POLISH_ITER",
    "WARM_PATIENCE",
    "WARM_PATIENCE_TOL",
]

#: Radius the fast gain aims for (stable with a margin; the refinement lowers the MSE).
FAST_TARGET = 0.95
#: MSE iterations :func:`polished_recovery_gains` spends from the fast gain, at most.
POLISH_ITER = 40
#: The stop rule of an MSE stage started near its minimum (a polish from a fast gain, a
#: refinement from the gains in force carried over): it stops when its objective fell by
#: less than WARM_PATIENCE_TOL (relative) over the last WARM_PATIENCE iterations, the
#: same mean rate as the design's default (1e-3 over 20) judged over a shorter window.
WARM_PATIENCE = 5
WARM_PATIENCE_TOL = 2.5e-4


class RecoveryDesignError(SocmonError):
    """A failure that cannot be recovered, or no stabilising gain for its configuration."""


@dataclass(frozen=True, eq=False)
class PrecomputedRecovery:
    """The recovery of one failure set, designed ahead of time.

    Attributes
    ----------
    failed : tuple of int, failed rows (0-based) of the configuration before
    plan : RecoveryPlan
    G : list of arrays, gains per row of ``plan.scenario_after``
    delays : (N', N') int array the gains are designed for and certified against
    rho : float, exact radius of the new delayed loop
    mse_steady : float or None, exact steady MSE (None when not refined or unstable)
    refined : bool, the MSE-optimised gain (else the fast stabilising one)
    seconds : float, design time of this set
    """

    failed: tuple
    plan: object
    G: list
    delays: np.ndarray
    rho: float
    mse_steady: float | None
    refined: bool
    seconds: float
    status: str = ""
    info: dict = field(default_factory=dict)

    @property
    def stable(self) -> bool:
        return bool(self.rho < 1)

    def recovery(self):
        """The simulator's :class:`design.simulate.Recovery` for this set."""
        from .simulate import Recovery

        return Recovery.from_plan(self.plan, self.G, delays=self.delays)


def initial_gains(plan, previous, scenario) -> list:
    """Warm-start gains for ``plan.scenario_after`` from ``previous`` (gains of ``scenario``).

    Row i of the new configuration holds agent ``plan.agent_ids[i]``. A survivor keeps
    its columns; an agent in a failed agent's place (a standby) starts from the failed
    agent's columns for the nodes both measure; any other measured node starts from the
    reset column ``e_v`` (``G_i = H_i^T``: replace the state by the measurement).
    """
    new = plan.scenario_after
    if new is None:
        raise RecoveryDesignError("initial gains: the plan has no new configuration")
    prev = [np.asarray(g, dtype=float) for g in previous]
    if len(prev) != scenario.N:
        raise RecoveryDesignError(f"previous: {len(prev)} gain blocks for N = {scenario.N} agents")
    took = {r.by: r.failed for r in plan.replacements if r.by_standby}
    n = new.n
    out = []
    for row, aid in enumerate(plan.agent_ids):
        src = aid - 1 if aid <= scenario.N else took.get(aid)
        cols = []
        for v in new.measure[row]:
            if src is not None and v in scenario.measure[src]:
                cols.append(prev[src][:, list(scenario.measure[src]).index(v)])
            else:
                e = np.zeros(n)
                e[v] = 1.0
                cols.append(e)
        out.append(np.column_stack(cols) if cols else np.zeros((n, 0)))
    return out


def _resolve_new(new, delays) -> np.ndarray:
    """:func:`design.gain_design.resolve_design_delays` for the new configuration."""
    from .gain_design import DesignError, resolve_design_delays

    try:
        return resolve_design_delays(new, delays)
    except DesignError as exc:
        raise RecoveryDesignError(f"{exc} (for the new configuration)") from None


def fast_recovery_gains(scenario_after, delays, init=None, seed: int = 0,
                        target: float = FAST_TARGET, max_iter: int = 60, **options):
    """A first stabilising gain for ``scenario_after``: objective rho, stop below
    ``target``, at most ``max_iter`` iterations (one start from ``init`` when given,
    else two). Deterministic; ``rho`` is exact (None with ``exact_rho=False`` when the
    start was counted below a bound: ``rho_below``); ``mse_steady`` is not computed. Without
    the distributed pair's rank when W (x) A is stable (detectable then: the check is a
    staircase of order nN, 1.1-1.5 s at communities-32), the gap terms and the gap report
    (N eigenvalue problems of the companion order: 3 of order 864 for Sampson at T = 15):
    the refined gain has them."""
    from .gain_design import design_gains

    opts = {"starts": 1 if init is not None else 2, "gaps": False, "report_gaps": False,
            "pair_rank": False, **options}
    return design_gains(scenario_after, delays=_resolve_new(scenario_after, delays),
                        objective="rho", seed=seed, target=target, max_iter=max_iter,
                        init=init, exact_mse=False, **opts)


def polished_recovery_gains(scenario_after, delays, init, max_iter: int = POLISH_ITER,
                            seed: int = 0, **options):
    """A first gain of low steady MSE at a fraction of the refined design's cost: from the
    stabilising gain ``init`` (:func:`fast_recovery_gains`), at most ``max_iter`` BFGS
    iterations on the exact steady MSE (impulse response), without the gap stage, the
    gap report or the Lyapunov certificate of the MSE; ``rho`` is exact. When the MSE
    stage leaves the stable set, ``init`` comes back (see
    :func:`design.gain_design.design_gains`).

    Why: a fast gain only stabilises, and its exact steady MSE is 1.6-2.4x the refined
    gain's on paper-14-live (T = 3, 7, 15); a precomputed failure switched to it first and
    its level and transient made the error's peak (agent 2 at T = 3, averaged over 1,200
    runs: 2.9x the refined level, 2.0x with this gain or the refined one at once). 40
    iterations from the fast gain come within 0.5 % of the refined MSE there, for
    0.2-0.45 s of CPU at T = 3 and 7 and 0.7-1.2 s at T = 15 (the refined design: seconds
    to minutes). The stage stops earlier when it stalls (:data:`WARM_PATIENCE`): on
    paper-14-live's single failures and pair at T = 3, 7, 15 it ends within 3e-4
    (relative) of the MSE of the 40 iterations for 10-45 % less CPU, and at communities-32
    after 14 iterations instead of 26 (4.7 s of CPU a failure instead of 8.4)."""
    from .gain_design import design_gains

    opts = {"starts": 1, "gaps": False, "report_gaps": False, "pair_rank": False,
            "mse_patience": WARM_PATIENCE, "mse_patience_tol": WARM_PATIENCE_TOL,
            **options}
    return design_gains(scenario_after, delays=_resolve_new(scenario_after, delays),
                        objective="mse", seed=seed, init=init, max_iter=max_iter,
                        exact_mse=False, **opts)


def refined_recovery_gains(scenario_after, delays, init=None, seed: int = 0, **options):
    """The MSE-optimised gain for ``scenario_after`` (one start from ``init`` when given,
    else the design's default starts); exact radius and exact steady MSE."""
    from .gain_design import design_gains

    opts = {"pair_rank": False, **options}
    if init is not None:
        opts.setdefault("starts", 1)
    return design_gains(scenario_after, delays=_resolve_new(scenario_after, delays),
                        objective="mse", seed=seed, init=init, **opts)


def _plan(scenario, failed):
    from .recovery import plan_recovery

    plan = plan_recovery(scenario, failed)
    if plan.scenario_after is None or not plan.structurally_observable_after:
        raise RecoveryDesignError(
            f"the failure of agents {[a + 1 for a in failed]} cannot be recovered (no "
            "equivalent sensor or no connected network left)")
    return plan


def build_recovery(scenario, failed, delays, seed: int = 0, objective: str = "mse", init=None,
                   previous=None, **design_options):
    """Recovery plan for ``failed`` (0-based rows) and gains designed for it.

    Parameters
    ----------
    delays : spec string ("scenario", "none", "uniform:T") resolved on the new
        configuration, or its (N', N') int matrix
    objective : "mse" (default) or "rho"
    init : gains for the new configuration to start from; default: built from
        ``previous`` (the gains before the failure) by :func:`initial_gains` when given
    **design_options : passed to :func:`design.gain_design.design_gains`

    Returns
    -------
    (Recovery, info) : info is JSON-ready (ids 1-based, nodes by label)

    Raises
    ------
    RecoveryDesignError
        No recovery for this failure, or no stabilising gain for its configuration.
    """
    from .gain_design import design_gains
    from .simulate import Recovery

    plan = _plan(scenario, failed)
    new = plan.scenario_after
    D = _resolve_new(new, delays)
    if init is None and previous is not None:
        init = initial_gains(plan, previous, scenario)
    opts = dict(design_options)
    if init is not None:
        opts.setdefault("starts", 1)
    result = design_gains(new, delays=D, seed=seed, objective=objective, init=init, **opts)
    if not result.stable:
        raise RecoveryDesignError(
            f"no stabilising gain found for the recovered configuration "
            f"(best radius {result.rho:.6g})")
    info = {
        "agents_after": list(plan.agent_ids),
        "measure_after": [new.agent_labels(i) for i in range(new.N)],
        "replacements": [
            {"failed": r.failed + 1, "from": scenario.labels[r.node_from],
             "to": scenario.labels[r.node_to], "by": r.by}
            for r in plan.replacements
        ],
        "added_links": [{"from": u, "to": v} for u, v in plan.added_links],
        "rho_exact_after_recovery": float(result.rho),
        "mse_steady_exact_after_recovery": (None if result.mse_steady is None
                                   or not np.isfinite(result.mse_steady)
                                   else float(result.mse_steady)),
        "design_seconds": float(result.seconds),
        "design_status": result.status,
    }
    return Recovery.from_plan(plan, result.G, delays=D), info


def precompute_failures(scenario, delays, G=None, sets: str = "single", refine: bool = True,
                        seed: int = 0, fast_options=None, refine_options=None) -> dict:
    """Recoveries of every failure set of a kind, designed ahead of time.

    Parameters
    ----------
    scenario : Scenario (its standbys are used by the plans)
    delays : spec string resolved on each new configuration, or the (N, N) int matrix
        of ``scenario`` (carried over by the plan; new links get the largest delay)
    G : gains of ``scenario``: warm start of every design (:func:`initial_gains`)
    sets : "single" (N sets) or "pairs" (N(N-1)/2 sets)
    refine : also design the MSE-optimised gain from the fast one (default True)

    Returns
    -------
    dict : tuple of failed rows (0-based, sorted) -> PrecomputedRecovery. Sets without a
    recovery, or without a stabilising gain, are left out (``None`` values are never
    stored). Cost: one fast and, with ``refine``, one refined design per set.
    """
    if sets not in ("single", "pairs"):
        raise RecoveryDesignError(f"sets: expected 'single' or 'pairs', got {sets!r}")
    base = scenario
    spec = delays
    if delays is not None and not isinstance(delays, str):
        base = scenario.replace(delays=np.asarray(delays, dtype=int))
        spec = "scenario"
    size = 1 if sets == "single" else 2
    out = {}
    for failed in itertools.combinations(range(scenario.N), size):
        t0 = time.perf_counter()
        try:
            plan = _plan(base, list(failed))
        except RecoveryDesignError:
            continue
        new = plan.scenario_after
        D = _resolve_new(new, spec)
        init = initial_gains(plan, G, base) if G is not None else None
        try:
            res = fast_recovery_gains(new, D, init=init, seed=seed, **(fast_options or {}))
        except SocmonError:
            continue
        refined = False
        if refine and res.stable:
            res2 = refined_recovery_gains(new, D, init=res.G, seed=seed, **(refine_options or {}))
            if res2.stable:
                res, refined = res2, True
        if not res.stable:
            continue
        out[tuple(failed)] = PrecomputedRecovery(
            failed=tuple(failed), plan=plan, G=list(res.G), delays=D, rho=float(res.rho),
            mse_steady=res.mse_steady if refined else None, refined=refined,
            seconds=time.perf_counter() - t0, status=res.status)
    return out
