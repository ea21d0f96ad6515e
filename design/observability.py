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

import numpy as np
import scipy.sparse as sp

__all__ = [
    "observable_basis",
    "observability_rank",
    "is_observable",
    "unobservable_modes",
    "default_tolerance",
]


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
    new = _orth(C.T, tol)
    basis = new
    while new.shape[1] and basis.shape[1] < n:
        Z = AT @ new
        for _ in range(2):  # classical Gram-Schmidt, twice, is numerically orthogonal
            Z = Z - basis @ (basis.T @ Z)
        new = _orth(Z, tol)
        basis = np.hstack([basis, new])
    return basis[:, :n]


def observability_rank(A, C, tol=None) -> int:
    """Dimension of the observable subspace of (A, C)."""
    return int(observable_basis(A, C, tol).shape[1])


def is_observable(A, C, tol=None) -> bool:
    """True iff (A, C) is observable (numerically, with tolerance ``tol``)."""
    return observability_rank(A, C, tol) == A.shape[0]


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
    V = observable_basis(A, C, tol)
    n, r = A.shape[0], V.shape[1]
    if r >= n:
        return np.zeros(0)
    # complete V to an orthonormal basis of R^n; the last n - r columns span V^perp
    Qfull, _ = np.linalg.qr(np.hstack([V, np.eye(n)]), mode="complete")
    U = Qfull[:, r:n]
    # re-orthogonalise against V (QR of [V, I] already gives it; this guards rounding)
    U = U - V @ (V.T @ U)
    U, _ = np.linalg.qr(U)
    AU = A @ U
    AU = np.asarray(AU.todense()) if sp.issparse(AU) else np.asarray(AU)
    vals = np.linalg.eigvals(U.T @ AU)
    if np.all(np.abs(vals.imag) <= 1e-12 * max(1.0, float(np.max(np.abs(vals))))):
        vals = vals.real
    order = np.lexsort((vals.imag if np.iscomplexobj(vals) else np.zeros(vals.size), -np.abs(vals)))
    return vals[order]


def _orth(Z, tol) -> np.ndarray:
    if Z.size == 0:
        return Z
    U, s, _ = np.linalg.svd(Z, full_matrices=False)
    return U[:, : int(np.sum(s > tol))]
