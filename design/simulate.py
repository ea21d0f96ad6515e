"""Monte-Carlo simulation of the distributed estimator, vectorised across trials.

Every random number comes from :mod:`design.noise` and every estimator update is
:func:`design.estimator.estimator_step` (with the trials as its batch axis), so a live
run with the same seed reproduces trial 0 of a simulation.

Timeline (k = 0, 1, ..., steps)
-------------------------------
- ``x_0 = noise.initial_state(seed)``; ``x_{k+1} = A x_k + nu_k`` with
  ``nu_k = noise.process_noise(seed, k)``.
- Agent with id ``a`` (1-based) holds ``xhat^a_0 = noise.initial_estimate(seed, a)`` at
  step 0, stamped 0. Nothing exists before step 0: an estimate stamped s < 0 is never
  held. Agents compute steps k = 1..steps.
- At step k agent i first receives: on each link j -> i with delay tau (the current
  configuration's), the estimate of j stamped ``s = k - 1 - tau`` arrives unless
  ``s < 0``, j had not published stamp s, or ``noise.message_dropped(seed, j, i, s, drop)``
  says it is lost. Agent i keeps, per neighbour, the freshest estimate received so far.
- Then it calls ``estimator_step`` with its own ``xhat^i_{k-1}``, each neighbour's
  freshest held estimate with ``age = k - stamp`` (``1 + tau`` when on time; older when
  the on-time one was dropped, propagated by ``A^age``) or ``x=None`` when nothing is
  held (its weight goes to self), and ``y^i_k = H_i x_k + zeta^i_k`` with
  ``zeta^i_k = noise.measurement_noise(seed, i, k)``. The result ``xhat^i_k`` is
  published with stamp k.
- The neighbour policy is :func:`design.estimator.neighbour_input`, the same as a live
  agent's: a held estimate is used while its age is at most ``max_age`` (default
  :func:`design.estimator.hold_limit` of the largest delay), then its weight goes to self.
- Failure at step f of agents F: they do not compute step f or later. What they
  published (stamps <= f - 1) still arrives on its links' delays, and their neighbours
  hold and propagate it like any late or lost estimate until it is older than
  ``max_age``; their error leaves the MSE from step f on. This is exactly what a live
  agent does when a neighbour crashes after publishing step f - 1.
- Recovery at step a = ``recover.activate_at`` (default f): the configuration of
  :class:`Recovery` (its W, delays, sensors and gains) is used from step a on. Surviving
  agents keep their estimates and what they hold. A replacement agent takes over, as its
  own estimate stamped a - 1 (published with that stamp), the freshest estimate of the
  failed agent it replaces that it has received, propagated to step a - 1: ``xhat_{f-1}``
  (``A^(a-f) xhat_{f-1}``) once that has crossed the standby's link (the run's largest
  delay T), else ``xhat_{a-1-T}``, as a live standby does with ``take_over``; a new agent that
  replaces nobody starts from ``noise.initial_estimate(seed, id)``. Agents hold nothing
  from a new agent until its messages arrive.

Accuracy with unstable A
------------------------
``x_k`` grows like ``rho(A)^k``, so ``x - xhat`` computed from the two loses about
``k log10(rho(A))`` digits. By default (``coordinates="error"``) the simulator runs the
same estimator step on the estimates *relative to the truth*, ``z^i = xhat^i - x``: the
step is linear, and with ``x_k = A^a x_{k-a} + S_a(k)``,
``S_a(k) = sum_{m<a} A^m nu_{k-1-m}``, the relative prediction is the step's prediction
on relative estimates minus ``w_self S_1(k) + sum_j w_ij S_{a_j}(k)`` (passed to the step
as one extra input of age 0), and the relative measurement is ``zeta``. Nothing of the
size of ``x`` is formed, so the error keeps full precision for any number of steps
while the loop is stable (only a cold-started replacement forms ``x``, once).
``coordinates="absolute"`` runs ``x`` and ``xhat`` as a live run does.

Faults and residuals
--------------------
``faults`` (a sequence of :class:`Fault`) corrupt one agent from a step on: its readings
(``bias``: a constant offset; ``drift``: a growing one; ``noise``: the sensor noise
scaled) or what it publishes (``lie``: its estimate plus an offset, its own state staying
honest). Offsets are in measurement-noise std-devs ``sqrt(r)``, on every measured node
(readings) or every state component (a lie). A fault of a standby acts only while it
holds a role, as a live standby's. ``residuals`` (a
:class:`design.residuals.ResidualTest`, or True for the default one of the run's gains
and delays) makes the simulator form, per agent and step, its innovation and the
discrepancy with each in-neighbour's propagated estimate, and the windowed statistics of
:mod:`design.residuals` (:attr:`SimulationResult.residual_stats`), so that detection can
be swept offline over many trials. Both are off by default and cost nothing then.

Examples
--------
>>> import numpy as np
>>> from design.scenario import load_scenario
>>> s = load_scenario("paper-14")
>>> res = simulate(s, [np.zeros((14, 1))] * 3, steps=20, trials=4, seed=1)
>>> res.mse.shape, res.mse_trials.shape
((21,), (4, 21))
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from . import noise
from .errors import GainsError, SocmonError
from .estimator import (
    continued_stamp,
    AgentRole,
    NeighbourEstimate,
    PowerCache,
    estimator_step,
    hold_limit,
    neighbour_input,
)
from .gains import Gains, check_gains_fit
from .metrics import steady_mse, steady_window
from .residuals import ResidualTest, residual_test

__all__ = [
    "Fault",
    "FAULT_KINDS",
    "SENSOR_FAULT_KINDS",
    "apply_sensor_faults",
    "Recovery",
    "SimulationError",
    "SimulationResult",
    "simulate",
    "DIVERGENCE_FACTOR",
    "GROWTH_FACTOR",
]

#: A run has diverged if its steady MSE exceeds this factor times its initial MSE ...
DIVERGENCE_FACTOR = 1e3
#: ... and is still growing: more than this factor times the mean of the quarter before.
GROWTH_FACTOR = 2.0


class SimulationError(SocmonError):
    """Bad arguments to :func:`simulate` (the message names the argument)."""


#: Fault kinds of :class:`Fault`.
FAULT_KINDS = ("bias", "drift", "noise", "lie")


@dataclass(frozen=True)
class Fault:
    """One agent goes wrong from step ``start`` on.

    Attributes
    ----------
    kind : {"bias", "drift", "noise", "lie"}
        ``bias``: its readings get ``size * sqrt(r)`` on every measured node;
        ``drift``: ``size * sqrt(r) * (k - start + 1) / ramp`` at step k (``size`` std-devs
        after ``ramp`` steps, growing on); ``noise``: its sensor noise is multiplied by
        ``size``; ``lie``: the estimates it publishes (stamps >= start) carry
        ``size * sqrt(r)`` on every state component, its own estimate staying honest.
    agent : int
        0-based row of the agent in the initial scenario (it keeps its id after a
        recovery), or ``N + j`` for its standby ``j`` (id ``N + j + 1``), which goes wrong
        only while it holds a role (as a live standby: it computes and publishes nothing
        before), from the later of ``start`` and the first step it computes in one.
    start : int >= 1
    size : float
    ramp : int >= 1
        Steps for a drift to reach ``size``.
    direction : sequence of float, optional
        Shape of the offset (bias, drift: one entry per measured node; lie: one per
        state component), multiplied by the offset; default all ones.
    """

    kind: str
    agent: int
    start: int
    size: float
    ramp: int = 100
    direction: tuple | None = None

    def vector(self, length: int) -> np.ndarray:
        """The offset's shape (``direction``, or ones of ``length``)."""
        if self.direction is None:
            return np.ones(length)
        return np.asarray(self.direction, dtype=float)

    def offset(self, k: int, sigma: float) -> float:
        """The offset of step k, in the units of the readings (bias, drift, lie)."""
        if k < self.start:
            return 0.0
        if self.kind == "drift":
            return self.size * sigma * (k - self.start + 1) / self.ramp
        return self.size * sigma


