"""The delayed closed loop applied without forming it: cost that follows the structure.

The loop of :mod:`design.closed_loop` has two structures a dense matrix throws away:

- ``F_r = L K_r`` with ``K_r = W_r (x) A^(r+1)``: as sparse as W's links times A's
  pattern (communities-32: 10,752 non-zeros, against 4.7 million entries dense);
- ``L = I - Gb Hb``: identity minus a block-diagonal gain (n x p_i blocks) times a row
  selection, a low-rank correction of p = sum p_i columns.

:class:`LoopOperator` applies the companion matrix (and its transpose) and the noise-
augmented system of :meth:`ClosedLoop.noise_state_space` through these factors: one
product costs ``O(nnz(K) + n p)`` per column instead of ``O((taubar + 1)^2 (nN)^2)``.
On it the exact radius is ARPACK's (:func:`design.closed_loop.spectral_radius`, two
starts that must agree, a dense fallback where that is possible), and the steady MSE is
the sum of the squared impulse response ``sum_k ||C M^k B||_F^2`` (Smith's iteration
with the low-rank factor B of the noise, ``n + p`` columns), never a dense Lyapunov solve.

>>> import numpy as np
>>> from design.closed_loop import ClosedLoop
>>> A = np.array([[0.9, 0.2], [0.0, 0.5]]); W = np.array([[0.5, 0.5], [0.5, 0.5]])
>>> loop = ClosedLoop(A, W, np.array([[0, 2], [1, 0]]), [(0,), (1,)],
...                   [np.array([[0.5], [0.1]]), np.array([[0.0], [0.4]])])
>>> op = LoopOperator(loop)
>>> v = np.arange(loop.order, dtype=float)
>>> bool(np.allclose(op.matvec(v), loop.companion(sparse=False) @ v))
True
>>> round(impulse_mse(op, 1.0, 1.0) / loop.mse_steady(1.0, 1.0), 9)
1.0
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

__all__ = ["LoopOperator", "impulse_mse", "lag_blocks", "noise_blocks", "block_gain",
           "IMPULSE_TOL", "IMPULSE_MAX_STEPS"]

#: The impulse sum stops once the state left holds less than this share of the sum.
IMPULSE_TOL = 1e-15
#: ... or after this many steps (a loop this slow is reported as not settled).
IMPULSE_MAX_STEPS = 200_000


def lag_blocks(W, delays, A_powers) -> dict:
    """``{r: K_r}``, ``K_r = W_r (x) A^(r+1)`` sparse (CSR), for every delay r on W's
    links (``A_powers[k] = A^k``)."""
    W, D = np.asarray(W, dtype=float), np.asarray(delays, dtype=int)
    links = W > 0
    return {int(r): sp.kron(sp.csr_matrix(np.where(links & (D == r), W, 0.0)),
                            sp.csr_matrix(A_powers[int(r) + 1]), format="csr")
            for r in np.unique(D[links])}


def noise_blocks(W, delays, A_powers) -> list:
    """``[C_0, ..., C_T]``, ``C_s = c_s (x) A^s`` sparse (nN x n), ``c_s[i]`` the weight
    of agent i's links delayed by s or more: how the process noise of the delay window
    enters."""
    W, D = np.asarray(W, dtype=float), np.asarray(delays, dtype=int)
    links = W > 0
    T = int(D.max()) if D.size else 0
    return [sp.kron(sp.csr_matrix(np.where(links & (D >= s), W, 0.0).sum(axis=1)[:, None]),
                    sp.csr_matrix(A_powers[s]), format="csr") for s in range(T + 1)]


def block_gain(G):
    """The block-diagonal gain ``Gb`` (nN x p) of the per-agent ``G_i`` (n x p_i), CSR.

    Built from the blocks' entries at once (every entry stored, zeros included: the
    pattern depends on the shapes only): ``sp.block_diag`` took 20-40 ms for the 31
    blocks of a communities-32 configuration, once per evaluation of a design.

    >>> block_gain([np.array([[1.0], [2.0]]), np.array([[3.0, 4.0], [5.0, 6.0]])]).toarray()
    array([[1., 0., 0.],
           [2., 0., 0.],
           [0., 3., 4.],
           [0., 5., 6.]])
    """
    G = [np.asarray(g, dtype=float).reshape(np.shape(g)[0], -1) for g in G]
    rows = [g.shape[0] for g in G]
    cols = [g.shape[1] for g in G]
    m, p = sum(rows), sum(cols)
    data = np.concatenate([g.ravel() for g in G]) if G else np.zeros(0)
    # row r of block i holds the columns c_i .. c_i + p_i - 1
    width = np.repeat(cols, rows)
    indptr = np.concatenate([[0], np.cumsum(width)]).astype(np.int64)
    first = np.repeat(np.cumsum([0] + cols[:-1]), rows)
    indices = (np.repeat(first, width)
               + np.arange(indptr[-1]) - np.repeat(indptr[:-1], width)).astype(np.int32)
    return sp.csr_matrix((data, indices, indptr), shape=(m, p))


class LoopOperator:
    """Products with the companion matrix of a :class:`ClosedLoop` (order (T+1) nN) and
    with its noise-augmented system, from the sparse ``K_r`` and the low-rank ``L``.

    Vectors are stacked as in :meth:`ClosedLoop.companion` (``e_k, ..., e_{k-T}``) and,
    for the augmented system, followed by the process-noise window
    (``nu_{k-1}, ..., nu_{k-T}``). Blocks of several columns are applied at once."""

    def __init__(self, loop):
        n, N, T = loop.n, loop.N, loop.taubar
        m = n * N
        self.n, self.N, self.T, self.m = n, N, T, m
        self.order = (T + 1) * m
        self.aug_order = self.order + T * n
        self.K = lag_blocks(loop.W, loop.delays, loop.A_powers)
        self.KT = {r: K.T.tocsr() for r, K in self.K.items()}
        # process noise entering through the window: C_s = c_s (x) A^s, s = 0..T
        self.C = noise_blocks(loop.W, loop.delays, loop.A_powers)
        # L = I - Gb Hb: Hb picks each agent's measured rows of its own block
        self.rows = np.array([i * n + v for i, mi in enumerate(loop.measure) for v in mi],
                             dtype=int)
        self.p = int(self.rows.size)
        self.Gb = block_gain(loop.G) if loop.G else sp.csr_matrix((m, 0))
        self.GbT = self.Gb.T.tocsr()

    # -- L and its transpose --------------------------------------------------------
    def apply_L(self, Y):
        """``L Y`` (Y: nN rows)."""
        return Y - self.Gb @ Y[self.rows]

    def apply_LT(self, Y):
        """``L^T Y``."""
        out = np.array(Y, copy=True)
        out[self.rows] -= self.GbT @ Y
        return out

    # -- the companion matrix ---------------------------------------------------------
    def matvec(self, x):
        """``M x`` for the companion matrix M (x: one vector or a block of columns)."""
        m, T = self.m, self.T
        acc = None
        for r, K in self.K.items():
            term = K @ x[r * m:(r + 1) * m]
            acc = term if acc is None else acc + term
        if acc is None:
            acc = np.zeros_like(x[:m])
        return np.concatenate([self.apply_L(acc), x[:T * m]]) if T else self.apply_L(acc)

    def rmatvec(self, y):
        """``M^T y``."""
        m, T = self.m, self.T
        out = np.zeros_like(y)
        top = self.apply_LT(y[:m])
        for r, KT in self.KT.items():
            out[r * m:(r + 1) * m] += KT @ top
        if T:
            out[:T * m] += y[m:]
        return out

    def linear_operator(self) -> spla.LinearOperator:
        """The companion matrix as a scipy LinearOperator (matvec, rmatvec, matmat)."""
        return spla.LinearOperator((self.order, self.order), matvec=self.matvec,
                                   rmatvec=self.rmatvec, matmat=self.matvec,
                                   rmatmat=self.rmatvec, dtype=float)

    # -- the noise-augmented system -----------------------------------------------------
    def noise_input(self, q: float, r: float) -> np.ndarray:
        """``B`` of :meth:`ClosedLoop.noise_state_space`, dense (aug_order x (n + p)):
        its columns are the unit-variance process noise then the readings' noise."""
        m, n, T = self.m, self.n, self.T
        B = np.zeros((self.aug_order, n + self.p))
        B[:m, :n] = np.sqrt(q) * self.apply_L(self.C[0].toarray())
        if T:
            B[self.order:self.order + n, :n] = np.sqrt(q) * np.eye(n)
        B[:m, n:] = -np.sqrt(r) * self.Gb.toarray()
        return B

    def aug_matvec(self, X):
        """``M X`` for the augmented system of :meth:`ClosedLoop.noise_state_space`."""
        m, n, T, o = self.m, self.n, self.T, self.order
        if not T:
            return self.matvec(X)
        acc = None
        for r, K in self.K.items():
            term = K @ X[r * m:(r + 1) * m]
            acc = term if acc is None else acc + term
        for s in range(1, T + 1):
            term = self.C[s] @ X[o + (s - 1) * n:o + s * n]
            acc = term if acc is None else acc + term
        nu = np.zeros_like(X[o:o + n])
        return np.concatenate([self.apply_L(acc), X[:T * m], nu, X[o:o + (T - 1) * n]])


