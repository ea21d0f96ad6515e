"""Residual tests with exact thresholds, and the isolation of a faulty sensor or agent.

Two residuals are formed at every step k by every agent i (agents are 0-based rows):

- its **innovation** ``y^i_k - H_i xhat^i_{k|k-1}`` (p_i numbers);
- for each in-neighbour j (link j -> i, delay tau), the **discrepancy** between j's
  estimate as agent i uses it and agent i's own prediction,
  ``A^(1+tau) xhat^j_{k-1-tau} - xhat^i_{k|k-1}`` (n numbers).

On a healthy loop both are linear in the augmented state of
:meth:`design.closed_loop.ClosedLoop.noise_state_space` and in that step's fresh noise
(with ``e = x - xhat``, ``S_a(k) = sum_{m<a} A^m nu_{k-1-m}``):

    innovation   = H_i e^{i,prior}_k + zeta^i_k
    discrepancy  = e^{i,prior}_k - A^(1+tau) e^j_{k-1-tau} - S_{1+tau}(k)
    e^{prior}_k  = sum_r (W_r (x) A^(r+1)) e_{k-1-r} + sum_s (c_s (x) A^s) nu_{k-1-s}

so they are outputs ``v_k = C_v xi_{k-1} + D_v w_{k-1}`` of the loop's noise state
space. Their steady covariance and autocovariance follow exactly from the discrete
Lyapunov solution ``P`` of that state space:
``Gamma(0) = C_v P C_v^T + D_v D_v^T``, ``Gamma(l) = C_v M^(l-1) (M P C_v^T + B D_v^T)``.

The test: a sliding window sum
------------------------------
Each statistic sums its residual over the last ``window`` steps,
``s_k = v_{k-window+1} + ... + v_k``, and normalises it by the sum's exact covariance
``Sigma = window Gamma(0) + sum_{l=1}^{window-1} (window - l)(Gamma(l) + Gamma(l)^T)``:
``T_k = s_k^T Sigma^+ s_k``. On a healthy loop in steady state ``s_k`` is Gaussian with
covariance ``Sigma``, so ``T_k`` is **exactly** chi-square with ``rank(Sigma)`` degrees of
freedom at every step, and the threshold ``chi2.isf(alpha_test, dof)`` gives an exact
per-step false-alarm probability ``alpha_test``. Why a window and not a CUSUM:

- the threshold is exact and computed once per configuration, with no Monte-Carlo
  calibration: the correlation of consecutive residuals (the loop's memory, and the
  window's overlap) is inside ``Sigma``;
- the expected number of alarm steps over a run is ``alpha_test`` times the number of
  tested steps, **exactly**, whatever the correlation between consecutive statistics
  (linearity of expectation). The correlation only groups alarms in bursts: the number of
  alarm *episodes* is at most the number of alarm steps, so the figure is a bound for
  episodes. A CUSUM's false-alarm rate on correlated inputs has no closed form (it needs
  ARL approximations or a Monte-Carlo calibration per configuration);
- a window sum is the likelihood-ratio statistic for a constant offset over the window,
  the fault we care most about (a bias, a lie); a drift is a ramp that it accumulates too.
  It is slower than a per-step test on a large fault by at most ``window - 1`` steps,
  and it sees a fault ``sqrt(window)`` times smaller.

Where ``Sigma`` is singular or nearly so (the residual hardly moves in some directions on
a healthy loop: on paper-14-live the discrepancy's eigenvalues fall continuously from 1
to 1e-14 of the largest) the statistic uses the pseudo-inverse through an
eigen-whitening that keeps the eigenvalues above :data:`RANK_RTOL` times the largest:
``dof`` is that rank (:attr:`Residual.singular` says when it is below the dimension).
The discarded directions are not left unwatched: they are exactly where a lie would
otherwise hide (a receiver uses the lied estimate whatever its direction). A second,
conservative test alarms when the window sum's component there,
``||N^T s||^2 / floor``, exceeds ``chi2.isf(alpha * NULL_SHARE, dim - dof)``: every
discarded direction has a variance below the floor, so its false-alarm probability is
at most ``alpha * NULL_SHARE`` (in practice far below). The residual's statistic is the
larger of the two on the main test's threshold scale, so one threshold per residual
still decides.

The false-alarm rate ``alpha`` is per agent and per step: it is split evenly over an
agent's tests (its innovation and one discrepancy per in-neighbour), so the expected
number of alarm steps of a healthy run is ``alpha * N * tested steps``. The default
:data:`DEFAULT_ALPHA` gives 0.01 over a 10,000-step run of ``paper-14-live`` (3 agents).
Statistics start once the initial transient has decayed (:attr:`ResidualTest.first_step`):
before that the covariance is not the steady one. The warm-up is computed from the loop,
not guessed from its radius: the transient of the initial errors, propagated by the
augmented loop and whitened like each statistic, must be below :data:`WARMUP_TOL` of
the steady covariance (a bound with the operator 2-norm). Directions of tiny steady
variance make it longer than ``log(tol) / log(rho)``: they are whitened strongly, and the
initial errors excite them.

Isolation
---------
:func:`isolate` turns per-agent reports (each statistic divided by its threshold) into a
:class:`Verdict`; see its docstring for the rules and for what cannot be distinguished.

Examples
--------
>>> import numpy as np
>>> from design.scenario import load_scenario
>>> s = load_scenario("paper-14-live")
>>> G = [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure]
>>> test = residual_test(s, G, window=4)
>>> [r.name for r in test.residuals]
['innovation 1', 'innovation 2', 'innovation 3', 'link 2->1', 'link 3->2', 'link 1->3']
>>> test.first_step, [r.dof for r in test.residuals][:4]
(383, [1, 1, 1, 6])
>>> round(test.expected_false_alarms(10_000), 5)    # 0.01 over the 10,000 steps, less warm-up
0.00962
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from scipy import stats as _stats

from .closed_loop import ClosedLoop, closed_loop_for
from .errors import SocmonError

__all__ = [
    "Residual",
    "ResidualTest",
    "ResidualError",
    "residual_test",
    "residual_state_space",
    "residual_autocovariances",
    "window_covariance",
    "first_alarms",
    "AgentReport",
    "Verdict",
    "isolate",
    "reports_at",
    "AgentResiduals",
    "AgentTests",
    "agent_tests",
    "configuration_tests",
    "AGENT_MAX_ORDER",
    "SENSOR_BIAS",
    "INCONSISTENT",
    "TIE_RATIO",
    "DEFAULT_ALPHA",
    "DEFAULT_WINDOW",
    "RANK_RTOL",
    "WARMUP_TOL",
    "NULL_SHARE",
    "MAX_ORDER",
]

#: Expected false alarms (alarm steps, all agents) of a healthy run of the reference ...
REFERENCE_FALSE_ALARMS = 0.01
#: ... over this many steps ...
REFERENCE_STEPS = 10_000
#: ... with this many agents (paper-14-live).
REFERENCE_AGENTS = 3
#: Default false-alarm probability per agent per step: 0.01 / (10,000 * 3) = 3.3e-7.
DEFAULT_ALPHA = REFERENCE_FALSE_ALARMS / (REFERENCE_STEPS * REFERENCE_AGENTS)
#: Default window (steps) of the sums. On paper-14-live with its designed gains it finds a
#: bias of 3 noise std-devs on agent 1 in a median of 6 steps and of 5 on agent 3 in 16
#: (windows 1, 4, 16, 32: 54, 9, 9, 13 and 187, 29, 17, 20; docs/residuals.md): shorter
#: windows miss small faults, longer ones delay large ones.
DEFAULT_WINDOW = 8
#: Eigenvalues of a window covariance below this share of its largest are dropped
#: (pseudo-inverse): the statistic's degrees of freedom are the rank kept.
RANK_RTOL = 1e-9
#: Share of a singular residual's false-alarm budget given to its null-space test.
NULL_SHARE = 0.01
#: Statistics are tested once the initial transient's share of their whitened
#: covariance is below this (a bound, see ``_warmup``): the chi-square tail at the
#: default thresholds is then within 0.1 % of its steady value.
WARMUP_TOL = 1e-5
#: ... and the transient must have settled within this many steps.
WARMUP_MAX_STEPS = 100_000
#: Largest order of the augmented state for which the dense Lyapunov solve is done.
MAX_ORDER = 4000
#: The largest loop (nN (1 + largest delay)) whose residual tests are computed for the
#: agents of a run: by each agent at its start (the initial configuration) and by the
#: monitor's gain worker for every configuration it designs gains for. paper-14-live with
#: its own delays (order 126) takes 0.02 s; at 7-step delays (order 336) 22 s and at 15
#: (672) 95 s on this machine under load: too long for a process's start or a switch.
AGENT_MAX_ORDER = 200

INNOVATION = "innovation"
DISCREPANCY = "discrepancy"
#: Explanations whose scores are within this factor of the best are a near-tie, broken by
#: the agents' own innovation levels (see :func:`isolate`).
TIE_RATIO = 1.5
#: Verdict kinds.
SENSOR_BIAS = "sensor bias"
INCONSISTENT = "inconsistent estimates"


class ResidualError(SocmonError):
    """Bad arguments to the residual tests (the message names the argument)."""


@dataclass(frozen=True, eq=False)
class Residual:
    """One tested residual: an agent's innovation, or one of its links' discrepancy.

    Attributes
    ----------
    name : str
        ``"innovation 2"`` or ``"link 3->2"`` (1-based agent ids, sender -> receiver).
    kind : str
        ``"innovation"`` or ``"discrepancy"``.
    agent : int
        0-based row of the agent that computes it (the receiver of a link).
    sender : int or None
        0-based row of the in-neighbour (discrepancy only).
    age : int or None
        ``1 + tau``: the power of A that propagates the sender's estimate.
    offset : int
        First column of this residual in the stacked residual vector.
    dim, dof : int
        Dimension of the residual (p_i or n) and degrees of freedom of its statistic.
    cov_step : (dim, dim) array
        Steady covariance of the residual at one step, ``Gamma(0)``.
    cov_window : (dim, dim) array
        Exact covariance of the window sum, ``Sigma``.
    whiten : (dof, dim) array
        ``T = ||whiten @ s||^2`` for a window sum ``s``.
    alpha : float
        False-alarm probability of this statistic at one step.
    threshold : float
        ``chi2.isf(alpha * (1 - NULL_SHARE), dof)`` (``chi2.isf(alpha, dof)`` when
        ``Sigma`` is regular).
    null_basis : (dim, dim - dof) array or None
        The discarded directions (variance below ``null_floor``), when there are any.
    null_floor : float
        :data:`RANK_RTOL` times the largest eigenvalue of ``Sigma``.
    null_threshold : float
        ``chi2.isf(alpha * NULL_SHARE, dim - dof)``: the null-space test alarms when
        ``||null_basis^T s||^2 / null_floor`` exceeds it. Each discarded direction has a
        variance below the floor, so its false-alarm probability is at most
        ``alpha * NULL_SHARE`` (a bound, not exact: in practice far below).
    """

    name: str
    kind: str
    agent: int
    sender: int | None
    age: int | None
    offset: int
    dim: int
    dof: int
    cov_step: np.ndarray
    cov_window: np.ndarray
    whiten: np.ndarray
    alpha: float
    threshold: float
    null_basis: np.ndarray | None = None
    null_floor: float = 0.0
    null_threshold: float = math.inf

    @property
    def singular(self) -> bool:
        """True when the window covariance is singular and its pseudo-inverse is used."""
        return self.dof < self.dim

    def statistic(self, s) -> np.ndarray:
        """``T = s^T Sigma^+ s`` of window sums ``s`` (..., dim), raised to the threshold
        scale of the null-space test when that one is the stronger alarm:
        ``max(T, T_null * threshold / null_threshold)``."""
        s = np.asarray(s)
        z = s @ self.whiten.T
        T = np.einsum("...i,...i->...", z, z)
        if self.null_basis is None:
            return T
        zn = s @ self.null_basis
        Tn = np.einsum("...i,...i->...", zn, zn) / self.null_floor
        return np.maximum(T, Tn * (self.threshold / self.null_threshold))


@dataclass(frozen=True, eq=False)
class ResidualTest:
    """The residual tests of one configuration (scenario, gains, delays).

    Attributes
    ----------
    residuals : tuple of Residual
        Innovations of agents 0..N-1, then the discrepancies of every link, receivers in
        order and senders in order within a receiver.
    window : int
    alpha : float
        False-alarm probability per agent per step.
    warmup : int
        Steps of the initial transient: a residual is used from step ``warmup + 1`` on.
    rho : float
        Spectral radius of the closed loop.
    N, n : int
    """

    residuals: tuple
    window: int
    alpha: float
    warmup: int
    rho: float
    N: int
    n: int
    delays: np.ndarray = field(repr=False, default=None)

    @property
    def first_step(self) -> int:
        """First step whose statistic is tested (its window holds settled steps only)."""
        return self.warmup + self.window

    @property
    def dim(self) -> int:
        """Length of the stacked residual vector."""
        return sum(r.dim for r in self.residuals)

    @property
    def thresholds(self) -> np.ndarray:
        return np.array([r.threshold for r in self.residuals])

    @property
    def names(self) -> list:
        return [r.name for r in self.residuals]

    def for_agent(self, i: int) -> list:
        """The residuals agent row ``i`` computes (its innovation first)."""
        return [r for r in self.residuals if r.agent == i]

    def statistics(self, sums) -> np.ndarray:
        """Statistics (..., S) of stacked window sums (..., dim)."""
        sums = np.asarray(sums)
        return np.stack([r.statistic(sums[..., r.offset:r.offset + r.dim])
                         for r in self.residuals], axis=-1)

    def window_statistics(self, vectors) -> np.ndarray:
        """Statistics (..., steps+1, S) of stacked residual vectors (..., steps+1, dim)
        indexed by step (NaN where a window is not complete or not settled)."""
        v = np.asarray(vectors, dtype=float)
        steps = v.shape[-2] - 1
        out = np.full(v.shape[:-1] + (len(self.residuals),), np.nan)
        if steps < self.first_step:
            return out
        c = np.cumsum(v, axis=-2)
        k = np.arange(self.first_step, steps + 1)
        sums = c[..., k, :] - c[..., k - self.window, :]
        out[..., k, :] = self.statistics(sums)
        return out

    def levels(self, stats) -> np.ndarray:
        """Statistics divided by their thresholds (>= 1 is an alarm)."""
        return np.asarray(stats) / self.thresholds

    def expected_false_alarms(self, steps: int) -> float:
        """Expected alarm steps (all statistics) of a healthy run of ``steps`` steps."""
        tested = max(0, int(steps) - self.first_step + 1)
        return tested * sum(r.alpha for r in self.residuals)

    def receivers(self, j: int) -> list:
        """0-based rows of the agents that receive agent ``j``'s estimates."""
        return [r.agent for r in self.residuals if r.sender == j]


