"""The monitor's controller: verdicts answered by reassigning roles, as a state machine.

:class:`MonitorCore` takes in the agents' liveliness events and statuses with the time
they arrived, hands them to its failure detector (:class:`agent.monitor.detector.
FailureDetector`: the evidence about each agent and the ``crash``, ``hang``, ``sensor`` and
``silent`` verdicts it supports), and gives out the control messages that hand a failed
agent's role to an observationally equivalent replacement. The process shell
(:mod:`agent.monitor.process`) only feeds it from a :class:`broker_free_net.Peer`; unit
tests step it by hand, so tests control time.

The controller's own verdict is ``delay``: the delays the agents learned on their links
exceed the ones the gains were designed for and the exact closed loop with the learned
delays is no longer stable (radius >= 1). Nobody is removed: the monitor designs gains
for the learned delays and assigns them under a new epoch (same roles).

Reassignment (see docs/monitor.md): on a verdict the monitor plans the failure on the
configuration in force (:func:`design.roster.replan`), takes the gains precomputed for
that failure (or designs a first stabilising gain), and publishes, under one new epoch
and one ``activate_at`` a few steps ahead, an assignment to every agent whose role
changes and a roster (the ids in force from ``activate_at``) to everyone. Every
receiver fences: from ``activate_at`` it ignores estimates of ids outside the roster,
and an agent that finds itself outside it drops its role and becomes a standby. The
monitor re-sends until each assigned agent's status shows the epoch, and treats a
replacement that does not confirm within ``confirm_timeout_s`` as failed.

Examples
--------
>>> from design.scenario import load_scenario
>>> import numpy as np
>>> s = load_scenario("paper-14")
>>> core = MonitorCore(MonitorConfig(), s, [np.zeros((14, 1))] * 3, s.delays)
>>> core.on_liveliness("agent", 1, True, now=0.0)
True
>>> core.roster.ids
(1, 2, 3)
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from agent.monitor.detector import FailureDetector, Verdict
from agent.protocol.timing import DEFAULT as TIMING
from agent.protocol.timing import Timing
from design.gains import gain_digest

__all__ = ["MonitorConfig", "MonitorCore", "Verdict", "Assignment", "RosterUpdate",
           "GainSource"]


@dataclass(frozen=True)
class MonitorConfig:
    """Thresholds of the monitor (defaults and the trade-off: docs/monitor.md).

    Parameters
    ----------
    hang_timeout_s : float
        No progress of an agent's step for this long (while the others advance) is a hang.
        Lower detects faster; under ``hang_timeout_s`` a slow agent risks conviction.
    hang_timeout_max_s, hang_phi : float
        The timeout adapts to the statuses' pace (:class:`agent.monitor.detector.StatusPace`): the gap a healthy
        loop's statuses exceed with probability ``10^-hang_phi`` under the pace observed,
        never below ``hang_timeout_s`` nor above ``hang_timeout_max_s``.
    hang_lag_steps : int
        ... and the others must have advanced by more than this many steps meanwhile.
    sensor_lag_steps : int
        An agent whose last reading is this many steps behind the others' steps.
    silent_steps : int
        Age (steps) of the freshest estimate its listeners hold from an agent, beyond the
        link's delay, past which it counts as silent.
    lead_steps : int
        ``activate_at`` = the verdict's step + this (the assignment's head start), and
        at least this less one step after the roles are sent (a gain designed on request);
        doubled by every re-issue up to twice the hang timeout, halved back towards it by
        every reassignment confirmed without one (:attr:`MonitorCore.lead`).
    resend_s : float
        Re-send unconfirmed assignments this often.
    confirm_timeout_s : float
        A replacement that has not confirmed by then is treated as failed.
    pause_guard_s : float
        A gap between two ticks longer than this suspends verdicts (the monitor itself
        was paused) until ``hang_timeout_s`` of fresh evidence has passed.
    rejoin_s : float
        Probation: a convicted agent that came back (fenced into a standby) rejoins the
        standby pool once it has been healthy (:meth:`MonitorCore.healthy_standby`) for
        this long without a break.
    epoch_jump_max : int
        Epochs heard from the network (statuses, rosters) above the highest seen plus
        this are refused: every epoch comes from a monitor, one per reassignment.
    step_ahead_s : float
        A status whose step is more than this (in steps of ``step_s``) ahead of every
        other agent's step, extrapolated from when it was reached, is refused
        (``step``): one agent alone cannot ratchet the monitor's clock up.
    settle_s : float
        After a first verdict, wait this long for others (agents killed together: their
        tokens go within a few ms) so that one reassignment answers them all.
    step_s : float
        The run's step period: the current step is extrapolated from the newest status
        (statuses come every ``Timing.status_s``, ten steps at 20 ms).
    world_gone_s : float
        Once the world's token is gone, the agents leave with it (within
        ``Timing.agent_world_gone_s``) and nothing
        is convicted; once the world's end was heard, :meth:`MonitorCore.run_ended` says
        the run is over when no agent's token is left, or this long after the world left.
    world_silent_s : float
        A world whose token went without its end (paused, cut off; or this monitor was)
        is waited for this long before the run counts as over.
    lease_s : float
        The link lease of this monitor's transport (``--lease-ms``, 1 s by default: the
        processes of one run share it): a token that went within
        :data:`agent.monitor.detector.CRASH_HEARD_LEASE` of a lease after its agent was
        last heard went with its process, not by its link's lease.
    """

    hang_timeout_s: float = TIMING.hang_timeout_s
    hang_timeout_max_s: float = TIMING.hang_timeout_max_s
    hang_phi: float = TIMING.hang_phi
    status_s: float = TIMING.status_s
    hang_lag_steps: int = 10
    sensor_lag_steps: int = 25
    silent_steps: int = 25
    lead_steps: int = 10
    resend_s: float = TIMING.resend_s
    confirm_timeout_s: float = TIMING.confirm_timeout_s
    pause_guard_s: float = TIMING.pause_guard_s
    step_s: float = 0.02
    settle_s: float = 0.01
    rejoin_s: float = TIMING.rejoin_s
    epoch_jump_max: int = TIMING.epoch_jump_max
    step_ahead_s: float = TIMING.step_ahead_s
    world_gone_s: float = TIMING.monitor_world_gone_s
    world_silent_s: float = TIMING.monitor_world_silent_s
    lease_s: float = 1.0

    @classmethod
    def from_timing(cls, timing: Timing, **fields) -> "MonitorConfig":
        """The monitor's thresholds with the periods and timeouts of ``timing``."""
        return cls(hang_timeout_s=timing.hang_timeout_s,
                   hang_timeout_max_s=timing.hang_timeout_max_s, hang_phi=timing.hang_phi,
                   status_s=timing.status_s,
                   resend_s=timing.resend_s,
                   confirm_timeout_s=timing.confirm_timeout_s,
                   pause_guard_s=timing.pause_guard_s, rejoin_s=timing.rejoin_s,
                   epoch_jump_max=timing.epoch_jump_max,
                   step_ahead_s=timing.step_ahead_s, world_gone_s=timing.monitor_world_gone_s,
                   world_silent_s=timing.monitor_world_silent_s, **fields)


@dataclass(frozen=True, eq=False)
class Assignment:
    """One role for one agent, under ``epoch`` from step ``activate_at``, with the agent's
    residual tests of that configuration when they are known (``tests``:
    :class:`design.residuals.AgentTests`)."""

    agent: int
    epoch: int
    activate_at: int
    spec: object         # design.roster.RoleSpec
    tests: object = None

    def encode(self, signer=None, run: str | None = None) -> bytes:
        """The ``ctl/<agent>`` message (:func:`agent.protocol.wire.encode_ctl`), signed
        with ``signer`` for run ``run`` when given."""
        from agent.protocol import wire

        sp = self.spec
        return wire.encode_ctl(self.agent, self.epoch, self.activate_at, sp.measure,
                               sp.neighbours, sp.self_weight, sp.gain, take_over=sp.take_over,
                               signer=signer, continues=sp.continues, run=run,
                               residuals=None if self.tests is None else self.tests.to_wire())


@dataclass(frozen=True)
class RosterUpdate:
    """The ids in force from ``activate_at`` under ``epoch`` (the fencing token), and the
    convicted agents on probation (``probation``) and of them those that never rejoin
    (``barred``, convicted of a cause in :data:`NEVER_REJOIN`): a monitor that adopts
    the configuration from this roster (restarted, or taking the seat) keeps them out
    of the standby pool as the one that convicted them did."""

    epoch: int
    activate_at: int
    ids: tuple
    probation: tuple = ()
    barred: tuple = ()


