"""The protocol of an agent, as a state machine that never touches a socket.

:class:`AgentCore` takes decoded messages in (sensor readings, neighbour estimates, role
assignments, liveliness, impairment changes) with the time they arrived, and gives out the
estimates to publish and a status (the world's state machine is
:class:`agent.world.core.WorldCore`). The process shell (:mod:`agent.node.process`) only
feeds it from a :class:`broker_free_net.Peer`; unit tests step them by hand, so tests
control time.

Timeline (the same as the simulator's; every random number comes from
:mod:`design.noise`):

- step 0: the true state is ``x_0 = initial_state(seed)``; agent i's estimate is
  ``xhat^i_0 = initial_estimate(seed, i)`` (no update at step 0); it is published stamped 0;
- step k >= 1: ``x_k = A x_{k-1} + process_noise(seed, k-1)``; agent i reads
  ``y^i_k = H_i x_k + measurement_noise(seed, i, k, p_i)`` and runs
  :func:`design.estimator.estimator_step` with, from each neighbour j, the estimate stamped
  ``k - 1 - tau_ij`` (age ``1 + tau_ij``). Nothing exists before step 0: while no
  estimate of j is held (``k - 1 - tau_ij < 0``), j's weight goes to the agent's own
  prediction, as in :func:`design.estimator.estimator_step`;
- an agent that gets a role while it has no estimate (a standby agent) starts from the
  estimate of the agent named in the assignment's ``take_over`` (the freshest one held,
  propagated by A to step ``activate_at - 1``), or cold from
  ``initial_estimate(seed, id)``, and publishes that estimate stamped ``activate_at - 1``
  (the simulator's replacement does the same).

Timing invariants (one place):

- the world's step is the clock: an agent computes step k once the sensor readings for k
  have arrived and, from every live neighbour j, the estimate stamped ``k - 1 - tau_ij``
  (``tau_ij`` learned), or ``deadline_s`` after the readings arrived, whichever is first;
- a neighbour estimate missing at the deadline (or at once when a fresher one from the
  same neighbour is held, when an injected step delay holds the neighbour's messages until
  this agent's step moves on, when a keyed drop (``drop``) lost it, or when the
  neighbour's liveliness token is gone) counts one drop and is replaced by the freshest
  estimate held from that neighbour (stamp <= k - 1), propagated by ``A^(k - stamp)``;
  what is used follows :func:`design.estimator.neighbour_input`, the policy the simulator
  shares: an estimate older than ``max_age`` is lost and, as when nothing is held, its
  weight goes to the agent's own prediction. Liveliness only decides whether to wait, so
  the numbers do not depend on when a crash is noticed;
- keyed drops (``drop`` > 0): the estimate stamped s on link j -> i is lost iff
  ``design.noise.message_dropped(seed, j, i, s, drop)``, decided when it would be used,
  exactly as the simulator draws it;
- ``tau_ij`` is the smallest lateness ``max(0, k_done - stamp)`` among the last
  ``learn_window`` estimates delivered from j (``k_done`` = the receiver's last computed
  step when the estimate was delivered): a delay change is learned within ``learn_window``
  messages, a single late message does not change it;
- a receiver-side step delay of d on link j -> i (``LinkImpairments``) releases the estimate
  stamped s once ``k_done >= s + d``, so it is learned as ``tau_ij = d``;
- a role assignment is applied atomically before computing step ``activate_at``;
- a roster (the monitor's fence: the ids in force from ``activate_at`` under an epoch)
  is applied before computing step ``activate_at``: from then on estimates of ids
  outside it are ignored (counted ``fenced``), and an agent outside it whose role is
  older than the roster's epoch drops its role and becomes a standby.

Examples
--------
>>> import numpy as np
>>> core = AgentCore(AgentConfig(agent=2, A=np.eye(2), labels=("a", "b"), agents=(1, 2),
...                              seed=0, measurement_noise=0.0))
>>> core.active, core.step
(False, -1)
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from broker_free_net.codec import shorten
from broker_free_net.impair import DELIVER, HOLD, LinkImpairments, apply_impairment_message
from design import noise
from design.estimator import (
    FRESH,
    HELD,
    LOST,
    NONE,
    AgentRole,
    PowerCache,
    continued_stamp,
    estimator_step,
    hold_limit,
    neighbour_input,
)
from design.gains import gain_digest
from design.plausibility import ESTIMATE_MULTIPLE, READING_MULTIPLE, StateScale

from agent.protocol.wire import STAMP_WINDOW

__all__ = [
    "AssignmentError",
    "Role",
    "AgentConfig",
    "AgentCore",
    "validate_assignment",
    "initial_role",
    "agent_config",
    "WEIGHT_SUM_TOL",
]

#: |self_weight + sum of neighbour weights - 1| allowed in a role.
WEIGHT_SUM_TOL = 1e-9
#: Sensor stamps more than this ahead of the agent's step (0 before the clock starts) are
#: ignored: the stamp window of every key (:data:`agent.protocol.wire.STAMP_WINDOW`).
SENSOR_WINDOW = STAMP_WINDOW
#: A reading more than this many steps ahead of the agent's step is held aside until the
#: reading of the step just before or after it arrives (a world that was silent for a while
#: sends one every step; one stray stamp is never believed and cannot make the agent skip
#: the readings in between).
SENSOR_GAP = 64
#: Once the agent keeps pace with the world, a reading is refused (``sensor_future``) when
#: it is further ahead than SENSOR_GAP plus this many times the steps the world can have
#: made since the agent's newest in-order reading (elapsed time / the observed period): a
#: world cannot run ahead of its own clock, a forged stamp far ahead can.
SENSOR_PACE_FACTOR = 2.0
#: Steps of readings held at most (``SENSOR_GAP`` aside); beyond it the farthest go first.
SENSOR_HELD = 4096
#: Steps one :meth:`AgentCore.poll` computes at most; the caller polls again at once.
MAX_POLL_STEPS = 256
#: Rosters heard and not yet in force that an agent keeps (the newest): a genuine run has
#: one or two at a time; the bound holds against a flood of unsigned ones.
MAX_PENDING_ROSTERS = 16


_UNSET = object()


class AssignmentError(ValueError):
    """A role assignment is invalid or cannot be applied; the message says why."""


@dataclass(frozen=True, eq=False)
class Role:
    """What an agent does from step ``activate_at`` on.

    ``measure`` are node labels (order = columns of ``gain``), ``neighbours`` maps agent id
    (1-based) -> weight, ``gain`` is ``G_i`` (n x p_i).
    """

    epoch: int
    activate_at: int
    measure: tuple
    neighbours: dict
    self_weight: float
    gain: np.ndarray
    take_over: int | None = None
    #: new neighbour -> the failed agent whose stream it continues (the continuity rule)
    continues: dict = field(default_factory=dict)
    #: the agent's residual tests of the configuration this role belongs to
    #: (design.residuals.AgentTests), when the assignment carried them
    residuals: object = None


def validate_assignment(msg: dict, agent: int, labels, agents, n: int) -> Role:
    """Check a decoded assignment message for agent ``agent``; return its :class:`Role`.

    Raises
    ------
    AssignmentError
        Naming every problem found (wrong agent, unknown label or neighbour, weights not
        summing to 1, gain of the wrong shape or not finite).
    """
    problems = []
    if msg["agent"] != agent:
        problems.append(f"agent: message for agent {msg['agent']}, this is agent {agent}")
    label_set = set(labels)
    unknown = [m for m in msg["measure"] if m not in label_set]
    if unknown:
        problems.append(f"measure: unknown node labels {unknown}")
    nbrs = dict(msg["neighbours"])
    if agent in nbrs:
        problems.append("neighbours: an agent is not its own neighbour (use self_weight)")
    strangers = sorted(a for a in nbrs if a not in set(agents))
    if strangers:
        problems.append(f"neighbours: unknown agents {strangers}")
    w_self = float(msg["self_weight"])
    if not w_self > 0:
        problems.append(f"self_weight: must be > 0, got {w_self}")
    total = w_self + sum(nbrs.values())
    if abs(total - 1.0) > WEIGHT_SUM_TOL:
        problems.append(f"weights: self_weight + neighbour weights = {total!r}, must be 1")
    gain = np.asarray(msg["gain"], dtype=float)
    if gain.shape != (n, len(msg["measure"])):
        problems.append(f"gain: shape {gain.shape}, expected ({n}, {len(msg['measure'])}) "
                        "(n x measured nodes)")
    take_over = msg.get("take_over")
    if take_over is not None and (take_over == agent or take_over not in set(agents)):
        problems.append(f"take_over: {take_over} is not another agent of the run")
    continues = dict(msg.get("continues") or {})
    bad = sorted(b for b, f in continues.items() if b not in nbrs or f not in set(agents)
                 or f == agent or f == b)
    if bad:
        problems.append(f"continues: neighbours {bad} are not new neighbours continuing "
                        "another agent of the run")
    tests = None
    if msg.get("residuals") is not None and not problems:
        from design.residuals import AgentTests, ResidualError

        try:
            tests = AgentTests.from_wire(agent, msg["residuals"], n, len(msg["measure"]),
                                         [a for a, w in nbrs.items() if w > 0])
        except ResidualError as exc:
            problems.append(str(exc))
    if problems:
        raise AssignmentError("; ".join(problems))
    return Role(take_over=take_over, continues=continues, residuals=tests,
                epoch=int(msg["epoch"]), activate_at=int(msg["activate_at"]),
                measure=tuple(msg["measure"]),
                neighbours={a: w for a, w in nbrs.items() if w > 0},
                self_weight=w_self, gain=gain.copy())


@dataclass(frozen=True, eq=False)
class AgentConfig:
    """Everything an agent process is configured with (no networking).

    Parameters
    ----------
    agent : int
        This agent's id (1-based).
    A : (n, n) array
    labels : tuple of str
        Node labels, index order of the state.
    agents : tuple of int
        Every agent id of the run (active and standby).
    seed : int
        Run seed (initial estimates and measurement noise, :mod:`design.noise`).
    measurement_noise : float
        Variance r of each sensor reading's noise.
    role : Role or None
        Initial role (epoch 0); None for a standby agent.
    link_delays : dict
        ``{source agent: d}``: receiver-side step delay injected at start on link source -> agent.
    deadline_s : float
        How long to wait for late neighbour estimates after the step's readings arrived.
    learn_window : int
        Number of recent deliveries the delay of a link is learned from.
    history : int
        Estimates kept per neighbour (stamps); at least ``max_age + 1`` are kept.
    impair_seed : int
        Seed of the random drops of injected impairments.
    max_age : int
        Oldest age at which a held neighbour estimate is used (the neighbour policy,
        :func:`design.estimator.hold_limit`); powers of A are kept up to it.
    process_noise : float
        Variance q of the world's process noise (with ``A`` and ``measurement_noise``,
        the scale past which a value is implausible: :mod:`design.plausibility`).
    drop : float
        Probability of a keyed drop (:func:`design.noise.message_dropped`) per estimate
        and link, the simulator's drop model; 0 for none.
    residuals : design.residuals.AgentResiduals or None
        The agent's residual tests of its initial configuration (its innovation, and the
        discrepancy of each in-neighbour's on-time estimate, against thresholds from the
        exact loop); their levels are in its status while that configuration holds.
    test_residuals : bool
        Run the residual tests an assignment carries (those of the configuration it
        belongs to, computed by the monitor) from its ``activate_at`` on.
    lie : design.simulate.Fault or None
        A scripted misbehaviour (kind ``lie``): the estimates it publishes from the fault's
        step on carry its offset, its own estimate staying honest (as the simulator's).
    sensor_faults : tuple of design.simulate.Fault
        Scripted faults of its sensor (kinds ``bias``, ``drift``, ``noise``): its readings
        from each fault's step on, as the simulator's
        (:func:`design.simulate.apply_sensor_faults`).
    """

    agent: int
    A: np.ndarray
    labels: tuple
    agents: tuple
    seed: int
    measurement_noise: float
    role: Role | None = None
    process_noise: float = 0.0
    link_delays: dict = field(default_factory=dict)
    deadline_s: float = 0.02
    learn_window: int = 8
    history: int = 64
    impair_seed: int = 0
    max_age: int = hold_limit(0)
    drop: float = 0.0
    residuals: object = None
    test_residuals: bool = False
    lie: object = None
    sensor_faults: tuple = ()


class _Neighbour:
    """What an agent holds from one other agent."""

    __slots__ = ("est", "lateness", "heard", "missed", "alive", "step_held", "joined",
                 "cont", "newest", "in_order")

    def __init__(self, window: int):
        self.est: dict = {}              # stamp -> x
        self.newest = None               # the newest stamp held (pruning never drops it)
        self.in_order = True             # stamps were added in increasing order: the
                                         # dict's order is theirs
        self.lateness = deque(maxlen=window)
        self.heard = False               # at least one estimate delivered
        self.missed: set = set()         # stamps needed but missing at a deadline
        self.alive = True
        self.step_held = 0               # messages held by an injected step delay
        self.joined = 0                  # the step the link joined the current role
        self.cont = None                 # (failed agent, first own stamp): the link
                                         # continues that agent's stream before it

    @property
    def tau(self):
        return min(self.lateness) if self.lateness else None

    @property
    def since(self) -> int:
        """The oldest stamp usable on the link of the current role: ``joined - 1 - tau``,
        with the delay learned by now (0 while nothing came: nothing is held then). Read
        when used, not fixed when the link joined: with neighbour-only subscriptions a
        new link's first estimates (its publisher's cache answering the subscription) may
        come after the step it joined, and only they teach its delay."""
        tau = self.tau
        return self.joined - 1 - (0 if tau is None else tau)

    def keep(self, stamp: int, x, history: int) -> None:
        """Hold ``x`` stamped ``stamp``; drop the stamps ``history`` or more older than the
        newest. While stamps come in order the oldest are the dict's first ones, so the
        pruning stops at the first one kept instead of scanning all (once per delivery)."""
        est = self.est
        newest = self.newest
        if newest is None or stamp > newest:
            self.newest = newest = stamp
        elif stamp not in est:
            self.in_order = False
        est[stamp] = x
        if len(est) > history:
            floor = newest - history
            if self.in_order:
                stale = []
                for s in est:
                    if s > floor:
                        break
                    stale.append(s)
            else:
                stale = [s for s in est if s <= floor]
            for s in stale:
                del est[s]

    def freshest(self, at_most: int, usable=None):
        stamps = [s for s in self.est if s <= at_most and (usable is None or usable(s))]
        return max(stamps) if stamps else None


class AgentCore:
    """The agent's protocol: stepped by the caller with explicit times (seconds).

    Feed it with :meth:`on_sensor`, :meth:`on_estimate`, :meth:`on_assignment`,
    :meth:`on_impairment`, :meth:`set_alive`, :meth:`note_heard`; call :meth:`poll` to
    run every step that can run now; :meth:`next_wakeup` says when a deadline or a held
    message falls due.
    """

    def __init__(self, config: AgentConfig):
        self.config = config
        self._gains_digest = None          # of the gain it started with (_started_gains)
        self.id = int(config.agent)
        self.A = np.asarray(config.A, dtype=float)
        self.n = self.A.shape[0]
        self.labels = tuple(config.labels)
        self._label_index = {label: i for i, label in enumerate(self.labels)}
        self.powers = PowerCache(self.A, max_power=max(int(config.max_age), 1))
        self.history = max(int(config.history), int(config.max_age) + 1)
        self._dropped: dict = {}          # (sender, stamp) -> lost by a keyed drop
        self._est_role = None             # (role, columns read, AgentRole) last used
        self._wanted = (_UNSET, _UNSET, ())  # (role, pending, wanted_labels()) last asked
        self._measurement_noise = noise.StepDraws(
            lambda k, p: noise.measurement_noise(config.seed, self.id, k, p,
                                                 config.measurement_noise)[0])
        self.states = {FRESH: 0, HELD: 0, LOST: 0, NONE: 0}
        self.role: Role | None = config.role
        self.pending: Role | None = None
        self.epoch = config.role.epoch if config.role is not None else 0
        self.x = None                     # xhat_{k|k} at k = self.step (None: no role yet)
        self.step = -1                    # last completed step
        self.sensor: dict = {}            # step -> {label: value}
        self.sensor_aside: dict = {}      # step -> {label: value}: far ahead, not yet believed
        self.ready_at: float | None = None  # when the readings of step + 1 were in hand
        self.nbrs: dict = {}
        self.impair = LinkImpairments(seed=config.impair_seed)
        for src, d in config.link_delays.items():
            if d:
                self.impair.set((int(src), self.id), delay_steps=int(d))
        self.drops = 0
        self.late = 0
        self.impaired = 0
        self.sensor_missed = 0
        self.sensor_future = 0            # readings refused: ahead of the world's pace
        self.scale = StateScale(self.A, config.process_noise, config.measurement_noise)
        self.implausible = {"estimates": 0, "readings": 0}  # refused: far beyond the scale
        self.sensor_last = -1
        self._pace = None                 # (newest in-order step, its arrival, period s)
        self.ctl_accepted = 0
        self.ctl_rejected = 0
        self.ctl_last_error = ""
        self.heard: set = set()
        self.roster_epoch = 0
        # rosters heard, not yet in force: (epoch, activate_at, frozenset ids), epochs and
        # activate_at both increasing (an agent behind the run, e.g. resumed after a pause,
        # hears several at once, and each takes effect at its own step)
        self.roster_pending: list = []
        self.fence = None                 # ids in force, or None before any roster
        self.fenced = 0
        self.residual_levels: dict = {}   # the residual tests' levels at the last step
        self._residual_peak: dict = {}    # ... their largest since the last status
        self._residual_first: dict = {}   # test -> (step, level) of its first alarm since
        self.residual_alarms = 0          # steps at which a test alarmed (level >= 1)
        # the residual tests in force (design.residuals.AgentResiduals): the initial
        # configuration's, then those an assignment carries (a role changes only there);
        # they hold while the agent has its role and no newer roster is in force
        self.residuals = config.residuals
        self._ever_tested = config.residuals is not None

    # -- helpers ------------------------------------------------------------------
    @property
    def active(self) -> bool:
        return self.role is not None

    def _nb(self, agent: int) -> _Neighbour:
        nb = self.nbrs.get(agent)
        if nb is None:
            nb = self.nbrs[agent] = _Neighbour(self.config.learn_window)
        return nb

    def wanted_labels(self) -> tuple:
        """Sensor labels this agent must receive (current and pending roles, or a clock).
        Kept while the role and the pending role are the same objects (roles are frozen):
        asked several times a message."""
        held = self._wanted
        if held[0] is self.role and held[1] is self.pending:
            return held[2]
        wanted = []
        for role in (self.role, self.pending):
            if role is not None:
                wanted += [m for m in role.measure if m not in wanted]
        out = tuple(wanted) if wanted else (self.labels[0],)
        self._wanted = (self.role, self.pending, out)
        return out

    def learned_delays(self) -> dict:
        """``{neighbour: tau}`` for the current neighbours heard from."""
        if self.role is None:
            return {}
        out = {}
        for j in self.role.neighbours:
            nb = self.nbrs.get(j)
            if nb is not None and nb.tau is not None:
                out[j] = nb.tau
        return out

    def neighbour_ages(self) -> dict:
        """``{neighbour: step - stamp of the freshest estimate held}`` for the current role
        (-1 when nothing is held): the evidence of a neighbour gone silent."""
        if self.role is None or self.step < 0:
            return {}
        out = {}
        for j in self.role.neighbours:
            nb = self.nbrs.get(j)
            s = nb.freshest(self.step) if nb is not None else None
            out[j] = -1 if s is None else self.step - s
        return out

    # -- inputs ------------------------------------------------------------------
    def on_sensor(self, label: str, step: int, value: float, now: float | None = None) -> bool:
        """A sensor reading of node ``label`` at ``step`` (the true state, without noise).

        Returns False if it is ignored: a step already computed, or more than
        ``SENSOR_WINDOW`` ahead, or beyond the model's scale (:mod:`design.plausibility`,
        counted in ``implausible``). A reading more than ``SENSOR_GAP`` ahead is held aside
        (unused) until a reading of an adjacent step arrives, which a world that resumes
        after a silence sends at once; a lone stray stamp is never believed. At most
        ``SENSOR_HELD`` steps are held, ``SENSOR_GAP`` of them aside (farthest dropped).

        With ``now`` (the arrival time): once the agent keeps pace with the world (two
        in-order readings seen), a reading further ahead than the world can be
        (:data:`SENSOR_PACE_FACTOR`) is refused and counted ``sensor_future``; an agent
        that was stopped for seconds accepts the readings of those seconds.
        """
        step = int(step)
        base = max(self.step, 0)
        if step <= self.step or step > base + SENSOR_WINDOW:
            return False
        pace = self._pace
        if now is not None and pace is not None and pace[2] is not None:
            newest, at, period = pace
            if step > newest + SENSOR_GAP + SENSOR_PACE_FACTOR * max(now - at, 0.0) / period:
                self.sensor_future += 1
                return False
        if not self.scale.plausible(value, step, READING_MULTIPLE):
            self.implausible["readings"] += 1
            return False
        if now is not None and step <= base + SENSOR_GAP:
            self._note_pace(step, now)
        aside = self.sensor_aside
        for s in [s for s in aside if s <= self.step]:
            del aside[s]
        reading = {label: float(value)}
        if step > base + SENSOR_GAP:
            if not any(s in self.sensor or s in aside for s in (step - 1, step + 1)) \
                    and step not in self.sensor:
                aside.setdefault(step, {}).update(reading)
                while len(aside) > SENSOR_GAP:
                    del aside[max(aside)]
                return True
            for direction in (-1, 1):  # the readings aside next to this one are believed too
                s = step + direction
                while s in aside:
                    self._hold_reading(s, aside.pop(s))
                    s += direction
        self._hold_reading(step, reading)
        return True

    def on_sensors(self, step: int, x, now: float | None = None) -> int:
        """The world's readings of every node at ``step`` (one message a step, ``x`` in
        the order of ``labels``): each node this agent wants goes to :meth:`on_sensor`.
        With the world's link into this agent cut (an injected partition of link
        ``0 -> agent``, a stuck sensor) nothing is taken and ``impaired`` counts it.
        Returns the readings taken."""
        if self.impair.get((0, self.id)).partition:
            self.impaired += 1
            return 0
        index = self._label_index
        taken = 0
        for label in self.wanted_labels():
            taken += self.on_sensor(label, step, float(x[index[label]]), now=now)
        return taken

    def _note_pace(self, step: int, now: float) -> None:
        """The world's pace from in-order readings: the newest step, when it came, and the
        period between steps (the shortest seen over a reading one step after another,
        floored at 1 ms: bursts after a stall must not make the world look slow)."""
        pace = self._pace
        if pace is None:
            self._pace = (step, now, None)
        elif step > pace[0]:
            period = pace[2]
            if step == pace[0] + 1 and now > pace[1]:
                gap = max(now - pace[1], 1e-3)
                period = gap if period is None else min(period, gap) * 0.5 + period * 0.5
            self._pace = (step, now, period)

    def _hold_reading(self, step: int, readings: dict) -> None:
        if step <= self.step:
            return
        self.sensor.setdefault(step, {}).update(readings)
        self.sensor_last = max(self.sensor_last, step)
        while len(self.sensor) > SENSOR_HELD:
            del self.sensor[max(self.sensor)]

    def on_estimate(self, sender: int, stamp: int, x, now: float) -> str:
        """An estimate of agent ``sender`` stamped ``stamp``; returns the link's decision."""
        if sender == self.id:
            return "self"
        if self.fence is not None and sender not in self.fence:
            self.fenced += 1
            return "fenced"
        x = np.array(x, dtype=float)
        # judged at its stamp, the step it is used at (an estimate is never used before)
        if not self.scale.plausible(x, int(stamp), ESTIMATE_MULTIPLE):
            self.implausible["estimates"] += 1
            return "implausible"
        step_held = self.impair.get((sender, self.id)).delay_steps > 0
        decision = self.impair.offer(sender, self.id, (stamp, x, step_held),
                                     stamp_step=stamp, arrival=now)
        if decision.action == DELIVER:
            self._deliver(sender, stamp, x)
        elif decision.action == HOLD:
            if step_held:
                self._nb(sender).step_held += 1
        else:
            self.impaired += 1
        return decision.action

    def _deliver(self, sender: int, stamp: int, x) -> None:
        nb = self._nb(sender)
        if stamp in nb.missed:
            nb.missed.discard(stamp)
            self.late += 1
        nb.heard = True
        # the link's delay is learned from fresh estimates only: a stamp older than the
        # newest held is a replay (a publisher's cache answering a subscription declared
        # again when the role changed: up to `history` old estimates at once) or a late
        # straggler, whose age says nothing of the link and would push the fresh samples
        # out of the window
        if nb.newest is None or stamp > nb.newest:
            nb.lateness.append(max(0, self.step - stamp))
        nb.keep(stamp, x, self.history)

    def on_impairment(self, msg: dict) -> bool:
        """Apply a decoded impairment change if it concerns a link into this agent.

        Link ``0 -> agent`` is the world's (the sensor readings): a partition of it
        silences this agent's sensors."""
        if msg["op"] != "clear_all" and msg.get("dst") != self.id:
            return False
        apply_impairment_message(self.impair, msg)
        return True

    def on_assignment(self, msg: dict) -> Role:
        """A decoded role assignment; applied before step ``activate_at``.

        Raises
        ------
        AssignmentError
            Invalid, older than the current or pending epoch, or ``activate_at`` already past.
        """
        try:
            role = validate_assignment(msg, self.id, self.labels, self.config.agents, self.n)
            newest = max(self.epoch, self.pending.epoch if self.pending else 0)
            if role.epoch <= newest:
                raise AssignmentError(f"epoch: {role.epoch} is not newer than epoch {newest}")
            if role.activate_at <= self.step:
                raise AssignmentError(
                    f"activate_at: step {role.activate_at} already done (at step {self.step})")
        except AssignmentError as exc:
            self.ctl_rejected += 1
            self.ctl_last_error = shorten(str(exc))
            raise
        self.pending = role
        self.ctl_accepted += 1
        return role

    def on_roster(self, msg: dict) -> bool:
        """A decoded roster; True if it is newer than the one known (applied at its step).

        A newer roster supersedes the pending ones that would start at or after its own
        ``activate_at`` (they are never in force); an earlier one still takes effect at its
        step, so an agent that hears two rosters at once still drops a role at the first.
        """
        epoch = int(msg["epoch"])
        newest = max(self.roster_epoch,
                     self.roster_pending[-1][0] if self.roster_pending else 0)
        if epoch <= newest:
            return False
        at = int(msg["activate_at"])
        kept = [r for r in self.roster_pending if r[1] < at]
        self.roster_pending = (kept + [(epoch, at, frozenset(msg["ids"]))])[-MAX_PENDING_ROSTERS:]
        return True

    def _apply_roster(self, k: int) -> None:
        while self.roster_pending and self.roster_pending[0][1] <= k:
            epoch, _, ids = self.roster_pending.pop(0)
            self.roster_epoch, self.fence = epoch, ids
            if self.id not in ids and self.role is not None and self.epoch < epoch:
                # replaced while away (paused, cut off): fenced, back to standby
                self.role, self.x, self.epoch = None, None, epoch
                if self.pending is not None and self.pending.epoch <= epoch:
                    self.pending = None

    def set_alive(self, agent: int, alive: bool) -> None:
        self._nb(agent).alive = bool(alive)

    def note_heard(self, agent: int) -> None:
        """A status of ``agent`` reached this agent (the start handshake)."""
        if agent != self.id:
            self.heard.add(agent)

    # -- stepping ------------------------------------------------------------------
    def _release(self, now: float) -> None:
        for src, _dst, (stamp, x, step_held) in self.impair.release(now_step=self.step,
                                                                    now_time=now):
            if step_held:
                self._nb(src).step_held -= 1
            self._deliver(src, stamp, x)

    def next_wakeup(self, now: float, poll_s: float = 0.001):
        """Latest time at which :meth:`poll` must run again without a new message.

        A step deadline, or ``now + poll_s`` while impaired messages are held (they fall
        due by step or by time); None when only a new message can move the agent on.
        """
        times = []
        if self.ready_at is not None:
            times.append(self.ready_at + self.config.deadline_s)
        if self.impair.held:
            times.append(now + poll_s)
        return min(times) if times else None

    def _readings(self, k: int):
        """(values by label, is_complete) for step k, or None to keep waiting."""
        wanted = self.wanted_labels()
        have = self.sensor.get(k)
        if have is None:
            have = {}
        for m in wanted:
            if m not in have:
                break
        else:
            return have, True
        # a reading of a later step on a wanted label: the missing ones for k are lost
        for s, v in self.sensor.items():
            if s > k:
                for m in wanted:
                    if m in v:
                        return have, False
        return None

    def poll(self, now: float) -> list:
        """Run the steps that can run at time ``now`` (at most ``MAX_POLL_STEPS``: call again
        while it keeps moving); return ``[(step, x, epoch)]`` to publish: each estimate
        under the epoch of the role that computed it (a batch may cross a role change)."""
        out = []
        for _ in range(MAX_POLL_STEPS):
            if self.impair.held:
                self._release(now)
            k = self.step + 1
            got = self._readings(k) if self.step >= 0 else self._first_readings()
            if got is None:
                return out
            if self.step < 0:
                out += self._start(got)
                continue
            readings, complete = got
            if self.roster_pending:
                self._apply_roster(k)
            if self.pending is not None and self.pending.activate_at <= k:
                out += self._activate(self.pending, k)
            if self.role is None:
                self._finish(k, None)
                continue
            if self.ready_at is None:
                self.ready_at = now
            plan = self._plan(k, now)
            if plan is None:
                return out
            if not complete:
                self.sensor_missed += 1
            out.append((k, self._published(k, self._compute(k, readings, plan)), self.epoch))
        return out

    def _published(self, k: int, x):
        """The estimate published for step k: ``x``, or ``x`` plus a scripted lie's offset
        (:attr:`AgentConfig.lie`, the simulator's :class:`design.simulate.Fault`)."""
        lie = self.config.lie
        if lie is None or k < lie.start:
            return x
        return x + lie.offset(k, math.sqrt(self.config.measurement_noise)) * lie.vector(self.n)

    def _first_readings(self):
        wanted = self.wanted_labels()
        steps = [s for s, v in self.sensor.items() if any(m in v for m in wanted)]
        return min(steps) if steps else None

    def _start(self, k0: int) -> list:
        """First reading seen at step k0 (0 in a normal run): hold the initial estimate."""
        if self.pending is not None and self.pending.activate_at <= k0:
            self._activate(self.pending, k0)
        self._finish(k0, None)
        if self.role is None:
            return []
        self.x = noise.initial_estimate(self.config.seed, self.id, self.n)[0]
        return [(k0, self.x, self.epoch)]

    def _activate(self, role: Role, k: int) -> list:
        """Apply ``role`` before step k; a new estimate is published stamped k - 1."""
        out = []
        if self.x is None and self.step >= 0:
            nb = self.nbrs.get(role.take_over) if role.take_over else None
            s = nb.freshest(k - 1) if nb is not None else None
            if s is not None:
                # one-off propagation: may be older than the hold limit, not cached
                self.x = np.linalg.matrix_power(self.A, k - 1 - s) @ nb.est[s]
            else:
                self.x = noise.initial_estimate(self.config.seed, self.id, self.n)[0]
            out.append((k - 1, self.x, role.epoch))     # published under the new epoch
        # a link new in this role carries, like the simulator's, only what is delivered on
        # it from step k on: the estimate stamped k - 1 - tau and later ones (what the
        # agent heard from that neighbour before is not held on this link); tau is the
        # link's delay when the link is read (_Neighbour.since), which a link heard for the
        # first time at this step may not have taught yet
        old = self.role.neighbours if self.role is not None else {}
        for j in role.neighbours:
            if j not in old:
                nb = self._nb(j)
                nb.joined = k
                # the continuity rule (design.estimator.continued_stamp): a neighbour
                # that takes over a failed agent's row carries, before its own first
                # estimate (stamped k - 1), the stream this agent receives from that agent
                f = role.continues.get(j)
                nb.cont = (f, k - 1) if f is not None and f in self.nbrs else None
        self.role, self.pending, self.epoch = role, None, role.epoch
        self._new_residuals(role, k)
        return out

    def _new_residuals(self, role: Role, k: int) -> None:
        """The residual tests of ``role``'s configuration, from step k (their warm-up
        counts from there), when its assignment carried them and this agent runs them;
        else none (the old ones tested a loop no longer run). What was reported of the
        old tests is not carried over."""
        from design.residuals import AgentResiduals

        tested = role.residuals is not None and self.config.test_residuals
        self.residuals = AgentResiduals(role.residuals, epoch=role.epoch, start=k) \
            if tested else None
        self._ever_tested = self._ever_tested or tested
        self._residual_peak, self._residual_first, self.residual_levels = {}, {}, {}

    def _residuals_in_force(self) -> bool:
        """The agent has a role (not fenced) and no newer roster replaced the tests'
        configuration (a change that reassigned others but not this agent)."""
        res = self.residuals
        return res is not None and self.role is not None and self.roster_epoch <= res.epoch

    def _usable(self, sender: int, stamp: int) -> bool:
        """False iff a keyed drop lost the estimate of ``sender`` stamped ``stamp``."""
        p = self.config.drop
        if p <= 0:
            return True
        key = (sender, stamp)
        lost = self._dropped.get(key)
        if lost is None:
            lost = bool(noise.message_dropped(self.config.seed, sender, self.id, stamp, p)[0])
            self._dropped[key] = lost
            if len(self._dropped) > 4 * self.history * max(1, len(self.nbrs)):
                floor = self.step - self.history
                self._dropped = {kk: v for kk, v in self._dropped.items() if kk[1] > floor}
        return not lost

    def _plan(self, k: int, now: float):
        """``{neighbour: (stamp used or None, stamp needed, whose estimate)}`` for step k, or
        None to wait."""
        plan, waiting = {}, False
        for j in self.role.neighbours:
            nb = self._nb(j)
            tau = nb.tau
            need = max(k - 1 - (0 if tau is None else tau), 0)
            if need in nb.est and need >= nb.since and self._usable(j, need):
                plan[j] = (need, need, j)
            elif (nb.alive and not nb.step_held and need not in nb.est
                  and not (nb.est and max(nb.est) > need)):
                # no use waiting when a fresher estimate is held (the one needed was lost),
                # when a keyed drop lost it, when this link's injected step delay holds the
                # neighbour's messages until this agent's step moves on, or when the
                # neighbour's liveliness token is gone
                waiting = True
                plan[j] = (None, need, j)
            else:
                plan[j] = (None, need, j)
        if waiting and now < self.ready_at + self.config.deadline_s:
            return None
        for j, (s, need, _) in plan.items():
            if s is None:
                nb = self.nbrs[j]
                if nb.heard:
                    self.drops += 1
                    nb.missed.add(need)
                    if len(nb.missed) > self.history:
                        nb.missed.discard(min(nb.missed))
                stamp, src = self._freshest(j, k - 1)
                plan[j] = (stamp, need, src)
        return plan

    def _freshest(self, j: int, at_most: int) -> tuple:
        """``(stamp, source)``: the freshest estimate usable on the link from ``j``: its own
        (from the link's first usable stamp on) or, on a link that continues a failed
        agent's row (:func:`design.estimator.continued_stamp`), that agent's before ``j``'s
        first stamp. ``(None, j)`` when nothing is usable."""
        nb = self.nbrs[j]
        since = nb.since
        s = nb.freshest(at_most, lambda st: st >= since and self._usable(j, st))
        if s is None and nb.cont is not None:
            f, first = nb.cont
            src = self.nbrs[f]
            s = src.freshest(at_most, lambda st: continued_stamp(st, first)
                             and self._usable(f, st))
            if s is not None:
                return s, f
        return s, j

    def _compute(self, k: int, readings: dict, plan: dict):
        role = self.role
        cols = [c for c, m in enumerate(role.measure) if m in readings]
        z = self._measurement_noise(k, len(role.measure))
        if self.config.sensor_faults:
            from design.simulate import apply_sensor_faults   # (its module is slow to load)

            z = apply_sensor_faults(self.config.sensor_faults, k, z,
                                    math.sqrt(self.config.measurement_noise))
        y = np.array([readings[role.measure[c]] for c in cols]) + z[cols]
        held = self._est_role           # the estimator's role for this role and readings
        if held is None or held[0] is not role or held[1] != cols:
            measured = tuple(self.labels.index(role.measure[c]) for c in cols)
            held = self._est_role = (role, cols, AgentRole(
                measured=measured, self_weight=role.self_weight, G=role.gain[:, cols]))
        est_role = held[2]
        nbs = []
        for j, (s, need, src) in plan.items():
            x = None if s is None else self.nbrs[src].est[s]
            nb, state = neighbour_input(role.neighbours[j], k, s, x, self.config.max_age, need)
            self.states[state] += 1
            nbs.append(nb)
        prior, post = estimator_step(self.powers, est_role, self.x, nbs, y)
        if self._residuals_in_force():
            self._residuals(k, y if len(cols) == len(role.measure) else None,
                            prior, est_role, plan)
        self._finish(k, post)
        return post

    def _residuals(self, k: int, y, prior, est_role, plan: dict) -> None:
        """The residual tests of step k (:class:`design.residuals.AgentResiduals`): the
        innovation when every reading came, and on each link whose estimate used was the
        on-time one at the tested age, ``A^age xhat^j - prior``."""
        res = self.residuals
        if y is None or any(s != need or src != j for j, (s, need, src) in plan.items()) \
                or any(k - need != res.link_age[j] for j, (_, need, _) in plan.items()
                       if j in res.link_age and need > 0):
            # inputs missing or late, or on time at a delay learned other than the one
            # the thresholds were computed for (an injected delay: a healthy agent's own
            # innovation then left their distribution, a false "sensor bias")
            res.disturb(k)
        innovation = None if y is None else y - prior[list(est_role.measured)]
        disc, ages = {}, res.link_age
        for j, (s, need, src) in plan.items():
            # the on-time estimate, at the age the link's test was computed for (a delay
            # learned otherwise, e.g. after a burst of late messages, is not tested)
            if s is not None and s == need and src == j and k - s == ages.get(j):
                disc[j] = self.nbrs[j].est[s] @ self.powers.transposed(k - s) - prior
        self.residual_levels = res.step(k, innovation, disc)
        for name, level in self.residual_levels.items():
            self._residual_peak[name] = max(level, self._residual_peak.get(name, 0.0))
            if level >= 1 and name not in self._residual_first:
                self._residual_first[name] = (k, level)
        self.residual_alarms += any(v >= 1 for v in self.residual_levels.values())

    def _finish(self, k: int, post) -> None:
        if post is not None:
            self.x = post
        self.step = k
        self.ready_at = None
        for s in [s for s in self.sensor if s <= k]:
            del self.sensor[s]

    # -- status ------------------------------------------------------------------
    def _residual_status(self) -> dict:
        """``residuals``: the largest level of each test since the last status, the step
        and level of each test's first alarm since then, the alarm steps so far, the last
        disturbed step and the epoch of the configuration tested; ``off`` while no tests
        of the configuration in force are run."""
        if not self._ever_tested:
            return {}
        if not self._residuals_in_force():
            return {"residuals": {"off": "the configuration changed",
                                  "alarms": self.residual_alarms}}
        peak, self._residual_peak = self._residual_peak, {}
        first, self._residual_first = self._residual_first, {}
        res = self.residuals
        return {"residuals": {"levels": {k: round(v, 4) for k, v in peak.items()},
                              "first": {k: [s, round(v, 4)] for k, (s, v) in first.items()},
                              "alarms": self.residual_alarms,
                              "disturbed": -1 if res.disturbed_at is None else res.disturbed_at,
                              "settle": res.warmup + res.window, "epoch": res.epoch}}

    def _started_gains(self) -> str:
        """:func:`design.gains.gain_digest` of the gain it started with (once)."""
        if self._gains_digest is None:
            self._gains_digest = gain_digest(self.role.gain)
        return self._gains_digest

    def status(self) -> dict:
        """The status fields of this agent (see docs/runtime.md)."""
        role = self.role
        return {
            "agent": self.id,
            "step": self.step,
            "active": role is not None,
            "epoch": self.epoch,
            "measure": list(role.measure) if role else [],
            "neighbours": dict(role.neighbours) if role else {},
            "delays": self.learned_delays(),
            "drops": self.drops,
            "late": self.late,
            "inputs": dict(self.states),
            "ages": self.neighbour_ages(),
            "fenced": self.fenced,
            "roster_epoch": self.roster_epoch,
            "impaired": self.impaired,
            "sensor": {"labels": list(self.wanted_labels()), "last_step": self.sensor_last,
                       "missed": self.sensor_missed, "future": self.sensor_future},
            "implausible": dict(self.implausible),
            **self._residual_status(),
            # the start handshake's: once the clock runs, N ids in every status (read by
            # every monitor) would serve nobody
            **({"heard": sorted(self.heard)} if self.step < 0 else {}),
            # what it was started with, for the world and the monitor to check against
            # theirs (a hand-started process with another --seed or --gains): the seed
            # for the start, the gain while it runs the role it started with (a monitor
            # may join as the clock starts)
            **({"seed": self.config.seed}
               if self.step < 0 and 0 <= self.config.seed < 2**63 else {}),
            **({"gains": self._started_gains()} if role and self.epoch == 0 else {}),
            "links": {str(src): {k: v for k, v in vars(p).items() if v not in (None, 0, 0.0, False)}
                      for (src, dst), p in self.impair.links().items() if not p.is_identity},
            "ctl": {"accepted": self.ctl_accepted, "rejected": self.ctl_rejected,
                    "last_error": self.ctl_last_error,
                    "pending": self.pending.epoch if self.pending else 0},
        }