def _check_window_alpha(window, alpha):
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 1:
        raise ResidualError(f"window: must be an integer >= 1, got {window!r}")
    if isinstance(alpha, bool) or not isinstance(alpha, (int, float, np.floating)) \
            or not 0 < alpha < 1:
        raise ResidualError(f"alpha: must be a probability in (0, 1), got {alpha!r}")


def _links(loop: ClosedLoop) -> list:
    """(receiver i, sender j, tau) for every link j -> i of W, receivers in order."""
    return [(i, j, int(loop.delays[i, j])) for i in range(loop.N) for j in range(loop.N)
            if j != i and loop.W[i, j] > 0]


def residual_state_space(loop: ClosedLoop, q: float, r: float):
    """``(M, B, Cv, Dv, layout)``: the stacked residuals as outputs of the loop's noise
    state space (:meth:`ClosedLoop.noise_state_space`).

    ``xi_{k+1} = M xi_k + B w_k`` and the residuals of step k+1 are
    ``v_{k+1} = Cv xi_k + Dv w_k`` (``w_k`` = unit-variance ``nu_k``, ``zeta_{k+1}``).
    ``layout`` lists ``(kind, agent, sender, age, offset, dim)`` per residual.
    """
    n, N, T = loop.n, loop.N, loop.taubar
    m = n * N
    M, B, _ = loop.noise_state_space(q, r)
    order = M.shape[0]
    nu0 = (T + 1) * m                         # first column of the noise window
    Ap = loop.A_powers
    p_of = [len(mi) for mi in loop.measure]
    p = sum(p_of)
    nin = n + p                               # inputs: nu_k (n), zeta_{k+1} (p)
    # prior error of every agent at step k+1
    Cp = np.zeros((m, order))
    Dp = np.zeros((m, nin))
    for i in range(N):
        for j in range(N):
            w = loop.W[i, j]
            if w <= 0:
                continue
            tau = int(loop.delays[i, j]) if j != i else 0
            Cp[i * n:(i + 1) * n, tau * m + j * n: tau * m + (j + 1) * n] += w * Ap[tau + 1]
            # S_{1+tau}(k+1) = sum_{s=0..tau} A^s nu_{k-s}
            Dp[i * n:(i + 1) * n, :n] += w * np.sqrt(q) * Ap[0]
            for s in range(1, tau + 1):
                Cp[i * n:(i + 1) * n, nu0 + (s - 1) * n: nu0 + s * n] += w * Ap[s]
    rows_C, rows_D, layout = [], [], []
    offset = 0
    zcol = n
    for i in range(N):
        sel = [i * n + v for v in loop.measure[i]]
        Ci = Cp[sel]
        Di = Dp[sel].copy()
        Di[:, zcol:zcol + p_of[i]] += np.sqrt(r) * np.eye(p_of[i])
        zcol += p_of[i]
        rows_C.append(Ci)
        rows_D.append(Di)
        layout.append((INNOVATION, i, None, None, offset, p_of[i]))
        offset += p_of[i]
    for i, j, tau in _links(loop):
        Ci = Cp[i * n:(i + 1) * n].copy()
        Di = Dp[i * n:(i + 1) * n].copy()
        Ci[:, tau * m + j * n: tau * m + (j + 1) * n] -= Ap[tau + 1]
        Di[:, :n] -= np.sqrt(q) * Ap[0]
        for s in range(1, tau + 1):
            Ci[:, nu0 + (s - 1) * n: nu0 + s * n] -= Ap[s]
        rows_C.append(Ci)
        rows_D.append(Di)
        layout.append((DISCREPANCY, i, j, tau + 1, offset, n))
        offset += n
    return M, B, np.vstack(rows_C), np.vstack(rows_D), layout


