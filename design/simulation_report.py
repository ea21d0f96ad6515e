"""A Monte-Carlo run beside the exact figures of the loop it simulates (what ``socmon
simulate`` reports).

:func:`recovery_for` designs the recovery of a failure for the objective the gains were
designed for, warm started from them; :func:`simulation_record` turns a
:class:`~design.simulate.SimulationResult` into a JSON-ready record: the MSE, its 10-90
percentile band across trials and, when the run simulates exactly the loop
:func:`~design.closed_loop.exact_performance` solves (no failure, no drops), that loop's
exact steady MSE and spectral radius; when it runs that loop until a failure (no drops),
its exact steady MSE as the level before the failure.

>>> import numpy as np
>>> from design.scenario import scenario_from_dict
>>> from design.simulate import simulate
>>> s = scenario_from_dict({"social": {"A": [[0.5]]}, "agents": {"measure": [["1"]]}})
>>> G = [np.array([[0.5]])]
>>> rec, before = simulation_record(s, G, simulate(s, G, 20, 2, 0), s.delays)
>>> rec["rho_exact"], rec["unstable"], rec["mse_steady_exact"] == before.mse
(0.25, False, True)
"""

from __future__ import annotations

from .closed_loop import exact_performance
from .reconfigure import build_recovery

__all__ = ["recovery_objective", "recovery_for", "simulation_record"]


def recovery_objective(meta) -> str:
    """The design objective of a recovery for gains with ``meta``: theirs ("rho" or
    "mse"), else "rho".

    >>> recovery_objective({"objective": "mse"}), recovery_objective({})
    ('mse', 'rho')
    """
    objective = meta.get("objective")
    return objective if objective in ("rho", "mse") else "rho"


def recovery_for(scenario, gains, failed, delays, seed: int = 0, time_limit=None,
                 progress=None):
    """:func:`design.reconfigure.build_recovery` of the failure of ``failed`` (0-based
    rows) for :class:`~design.gains.Gains` ``gains``: their objective
    (:func:`recovery_objective`), warm started from them, the design capped at
    ``time_limit`` seconds when given. Returns ``(Recovery, info)``, info naming the
    objective too; raises RecoveryDesignError."""
    objective = recovery_objective(gains.meta)
    budget = {} if time_limit is None else {"time_limit": time_limit}
    recover, info = build_recovery(scenario, failed, delays, seed=seed, objective=objective,
                                   previous=gains.G, progress=progress, **budget)
    info["objective"] = objective
    return recover, info


def simulation_record(scenario, G, result, delays, *, gains_file=None, delays_spec=None,
                      recovery_info=None):
    """``(record, before)``: the JSON-ready record of ``result`` (a simulation of
    ``scenario`` with gains ``G`` and link ``delays``; ``gains_file`` and ``delays_spec``
    name them in it) and the exact performance of the loop before any failure (None when
    not computed: the run has drops or a failure without recovery).

    The record is :meth:`~design.simulate.SimulationResult.to_dict` with ``mse_p10`` and
    ``mse_p90``, ``scenario``, ``gains_file``, ``delays``, ``delays_spec``,
    ``mse_steady_exact`` and ``rho_exact`` (None unless the run is the exact loop),
    ``mse_steady_exact_before_failure`` (the exact loop's steady MSE when the run is that
    loop until a failure; None without a failure or with drops), ``unstable`` (its
    exact radius is >= 1) and, given ``recovery_info``, ``recovery`` (with the level
    after the recovery, ``mse_steady_exact_after_recovery``).
    """
    out = result.to_dict()
    lo, hi = result.band()
    out["mse_p10"], out["mse_p90"] = lo.tolist(), hi.tolist()
    out["scenario"] = scenario.name
    out["gains_file"] = gains_file
    out["delays"] = delays.tolist()
    out["delays_spec"] = delays_spec
    exact = result.fail_step is None and result.drop == 0   # the loop certify sees
    until_failure = result.fail_step is not None and result.drop == 0   # that loop, then not
    before = exact_performance(scenario, G, delays) \
        if exact or until_failure or result.recovered else None
    out["mse_steady_exact"] = before.mse if exact else None
    out["mse_steady_exact_before_failure"] = before.mse if until_failure else None
    out["rho_exact"] = before.rho if exact else None
    out["unstable"] = out["rho_exact"] is not None and not out["rho_exact"] < 1
    if recovery_info is not None:
        out["recovery"] = recovery_info
    return out, before
