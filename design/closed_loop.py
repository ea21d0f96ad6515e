"""The exact error dynamics of the distributed estimator, with link delays.

Per agent i, with ``L_i = I - G_i H_i`` (``G_i = K^i H_i^T``, n x p_i), the estimator of
:mod:`design.estimator` has the exact error recursion (e = x - xhat, stacked over agents)

    e_k = sum_{r=0..taubar} F_r e_{k-1-r}  +  sum_{s=0..taubar} B_s nu_{k-1-s}  -  G zeta_k

    F_r = L (W_r (x) A^(r+1)),   B_s = L (c_s (x) A^s),   c_s[i] = sum_{j: tau_ij >= s} w_ij

where ``W_r`` keeps the links of W with delay r (self links have delay 0) and ``L``, ``G``
are block-diagonal. The process noise enters through a moving average over the delay
window: a delayed estimate propagated by ``A^(1+tau)`` misses the noise of the steps in
between. The companion matrix of order (taubar+1) nN is the exact closed loop; its
spectral radius < 1 is the exact stability certificate, and the steady covariance of the
state augmented with the noise window solves a discrete Lyapunov equation.

Examples
--------
>>> import numpy as np
>>> A = np.array([[1.1]]); W = np.array([[1.0]])
>>> loop = ClosedLoop(A, W, np.zeros((1, 1), int), [(0,)], [np.array([[0.5]])])
>>> round(loop.spectral_radius(), 6)     # (1 - 0.5) * 1.1
0.55
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .errors import GainsError, SocmonError

__all__ = [
    "ClosedLoop",
    "closed_loop_for",
    "delay_free_matrix",
    "theorem1_matrix",
    "spectral_radius",
    "DENSE_EIG_MAX_ORDER",
    "LoopPerformance",
    "exact_performance",
    "EXACT_MSE_MAX_ORDER",
    "STRUCTURED_MIN_ORDER",
]

#: Largest order of the noise state space (companion order + the process-noise window)
#: whose steady MSE :func:`exact_performance` computes (by the structured impulse sum
#: above :data:`STRUCTURED_MIN_ORDER`: communities-32, order 2,176, in 0.2 s).
EXACT_MSE_MAX_ORDER = 200_000
#: Above this order the loop is applied through its sparse and low-rank factors
#: (:class:`design.structured.LoopOperator`): the impulse sum for the MSE, and ARPACK
#: for the radius when W's links are sparse (:attr:`ClosedLoop.sparse_links`). Below it,
#: dense eigenvalues and a dense Lyapunov solve (communities-16 at 2-step delays, order
#: 1,728: 41 s dense, 0.1 s structured, agreeing to 1e-14).
STRUCTURED_MIN_ORDER = 600
#: Above this companion order the spectral radius of a dense matrix is computed by ARPACK.
DENSE_EIG_MAX_ORDER = 2000
#: Largest order for which a stalled ARPACK run falls back to dense eigenvalues.
DENSE_FALLBACK_MAX_ORDER = 8000
#: ARPACK runs from two starting vectors must agree on the radius to this relative
#: tolerance; else with more Arnoldi vectors, else the dense eigenvalues decide.
ARPACK_AGREE_RTOL = 1e-10
#: :meth:`ClosedLoop.count_outside` samples its circle at up to this many points ...
COUNT_MAX_POINTS = 1024
#: ... and pays (:attr:`ClosedLoop.count_pays`) for loops of at most this many estimated
#: states nN (a linear solve of that order per point) with delays of at least
#: :data:`COUNT_MIN_TAUBAR` steps (below, the dense eigenvalue problem costs as little).
COUNT_MAX_STATES = 160
COUNT_MIN_TAUBAR = 3
#: points of the circle solved at once (memory: about 50 x nN^2 bytes a point)
COUNT_CHUNK = 64


def spectral_radius(M, dense=None) -> float:
    """Largest eigenvalue modulus of a dense or sparse square matrix (or LinearOperator;
    ``dense``: a function giving it as a dense array, for the fallback)."""
    order = M.shape[0]
    if order == 0:
        return 0.0
    if not (sp.issparse(M) or isinstance(M, spla.LinearOperator)) and order <= DENSE_EIG_MAX_ORDER:
        return float(np.max(np.abs(sla.eigvals(np.asarray(M), check_finite=True))))
    if order <= DENSE_EIG_MAX_ORDER and sp.issparse(M):
        return float(np.max(np.abs(sla.eigvals(M.toarray()))))
    # Many eigenvalues of (nearly) equal modulus, e.g. the (tau+1)-th roots that long
    # uniform delays produce, can stall Arnoldi or make it settle on a Ritz value just
    # inside the true radius (seen: 0.97984 and 0.97998 for 0.98 at order 2562, varying
    # with ARPACK's random start). Two deterministic starts must agree; else more
    # Arnoldi vectors; else the dense QR algorithm decides.
    starts = [np.ones(order), np.random.default_rng(0).standard_normal(order)]
    why = "the runs from two starting vectors disagreed"
    for k, ncv in ((6, 40), (20, 120)):
        k = min(k, order - 2)
        try:
            radii = [float(np.max(np.abs(spla.eigs(
                M, k=k, which="LM", ncv=min(order - 1, max(4 * k + 1, ncv)), tol=1e-12,
                maxiter=1000, v0=v0, return_eigenvectors=False)))) for v0 in starts]
        except spla.ArpackNoConvergence:
            why = "ARPACK did not converge"
            break
        if abs(radii[0] - radii[1]) <= ARPACK_AGREE_RTOL * max(radii):
            return max(radii)
    if order > DENSE_FALLBACK_MAX_ORDER or (isinstance(M, spla.LinearOperator)
                                             and dense is None):
        raise SocmonError(
            f"spectral radius: {why} on a matrix of order {order} "
            f"(dense fallback is limited to order {DENSE_FALLBACK_MAX_ORDER})"
        )
    if dense is not None:
        Md = dense()
    else:
        Md = M.toarray() if sp.issparse(M) else np.asarray(M)
    return float(np.max(np.abs(sla.eigvals(Md))))


class ClosedLoop:
    """Exact delayed error dynamics for one gain, one W and one delay matrix.

    Parameters
    ----------
    A : (n, n) array
    W : (N, N) row-stochastic array
    delays : (N, N) int array, ``delays[i, j]`` on link j -> i
    measure : sequence of sequences of node indices (0-based), one per agent
    G : sequence of arrays, ``G[i]`` of shape (n, p_i): agent i's ``K^i H_i^T``
    rho : float, optional
        The exact spectral radius of this very loop when it is known already (a design
        that certified it): :meth:`spectral_radius` then returns it instead of computing
        it again.
    """

    def __init__(self, A, W, delays, measure, G, *, rho: float | None = None):
        self.A = np.asarray(A, dtype=float)
        self.W = np.asarray(W, dtype=float)
        self.delays = np.asarray(delays, dtype=int)
        self.measure = [tuple(int(j) for j in m) for m in measure]
        self.G = [np.asarray(g, dtype=float) for g in G]
        n, N = self.A.shape[0], self.W.shape[0]
        if len(self.measure) != N or len(self.G) != N:
            raise GainsError(
                f"gains: {len(self.G)} gain blocks and {len(self.measure)} sensor sets "
                f"for N = {N} agents"
            )
        for i, (g, m) in enumerate(zip(self.G, self.measure)):
            if g.shape != (n, len(m)):
                raise GainsError(
                    f"gains: K{i + 1} must be {n} x {len(m)} (n x nodes measured by agent "
                    f"{i + 1}), got {g.shape[0]} x {g.shape[1] if g.ndim > 1 else 1}"
                )
            if not np.all(np.isfinite(g)):
                raise GainsError(f"gains: K{i + 1} has non-finite entries")
        self.n, self.N = n, N
        self.taubar = int(self.delays.max()) if self.delays.size else 0
        self._rho = None if rho is None else float(rho)

    # -- building blocks ------------------------------------------------------------
    @cached_property
    def A_powers(self) -> list:
        """``[A^0, A^1, ..., A^(taubar+1)]``."""
        P = [np.eye(self.n)]
        for _ in range(self.taubar + 1):
            P.append(P[-1] @ self.A)
        return P

    @cached_property
    def L(self) -> list:
        """``L_i = I - G_i H_i`` per agent."""
        out = []
        for g, m in zip(self.G, self.measure):
            Li = np.eye(self.n)
            Li[:, list(m)] -= g
            out.append(Li)
        return out

    @cached_property
    def LA_powers(self) -> list:
        """``LA[i][r] = L_i A^(r)`` for r = 0..taubar+1 (only the powers in use are filled)."""
        used = {0, 1} | {int(t) + 1 for t in np.unique(self.delays)}
        return [
            {r: self.L[i] @ self.A_powers[r] for r in used} for i in range(self.N)
        ]

    def F(self, r: int) -> np.ndarray:
        """Block matrix ``F_r = L (W_r (x) A^(r+1))`` of order nN."""
        n, N = self.n, self.N
        out = np.zeros((n * N, n * N))
        for i in range(N):
            for j in range(N):
                if self.W[i, j] > 0 and self.delays[i, j] == r:
                    out[i * n:(i + 1) * n, j * n:(j + 1) * n] = (
                        self.W[i, j] * self.LA_powers[i][r + 1]
                    )
        return out

    @cached_property
    def lags(self) -> list:
        """Delays r for which ``F_r`` is non-zero."""
        return sorted({int(self.delays[i, j]) for i in range(self.N) for j in range(self.N)
                       if self.W[i, j] > 0})

    @property
    def order(self) -> int:
        return (self.taubar + 1) * self.n * self.N

    def companion(self, sparse: bool | None = None):
        """Companion matrix of order (taubar+1) nN: first block row [F_0 ... F_taubar]."""
        m = self.n * self.N
        T = self.taubar
        if sparse is None:
            sparse = self.order > DENSE_EIG_MAX_ORDER
        if not sparse:
            M = np.zeros((self.order, self.order))
            for r in self.lags:
                M[:m, r * m:(r + 1) * m] = self.F(r)
            if T:
                M[m:, : T * m] = np.eye(T * m)
            return M
        blocks = [[None] * (T + 1) for _ in range(T + 1)]
        for r in range(T + 1):
            blocks[0][r] = sp.csr_matrix(self.F(r)) if r in self.lags else None
        for r in range(1, T + 1):
            blocks[r][r - 1] = sp.identity(m, format="csr")
        if blocks[0][0] is None:
            blocks[0][0] = sp.csr_matrix((m, m))
        return sp.bmat(blocks, format="csr")

    # -- certificates -----------------------------------------------------------------
    @cached_property
    def operator(self):
        """The loop applied through its sparse and low-rank factors
        (:class:`design.structured.LoopOperator`)."""
        from .structured import LoopOperator

        return LoopOperator(self)

    @property
    def sparse_links(self) -> bool:
        """True when W has at most a quarter of the N^2 possible links: above
        :data:`STRUCTURED_MIN_ORDER` the radius is then ARPACK's on the structured loop
        (dense eigenvalues otherwise, up to :data:`DENSE_EIG_MAX_ORDER`)."""
        return int(np.count_nonzero(self.W > 0)) <= 0.25 * self.N ** 2

    def components(self) -> list:
        """The agents (rows) of each strongly connected component of the network's links
        (``W[i, j] > 0``, any delay), numbered by their smallest row."""
        from .graph import canonical_components, influence_graph

        k, labels, _ = canonical_components(influence_graph(self.W))
        return [np.flatnonzero(labels == c).tolist() for c in range(k)]

    def spectral_radius(self) -> float:
        """Exact spectral radius of the delayed closed loop (computed once).

        When the network's links are not strongly connected (the gap loop of a ring
        without its failed agent is a chain), the loop is block triangular in the order of
        its components: the determinant of its matrix polynomial
        ``lambda^(T+1) I - sum_r lambda^(T-r) F_r`` is the product of the components' own,
        so its spectrum is the union of theirs and the radius is the largest of the
        components' radii, each the exact radius of the component's own delayed loop (its
        agents, their gains and the links among them). communities-32: a gap loop of
        order 2,040 is 30 dense eigenvalue problems of order 68."""
        if self._rho is None:
            parts = self.components() if self.N > 1 else [[0]]
            if len(parts) > 1:
                self._rho = max(self.part(rows).spectral_radius() for rows in parts)
            elif self.order > STRUCTURED_MIN_ORDER and self.sparse_links:
                self._rho = spectral_radius(self.operator.linear_operator(),
                                            dense=lambda: self.companion(sparse=False))
            elif self.taubar == 0:
                self._rho = spectral_radius(self.F(0))
            else:
                self._rho = spectral_radius(self.companion())
        return self._rho

    def part(self, rows) -> "ClosedLoop":
        """The loop of the agents ``rows`` alone: their gains and the links among them
        (the weights and delays as they are; a diagonal block of the companion's matrix
        polynomial)."""
        ix = np.ix_(rows, rows)
        return ClosedLoop(self.A, self.W[ix], self.delays[ix],
                          [self.measure[i] for i in rows], [self.G[i] for i in rows])

    def is_stable(self, margin: float = 0.0) -> bool:
        return self.spectral_radius() < 1.0 - margin

    def count_outside(self, c: float, max_points: int = COUNT_MAX_POINTS) -> int | None:
        """How many eigenvalues of the delayed loop have a modulus above ``c`` (with their
        multiplicity), counted by the argument principle; None when the count does not
        settle within ``max_points`` points of the circle (an eigenvalue on or near it).

        The eigenvalues are the roots of ``det(lambda^(T+1) I - sum_r lambda^(T-r) F_r)
        = lambda^((T+1) nN) q(1/lambda)`` with the polynomial ``q(w) = det Q(w)``, ``Q(w)
        = I - sum_r w^(r+1) F_r`` (``q(0) = 1``): those of modulus above ``c`` are the zeros
        of ``q`` inside ``|w| < 1/c``, ``(1/2 pi i) oint q'/q dw``, the mean over the
        circle of ``w tr(Q(w)^-1 Q'(w))``. The trapezoid sum converges geometrically when
        no zero is near the circle (the error of a zero at ``w0`` is about
        ``(|w0| c)^(-K)`` for ``K`` points, ``(|w0| c)^K`` inside); it is taken on nested grids of 32, 64, ...
        points (half of them: ``Q`` is real, its values at conjugate points conjugate)
        until two consecutive sums agree on an integer. A solve of order nN a point instead
        of an eigenvalue problem of order (T+1) nN: Sampson-like at 15-step delays (nN =
        72, order 1,152) 25-90 ms against 0.35-0.4 s.

        >>> A = np.array([[1.1]]); W = np.array([[1.0]])
        >>> loop = ClosedLoop(A, W, np.zeros((1, 1), int), [(0,)], [np.array([[0.5]])])
        >>> loop.count_outside(0.6), loop.count_outside(0.5)     # the one eigenvalue: 0.55
        (0, 1)
        """
        c = float(c)
        if not c > 0:
            raise ValueError(f"count_outside: the radius must be positive, got {c!r}")
        m = self.n * self.N
        lags = np.array(self.lags, dtype=float)
        F = np.stack([self.F(int(r)) for r in self.lags]).astype(complex)

        def integrand(k, K):
            # w tr(Q^-1 Q'(w)) = -tr(Q^-1 sum_r (r+1) w^(r+1) F_r) at w_k = e^(2 pi i k/K)/c,
            # COUNT_CHUNK points at a time (three complex arrays of nN x nN a point)
            out = []
            for part in np.array_split(np.asarray(k, dtype=float),
                                       max(1, -(-len(k) // COUNT_CHUNK))):
                w = np.exp(2j * np.pi * part / K) / c
                coef = w[:, None] ** (lags[None, :] + 1.0)
                Q = np.eye(m) - np.einsum("kl,lij->kij", coef, F)
                dQ = np.einsum("kl,lij->kij", coef * (lags[None, :] + 1.0), F)
                try:
                    X = np.linalg.solve(Q, dQ)
                except np.linalg.LinAlgError:
                    return None
                out.append(-np.trace(X, axis1=1, axis2=2))
            return np.concatenate(out)

        # the sum over k = 0..K-1 is g_0 + g_(K/2) + 2 Re sum_(0<k<K/2) g_k
        K = 32
        g = integrand(np.arange(K // 2 + 1), K)
        if g is None:
            return None
        total = g[0].real + g[-1].real + 2.0 * g[1:-1].real.sum()
        previous = None
        with np.errstate(all="ignore"):
            while True:
                value = total / K
                if not np.isfinite(value):
                    return None
                n = round(value)
                if (previous is not None and n >= 0 and abs(value - n) < 1e-7
                        and abs(previous - n) < 1e-2):
                    return int(n)
                if 2 * K > max_points:
                    return None
                previous, K = value, 2 * K
                g = integrand(np.arange(1, K // 2, 2), K)     # the new points, odd k
                if g is None:
                    return None
                total += 2.0 * g.real.sum()

    @property
    def count_pays(self) -> bool:
        """True when :meth:`count_outside` costs less than the exact radius: at most
        :data:`COUNT_MAX_STATES` estimated states and delays of at least
        :data:`COUNT_MIN_TAUBAR` steps, radius not known yet."""
        return (self._rho is None and self.taubar >= COUNT_MIN_TAUBAR
                and self.n * self.N <= COUNT_MAX_STATES)

    # -- noise and steady error -----------------------------------------------------
    def noise_input(self, q: float, r: float):
        """``(B, Gz)``: process-noise blocks ``B_s`` (nN x n, s = 0..taubar) and ``G``.

        ``B[s] = L (c_s (x) A^s)`` with ``c_s[i] = sum_{j: tau_ij >= s} w_ij`` (the blocks
        of :mod:`design.structured`, made dense).
        """
        op = self.operator
        return [op.apply_L(C.toarray()) for C in op.C], op.Gb.toarray()

    def noise_state_space(self, q: float, r: float):
        """``(M, B, C)``: the error as a linear system driven by unit-variance white noise.

        ``x_{k+1} = M x_k + B w_k``, ``e_k = C x_k`` with ``w_k = (nu_k / sqrt(q),
        zeta_{k+1} / sqrt(r))``: the process noise (n components) and the readings' noise of
        the next step (p components, entering as ``-G zeta``). Without delays ``x = e``
        and ``M = F_0``; with delays ``x = (e_k, ..., e_{k-T}, nu_{k-1}, ..., nu_{k-T})``,
        the companion state augmented with the process-noise window, and ``M`` has the
        spectral radius of the companion matrix. The steady error covariance is
        ``C P C^T`` with ``P = M P M^T + B B^T``.
        """
        m, n, T = self.n * self.N, self.n, self.taubar
        Bs, Gz = self.noise_input(q, r)
        if T == 0:
            M, Bin, Gin = self.F(0), Bs[0], Gz
        else:
            # fresh inputs nu_k, zeta_{k+1}
            order = (T + 1) * m + T * n
            M = np.zeros((order, order))
            M[: (T + 1) * m, : (T + 1) * m] = self.companion(sparse=False)
            nu0 = (T + 1) * m
            for s in range(1, T + 1):
                M[:m, nu0 + (s - 1) * n: nu0 + s * n] = Bs[s]
            if T > 1:
                M[nu0 + n:, nu0: nu0 + (T - 1) * n] = np.eye((T - 1) * n)
            Bin = np.zeros((order, n))
            Bin[:m] = Bs[0]
            Bin[nu0: nu0 + n] = np.eye(n)
            Gin = np.zeros((order, Gz.shape[1]))
            Gin[:m] = Gz
        B = np.hstack([np.sqrt(q) * Bin, -np.sqrt(r) * Gin])
        C = np.eye(m, M.shape[0])
        return M, B, C

    def steady_error_covariance(self, q: float, r: float) -> np.ndarray:
        """Steady covariance (nN x nN) of the stacked error with ``Q = qI``, ``R = rI``.

        Solves the discrete Lyapunov equation of :meth:`noise_state_space` (the companion
        system augmented with the process-noise window). Raises ValueError if the loop is
        not stable.
        """
        rho = self.spectral_radius()
        if not rho < 1:
            raise ValueError(f"closed loop is not stable (rho = {rho:.6g}): no steady error")
        M, B, C = self.noise_state_space(q, r)
        P = _solve_lyapunov(M, B @ B.T)
        return C @ P @ C.T

    def mse_steady(self, q: float, r: float) -> float:
        """Steady mean-squared error per agent and per state: ``trace(P) / (nN)`` (above
        :data:`STRUCTURED_MIN_ORDER`, by the impulse sum of :mod:`design.structured`).
        Raises ValueError if the loop is not stable."""
        if self.order + self.taubar * self.n > STRUCTURED_MIN_ORDER:
            from .structured import impulse_mse

            rho = self.spectral_radius()
            if not rho < 1:
                raise ValueError(f"closed loop is not stable (rho = {rho:.6g}): no steady "
                                 "error")
            return impulse_mse(self.operator, q, r)
        P = self.steady_error_covariance(q, r)
        return float(np.trace(P) / (self.n * self.N))


def _solve_lyapunov(M, S):
    P = sla.solve_discrete_lyapunov(M, S)
    return 0.5 * (P + P.T)


@dataclass(frozen=True)
class LoopPerformance:
    """The exact performance of a loop: its spectral radius and steady MSE (None when the
    loop is not stable, or too large to solve: ``why`` says which)."""

    rho: float
    mse: float | None
    why: str = ""

    @property
    def stable(self) -> bool:
        return bool(self.rho < 1)

    @property
    def mse_or_inf(self) -> float:
        """The MSE, inf when there is none (a run summary's and the chaos bounds' value)."""
        return float("inf") if self.mse is None else self.mse


def exact_performance(scenario, G, delays=None, mse: bool = True) -> LoopPerformance:
    """The one definition of "the exact radius, and the steady MSE if stable" of
    ``scenario``'s loop with gains ``G`` and ``delays`` (default: the scenario's).

    ``mse=False`` skips the Lyapunov solve. The MSE is left out (None, ``why`` says so)
    above :data:`EXACT_MSE_MAX_ORDER`.

    >>> import numpy as np
    >>> from design.scenario import scenario_from_dict
    >>> s = scenario_from_dict({"social": {"A": [[1.1]]}, "agents": {"measure": [["1"]]}})
    >>> p = exact_performance(s, [np.array([[0.5]])])
    >>> round(p.rho, 6), p.mse > 0, exact_performance(s, [np.array([[0.0]])]).why
    (0.55, True, 'not stable')
    """
    if isinstance(delays, str):
        from .scenario import resolve_delays

        delays = resolve_delays(scenario, delays)
    loop = closed_loop_for(scenario, G, delays)
    rho = float(loop.spectral_radius())
    if not rho < 1:
        return LoopPerformance(rho, None, "not stable")
    if not mse:
        return LoopPerformance(rho, None, "not computed")
    if loop.order + loop.taubar * loop.n > EXACT_MSE_MAX_ORDER:
        return LoopPerformance(rho, None, f"order above {EXACT_MSE_MAX_ORDER}")
    return LoopPerformance(rho, loop.mse_steady(scenario.process_noise,
                                                scenario.measurement_noise))


def closed_loop_for(scenario, G, delays=None) -> ClosedLoop:
    """The :class:`ClosedLoop` of ``scenario`` with gains ``G`` and ``delays``.

    ``delays`` defaults to the scenario's own delay matrix.
    """
    D = scenario.delays if delays is None else delays
    return ClosedLoop(scenario.A, scenario.W, D, scenario.measure, G)


def delay_free_matrix(A, W, measure, G) -> np.ndarray:
    """``Ahat = (I - K D_H)(W (x) A)``, the delay-free closed loop."""
    return ClosedLoop(A, W, np.zeros(np.shape(W), int), measure, G).F(0)


def theorem1_matrix(A, W, measure, G, tau: int) -> np.ndarray:
    """The paper's Theorem 1 matrix ``(I - K D_H)(W (x) A^(tau+1))``.

    Theorem 1's criterion is ``rho(theorem1_matrix) < 1``; it is exact (to the power
    tau+1) only when every link, self links included, carries delay tau.
    """
    loop = ClosedLoop(A, W, np.zeros(np.shape(W), int), measure, G)
    Ap = np.linalg.matrix_power(loop.A, tau + 1)
    n, N = loop.n, loop.N
    out = np.zeros((n * N, n * N))
    for i in range(N):
        LAp = loop.L[i] @ Ap
        for j in range(N):
            if loop.W[i, j] > 0:
                out[i * n:(i + 1) * n, j * n:(j + 1) * n] = loop.W[i, j] * LAp
    return out