def residual_autocovariances(loop: ClosedLoop, q: float, r: float, lags: int):
    """``[Gamma(0), ..., Gamma(lags)]`` of the stacked residuals on the healthy loop in
    steady state, ``Gamma(l) = Cov(v_{k+l}, v_k)``, and the layout of
    :func:`residual_state_space`. Raises ResidualError if the loop is not stable."""
    out, layout, _M, _Cv, _P = _steady(loop, q, r, lags)
    return out, layout


def _steady(loop, q, r, lags):
    rho = loop.spectral_radius()
    if not rho < 1:
        raise ResidualError(f"gains: the closed loop is not stable (rho = {rho:.6g}): the "
                            "residuals have no steady covariance")
    M, B, Cv, Dv, layout = residual_state_space(loop, q, r)
    if M.shape[0] > MAX_ORDER:
        raise ResidualError(f"scenario: the loop's augmented state has order {M.shape[0]}, "
                            f"above {MAX_ORDER} (dense Lyapunov solve)")
    P = sla.solve_discrete_lyapunov(M, B @ B.T)
    P = 0.5 * (P + P.T)
    out = [Cv @ P @ Cv.T + Dv @ Dv.T]
    X = M @ P @ Cv.T + B @ Dv.T
    for _ in range(int(lags)):
        out.append(Cv @ X)
        X = M @ X
    return out, layout, M, Cv, P


