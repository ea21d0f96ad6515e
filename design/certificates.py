"""Stability and error certificates of a gain (what ``socmon certify`` reports).

For a scenario and a gain ``G`` (per agent ``G_i = K^i H_i^T``):

* **exact radius** of the delayed closed loop (:class:`design.closed_loop.ClosedLoop`)
  for the scenario's own delays and, per row, for every inter-agent link delayed by
  ``tau`` (self links undelayed, as in the estimator); < 1 is the exact certificate;
* **the paper's Theorem 1 criterion** ``rho((I - K D_H)(W (x) A^(tau+1))) < 1`` per row
  and ``tau_star``, the largest tau such that it holds for every tau' = 0..tau
  (searched consecutively from 0 up to ``tau_cap``; ``tau_star_capped`` says the cap was
  reached, so the true value is at least the cap);
* **the paper's table formula** ``rho(Ahat)^(1/(tau+1))`` (Tables 2-4), labelled as the
  paper's: it is not a certificate for the compensated estimator (NOTES section 3);
* **the exact steady MSE** ``trace(P) / (nN)`` of the delay-free loop (discrete Lyapunov)
  and of the loop with the scenario's delays (exact, noise window included), each
  when that loop is stable;
* **the paper's Phi** (Remark 2): ``(alpha1 N ||Q|| + alpha2 ||R||) / (N beta)`` with
  ``alpha1 = ||I - K D_H||^2``, ``alpha2 = ||K||^2`` (``K^i = G_i H_i``, the smallest
  ``K^i`` that gives ``G_i``) and, since the paper leaves ``beta`` unspecified, the
  choice ``beta = 1 - ||Ahat||_2^2``: from ``E|e_k|^2 <= ||Ahat||^2 E|e_{k-1}|^2 +
  E|eta|^2`` this is the contraction that makes Phi a bound-like figure. It exists only
  when ``||Ahat||_2 < 1``; otherwise Phi is None and ``phi_note`` says why.

Examples
--------
>>> import numpy as np
>>> from design.scenario import load_scenario
>>> s = load_scenario("paper-14")
>>> G = [np.zeros((14, 1)) for _ in range(3)]
>>> c = certify(s, G, taus=[0, 3])
>>> round(c["rho_delay_free"], 4), c["tau_star"], c["rows"][1]["tau"]
(1.0857, None, 3)
"""

from __future__ import annotations

import math

import numpy as np

from .closed_loop import ClosedLoop, spectral_radius, theorem1_matrix
from .errors import SocmonError
from .gains import check_gains_fit
from .scenario import uniform_delays

__all__ = [
    "CertifyError",
    "DEFAULT_TAUS",
    "DEFAULT_TAU_CAP",
    "paper_formula",
    "theorem1_radius",
    "find_tau_star",
    "paper_phi",
    "certify",
]

DEFAULT_TAUS = (0, 3, 7, 15)
#: Largest tau examined when searching the Theorem 1 tau_star.
DEFAULT_TAU_CAP = 100


class CertifyError(SocmonError):
    """Bad certificate request (negative or non-integer tau, bad cap)."""


def paper_formula(rho_delay_free: float, tau: int) -> float:
    """The paper's table value ``rho(Ahat)^(1/(tau+1))`` (Tables 2-4; not a certificate).

    >>> round(paper_formula(0.871, 3), 3), round(paper_formula(0.461, 5), 3)
    (0.966, 0.879)
    """
    return float(rho_delay_free) ** (1.0 / (int(tau) + 1))


def theorem1_radius(A, W, measure, G, tau: int) -> float:
    """``rho((I - K D_H)(W (x) A^(tau+1)))``: Theorem 1 holds at tau iff it is < 1."""
    return spectral_radius(theorem1_matrix(A, W, measure, G, int(tau)))


def find_tau_star(A, W, measure, G, cap: int = DEFAULT_TAU_CAP):
    """Largest tau in 0..cap with Theorem 1 holding at every tau' <= tau.

    Returns
    -------
    (tau_star, capped) : (int or None, bool)
        ``tau_star`` is None when the criterion fails already at tau = 0; ``capped`` is
        True when it holds up to ``cap`` (so the true tau_star is at least ``cap``).
    """
    if not isinstance(cap, (int, np.integer)) or isinstance(cap, bool) or cap < 0:
        raise CertifyError(f"tau_cap: must be a non-negative integer, got {cap!r}")
    for tau in range(int(cap) + 1):
        if not theorem1_radius(A, W, measure, G, tau) < 1.0:
            return (tau - 1 if tau > 0 else None), False
    return int(cap), True


