"""Figures computed from simulated or recorded error series.

One definition of the steady mean-squared error used by the simulator, the live run's
summary, the paper's reproduction and the tests: the mean over the last quarter of the
steps, ``max(1, steps // 4)`` entries (the first three quarters are the transient); a
step without any estimate (NaN, in a live record) is left out, an infinite one makes it
infinite. And one definition of the error of a step: :func:`mse_of_step`; of the
uncertainty of one run's steady MSE: :func:`batch_means_se`.

Examples
--------
>>> steady_mse([9.0, 5.0, 1.0, 2.0, 1.0, 3.0, 2.0, 4.0])     # the last 2 of 8 entries
3.0
"""

from __future__ import annotations

import numpy as np

__all__ = ["steady_window", "steady_mse", "mse_of_step", "mean_recorded", "BATCHES",
           "batch_means_se"]

#: Batches of :func:`batch_means_se` (10-30 is the usual advice, Schmeiser 1982: fewer
#: batches are longer, so their means are less correlated, at the price of a noisier
#: standard error).
BATCHES = 10


def steady_window(steps: int) -> int:
    """Number of final steps that count as steady: ``max(1, steps // 4)``.

    >>> [steady_window(k) for k in (1, 3, 4, 7, 8, 300)]
    [1, 1, 1, 1, 2, 75]
    """
    return max(1, int(steps) // 4)


def steady_mse(mse, axis: int = -1):
    """Mean of ``mse`` over its last :func:`steady_window` entries along ``axis``.

    A 1-D series gives a float; ``mse_trials`` (trials x steps) gives one value per trial.

    Examples
    --------
    >>> steady_mse([4.0, 2.0, 1.0])          # fewer than 4 steps: the last entry alone
    1.0
    >>> steady_mse(np.array([[1.0, 1, 1, 1, 3, 5, 7, 9], [0, 0, 0, 0, 0, 0, 2, 2]]))
    array([8., 2.])
    >>> steady_mse([1.0, 1, 1, 1, 1, 1, 2, float("nan")])    # a step nobody estimated
    2.0
    >>> steady_mse([1.0, 1, 1, 1, 1, 1, float("nan"), float("nan")])
    nan
    """
    a = np.asarray(mse, dtype=float)
    if a.ndim == 0 or a.shape[axis] == 0:
        raise ValueError(f"mse: needs at least one step, got shape {a.shape}")
    q = steady_window(a.shape[axis])
    tail = np.take(a, np.arange(a.shape[axis] - q, a.shape[axis]), axis=axis)
    missing = np.isnan(tail)
    if not missing.any():
        out = tail.mean(axis=axis)
    else:
        count = (~missing).sum(axis=axis)
        total = np.where(missing, 0.0, tail).sum(axis=axis)
        with np.errstate(invalid="ignore", divide="ignore"):
            out = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return float(out) if np.ndim(out) == 0 else out


def mean_recorded(values) -> float:
    """The mean of a window of per-step MSEs, steps nobody estimated (NaN) left out; NaN
    for an empty window, inf when one is infinite (the window :func:`steady_mse` takes).

    >>> mean_recorded([1.0, float("nan"), 3.0]), mean_recorded([])
    (2.0, nan)
    """
    a = np.asarray(list(values), dtype=float)
    a = a[~np.isnan(a)]
    if not len(a):
        return float("nan")
    return float(a.mean()) if np.isfinite(a).all() else float("inf")


def mse_of_step(estimates, truth) -> float | None:
    """The error of one step: the mean over ``estimates`` (each agent's estimate of the
    state) of their mean squared error against ``truth``; None without an estimate.

    >>> mse_of_step([np.array([1.0, 1.0]), np.array([0.0, 2.0])], np.array([0.0, 0.0]))
    1.5
    """
    errs = [float(np.mean((np.asarray(x) - truth) ** 2)) for x in estimates]
    return float(np.mean(errs)) if errs else None


def batch_means_se(values, batches: int = BATCHES) -> float | None:
    """The standard error of the mean of a window of per-step MSEs of one run, by batch
    means: the window (steps nobody estimated left out) cut into ``batches`` consecutive
    batches of equal length (the first ``len % batches`` entries left out), the sample
    standard deviation of the batch means over ``sqrt(batches)``. The per-step errors of
    one run are correlated over a few steps (more as the loop's radius nears 1), so their
    plain standard deviation over ``sqrt(n)`` would understate it. None when the window
    has fewer than two steps per batch or an infinite entry.

    >>> batch_means_se([1.0, 3.0] * 10, batches=10)     # every batch's mean is 2
    0.0
    >>> round(batch_means_se([1.0] * 10 + [3.0] * 10, batches=2), 6)
    1.0
    >>> batch_means_se([1.0, 2.0, 3.0]) is None           # too short to tell
    True
    """
    a = np.asarray(list(values), dtype=float)
    a = a[~np.isnan(a)]
    if batches < 2 or len(a) < 2 * batches or not np.isfinite(a).all():
        return None
    length = len(a) // batches
    means = a[len(a) - batches * length:].reshape(batches, length).mean(axis=1)
    return float(means.std(ddof=1) / np.sqrt(batches))