def _warmup(loop, M, P, blocks, window) -> int:
    """Steps after which every window statistic's covariance is within
    :data:`WARMUP_TOL` of the steady one, in its own whitened coordinates.

    The augmented state's covariance at step t differs from the steady ``P`` by
    ``M^t D M^t^T``; the whitened window sum's deviation is then at most
    ``(sum over the window of ||Wh C M^(t-1)||_2)^2 ||D||_2``. ``||D||_2`` is bounded by
    ``||P|| + (N + 1) max(1, ||A||_2^2)^(taubar+1)``: the initial errors ``x_0 - xhat^i_0``
    (unit normal draws, the truth common to all agents: covariance ``(J + I) (x) I``,
    norm N + 1) grown for at most ``taubar + 1`` steps before every link carries an
    estimate (the loop proper starts then).
    """
    grow = max(1.0, float(np.linalg.norm(loop.A, 2)) ** 2) ** (loop.taubar + 1)
    D = float(np.linalg.norm(P, 2)) + (loop.N + 1) * grow
    start = loop.taubar + 1
    norms = []          # per step t: max over residuals of ||Wh C M^t||_2 (t from 0)
    # the rows Wh C of every residual, stacked, carried forward as Z_t = (Wh C) M^t: a few
    # rows times M per step, not the order-cubed power M^t (the urgent design of an
    # unforeseen failure waited for this)
    # (M is a delayed loop's augmented state: a few per cent of it is not zero)
    blocks = [(Wh, C) for Wh, C in blocks if Wh.shape[0]]     # a block of no rows: norm 0
    if not blocks:
        return start + window
    Z = np.vstack([Wh @ C for Wh, C in blocks])
    Mt = sp.csr_matrix(M.T)
    cuts = np.cumsum([0] + [Wh.shape[0] for Wh, _C in blocks])
    for t in range(WARMUP_MAX_STEPS):
        # ||Z_b||_2^2 is the largest eigenvalue of Z_b Z_b^T (a few rows square)
        norms.append(math.sqrt(max(max(float(np.linalg.eigvalsh(Z[a:b] @ Z[a:b].T)[-1]), 0.0)
                                   for a, b in zip(cuts, cuts[1:]))))
        if t + 1 >= window:
            worst = sum(norms[t + 1 - window:t + 1])
            if worst * worst * D <= WARMUP_TOL:
                return start + t + 1
        Z = (Mt @ Z.T).T
    raise ResidualError(f"gains: the loop's transient has not settled after "
                        f"{WARMUP_MAX_STEPS} steps (too close to the unit circle)")


def window_covariance(gammas, window: int) -> np.ndarray:
    """Covariance of the sum of ``window`` consecutive residuals from the
    autocovariances ``gammas[l] = Cov(v_{k+l}, v_k)``, l = 0..window-1."""
    S = window * gammas[0]
    for lag in range(1, window):
        S = S + (window - lag) * (gammas[lag] + gammas[lag].T)
    return 0.5 * (S + S.T)


def _whitening(S):
    """``(whiten, null_basis, floor)`` of a covariance: eigen-whitening of the directions
    above the floor (``RANK_RTOL`` times the largest eigenvalue), and the others."""
    lam, V = np.linalg.eigh(S)
    top = float(lam.max()) if lam.size else 0.0
    floor = RANK_RTOL * top
    keep = lam > floor if top > 0 else np.zeros_like(lam, bool)
    null = V[:, ~keep] if (~keep).any() and top > 0 else None
    return (V[:, keep] / np.sqrt(lam[keep])).T, null, floor


def _full_whitening(r: Residual) -> np.ndarray:
    """The main whitening and the null directions scaled by the floor: the transient
    must be negligible on both tests' scales."""
    if r.null_basis is None:
        return r.whiten
    return np.vstack([r.whiten, r.null_basis.T / np.sqrt(r.null_floor)])