class GainSource:
    """The gains known for each configuration, and how to get the ones missing.

    Each entry is ``(G, info)``: ``G`` the list of G_i by row, ``info`` what
    :func:`design_gains_for` says of it (``kind``: ``"fast"`` a first certified gain,
    ``"refined"`` the gain of least steady MSE, ``"initial"`` the run's own; ``rho``, the
    exact radius of the delayed loop, or None and ``rho_below`` when its eigenvalues were
    counted below that; ``mse``, its exact steady MSE; ``polished``, a fast
    gain given a few MSE iterations). A refined entry is never replaced by a fast one, nor
    a polished one by a plain fast one. The worker's assessment of a gain (``assessed``:
    its exact radius and MSE, :meth:`agent.monitor.gain_worker.GainWorker.assess`) is
    kept apart (:meth:`assessment`) and completes the entry of the same gain.

    With a ``worker`` (:class:`agent.monitor.gain_worker.GainWorker`, the monitor process) nothing
    is designed here: :meth:`ready` asks the worker once and says False until its answer
    has been :meth:`put`; without one (unit tests, tools) :meth:`ready` designs a fast
    gain at once with ``design``.
    """

    def __init__(self, design=None, worker=None):
        self._cache: dict = {}            # key -> (G, info)
        self._assessed: dict = {}         # key -> (G, info): the worker's assessments
        self._none: set = set()           # keys for which no stabilising gain was found
        self._requested: set = set()
        self._design = design or design_gains_for
        self.worker = worker

    @staticmethod
    def key(roster) -> tuple:
        s = roster.scenario
        return (tuple(roster.ids), s.W.tobytes(), tuple(tuple(m) for m in s.measure),
                np.asarray(roster.delays).tobytes())

    def put(self, roster, G, info=None) -> None:
        """A design's answer for ``roster`` (``G`` None: no stabilising gain)."""
        k = self.key(roster)
        info = dict(info or {})
        if G is None:
            if k not in self._cache:
                self._none.add(k)
            return
        old = self._cache.get(k)
        if info.get("assessed"):
            G = [np.asarray(g, dtype=float) for g in G]
            self._assessed[k] = (G, info)
            if old is not None and _same_gains(old[0], G):
                self._cache[k] = (old[0], {**old[1], "rho": info.get("rho"),
                                           "mse": info.get("mse")})
            return
        if old is not None and info.get("kind") == "fast" and (
                old[1].get("kind") == "refined"
                or old[1].get("polished") and not info.get("polished")):
            return
        self._cache[k] = ([np.asarray(g, dtype=float) for g in G], info)
        self._none.discard(k)

    def assessment(self, roster):
        """``(G, info)`` of the worker's newest assessment for ``roster`` (a gain's exact
        radius and steady MSE), or ``(None, {})``."""
        entry = self._assessed.get(self.key(roster))
        return (entry[0], dict(entry[1])) if entry is not None else (None, {})

    def has(self, roster) -> bool:
        return self.key(roster) in self._cache

    def known(self, roster) -> bool:
        """Gains for ``roster`` are here, or it is known that none stabilise it."""
        k = self.key(roster)
        return k in self._cache or k in self._none

    def info(self, roster) -> dict:
        entry = self._cache.get(self.key(roster))
        return dict(entry[1]) if entry is not None else {}

    def ready(self, roster, init=None) -> bool:
        """True once gains for ``roster`` are known, or known not to exist (``init``: a
        warm start for its first gain, :func:`design.roster.carried_gains`)."""
        k = self.key(roster)
        if k in self._cache or k in self._none:
            return True
        if self.worker is None:
            self.put(roster, *self._design(roster, "fast", init=init))
            return True
        if k not in self._requested:
            self._requested.add(k)
            self._requested.add(("asked",) + k)      # its refined gain is on the way too
            self.worker.request(roster, init=init)
        return False

    def refine(self, roster) -> None:
        """Ask the worker (once) for the refined gain of ``roster``, in force on a fast one,
        then for the exact steady MSE of that fast gain (a Lyapunov solve of seconds at
        large delays: the fast gain is sent without it, the MSE follows)."""
        k = ("refine",) + self.key(roster)
        if self.worker is not None and k not in self._requested:
            self._requested.add(k)
            if ("asked",) + self.key(roster) not in self._requested:
                self.worker.request(roster, kinds=("refined",))
            G, info = self.get(roster)
            if G is not None and info.get("kind") == "fast" and info.get("mse") is None:
                self.worker.assess(roster, G, info)

    def get(self, roster):
        """``(G, info)``, or ``(None, {})`` when none is known (see :meth:`ready`)."""
        entry = self._cache.get(self.key(roster))
        return (entry[0], dict(entry[1])) if entry is not None else (None, {})

    def design(self, roster, refined: bool = False):
        """Design gains for ``roster`` now (no cache): ``(G or None, info)``."""
        return self._design(roster, "refined" if refined else "fast")


def _same_gains(G, H) -> bool:
    return G is not None and H is not None and len(G) == len(H) and all(
        np.array_equal(g, h) for g, h in zip(G, H))


def _gain_record(info: dict) -> dict:
    """The keys a history record (and the monitor's events) keep of a gain's ``info``."""
    out = {"gains": info.get("kind", "unknown"), "gains_rho": info.get("rho"),
           "gains_mse": info.get("mse")}
    if info.get("rho") is None and info.get("rho_below") is not None:
        out["gains_rho_below"] = info["rho_below"]
    if info.get("polished"):
        out["gains_polished"] = True
    return out


def _gain_words(info: dict) -> str:
    """``fast gains, exact radius 0.8123, steady MSE 0.4567`` (what is known)."""
    words = f"{info.get('kind', 'unknown')} gains" + (" (MSE-polished)" if info.get("polished")
                                                       else "")
    if info.get("rho") is not None:
        words += f", exact radius {info['rho']:.4f}"
    elif info.get("rho_below") is not None:
        words += f", radius below {info['rho_below']:g} (counted; exact to follow)"
    if info.get("mse") is not None:
        words += f", steady MSE {info['mse']:.4g}"
    return words


def design_gains_for(roster, kind: str = "fast", progress=None, init=None):
    """``(G, info)`` for the configuration ``roster``, designed against its delays.

    ``kind="fast"``: :func:`design.reconfigure.fast_recovery_gains`, a first stabilising
    gain (a target radius, few iterations; from ``init`` first when given, a warm start
    such as :func:`design.roster.carried_gains`); ``"polished"`` (what the precompute sends
    after its fast pass): that gain (``init`` when given: the fast gain already designed)
    then :func:`design.reconfigure.polished_recovery_gains`, a few MSE iterations,
    reported as a first gain (``kind`` ``"fast"``, ``polished`` True: the refined gain
    still follows once it is in force); ``"refined"``:
    :func:`design.reconfigure.refined_recovery_gains` (least steady MSE), falling back to
    the fast one when it is not stable. Bounded by iterations, not by the clock
    (``progress``: called at every iteration, see :func:`design.gain_design.design_gains`). ``G`` is
    None when no stabilising gain was found; ``info`` holds ``kind``, the exact radius
    ``rho``, the exact steady MSE ``mse``, the design's ``seconds`` and ``residuals``, each
    agent's residual tests of the configuration with those gains
    (:func:`design.residuals.configuration_tests`: ``{}`` above
    :data:`design.residuals.AGENT_MAX_ORDER`), which its assignment carries.
    """
    return with_residual_tests(roster, *_design_gains(roster, kind, progress, init))


def with_residual_tests(roster, G, info: dict):
    """``(G, info)`` with ``info["residuals"]``: each agent's residual tests of ``roster``
    with gains ``G`` (:func:`design.residuals.configuration_tests`; ``{}`` above
    :data:`design.residuals.AGENT_MAX_ORDER` or when ``G`` is None)."""
    from design.residuals import configuration_tests

    info = dict(info)
    info["residuals"] = {} if G is None else configuration_tests(roster.scenario, G,
                                                                 roster.delays, roster.ids)
    return G, info


def _design_gains(roster, kind: str = "fast", progress=None, init=None):
    """:func:`design_gains_for` but the residual tests."""
    from design.errors import SocmonError
    from design.reconfigure import (fast_recovery_gains, polished_recovery_gains,
                                    refined_recovery_gains)

    if kind == "polished":
        if init is None:
            init, first = _design_gains(roster, "fast", progress)
            if init is None:
                return None, first
        try:
            res = polished_recovery_gains(roster.scenario, roster.delays, init,
                                          progress=progress)
        except SocmonError:
            res = None
        if res is None or not res.stable:
            return _design_gains(roster, "fast", progress)
        return list(res.G), {"kind": "fast", "polished": True, "rho": float(res.rho),
                             "mse": None, "seconds": float(res.seconds)}
    design = refined_recovery_gains if kind == "refined" else fast_recovery_gains
    # a fast gain from a warm start (design.roster.carried_gains) tries it first, then the
    # reset gain: no eigenvalue problem when the start's eigenvalues count below halfway
    # from the target to 1 (design.gain_design.counted_bound; its exact radius follows
    # with its steady MSE, GainWorker.assess)
    warm = ({"init": init, "starts": 2, "exact_rho": False}
            if kind == "fast" and init is not None else {})
    try:
        res = design(roster.scenario, roster.delays, progress=progress, **warm)
    except SocmonError:
        res = None
    if res is None or not res.stable:
        return _design_gains(roster, "fast", progress) if kind == "refined" else (None, {})
    info = {"kind": kind, "rho": None if res.rho is None else float(res.rho),
            "mse": None if res.mse_steady is None else float(res.mse_steady),
            "seconds": float(res.seconds)}
    if res.rho is None:
        info["rho_below"] = float(res.rho_below)
    return list(res.G), info


def _stability(loop) -> tuple:
    """``(stable, words)`` of a delayed loop, in the monitor's loop: its eigenvalues
    counted against the unit circle (:meth:`design.closed_loop.ClosedLoop.count_outside`:
    milliseconds where the exact radius is a dense eigenvalue problem of order (T+1) nN,
    0.35-1 s for Sampson-like at 15-step delays, that held the loop's detection back),
    the exact radius when the count does not pay or settle."""
    count = loop.count_outside(1.0, max_points=512) if loop.count_pays else None
    if count is None:
        rho = loop.spectral_radius()
        return rho < 1, f"radius {rho:.4f}"
    if count == 0:
        return True, "every eigenvalue counted inside the unit circle: radius < 1"
    return False, (f"{count} eigenvalue{'s' if count > 1 else ''} counted outside the unit "
                   "circle: radius >= 1")


def _tests_epoch(res) -> int | None:
    """The epoch of the configuration whose residual tests an agent's status reports
    (``residuals``: 0, the initial one's, from agents that do not say), or None when it
    reports none."""
    if not isinstance(res, dict) or not isinstance(res.get("levels"), dict):
        return None
    epoch = res.get("epoch", 0)
    return epoch if isinstance(epoch, int) and not isinstance(epoch, bool) else None


def _configuration_words(epoch: int) -> str:
    return "the initial configuration" if epoch == 0 else f"the configuration of epoch {epoch}"