def initial_role(scenario, gains, agent: int):
    """The scenario's role of agent ``agent`` (1-based), or None for a standby agent."""
    i = agent - 1
    if i >= scenario.N:
        return None
    return Role(epoch=0, activate_at=0, measure=tuple(scenario.agent_labels(i)),
                neighbours={j + 1: float(scenario.W[i, j]) for j in scenario.neighbours[i]},
                self_weight=float(scenario.W[i, i]), gain=np.asarray(gains[i], dtype=float))


def agent_config(scenario, agent: int, gains, seed: int, delays, deadline_s: float,
                 impair_seed: int = 0, drop: float = 0.0, max_age=None,
                 residuals: bool = False, lie=None, sensor_faults=()) -> AgentConfig:
    """The :class:`AgentConfig` of agent ``agent`` (1-based) of ``scenario``.

    The receiver-side delay of link b -> ``agent`` is
    :func:`design.roster.link_delay_table` of ``delays`` (0-based (N, N), steps): the
    scenario's delay on its links, the largest delay on every other pair (standby
    agents included), so that a role change keeps the delays the simulator and the
    monitor assume. ``max_age`` defaults to ``hold_limit(delays.max())``.
    ``residuals``: run the residual tests of the initial configuration
    (:func:`residual_tests_for`) when the agent has a role in it, and those the
    assignments carry.
    """
    from design.estimator import hold_limit
    from design.roster import link_delay_table

    M = scenario.N + scenario.standby
    if not 1 <= agent <= M:
        raise ValueError(f"--id: no agent {agent} in scenario {scenario.name!r} "
                         f"(agents 1..{scenario.N}, standby {scenario.N + 1}..{M})")
    i = agent - 1
    table = link_delay_table(scenario, delays)
    link_delays = {b + 1: int(table[i, b]) for b in range(M) if b != i and table[i, b] > 0}
    top = int(np.max(delays)) if np.size(delays) else 0
    return AgentConfig(
        agent=agent, A=scenario.A, labels=scenario.labels, agents=tuple(range(1, M + 1)),
        seed=int(seed), measurement_noise=scenario.measurement_noise,
        process_noise=scenario.process_noise,
        role=initial_role(scenario, gains, agent) if gains is not None or i >= scenario.N
        else None,
        link_delays=link_delays, deadline_s=float(deadline_s), impair_seed=impair_seed,
        drop=float(drop), max_age=hold_limit(top) if max_age is None else int(max_age),
        residuals=residual_tests_for(scenario, gains, delays, i)
        if residuals and gains is not None and i < scenario.N else None,
        test_residuals=bool(residuals), lie=lie,
        sensor_faults=tuple(sensor_faults))


def residual_tests_for(scenario, gains, delays, row: int):
    """:class:`design.residuals.AgentResiduals` of agent row ``row`` of the initial
    configuration, or None when its loop is above
    :data:`design.residuals.AGENT_MAX_ORDER` or not stable (no steady covariance to test
    against)."""
    from design.residuals import AgentResiduals, configuration_tests

    tests = configuration_tests(scenario, gains, delays).get(row + 1)
    return AgentResiduals(tests) if tests is not None else None