#: The kinds of :class:`Fault` that act on an agent's readings.
SENSOR_FAULT_KINDS = ("bias", "drift", "noise")


def apply_sensor_faults(faults, k: int, zeta, sigma: float):
    """The measurement noise ``zeta`` of one agent's readings at step ``k`` (last axis:
    its measured nodes, in its role's order) with its sensor faults applied from their
    start: every ``noise`` fault scales it, then every ``bias`` and ``drift`` adds its
    offset (``sigma``: the sensor noise's standard deviation). The one rule of the
    simulator and of an agent process given scripted sensor faults
    (``socmon up --fault bias:...``); other kinds are left alone.

    >>> apply_sensor_faults([Fault("bias", 0, 10, 2.0), Fault("noise", 0, 5, 3.0)], 10,
    ...                     np.array([0.1, -0.1]), 0.5).tolist()
    [1.3, 0.7]
    >>> apply_sensor_faults([Fault("bias", 0, 10, 2.0)], 9, np.array([0.1]), 0.5).tolist()
    [0.1]
    """
    active = [f for f in faults if f.kind in SENSOR_FAULT_KINDS and k >= f.start]
    for f in active:
        if f.kind == "noise":
            zeta = zeta * f.size
    for f in active:
        if f.kind != "noise":
            zeta = zeta + f.offset(k, sigma) * f.vector(np.shape(zeta)[-1])
    return zeta


def _check_faults(faults, N, steps, n=None, measure=None, standby=0):
    out = {}
    M = N + standby
    for f in faults:
        if not isinstance(f, Fault):
            raise SimulationError(f"faults: expected Fault entries, got {type(f).__name__}")
        if f.kind not in FAULT_KINDS:
            raise SimulationError(f"faults: kind must be one of {FAULT_KINDS}, got {f.kind!r}")
        _check_int(f.agent, "fault agent row", 0)
        if f.agent >= M:
            raise SimulationError(f"faults: no agent row {f.agent} (rows are 0..{N - 1}"
                                  + (f", standbys {N}..{M - 1}" if standby else "") + ")")
        _check_int(f.start, "fault start", 1)
        _check_int(f.ramp, "fault ramp", 1)
        if isinstance(f.size, bool) or not isinstance(f.size, (int, float, np.floating)) \
                or not math.isfinite(f.size):
            raise SimulationError(f"faults: size must be a finite number, got {f.size!r}")
        if f.kind == "noise" and f.size < 0:
            raise SimulationError(f"faults: a noise factor must be >= 0, got {f.size!r}")
        if f.direction is not None and f.agent >= N and f.kind in ("bias", "drift"):
            raise SimulationError(f"faults: a {f.kind} fault of standby row {f.agent} takes "
                                  "no direction (the nodes it measures come with its role)")
        if f.direction is not None:
            want = {"lie": n, "noise": 0}.get(f.kind, len(measure[f.agent]) if measure else 0)
            d = np.asarray(f.direction, dtype=float)
            if d.ndim != 1 or d.size != want or not np.all(np.isfinite(d)):
                raise SimulationError(f"faults: the direction of a {f.kind} fault of agent row "
                                      f"{f.agent} must be {want} finite numbers, got "
                                      f"{f.direction!r}")
        out.setdefault(f.agent + 1, []).append(f)
    return out