def _residual_name(name) -> tuple | None:
    """``("innovation", i)`` or ``("link", j, i)`` (1-based ids) of a residual test's name
    as an agent reports it (``"innovation 2"``, ``"link 3->2"``), or None."""
    import re

    if not isinstance(name, str) or len(name) > 32:
        return None
    m = re.fullmatch(r"innovation (\d{1,6})", name)
    if m:
        return ("innovation", int(m.group(1)))
    m = re.fullmatch(r"link (\d{1,6})->(\d{1,6})", name)
    return ("link", int(m.group(1)), int(m.group(2))) if m else None


#: Causes after which a convicted agent never rejoins the standbys: probation checks that
#: an agent is up, advancing and reading its sensor, and a liar is all of that
#: (:meth:`MonitorCore._probation`).
NEVER_REJOIN = ("inconsistent estimates",)


class MonitorCore:
    """The monitor's protocol, stepped by the caller with explicit times (seconds).

    Feed it with :meth:`on_liveliness` and :meth:`on_status`; call :meth:`tick` to get
    the verdicts found and the control messages to publish now.
    """

    def __init__(self, config: MonitorConfig, scenario, G, delays, gains: GainSource = None,
                 epoch: int = 0):
        from design.roster import Roster, role_specs

        self.config = config
        self.scenario = scenario
        self.events: list = []            # human-readable log lines, drained by the shell
        #: the evidence and the verdicts it supports (the controller keeps its roster)
        self.detector = FailureDetector(config, Roster.initial(scenario, delays),
                                        range(1, scenario.N + scenario.standby + 1),
                                        self.events)
        self.G = [np.asarray(g, dtype=float) for g in G]
        self.specs = role_specs(self.roster, self.G)
        self.gains = gains or GainSource()
        self.gain_info = {"kind": "initial"}   # what the gains in force are
        self.gain_notes: list = []             # exact MSEs of fast gains, known later
        self.gains.put(self.roster, self.G, self.gain_info)
        self._pending: dict | None = None     # a reassignment waiting for its gains
        self._delay_pending: dict | None = None   # a delay verdict waiting for its gains
        self.epoch = int(epoch)
        self.verdicts: list = []
        self.on_probation: set = set()    # convicted, not yet healthy for rejoin_s
        self.barred: set = set()          # on probation for good (NEVER_REJOIN)
        self._epoch_seen = 0              # the highest epoch accepted from the network
        self._gains_said: set = set()     # agents started with another gain (said once)
        # the initial gains' digests (_check_gains; kept when an adoption drops self.G)
        self._own_gains = [gain_digest(g) for g in self.G]
        self.rejoins: list = []           # {"agent", "step", "healthy_s", "standby"}
        self.unrecoverable = False
        self.outbox: list = []            # (Assignment | RosterUpdate) to (re)send
        self._unconfirmed: dict = {}      # agent -> Assignment awaiting its status
        # the assignments' head start (steps): lead_steps, doubled by every re-issue (the
        # agents heard the roles too late: a loaded host), halved back towards lead_steps
        # by every reassignment confirmed without one
        self.lead = config.lead_steps
        self._sent_at: float | None = None
        self._assigned_at: float | None = None
        self._roster_msg: RosterUpdate | None = None
        # the last reassignment sent: the configuration it was planned on (standbys
        # included), its failures and verdicts, the agents it assigned (see _joint_plan)
        self._last_plan: dict | None = None
        self.history: list = []           # [{epoch, activate_at, verdicts, ids, specs}]
        self.reissues: list = []          # [{epoch, activate_at, unconfirmed, reason}]
        self._first_verdict_at = None     # the settle window of simultaneous failures
        self._first_seen: dict = {}       # agent -> when its verdict was first found
        self._delays_checked = None       # learned delays last certified
        self._off_design = None           # see _delays_off_design
        #: the agents report an epoch this monitor did not issue: :meth:`adopt` before acting
        self.behind = False
        self._adopt_wait = None            # the last reason an adoption had to wait
        self._recorded = {"verdicts": 0, "history": 0, "gains": 0, "reissue": 0, "rejoin": 0,
                          "evidence_refused": 0, "residual_alert": 0,
                          "waiting": None}   # see new_records
        self.residual_alerts: list = []   # residual alarms isolated to an agent (alerts)
        self._alerted: set = set()        # (agent, kind) already alerted
        self._residual_peaks: dict = {}   # agent -> {test: largest level since isolated}
        self._residual_alarm_step = None  # the earliest first alarm reported
        self._residual_first: dict = {}   # (agent, test) -> (step, level) of its first alarm
        self._residual_last_alarm = -1    # the newest status step with an alarm
        self._residual_hold = False       # an episode was isolated: wait until it is over
        self._residual_verdicts: list = []   # corroborated isolations, until convicted
        self._residual_epoch = self.epoch  # the configuration whose tests are noted

    # -- the configuration in force, and the detector's view of it ---------------------
    @property
    def roster(self):
        """The configuration in force (:class:`design.roster.Roster`); the detector
        judges its agents."""
        return self.detector.roster

    @roster.setter
    def roster(self, value) -> None:
        self.detector.roster = value

    # what the detector knows, read through the controller (the shells and tools read it)
    agents = property(lambda self: self.detector.agents)
    failed = property(lambda self: self.detector.failed)
    convicted_at = property(lambda self: self.detector.convicted_at)
    rejected = property(lambda self: self.detector.rejected)
    anomalies = property(lambda self: self.detector.anomalies)
    pace = property(lambda self: self.detector.pace)
    world_gone_at = property(lambda self: self.detector.world_gone_at)
    world_end = property(lambda self: self.detector.world_end)
    last_step_reported = property(lambda self: self.detector.last_step_reported)

    def hang_timeout(self, now: float | None = None) -> float:
        return self.detector.hang_timeout(now)

    def current_step(self, now: float) -> int:
        return self.detector.current_step(now)

    def step_ceiling(self, now: float, exclude=None) -> int | None:
        return self.detector.step_ceiling(now, exclude)

    def newest_step(self, exclude=None) -> int:
        return self.detector.newest_step(exclude)

    def reject(self, reason: str, agent, detail: str) -> None:
        self.detector.reject(reason, agent, detail)

    def healthy_standby(self, agent: int, now: float) -> bool:
        return self.detector.healthy_standby(agent, now)

    def run_ended(self, now: float) -> bool:
        return self.detector.run_ended(now)

    # -- inputs --------------------------------------------------------------------
    def on_liveliness(self, role: str, agent, alive: bool, now: float,
                      session: str | None = None) -> bool | None:
        """A liveliness token came or went (:meth:`FailureDetector.on_liveliness`); a
        standby's going is logged with the replacements left."""
        a = self.detector.evidence(agent) if role == "agent" else None
        was_alive = a is not None and a.alive
        out = self.detector.on_liveliness(role, agent, alive, now, session)
        if was_alive and out is False and int(agent) not in self.roster.ids \
                and self.world_gone_at is None:
            # no role to hand over, but one failure fewer can be answered
            left = len(self.standby_pool(now, exclude=(int(agent),)))
            self.events.append(f"agent {agent} gone (its token went): " + (
                "convicted earlier (" + next((v.cause for v in reversed(self.verdicts)
                                              if v.agent == int(agent)), "?")
                + "), out of the configuration since, on probation"
                if int(agent) in self.on_probation else "a standby" + (
                    " (convicted earlier, rejoined after probation)"
                    if int(agent) in self.convicted_at else ""))
                + f"; {left} standby left to replace a failed agent")
        return out

    def on_status(self, msg: dict, now: float, sender: int | None = None) -> None:
        """An agent's status (:meth:`FailureDetector.on_status`, refused above
        :meth:`epoch_ceiling`). An epoch above this monitor's own means another monitor
        acted while this one was away (restarted, paused, cut off): it continues above
        it, :attr:`behind` until it has adopted the configuration in force."""
        a = self.detector.on_status(msg, now, sender, epoch_ceiling=self.epoch_ceiling())
        if a is None:
            return
        self._epoch_seen = max(self._epoch_seen, a.epoch)
        self._check_gains(int(msg["agent"]), msg)
        self._note_residuals(int(msg["agent"]), msg)
        if self.epoch < a.epoch:
            self.epoch = a.epoch
            self.behind = True

    def _check_gains(self, agent: int, msg: dict) -> None:
        """An agent's start status names the gain it was started with: one other than this
        monitor's (another ``--gains`` file) is said once, as a warning, since the
        predictions and the replacements designed here assume this monitor's."""
        said = self._gains_said
        if "gains" not in msg or agent in said or not 1 <= agent <= len(self._own_gains):
            return
        if msg["gains"] != self._own_gains[agent - 1]:
            said.add(agent)
            self.events.append(
                f"warning: agent {agent} was started with another gain than this monitor's "
                f"(digest {msg['gains']}, here {self._own_gains[agent - 1]}): another "
                "--gains file? The predictions and the replacements designed here assume "
                "this monitor's")

    def on_estimate_seen(self, agent, now: float) -> None:
        """The monitor's own observation (:meth:`FailureDetector.on_estimate_seen`)."""
        self.detector.on_estimate_seen(agent, now)

    def on_world_end(self, step: int) -> None:
        """The world's end message: the run is over after ``step``."""
        self.detector.on_world_end(step)

    # -- evidence ------------------------------------------------------------------------
    def epoch_ceiling(self) -> int:
        """The largest epoch accepted from the network now: the highest seen (this monitor's
        own, adopted ones included) plus :attr:`MonitorConfig.epoch_jump_max`."""
        return max(self.epoch, self._epoch_seen) + self.config.epoch_jump_max

    def accept_roster(self, msg: dict) -> bool:
        """A roster heard on the wire (already signature-checked by the caller when the
        run signs) is taken for adoption only within :meth:`epoch_ceiling`."""
        if int(msg["epoch"]) > self.epoch_ceiling():
            self.reject("epoch", 0, f"a roster with epoch {msg['epoch']}, above the highest "
                        f"epoch seen plus {self.config.epoch_jump_max} ({self.epoch_ceiling()})")
            return False
        self._epoch_seen = max(self._epoch_seen, int(msg["epoch"]))
        return True

    @property
    def roster_message(self):
        """The :class:`RosterUpdate` in force (re-published by the shell), with the
        agents on probation as they are now, or None."""
        m = self._roster_msg
        return None if m is None else self._roster_update(m.epoch, m.activate_at, m.ids)

    def _roster_update(self, epoch: int, activate_at: int, ids) -> RosterUpdate:
        return RosterUpdate(int(epoch), int(activate_at), tuple(int(a) for a in ids),
                            probation=tuple(sorted(self.on_probation)),
                            barred=tuple(sorted(self.barred)))

    def new_records(self) -> list:
        """``(kind, fields)`` of what happened since the last call, for the run's record
        (``events.jsonl`` and the monitor's events on the wire; docs/monitor.md): every
        ``verdict``, ``reassign``, ``gains`` note, ``reissue``, ``rejoin``,
        ``evidence_refused``, and ``confirmed`` once every agent of a reassignment runs
        its epoch. Times are this core's (``mono``: the caller's monotonic clock)."""
        seen = self._recorded
        out = []
        lists = (("verdicts", self.verdicts), ("history", self.history),
                 ("gains", self.gain_notes), ("reissue", self.reissues),
                 ("rejoin", self.rejoins), ("evidence_refused", self.anomalies),
                 ("residual_alert", self.residual_alerts))
        if any(seen[name] != len(items) for name, items in lists):  # asked at every tick
            out = self._records_since(seen)
        if self.history and not self.confirmed():
            seen["waiting"] = self.epoch
        elif seen["waiting"] is not None and self.confirmed():
            out.append(("confirmed", {"epoch": self.epoch, "waited_for": seen["waiting"]}))
            seen["waiting"] = None
        return out

    def _records_since(self, seen: dict) -> list:
        """The records of :meth:`new_records` past the counts ``seen`` (updated)."""
        out = []
        for v in self.verdicts[seen["verdicts"]:]:
            out.append(("verdict", {"agent": v.agent, "cause": v.cause, "evidence": v.evidence,
                                    "step": v.step, "mono": v.at}))
        for h in self.history[seen["history"]:]:
            out.append(("reassign", {**{k: v for k, v in h.items()
                                        if k not in ("decided_at", "sent_at")},
                                     "mono": h["decided_at"], "mono_sent": h["sent_at"]}))
        for name, items in (("gains", self.gain_notes), ("reissue", self.reissues),
                            ("rejoin", self.rejoins), ("evidence_refused", self.anomalies),
                            ("residual_alert", self.residual_alerts)):
            out += [(name, dict(r)) for r in items[seen[name]:]]
        for name, items in (("verdicts", self.verdicts), ("history", self.history),
                            ("gains", self.gain_notes), ("reissue", self.reissues),
                            ("rejoin", self.rejoins), ("evidence_refused", self.anomalies),
                            ("residual_alert", self.residual_alerts)):
            seen[name] = len(items)
        return out

    # -- the clock -----------------------------------------------------------------
    def watch(self, now: float) -> None:
        """A passive monitor's tick: its detector's clock moves on (the evidence keeps
        coming), so that a gap is a pause of this process, not the time it stood by."""
        self.detector.observe(now)

    def tick(self, now: float) -> list:
        """Verdicts and reassignment at time ``now``; returns messages to publish now.

        Nothing while :attr:`behind` (the configuration held is not the one in force:
        the caller rebuilds it with :meth:`adopt` first)."""
        cfg = self.config
        detector = self.detector
        detector.observe(now)
        if self.world_gone_at is not None or self.behind:
            return []                      # the world is gone, or the roster is stale
        out = []
        self._check_confirmations(now)
        suspended = detector.suspended(now)
        if not suspended:
            self._probation(now)
            out += self._retry_unanswered(now)
        if self._pending is not None:
            out += self._emit_reassign(now)     # its gains came back from the worker
        self._note_gain_mse()
        self._residual_alerts(now)
        if not suspended and self.last_step_reported >= 0 and not self._unconfirmed \
                and self._pending is None and not self._switch_ahead(now):
            out += self.check_delays(now)
            if not out:
                out += self._upgrade_gains(now)
        if self.last_step_reported >= 0:
            # a deleted token is evidence of its own: even while the monitor's own pause
            # suspends the verdicts that read clocks, a crash is answered
            found = detector.crash_verdicts(now) if suspended else detector.verdicts(now)
            found += self._residual_convictions(found)
            # when its verdict was first found, while the evidence holds: an agent convicted
            # again later (it came back, rejoined, failed again) starts a new time
            self._first_seen = {a: t for a, t in self._first_seen.items()
                                if any(v.agent == a for v in found)}
            for v in found:
                self._first_seen.setdefault(v.agent, now)
            found = [dataclasses.replace(v, at=self._first_seen[v.agent],
                                         step=min(v.step, self.current_step(
                                             self._first_seen[v.agent]))) for v in found]
            if found and self._first_verdict_at is None:
                self._first_verdict_at = now
            if found and now - self._first_verdict_at >= cfg.settle_s:
                self._first_verdict_at = None
                out += self._reassign(found, now)
        if self._unconfirmed and self._roster_msg is not None \
                and self.current_step(now) >= self._roster_msg.activate_at - 1 \
                and self._late_but_running():
            out += self._reissue(now)
        elif self._unconfirmed and self._sent_at is not None and now - self._sent_at >= cfg.resend_s:
            out += list(self._unconfirmed.values())
            if self._roster_msg is not None:
                out.append(self._roster_msg)
            self._sent_at = now
        return out

    def _note_residuals(self, agent: int, msg: dict) -> None:
        """Keep the largest level of each residual test an agent reported since the last
        isolation (untrusted input: names and levels checked, at most 64 of them)."""
        res = msg.get("residuals")
        levels = res.get("levels") if isinstance(res, dict) else None
        if not isinstance(levels, dict) or _tests_epoch(res) != self.epoch:
            return                # no tests, or those of another configuration
        if self._residual_alarm_step is None:
            # no alarm pending: this status's levels replace the agent's last (kept, not
            # cleared at a quiet tick: the status covering the first alarm may be read a
            # tick before the alarm is, and is the agent's part of that picture)
            self._residual_peaks[agent] = {}
        peaks = self._residual_peaks.setdefault(agent, {})
        for name, level in list(levels.items())[:64]:
            if isinstance(level, bool) or not isinstance(level, (int, float)) \
                    or not math.isfinite(level) or level < 0:
                continue
            parsed = _residual_name(name)
            if parsed is None or parsed[-1] != agent:
                continue
            peaks[parsed[:-1]] = max(float(level), peaks.get(parsed[:-1], 0.0))
            if level >= 1:
                step = msg.get("step")
                if isinstance(step, int) and not isinstance(step, bool):
                    self._residual_last_alarm = max(self._residual_last_alarm, step)
        first = res.get("first")
        for name, entry in (list(first.items())[:64] if isinstance(first, dict) else ()):
            parsed = _residual_name(name)
            if parsed is None or parsed[-1] != agent or not isinstance(entry, list) \
                    or len(entry) != 2 or isinstance(entry[0], bool) \
                    or not isinstance(entry[0], int) or isinstance(entry[1], bool) \
                    or not isinstance(entry[1], (int, float)) or not math.isfinite(entry[1]) \
                    or entry[1] < 1:
                continue
            key = (agent, parsed[:-1])
            if key not in self._residual_first or entry[0] < self._residual_first[key][0]:
                self._residual_first[key] = (entry[0], float(entry[1]))
            if self._residual_alarm_step is None or entry[0] < self._residual_alarm_step:
                self._residual_alarm_step = entry[0]

    def _reset_residuals(self) -> None:
        self._residual_peaks, self._residual_first, self._residual_alarm_step = {}, {}, None

    def _residual_alerts(self, now: float) -> None:
        """The agents' residual tests of the configuration in force (the initial one's,
        computed by each agent, or those its assignments carried: every agent of the
        configuration must report tests of the current epoch) isolated to one agent (:func:`design.residuals.isolate`): a corroborated
        ``inconsistent estimates`` is a verdict (convicted by :meth:`tick` like any other);
        anything else is an alert, an event and a record once per agent and kind.

        An alarm is isolated once every agent of the configuration has reported a step at
        least as late as the earliest first alarm (statuses arrive at different times, and
        the first alarm heard may be a consequence, a receiver of a receiver, of one
        another agent reports later), on the picture at that earliest step: the tests that
        alarmed then, at their level then (what alarmed later is a consequence around the
        loop, as the simulator's benchmark isolates at the first alarm step). Nothing is isolated while an agent was disturbed
        lately (it used a held, late or lost estimate, or missed readings, within its
        settle window: that reaches every agent through the loop).

        Only a corroborated isolation convicts (:attr:`design.residuals.Verdict.
        corroborated`: at least two receivers flag the agent, each singling it out,
        nothing alarms elsewhere, no near-tie): a lie seen by a single receiver cannot be
        told from a fault of that receiver or link, and a ``sensor bias`` read from an
        agent's own innovation may be a fault elsewhere that reached its prior
        (docs/residuals.md); a wrong conviction removes a healthy agent."""
        from design.residuals import INCONSISTENT, AgentReport, isolate

        if self._residual_epoch != self.epoch:
            # a new configuration: what was noted of the last one's tests is no picture
            # of this one's
            self._reset_residuals()
            self._residual_hold, self._residual_epoch = False, self.epoch
        if self._pending is not None or any(
                _tests_epoch(self.agents[a].status.get("residuals")) != self.epoch
                for a in self.roster.ids):
            return     # a switch under way, or an agent not (yet) testing this configuration
        newest = self.last_step_reported
        settle, disturbed = 0, {}
        for a in self.roster.ids:
            res = self.agents[a].status.get("residuals")
            if isinstance(res, dict) and isinstance(res.get("disturbed"), int) \
                    and isinstance(res.get("settle"), int):
                settle = max(settle, res["settle"])
                if res["disturbed"] >= 0:
                    disturbed[a] = res["disturbed"] + res["settle"]    # tests back then
        if self._residual_hold:
            # one alert per episode: the fault goes on, and what alarms next are its
            # consequences around the loop; the episode ends after settle quiet steps
            if newest - self._residual_last_alarm > settle:
                self._residual_hold = False
            self._reset_residuals()
            return
        if any(newest < back for back in disturbed.values()):
            self._reset_residuals()
            return
        first = self._residual_alarm_step
        if first is None:
            return
        if any(self.agents[a].step < first for a in self.roster.ids):
            return                     # not every agent has reported the steps since
        reports = []
        for a in self.roster.ids:
            # the picture at the first alarm: what alarmed then, at its level then; what
            # alarmed only later (a consequence around the loop) counts as quiet
            levels = {}
            for test, peak in self._residual_peaks.get(a, {}).items():
                got = self._residual_first.get((a, test))
                levels[test] = got[1] if got is not None and got[0] <= first else (
                    peak if peak < 1 else 0.0)
            reports.append(AgentReport(a, levels.get(("innovation",), 0.0),
                                       {k[1]: v for k, v in levels.items() if k[0] == "link"}))
        self._reset_residuals()
        self._residual_hold = True
        blind = sorted(a for a, back in disturbed.items() if back >= first)
        if blind:
            # an agent's tests were starting over at the first alarm (it had used a held
            # estimate): its silence is no evidence, and the picture could name a
            # consequence
            self.events.append(f"residual alarm from step {first} not isolated: the tests "
                               f"of agents {blind} were starting over then")
            return
        verdict = isolate(reports)        # agent ids throughout
        if verdict is None:
            return
        agent = verdict.agent
        convict = verdict.kind == INCONSISTENT and verdict.corroborated \
            and agent in self.roster.ids and agent not in self.failed
        # an alert is raised once per agent and kind; a corroborated lie convicts whatever
        # was alerted of that agent before (an earlier, weaker picture of the same lie)
        if not convict and (agent, verdict.kind) in self._alerted:
            return
        self._alerted.add((agent, verdict.kind))
        if convict:
            own = next(r for r in reports if r.agent == agent)
            evidence = (
                f"residual tests of {_configuration_words(self.epoch)}, first alarm at step "
                f"{first}: "
                + " and ".join(f"agent {i} (link {agent}->{i} at {lv:.3g} x threshold)"
                               for i, lv in verdict.flagged_by)
                + f" flag its published estimates; its own tests were quiet then "
                f"(innovation {own.innovation:.3g} x threshold"
                + (f", links from agents {sorted(own.discrepancy)} below threshold"
                   if own.discrepancy else "")
                + "); nothing alarms at an agent that does not receive from it")
            self._residual_verdicts.append(
                Verdict(agent, INCONSISTENT, evidence, now, self.current_step(now)))
            self.events.append(f"residual conviction: agent {agent} {INCONSISTENT} (from "
                               f"step {first}); it will not rejoin after probation")
            return
        record = {"agent": agent, "fault": verdict.kind, "score": round(verdict.score, 3),
                  "evidence": list(verdict.evidence), "step": first,
                  "alternatives": [[a, kind, round(s, 3)]
                                   for a, kind, s in verdict.alternatives]}
        self.residual_alerts.append(record)
        self.events.append(f"residual alert: agent {agent} {verdict.kind} (level "
                           f"{verdict.score:.3g}, from step {first}): "
                           f"{'; '.join(verdict.evidence)}; not convicted (an alert)")

    def _residual_convictions(self, found: list) -> list:
        """The corroborated residual verdicts not yet answered (:meth:`tick` adds them to
        the detector's, so they go through the same settle window and reassignment):
        each until its agent is convicted, or has left the configuration."""
        self._residual_verdicts = [v for v in self._residual_verdicts
                                   if v.agent in self.roster.ids and v.agent not in self.failed]
        named = {v.agent for v in found}
        return [v for v in self._residual_verdicts if v.agent not in named]

    def _switch_ahead(self, now: float, margin: int = 0) -> bool:
        """The roles last sent are not yet in force (at least ``margin`` steps before
        their ``activate_at``): new gains for them (the refinement, the learned delays)
        wait for that step, so that they never postpone a recovery by superseding it with
        a later ``activate_at``; a failure found meanwhile may join them
        (:meth:`_joint_plan`)."""
        return self._roster_msg is not None \
            and self.current_step(now) < self._roster_msg.activate_at - margin

    def _late_but_running(self) -> bool:
        """Some agent that has not confirmed has stepped since its assignment went out: it
        runs but did not hear the roles in time, and a re-issue reaches it. One that has not
        stepped since (it died before its verdict came) is not re-issued to: the others'
        pending roles would be replaced before their step while some already ran them, a
        mixed switch (the dead agent is convicted and answered instead)."""
        sent = self._assigned_at
        return any(self.agents[a].progress_at is not None and sent is not None
                   and self.agents[a].progress_at > sent for a in self._unconfirmed)

    def _reissue(self, now: float) -> list:
        """``activate_at`` passed before every agent confirmed: the same roles again under
        a new epoch, every agent of the configuration, a later ``activate_at``."""
        late = sorted(self._unconfirmed)
        self.epoch += 1
        self.lead = min(2 * self.lead, self._lead_cap())
        lead = self.head_start()
        at = self.current_step(now) + lead
        out = []
        self._unconfirmed = {}
        tests = self.gain_info.get("residuals") or {}
        for agent, spec in self.specs.items():
            asg = Assignment(agent, self.epoch, at, spec, tests.get(agent))
            out.append(asg)
            self._unconfirmed[agent] = asg
        self._roster_msg = self._roster_update(self.epoch, at, self.roster.ids)
        out.append(self._roster_msg)
        self._sent_at = now
        if self.history:
            self.history[-1] = {**self.history[-1], "epoch": self.epoch, "activate_at": at,
                                "reissued": self.history[-1].get("reissued", 0) + 1}
        self.reissues.append({"epoch": self.epoch, "activate_at": at, "unconfirmed": late,
                              "reason": f"activate_at passed before agents {late} confirmed"})
        self.events.append(f"epoch {self.epoch}: activate_at passed before agents {late} "
                           f"confirmed; re-issued from step {at} ({lead} steps ahead)")
        return out

    def check_delays(self, now: float) -> list:
        """The ``delay`` verdict: learned delays above the design and the exact loop with
        them unstable -> gains designed for the learned delays, same roles, new epoch
        (sent when the gains are known: the gain worker designs them)."""
        from design.closed_loop import closed_loop_for

        if self._delay_pending is not None:
            p = self._delay_pending
            if not self.gains.ready(p["roster"], init=self.warm_start(p["roster"])):
                return []
            self._delay_pending = None
            G, info = self.gains.get(p["roster"])
            if G is None:
                self.events.append("no stabilising gain for the learned delays: keeping the "
                                   "gains in force")
                return []
            return self._assign_all(p["roster"], G, info, now, p["record"],
                                    "gains for the learned delays")
        above = self._delays_off_design()
        key = tuple(sorted(above.items()))
        if not above or key == self._delays_checked or self.G is None:
            return []
        self._delays_checked = key
        new = self.roster.with_delays(above)
        stable, radius = _stability(closed_loop_for(new.scenario, self.G, new.delays))
        evidence = ", ".join(f"link {b}->{a}: {t} steps (designed {self.roster.delays[self.roster.row_of(a), self.roster.row_of(b)]})"
                             for (a, b), t in sorted(above.items()))
        if stable:
            self.events.append(f"learned delays differ from the design ({evidence}) but the "
                               f"exact loop is still stable ({radius})")
            return []
        v = Verdict(0, "delay", f"{evidence}; the exact loop is not stable ({radius})", now,
                    self.current_step(now))
        self.verdicts.append(v)
        self.events.append(f"verdict: delay ({v.evidence})")
        self._delay_pending = {"roster": new, "record": {
            "causes": {"0": "delay"}, "delays": {f"{b}->{a}": t for (a, b), t
                                                in sorted(above.items())}}}
        return self.check_delays(now)

    def _delays_off_design(self) -> dict:
        """``{(receiver, sender): tau}``: the links of the configuration in force whose
        learned delay differs from the one the gains were designed for (stability is not
        monotone in the delays: shorter ones are checked too). Read from the statuses of
        its agents at every tick: an agent's links are read again only when its status
        changed (a status is replaced, never changed, when the next one comes), so a tick
        costs a look at each agent, not at each link (32 agents send 160 statuses a
        second, and the whole map read again at each tick was a sixth of the monitor's
        loop)."""
        roster = self.roster
        held = self._off_design
        if held is None or held[0] is not roster:
            held = self._off_design = (roster, {}, {})
        per = held[1]
        _, rows, listens, D, _ = self.detector.roster_view()    # (held for its roster)
        changed = False
        for a in roster.ids:
            status = self.agents[a].status
            got = per.get(a)
            if got is not None and got[0] is status:
                continue
            row = rows[a]
            links = {(a, b): tau for b, tau in self.detector.learned_delays(a).items()
                     if a != b and b in rows and listens[row][rows[b]]
                     and tau != D[row][rows[b]]}
            per[a] = (status, links)
            changed = changed or bool(links) or bool(got and got[1])
        if changed:
            above = {}
            for _, links in per.values():
                above.update(links)
            self._off_design = held = (roster, per, above)
        return held[2]

    def subscription_steps(self) -> int:
        """Steps the agents need to have a new link's estimates: the longest an agent
        reports (its status's ``estimates_from``) for declaring a subscription or for the
        first estimate a publisher's cache replayed into it, rounded up, plus one step;
        0 when none reports. At most :meth:`_lead_cap` (a status is an agent's word).
        At 10 ms steps, 41 ms reported: 6 steps."""
        longest = 0.0
        for a in self.agents.values():
            got = a.status.get("estimates_from") if a.status else None
            if not isinstance(got, dict):
                continue
            for field in ("declare_ms_max", "ready_ms_max"):
                ms = got.get(field)
                if isinstance(ms, (int, float)) and not isinstance(ms, bool) \
                        and math.isfinite(ms) and ms > longest:
                    longest = ms
        if longest <= 0:
            return 0
        return min(math.ceil(longest / 1e3 / self.config.step_s - 1e-9) + 1, self._lead_cap())

    def head_start(self) -> int:
        """The steps between sending roles and their ``activate_at``: :attr:`lead`, and
        never fewer than the agents need to subscribe to a new link
        (:meth:`subscription_steps`)."""
        return max(self.lead, self.subscription_steps())

    def _lead_cap(self) -> int:
        """The longest head start: twice the hang timeout, in steps."""
        return max(self.config.lead_steps,
                   math.ceil(2 * self.config.hang_timeout_s / self.config.step_s))

    def _check_confirmations(self, now: float) -> None:
        waiting = bool(self._unconfirmed)
        for agent, asg in list(self._unconfirmed.items()):
            a = self.agents[agent]
            if a.epoch >= asg.epoch or a.pending >= asg.epoch:
                del self._unconfirmed[agent]
                self.events.append(f"agent {agent} confirmed epoch {asg.epoch}")
            elif agent in self.failed:
                # convicted since: its reassignment answers it; re-issuing the roles to
                # it would only churn epochs while that reassignment waits for its gains
                del self._unconfirmed[agent]
                self.events.append(f"agent {agent} was convicted before it confirmed epoch "
                                   f"{asg.epoch}: not waited for")
        if waiting and not self._unconfirmed and self.history \
                and not self.history[-1].get("reissued") and self.lead > self.config.lead_steps:
            self.lead = (self.lead + self.config.lead_steps) // 2
        if (self._unconfirmed and self._assigned_at is not None
                and now - self._assigned_at > self.config.confirm_timeout_s):
            for agent in sorted(self._unconfirmed):
                a = self.agents[agent]
                stale = a.progress_at is None or now - a.progress_at > self.config.confirm_timeout_s
                if stale and agent in self.roster.ids and agent not in self.failed:
                    a.alive = False      # convicted at the next detection as 'crash'
                    self.events.append(f"agent {agent} did not confirm epoch "
                                       f"{self._unconfirmed[agent].epoch} and reports no "
                                       "progress: treated as failed")
                    del self._unconfirmed[agent]

    # -- reassignment ----------------------------------------------------------------
    def _reassign(self, verdicts: list, now: float, unanswered=()) -> list:
        """Record the verdicts, plan the failure on the configuration in force and emit
        the new roles as soon as their gains are known (:meth:`_emit_reassign`). Verdicts
        found while an earlier plan still waits for its gains join that plan.
        ``unanswered``: agents convicted earlier whose recovery was impossible then (no
        standby), planned again now that the pool has one."""
        from design.errors import SocmonError
        from design.roster import replan

        self.verdicts += verdicts
        failed = sorted({v.agent for v in verdicts} | set(unanswered))
        self.failed.update(failed)
        for a in failed:
            self.convicted_at[a] = now
            self.on_probation.add(a)
            self.agents[a].healthy_since = None
        self.barred.update(v.agent for v in verdicts if v.cause in NEVER_REJOIN)
        for v in verdicts:
            self.events.append(f"verdict: agent {v.agent} {v.cause} ({v.evidence})")
        if self._pending is not None:
            verdicts = self._pending["verdicts"] + verdicts
            failed = sorted(set(self._pending["failed"]) | set(failed))
        joint = self._joint_plan(verdicts, failed, now) if self._pending is None else None
        if joint is not None:
            self._pending = joint
            return self._emit_reassign(now)
        roster = dataclasses.replace(self.roster, standby_ids=self.standby_pool(now, failed))
        try:
            plan, nxt = replan(roster, failed, numerical=False)
        except SocmonError as exc:
            nxt, plan = None, None
            self.events.append(f"no recovery plan: {exc}")
        if nxt is None or not plan.structurally_observable_after:
            self._pending = None
            self.unrecoverable = True
            self.events.append(
                f"RECOVERY IMPOSSIBLE after the failure of {failed}: no equivalent agent or "
                "connected network left; keeping the configuration in force and monitoring")
            return []
        self.failed.difference_update(nxt.ids)       # a returned agent taken again is healthy
        self._pending = {"verdicts": verdicts, "failed": failed, "roster": roster,
                         "plan": plan, "nxt": nxt, "at": now, "asked": False}
        return self._emit_reassign(now)

    def _joint_plan(self, verdicts, failed, now: float):
        """A failure found after the last reassignment went out but before it came into
        force (agents killed together whose verdicts came apart under load): planned with
        that one's failures on the configuration still in force, when the gains of that
        joint configuration are known already (the precompute does pairs of failures for
        small networks), instead of one after the other on the configuration not yet in
        force, whose gains nobody foresaw. Sampson-like at T = 7, agents 1 and 2 killed at
        one step, verdicts 0.1 s apart: the second plan waited 1.5 s for its gains and the
        roles came 83 steps after the verdict. The pending roles are superseded (every
        agent of the joint configuration gets the new epoch). None when that does not
        apply: the last reassignment is in force already, the joint plan is not known, or
        it leaves out a live agent that the last one assigned a role (its pending role
        would not be replaced)."""
        from design.errors import SocmonError
        from design.roster import replan

        last = self._last_plan
        if last is None or not self._switch_ahead(now, margin=1) or last["epoch"] != self.epoch:
            return None
        both = sorted(set(last["failed"]) | set(failed))
        # its standbys as that plan had them (the one it took is in the roles not yet in
        # force, not out of the pool), less any convicted since
        base = last["roster"]
        base = dataclasses.replace(base, standby_ids=tuple(
            a for a in base.standby_ids if a not in both and a not in self.failed))
        try:
            plan, nxt = replan(base, both, numerical=False)
        except SocmonError:
            return None
        if nxt is None or not plan.structurally_observable_after \
                or not self.gains.has(nxt) \
                or not set(last["assigned"]) - set(both) <= set(nxt.ids):
            return None
        self.failed.difference_update(nxt.ids)
        self.events.append(f"agents {both} planned together on the configuration still in "
                           f"force (ids {list(base.ids)}): epoch {self.epoch} was not in "
                           "force yet and their joint gains are known")
        return {"verdicts": last["verdicts"] + verdicts, "failed": both, "roster": base,
                "plan": plan, "nxt": nxt, "at": now, "asked": False, "joint": True}

    def warm_start(self, nxt):
        """The gains in force carried over to the configuration ``nxt``
        (:func:`design.roster.carried_gains`), None when none are known (an adopted
        configuration)."""
        from design.roster import carried_gains

        return None if self.G is None else carried_gains(self.roster, self.G, nxt)

    def _emit_reassign(self, now: float) -> list:
        """The pending reassignment, once its gains are known; ``activate_at`` counts from
        now (not from the verdict), so it is never already past when it is sent."""
        from design.roster import role_specs

        p = self._pending
        nxt, plan, roster = p["nxt"], p["plan"], p["roster"]
        if not self.gains.ready(nxt, init=self.warm_start(nxt)):
            if not p["asked"]:
                p["asked"] = True
                self.events.append(f"gains for ids {list(nxt.ids)} not precomputed: designing "
                                   "them in the gain worker; detection goes on meanwhile")
            return []
        self._pending = None
        G, info = self.gains.get(nxt)
        if G is None:
            self.unrecoverable = True
            self.events.append("no stabilising gain for the new configuration; keeping the "
                               "configuration in force")
            return []
        precomputed = not p["asked"]
        take_over = {r.by: roster.ids[r.failed] for r in plan.replacements if r.by_standby}
        specs = role_specs(nxt, G, take_over=take_over)
        self.epoch += 1
        # the head start counts from the verdict: the settle window and a gain looked up
        # come out of it, and it is never less than lead - 1 steps from now (a gain
        # designed on request comes after the verdict's step has passed)
        verdict_step = min((v.step for v in p["verdicts"]), default=-1)
        lead = self.head_start()
        activate_at = max(verdict_step + lead,
                          max(self.current_step(now), 0) + max(lead - 1, 1))
        # a reassignment still waiting for its activate_at is superseded at the same step
        # (agents replace a pending assignment by a newer one): no agent runs the older
        # configuration for a step while another runs the newer one
        prev = self._roster_msg
        if prev is not None and prev.activate_at >= max(self.current_step(now), 0) \
                + self.config.lead_steps // 2:
            activate_at = min(activate_at, prev.activate_at)
        # ... else, when it is still pending but too close to reuse its step, every agent
        # gets the new epoch: one whose role did not change since the pending one would
        # otherwise run that one from its step while the others wait for the new one
        # (seen: agents 1 and 2 killed two steps apart, the second answered in 0.09 s)
        superseded = (prev is not None and activate_at != prev.activate_at
                      and prev.activate_at > max(self.current_step(now), 0)) \
            or p.get("joint", False)
        self._unconfirmed = {a: asg for a, asg in self._unconfirmed.items() if a in nxt.ids}
        out = []
        tests = info.get("residuals") or {}
        for agent, spec in specs.items():
            if not spec.same_as(self.specs.get(agent)) or spec.take_over or superseded:
                asg = Assignment(agent, self.epoch, activate_at, spec, tests.get(agent))
                out.append(asg)
                self._unconfirmed[agent] = asg
        roster_msg = self._roster_update(self.epoch, activate_at, nxt.ids)
        out.append(roster_msg)
        self._roster_msg = roster_msg
        self._sent_at = self._assigned_at = now
        verdicts = p["verdicts"]
        self._last_plan = {"epoch": self.epoch, "roster": roster, "failed": p["failed"],
                           "verdicts": verdicts,
                           "assigned": sorted(m.agent for m in out if isinstance(m, Assignment))}
        self.history.append({
            "epoch": self.epoch, "activate_at": activate_at, "failed": p["failed"],
            "causes": {v.agent: v.cause for v in verdicts}, "ids": list(nxt.ids),
            "replacements": [{"failed": roster.ids[r.failed], "by": r.by,
                              "from": self.scenario.labels[r.node_from],
                              "to": self.scenario.labels[r.node_to]} for r in plan.replacements],
            "added_links": [list(x) for x in plan.added_links],
            "precomputed": precomputed, "decided_at": p["at"], "sent_at": now,
            **_gain_record(info),
        })
        self.events.append(
            f"epoch {self.epoch}: {self._role_changes(nxt, plan)}"
            f"; ids {list(nxt.ids)} from step {activate_at}"
            + (" (precomputed gains" if precomputed else
               f" (gains designed in {now - p['at']:.2f} s") + f", {_gain_words(info)})")
        self.roster, self.G, self.specs, self.gain_info = nxt, G, specs, info
        if info.get("kind") == "fast":
            self.gains.refine(nxt)             # replaced under a new epoch when it is ready
        return out

    def _role_changes(self, nxt, plan) -> str:
        """What a reassignment changes, in words: every node each replacing agent measures
        now (the new one marked) and the links added (\"2 measures 9 and 8 (8 new); link
        added: 3 listens to 2\")."""
        labels = self.scenario.labels
        parts = []
        for r in plan.replacements:
            nodes = [labels[v] for v in nxt.scenario.measure[nxt.row_of(r.by)]]
            parts.append(f"{r.by} measures {' and '.join(nodes)}"
                         + (f" ({labels[r.node_to]} new)" if len(nodes) > 1 else ""))
        words = ", ".join(parts) or "no replacement needed"
        links = [f"{b} listens to {a}" for a, b in plan.added_links]
        if links:
            words += f"; link{'s' if len(links) > 1 else ''} added: {', '.join(links)}"
        return words

    def _assign_all(self, new, G, info, now: float, record: dict, why: str,
                    lead: int | None = None) -> list:
        """The same roles with new gains (or delays) under a new epoch: every agent of
        ``new`` gets an assignment, ``lead`` steps ahead (default :attr:`lead`)."""
        from design.roster import role_specs

        self.roster, self.G, self.gain_info = new, G, info
        self.specs = role_specs(new, G)
        self.epoch += 1
        at = max(self.current_step(now), 0) + (self.head_start() if lead is None
                                               else max(lead, self.subscription_steps()))
        tests = info.get("residuals") or {}
        out = [Assignment(a, self.epoch, at, sp, tests.get(a)) for a, sp in self.specs.items()]
        self._unconfirmed = {m.agent: m for m in out}
        self._roster_msg = self._roster_update(self.epoch, at, new.ids)
        out.append(self._roster_msg)
        self._sent_at = self._assigned_at = now
        self.history.append({"epoch": self.epoch, "activate_at": at, "failed": [],
                             "ids": list(new.ids), "replacements": [], "added_links": [],
                             "precomputed": False, "decided_at": now, "sent_at": now,
                             **record, **_gain_record(info)})
        self.events.append(f"epoch {self.epoch}: {why} from step {at} ({_gain_words(info)})")
        return out

    def _note_gain_mse(self) -> None:
        """The fast gain in force went out without its exact steady MSE (and, when its
        eigenvalues were counted below a bound, without its exact radius); when the
        worker sends them, they are said (an event, and a note in :attr:`gain_notes`)."""
        if self.gain_info.get("kind") != "fast" or self.gain_info.get("assessed") \
                or self.G is None:
            return
        G, info = self.gains.assessment(self.roster)
        if info.get("rho") is None or not _same_gains(G, self.G):
            return
        below = self.gain_info.get("rho_below")
        self.gain_info = {**{k: v for k, v in self.gain_info.items() if k != "rho_below"},
                          "mse": info.get("mse"), "rho": info["rho"], "assessed": True}
        if below is not None and not info["rho"] < below:
            # the count said otherwise: never seen; said, and the refined gain replaces it
            self.events.append(f"WARNING: epoch {self.epoch}: the fast gain's exact radius "
                               f"{info['rho']:.4f} is not below {below:g}, as its count said")
        self.gain_notes.append({"epoch": self.epoch, **_gain_record(self.gain_info)})
        self.events.append(f"epoch {self.epoch}: in force: {_gain_words(self.gain_info)}")

    def _upgrade_gains(self, now: float) -> list:
        """The configuration in force runs a fast gain and its refined gain has come back:
        the same roles with the refined gain, under a new epoch, a hang timeout ahead."""
        if self.gain_info.get("kind") != "fast" or self.G is None:
            return []
        G, info = self.gains.get(self.roster)
        if G is None or info.get("kind") != "refined":
            return []
        # not urgent: a hang timeout ahead, so that an agent slow under load hears it in
        # time and the network switches together
        lead = max(self.lead, math.ceil(self.config.hang_timeout_s / self.config.step_s))
        return self._assign_all(self.roster, G, info, now, {"causes": {"0": "refined"}},
                                "refined gains for the configuration in force", lead=lead)

    def _probation(self, now: float) -> None:
        """Agents on probation that stayed healthy for ``rejoin_s`` rejoin the standby pool
        (an event and an entry of :attr:`rejoins`); a break
        (:meth:`FailureDetector.standby_break`) starts the probation over: at once when the
        agent is down or cut off, after half the hang timeout when it is only slow. An
        agent whose last conviction is of a cause in :data:`NEVER_REJOIN` (it lied about its
        estimates) stays on probation for good: looking healthy proves nothing of it."""
        for a in sorted(self.on_probation):
            st = self.agents[a]
            if a in self.barred:
                continue
            if a in self.roster.ids:
                if a not in self.failed:            # taken again meanwhile
                    self.on_probation.discard(a)
                continue        # still in the roster: its reassignment waits for gains
            broken = self.detector.standby_break(a, now)
            if broken is None:
                st.slow_since = None
            elif broken[0] == "slow" and (st.slow_since is None
                                          or now - st.slow_since < self.config.hang_timeout_s / 2):
                # a slowness shorter than half the hang timeout (a loaded host) is no break
                st.slow_since = now if st.slow_since is None else st.slow_since
            else:
                if st.healthy_since is not None:
                    self.events.append(f"agent {a}'s probation starts over: {broken[1]}")
                st.healthy_since = st.slow_since = None
                continue
            if st.healthy_since is None:
                st.healthy_since = now
            if broken is None and now - st.healthy_since >= self.config.rejoin_s:
                self.on_probation.discard(a)
                self.failed.discard(a)
                pool = self.standby_pool(now)
                self.rejoins.append({"agent": a, "step": self.current_step(now),
                                     "healthy_s": round(now - st.healthy_since, 3),
                                     "standby": list(pool)})
                self.events.append(
                    f"agent {a} rejoined as a standby after {now - st.healthy_since:.1f} s of "
                    f"probation (progressing, sensor fresh, no impaired link): standbys "
                    f"{list(pool)}, {len(pool)} failure(s) can be answered by a replacement")

    def _retry_unanswered(self, now: float) -> list:
        """A failure whose recovery was impossible (no standby then) is planned again as
        soon as the pool has an agent (one that passed probation, or a new standby)."""
        stuck = [a for a in self.roster.ids if a in self.failed]
        if not (self.unrecoverable and stuck and self._pending is None
                and not self._unconfirmed and self.standby_pool(now)):
            return []
        self.unrecoverable = False
        self.events.append(f"a standby is available again: planning the recovery of "
                           f"{stuck} (impossible when they failed)")
        return self._reassign([], now, unanswered=stuck)

    def standby_pool(self, now: float, exclude=()) -> tuple:
        """Ids that can take a role now: alive, advancing as standbys (no role; a standby
        whose step has not moved for the hang timeout while the others' did is not), and
        not on probation after a conviction. A replaced agent that came back (SIGCONT, a
        healed partition) and was fenced into a standby rejoins the pool after probation
        (:meth:`_probation`)."""
        cfg = self.config
        out = []
        for a in sorted(self.agents):
            st = self.agents[a]
            if a in self.roster.ids or a in exclude or not st.alive or st.progress_at is None:
                continue
            if st.status.get("active"):
                continue
            if now - st.progress_at > cfg.hang_timeout_s and \
                    self.detector.newest_step(exclude=a) > st.step:
                continue        # stale while the others advanced (not: before the clock)
            if a in self.on_probation:
                continue
            out.append(a)
        first = [a for a in self.roster.standby_ids if a in out]
        return tuple(first + [a for a in out if a not in first])

    def confirmed(self) -> bool:
        return not self._unconfirmed

    # -- state from the network ------------------------------------------------------
    def _say_adopt_wait(self, line: str) -> None:
        if line != self._adopt_wait:          # said once per distinct reason
            self.events.append(line)
            self._adopt_wait = line

    def adopt(self, ids=None, epoch: int = 0, probation=(), barred=(),
              activate_at: int | None = None) -> bool:
        """Rebuild the configuration in force from the agents' statuses.

        A monitor that was (re)started, or that takes over from another one, knows
        nothing of past reassignments: the roster it heard (``ids``, ``epoch``) or, if
        none, the agents whose status says they are active, and each one's measured
        nodes and neighbour weights from its status, are the configuration in force.
        Without a roster, those are the agents whose last status says they are active in
        the newest epoch the live active agents run: one whose token is down is in it
        too (stopped, cut off, or dead: the verdicts decide, as for any agent of the
        configuration; left out, it would count as failed with no verdict and nothing
        would answer it), one still active in an older epoch is not (fenced out without
        having heard it). Agents of
        the scenario outside it count as failed; live agents without a role are the
        standbys. Epochs continue above every epoch seen. Returns False while a status
        is missing.
        """
        from design.errors import SocmonError
        from design.roster import Roster

        s = self.scenario
        if ids is None:
            live = [st.epoch for st in self.agents.values()
                    if st.alive and st.status.get("active")]
            ids = sorted(a for a, st in self.agents.items() if st.status.get("active")
                         and live and st.epoch == max(live))
        rows = [int(a) for a in ids]
        idle = [a for a in rows if not self.agents[a].status.get("active")]
        if not rows or idle:
            tokens = sorted(a for a, st in self.agents.items() if st.alive)
            heard = sorted(a for a, st in self.agents.items() if st.status)
            why = (f"agents {idle} of {rows} report no role" if rows
                   else "no live agent reports a role")
            self._say_adopt_wait(f"adoption waits: {why} (tokens seen: {tokens}; statuses "
                                 f"heard from: {heard})")
            return False
        W = np.zeros((len(rows), len(rows)))
        measure = []
        for i, a in enumerate(rows):
            st = self.agents[a].status
            for b, w in st["neighbours"].items():
                if b in rows and b != a:
                    W[i, rows.index(b)] = w
            W[i, i] = 1.0 - W[i].sum()
            measure.append(tuple(s.index_of(label) for label in st["measure"]))
        convicted = {int(a) for a in probation} - set(rows)
        self.on_probation |= convicted
        self.barred |= {int(a) for a in barred} & convicted
        standby = tuple(a for a, st in sorted(self.agents.items())
                        if a not in rows and st.alive and not st.status.get("active")
                        and a not in self.failed and a not in convicted)
        table = self.roster.table
        D = table[np.ix_([a - 1 for a in rows], [a - 1 for a in rows])]
        D = np.where((W > 0) & ~np.eye(len(rows), dtype=bool), D, 0)
        try:
            scen = s.replace(W=W, measure=tuple(measure), delays=D, standby=len(standby))
        except SocmonError as exc:
            # statuses from before and after a change, or a token not yet seen again:
            # wait for a consistent picture rather than act on this one
            self._say_adopt_wait(f"adoption waits: the statuses of {rows} do not form a "
                                 f"configuration yet ({str(exc)[:120]})")
            return False
        self.roster = Roster(scen, tuple(rows), standby, table, D)
        self.failed.update(a for a in range(1, s.N + 1) if a not in rows)
        self.failed.update(convicted)
        self.G, self.specs = None, {}
        self.epoch = max([self.epoch, int(epoch)] + [st.epoch for st in self.agents.values()])
        self.behind = False
        if activate_at is not None and int(epoch) == self.epoch:
            self._roster_msg = self._roster_update(epoch, activate_at, rows)
        self.events.append(f"adopted the configuration in force: ids {rows}, standby "
                           f"{list(standby)}, epoch {self.epoch}" + (
                               f"; on probation (convicted before): {sorted(convicted)}"
                               if convicted else "") + (
                               f", never to rejoin: {sorted(self.barred & convicted)}"
                               if self.barred & convicted else ""))
        return True