def residual_test(scenario, G, delays=None, window: int = DEFAULT_WINDOW,
                  alpha: float = DEFAULT_ALPHA) -> ResidualTest:
    """The residual tests of ``scenario`` with gains ``G`` and ``delays`` (default: the
    scenario's), computed once from the exact closed loop.

    Parameters
    ----------
    scenario : Scenario
    G : list of arrays or Gains
    delays : (N, N) int array, optional
    window : int >= 1
        Steps summed by each statistic.
    alpha : float in (0, 1)
        False-alarm probability per agent per step (split over the agent's tests).

    Raises
    ------
    ResidualError
        The loop is not stable, or a bad ``window``/``alpha``.
    """
    _check_window_alpha(window, alpha)
    G = list(getattr(G, "G", G))
    loop = closed_loop_for(scenario, G, delays)
    q, r = float(scenario.process_noise), float(scenario.measurement_noise)
    gammas, layout, M, Cv, P = _steady(loop, q, r, window - 1)
    tests_of = [1 + sum(1 for (_k, a, *_rest) in layout if a == i and _k == DISCREPANCY)
                for i in range(loop.N)]
    residuals = []
    for kind, i, j, age, offset, dim in layout:
        sl = slice(offset, offset + dim)
        Sw = window_covariance([g[sl, sl] for g in gammas], window)
        Wh, null, floor = _whitening(Sw)
        dof = Wh.shape[0]
        a = alpha / tests_of[i]
        a_main = a if null is None else a * (1 - NULL_SHARE)
        name = f"innovation {i + 1}" if kind == INNOVATION else f"link {j + 1}->{i + 1}"
        residuals.append(Residual(
            name=name, kind=kind, agent=i, sender=j, age=age, offset=offset, dim=dim,
            dof=dof, cov_step=gammas[0][sl, sl], cov_window=Sw, whiten=Wh, alpha=a,
            threshold=(float(_stats.chi2.isf(a_main, dof)) if dof else
                       float(_stats.chi2.isf(a * NULL_SHARE, null.shape[1]))),
            null_basis=null, null_floor=floor,
            null_threshold=(float(_stats.chi2.isf(a * NULL_SHARE, null.shape[1]))
                            if null is not None else math.inf)))
    rho = float(loop.spectral_radius())
    warmup = _warmup(loop, M, P, [(_full_whitening(r), Cv[r.offset:r.offset + r.dim])
                                  for r in residuals], window)
    return ResidualTest(residuals=tuple(residuals), window=int(window), alpha=float(alpha),
                        warmup=int(warmup), rho=rho, N=loop.N, n=loop.n,
                        delays=np.array(loop.delays))


def first_alarms(stats, thresholds, start: int = 0) -> np.ndarray:
    """First step >= ``start`` at which each statistic exceeds its threshold.

    ``stats`` (..., steps+1, S) (NaN never alarms); returns (..., S) ints, -1 where
    there is no alarm.
    """
    stats = np.asarray(stats)
    with np.errstate(invalid="ignore"):
        hit = stats > np.asarray(thresholds)
    hit[..., :start, :] = False
    anyhit = hit.any(axis=-2)
    first = np.argmax(hit, axis=-2)
    return np.where(anyhit, first, -1)


# ---------------------------------------------------------------------------------
# isolation


@dataclass(frozen=True)
class AgentReport:
    """What one agent reports at a step: its tests' levels (statistic / threshold).

    ``innovation`` is the level of its own innovation test; ``discrepancy`` maps each
    in-neighbour (0-based row, or any id used consistently) to the level of its test on
    that link. A level >= 1 is an alarm; booleans are accepted (True = 1, an alarm).
    """

    agent: int
    innovation: float
    discrepancy: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Verdict:
    """The agent found at fault, the kind of fault, and why.

    ``alternatives`` lists the other explanations the reports do not exclude, strongest
    first (``(agent, kind, score)``); ``score`` is the level of the verdict's evidence.
    ``flagged_by`` is ``((receiver, level), ...)``, by receiver, for the kinds read from
    the receivers' links (``inconsistent estimates``, absorbed ``sensor bias``).
    ``corroborated`` is True only for an ``inconsistent estimates`` verdict that other
    agents' independent reports establish and nothing else explains (the rule:
    :func:`isolate`): the one verdict a monitor may convict on.
    """

    agent: int
    kind: str
    evidence: tuple
    score: float
    alternatives: tuple = ()
    flagged_by: tuple = ()
    corroborated: bool = False


