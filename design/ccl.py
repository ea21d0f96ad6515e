"""The paper's Algorithm 1 (Appendix): LMI gain design by cone-complementarity linearisation.

For the delay-free closed loop ``Ahat = (I - K D_H)(W (x) A)`` with the structured gain
(block row i of ``K D_H (W (x) A)`` is ``G_i`` times the measured rows of block row i
of ``W (x) A``), the stability condition ``Ahat^T R^{-1} Ahat < R^{-1}`` is written with
``Q = R^{-1}`` as the two LMIs

    [[Q, Ahat^T], [Ahat, R]] >= eps I,      [[Q, I], [I, R]] >= 0,

and the non-convex ``Q R = I`` is approached by the cone-complementarity iteration of
El Ghaoui, Oustry and Ait Rami (1997): minimise ``trace(Q_t R + R_t Q)`` over the LMIs,
set ``(Q_t, R_t) = (Q, R)`` and repeat. The paper stops as soon as ``rho(Ahat) < 1``;
``keep_iterating`` continues until the trace reaches ``2 nN`` (within ``trace_tol``) or
``max_iter``. Every solve's status is recorded; a solve that does not end ``optimal``
raises :class:`SolverError`.

The problem is compiled once (``Q_t``, ``R_t`` are cvxpy Parameters, so each iteration
re-solves the same canonicalised problem).

Examples
--------
>>> import numpy as np
>>> lmi = CCLProblem(np.array([[1.2]]), np.array([[1.0]]), [(0,)])
>>> lmi.G[0].value = np.array([[0.5]])
>>> lmi.Q.value = np.array([[2.0]]); lmi.R.value = np.array([[0.5]])
>>> lmi.lmi_closed_loop.value          # [[Q, Ahat^T], [Ahat, R]] with Ahat = 0.6
array([[2. , 0.6],
       [0.6, 0.5]])
"""

from __future__ import annotations

import time

import numpy as np

from .closed_loop import spectral_radius
from .errors import SocmonError

__all__ = ["CCLProblem", "ccl_design", "SolverError", "SOLVERS"]

#: Conic solvers accepted by ``solver=``.
SOLVERS = ("CLARABEL", "SCS")


class SolverError(SocmonError):
    """A conic solve did not end ``optimal`` (infeasible, inaccurate, failed)."""

    def __init__(self, message, status=None, history=()):
        self.status = status
        self.history = list(history)
        super().__init__(message)


class CCLProblem:
    """The LMIs of the Appendix as a compiled cvxpy problem.

    Attributes
    ----------
    G : list of cvxpy Variables (n x p_i)
    Q, R : symmetric cvxpy Variables (nN x nN)
    Qt, Rt : symmetric cvxpy Parameters (the linearisation point)
    Ahat : cvxpy expression, the delay-free closed loop (affine in G)
    lmi_closed_loop, lmi_coupling : the two ``cp.bmat`` block matrices
    """

    def __init__(self, A, W, measure, eps: float = 1e-6):
        import cvxpy as cp

        A = np.asarray(A, dtype=float)
        W = np.asarray(W, dtype=float)
        n, N = A.shape[0], W.shape[0]
        m = n * N
        self.n, self.N, self.m = n, N, m
        self.measure = [tuple(int(j) for j in mi) for mi in measure]
        WA = np.kron(W, A)
        self.WA = WA
        self.G = [cp.Variable((n, len(mi)), name=f"G{i + 1}") for i, mi in enumerate(self.measure)]
        rows = []
        for i, mi in enumerate(self.measure):
            block = WA[i * n:(i + 1) * n, :]
            Ci = WA[i * n + np.asarray(mi, dtype=int), :]      # measured rows (p_i x nN)
            rows.append(block - self.G[i] @ Ci)
        self.Ahat = cp.vstack(rows)
        self.Q = cp.Variable((m, m), symmetric=True, name="Q")
        self.R = cp.Variable((m, m), symmetric=True, name="R")
        self.Qt = cp.Parameter((m, m), symmetric=True, name="Qt")
        self.Rt = cp.Parameter((m, m), symmetric=True, name="Rt")
        I = np.eye(m)
        self.lmi_closed_loop = cp.bmat([[self.Q, self.Ahat.T], [self.Ahat, self.R]])
        self.lmi_coupling = cp.bmat([[self.Q, I], [I, self.R]])
        self.eps = float(eps)
        # Q, R > 0 (the paper's third condition) follow from the first LMI with its
        # margin; stating them again adds two PSD cones and doubles the solve time.
        constraints = [
            self.lmi_closed_loop >> self.eps * np.eye(2 * m),
            self.lmi_coupling >> 0,
        ]
        self.constraints = constraints
        self.init_problem = cp.Problem(cp.Minimize(cp.trace(self.Q + self.R)), constraints)
        self.problem = cp.Problem(
            cp.Minimize(cp.trace(self.Qt @ self.R + self.Rt @ self.Q)), constraints
        )

    def gains(self) -> list:
        return [np.array(g.value, dtype=float) for g in self.G]

    def closed_loop_value(self) -> np.ndarray:
        """``Ahat`` at the current value of G (numpy)."""
        return np.asarray(self.Ahat.value, dtype=float)


