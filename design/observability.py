"""Numerical observability by the orthogonal staircase (Krylov) method.

The observable subspace of (A, C) is the Krylov space spanned by C^T, A^T C^T,
(A^T)^2 C^T, ... . We build an orthonormal basis of it block by block: each new block is
A^T applied to the previous *orthonormal* block, orthogonalised twice against the basis,
and its numerical rank decided by an SVD with a tolerance. No power A^k is ever formed,
so the method does not suffer from the growth or decay of A^k that makes the textbook
rank test of [C; CA; ...; CA^(n-1)] unreliable beyond small n (it is the controllability
staircase of Rosenbrock / Van Dooren applied to the dual pair).

Examples
--------
>>> import numpy as np
>>> A = np.array([[1., 0], [1, 1]])     # node 1 influences node 2
>>> observability_rank(A, np.array([[0., 1]])), observability_rank(A, np.array([[1., 0]]))
(2, 1)
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

__all__ = [
    "observable_basis",
    "observability_rank",
    "unobservable_modes",
    "default_tolerance",
    "PairObservability",
    "pair_observability",
    "distributed_pair",
    "distributed_detectability",
    "distributed_detectable",
    "all_modes_stable",
    "stable_modes_bound",
    "DENSE_KRON_MAX_ORDER",
]

#: Above this order nN the Kronecker product W (x) A is kept sparse.
DENSE_KRON_MAX_ORDER = 600


def default_tolerance(A, C) -> float:
    """Rank tolerance ``n^2 * eps * max(||A||_F, ||C||_F, 1)`` (SLICOT's TB01UD choice)."""
    n = A.shape[0]
    normA = sp.linalg.norm(A) if sp.issparse(A) else np.linalg.norm(A)
    normC = np.linalg.norm(np.asarray(C))
    return n * n * np.finfo(float).eps * max(normA, normC, 1.0)


def observable_basis(A, C, tol=None) -> np.ndarray:
    """Orthonormal basis (n x r) of the observable subspace of (A, C).

    Parameters
    ----------
    A : (n, n) array or sparse matrix
    C : (p, n) array
    tol : float, optional
        Singular values at or below ``tol`` count as zero; default
        :func:`default_tolerance`.
    """
    C = np.atleast_2d(np.asarray(C, dtype=float))
    n = A.shape[0]
    if A.shape != (n, n):
        raise ValueError(f"A: must be square, got shape {A.shape}")
    if C.shape[1] != n:
        raise ValueError(f"C: must have n = {n} columns, got shape {C.shape}")
    if tol is None:
        tol = default_tolerance(A, C)
    AT = A.T.tocsr() if sp.issparse(A) else np.asarray(A, dtype=float).T
    new = _orth(C.T, tol)[:, :n]
    r = new.shape[1]
    # the basis lives in the first r columns of a buffer that doubles when full: appending
    # a block copies the basis only O(log n) times (np.hstack per block copied it n/p
    # times, a third of the time at order 3000)
    buf = np.empty((n, min(n, max(2 * r, 64))), order="F")
    buf[:, :r] = new
    while new.shape[1] and r < n:
        basis = buf[:, :r]
        Z = AT @ new
        for _ in range(2):  # classical Gram-Schmidt, twice, is numerically orthogonal
            Z = Z - basis @ (basis.T @ Z)
        new = _orth(Z, tol)[:, :n - r]
        k = new.shape[1]
        if r + k > buf.shape[1]:
            grown = np.empty((n, min(n, max(2 * buf.shape[1], r + k))), order="F")
            grown[:, :r] = buf[:, :r]
            buf = grown
        buf[:, r:r + k] = new
        r += k
    return buf[:, :r]


def observability_rank(A, C, tol=None) -> int:
    """Dimension of the observable subspace of (A, C)."""
    return int(observable_basis(A, C, tol).shape[1])


def unobservable_modes(A, C, tol=None) -> np.ndarray:
    """Eigenvalues of A restricted to the unobservable subspace of (A, C).

    The unobservable subspace is the orthogonal complement of the staircase basis
    ``V`` of :func:`observable_basis`; it is A-invariant, so with ``U`` an orthonormal
    basis of it, ``A U = U (U^T A U)`` and the unobservable modes are the eigenvalues of
    ``U^T A U``. (A, C) is detectable iff all of them lie strictly inside the unit
    circle. Empty when (A, C) is observable. A sparse ``A`` is made dense only for the
    (n - r)-column product ``A U``.

    Examples
    --------
    >>> import numpy as np
    >>> A = np.array([[0.5, 0], [1, 2.0]])    # node 1 -> node 2; measure node 1 only
    >>> unobservable_modes(A, np.array([[1., 0]]))
    array([2.])
    >>> unobservable_modes(A, np.array([[0., 1]])).size
    0
    """
    return _modes_outside(A, observable_basis(A, C, tol))


def _modes_outside(A, V) -> np.ndarray:
    """Eigenvalues of A on the orthogonal complement of the A^T-invariant span of ``V``."""
    n, r = A.shape[0], V.shape[1]
    if r >= n:
        return np.zeros(0)
    # complete V to an orthonormal basis of R^n: the last n - r columns of the complete
    # Householder QR of V span V^perp (a QR of [V, I] gave the same at twice the memory)
    Qfull, _ = np.linalg.qr(V, mode="complete")
    U = Qfull[:, r:n]
    del Qfull
    # re-orthogonalise against V (the QR already gives it; this guards rounding)
    U = U - V @ (V.T @ U)
    U, _ = np.linalg.qr(U)
    AU = A @ U
    AU = np.asarray(AU.todense()) if sp.issparse(AU) else np.asarray(AU)
    vals = np.linalg.eigvals(U.T @ AU)
    if np.all(np.abs(vals.imag) <= 1e-12 * max(1.0, float(np.max(np.abs(vals))))):
        vals = vals.real
    order = np.lexsort((vals.imag if np.iscomplexobj(vals) else np.zeros(vals.size), -np.abs(vals)))
    return vals[order]


@dataclass(frozen=True, eq=False)
class PairObservability:
    """Observability of a pair (A, C): rank of ``order`` and the unobservable modes.

    ``detectable`` iff every unobservable mode lies strictly inside the unit circle.
    """

    rank: int
    order: int
    unobservable_modes: np.ndarray

    @property
    def observable(self) -> bool:
        return self.rank == self.order

    @property
    def detectable(self) -> bool:
        return bool(np.all(np.abs(self.unobservable_modes) < 1.0))

    @property
    def max_unobservable_modulus(self) -> float:
        m = self.unobservable_modes
        return float(np.max(np.abs(m))) if m.size else 0.0


def pair_observability(A, C, tol=None) -> PairObservability:
    """Rank and unobservable modes of (A, C) from one staircase.

    >>> A = np.array([[0.5, 0], [1, 2.0]])
    >>> p = pair_observability(A, np.array([[1., 0]]))
    >>> p.rank, p.order, p.observable, p.detectable
    (1, 2, False, False)
    """
    V = observable_basis(A, C, tol)
    return PairObservability(rank=int(V.shape[1]), order=int(A.shape[0]),
                             unobservable_modes=_modes_outside(A, V))


def distributed_pair(A, W, measure):
    """The distributed pair ``(W (x) A, C)`` of the paper's Lemma 3.

    ``C`` holds one row ``e_{i n + v}`` per node v measured by agent i (0-based): its row
    space is that of ``D_H = blockdiag(H_i^T H_i)``, so (W (x) A, C) and (W (x) A, D_H)
    have the same observable subspace. ``W (x) A`` is sparse when the order nN exceeds
    :data:`DENSE_KRON_MAX_ORDER`.

    >>> WA, C = distributed_pair(np.eye(2), np.eye(2), [[1], [0]])
    >>> WA.shape, np.flatnonzero(C).tolist()
    ((4, 4), [1, 6])
    """
    A = A if sp.issparse(A) else np.asarray(A, dtype=float)
    W = np.asarray(W, dtype=float)
    n, N = A.shape[0], W.shape[0]
    rows = [i * n + int(v) for i, m in enumerate(measure) for v in m]
    C = np.zeros((len(rows), n * N))
    C[np.arange(len(rows)), rows] = 1.0
    if n * N > DENSE_KRON_MAX_ORDER or sp.issparse(A):
        return sp.kron(sp.csr_matrix(W), sp.csr_matrix(A), format="csr"), C
    return np.kron(W, A), C


def distributed_detectability(A, W, measure, tol=None) -> PairObservability:
    """Observability and detectability of the distributed pair (W (x) A, D_H).

    The one definition used by the analysis, the recovery plan and the gain design: a
    stabilising structured gain can exist only if this pair is detectable.

    Examples
    --------
    >>> from design.scenario import load_scenario
    >>> s = load_scenario("paper-14")
    >>> d = distributed_detectability(s.A, s.W, s.measure)
    >>> d.rank, d.order, d.detectable
    (33, 42, True)
    """
    if sp.issparse(A):
        return pair_observability(*distributed_pair(A, W, measure), tol)
    A, W = np.ascontiguousarray(A, dtype=float), np.ascontiguousarray(W, dtype=float)
    key = (A.shape, hashlib.blake2b(A.data).digest(), W.shape, W.tobytes(),
           tuple(tuple(int(v) for v in m) for m in measure), tol)
    hit = _DETECTABILITY.get(key)
    if hit is None:
        WA, C = distributed_pair(A, W, measure)
        hit = pair_observability(WA, C, tol)
        if len(_DETECTABILITY) >= _DETECTABILITY_MAX:
            _DETECTABILITY.pop(next(iter(_DETECTABILITY)))
        _DETECTABILITY[key] = hit
    return hit


#: Above this order n, :func:`stable_modes_bound` does not take A's eigenvalues (a dense
#: problem) and gives no bound.
STABLE_BOUND_MAX_ORDER = 2000
#: :func:`distributed_detectable` decides without the staircase when the bound is below
#: 1 - this (the eigenvalues of A carry rounding of order eps ||A||).
STABLE_BOUND_MARGIN = 1e-9


def stable_modes_bound(A, W) -> float:
    """An upper bound of the moduli of every mode of ``W (x) A``: ``||W||_inf rho(A)``
    (the eigenvalues of a Kronecker product are the products of the factors'; rho(W) <=
    ||W||_inf, which is 1 for a row-stochastic W); ``inf`` when A is sparse or of order
    above :data:`STABLE_BOUND_MAX_ORDER`.

    >>> stable_modes_bound(np.diag([0.5, -0.9]), np.array([[0.5, 0.5], [0.25, 0.75]]))
    0.9
    """
    if sp.issparse(A):
        return float("inf")
    A, W = np.atleast_2d(np.asarray(A, dtype=float)), np.atleast_2d(np.asarray(W, dtype=float))
    if A.shape[0] > STABLE_BOUND_MAX_ORDER:
        return float("inf")
    rho_A = float(np.max(np.abs(np.linalg.eigvals(A)), initial=0.0))
    return float(np.max(np.sum(np.abs(W), axis=1), initial=0.0)) * rho_A


def all_modes_stable(A, W, measure) -> bool:
    """Whether every mode of ``W (x) A`` lies inside the unit circle by
    :func:`stable_modes_bound` (below 1 - :data:`STABLE_BOUND_MARGIN`), for a well-formed
    pair only (A and W square, one measured list per agent, nodes of A): then the pair
    ``(W (x) A, D_H)`` is detectable whatever the measurements. False otherwise, also for
    a malformed pair, which :func:`distributed_detectability` rejects with its error."""
    if not sp.issparse(A):
        A = np.atleast_2d(np.asarray(A, dtype=float))
    W = np.asarray(W, dtype=float)
    n = A.shape[0]
    if A.ndim != 2 or A.shape != (n, n) or W.ndim != 2 or W.shape[0] != W.shape[1] \
            or W.shape[0] != len(measure) or not len(measure) \
            or not all(0 <= int(v) < n for m in measure for v in m):
        return False
    return stable_modes_bound(A, W) < 1.0 - STABLE_BOUND_MARGIN


def distributed_detectable(A, W, measure, tol=None) -> bool:
    """Whether (W (x) A, D_H) is detectable, as :func:`distributed_detectability` says,
    without its staircase when every mode of ``W (x) A`` lies inside the unit circle
    (:func:`all_modes_stable`): then every unobservable mode does too, whatever the
    measurements.

    Why: the staircase is of order nN (1.1-1.5 s at communities-32, most of the
    monitor's fast design of a single failure there), where a stable A answers at once.

    >>> distributed_detectable(np.diag([0.5, 0.9]), np.eye(2), [[0], [0]])
    True
    >>> distributed_detectable(np.diag([0.5, 1.2]), np.eye(2), [[0], [0]])
    False
    """
    if all_modes_stable(A, W, measure):
        return True
    return distributed_detectability(A, W, measure, tol).detectable


#: distributed_detectability's answers by (A, W, measure, tol): a recovery plan with its
#: numerical checks (``socmon plan``, ``analyze``) and the design of its gain ask it of one
#: configuration in turn (a staircase of order nN each: 1.2-2.8 s at communities-32; the
#: monitor's plans and designs skip it when every mode of W (x) A is stable)
_DETECTABILITY: dict = {}
_DETECTABILITY_MAX = 64


def _orth(Z, tol) -> np.ndarray:
    if Z.size == 0:
        return Z
    U, s, _ = np.linalg.svd(Z, full_matrices=False)
    return U[:, : int(np.sum(s > tol))]