def isolate(reports) -> Verdict | None:
    """Name the faulty agent from per-agent reports, or None when nothing alarms.

    Rules (levels are statistic / threshold, >= 1 an alarm; "a flags b" means agent a's
    test on the link b -> a alarms):

    - **sensor bias** of agent a, direct: a's own innovation alarms. Score: its level.
      A faulty sensor enters the loop through its own agent's update, so it shows first
      in that agent's innovation.
    - **sensor bias** of agent a, absorbed: a's innovation is quiet but every receiver
      of a flags a, and a's tests on each of its senders are within a factor
      :data:`TIE_RATIO` of that (alarming or not): a's estimate is away from all of its
      neighbours, both ways (the estimator has taken the bias into its state). Score:
      the weakest receiver's level.
    - **inconsistent estimates** of agent a (a lies about its estimate, its own state
      being honest): every receiver of a flags a, while a's own reports are quiet and
      more than :data:`TIE_RATIO` below that (its innovation, and its tests on its
      senders: its prediction agrees with them), and no link between two other agents
      alarms as strongly as the weakest of a's links (those are the lie spreading
      through the receivers, weaker and later). Score: the weakest of a's links.
    - Between the two (a's tests on its senders quiet but within the factor): neither.
    - The explanation with the highest score wins; explanations within a factor
      :data:`TIE_RATIO` of it are broken by the agent's own innovation level (a sensor
      fault raises it even below its threshold, a lie does not); the rest are returned
      as ``alternatives``.
    - Alarms that fit no rule give the kind ``"unexplained"`` naming the agent with the
      strongest alarm (its innovation, or the sender of the strongest link).

    **Corroborated** (:attr:`Verdict.corroborated`): an ``inconsistent estimates`` verdict
    of agent a (so a's own tests are quiet, more than :data:`TIE_RATIO` below the weakest
    of its links) such that

    1. a has at least two receivers, and every one flags it clearly, at
       :data:`TIE_RATIO` times its threshold or more: two independent reports or more,
       from agents other than a, each on its own link;
    2. nothing alarms at an agent that does not receive from a (a's own tests are quiet
       by the rule): with 1, every test there is more than :data:`TIE_RATIO` below the
       weakest of a's links;
    3. every other agent c that sends to a receiver of a also sends to a, or to an agent
       that does not receive from a (a structural condition: a lie of c, which also
       makes a's receivers' priors move, would show in a's own tests or by 2);
    4. no other explanation is within :data:`TIE_RATIO` of it (no near-tie).

    The margins of 1 and 2 are there because a fault that spreads through the loop
    (extra sensor noise, an absorbed bias) moves many tests together, and at the first
    alarm two of them may have crossed their thresholds by a hair before the others: on a
    4-agent network where each agent listens to the next two, 33 of 7,200 simulated
    sensor faults gave such a picture naming an honest agent without the margins, none
    with them; every lie of 0.5 noise std-devs or more on every component is still
    convicted (docs/residuals.md).

    With the rule's own conditions (a's tests quiet, no link between two other agents as
    strong as a's weakest) these make the link from a each receiver's strongest test: each
    receiver's report, taken alone, points at a. A lie enters each receiver's prior with
    the receiver's weight on a, so the receiver's other links may alarm too; how much
    depends on their whitening (on paper-14-live with every agent listening to both
    others, a lie of agent 3 shows at agent 2 on link 1->2 at 0.93 x its level on link
    3->2), so no margin is asked there.

    No other single fault gives that picture at the first alarm: a corrupted link, or a
    receiver propagating with a wrong delay, shows at one receiver only (1); a sensor
    fault of a receiver shows in that receiver's innovation, or makes it flag all its
    senders alike, a first (the rule); a fault of a third agent reaches a's own tests or
    an agent outside a's receivers (3, with the rule or 2). An estimate of a corrupted
    inside a, if a's own tests stay quiet, passes too: a is at fault either way. What it
    does not exclude: two faults at once, colluding agents (see below). A ``sensor bias``
    verdict is never corroborated: an agent's own innovation alarms first also when a
    fault elsewhere has reached its prior (docs/residuals.md: on paper-14-live a bias of
    agent 3 is first seen in agent 2's innovation in 1-3 % of the trials).

    What these reports cannot distinguish:

    - a fault inside the noise: an offset whose effect on the window sums is small
      against their covariance is not seen (``docs/residuals.md`` gives the sizes);
    - an agent with a single receiver: its lie shows on one link only, which a fault of
      that link (corrupted transport) or a receiver that propagates with a wrong delay
      also explains; the verdict says the evidence is not corroborated;
    - colluding agents: two liars telling the same lie look like one consistent pair;
      a liar whose receivers are all liars is not seen by anyone;
    - an absorbed sensor bias against an estimate corrupted inside the agent (a bug, a
      bad gain): both put the agent's estimate away from all its neighbours;
    - on a cycle where every agent has one sender and one receiver, an absorbed bias
      makes every link alarm at once: only the sub-threshold innovation levels tell the
      agents apart, and they may not (docs/residuals.md: isolation rate per agent);
    - a lie or a bias along directions the window covariance discards (pseudo-inverse);
    - once the fault has spread, honest agents' estimates are biased too (the loop
      carries the error): later alarms of honest agents are consequences, so the
      first alarms are the ones to judge (decide at the first alarm);
    - a slow drift can stay below the threshold while the estimate follows it.
    """
    reports = list(reports)
    innov = {rep.agent: float(rep.innovation) for rep in reports}
    links = {(j, rep.agent): float(level) for rep in reports
             for j, level in dict(rep.discrepancy).items()}
    if not any(v >= 1 for v in innov.values()) and not any(v >= 1 for v in links.values()):
        return None
    agents = sorted(set(innov) | {a for link in links for a in link})
    receivers = {a: sorted(i for (j, i) in links if j == a) for a in agents}
    senders = {a: sorted(j for (j, i) in links if i == a) for a in agents}

    def alarmed_touching(a):
        return sorted(link for link, v in links.items() if v >= 1 and a in link)

    hyps = []   # (score, agent, kind, evidence, flagged_by, corroborated)
    for a in agents:
        own = innov.get(a, 0.0)
        if own >= 1:
            ev = [f"innovation of agent {a} at {own:.3g} x its threshold"]
            if alarmed_touching(a):
                ev.append(f"links touching agent {a} alarm too (its estimate is off): "
                          f"{alarmed_touching(a)}")
            hyps.append((own, a, SENSOR_BIAS, tuple(ev), (), False))
            continue
        ins = [links[(j, a)] for j in senders[a]]
        outs = [links[(a, i)] for i in receivers[a]]
        if not outs or min(outs) < 1:
            continue
        weakest = min(outs)
        flagged = tuple((i, links[(a, i)]) for i in receivers[a])
        if ins and min(ins) * TIE_RATIO >= weakest:
            hyps.append((weakest, a, SENSOR_BIAS, (
                f"all receivers of agent {a} ({receivers[a]}) flag it (weakest "
                f"{weakest:.3g} x threshold) and it is as far from all its senders "
                f"{senders[a]} (weakest {min(ins):.3g})",
                f"its innovation is quiet ({own:.3g} x threshold): the bias is absorbed "
                "into its estimate, or its estimate is corrupted inside the agent"),
                flagged, False))
        elif max(ins, default=0.0) < 1 and max(ins, default=0.0) * TIE_RATIO < weakest:
            others = [v for link, v in links.items() if a not in link]
            if others and max(others) >= weakest:
                continue
            ev = [f"every receiver of agent {a} ({receivers[a]}) flags its estimate "
                  f"(weakest at {weakest:.3g} x threshold)",
                  f"agent {a}'s own tests are quiet (innovation {own:.3g} x threshold"
                  + (f", links from its senders {senders[a]}" if senders[a] else "") + ")"]
            if not any(v >= 1 for v in others):
                ev.append("no alarm between the other agents")
            # corroboration (see the docstring): clear alarms (weakest >= TIE_RATIO), and
            # nothing alarms at an agent that does not receive from a
            near = set(receivers[a])
            outside = sorted({i for (j, i), v in links.items() if v >= 1 and i not in near}
                             | {b for b, v in innov.items() if v >= 1 and b not in near})
            # ... and every other sender c of a's receivers is watched: it sends to a, or
            # to an agent outside a's receivers
            unwatched = sorted(c for c in {j for i in receivers[a] for j in senders[i]}
                               if c != a and c not in senders[a]
                               and set(receivers[c]) <= near | {a})
            if len(receivers[a]) == 1:
                ev.append("single receiver: not corroborated (a fault of that link, or a "
                          "receiver propagating with a wrong delay, looks the same)")
            elif weakest < TIE_RATIO:
                ev.append(f"not corroborated: its receivers' alarms are not clear (weakest "
                          f"{weakest:.3g} x threshold, below {TIE_RATIO:g})")
            elif outside:
                ev.append(f"not corroborated: agents {outside}, which do not receive from "
                          f"agent {a}, alarm too")
            elif unwatched:
                ev.append(f"not corroborated: a lie of agents {unwatched} (they send to "
                          f"agent {a}'s receivers only, not to agent {a}) could look the same")
            else:
                ev.append(f"corroborated: {len(receivers[a])} receivers flag it clearly, and "
                          "nothing alarms at an agent that does not receive from it")
            hyps.append((weakest, a, INCONSISTENT, tuple(ev), flagged,
                         len(receivers[a]) >= 2 and weakest >= TIE_RATIO and not outside
                         and not unwatched))
    if not hyps:
        (j, i), lv = max(links.items(), key=lambda kv: kv[1]) if links else ((None, None), -1)
        a, lv_a = max(innov.items(), key=lambda kv: kv[1]) if innov else (None, -1)
        if lv_a >= lv:
            return Verdict(a, "unexplained", (f"innovation of agent {a} at {lv_a:.3g} x "
                                              "threshold",), lv_a)
        return Verdict(j, "unexplained",
                       (f"link {j}->{i} at {lv:.3g} x threshold fits no rule (not every "
                        f"receiver of {j} flags it, or {j} also flags its senders)",), lv)
    hyps.sort(key=lambda h: h[0], reverse=True)
    best = hyps[0][0]
    close = [h for h in hyps if h[0] * TIE_RATIO >= best]
    if len(close) > 1:
        close.sort(key=lambda h: (innov.get(h[1], 0.0), h[0]), reverse=True)
        chosen = close[0]
        # a near-tie is never corroborated: another explanation is nearly as good
        ev = tuple(e for e in chosen[3] if not e.startswith("corroborated")) + (
            f"near-tie with {[(h[1], h[2]) for h in close[1:]]} broken by the innovation "
            f"level ({innov.get(chosen[1], 0.0):.3g})"
            + ("; not corroborated" if chosen[5] else ""),)
        chosen = (chosen[0], chosen[1], chosen[2], ev, chosen[4], False)
    else:
        chosen = hyps[0]
    alts = tuple((h[1], h[2], h[0]) for h in hyps if h is not chosen and h[1:3] != chosen[1:3])
    return Verdict(chosen[1], chosen[2], chosen[3], chosen[0], alts, flagged_by=chosen[4],
                   corroborated=chosen[5])