def _solve(problem, solver, what, history, verbose=False, solver_options=None):
    import cvxpy as cp

    t0 = time.perf_counter()
    try:
        problem.solve(solver=solver, verbose=verbose, **(solver_options or {}))
    except cp.error.SolverError as exc:
        history.append({"solve": what, "status": "solver_error", "seconds": time.perf_counter() - t0})
        raise SolverError(f"{what}: solver {solver} failed ({exc})", "solver_error", history) from None
    status = problem.status
    entry = {"solve": what, "status": status, "seconds": time.perf_counter() - t0}
    history.append(entry)
    if status != cp.OPTIMAL:
        hint = ("the LMIs have no solution: no block-diagonal gain is certified for this "
                "network" if status in (cp.INFEASIBLE, cp.INFEASIBLE_INACCURATE)
                else f"try the other solver ({'/'.join(SOLVERS)}) or a larger margin")
        raise SolverError(f"{what}: solver {solver} returned status {status!r}: {hint}",
                          status, history)
    return entry


def ccl_design(A, W, measure, solver: str = "CLARABEL", max_iter: int = 50,
               keep_iterating: bool = False, eps: float = 1e-6, trace_tol: float = 1e-3,
               deadline=None, verbose: bool = False, solver_options=None,
               callback=None) -> dict:
    """Algorithm 1 of the paper; returns a dict with ``G``, ``rho_delay_free``, ``history``.

    Parameters
    ----------
    solver : "CLARABEL" or "SCS"
    max_iter : cone-complementarity iterations after the initial feasibility solve
    keep_iterating : continue after ``rho(Ahat) < 1`` until the trace is within
        ``trace_tol * 2nN`` of ``2nN`` (or ``max_iter``), keeping the lowest-rho gain
    eps : margin of the strict LMIs
    deadline : ``time.perf_counter()`` value after which no new solve starts
    solver_options : dict passed to the solver (e.g. ``{"max_iters": 10000}`` for SCS)
    callback : callable ``(iteration, rho_delay_free)`` called after every solve, or None

    Raises
    ------
    SolverError
        A solve ended with a status other than ``optimal``.
    ValueError
        Unknown solver.
    """
    solver = str(solver).upper()
    if solver not in SOLVERS:
        raise ValueError(f"solver: expected one of {', '.join(SOLVERS)}, got {solver!r}")
    lmi = CCLProblem(A, W, measure, eps=eps)
    history = []
    _solve(lmi.init_problem, solver, "initial feasibility solve", history, verbose,
           solver_options)
    G = lmi.gains()
    rho = spectral_radius(lmi.closed_loop_value())
    history[-1].update({"iteration": 0, "rho_delay_free": rho})
    if callback is not None:
        callback(0, float(rho))
    best = (rho, G)
    target = 2.0 * lmi.m
    iterations = 0
    reason = "max iterations"
    if rho < 1 and not keep_iterating:
        reason = "rho(Ahat) < 1"
    else:
        Qk, Rk = lmi.Q.value, lmi.R.value
        for it in range(1, max_iter + 1):
            if deadline is not None and time.perf_counter() > deadline:
                reason = "time limit"
                break
            lmi.Qt.value = 0.5 * (Qk + Qk.T)
            lmi.Rt.value = 0.5 * (Rk + Rk.T)
            _solve(lmi.problem, solver, f"iteration {it}", history, verbose, solver_options)
            iterations = it
            Qk, Rk = lmi.Q.value, lmi.R.value
            G = lmi.gains()
            rho = spectral_radius(lmi.closed_loop_value())
            trace = float(lmi.problem.value)
            history[-1].update({"iteration": it, "trace": trace, "rho_delay_free": rho})
            if callback is not None:
                callback(it, float(rho))
            if rho < best[0]:
                best = (rho, G)
            if rho < 1 and not keep_iterating:
                reason = "rho(Ahat) < 1"
                break
            if keep_iterating and abs(trace - target) <= trace_tol * target:
                reason = "trace reached 2nN"
                break
    rho_best, G_best = best if keep_iterating else (rho, G)
    return {"G": G_best, "rho_delay_free": float(rho_best), "history": history,
            "iterations": iterations, "reason": reason}