def paper_phi(loop: ClosedLoop, q: float, r: float) -> dict:
    """The paper's Phi (Remark 2) for the delay-free ``loop``, with its ingredients.

    ``beta = 1 - ||Ahat||_2^2`` (the module docstring says why); ``phi`` is None when
    ``||Ahat||_2 >= 1``.

    >>> import numpy as np
    >>> loop = ClosedLoop(np.array([[1.0]]), np.eye(1), np.zeros((1, 1), int), [(0,)],
    ...                   [np.array([[0.5]])])
    >>> d = paper_phi(loop, q=0.1, r=0.1)     # Ahat = 0.5: (0.25*0.1 + 0.25*0.1) / 0.75
    >>> round(d["phi"], 6)
    0.066667
    """
    Ahat = loop.F(0)
    norm_Ahat = float(np.linalg.norm(Ahat, 2))
    alpha1 = max(float(np.linalg.norm(L, 2)) for L in loop.L) ** 2
    alpha2 = max(float(np.linalg.norm(g, 2)) if g.size else 0.0 for g in loop.G) ** 2
    N = loop.N
    out = {
        "phi_alpha1": alpha1,
        "phi_alpha2": alpha2,
        "norm_Ahat": norm_Ahat,
        "phi_beta_choice": "beta = 1 - ||Ahat||_2^2 (the paper leaves beta unspecified)",
    }
    if norm_Ahat < 1.0:
        beta = 1.0 - norm_Ahat**2
        out["phi_beta"] = beta
        out["phi"] = (alpha1 * N * q + alpha2 * r) / (N * beta)
        out["phi_note"] = "paper's Remark 2 approximation, not an exact figure"
    else:
        out["phi_beta"] = None
        out["phi"] = None
        out["phi_note"] = (
            f"||Ahat||_2 = {norm_Ahat:.4g} >= 1: beta = 1 - ||Ahat||^2 is not positive, "
            "so Phi is undefined for this gain (rho(Ahat) < 1 does not imply ||Ahat|| < 1)"
        )
    return out


def _check_taus(taus) -> list:
    out = []
    for t in taus:
        if isinstance(t, bool) or not isinstance(t, (int, np.integer)) or t < 0:
            raise CertifyError(f"taus: each tau must be a non-negative integer, got {t!r}")
        out.append(int(t))
    return out


def certify(scenario, G, taus=DEFAULT_TAUS, tau_cap: int = DEFAULT_TAU_CAP,
            progress=None) -> dict:
    """All certificates of gain ``G`` on ``scenario`` (JSON-ready apart from numpy scalars).

    Parameters
    ----------
    scenario : Scenario
    G : list of (n, p_i) arrays
    taus : iterable of int
        Uniform inter-agent delays for the rows.
    tau_cap : int
        Upper end of the Theorem 1 tau_star search.
    progress : callable or None
        Called with a short text before each stage (the tau_star search, each row), for a
        status line; the function prints nothing itself.

    Returns
    -------
    dict
        Keys (docs/json.md) ``rho_delay_free``, ``rho_exact`` and ``stable`` (with the
        scenario's ``delays``), ``scenario_taubar``, ``stable_delay_free``, ``tau_star``,
        ``tau_star_cap``, ``tau_star_capped``, ``rows`` (each ``tau``, ``rho_exact``,
        ``stable``, ``mse_steady_exact``, ``paper_formula``, ``theorem1_rho``,
        ``theorem1_holds``), ``mse_steady_delay_free``, ``mse_steady_exact``, ``phi`` and
        its ingredients, and ``notes``.
    """
    s = scenario
    taus = _check_taus(taus)
    check_gains_fit(G, s)
    say = progress or (lambda text: None)
    A, W, measure = s.A, s.W, s.measure
    q, r = s.process_noise, s.measurement_noise
    zero = np.zeros_like(s.delays)
    free = ClosedLoop(A, W, zero, measure, G)
    Ahat = free.F(0)
    rho_free = spectral_radius(Ahat)
    own = ClosedLoop(A, W, s.delays, measure, G)
    rho_own = own.spectral_radius() if s.taubar else rho_free
    say(f"Theorem 1 criterion for tau = 0..{tau_cap}")
    tau_star, capped = find_tau_star(A, W, measure, G, tau_cap)
    rows = []
    for i, tau in enumerate(taus):
        say(f"tau = {tau} ({i + 1} of {len(taus)}): exact radius and steady MSE")
        loop = ClosedLoop(A, W, uniform_delays(W, tau), measure, G)
        rho_exact = loop.spectral_radius() if tau else rho_free
        t1 = theorem1_radius(A, W, measure, G, tau)
        rows.append({
            "tau": tau,
            "rho_exact": rho_exact,
            "stable": rho_exact < 1.0,
            "mse_steady_exact": loop.mse_steady(q, r) if rho_exact < 1.0 else None,
            "paper_formula": paper_formula(rho_free, tau),
            "theorem1_rho": t1,
            "theorem1_holds": t1 < 1.0,
        })
    out = {
        "scenario": s.name,
        "scenario_digest": s.digest(),
        "delays": s.delays.tolist(),
        "rho_delay_free": rho_free,
        "rho_exact": rho_own,
        "scenario_taubar": s.taubar,
        "stable_delay_free": rho_free < 1.0,
        "stable": rho_own < 1.0,
        "tau_star": tau_star,
        "tau_star_cap": int(tau_cap),
        "tau_star_capped": capped,
        "rows": rows,
        "mse_steady_delay_free": free.mse_steady(q, r) if rho_free < 1 else None,
        "mse_steady_exact": own.mse_steady(q, r) if rho_own < 1 else None,
    }
    out.update(paper_phi(free, q, r))
    out["notes"] = [
        "rho_exact: exact spectral radius of the delayed closed loop, every inter-agent "
        "link delayed by tau (self links undelayed); < 1 certifies stability",
        "paper_formula: the paper's table value rho(Ahat)^(1/(tau+1)); not a certificate",
        "theorem1: the paper's criterion rho((I - K D_H)(W (x) A^(tau+1))) < 1; tau_star "
        f"is the largest tau with it holding for all tau' <= tau, searched up to {tau_cap}",
        "mse: trace(P)/(nN) of the exact steady error covariance (discrete Lyapunov); "
        "None when the loop is unstable",
    ]
    if not math.isfinite(rho_free):
        out["notes"].append("rho_delay_free is not finite: check the gains")
    return out
