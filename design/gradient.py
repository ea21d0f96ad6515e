"""First-order gain design on the exact delayed closed loop.

The free numbers are the gains ``G_i`` (n x p_i); ``G_i`` enters only block row i of the
first block row of the companion matrix (see :mod:`design.closed_loop`):

    M[rows_i, :] = L_i R_i,   L_i = I - G_i H_i,
    R_i = [ w_ij A^(tau_ij + 1) at column block (tau_ij, j) ]    (the companion part)

so ``dM[rows_i, :] = -dG_i (H_i R_i)`` and every derivative below is a sum over agents.

Spectral radius
    For a simple eigenvalue ``lambda`` with right vector v and left vector u
    (``u^H M = lambda u^H``), ``d lambda = u^H dM v / (u^H v)``, hence

        d|lambda| / dG_i = -Re( conj(lambda)/|lambda| * conj(u_i) (H_i R_i v)^T / (u^H v) ).

    ``spectral_radius_and_gradient`` returns the exact radius and the gradient of the top
    eigenvalue's modulus (optionally a soft maximum over the top few, ``smooth > 0``).

Steady MSE
    The error augmented with the process-noise window obeys ``z+ = Ma z + Bin nu + Gin zeta``
    (the construction of :meth:`ClosedLoop.steady_error_covariance`). With
    ``P = Ma P Ma^T + S``, ``S = q Bin Bin^T + r Gin Gin^T`` and ``J = trace(C P)``,
    ``C = E^T E / (nN)`` (E picks the current error), the adjoint ``X = Ma^T X Ma + C``
    gives ``dJ = <2 X Ma P, dMa> + <X, dS>``. Block row i of ``Ma`` is ``L_i Ra_i``, of
    ``Bin`` is ``L_i`` and of ``Gin`` is ``G_i`` at agent i's columns, so

        dJ/dG_i = -(2 X Ma P)[rows_i] (H_i Ra_i)^T - 2q (X Bin)[rows_i] H_i^T
                  + 2r (X Gin)[rows_i, cols_i].

Both gradients are checked against finite differences in ``tests/test_gain_design.py``.
The optimiser is BFGS with a weak Wolfe line search, which is known to behave well on
the nonsmooth spectral radius (Lewis and Overton, 2013); unstable trial points are
rejected by the line search (their value is +inf for the MSE objective).

Examples
--------
>>> import numpy as np
>>> model = LoopModel(np.array([[1.1]]), np.array([[1.0]]), np.zeros((1, 1), int), [(0,)])
>>> rho, grad = model.spectral_radius_and_gradient(np.array([0.5]))
>>> round(rho, 6), np.round(grad, 6)            # rho = 1.1 (1 - g)
(0.55, array([-1.1]))
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .closed_loop import DENSE_FALLBACK_MAX_ORDER, ClosedLoop
from .errors import SocmonError
from .gap import gap_weights
from .observability import all_modes_stable, distributed_detectability
from .structured import block_gain, lag_blocks, noise_blocks

__all__ = ["LoopModel", "bfgs_minimise", "OptimResult", "DENSE_SPECTRUM_MAX_ORDER"]

#: Up to this companion order the spectrum is computed densely (all eigenpairs);
#: above it, ARPACK computes a few eigenpairs of largest modulus, warm started.
DENSE_SPECTRUM_MAX_ORDER = 400
#: Up to this nN the impulse-response MSE uses dense lag and gain matrices (sparse
#: products cost more than they save on small blocks).
SPARSE_IMPULSE_MIN_ORDER = 300
#: Steps between two checkpoints of a large loop's impulse response (see mse_impulse).
IMPULSE_SEGMENT = 32
#: ARPACK restarts before falling back to the dense eigensolver for good.
ARPACK_MAX_RESTARTS = 60


class LoopModel:
    """The closed loop of one (A, W, delays, measure) as a function of the gains.

    Parameters
    ----------
    A, W, delays, measure
        As for :class:`design.closed_loop.ClosedLoop`.

    Notes
    -----
    The gains are packed in one vector ``x``: ``G_1`` flattened row-major, then ``G_2``,
    and so on (``n * sum(p_i)`` numbers).
    """

    def __init__(self, A, W, delays, measure):
        self.A = np.asarray(A, dtype=float)
        self.W = np.asarray(W, dtype=float)
        self.delays = np.asarray(delays, dtype=int)
        self.measure = [tuple(int(j) for j in m) for m in measure]
        self.n, self.N = self.A.shape[0], self.W.shape[0]
        self.m = self.n * self.N
        self.taubar = int(self.delays.max()) if self.delays.size else 0
        self.order = (self.taubar + 1) * self.m
        self.sizes = [self.n * len(mi) for mi in self.measure]
        self.offsets = np.concatenate([[0], np.cumsum(self.sizes)]).astype(int)
        self.size = int(self.offsets[-1])
        P = [np.eye(self.n)]
        for _ in range(self.taubar + 1):
            P.append(P[-1] @ self.A)
        self.A_powers = P
        # links[i] = [(j, tau, w)]
        self.links = [
            [(j, int(self.delays[i, j]), float(self.W[i, j])) for j in range(self.N)
             if self.W[i, j] > 0]
            for i in range(self.N)
        ]
        # measured rows of A^(tau+1) per link: (p_i x n)
        self._HA = [
            [(j, tau, w * self.A_powers[tau + 1][list(self.measure[i]), :])
             for (j, tau, w) in self.links[i]]
            for i in range(self.N)
        ]
        self.dense_only = False
        self._v0 = None     # ARPACK warm starts
        self._u0 = None

    # -- packing ----------------------------------------------------------------------
    def unpack(self, x) -> list:
        """Vector -> list of ``G_i`` (n x p_i)."""
        x = np.asarray(x, dtype=float)
        return [x[self.offsets[i]:self.offsets[i + 1]].reshape(self.n, len(self.measure[i]))
                for i in range(self.N)]

    def pack(self, G) -> np.ndarray:
        """List of ``G_i`` -> vector."""
        return np.concatenate([np.asarray(g, dtype=float).ravel() for g in G]) \
            if self.N else np.zeros(0)

    def closed_loop(self, x) -> ClosedLoop:
        return ClosedLoop(self.A, self.W, self.delays, self.measure, self.unpack(x))

    # -- spectral radius --------------------------------------------------------------
    def _top_eigenpairs(self, M, k, dense=None):
        """Top-``k`` eigenvalues by modulus with right (columns) and left vectors (``M``:
        a matrix or a LinearOperator; ``dense``: a function giving it dense, for the
        fallback)."""
        order = M.shape[0]
        if order <= DENSE_SPECTRUM_MAX_ORDER or order - 2 <= k or self.dense_only:
            return _dense_top_eigenpairs(M if dense is None else dense(), k)
        want = k
        k = min(max(k, 6), order - 2)             # Arnoldi converges better on a few
        ncv = min(order - 1, max(3 * k + 1, 30))
        # fixed first starts: without one ARPACK draws a random vector, and a design
        # (a BFGS path through a nonsmooth radius) would differ from run to run
        start = np.cos(np.arange(order) + 0.5) + 1.0
        # eigenvalues of nearly equal modulus (typical near a minimum of the radius) stall
        # Arnoldi: once more with three times the Arnoldi vectors, then dense from now on
        # for this model (where the order allows it: dense is O(order^3))
        for wide in (1, 3):
            n_cv = min(order - 1, wide * ncv)
            try:
                lam, vr = spla.eigs(M, k=k, which="LM", ncv=n_cv, tol=1e-10,
                                    v0=start if self._v0 is None else self._v0,
                                    maxiter=ARPACK_MAX_RESTARTS * wide)
                mu, vl = spla.eigs(M.T, k=k, which="LM", ncv=n_cv, tol=1e-10,
                                   v0=start if self._u0 is None else self._u0,
                                   maxiter=ARPACK_MAX_RESTARTS * wide)
                break
            except spla.ArpackNoConvergence:
                continue
        else:
            if order > DENSE_FALLBACK_MAX_ORDER:
                raise SocmonError(f"the radius's eigenvectors: ARPACK did not converge on "
                                  f"the loop of order {order} (dense fallback is limited "
                                  f"to order {DENSE_FALLBACK_MAX_ORDER})")
            self.dense_only = True
            return _dense_top_eigenpairs(M if dense is None else dense(), want)
        idx = np.argsort(-np.abs(lam), kind="stable")[:want]
        lam, vr = lam[idx], vr[:, idx]
        # left vectors: M^T y = mu y  <=>  u = conj(y) satisfies u^H M = mu u^H
        left = np.empty_like(vr)
        for c, l in enumerate(lam):
            d = int(np.argmin(np.abs(mu - l)))
            left[:, c] = np.conj(vl[:, d])
        self._v0 = np.real(vr[:, 0]) + np.imag(vr[:, 0])
        self._u0 = np.real(left[:, 0]) + np.imag(left[:, 0])
        return lam, vr, left

    def spectral_radius_and_gradient(self, x, smooth: float = 0.0, k: int = 6):
        """Exact radius of the delayed closed loop and the gradient of the top modulus.

        Parameters
        ----------
        x : gains vector
        smooth : float
            0: gradient of the largest modulus (an eigenvalue of a complex pair gives the
            same modulus gradient as its conjugate). > 0: gradient of the soft maximum
            ``smooth * log sum exp(|lambda_k| / smooth)`` over the top ``k`` eigenvalues
            (the returned value is then that soft maximum).
        """
        loop = self.closed_loop(x)
        kk = max(1, min(k if smooth > 0 else 1, loop.order))
        if loop.order <= DENSE_SPECTRUM_MAX_ORDER or self.dense_only:
            M = loop.F(0) if self.taubar == 0 else loop.companion(sparse=False)
            lam, vr, vl = self._top_eigenpairs(M, kk)
        else:
            # through the loop's sparse and low-rank factors (design.structured)
            lam, vr, vl = self._top_eigenpairs(loop.operator.linear_operator(), kk,
                                               dense=lambda: loop.companion(sparse=False))
        mod = np.abs(lam)
        rho = float(mod.max())
        if smooth > 0:
            wts = np.exp((mod - rho) / smooth)
            value = rho + smooth * float(np.log(wts.sum()))
            wts = wts / wts.sum()
        else:
            wts = np.zeros(len(lam))
            wts[int(np.argmax(mod))] = 1.0
            value = rho
        grad = np.zeros(self.size)
        for c in np.flatnonzero(wts > 1e-12):
            grad += wts[c] * self._modulus_gradient(lam[c], vr[:, c], vl[:, c])
        return value, grad

    def _modulus_gradient(self, lam, v, u):
        n, m = self.n, self.m
        uv = np.vdot(u, v)          # u^H v
        if lam == 0 or uv == 0:
            return np.zeros(self.size)
        phase = np.conj(lam) / abs(lam)
        g = np.zeros(self.size)
        for i in range(self.N):
            w = np.zeros(len(self.measure[i]), dtype=complex)
            for (j, tau, HA) in self._HA[i]:
                w += HA @ v[tau * m + j * n: tau * m + (j + 1) * n]
            ui = u[i * n:(i + 1) * n]
            gi = -np.real(phase * np.outer(np.conj(ui), w) / uv)
            g[self.offsets[i]:self.offsets[i + 1]] = gi.ravel()
        return g

    def spectral_radius(self, x) -> float:
        """Exact radius (through :class:`ClosedLoop`)."""
        return self.closed_loop(x).spectral_radius()

    # -- steady MSE -------------------------------------------------------------------
    def _augmented(self, x, q, r):
        """``(Ma, Bin, Gin, Ra)``: augmented closed loop, noise inputs, pre-L row blocks."""
        loop = self.closed_loop(x)
        n, m, T, N = self.n, self.m, self.taubar, self.N
        order = (T + 1) * m + T * n
        nu0 = (T + 1) * m
        # pre-L row blocks Ra_i (n x order)
        Ra = []
        for i in range(N):
            Ri = np.zeros((n, order))
            for (j, tau, w) in self.links[i]:
                Ri[:, tau * m + j * n: tau * m + (j + 1) * n] += w * self.A_powers[tau + 1]
            for s in range(1, T + 1):
                c = sum(w for (_, tau, w) in self.links[i] if tau >= s)
                if c:
                    Ri[:, nu0 + (s - 1) * n: nu0 + s * n] = c * self.A_powers[s]
            Ra.append(Ri)
        Ma = np.zeros((order, order))
        for i in range(N):
            Ma[i * n:(i + 1) * n] = loop.L[i] @ Ra[i]
        if T:
            Ma[m:(T + 1) * m, :T * m] = np.eye(T * m)
        if T > 1:
            Ma[nu0 + n:, nu0: nu0 + (T - 1) * n] = np.eye((T - 1) * n)
        Bin = np.zeros((order, n))
        c0 = np.array([sum(w for (_, _, w) in self.links[i]) for i in range(N)])
        for i in range(N):
            Bin[i * n:(i + 1) * n] = c0[i] * loop.L[i]
        if T:
            Bin[nu0: nu0 + n] = np.eye(n)
        p = sum(len(mi) for mi in self.measure)
        Gin = np.zeros((order, p))
        col = 0
        for i, g in enumerate(loop.G):
            Gin[i * n:(i + 1) * n, col:col + g.shape[1]] = g
            col += g.shape[1]
        return Ma, Bin, Gin, Ra, c0

    def mse_and_gradient(self, x, q: float, r: float, rho_max: float = 1.0,
                         method: str = "lyapunov", bound: float = np.inf):
        """Steady MSE ``trace(P)/(nN)`` and its gradient; ``(inf, None)`` if unstable.

        ``method="lyapunov"``: two dense Lyapunov solves of the augmented loop; stability
        judged on the exact radius (``< rho_max``). ``method="impulse"``:
        :meth:`mse_impulse` (no eigenvalues, no dense solve; a loop whose impulse
        response has not settled within the step budget of ``rho_max``, or whose sum
        passes ``bound``, is ``inf``).
        """
        if method == "impulse":
            steps = _impulse_steps(rho_max, self.taubar)
            J, g, _ = self.mse_impulse(x, q, r, max_steps=steps, bound=bound)
            return J, g
        Ma, Bin, Gin, Ra, c0 = self._augmented(x, q, r)
        n, m, N = self.n, self.m, self.N
        rho = float(np.max(np.abs(sla.eigvals(Ma[: (self.taubar + 1) * m,
                                                  : (self.taubar + 1) * m]))))
        if not rho < rho_max:
            return np.inf, None
        S = q * (Bin @ Bin.T) + r * (Gin @ Gin.T)
        P = _dlyap(Ma, S)
        C = np.zeros_like(Ma)
        C[:m, :m] = np.eye(m) / m
        X = _dlyap(Ma.T, C)
        J = float(np.trace(P[:m, :m]) / m)
        Gam = 2.0 * (X[:m] @ Ma) @ P          # rows of 2 X Ma P that G touches
        XB = X[:m] @ Bin
        XG = X[:m] @ Gin
        grad = np.zeros(self.size)
        col = 0
        for i in range(N):
            rows = slice(i * n, (i + 1) * n)
            mi = list(self.measure[i])
            gi = -Gam[rows] @ Ra[i][mi].T
            gi -= 2.0 * q * c0[i] * XB[rows][:, mi]
            gi += 2.0 * r * XG[rows, col:col + len(mi)]
            col += len(mi)
            grad[self.offsets[i]:self.offsets[i + 1]] = gi.ravel()
        return J, grad


    # -- steady MSE by the impulse response (structured, no dense Lyapunov solve) ------
    def _impulse_setup(self):
        """x-independent blocks: ``R_r = W_r (x) A^(r+1)`` per lag and ``Q_s = c_s (x) A^s``."""
        if getattr(self, "_imp", None) is not None:
            return self._imp
        n, m = self.n, self.m
        # sparse: W's links times A's pattern (never a dense nN x nN block per lag)
        R = lag_blocks(self.W, self.delays, self.A_powers)
        Q = [C.toarray() for C in noise_blocks(self.W, self.delays, self.A_powers)]
        rows = np.array([i * n + v for i, mi in enumerate(self.measure) for v in mi], dtype=int)
        lags = sorted(R)
        if m <= SPARSE_IMPULSE_MIN_ORDER:       # small: dense products cost less
            R = {r: R[r].toarray() for r in lags}
        self._imp = {"R": [(r, R[r], R[r].T.copy() if isinstance(R[r], np.ndarray)
                            else R[r].T.tocsr()) for r in lags],
                     "Q": Q, "rows": rows}
        return self._imp

    def mse_impulse(self, x, q: float, r: float, max_steps: int = 20000, tol: float = 1e-13,
                    bound: float = np.inf):
        """Steady MSE and its gradient from the impulse response of the delayed loop.

        ``e_k = sum_t h_t w_(k-t)`` with ``h_0 = [0, -G]``, ``h_t = L u_t``,
        ``u_t = sum_r R_r h_(t-1-r) + [Q_(t-1), 0]``; ``J = sum_t trace(h_t S h_t^T) / (nN)``,
        ``S = diag(q I, r I)``. The sum stops when the last ``taubar + 1`` terms (the whole
        state of the loop) hold less than ``tol`` of it; the gradient is the exact
        gradient of that truncated sum (backward recursion for the adjoint). Cost per
        step: one product per lag on (nN x (n + p)) blocks, instead of dense solves of
        order (taubar + 1) nN + taubar n.

        Returns ``(J, grad, steps)``; ``(inf, None, steps)`` when the sum passes
        ``bound`` or has not settled after ``max_steps`` steps (an unstable loop, or one
        too close to the unit circle for this budget).
        """
        n, m, T, N = self.n, self.m, self.taubar, self.N
        imp = self._impulse_setup()
        rows, Rl, Q = imp["rows"], imp["R"], imp["Q"]
        G = self.unpack(x)
        p = rows.size
        # L = I - Gb Hb applied as such (Hb picks the measured rows): O(n p) a column
        Gs = block_gain(G)
        Gb = Gs.toarray()
        if m <= SPARSE_IMPULSE_MIN_ORDER:
            Gs = Gb
        GsT = Gs.T.copy() if isinstance(Gs, np.ndarray) else Gs.T.tocsr()
        # The response is carried with its columns scaled by S^(1/2): the recursion is
        # linear in the columns, so the weighted energy trace(h S h^T) is a plain sum of
        # squares, and the adjoint of the scaled response gives the same gradient
        # (lam u^T = (lam S^(-1/2)) (u S^(1/2))^T)
        sq, sr = np.sqrt(q), np.sqrt(r)
        Qs = [sq * Qk for Qk in Q]
        h0 = np.zeros((m, n + p))
        h0[:, n:] = -sr * Gb
        # Gb u[rows] and the gradient's products agent by agent, as batched products of
        # (N, n, pmax) and (N, pmax, n + p) arrays: agent i's gain against its p_i
        # measured rows of u, padded with zeros to the largest p_i
        sizes = [len(mi) for mi in self.measure]
        pmax = max(sizes, default=0)
        pad = np.full((N, pmax), p, dtype=int)         # index p: a row of zeros
        Gpad = np.zeros((N, n, pmax))
        for i, k in enumerate(np.cumsum([0] + sizes[:-1])):
            pad[i, :sizes[i]] = np.arange(k, k + sizes[i])
            Gpad[i, :, :sizes[i]] = G[i]
        # one scratch block for every step: a fresh nN x (n + p) array a step cost page
        # faults (the allocator hands blocks of this size back to the system when freed)
        buf = np.empty((m, n + p))
        buf3 = buf.reshape(N, n, n + p)
        zero_row = np.zeros((1, n + p))

        def step(t, H):
            """``(h_t, u_t[rows])`` from the earlier responses in ``H`` (the measured
            rows by agent, (N, pmax, n + p))."""
            u = None
            for (lag, Rr, _) in Rl:
                if t - 1 - lag >= 0:
                    term = Rr @ H[t - 1 - lag]      # a new array: summed in place
                    if u is None:
                        u = term
                    else:
                        u += term
            if u is None:
                u = np.zeros((m, n + p))
            if t - 1 <= T:
                u[:, :n] += Qs[t - 1]
            ur = np.concatenate([u[rows], zero_row])[pad]
            np.matmul(Gpad, ur, out=buf3)
            u -= buf                        # h_t = L u_t = u_t - Gb u_t[rows], in place
            return u, ur

        # Large loops keep the response only at checkpoints (the T + 1 steps before every
        # IMPULSE_SEGMENT-th step) and recompute a segment at a time for the backward
        # pass: the same operations, so the same numbers, in a fraction of the memory
        # (communities-64: 13 MB a step, about 400 steps)
        seg = IMPULSE_SEGMENT if m > SPARSE_IMPULSE_MIN_ORDER else None

        def kept(k):
            return seg is None or k == 0 or -(-(k + 1) // seg) * seg <= k + 1 + T

        H, U = {0: h0}, [None]
        terms = [float(np.vdot(h0, h0))]     # trace(h S h^T): the columns are scaled
        total = terms[0]
        window = terms[0]
        t = 0
        while True:
            t += 1
            h, ur = step(t, H)
            H[t] = h
            U.append(ur)                    # only the measured rows enter the gradient
            if t - T - 1 >= 0 and not kept(t - T - 1):
                del H[t - T - 1]            # no later step reads it
            e = float(np.vdot(h, h))
            total += e
            window += e
            if t > T:
                window -= terms[t - T - 1]
            terms.append(e)
            if t > T + 1 and window <= tol * total:
                break
            if total / m > bound or not np.isfinite(total) or t >= max_steps:
                return np.inf, None, t
        J = total / m
        # adjoint: lam_t = (2/m) h_t S + sum_r R_r^T mu_(t+1+r),  mu_t = L^T lam_t
        # (scaled as the response: lam_t S^(-1/2))
        mu = {}
        acc = np.zeros((N, n, pmax))
        lam = None
        length = t + 1 if seg is None else seg
        for a in range((t // length) * length, -1, -length):
            b = min(a + length, t + 1)
            for k in range(a, b):           # the segment again, from its checkpoint
                if k not in H:
                    H[k] = step(k, H)[0]
            for s in range(b - 1, a - 1, -1):
                lam = None
                for (lag, _, RrT) in Rl:
                    if s + 1 + lag <= t:
                        term = RrT @ mu[s + 1 + lag]
                        if lam is None:
                            lam = term
                        else:
                            lam += term
                if lam is None:
                    lam = (2.0 / m) * H[s]
                else:
                    lam += np.multiply(H[s], 2.0 / m, out=buf)
                if s >= 1:
                    acc += np.matmul(lam.reshape(N, n, n + p), U[s].transpose(0, 2, 1))
                    U[s] = None
                    lam[rows] -= GsT @ lam      # mu_s = L^T lam_s (lam_s not needed after)
                    mu[s] = lam
                mu.pop(s + T + 1, None)     # no earlier step reads it
                if seg is not None and s > 0:
                    del H[s]
        # lam is lam_0 here: its noise columns, unscaled, are the gradient through h_0
        grad = np.zeros(self.size)
        col = 0
        for i, g in enumerate(G):
            pi = g.shape[1]
            gi = -acc[i, :, :pi] - sr * lam[i * n:(i + 1) * n, n + col:n + col + pi]
            grad[self.offsets[i]:self.offsets[i + 1]] = gi.ravel()
            col += pi
        return J, grad, t



def _impulse_steps(rho_max, taubar):
    """Step budget of the impulse-response sum: a loop of radius ``rho_max`` has decayed
    by 1e-14 in energy after this many steps (at least 200, at most 50,000)."""
    if not rho_max < 1:
        return 50_000
    steps = int(np.ceil(np.log(1e-14) / (2.0 * np.log(rho_max)))) + 2 * (taubar + 1)
    return int(min(max(steps, 200), 50_000))


def _dense_top_eigenpairs(M, k):
    """Top-``k`` eigenvalues by modulus (dense QR, eigenvalues only) and their right and
    left vectors by two steps of inverse iteration on one LU of ``M - lambda I``: about
    half the cost of ``eig`` with both sets of vectors for the few pairs needed."""
    Md = M.toarray() if sp.issparse(M) else np.asarray(M)
    lam = sla.eigvals(Md)
    idx = np.argsort(-np.abs(lam), kind="stable")[:k]
    lam = lam[idx]
    order = Md.shape[0]
    vr = np.empty((order, len(lam)), dtype=complex)
    vl = np.empty((order, len(lam)), dtype=complex)
    b = np.cos(np.arange(order) + 0.5) + 1.0     # fixed start, not orthogonal to a vector
    scale = max(1.0, float(np.abs(Md).max()))
    exact = None                                  # (values, left, right) of eig, if needed
    for c, mu in enumerate(lam):
        shifted = Md - mu * np.eye(order)
        with warnings.catch_warnings(), np.errstate(divide="ignore", invalid="ignore"):
            # an exactly singular shift is expected (mu is an eigenvalue) and handled here
            warnings.simplefilter("ignore", sla.LinAlgWarning)
            lu = sla.lu_factor(shifted, check_finite=False)
            piv = np.abs(np.diag(lu[0]))
            if piv.min() == 0:                    # exactly singular: nudge the shift
                lu = sla.lu_factor(shifted - (1e-14 * scale) * np.eye(order),
                                   check_finite=False)
            v, u = b.astype(complex), b.astype(complex)
            for _ in range(2):
                v = sla.lu_solve(lu, v, check_finite=False)
                v /= np.linalg.norm(v)
                u = sla.lu_solve(lu, u, trans=2, check_finite=False)
                u /= np.linalg.norm(u)
        if not (np.all(np.isfinite(v)) and np.all(np.isfinite(u))):
            # inverse iteration broke down (a shift singular even after the nudge, e.g. a
            # zero eigenvalue of a rank-deficient loop): take the vectors from eig
            if exact is None:
                exact = sla.eig(Md, left=True, right=True)
            i = int(np.argmin(np.abs(exact[0] - mu)))
            v, u = exact[2][:, i], exact[1][:, i]
        vr[:, c], vl[:, c] = v, u
    return lam, vr, vl


def _dlyap(M, S):
    """``P = M P M^T + S`` (symmetrised)."""
    P = sla.solve_discrete_lyapunov(M, S)
    return 0.5 * (P + P.T)


# ---------------------------------------------------------------------------------
# BFGS with a weak Wolfe line search


@dataclass
class OptimResult:
    x: np.ndarray
    f: float
    iterations: int
    evaluations: int
    reason: str
    history: list = field(default_factory=list)


def bfgs_minimise(fg, x0, max_iter=200, stop=None, deadline=None, f_tol=1e-9,
                  patience=20, patience_tol=1e-4, step0=None, label="",
                  callback=None, bounded=False) -> OptimResult:
    """Minimise ``fg(x) -> (f, g)`` by BFGS with a weak Wolfe line search.

    ``f`` may be ``inf`` (rejected trial point). ``stop(f)`` ends the run early when it
    returns True; ``deadline`` is a ``time.perf_counter()`` value. The run also ends when
    the last ``patience`` iterations lowered ``f`` by less than ``patience_tol * |f|`` in
    total (a nonsmooth minimum is approached slowly). ``callback(iteration, f)`` is
    called with the start value (iteration 0) and after every accepted iteration; it
    must not change anything. Deterministic.

    ``bounded``: call ``fg(x, bound)`` instead, ``bound`` the largest value the line
    search can accept at ``x`` (its sufficient-decrease threshold; ``inf`` for the start):
    ``fg`` may answer ``inf`` (and any gradient) as soon as it knows its value is above
    it, e.g. a sum of positive terms that passed it, and skip the rest, the gradient
    included. The iterates are the same: such a point is rejected either way.
    """
    x = np.asarray(x0, dtype=float).copy()
    f, g = fg(x, np.inf) if bounded else fg(x)
    evals = 1
    history = [{"stage": label, "iteration": 0, "value": float(f)}]
    if callback is not None:
        callback(0, float(f))
    if not np.isfinite(f):
        return OptimResult(x, f, 0, evals, "infeasible start", history)
    if stop is not None and stop(f):
        return OptimResult(x, f, 0, evals, "target reached", history)
    dim = x.size
    Hinv = None
    reason = "max iterations"
    stall = 0
    it = 0
    for it in range(1, max_iter + 1):
        gn = float(np.linalg.norm(g))
        if gn == 0 or not np.isfinite(gn):
            reason = "zero gradient"
            break
        if Hinv is None:
            scale = step0 if step0 is not None else 0.1 * max(1.0, np.linalg.norm(x)) / gn
            Hinv = scale * np.eye(dim)
        d = -Hinv @ g
        gd = float(g @ d)
        if gd >= 0:
            Hinv = (0.1 * max(1.0, np.linalg.norm(x)) / gn) * np.eye(dim)
            d = -Hinv @ g
            gd = float(g @ d)
        t, xt, ft, gt, ne = _weak_wolfe(fg, x, f, g, d, gd, bounded=bounded)
        evals += ne
        if xt is None:
            # no decrease along d: restart from steepest descent once, then give up
            if stall:
                reason = "line search failed"
                break
            stall = 1
            Hinv = None
            continue
        stall = 0
        s, y = xt - x, gt - g
        sy = float(s @ y)
        decrease = f - ft
        x, f, g = xt, ft, gt
        history.append({"stage": label, "iteration": it, "value": float(f), "step": float(t)})
        if callback is not None:
            callback(it, float(f))
        if sy > 1e-12 * np.linalg.norm(s) * np.linalg.norm(y):
            _bfgs_update(Hinv, s, y, 1.0 / sy)
        if stop is not None and stop(f):
            reason = "target reached"
            break
        if decrease <= f_tol * max(1.0, abs(f)):
            reason = "converged (no decrease)"
            break
        if patience and len(history) > patience and (
                history[-1 - patience]["value"] - f <= patience_tol * max(abs(f), 1e-12)):
            reason = f"converged (relative decrease < {patience_tol:g} in {patience} iterations)"
            break
        if deadline is not None and time.perf_counter() > deadline:
            reason = "time limit"
            break
    return OptimResult(x, f, it, evals, reason, history)


def _bfgs_update(Hinv, s, y, rho):
    """The BFGS update of the inverse Hessian, in place:
    ``Hinv - rho (s Hy^T + Hy s^T) + (rho^2 y^T Hy + rho) s s^T``, ``Hy = Hinv y``.

    Three rank-one updates by BLAS ``dger`` on Hinv's own memory: the same matrix as the
    formula with ``np.outer`` (to rounding), without its five temporaries of Hinv's size
    (communities-32: 2,176^2 entries, 38 MB each, fresh pages every iteration: about
    40 ms an iteration, a second of a refined design)."""
    Hy = Hinv @ y
    c = rho * rho * float(y @ Hy) + rho
    # dger updates a column-major matrix: Hinv.T is Hinv's memory as one (its transpose
    # gets the transposed updates, and the sum of the three is symmetric)
    At = Hinv.T
    for alpha, u, v in ((-rho, s, Hy), (-rho, Hy, s), (c, s, s)):
        out = sla.blas.dger(alpha, u, v, a=At, overwrite_a=True)
        if out is not At and not np.shares_memory(out, Hinv):    # pragma: no cover
            Hinv[...] = out.T       # a BLAS wrapper that copied: keep the result anyway


def _weak_wolfe(fg, x, f, g, d, gd, c1=1e-4, c2=0.9, max_evals=30, bounded=False):
    """Lewis-Overton bracketing line search; returns (t, x_t, f_t, g_t, evals).

    If the weak Wolfe conditions are not met within ``max_evals`` the best trial point
    with sufficient decrease is returned, or ``x_t = None`` when there is none.
    ``bounded``: ``fg(x_t, f + c1 t gd)``, see :func:`bfgs_minimise`.
    """
    lo, hi, t = 0.0, np.inf, 1.0
    best = None
    for ne in range(1, max_evals + 1):
        xt = x + t * d
        ft, gt = fg(xt, f + c1 * t * gd) if bounded else fg(xt)
        if not np.isfinite(ft) or ft > f + c1 * t * gd:
            hi = t
        else:
            if best is None or ft < best[2]:
                best = (t, xt, ft, gt)
            if float(gt @ d) < c2 * gd:
                lo = t
            else:
                return t, xt, ft, gt, ne
        t = 0.5 * (lo + hi) if np.isfinite(hi) else 2.0 * t
        if hi - lo < 1e-14 * max(1.0, lo):
            break
    if best is not None:
        return (*best, ne)
    return 0.0, None, f, g, ne


class GapTerms:
    """The gap loops of a design as functions of the whole gain vector.

    One :class:`LoopModel` per single failure (N >= 2). The gains vector
    is the design's (all N agents packed as :meth:`LoopModel.pack` does); a gap's model
    sees it without the failed agent's block. :meth:`drop_impossible` removes the gaps
    whose distributed pair is not detectable (no gain makes them stable) and lists them
    in ``impossible`` as ``(failed id, largest unobservable modulus)``: a staircase per
    gap, so only for the gaps that need it.

    :meth:`penalty_and_gradient` is the exact penalty ``sum_f max(0, rho_f - threshold)``
    with the gradient of each gap's top eigenvalue modulus (eigenvalue sensitivity, as
    for the nominal radius), or of a soft maximum of its top moduli.
    """

    def __init__(self, scenario, delays):
        self.scenario = scenario
        D = np.asarray(delays, dtype=int)
        N = len(scenario.measure)
        sizes = [scenario.n * len(m) for m in scenario.measure]
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
        self.size = int(offsets[-1])
        self.models, self.impossible = [], []
        for f in range(N if N >= 2 else 0):
            keep, W2 = gap_weights(scenario.W, f)
            model = LoopModel(scenario.A, W2, D[np.ix_(keep, keep)],
                              [scenario.measure[r] for r in keep])
            index = np.concatenate([np.arange(offsets[r], offsets[r + 1]) for r in keep])
            self.models.append((f + 1, model, index))

    def drop_impossible(self, failed_ids) -> None:
        """Check the detectability of the gaps of ``failed_ids``; drop those without."""
        for f in sorted(set(failed_ids)):
            keep, W2 = gap_weights(self.scenario.W, f - 1)
            measure = [self.scenario.measure[r] for r in keep]
            if all_modes_stable(self.scenario.A, W2, measure):
                continue                # detectable at once: every mode of W2 (x) A stable
            d = distributed_detectability(self.scenario.A, W2, measure)
            if not d.detectable:
                self.impossible.append((f, float(d.max_unobservable_modulus)))
                self.models = [t for t in self.models if t[0] != f]

    @staticmethod
    def worst(radii: dict) -> float:
        return max(radii.values()) if radii else 0.0

    def radii(self, x) -> dict:
        """Failed id -> exact radius of its gap loop (the gaps still in the terms)."""
        x = np.asarray(x, dtype=float)
        return {f: float(m.spectral_radius(x[idx])) for f, m, idx in self.models}

    def penalty_and_gradient(self, x, threshold: float, smooth: float = 0.0, k: int = 12):
        """``(P, dP/dx, radii)``, ``P = sum_f max(0, rho_f - threshold)``; with
        ``smooth > 0``, ``rho_f`` is the soft maximum of the top ``k`` moduli
        (:meth:`LoopModel.spectral_radius_and_gradient`), above the radius by at most
        ``smooth * log k``."""
        x = np.asarray(x, dtype=float)
        total, grad, radii = 0.0, np.zeros(self.size), {}
        for f, model, idx in self.models:
            rho, g = model.spectral_radius_and_gradient(x[idx], smooth=smooth, k=k)
            radii[f] = float(rho)
            if rho > threshold:
                total += rho - threshold
                grad[idx] += g
        return total, grad, radii