@dataclass(frozen=True, eq=False)
class Recovery:
    """The configuration that takes over at the failure step.

    Attributes
    ----------
    scenario : Scenario
        The new configuration (same social system A and process noise; its own W,
        delays, sensors and measurement noise).
    G : list of arrays
        Gains for it, ``G[i]`` of shape n x p_i for row i of ``scenario``.
    ids : tuple of int
        1-based agent id of each row of ``scenario``: survivors keep their ids,
        replacement agents have new ids (e.g. standby ids N+1, ...).
    replaces : dict
        New id -> 0-based row (in the old configuration) of the failed agent whose last
        estimate it takes over. A new id absent from it starts cold from
        ``noise.initial_estimate(seed, id)``.
    delays : array or None
        Delay matrix used after the switch; default ``scenario.delays``.
    activate_at : int or None
        Step from which the new configuration is used (>= the failure step); None: the
        failure step (an instant recovery). A live run's monitor activates a few steps
        after it detected the failure.
    waiting : frozenset
        New ids that hold a row but have not started it (a live standby that heard its
        assignment after its step, until a re-issue): they compute and publish nothing
        (their receivers read, under ``replaces``'s continuity rule, only the failed
        agent's stream), and take over in the first later configuration that no longer
        names them here.
    """

    scenario: object
    G: list
    ids: tuple
    replaces: dict = field(default_factory=dict)
    delays: object = None
    activate_at: int | None = None
    waiting: frozenset = frozenset()

    @classmethod
    def from_plan(cls, plan, G, delays=None) -> "Recovery":
        """From a :class:`design.recovery.RecoveryPlan`: standbys take over the estimate
        of the failed agent whose place in W they take; survivors keep theirs."""
        if plan.scenario_after is None:
            raise SimulationError("recover: the recovery plan has no new configuration")
        replaces = {r.by: r.failed for r in plan.replacements if r.by_standby}
        return cls(scenario=plan.scenario_after, G=list(G), ids=tuple(plan.agent_ids),
                   replaces=replaces, delays=delays)

    def at(self, step: int) -> "Recovery":
        """The same recovery, activated at ``step``."""
        return Recovery(self.scenario, self.G, self.ids, self.replaces, self.delays, step,
                        self.waiting)


@dataclass(frozen=True, eq=False)
class SimulationResult:
    """Mean-squared error of a Monte-Carlo run.

    Attributes
    ----------
    mse : ndarray (steps+1,)
        ``mse[k]`` = mean over trials, active agents and state components of
        ``(xhat - x)^2`` at step k (k = 0 is the initial estimates' error).
    mse_trials : ndarray (trials, steps+1)
        The same per trial (mean over agents and states), for bands.
    mse_steady : float
        Mean of ``mse`` over the last quarter of the steps (``max(1, steps // 4)``
        steps, ending at ``steps``).
    diverged : bool
        Any non-finite error, or the error both grew a thousandfold and is still
        growing: ``mse_steady > DIVERGENCE_FACTOR * mse[0]`` and ``mse_steady >
        GROWTH_FACTOR *`` the mean of the quarter before. A stable loop with a large
        steady MSE is not "diverged".
    estimates : ndarray (trials, steps+1, len(estimate_ids), n) or None
        With ``record_estimates``: ``xhat^a_k`` of every agent id in ``estimate_ids``
        (NaN while the agent does not run: failed, or a replacement before it starts).
    estimate_ids : tuple of int
        1-based agent ids of the columns of ``estimates`` (agents 1..N, then new ids).
    residual_test : design.residuals.ResidualTest or None
        The tests whose statistics were formed (``residuals``).
    residual_stats : ndarray (trials, steps+1, S) or None
        Statistic of every residual of ``residual_test`` (column order of its
        ``residuals``) at every step; NaN before ``residual_test.first_step``.
    innovations : ndarray (trials, steps+1, p) or None
        The raw innovations ``y^i_k - H_i xhat^i_{k|k-1}``, agents in order (NaN at
        step 0), for baselines that test them directly.
    faults : tuple of Fault
    """

    mse: np.ndarray
    mse_trials: np.ndarray
    mse_steady: float
    diverged: bool
    trials: int
    steps: int
    seed: int
    drop: float = 0.0
    fail_step: int | None = None
    failed: tuple = ()
    recovered: bool = False
    coordinates: str = "error"
    estimates: np.ndarray | None = None
    estimate_ids: tuple = ()
    residual_test: object = None
    residual_stats: np.ndarray | None = None
    innovations: np.ndarray | None = None
    faults: tuple = ()

    def band(self, lo: float = 10.0, hi: float = 90.0):
        """Percentiles ``lo`` and ``hi`` across trials, per step."""
        with np.errstate(invalid="ignore"):
            return (np.percentile(self.mse_trials, lo, axis=0),
                    np.percentile(self.mse_trials, hi, axis=0))

    def to_dict(self, per_trial: bool = False) -> dict:
        """JSON-ready record (agents 1-based)."""
        out = {
            "mse": self.mse.tolist(),
            "mse_steady": float(self.mse_steady),
            "diverged": bool(self.diverged),
            "trials": int(self.trials),
            "steps": int(self.steps),
            "seed": int(self.seed),
            "drop": float(self.drop),
            "fail_step": self.fail_step,
            "failed": [int(a) for a in self.failed],
            "recovered": bool(self.recovered),
            "coordinates": self.coordinates,
        }
        if per_trial:
            out["mse_trials"] = self.mse_trials.tolist()
        return out