def reports_at(test: ResidualTest, levels) -> list:
    """:class:`AgentReport` per agent (0-based rows) from the levels (S,) of one step."""
    levels = np.asarray(levels, dtype=float)
    out = []
    for i in range(test.N):
        innov, disc = 0.0, {}
        for s, r in enumerate(test.residuals):
            if r.agent != i or not np.isfinite(levels[s]):
                continue
            if r.kind == INNOVATION:
                innov = float(levels[s])
            else:
                disc[r.sender] = float(levels[s])
        out.append(AgentReport(i, innov, disc))
    return out


@dataclass(frozen=True, eq=False)
class AgentTests:
    """One agent's residual tests of one configuration: what it runs
    (:class:`AgentResiduals`) and what an assignment carries to it (:meth:`to_wire`).

    ``agent`` is its id; ``residuals`` its :class:`Residual` tests, its innovation first,
    named and keyed by agent id (``sender`` is the in-neighbour's id, ``agent`` its own);
    ``window`` and ``warmup`` as in :class:`ResidualTest` (the warm-up counts from the
    configuration's first step). Rebuilt from the wire (:meth:`from_wire`), a residual
    keeps what its statistic needs: ``cov_step`` and ``cov_window`` are None.
    """

    agent: int
    residuals: tuple
    window: int
    warmup: int

    @property
    def first_step(self) -> int:
        return self.warmup + self.window

    def to_wire(self) -> dict:
        """The assignment's ``residuals`` field (docs/runtime.md): ``window``, ``warmup``
        and per test ``from`` (the sender's id, 0 for the innovation), ``age`` (0 for the
        innovation), ``whiten``, ``alpha``, ``threshold`` and, for a singular one,
        ``null``, ``null_floor`` and ``null_threshold``."""
        tests = []
        for r in self.residuals:
            t = {"from": 0 if r.sender is None else int(r.sender),
                 "age": 0 if r.age is None else int(r.age),
                 "whiten": np.ascontiguousarray(r.whiten, dtype=float),
                 "alpha": float(r.alpha), "threshold": float(r.threshold)}
            if r.null_basis is not None:
                t.update(null=np.ascontiguousarray(r.null_basis, dtype=float),
                         null_floor=float(r.null_floor),
                         null_threshold=float(r.null_threshold))
            tests.append(t)
        return {"window": int(self.window), "warmup": int(self.warmup), "tests": tests}

    @classmethod
    def from_wire(cls, agent: int, msg: dict, n: int, measured: int,
                  neighbours) -> "AgentTests":
        """The tests of agent ``agent`` from an assignment's ``residuals`` field (its
        structure and types checked by the wire schema), checked against the role they
        come with: ``n`` states, ``measured`` readings, the in-neighbour ids
        ``neighbours``. Raises ResidualError naming every problem."""
        problems, residuals = [], []
        tests = list(msg["tests"])
        innovations = [t for t in tests if t["from"] == 0]
        if len(innovations) != 1 or tests[0]["from"] != 0:
            problems.append("residuals: the innovation's test must come first, once")
        senders = [t["from"] for t in tests if t["from"] != 0]
        strangers = sorted(set(senders) - set(neighbours))
        if strangers or len(set(senders)) != len(senders):
            problems.append(f"residuals: links from {sorted(senders)} are not this role's "
                            f"in-neighbours {sorted(neighbours)} once each")
        for t in tests:
            sender = t["from"] or None
            dim = n if sender is not None else int(measured)
            W = np.asarray(t["whiten"], dtype=float)
            null = t.get("null")
            name = (f"innovation {agent}" if sender is None else f"link {sender}->{agent}")
            k = 0 if null is None else np.shape(null)[1]
            bad = []
            if W.ndim != 2 or W.shape[1] != dim or W.shape[0] + k > dim:
                bad.append(f"whiten {W.shape} for a residual of {dim}")
            if null is not None and (np.ndim(null) != 2 or np.shape(null)[0] != dim or k < 1):
                bad.append(f"null {np.shape(null)} for a residual of {dim}")
            if (sender is None) != (t["age"] == 0):
                bad.append(f"age {t['age']}")
            if not t["threshold"] > 0:
                bad.append("threshold must be > 0")
            if null is not None and not (t.get("null_floor", 0) > 0
                                         and t.get("null_threshold", 0) > 0):
                bad.append("null_floor and null_threshold must be > 0 with null")
            if bad:
                problems.append(f"residuals: {name}: " + ", ".join(bad))
                continue
            residuals.append(Residual(
                name=name, kind=INNOVATION if sender is None else DISCREPANCY, agent=agent,
                sender=sender, age=t["age"] or None, offset=0, dim=dim,
                dof=W.shape[0], cov_step=None, cov_window=None, whiten=W,
                alpha=float(t["alpha"]), threshold=float(t["threshold"]),
                null_basis=None if null is None else np.asarray(null, dtype=float),
                null_floor=float(t.get("null_floor", 0.0)),
                null_threshold=float(t.get("null_threshold", math.inf))))
        if problems:
            raise ResidualError("; ".join(problems))
        return cls(agent=int(agent), residuals=tuple(residuals), window=int(msg["window"]),
                   warmup=int(msg["warmup"]))