def impulse_mse(op: LoopOperator, q: float, r: float, tol: float = IMPULSE_TOL,
                max_steps: int = IMPULSE_MAX_STEPS) -> float:
    """The steady MSE ``trace(C P C^T) / (nN)``, ``P = M P M^T + B B^T``, as the sum
    ``sum_k ||C M^k B||_F^2 / (nN)`` over the impulse response of the augmented loop.

    The sum stops once the whole state left (``||M^k B||_F^2``, the error window and
    the noise window) is below ``tol`` of the sum: what is left of it decays from there
    at the loop's rate. Raises ValueError when the state has not settled after
    ``max_steps`` steps or grows without bound (the loop is not stable)."""
    X = op.noise_input(q, r)
    m = op.m
    total = 0.0
    for _ in range(max_steps):
        e = float(np.einsum("ij,ij->", X[:m], X[:m]))
        total += e
        left = float(np.einsum("ij,ij->", X, X))
        if not np.isfinite(total) or left > 1e30 * max(total, 1e-300):
            raise ValueError("the impulse response grows without bound: the loop is not "
                             "stable")
        if left <= tol * total:
            return total / m
        X = op.aug_matvec(X)
    raise ValueError(f"the impulse response has not settled after {max_steps} steps "
                     "(the loop is not stable, or too close to the unit circle)")