# ---------------------------------------------------------------------------------
# configuration of one phase (before / after the failure step)


@dataclass
class _Config:
    W: np.ndarray
    delays: np.ndarray
    ids: list           # row -> 1-based id
    roles: list         # row -> AgentRole
    r: float            # measurement noise variance
    dead: frozenset = frozenset()   # ids of failed agents (rows kept, not computed)

    @property
    def live(self) -> list:
        return [(i, a) for i, a in enumerate(self.ids) if a not in self.dead]

    @property
    def links(self):
        """(row i, row j, weight, delay) for every neighbour link j -> i."""
        out = []
        N = self.W.shape[0]
        for i in range(N):
            for j in range(N):
                if j != i and self.W[i, j] > 0:
                    out.append((i, j, float(self.W[i, j]), int(self.delays[i, j])))
        return out


def _config(scenario, G, delays, ids) -> _Config:
    roles = [
        AgentRole(measured=scenario.measure[i], self_weight=float(scenario.W[i, i]), G=G[i])
        for i in range(scenario.N)
    ]
    return _Config(W=np.asarray(scenario.W, float), delays=np.asarray(delays, int),
                   ids=list(ids), roles=roles, r=float(scenario.measurement_noise))


def _check_int(value, name, minimum):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise SimulationError(f"{name}: must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _gain_list(G, scenario, where):
    G = G.G if isinstance(G, Gains) else list(G)
    check_gains_fit(G, scenario, where=where)
    out = [np.asarray(g, dtype=float) for g in G]
    for i, g in enumerate(out):
        if not np.all(np.isfinite(g)):
            raise GainsError(f"{where}: K{i + 1} has non-finite entries")
    return out


def _check_delays(D, scenario, name):
    D = np.asarray(D)
    if D.shape != scenario.W.shape or not np.issubdtype(D.dtype, np.integer):
        raise SimulationError(
            f"{name}: must be an integer {scenario.N} x {scenario.N} matrix, got "
            f"{D.dtype} array of shape {D.shape}"
        )
    if np.any(D < 0):
        raise SimulationError(f"{name}: delays must be non-negative")
    return D.astype(int)


# ---------------------------------------------------------------------------------


def simulate(scenario, G, steps: int, trials: int, seed: int, delays=None, drop: float = 0.0,
             fail=None, recover: Recovery | None = None, progress=None,
             coordinates: str = "error", record_estimates: bool = False,
             max_age: int | None = None, faults=(), residuals=None) -> SimulationResult:
    """Run ``trials`` Monte-Carlo trials of the distributed estimator for ``steps`` steps.

    Parameters
    ----------
    scenario : Scenario
    G : list of arrays or Gains
        ``G[i]`` (n x p_i) for agent row i.
    steps, trials : int >= 1
    seed : int >= 0
        Key of every random number (see :mod:`design.noise`).
    delays : (N, N) int array, optional
        Link delays; default ``scenario.delays``.
    drop : float in [0, 1)
        Probability that one message (one estimate on one link) is lost.
    fail : (int, sequence of int) or sequence of them, optional
        ``(f, rows)``: the agents in 0-based ``rows`` fail at step f (1 <= f <= steps);
        a list of such pairs: failures at different steps (each row once). A
        replacement takes over the last estimate of the row it replaces, propagated from
        that row's own failure step.
    recover : Recovery or sequence of Recovery, optional
        Configuration that takes over at the failure step or at its ``activate_at``
        (needs ``fail``). A sequence is a chain of reassignments (a live monitor that
        answered two failures one after the other): increasing ``activate_at``; failed
        agents may appear in an intermediate configuration (they compute nothing), not
        in the last one; ``replaces`` always names rows of the initial scenario.
    progress : callable, optional
        Called as ``progress(k, steps)`` after each step.
    coordinates : {"error", "absolute"}
        Compute relative to the truth (default; accurate for unstable A over any
        length) or in absolute coordinates as a live run does.
    record_estimates : bool
        Keep every estimate in :attr:`SimulationResult.estimates`
        (needs ``coordinates="absolute"``: the numbers a live run computes).
    max_age : int, optional
        Oldest age at which a held neighbour estimate is used (the neighbour policy,
        :func:`design.estimator.neighbour_input`); default
        ``hold_limit(largest delay)``, the same default as a live agent's.
    faults : sequence of Fault, optional
        Sensor and agent faults (see :class:`Fault`).
    residuals : ResidualTest or True, optional
        Form the residual statistics (:attr:`SimulationResult.residual_stats`) of this
        test, or of ``design.residuals.residual_test(scenario, G, delays)`` for True.
        Needs ``drop=0`` and no ``fail``: the thresholds are those of the healthy,
        lossless configuration.

    Returns
    -------
    SimulationResult

    Raises
    ------
    SimulationError, GainsError
        Naming the argument that is wrong.
    """
    steps = _check_int(steps, "steps", 1)
    trials = _check_int(trials, "trials", 1)
    seed = _check_int(seed, "seed", 0)
    if coordinates not in ("error", "absolute"):
        raise SimulationError(f"coordinates: expected 'error' or 'absolute', got {coordinates!r}")
    if record_estimates and coordinates != "absolute":
        raise SimulationError("record_estimates: needs coordinates='absolute'")
    if isinstance(drop, bool) or not isinstance(drop, (int, float, np.floating)) \
            or not math.isfinite(drop) or not 0 <= drop < 1:
        raise SimulationError(f"drop: must be a probability in [0, 1), got {drop!r}")
    drop = float(drop)
    n, N = scenario.n, scenario.N
    G = _gain_list(G, scenario, "gains")
    D = _check_delays(scenario.delays if delays is None else delays, scenario, "delays")
    if np.any((D != 0) & ~(scenario.W > 0)) or np.any(np.diag(D) != 0):
        raise SimulationError("delays: nonzero delay off the links of W or on a self link")

    fail_step, failed = None, ()
    fail_at = {}        # 0-based row -> the step it fails
    if fail is not None:
        try:
            pairs = list(fail) if fail and isinstance(fail[0], (list, tuple)) else [fail]
            pairs = [(f, list(rows)) for f, rows in pairs]
        except (TypeError, ValueError, IndexError, KeyError):
            raise SimulationError(f"fail: expected (step, [agent rows]) or a list of them, "
                                  f"got {fail!r}") from None
        if not pairs:
            raise SimulationError("fail: an empty list of failures")
        for f, rows in pairs:
            f = _check_int(f, "fail step", 1)
            if f > steps:
                raise SimulationError(f"fail step: {f} is after the last step {steps}")
            for a in rows:
                _check_int(a, "fail agent row", 0)
                if a >= N:
                    raise SimulationError(f"fail: no agent row {a} (rows are 0..{N - 1})")
            if not rows or len(set(rows)) != len(rows) or set(rows) & set(fail_at):
                raise SimulationError(f"fail: give distinct agent rows, got {fail!r}")
            fail_at.update({int(a): f for a in rows})
        fail_step = min(fail_at.values())
        failed = tuple(sorted(fail_at, key=lambda r: (fail_at[r], r)))
        if recover is None and len(failed) == N:
            raise SimulationError("fail: every agent fails and no recovery is given")
    if recover is not None and fail is None:
        raise SimulationError("recover: a recovery needs a failure (fail=...)")
    faults = tuple(faults or ())
    fault_of = _check_faults(faults, N, steps, n, scenario.measure, scenario.standby)
    if residuals is not None and residuals is not False:
        if drop or fail is not None:
            raise SimulationError("residuals: need drop=0 and no failure (the thresholds "
                                  "are those of the healthy, lossless configuration)")
        if residuals is True:
            residuals = residual_test(scenario, G, D)
        if not isinstance(residuals, ResidualTest):
            raise SimulationError(f"residuals: expected a ResidualTest or True, got "
                                  f"{type(residuals).__name__}")
        if (residuals.N, residuals.n) != (N, n) or not np.array_equal(residuals.delays, D):
            raise SimulationError("residuals: the test was computed for another "
                                  "configuration (agents, states or delays differ)")
    else:
        residuals = None

    A = np.asarray(scenario.A, float)
    P = PowerCache(A)
    q = float(scenario.process_noise)
    ids0 = list(range(1, N + 1))
    configs = [_config(scenario, G, D, ids0)]
    chain = [] if recover is None else (
        list(recover) if isinstance(recover, (list, tuple)) else [recover])
    if recover is not None and not chain:
        raise SimulationError("recover: an empty sequence of recoveries")
    activations = []
    for i, rec in enumerate(chain):
        at = fail_step if rec.activate_at is None else _check_int(
            rec.activate_at, "recover.activate_at", fail_step)
        configs.append(_recovery_config(rec, scenario, failed, ids0,
                                        last=i == len(chain) - 1, fail_at=fail_at, at=at))
        if at > steps:
            raise SimulationError(f"recover.activate_at: {at} is after the last step {steps}")
        if activations and at <= activations[-1]:
            raise SimulationError("recover: activate_at must increase along the sequence")
        activations.append(at)
    max_delay = max(int(c.delays.max()) if c.delays.size else 0 for c in configs)
    # a standby hears the failed agent it replaces on the run's largest delay
    take_delay = int(configs[0].delays.max()) if configs[0].delays.size else 0
    if max_age is None:
        max_age = hold_limit(max_delay)
    max_age = _check_int(max_age, "max_age", max_delay + 1)
    gap = 0 if not activations else activations[-1] - fail_step
    error_coords = coordinates == "error"
    # a replacement starts cold (from noise.initial_estimate, which needs x) when it
    # replaces nobody, or when nothing of the failed agent had reached it yet
    cold = any(a not in ids0 and (a not in rec.replaces or at - 1 - take_delay < 0)
               for rec, at in zip(chain, activations) for a in rec.ids)
    track_x = not error_coords or cold

    # -- state at step 0 ----------------------------------------------------------
    x0 = noise.initial_state(seed, n, trials)
    x = x0 if track_x else None
    est = {}        # id -> (trials, n): xhat (absolute) or xhat - x (error coordinates)
    for a in ids0:
        v = noise.initial_estimate(seed, a, n, trials)
        est[a] = v - x0 if error_coords else v
    published = {a: {0: est[a]} for a in ids0}    # id -> {stamp: value}
    held = {}       # (receiver id, sender id) -> (stamp, value)
    continued = {}  # (receiver, replacement) -> (failed id, old delay, first own stamp)
    # S[a] = S_a(k) = x_k - A^a x_{k-a} for the current step (S[0] unused; at k = 0 the
    # entries are placeholders: an age never exceeds k)
    S = [None] + [np.zeros((trials, n))] * (max(max_delay + 1, gap))
    config = configs[0]
    mse_trials = np.empty((trials, steps + 1))
    mse_trials[:, 0] = _mse(est, [a for _, a in config.live], x, error_coords)
    record_ids = list(ids0)
    for rec in chain:
        record_ids += [a for a in rec.ids if a not in record_ids]
    recorded = np.full((trials, steps + 1, len(record_ids), n), np.nan) \
        if record_estimates else None
    if recorded is not None:
        _record(recorded, 0, est, config, record_ids)
    rec = None if residuals is None else _ResidualRecorder(residuals, config, trials, steps)

    with np.errstate(over="ignore", invalid="ignore"):
        for k in range(1, steps + 1):
            if k in fail_at.values():
                config = _Config(config.W, config.delays, config.ids, config.roles, config.r,
                                 config.dead | frozenset(
                                     r + 1 for r, f in fail_at.items()
                                     if f == k and r + 1 in config.ids))
            if k in activations:
                i = activations.index(k)
                config = _apply_recovery(config, configs[i + 1], chain[i], est, published, x,
                                         S, P, seed, n, trials, error_coords, k,
                                         fail_at, ids0, held, continued, drop,
                                         take_delay=take_delay)
            nu = noise.process_noise(seed, k - 1, n, q, trials)
            if track_x:
                x = x @ P.transposed(1) + nu
            _receive(config, published, held, seed, k, drop, trials, continued)
            if error_coords:
                S = _advance_window(S, nu, P, max(min(_oldest_age(held, k), max_age),
                                                  max_delay + 1, gap))
            new = {}
            for i, a in config.live:
                nbs, noise_parts = _neighbours(config, i, held, est[a], k, max_age)
                role = config.roles[i]
                zeta = noise.measurement_noise(seed, a, k, len(role.measured), config.r, trials)
                if a in fault_of:
                    zeta = apply_sensor_faults(fault_of[a], k, zeta, math.sqrt(config.r))
                if error_coords:
                    # x_k = A^age x_{k-age} + S_age(k): subtract what the truth gained
                    d = None
                    for w, age, mask in noise_parts:
                        t = w * S[age] if mask is None else (w * S[age]) * mask[:, None]
                        d = t if d is None else d + t
                    nbs.append(NeighbourEstimate(1.0, 0, -d))
                    y = zeta
                else:
                    y = x[:, list(role.measured)] + zeta
                prior, new[a] = estimator_step(P, role, est[a], nbs, y)
                if rec is not None:
                    rec.agent_step(i, a, k, y, prior, held, P, S if error_coords else None)
            est.update(new)
            if rec is not None:
                rec.end_step(k)
            for a in new:
                published[a][k] = new[a]
                for fault in fault_of.get(a, ()):
                    if fault.kind == "lie" and k >= fault.start:
                        published[a][k] = new[a] + fault.offset(k, math.sqrt(config.r)) \
                            * fault.vector(n)
                # stamps below k - 1 - max_delay can no longer arrive on time
                published[a].pop(k - 2 - max_delay, None)
            mse_trials[:, k] = _mse(est, [a for _, a in config.live], x, error_coords)
            if recorded is not None:
                _record(recorded, k, est, config, record_ids)
            if progress is not None:
                progress(k, steps)
            if not np.isfinite(mse_trials[:, k]).any():
                mse_trials[:, k + 1:] = np.inf
                if progress is not None:
                    progress(steps, steps)
                break

    mse = mse_trials.mean(axis=0)
    q_len = steady_window(steps)
    mse_steady = steady_mse(mse)
    finite = bool(np.all(np.isfinite(mse_trials)))
    previous = float(mse[-2 * q_len:-q_len].mean()) if steps >= 2 * q_len + 1 else mse[0]
    diverged = (not finite) or not (
        mse_steady <= DIVERGENCE_FACTOR * mse[0] or mse_steady <= GROWTH_FACTOR * previous)
    return SimulationResult(
        mse=mse, mse_trials=mse_trials, mse_steady=mse_steady, diverged=bool(diverged),
        trials=trials, steps=steps, seed=seed, drop=drop, fail_step=fail_step,
        failed=tuple(a + 1 for a in failed), recovered=recover is not None,
        coordinates=coordinates, estimates=recorded,
        estimate_ids=tuple(record_ids) if recorded is not None else (),
        residual_test=residuals, faults=faults,
        residual_stats=None if rec is None else rec.stats,
        innovations=None if rec is None else rec.innovations,
    )


class _ResidualRecorder:
    """Forms the residuals of every agent at every step, and their window statistics
    (:mod:`design.residuals`): the ring of the last ``window`` residual vectors."""

    def __init__(self, test, config, trials, steps):
        self.test = test
        self.ids = list(config.ids)
        self.measured = [list(role.measured) for role in config.roles]
        self.cols = {}          # (row, sender row or None) -> columns of the stacked vector
        self.links_of = {}      # row -> [(sender row, columns)]
        for r in test.residuals:
            cols = slice(r.offset, r.offset + r.dim)
            self.cols[(r.agent, r.sender)] = cols
            if r.sender is not None:
                self.links_of.setdefault(r.agent, []).append((r.sender, cols))
        self.innov_cols = []
        for r in test.residuals:
            if r.sender is None:
                self.innov_cols.append(self.cols[(r.agent, None)])
        p = sum(c.stop - c.start for c in self.innov_cols)
        self.vec = np.full((trials, test.dim), np.nan)
        self.ring = np.zeros((test.window, trials, test.dim))
        self.stats = np.full((trials, steps + 1, len(test.residuals)), np.nan)
        self.innovations = np.full((trials, steps + 1, p), np.nan)

    def agent_step(self, i, a, k, y, prior, held, P, S):
        """Residuals of row i (id a) at step k from its reading y and prediction; on each
        link the held estimate propagated by ``A^age`` (less the noise window ``S`` in
        error coordinates, as the estimator step does)."""
        self.vec[:, self.cols[(i, None)]] = y - prior[:, self.measured[i]]
        for j, cols in self.links_of.get(i, ()):
            h = held.get((a, self.ids[j]))
            if h is None:
                self.vec[:, cols] = np.nan
                continue
            stamps, values = h
            age = k - int(stamps[0])
            d = values @ P.transposed(age) - prior
            if S is not None:
                d = d - S[age]
            self.vec[:, cols] = d

    def end_step(self, k):
        w = self.test.window
        self.ring[k % w] = self.vec
        c = 0
        for r in self.test.residuals:
            if r.sender is None:
                self.innovations[:, k, c:c + r.dim] = self.vec[:, r.offset:r.offset + r.dim]
                c += r.dim
        if k >= self.test.first_step:
            self.stats[:, k] = self.test.statistics(self.ring.sum(axis=0))


def _record(recorded, k, est, config, ids):
    """Store step k's estimates of the agents ``ids`` that are running (NaN otherwise)."""
    live = {a for _, a in config.live}
    for i, a in enumerate(ids):
        if a in live:
            recorded[:, k, i] = est[a]


def _recovery_config(recover, scenario, failed, ids0, last=True, fail_at=None,
                     at=None) -> _Config:
    if not isinstance(recover, Recovery):
        raise SimulationError(f"recover: expected a Recovery, got {type(recover).__name__}")
    new = recover.scenario
    if new.A.shape != scenario.A.shape or not np.array_equal(new.A, scenario.A):
        raise SimulationError("recover: the new configuration must keep the social matrix A")
    if new.process_noise != scenario.process_noise:
        raise SimulationError("recover: the new configuration must keep the process noise")
    G = _gain_list(recover.G, new, "recover gains")
    ids = list(recover.ids)
    if len(ids) != new.N or len(set(ids)) != len(ids):
        raise SimulationError(
            f"recover.ids: need {new.N} distinct agent ids (one per row), got {ids!r}")
    for a in ids:
        _check_int(a, "recover.ids entry", 1)
    # failed by the time this configuration takes over (a later failure comes after)
    failed_ids = {r + 1 for r in failed
                  if fail_at is None or at is None or fail_at[r] <= at}
    back = sorted(failed_ids & set(ids))
    if back and last:
        raise SimulationError(f"recover.ids: failed agents {back} cannot be in the new configuration")
    for a, row in dict(recover.replaces).items():
        if a not in ids or a in ids0:
            raise SimulationError(f"recover.replaces: {a!r} is not a new agent id of the plan")
        if row not in failed:
            raise SimulationError(
                f"recover.replaces: agent {a} takes over row {row!r}, which did not fail")
    D = new.delays if recover.delays is None else recover.delays
    D = _check_delays(D, new, "recover.delays")
    waiting = frozenset(recover.waiting)
    if not waiting <= set(ids) - set(ids0):
        raise SimulationError(f"recover.waiting: {sorted(waiting)} are not all new agent ids "
                              "of the configuration")
    out = _config(new, G, D, ids)
    out.dead = frozenset(a for a in ids if a in failed_ids) | waiting
    return out


def _apply_recovery(config, new, recover, est, published, x, S, P, seed, n, trials,
                    error_coords, k, fail_at, ids0, held, continued, drop=0.0,
                    take_delay=0):
    """Switch to the recovery configuration at step k (``fail_at``: row -> its failure step).

    A replacement takes over the freshest estimate of the failed agent it has received,
    stamp ``s = min(f - 1, k - 1 - take_delay)`` (its link from the failed agent has the
    run's largest delay), propagated to step k - 1: ``A^gap xhat_s`` (``gap = k - 1 -
    s``); in error coordinates that is ``A^gap z_s - S_gap(k-1)``, with ``S`` still the
    window of step k - 1 (cold, as a live standby, when nothing had reached it). Every
    receiver that listened to the failed agent and now listens to its replacement
    continues the failed agent's stream on that link (``continued``: (receiver,
    replacement) -> (failed id, its old link delay, the replacement's first stamp)): see
    :func:`_receive` and :func:`design.estimator.continued_stamp`.
    """
    replaces = dict(recover.replaces)
    old_delay = {(config.ids[i], config.ids[j]): tau for i, j, _w, tau in config.links}
    for b, row in replaces.items():
        f = ids0[row]
        for i, j, _w, tau in new.links:
            a = new.ids[i]
            if new.ids[j] != b or a in new.dead:
                continue
            if (a, f) in old_delay:                    # it listened to f
                continued[(a, b)] = (f, old_delay[(a, f)], k - 1)
                if (a, f) in held and (a, b) not in held:
                    held[(a, b)] = held[(a, f)]        # what it had already received
            elif a in replaces:
                # a replacement listening to another: as a standby it heard f's stream
                # too, on the run's delay for that pair (the new link's: uniform delays)
                continued[(a, b)] = (f, tau, k - 1)
                first = _heard_before(published.get(f, {}), k - 2 - tau, seed, f, a, drop,
                                      trials)
                if first is not None:
                    held[(a, b)] = first
    for a in new.ids:
        if a in new.dead or (a in est and a not in config.dead):
            continue
        # the freshest estimate of the failed agent the replacement has received by step
        # k - 1: a standby hears every agent on the largest link delay
        # (design.roster.link_delay_table), so that is stamp k - 1 - take_delay when the
        # failed agent's last one (f - 1) is still on its way
        heard = None
        if a in replaces:
            stamp = min(fail_at[replaces[a]] - 1, k - 1 - take_delay)
            heard = published.get(ids0[replaces[a]], {}).get(stamp) if stamp >= 0 else None
        if heard is not None:
            gap = k - 1 - stamp
            value = heard
            if gap:
                value = value @ P.transposed(gap)
                if error_coords:
                    value = value - S[gap]
        else:
            v = noise.initial_estimate(seed, a, n, trials)
            value = v - x if error_coords else v
        est[a] = value
        published[a] = {k - 1: value}
    return new


def _heard_before(stream, newest, seed, sender, receiver, drop, trials):
    """``(stamps, values)``: per trial the freshest estimate of ``stream`` ({stamp: value})
    stamped at most ``newest`` that the keyed drops let through to ``receiver``; None when
    no trial holds one."""
    stamps = np.full(trials, -1)
    values = None
    for s in sorted((st for st in stream if st <= newest), reverse=True):
        take = stamps < 0
        if drop > 0:
            take &= ~noise.message_dropped(seed, sender, receiver, s, drop, trials)
        if not take.any():
            continue
        v = np.broadcast_to(stream[s], (trials, stream[s].shape[-1]))
        values = np.where(take[:, None], v, 0.0 if values is None else values)
        stamps = np.where(take, s, stamps)
        if (stamps >= 0).all():
            break
    return None if values is None else (stamps, values)


def _mse(est, ids, x, error_coords):
    total = 0.0
    for a in ids:
        e = est[a] if error_coords else est[a] - x
        total = total + np.mean(e * e, axis=1)
    return total / len(ids)


def _neighbours(config, i, held, x_prev, k, max_age):
    """Neighbour inputs of row i at step k, and the weights/ages of the noise window.

    Each held estimate goes through :func:`design.estimator.neighbour_input` (the policy
    shared with the live agent). Where trials hold different stamps from one neighbour,
    one input per stamp is given, with the other trials' rows zeroed; trials holding
    nothing usable from it give its weight to self (an input of age 1 on the agent's own
    estimate, rows masked likewise).
    """
    a = config.ids[i]
    role = config.roles[i]
    nbs = []
    parts = []
    w_self = role.self_weight
    for j, b in enumerate(config.ids):
        w = float(config.W[i, j])
        if j == i or w <= 0:
            continue
        h = held.get((a, b))
        if h is None:
            nbs.append(NeighbourEstimate(w, 1, None))
            w_self += w
            continue
        stamps, values = h
        if (stamps == stamps[0]).all():
            nb, _ = neighbour_input(w, k, int(stamps[0]), values, max_age)
            nbs.append(nb)
            if nb.x is None:
                w_self += w
            else:
                parts.append((w, nb.age, None))
            continue
        for s in np.unique(stamps):
            mask = stamps == s
            nb, _ = neighbour_input(w, k, int(s), values, max_age)
            if nb.x is None:
                nbs.append(NeighbourEstimate(w, 1, x_prev * mask[:, None]))
                parts.append((w, 1, mask))
            else:
                nbs.append(NeighbourEstimate(w, nb.age, values * mask[:, None]))
                parts.append((w, nb.age, mask))
    parts.append((w_self, 1, None))
    return nbs, parts


def _oldest_age(held, k):
    ages = [k - int(st[st >= 0].min()) for st, _ in held.values() if (st >= 0).any()]
    return max(ages, default=1)


def _advance_window(S, nu, P, needed):
    """``S_a(k) = nu_{k-1} + A S_{a-1}(k-1)`` for a = 1..needed (S_1 = nu_{k-1})."""
    out = [None, nu]
    AT = P.transposed(1)
    for a in range(2, needed + 1):
        prev = S[a - 1] if a - 1 < len(S) else None
        if prev is None:
            raise AssertionError("noise window too short")  # pragma: no cover
        out.append(nu + prev @ AT)
    return out


def _receive(config, published, held, seed, k, drop, trials, continued=None):
    """Deliver, on every link, the estimate stamped ``k - 1 - tau`` unless it is lost.

    ``held[(receiver, sender)] = (stamps, values)``: per trial the stamp (-1 = nothing
    held) and the value of the freshest estimate received. A link that continues a
    failed agent's stream (``continued``) also delivers, on the failed agent's own link
    schedule, what it had published before the replacement's first stamp.
    """
    links = [(config.ids[i], config.ids[j], tau) for i, j, _w, tau in config.links]
    for (a, b), (f, tau_f, first) in (continued or {}).items():
        s = k - 1 - tau_f
        if continued_stamp(s, first):
            links.append((a, b, tau_f, f))
    for link in links:
        a, b, tau = link[:3]
        src = link[3] if len(link) > 3 else b         # whose published stream it carries
        s = k - 1 - tau
        value = published.get(src, {}).get(s)
        if value is None:
            continue
        h = held.get((a, b))
        take = np.ones(trials, dtype=bool) if h is None else h[0] < s
        if drop > 0:
            take &= ~noise.message_dropped(seed, src, a, s, drop, trials)
        if not take.any():
            continue
        if take.all() or h is None and take.all():
            held[(a, b)] = (np.full(trials, s), value)
        elif h is None:
            stamps = np.where(take, s, -1)
            held[(a, b)] = (stamps, np.where(take[:, None], value, 0.0))
        else:
            held[(a, b)] = (np.where(take, s, h[0]), np.where(take[:, None], value, h[1]))