def agent_tests(test: ResidualTest, ids=None) -> dict:
    """``{agent id: AgentTests}`` of every agent of ``test``'s configuration, row i held
    by ``ids[i]`` (default ``1..N``: the initial configuration, whose names are
    ``test``'s own).

    >>> import numpy as np
    >>> from design.scenario import load_scenario
    >>> s = load_scenario("paper-14-live")
    >>> G = [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure]
    >>> tests = agent_tests(residual_test(s, G, window=2), ids=(4, 2, 3))
    >>> [r.name for r in tests[4].residuals]
    ['innovation 4', 'link 2->4']
    """
    ids = tuple(range(1, test.N + 1)) if ids is None else tuple(int(a) for a in ids)
    if len(ids) != test.N:
        raise ResidualError(f"ids: {len(ids)} ids for a configuration of {test.N} agents")
    out = {}
    for row, a in enumerate(ids):
        mine = []
        for r in test.for_agent(row):
            sender = None if r.sender is None else ids[r.sender]
            mine.append(dataclasses.replace(
                r, agent=a, sender=sender,
                name=f"innovation {a}" if sender is None else f"link {sender}->{a}"))
        out[a] = AgentTests(agent=a, residuals=tuple(mine), window=test.window,
                            warmup=test.warmup)
    return out


def configuration_tests(scenario, G, delays, ids=None, max_order: int = AGENT_MAX_ORDER,
                        **kwargs) -> dict:
    """:func:`agent_tests` of :func:`residual_test` of a configuration (rows held by
    ``ids``), or ``{}`` when its loop is above ``max_order`` or not stable (no steady
    covariance to test against)."""
    D = np.asarray(scenario.delays if delays is None else delays)
    top = int(D.max()) if D.size else 0
    if scenario.n * scenario.N * (1 + top) > max_order:
        return {}
    try:
        return agent_tests(residual_test(scenario, G, D, **kwargs), ids)
    except (ResidualError, np.linalg.LinAlgError, ValueError):
        # not stable, or a solve that failed: no tests (the caller's designs go on)
        return {}


class AgentResiduals:
    """One agent's residual tests, stepped as it computes (what a live agent runs).

    ``tests`` are its :class:`AgentTests` of the configuration in force (under ``epoch``,
    from step ``start``: its warm-up counts from there, as from a run's start). At each
    step :meth:`step` takes the agent's innovation (None when some readings were missing)
    and, per in-neighbour id, the discrepancy of the estimate it used (None when that
    estimate was not the on-time one: held, late or lost). A residual that is None starts
    its window over: a late or held estimate is outside the distribution the threshold
    was computed for, so its test resumes ``window`` fresh steps later. Returns
    ``{residual name: level}`` of the statistics formed at that step (statistic /
    threshold; >= 1 is an alarm), as :meth:`ResidualTest.window_statistics` forms them
    for the simulator.

    >>> import numpy as np
    >>> from design.scenario import load_scenario
    >>> s = load_scenario("paper-14-live")
    >>> G = [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure]
    >>> res = AgentResiduals(agent_tests(residual_test(s, G, window=2))[1])
    >>> [r.name for r in res.residuals]
    ['innovation 1', 'link 2->1']
    >>> res.step(1, np.zeros(1), {2: np.zeros(s.n)})    # in the warm-up: nothing formed
    {}
    """

    def __init__(self, tests: AgentTests, epoch: int = 0, start: int | None = None):
        self.tests = tests
        self.epoch = int(epoch)
        self.residuals = list(tests.residuals)
        self.window = tests.window
        self.warmup = tests.warmup
        self.first_step = tests.first_step
        #: in-neighbour id -> the age its link is tested at (``1 + tau``): an estimate of
        #: another age (a delay learned otherwise) is outside the tested distribution
        self.link_age = {r.sender: r.age for r in self.residuals if r.sender is not None}
        self._rings = {r.name: [] for r in self.residuals}
        self.disturbed_at = None          # the last step whose inputs were not on time
        if start is not None:
            self.disturb(start)

    def disturb(self, k: int) -> None:
        """Step k ran on inputs the thresholds do not cover (a held, late or lost
        neighbour estimate, missing readings, the configuration's first step): the
        agent's own error left the healthy loop's distribution, and so do its later
        residuals until the transient decays. Every test starts over ``warmup`` steps
        later (as after the start)."""
        self.disturbed_at = int(k)
        for ring in self._rings.values():
            ring.clear()

    def step(self, k: int, innovation, discrepancies: dict) -> dict:
        levels = {}
        quiet = self.warmup if self.disturbed_at is None \
            else self.disturbed_at + self.warmup
        for r in self.residuals:
            v = innovation if r.sender is None else discrepancies.get(r.sender)
            ring = self._rings[r.name]
            if v is None or k <= quiet:
                ring.clear()
                continue
            ring.append(np.asarray(v, dtype=float))
            if len(ring) > self.window:
                ring.pop(0)
            if len(ring) == self.window and k >= self.first_step:
                levels[r.name] = float(r.statistic(np.sum(ring, axis=0)) / r.threshold)
        return levels
