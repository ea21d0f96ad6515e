"""The records of the design-side commands: a library result joined with what happens
between a failure and the switch (:mod:`design.gap`), and the warnings these call for.

``socmon analyze`` prints :func:`analysis_record`, ``certify`` :func:`certificate_record`,
``plan`` :func:`recovery_record` and ``design`` a :meth:`DesignResult.summary
<design.gain_design.DesignResult.summary>` checked by :func:`recheck_design`. Plain dicts
(docs/json.md names their keys), JSON-ready apart from numpy values; what only the
command line knows (the files read and written) it adds itself.

Examples
--------
>>> from design.recovery import plan_recovery
>>> from design.scenario import load_scenario
>>> s = load_scenario("paper-14")
>>> d = recovery_record(plan_recovery(s, [0]), s)
>>> d["scenario"], d["failed"], is_recovered(d)
('paper-14', [1], True)
"""

from __future__ import annotations

import numpy as np

from .closed_loop import ClosedLoop
from .gap import diverging_gaps, gap_possibilities, gap_report
from .scenario import uniform_delays

__all__ = ["DIVERGE", "hold_window_warnings", "analysis_record", "certificate_record",
           "recovery_record", "is_recovered", "recheck_design", "gap_design_warnings",
           "worse_than_no_correction"]

#: What a diverging gap means, said after each one.
DIVERGE = "the estimates diverge if the switch does not come within the hold window"


def hold_window_warnings(gaps) -> list:
    """A warning per gap loop (:class:`design.gap.GapLoop`) that diverges."""
    return [f"{line}: {DIVERGE}" for line in diverging_gaps(gaps)]


# -- socmon analyze -------------------------------------------------------------------

def analysis_record(analysis, G=None) -> dict:
    """``analysis.to_dict()`` (:func:`design.analysis.analyze`) with what any gain can do
    in the gaps (``gap_detectability``, ``own_loop_bound``: :func:`design.gap.gap_possibilities`)
    and, given gains ``G``, their gap loops with the scenario's delays (``gaps``) and a
    warning per diverging one."""
    scenario = analysis.scenario
    data = analysis.to_dict()
    possible, own = gap_possibilities(scenario)
    data["gap_detectability"] = possible
    data["own_loop_bound"] = {str(a): b for a, b in own.items()}
    if G is not None:
        gaps = gap_report(scenario, G, scenario.delays)
        data["gaps"] = [g.to_dict() for g in gaps]
        data["warnings"] = list(data["warnings"]) + hold_window_warnings(gaps)
    return data


# -- socmon certify -------------------------------------------------------------------

def certificate_record(certified: dict, scenario, G) -> dict:
    """The record of :func:`design.certificates.certify` (``certified``, extended in place
    and returned) with the gap loops of ``G`` at the scenario's delays (``gaps``), each
    row's gap radii with every link delayed by its tau (``gaps_rho_exact``, failed id ->
    radius) and a warning per diverging gap (``warnings``)."""
    gaps = gap_report(scenario, G, scenario.delays)
    certified["gaps"] = [g.to_dict() for g in gaps]
    for row in certified["rows"]:
        row["gaps_rho_exact"] = {
            str(g.failed): g.rho for g in gap_report(
                scenario, G, uniform_delays(scenario.W, row["tau"]), mse=False)}
    certified["warnings"] = hold_window_warnings(gaps)
    return certified


# -- socmon plan ----------------------------------------------------------------------

def recovery_record(plan, scenario, add_links: bool = True) -> dict:
    """The record of a :class:`design.recovery.RecoveryPlan`; ``no_new_links`` when the
    plan was not allowed to add links."""
    data = {"scenario": scenario.name, **plan.to_dict(scenario)}
    if not add_links:
        data["no_new_links"] = True
    return data


def is_recovered(d: dict) -> bool:
    """A :func:`recovery_record` recoverable with the links its plan may add (none with
    ``no_new_links``) and whose distributed pair is detectable afterwards, so that a
    stabilising gain exists.

    >>> is_recovered({"recoverable": True, "recoverable_without_new_links": False,
    ...               "no_new_links": True, "distributed_detectable_after": True})
    False
    """
    recoverable = (d["recoverable_without_new_links"] if d.get("no_new_links")
                   else d["recoverable"])
    return bool(recoverable and d.get("distributed_detectable_after", False))


# -- socmon design --------------------------------------------------------------------

def recheck_design(record: dict, scenario, D, G) -> dict:
    """``record`` (:meth:`design.gain_design.DesignResult.summary`) for the gain ``G`` as it
    will be used (read back from its file): its exact radius with delays ``D`` computed
    afresh (``rho_exact``, ``stable``) and the ``warnings`` it calls for
    (:func:`worse_than_no_correction`, :func:`gap_design_warnings`)."""
    rho = ClosedLoop(scenario.A, scenario.W, D, scenario.measure, G).spectral_radius()
    out = {**record, "rho_exact": rho, "stable": bool(rho < 1)}
    out["warnings"] = worse_than_no_correction(scenario, D, out) + gap_design_warnings(out)
    return out


def gap_design_warnings(record) -> list:
    """A warning per gap (single failure) whose loop diverges with the gain designed,
    saying whether no gain could have kept it stable.

    >>> gap_design_warnings({"gaps": [{"failed": 2, "stable": False, "rho_exact": 1.2}],
    ...                      "gap_design": {}})  # doctest: +NORMALIZE_WHITESPACE
    ['if agent 2 fails, the others run a loop of exact radius 1.2 until the switch:
      designed without the gap terms; the estimates diverge if the switch does not come
      within the hold window']
    """
    impossible = {g["failed"]: g["bound"]
                  for g in (record.get("gap_design") or {}).get("impossible", [])}
    out = []
    for g in record.get("gaps", []):
        if g["stable"]:
            continue
        why = (f"no gain can keep it stable (an unobservable mode of modulus "
               f"{impossible[g['failed']]:.4g})" if g["failed"] in impossible else
               "the gap terms could not keep it stable" if record["gap_design"] else
               "designed without the gap terms")
        out.append(f"if agent {g['failed']} fails, the others run a loop of exact radius "
                   f"{g['rho_exact']:.4g} until the switch: {why}; {DIVERGE}")
    return out


def worse_than_no_correction(scenario, D, record) -> list:
    """A warning when a radius-designed gain's exact steady MSE is above that of no
    correction at all (zero gains: each agent predicts, the loop is W (x) A), which is
    possible when A is stable: the radius objective does not design for the error."""
    mse = record.get("mse_steady_exact")
    if record.get("objective") != "rho" or mse is None or not np.isfinite(mse) \
            or not record["stable"]:
        return []
    zero = ClosedLoop(scenario.A, scenario.W, D, scenario.measure,
                      [np.zeros((scenario.n, len(m))) for m in scenario.measure])
    if not zero.spectral_radius() < 1:
        return []
    none = zero.mse_steady(scenario.process_noise, scenario.measurement_noise)
    if not mse > none:
        return []
    return [f"this gain's exact steady MSE ({mse:.6g}) is above that of no correction at "
            f"all (zero gains: {none:.6g}): the radius objective does not design for the "
            "error; --objective mse does"]