#: a (re)started monitor listens this long (the roster is re-published every ROSTER_S)
#: before it acts, so that it acts on the configuration in force, not on its scenario
LISTEN_S = 1.5
#: a monitor with a larger id hands the seat to a smaller one this long before the
#: smaller one's listening ends (a short gap rather than two monitors acting at once)
HANDOVER_S = 0.25
#: the monitor's loop period, and how often the acting monitor re-publishes the roster in
#: force (an agent coming back learns from it that it was replaced)
TICK_S = 0.01
ROSTER_S = 1.0


class MonitorSeat:
    """Which of several monitors acts, and what a monitor that (re)takes the seat adopts
    first: the policy of the monitor process and of the simulated runtime.

    The monitor with the smallest id whose token is alive acts, once it has listened
    ``listen_s``; the others stay passive and watch. An acting monitor goes on acting
    until a smaller id's token of a session it never saw (a restarted monitor) has been
    up for ``listen_s`` less :data:`HANDOVER_S` (that one acts then): a restarted monitor
    listening, or still precomputing before it declares its token, does not leave the
    run without a monitor. A smaller id back with a session seen before (a monitor that
    was paused, or cut off) acts at once, so the seat goes to it at once: two monitors
    never act together. A passive monitor keeps
    its detector's clock (:meth:`MonitorCore.watch`), so that taking the seat is not
    mistaken for a pause of its own. A monitor that becomes active adopts
    the configuration in force from the newest roster it heard (:meth:`on_roster`) or from
    the agents' statuses (:meth:`MonitorCore.adopt`), and does so again whenever the agents
    run an epoch it never issued (another monitor acted while it was paused or cut off).

    :meth:`decide` returns ``"act"`` (tick the core), ``"idle"`` (passive) or ``"wait"``
    (an adoption waits for more of the network); what it did is in :attr:`records`
    (``active``, ``adopted``: the run's record), :attr:`lines` (for the log),
    :attr:`precompute` (precompute the failures of the configuration in force) and
    :attr:`stand_down` (drop the precompute: another monitor acts), which the caller
    drains.

    The precompute of an acting monitor other than the first waits for the run's clock:
    before it, the first monitor is still precomputing before it joins (the clock waits
    for that, ``foresee_single_failures``), and a second monitor that acted meanwhile
    duplicated that work beside the starting agents
    (communities-32: three more design processes, each single failure's polish 9 s of
    CPU), then kept at it for minutes after it went passive. A monitor that goes passive
    stands down.
    """

    def __init__(self, core: MonitorCore, monitor_id: int, now: float,
                 listen_s: float = LISTEN_S):
        self.core, self.id = core, int(monitor_id)
        self.listen_s = listen_s
        self.listen_until = now + listen_s
        self.seen_since: dict = {}     # another monitor's id -> since when its token is up
        self.sessions_seen: set = set()   # (id, session) of the other monitors' tokens
        self.heard_roster: dict | None = None
        self.active = False
        self.records: list = []
        self.lines: list = []
        self.precompute = False
        self.stand_down = False
        self._precompute_due = False   # acting: precompute once the run's clock started
        self._alive_in = None          # the last monitors_alive, and its other ids (_decide)
        self._alive_ids: tuple = ()

    def on_roster(self, msg: dict) -> None:
        """A roster heard on ``ctl/0`` (its signature already checked by the caller)."""
        if self.core.accept_roster(msg) and (self.heard_roster is None
                                             or msg["epoch"] > self.heard_roster["epoch"]):
            self.heard_roster = msg

    def _seen_epoch(self) -> int:
        """The newest epoch the agents' statuses say they run or heard as the roster."""
        agents = self.core.agents.values()
        return max([st.status.get("roster_epoch", 0) or 0 for st in agents]
                   + [st.epoch for st in agents] + [0])

    def _adopt_heard(self) -> bool:
        """Adopt the roster heard if it is as new as anything the agents report and their
        statuses fit it; else the configuration the statuses give (a roster missed while
        this monitor listened, or one the agents have since moved past: waiting on it
        left a restarted monitor holding the seat without acting, 430 steps in a live
        chaos run)."""
        core, heard = self.core, self.heard_roster
        newest = max(core.epoch, self._seen_epoch())
        convicted = {} if heard is None else {"probation": heard.get("probation", ()),
                                              "barred": heard.get("barred", ())}
        if heard is not None and heard["epoch"] >= newest \
                and core.adopt(heard["ids"], heard["epoch"],
                               activate_at=heard["activate_at"], **convicted):
            return True
        return core.adopt(None, newest, **convicted)

    def decide(self, now: float, monitors_alive) -> str:
        """``monitors_alive``: the monitors whose token is up, as ids or as ``(id,
        session)`` pairs (the session tells a restarted monitor from one that was
        paused; an id alone counts as a new session when it comes)."""
        state = self._decide(now, monitors_alive)
        if state != "act":
            self.core.watch(now)
        if self._precompute_due and self.active and (self.id == 1
                                                     or self.core.last_step_reported >= 0):
            self.precompute, self._precompute_due = True, False
        return state

    def _decide(self, now: float, monitors_alive) -> str:
        core = self.core
        monitors_alive = tuple(monitors_alive)
        # the same monitors as at the last tick change nothing of what follows (each is
        # in seen_since already, its sessions seen): done again only when they change
        if monitors_alive != self._alive_in:
            alive: dict = {}
            for item in monitors_alive:
                i, session = item if isinstance(item, tuple) else (item, None)
                if int(i) != self.id:
                    alive.setdefault(int(i), set()).add(session)
            since = {}
            for i, sessions in alive.items():
                back = any(s is not None and (i, s) in self.sessions_seen for s in sessions)
                since[i] = self.seen_since.get(i, -math.inf if back else now)
                self.sessions_seen |= {(i, s) for s in sessions if s is not None}
            self.seen_since = since
            self._alive_in, self._alive_ids = monitors_alive, tuple(alive)
        # a smaller id acts once it has listened: until then this one goes on acting
        others = sorted(i for i in self._alive_ids
                        if now - self.seen_since[i] >= self.listen_s - HANDOVER_S)
        should = (not others or self.id < others[0]) and now >= self.listen_until
        if should and not self.active and core.detector.world_end is not None:
            # the run is over (the world's end heard): nothing is left to answer, and what
            # this monitor would act on are the last statuses the one before it acted on
            # (it raised a residual alert again, after the world's last step)
            return "idle"
        if should and not self.active:
            if core.history and not core.behind:
                pass                     # it acted before and nobody acted since
            elif core.history or self.heard_roster is not None or self._seen_epoch() > 0:
                # another monitor acted while this one was away (paused, cut off), or roles
                # were reassigned before it started: the configuration in force is the
                # roster heard or the agents' statuses; wait until they form one
                if not self._adopt_heard():
                    return "wait"
            self.lines.append("active")
            self.records.append(("active", {"monitor": self.id, "epoch": core.epoch}))
            self.active = self._precompute_due = True
        elif not should and self.active:
            self.lines.append(f"another monitor ({others[0]}) is active; passive")
            self.records.append(("passive", {"monitor": self.id, "to": others[0],
                                             "epoch": core.epoch}))
            self.active = self._precompute_due = False
            self.stand_down = True
        if self.active and core.behind:
            # the agents run an epoch this monitor never issued: another monitor acted while
            # this one was paused or cut off; rebuild from the network first
            if not self._adopt_heard():
                return "wait"
            self.records.append(("adopted", {"monitor": self.id, "epoch": core.epoch}))
            self._precompute_due = True
        return "act" if self.active else "idle"

