"""How large a value the model allows: the bound past which a reading or an estimate is
refused as implausible.

Under the model (``x_0 ~ N(0, I)``, ``x_{k+1} = A x_k + nu_k``, ``nu_k ~ N(0, q I)``,
readings with noise variance ``r``) the state's covariance is
``Sigma_{k+1} = A Sigma_k A^T + q I`` with ``Sigma_0 = I``. Its largest diagonal entry,
kept as a running maximum over the steps so far (a stable system's decaying transient
does not shrink the scale below the initial one), plus ``r + q``, gives a per-step
scale ``sigma_k``. A reading of the true state or an estimate of it past
``multiple * sigma_k`` in any entry is then many standard deviations out: a sender that
publishes it is broken or lying, and fusing it would carry it to every agent.

The multiples are wide on purpose (:data:`READING_MULTIPLE` for the world's readings of
the true state, :data:`ESTIMATE_MULTIPLE` for estimates, whose errors a gain may amplify
in a transient): the rule refuses the absurd (1e300, 1e30), never a healthy run's value.
What stays inside the bound is the business of detecting agents that lie.

The first :data:`EXACT_STEPS` covariances are computed one by one (``A`` sparse, so a
step costs ``2 nnz(A) n``). Beyond them the scale grows at the rate it grew over the
second half of those steps (none for a stable system whose transient has settled; about
``rho(A)^k`` for an unstable one), plus :data:`GROWTH_MARGIN` a step: an envelope, wide
where polynomial growth would make the rate look faster than it is.

>>> import numpy as np
>>> scale = StateScale(0.9 * np.eye(2), q=0.1, r=0.5)
>>> round(scale.sigma(0), 6)          # sqrt(1 + 0.5 + 0.1)
1.264911
>>> scale.plausible(np.array([3.0, -2.0]), 5, ESTIMATE_MULTIPLE)
True
>>> scale.plausible(np.array([1e300, 0.0]), 5, ESTIMATE_MULTIPLE)
False
>>> growing = StateScale(np.array([[1.1]]), q=0.0)
>>> growing.sigma(100) > 1.1 ** 100
True
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["StateScale", "READING_MULTIPLE", "ESTIMATE_MULTIPLE", "EXACT_STEPS", "GROWTH_MARGIN"]

READING_MULTIPLE = 1e3
"""Multiple of the state's scale past which a reading of the true state is refused."""

ESTIMATE_MULTIPLE = 1e4
"""Multiple of the state's scale past which an estimate is refused."""

EXACT_STEPS = 64
"""Steps whose covariance is computed one by one (later ones extrapolated)."""

GROWTH_MARGIN = 1.01
"""Factor a step added to the extrapolated growth of the state's variance."""


class StateScale:
    """The model's per-step scale of the state, and the plausibility rule built on it.

    Parameters
    ----------
    A : (n, n) array
    q : float
        Process-noise variance per node.
    r : float
        Measurement-noise variance per reading.
    """

    def __init__(self, A, q: float, r: float = 0.0):
        from scipy import sparse

        A = sparse.csr_matrix(np.asarray(A, dtype=float))
        n = A.shape[0]
        self.floor = float(q) + float(r)
        sigma = np.eye(n)
        top = 1.0
        tops = []                         # running max of max diag Sigma_k, k < EXACT_STEPS
        with np.errstate(over="ignore", invalid="ignore"):
            for _ in range(EXACT_STEPS):
                top = _worse(top, float(np.max(np.diag(sigma))))
                tops.append(top)
                if not math.isfinite(top):
                    break
                sigma = np.asarray(A @ np.asarray(A @ sigma).T) + float(q) * np.eye(n)
        tops += [tops[-1]] * (EXACT_STEPS - len(tops))
        self._tops = tops
        half = EXACT_STEPS // 2
        rate = (tops[-1] / tops[half - 1]) ** (1.0 / (EXACT_STEPS - half)) \
            if math.isfinite(tops[-1]) else math.inf
        self.growth = 1.0 if rate <= 1.0 + 1e-9 else rate * GROWTH_MARGIN
        """Factor a step by which the variance is taken to grow after the exact steps."""

    def _top(self, step: int) -> float:
        if step < EXACT_STEPS:
            return self._tops[max(step, 0)]
        last = self._tops[-1]
        if self.growth == 1.0:
            return last
        log_grown = math.log(last) + (step - EXACT_STEPS + 1) * math.log(self.growth)
        return math.exp(log_grown) if log_grown < 700.0 else math.inf

    def sigma(self, step: int) -> float:
        """The scale ``sigma_k`` of any entry of the state (or an estimate) at ``step``."""
        return math.sqrt(self._top(int(step)) + self.floor)

    def bound(self, step: int, multiple: float) -> float:
        """Largest plausible magnitude of an entry at ``step``."""
        return multiple * self.sigma(step)

    def plausible(self, values, step: int, multiple: float) -> bool:
        """True if every entry of ``values`` is finite and within ``bound(step, multiple)``."""
        v = np.asarray(values, dtype=float)
        if v.size == 0:
            return True
        top = float(np.abs(v).max())            # NaN or inf if any entry is
        return math.isfinite(top) and top <= self.bound(step, multiple)


def _worse(a: float, b: float) -> float:
    """The larger of two variances, NaN (an overflowed product) taken as infinite."""
    if not math.isfinite(b):
        return math.inf
    return max(a, b)
