"""The monitor's failure detector: what it knows of each agent, and the verdicts it supports.

:class:`FailureDetector` takes in the agents' liveliness events and statuses (and the
monitor's own observation of their estimates) with the time they arrived, and says at
any time which agents of the configuration in force have failed and why. It decides
nothing else: the controller (:class:`agent.monitor.core.MonitorCore`) answers its
verdicts with a reassignment, keeps the configuration in force up to date on it
(:attr:`FailureDetector.roster`) and marks the agents it convicted
(:attr:`FailureDetector.failed`).

Verdicts (one per cause, each with its evidence):

- ``crash``: the liveliness token of an agent in the configuration was deleted, with its
  process: it was heard just before (an exit closes the links at once), or else (the token
  went by its lease: the agent, or only its link to this monitor, fell silent) none of its
  listeners holds an estimate of it newer than the step the token went at once one would
  have reached them (:meth:`FailureDetector._token_went_with_its_process`). A listener
  holding a newer one shows the agent alive behind a lapsed link: that is no crash, and no
  hang either while its estimates carry steps past its last status;
- ``hang``: its token is alive but its loop does not advance: its reported step has not
  moved for the hang timeout while the other agents' steps moved on by more than
  ``hang_lag_steps`` (a whole run that is slow, e.g. a loaded machine, convicts nobody).
  The timeout is ``hang_timeout_s`` on a machine that keeps the statuses' pace, and grows
  with the pace observed (:class:`StatusPace`, phi accrual over every agent's status
  intervals) up to ``hang_timeout_max_s``: a loaded machine whose loops stall now and then
  delays detection instead of convicting healthy agents. An agent waiting for the run's
  clock (step -1) is behind only from the first status past it: the wait before counts not;
- ``sensor``: its status says the readings of its nodes have not arrived for
  ``sensor_lag_steps`` steps while the others advance;
- ``silent``: it looks alive and advances, but every agent that listens to it reports
  that the freshest estimate it holds from it is older than the link's delay plus
  :meth:`FailureDetector.silent_bound` steps (``silent_steps``, then the hang timeout in
  steps: its estimates no longer reach the network: a partition, a broken publisher); a
  single listener's report stands only when the monitor's own observation (the estimates
  it hears) or that listener's impaired link agrees. The rule reads the listeners' ages
  alone, with no clock of the monitor's own: a monitor that takes the seat in the middle
  of a silence (restarted, or handed the seat back) convicts on the evidence as it stands,
  instead of timing the silence again from when it started watching.

(The ``delay`` verdict, learned delays that make the loop unstable, is the controller's:
it needs the exact closed loop.)

The detector guards against the monitor's own pauses: when two observations
(:meth:`FailureDetector.observe`) are more than ``pause_guard_s`` apart, it suspends the
verdicts that read clocks and restarts every progress clock (it has no fresh evidence), as
Cassandra's failure detector does; a deleted token is evidence of its own and still
convicts (:meth:`FailureDetector.crash_verdicts`). Evidence that does not hold (a status
on another agent's key, an epoch or a step out of bounds, a second token for one id, one
listener's unconfirmed word) is refused and counted (:meth:`FailureDetector.reject`).

Examples
--------
>>> from design.roster import Roster
>>> from design.scenario import load_scenario
>>> from agent.monitor.core import MonitorConfig
>>> s = load_scenario("paper-14")
>>> d = FailureDetector(MonitorConfig(), Roster.initial(s, s.delays))
>>> d.on_liveliness("agent", 1, True, now=0.0)
True
>>> d.observe(0.0); d.on_status({"agent": 1, "step": 5, "epoch": 0}, now=0.1) is not None
True
>>> d.last_step_reported, d.verdicts(0.2)
(5, [])
"""

from __future__ import annotations

import functools
import math
import statistics
from dataclasses import dataclass, field

import numpy as np

__all__ = ["FailureDetector", "StatusPace", "Verdict", "AgentEvidence", "CRASH_SETTLE_S",
           "CRASH_HEARD_LEASE", "CRASH_CONFIRM_STEPS"]


#: While the monitor's own pause suspends its verdicts, a deleted token is believed once
#: it has been gone this long (seconds) without the other tokens going with it.
CRASH_SETTLE_S = 0.1


#: A token that went while its agent was heard (a status or an estimate) within this
#: fraction of the link lease (``MonitorConfig.lease_s``) went with its process: a
#: process that exits closes its links at once, while a link that lapses goes a lease
#: after the last thing heard over it. (At 0.5 s of a 1 s lease, ``up --kill``'s agent,
#: silent for the 0.3 s it flushes before its SIGKILL and up to a status period before
#: that, was judged by its listeners under load: convicted 40 steps late at 15-step
#: delays.)
CRASH_HEARD_LEASE = 0.8

#: A token that went by its lease is believed once no listener of its agent holds an
#: estimate of it this many steps newer than the run's step when it went, when one would
#: have reached them (this many steps more for lateness); one listener holding a newer
#: one shows the agent alive (the link to the monitor lapsed, not the agent).
CRASH_CONFIRM_STEPS = 5


#: Other sessions remembered as holding a token for one agent id (more are refused alike).
MAX_CLAIMS = 16


@functools.lru_cache(maxsize=8)
def _phi_quantile(phi: float) -> float:
    """The standard normal quantile exceeded with probability ``10^-phi`` (asked at every
    tick: computed once per phi)."""
    return statistics.NormalDist().inv_cdf(1.0 - 10.0 ** -phi)


class StatusPace:
    """The pace of the agents' statuses, pooled over the network, and the hang timeout it
    allows. Two estimates of how long a healthy loop's statuses may pause, the larger
    taken:

    - a phi accrual detector's (Hayashibara et al.; Pekko's ``PhiAccrualFailureDetector``):
      an exponentially weighted mean and variance of the gaps between two statuses of one
      agent, and the gap exceeded with probability ``10^-phi`` were gaps normal;
    - ``margin`` times the longest gap a healthy agent showed lately (a maximum that
      halves every ``half_life_s``): loaded machines stall loops in bursts, a tail no
      normal fit follows.

    Clamped to ``[floor, ceiling]``: on a machine that keeps the pace the timeout is the
    floor. Gaps of agents convicted meanwhile are not given (the caller's part).

    >>> pace = StatusPace(period=0.2)
    >>> round(pace.timeout(8.0, floor=1.0, ceiling=5.0, now=0.0), 2)
    1.0
    >>> for k, gap in enumerate([0.2] * 50 + [0.9, 0.2, 1.1, 0.2, 0.2, 0.7] * 10):
    ...     pace.add(gap, now=0.1 * k)
    >>> round(pace.timeout(8.0, floor=1.0, ceiling=5.0, now=11.0), 2)   # 2 x 1.1 s, decayed
    2.18
    """

    def __init__(self, period: float, alpha: float = 0.01, margin: float = 2.0,
                 half_life_s: float = 30.0):
        self.alpha, self.margin, self.half_life_s = alpha, margin, half_life_s
        self.mean = float(period)
        self.var = (float(period) / 4) ** 2       # a start a little scattered
        self.peak, self.peak_at = float(period), 0.0

    def add(self, gap: float, now: float) -> None:
        d = gap - self.mean
        self.mean += self.alpha * d
        self.var = (1 - self.alpha) * (self.var + self.alpha * d * d)
        if gap >= self._peak(now):
            self.peak, self.peak_at = gap, now

    def _peak(self, now: float) -> float:
        return self.peak * 0.5 ** (max(0.0, now - self.peak_at) / self.half_life_s)

    def timeout(self, phi: float, floor: float, ceiling: float, now: float) -> float:
        z = _phi_quantile(phi)
        wanted = max(self.mean + z * math.sqrt(self.var), self.margin * self._peak(now))
        return min(ceiling, max(floor, wanted))


@dataclass(frozen=True)
class Verdict:
    agent: int
    # crash, hang, sensor, silent; the controller's: unconfirmed, delay, inconsistent estimates
    cause: str
    evidence: str
    at: float            # monitor time of the verdict
    step: int            # the run's step then: the newest reported, extrapolated to ``at``


@dataclass
class AgentEvidence:
    """What the detector knows of one agent."""

    alive: bool = False
    step: int = -1
    epoch: int = 0
    pending: int = 0
    active: bool = False
    progress_at: float | None = None     # when its step last moved (reset by a pause)
    step_at: float | None = None         # when its step last moved, never reset
    status_at: float | None = None       # when its last status arrived
    gone_at: float | None = None         # when its token was last deleted
    gone_step: int = -1                  # the run's step then (extrapolated)
    gone_in_lapse: bool = False          # half or more of the configuration's went with it
    lapse_seen: bool = False             # a listener heard it since its token went
    unheard_step: int = -2               # its statuses stopped here, its listeners heard on
    others_at_progress: int = -1         # the others' newest step then
    healthy_since: float | None = None   # convicted, on probation: healthy since then
    slow_since: float | None = None      # on probation: a passing slowness since then
    estimate_at: float | None = None     # when the monitor last heard one of its estimates
    sensor_last: int = -1
    status: dict = field(default_factory=dict)
    token: str | None = None             # the session whose token is the agent's
    claims: set = field(default_factory=set)    # other sessions holding a token for its id
    contested_at: float | None = None    # its token went while another session held one


class FailureDetector:
    """The evidence about every agent of a run, and the verdicts it supports.

    ``config``: the thresholds (:class:`agent.monitor.core.MonitorConfig`); ``roster``: the
    configuration in force (:class:`design.roster.Roster`), kept up to date by the
    controller; ``agent_ids``: every agent of the run (default: the roster's scenario's
    agents and standbys); ``events``: the list the detector appends its log lines to (the
    controller's). Times are seconds on the caller's clock.
    """

    def __init__(self, config, roster, agent_ids=None, events: list | None = None):
        self.config = config
        self.roster = roster
        self.events = [] if events is None else events
        if agent_ids is None:
            s = roster.scenario
            agent_ids = range(1, s.N + s.standby + 1)
        self.agents: dict = {int(a): AgentEvidence() for a in agent_ids}
        self.failed: set = set()          # ids convicted and not healthy again since
        self.convicted_at: dict = {}      # id -> when it was last convicted
        self.rejected: dict = {}          # reason -> evidence refused (see reject)
        self.anomalies: list = []         # the first refusal of each reason and agent
        self._rejected_seen: set = set()
        self.pace = StatusPace(config.status_s)   # the statuses' pace: the hang timeout
        self._hang_said = config.hang_timeout_s   # the hang timeout last logged
        self._last_tick: float | None = None      # the last observation
        self._started = None                      # the first one
        self._suspended_until = -math.inf
        self._lapsed_until = -math.inf    # most tokens went at once: links lapsed
        self._watching_since = -math.inf  # the last fresh start (a pause, the world back)
        self._clock = (-1, 0.0)           # (newest step reported, when)
        self.world_seen = False
        self.world_gone_at: float | None = None   # the world's token went
        self._world_gone_step = -1                 # the newest step reported then
        self._stepped_since_world: set = set()     # agents reporting a step past it
        self.world_end: int | None = None          # its last step, once its end is heard
        self._view = None                          # see roster_view

    def observe(self, now: float) -> None:
        """The controller's clock ticks at ``now``: a gap since the last observation longer
        than ``pause_guard_s`` was the monitor's own pause (verdicts suspended until
        ``hang_timeout_s`` of fresh evidence); a hang timeout that moved is logged."""
        cfg = self.config
        if self._last_tick is not None and now - self._last_tick > cfg.pause_guard_s:
            self.fresh_evidence(now)
            self.events.append(f"monitor paused {now - self._last_tick:.2f} s: verdicts "
                               f"suspended for {cfg.hang_timeout_s:g} s")
        self._last_tick = now
        if self._started is None:
            self._started = now
        hang_s = self.hang_timeout(now)
        if abs(hang_s - self._hang_said) >= 0.25 * cfg.hang_timeout_s:
            self._hang_said = hang_s
            self.events.append(
                f"hang timeout {hang_s:.2f} s: statuses come every {self.pace.mean:.2f} s "
                f"+- {math.sqrt(self.pace.var):.2f} s (floor {cfg.hang_timeout_s:g}, "
                f"ceiling {cfg.hang_timeout_max_s:g})")

    def suspended(self, now: float) -> bool:
        """True while the verdicts that read clocks wait for fresh evidence."""
        return now < self._suspended_until

    def on_liveliness(self, role: str, agent, alive: bool, now: float,
                      session: str | None = None) -> bool | None:
        """A liveliness token came or went; for an agent of the run, return whether its own
        token is alive after it (None when the event changed nothing of it).

        With ``session`` (the zid in the token's key), the first session seen holding agent
        i's token is agent i's; a token of another session for the same id is refused
        (``token``) and changes nothing. When the agent's own token goes while another
        session still holds one for its id, the tokens no longer tell (zenoh resolves a
        relayed token's end by an id, and two tokens for one agent id have been seen to
        end the wrong one): the agent is then judged by the monitor's own observation,
        convicted ``crash`` once no estimate of it came for ``silent_steps`` steps (a dead
        agent cannot be hidden behind a token declared in its name, and an impostor
        leaving cannot convict a live agent)."""
        if role == "world":
            self._on_world(bool(alive), now)
            return None
        if role != "agent":
            return None
        a = self.evidence(agent)
        if a is None:
            return None
        if session is not None:
            alive = self._token(a, int(agent), str(session), bool(alive), now)
            if alive is None:
                return None
        if a.alive and not alive:
            a.gone_at, a.gone_step, a.lapse_seen = now, self.current_step(now), False
            a.gone_in_lapse = False
        a.alive = bool(alive)
        if not a.alive:
            self._mark_lapse(now)
        if alive and a.progress_at is None:
            a.progress_at = now
        return a.alive

    def _mark_lapse(self, now: float) -> None:
        """Half or more of the configuration's tokens gone (each within a lease of now):
        this monitor's own links lapsed, and every token gone then is marked so, for good
        (:meth:`_token_went_with_its_process`). Counted when the tokens go, not when a
        verdict is weighed: the links come back each in its own time, and the one that
        came back last, alone gone by then, was convicted ``crash`` 0.1 s after a 5 s
        SIGSTOP of the monitor (CI)."""
        lease = self.config.lease_s
        gone = [self.agents[j] for j in self.roster.ids if j in self.agents
                and not self.agents[j].alive and self.agents[j].gone_at is not None
                and now - self.agents[j].gone_at <= lease]
        if gone and 2 * len(gone) >= len(self.roster.ids):
            for a in gone:
                a.gone_in_lapse = True

    def _token(self, a: AgentEvidence, agent: int, session: str, alive: bool,
               now: float) -> bool | None:
        """Whether agent ``agent``'s own token is alive after this event, or None when the
        event is about another session's token for its id."""
        if alive:
            if a.token == session or (a.token is None and not a.claims):
                a.token, a.contested_at = session, None
                return True
            if len(a.claims) < MAX_CLAIMS:      # a flood of made-up sessions stays bounded
                a.claims.add(session)
            self.reject("token", agent, f"a second liveliness token for agent {agent} "
                        f"(session {session}; the agent's is {a.token}): another process "
                        "claims its id, and its token is not taken for the agent's")
            return None
        if session == a.token:
            a.token = None
            if not a.claims:
                return False
            a.contested_at = now
            self.events.append(f"agent {agent}'s liveliness token went while another process "
                               f"holds one for its id: judged by its estimates from now on")
            return None
        a.claims.discard(session)
        if a.token is None and not a.claims and a.contested_at is not None:
            a.contested_at = None               # every token of its id is gone now
            return False
        return None

    def _on_world(self, alive: bool, now: float, how: str = "") -> None:
        """The world came or went. Without it the agents stop stepping: no verdict is made
        while it is gone (whether it ended, or was paused or cut off: the agents wait for
        it); when it comes back, verdicts wait for fresh evidence. It is back when its
        token is, or when most agents of the configuration report steps ``hang_lag_steps``
        past the newest reported when it went (they step on its readings only: its
        token's return was missed, as a monitor whose links lapsed may miss it)."""
        if alive:
            if self.world_gone_at is not None:
                self.fresh_evidence(now)
                self.events.append(f"the world is back{how}: verdicts resume after "
                                   f"{self.config.hang_timeout_s:g} s of fresh evidence")
            self.world_seen, self.world_gone_at = True, None
        elif self.world_seen and self.world_gone_at is None:
            self.world_gone_at = now
            self._world_gone_step = self.last_step_reported
            self._stepped_since_world = set()
            if self.world_end is None:
                self.events.append(
                    f"the world went silent after step {self.last_step_reported} without "
                    f"its end (paused or cut off, or this monitor was): no verdicts while "
                    f"it is gone; waiting up to {self.config.world_silent_s:g} s")
            else:
                self.events.append(f"the world left after step {self.world_end}: no "
                                   "verdicts while it is gone")

    def on_world_end(self, step: int) -> None:
        """The world's end message: the run is over after ``step``."""
        if self.world_end is None:
            self.world_end = int(step)
            self.events.append(f"the world ended after step {self.world_end}")

    def run_ended(self, now: float) -> bool:
        """True once the world has ended (its end heard) and its token gone, and the agents
        have left too (no agent token is alive) or ``world_gone_s`` has passed; or once a
        world whose token went *without* its end has stayed silent ``world_silent_s``.

        A monitor that was itself paused or cut off sees every token go at once, the
        world's included, but heard no end: it waits for the network to come back instead
        of leaving a live run.
        """
        if self.world_gone_at is None:
            return False
        gone = now - self.world_gone_at
        if self.world_end is None:
            return gone >= self.config.world_silent_s
        return not any(a.alive for a in self.agents.values()) or gone >= self.config.world_gone_s

    def _clock_started(self, now: float, first: int) -> None:
        """The first status past step -1: the run's clock started. Every other agent
        still waiting for it (step -1, however long it waited before) has been behind only
        since now: its hang clock starts here, not when it came up."""
        for i, a in self.agents.items():
            if i != first and a.step < 0 and a.progress_at is not None:
                a.progress_at = now
                a.others_at_progress = -1

    def fresh_evidence(self, now: float) -> None:
        """Forget the progress clocks: verdicts wait ``hang_timeout_s`` of new evidence."""
        self._suspended_until = now + self.config.hang_timeout_s
        self._watching_since = now
        for a in self.agents.values():
            a.progress_at = now
            a.others_at_progress = self.newest_step()

    def reject(self, reason: str, agent, detail: str) -> None:
        """Evidence refused (counted in :attr:`rejected` by reason; the first of each
        reason and agent is an event and an entry of :attr:`anomalies`)."""
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        key = (reason, agent)
        if key not in self._rejected_seen and len(self._rejected_seen) < 1024:
            self._rejected_seen.add(key)
            self.anomalies.append({"reason": reason, "agent": agent, "detail": detail})
            self.events.append(f"evidence refused ({reason}): {detail}")

    def on_status(self, msg: dict, now: float, sender: int | None = None,
                  epoch_ceiling: float = math.inf):
        """An agent's status; ``sender``: the agent id of the key it came on (the shell
        parses it). A status whose payload names another agent than its key, carries an
        epoch above ``epoch_ceiling`` (the controller's bound), or a step too far ahead of
        the others', is refused (:meth:`reject`). Returns the agent's evidence it updated,
        or None."""
        if sender is not None and msg.get("agent") != sender:
            self.reject("sender", sender, f"a status on agent {sender}'s key names agent "
                        f"{msg.get('agent')}")
            return None
        a = self.evidence(msg.get("agent"))
        if a is None:
            return None
        if int(msg.get("epoch", 0)) > epoch_ceiling:
            self.reject("epoch", msg["agent"], f"agent {msg['agent']}'s status carries epoch "
                        f"{msg.get('epoch')}, above the highest epoch seen plus "
                        f"{self.config.epoch_jump_max} ({epoch_ceiling})")
            return None
        step = int(msg.get("step", -1))
        # no bound while this monitor has no fresh view: it was paused (its backlog holds
        # statuses from before, which would anchor the bound in the past) or suspends its
        # verdicts after a pause or the world's return
        fresh = self._last_tick is not None and now - self._last_tick <= \
            self.config.pause_guard_s and now >= self._suspended_until
        ceiling = self.step_ceiling(now, exclude=msg["agent"]) if fresh else None
        if ceiling is not None and step > ceiling:
            self.reject("step", msg["agent"], f"agent {msg['agent']}'s status reports step "
                        f"{step}, more than {self.config.step_ahead_s:g} s ahead of the other "
                        f"agents (step {ceiling} at most)")
            return None
        if self.world_gone_at is not None and self.world_end is None \
                and step > self._world_gone_step + self.config.hang_lag_steps \
                and msg["agent"] in self.roster.ids:
            self._stepped_since_world.add(msg["agent"])
            if 2 * len(self._stepped_since_world) > len(self.roster.ids):
                self._on_world(True, now, how=" (agents "
                               f"{sorted(self._stepped_since_world)} step past "
                               f"{self._world_gone_step}; its token was not seen back)")
        if step >= 0 > self._clock[0]:
            self._clock_started(now, msg["agent"])
        if step != a.step or a.step_at is None:
            a.step_at = now
        if step != a.step or a.progress_at is None:
            a.progress_at = now
            a.others_at_progress = self.newest_step(exclude=msg["agent"])
        a.step = step
        if a.status_at is not None and a.status_at >= self._watching_since \
                and self._last_tick is not None \
                and now - self._last_tick < self.config.pause_guard_s \
                and self.convicted_at.get(msg["agent"], -math.inf) < a.status_at \
                and msg["agent"] not in self.failed \
                and not (a.gone_at is not None and a.gone_at >= a.status_at):
            # a healthy gap between two of its statuses: one this monitor watched whole
            # (not across its own pause, nor the world's absence: after either, the
            # backlog's first status of each agent closes a gap as long as the pause), nor
            # across the agent's own conviction, nor of an agent on probation (convicted
            # and not rejoined: its stalls are a fault's, and a stopped standby's gaps
            # raised the timeout to 3.65 s, so that a later 1.5 s stop went unconvicted),
            # nor across the loss of its token (its lease lapsed: the process was stopped
            # or cut off; a standby stopped 3 s drove the timeout to its 5 s ceiling)
            self.pace.add(now - a.status_at, now)
        a.status_at = now
        if step >= self._clock[0]:
            self._clock = (step, now)
        a.epoch = int(msg.get("epoch", 0))
        a.active = bool(msg.get("active", False))
        ctl = msg.get("ctl") if isinstance(msg.get("ctl"), dict) else {}
        a.pending = int(ctl.get("pending", 0) or 0)
        sensor = msg.get("sensor") if isinstance(msg.get("sensor"), dict) else {}
        last = sensor.get("last_step", -1)
        a.sensor_last = int(last) if isinstance(last, int) else -1
        a.status = msg
        return a

    def evidence(self, agent):
        """The evidence about ``agent`` (an id, as sent), or None for an id not of the run."""
        try:
            agent = int(agent)
        except (TypeError, ValueError):
            return None
        return self.agents.get(agent)

    def current_step(self, now: float) -> int:
        """The newest step reported, extrapolated to ``now`` at the run's step period."""
        step, t = self._clock
        if step < 0:
            return step
        return step + max(0, int((now - t) / self.config.step_s))

    def step_ceiling(self, now: float, exclude=None) -> int | None:
        """The highest step a status may report now: the most advanced other agent's step
        (``exclude``: the sender), extrapolated at ``step_s`` from when it was reached (not
        from a pause's fresh start: after one the others are ahead by the pause), plus
        ``step_ahead_s``; None until another agent has reported. Taking the others' word
        and not the sender's keeps one agent from ratcheting the clock up."""
        best = None
        for i, a in self.agents.items():
            if i != exclude and a.step >= 0 and a.step_at is not None:
                at = a.step + max(0.0, now - a.step_at) / self.config.step_s
                best = at if best is None or at > best else best
        if best is None:
            return None
        return int(best + self.config.step_ahead_s / self.config.step_s)

    @property
    def last_step_reported(self) -> int:
        """The newest step any agent reported (-1 before the first)."""
        return self._clock[0]

    def lag_steps(self, agent: int) -> float:
        """How far ``agent`` was behind the most advanced other agent when it reached its
        step: the others' steps taken back (or on) to that moment at ``step_s``, so two
        statuses sent a status period apart are compared at one time. Others whose step
        moved more than half the hang timeout away from that moment (hung, or long
        silent) are not taken; 0 when none is left."""
        st = self.agents[agent]
        if st.step_at is None:
            return math.inf
        best = None
        for i, a in self.agents.items():
            if i != agent and a.alive and a.step >= 0 and a.step_at is not None \
                    and abs(st.step_at - a.step_at) <= self.config.hang_timeout_s / 2:
                at = a.step + (st.step_at - a.step_at) / self.config.step_s
                best = at if best is None or at > best else best
        return 0.0 if best is None else max(0.0, best - st.step)

    def newest_step(self, exclude=None) -> int:
        steps = [a.step for i, a in self.agents.items() if i != exclude and a.alive]
        return max(steps, default=-1)

    def hang_timeout(self, now: float | None = None) -> float:
        """The hang timeout at ``now`` (default: the last tick): ``hang_timeout_s``, grown
        with the statuses' observed pace (:class:`StatusPace`) up to
        ``hang_timeout_max_s``."""
        cfg = self.config
        if now is None:
            now = self._last_tick if self._last_tick is not None else 0.0
        return self.pace.timeout(cfg.hang_phi, cfg.hang_timeout_s, cfg.hang_timeout_max_s,
                                 now)

    def crash_verdicts(self, now: float) -> list:
        """The ``crash`` verdicts that hold while verdicts are suspended: a token deleted
        :data:`CRASH_SETTLE_S` ago or more, while fewer than half of the configuration's
        tokens are gone (when this monitor was paused or cut off, its links lapse and every
        token seems to go at once: that is no crash). Once that was seen, none until the
        suspension is over: the links come back each in its own time, and a token whose
        link came back last was convicted ``crash`` 0.1 s after the others' returned (a
        healthy agent replaced after a 1 s SIGSTOP of the monitor). A loop only starved
        of CPU keeps its links (zenoh's own threads answer the keep-alives), so a crash
        then is still answered at once."""
        if now < self._lapsed_until:
            return []
        gone = [i for i in self.roster.ids if not self.agents[i].alive]
        if 2 * len(gone) >= len(self.roster.ids):
            self._lapsed_until = self._suspended_until
            return []
        return [Verdict(i, "crash", "liveliness token deleted", now, self.current_step(now))
                for i in gone if i not in self.failed
                and self.agents[i].progress_at is not None
                and self.agents[i].gone_at is not None
                and now - self.agents[i].gone_at >= CRASH_SETTLE_S
                and self._token_went_with_its_process(i, now)]

    def _token_went_with_its_process(self, agent: int, now: float) -> bool:
        """Whether ``agent``'s deleted token shows its process gone, and not only its link
        to this monitor (a link lapses when either end is starved of CPU, paused or cut
        off past the lease; a lapsed link was convicted ``crash`` while the agent went on
        computing its role, heard by its listeners).

        - Heard (a status, an estimate) within :data:`CRASH_HEARD_LEASE` of the lease
          (``config.lease_s``) before the token went, while fewer than half of the
          configuration's tokens are gone, and were not when it went: it went with its
          process (an exit closes the links at once): yes, at once. (Half or more gone
          is this monitor's own links lapsing: a stall of its own, its statuses queued and
          read after it, convicted three healthy agents in a run beside two busy loops.)
        - Otherwise the token went by its lease: the listeners of the configuration in
          force decide. One holding an estimate of it stamped more than
          :data:`CRASH_CONFIRM_STEPS` past the step the token went at: no (it is alive,
          the lapse is refused as evidence: :meth:`reject` ``lapse``). Every live
          listener holding nothing newer when one would have reached it (that step, the
          link's delay and :data:`CRASH_CONFIRM_STEPS` more for lateness later): yes. No
          live listener: yes. Undecided (a listener's status not yet that far) for the
          hang timeout: yes."""
        a = self.agents[agent]
        if a.gone_at is None:           # never seen alive by this monitor
            return True
        heard = max((t for t in (a.status_at, a.estimate_at) if t is not None), default=None)
        gone = sum(not self.agents[j].alive for j in self.roster.ids)
        recent = CRASH_HEARD_LEASE * self.config.lease_s
        if heard is not None and a.gone_at - heard <= recent and not a.gone_in_lapse \
                and 2 * gone < len(self.roster.ids):
            # (half the configuration's tokens or more gone: this monitor's own links
            # lapsed, its loop stalled with statuses queued: those are no recent word)
            return True
        horizon = a.gone_step + CRASH_CONFIRM_STEPS
        heard_by = self._heard_past(agent, horizon)
        if heard_by is not None:
            if not a.lapse_seen:
                a.lapse_seen = True
                self.reject("lapse", agent, f"agent {agent}'s liveliness token went, but "
                            f"agent {heard_by[0]} holds its estimate of step {heard_by[1]} "
                            f"(the token went at step {a.gone_step}): its link to this "
                            "monitor lapsed; not convicted on the token")
            return False
        # a listener not yet at the step where an estimate past the horizon, on time,
        # would have reached it cannot tell
        undecided = any(self.agents[j].status.get("step", -1)
                        < horizon + self._on_time_age(j, agent)
                        for j in self._speaking_listeners(agent))
        return not undecided or now - a.gone_at > self.hang_timeout(now)

    def _advances_unheard(self, agent: int, a: AgentEvidence) -> bool:
        """Whether ``agent``, whose statuses stopped reaching this monitor, still computes:
        a listener holds an estimate of it ``hang_lag_steps`` past the step it last
        reported, and on time (its link to this monitor lapsed, its loop did not; refused
        as evidence of a hang once: :meth:`reject` ``lapse``)."""
        heard_by = self._heard_past(agent, a.step + self.config.hang_lag_steps, on_time=True)
        if heard_by is None:
            return False
        if a.unheard_step == a.step:
            return True
        a.unheard_step = a.step
        self.reject("lapse", agent, f"agent {agent}'s statuses stopped at step {a.step}, but "
                    f"agent {heard_by[0]} holds its estimate of step {heard_by[1]}: its "
                    "link to this monitor lapsed; not convicted of a hang")
        return True

    def _speaks(self, b: AgentEvidence) -> bool:
        """Whether a listener's word counts: its token is up, or its statuses still
        come (within the hang timeout: its token went with this monitor's own links)."""
        now = self._last_tick
        return b.alive or (b.status_at is not None and now is not None
                           and now - b.status_at < self.hang_timeout(now))

    def _heard_past(self, agent: int, step: int, on_time: bool = False):
        """``(listener, stamp)``: a live listener of ``agent`` in the configuration in
        force whose last status says it holds an estimate of ``agent`` stamped after
        ``step`` (so ``agent`` computed past it), and with ``on_time`` one at most
        :data:`CRASH_CONFIRM_STEPS` later than the link's delay (it hears it now), or
        None."""
        for j in self._speaking_listeners(agent):
            st = self.agents[j].status
            mine, age = st.get("step", -1), st.get("ages", {}).get(agent)
            if isinstance(age, int) and not isinstance(age, bool) and 0 <= age \
                    and mine - age > step \
                    and (not on_time or age <= self._on_time_age(j, agent)):
                return j, mine - age
        return None

    def _speaking_listeners(self, agent: int):
        """The listeners of ``agent`` in the configuration in force (its W) not convicted
        whose word counts (:meth:`_speaks`)."""
        return [j for j in self._listeners(agent)
                if j not in self.failed and self._speaks(self.agents[j])]

    def _on_time_age(self, listener: int, agent: int) -> int:
        """The largest age of ``agent``'s freshest estimate that ``listener`` holds when
        it hears it: one step and the link's delay, :data:`CRASH_CONFIRM_STEPS` more for
        lateness."""
        return self._link_delay(listener, agent) + 1 + CRASH_CONFIRM_STEPS

    def verdicts(self, now: float) -> list:
        """Every verdict the evidence supports at ``now`` against the agents of the
        configuration in force not yet convicted (the rules: the module's docstring)."""
        cfg = self.config
        found = []
        newest = self._clock[0]
        # the step of a verdict is the run's step when it is reached: the newest step
        # reported is up to a status period (10 steps) old, and a crash read from a token
        # came out "detected" a step or more before the crash
        at_step = self.current_step(now)
        silent_s = cfg.silent_steps * cfg.step_s
        hang_s = self.hang_timeout(now)
        for i in self.roster.ids:
            if i in self.failed:
                continue
            a = self.agents[i]
            if not a.alive and a.progress_at is not None \
                    and self._token_went_with_its_process(i, now):
                found.append(Verdict(i, "crash", "liveliness token deleted", now, at_step))
            elif a.contested_at is not None and a.token is None and now - max(
                    a.contested_at, a.estimate_at or a.contested_at) > silent_s:
                found.append(Verdict(i, "crash", "its liveliness token went, another process "
                                     "holds one for its id, and no estimate of it for "
                                     f"{cfg.silent_steps} steps", now, at_step))
            elif a.progress_at is None and now - self._started > cfg.hang_timeout_s:
                # a (re)started monitor never saw it: no token, no status, others advance
                found.append(Verdict(i, "crash", "no liveliness token and no status since "
                                     "the monitor started", now, at_step))
            elif (a.progress_at is not None and now - a.progress_at > hang_s
                  and newest - max(a.step, a.others_at_progress) > cfg.hang_lag_steps
                  and not self._advances_unheard(i, a)):
                # stuck: a quiet sensor if its loop still reports (statuses arrive) and its
                # last reading is behind; otherwise its loop is hung
                talking = a.status_at is not None and now - a.status_at < hang_s / 2
                if talking and a.sensor_last >= 0 and newest - a.sensor_last > cfg.sensor_lag_steps:
                    found.append(Verdict(
                        i, "sensor", f"no reading since step {a.sensor_last} while the others "
                        f"reached step {newest}; its loop still reports", now, at_step))
                else:
                    found.append(Verdict(
                        i, "hang", f"step {a.step} for {now - a.progress_at:.2f} s while the "
                        f"others reached step {newest}"
                        + ("" if talking else "; no status either")
                        + (f" (hang timeout {hang_s:.2f} s at the statuses' pace)"
                           if hang_s > cfg.hang_timeout_s else ""), now, at_step))
            else:
                ages = self._listener_ages(i)
                if ages and min(age - self._link_delay(j, i) for j, age in ages.items()) \
                        > self.silent_bound() and self._hearsay_holds(i, ages, now):
                    found.append(Verdict(
                        i, "silent", "its listeners hold nothing fresher than "
                        + ", ".join(f"{age} steps (agent {r})" for r, age in sorted(ages.items())),
                        now, at_step))
        return found

    def silent_bound(self) -> int:
        """Steps past a link's delay that every listener's freshest estimate of an agent
        must be older than to convict it ``silent``: ``silent_steps``, then the hang
        timeout in steps (the silence has lasted that long in the listeners' own steps).

        >>> from design.roster import Roster
        >>> from design.scenario import load_scenario
        >>> from agent.monitor.core import MonitorConfig
        >>> s = load_scenario("paper-14")
        >>> FailureDetector(MonitorConfig(silent_steps=25, hang_timeout_s=1.0, step_s=0.02),
        ...                 Roster.initial(s, s.delays)).silent_bound()
        75
        """
        cfg = self.config
        return cfg.silent_steps + math.ceil(cfg.hang_timeout_s / cfg.step_s - 1e-9)

    def on_estimate_seen(self, agent, now: float) -> None:
        """The monitor's own observation: an estimate of ``agent`` arrived at ``now`` (the
        shell tells it from the key alone, without decoding)."""
        a = self.evidence(agent)
        if a is not None:
            a.estimate_at = now

    def _hearsay_holds(self, agent: int, ages: dict, now: float) -> bool:
        """One listener's word is not enough to convict: a ``silent`` verdict from a single
        listener stands only if the monitor's own observation agrees (it has heard no
        estimate of ``agent`` for ``silent_steps`` steps) or that listener's status shows
        the link from ``agent`` impaired. Otherwise its hearsay is discounted (an
        anomaly: :meth:`reject` ``hearsay``)."""
        if len(ages) >= 2:
            return True
        (j,) = ages
        links = self.agents[j].status.get("links")
        if isinstance(links, dict) and str(agent) in links:
            return True
        seen = self.agents[agent].estimate_at
        window = self.config.silent_steps * self.config.step_s
        if seen is None or now - seen > window:
            return True
        self.reject("hearsay", j, f"agent {j} reports agent {agent} silent ({ages[j]} steps) "
                    f"but the monitor heard agent {agent}'s estimates {now - seen:.2f} s ago "
                    "and no impaired link: not convicted on one listener's word")
        return False

    def roster_view(self) -> tuple:
        """``(roster, {id: row}, W > 0, delays, {id: its listeners})`` of the configuration
        in force, as Python lists and tuples (the verdicts read them for every agent at
        every tick; a roster is frozen, so they are kept until it is replaced)."""
        view = self._view
        if view is None or view[0] is not self.roster:
            r = self.roster
            listens = (np.asarray(r.scenario.W) > 0).tolist()
            rows = {a: i for i, a in enumerate(r.ids)}
            listeners = {a: tuple(j for j in r.ids if j != a and listens[rows[j]][rows[a]])
                         for a in r.ids}
            view = self._view = (r, rows, listens, np.asarray(r.delays).tolist(), listeners)
        return view

    def _listeners(self, agent: int) -> tuple:
        """The listeners of ``agent`` in the configuration in force (its W), in roster
        order: an agent's degree, read at every tick for every agent (looping over the
        whole roster there made each tick's verdicts O(N^2): 1.1 ms a tick at 32 agents
        under load)."""
        return self.roster_view()[4][agent]

    def _listener_ages(self, agent: int) -> dict:
        """``{listener: age of the freshest estimate of agent it holds}`` (-1: none yet
        counts as not silent; listeners without a status are left out). The listeners are
        those of the configuration in force (its W), not whoever claims to listen."""
        out = {}
        for j in self._listeners(agent):
            st = self.agents[j].status
            if not st:
                continue
            age = st.get("ages", {}).get(agent)
            if age is None or age < 0:
                return {}
            out[j] = age
        return out

    def _link_delay(self, receiver: int, sender: int) -> int:
        """The delay of link ``sender -> receiver`` in force: the configuration's, or the
        one the receiver learned when larger (an estimate that old is on time), by at
        most ``silent_steps`` (a larger one is the ``delay`` verdict's matter, and a
        listener claiming a huge one must not silence the bound)."""
        _, rows, _, D, _ = self.roster_view()
        tau = int(D[rows[receiver]][rows[sender]])
        learned = self.agents[receiver].status.get("delays")
        if isinstance(learned, dict):
            got = learned.get(sender, learned.get(str(sender)))
            if isinstance(got, int) and not isinstance(got, bool):
                tau = max(tau, min(got, tau + self.config.silent_steps))
        return tau

    def learned_delays(self, agent: int) -> dict:
        """``{sender: tau}``: the delays ``agent``'s last status says it learned."""
        return {int(b): int(tau) for b, tau in self.agents[agent].status.get("delays", {}).items()}

    def healthy_standby(self, agent: int, now: float) -> bool:
        """What probation asks of a convicted agent at ``now``: nothing in
        :meth:`standby_break`."""
        return self.standby_break(agent, now) is None

    def standby_break(self, agent: int, now: float) -> tuple | None:
        """What breaks a convicted agent's probation at ``now``, as ``(kind, why)``, or
        None when it is healthy. ``kind`` ``"down"`` (its token is down, it holds a role,
        a status, its own or a neighbour's, shows a link into or out of it cut:
        partitioned, or dropping half or more; a delay is no cut) breaks at once;
        ``"slow"`` (its step did not move within half the hang timeout, or was more than
        the hold window, ``lead_steps``, behind the other agents' when it reached it
        (:meth:`lag_steps`), or its sensor readings, if it wants any, are older than that
        window) breaks once it lasts (the controller's grace)."""
        cfg, st = self.config, self.agents[agent]
        if not st.alive or st.progress_at is None:
            return "down", "no token or no status"
        if st.status.get("active"):
            return "down", "holds a role"
        me = str(agent)
        for b, other in self.agents.items():
            links = other.status.get("links")
            if not isinstance(links, dict):
                continue
            for src, p in links.items():
                cut = isinstance(p, dict) and (p.get("partition") or
                                               float(p.get("drop", 0) or 0) >= 0.5)
                if cut and (b == agent or src == me):    # a delay is no cut
                    return "down", f"link {src}->{b} cut"
        if now - st.progress_at > cfg.hang_timeout_s / 2:
            return "slow", "its step did not move"
        window, lag = max(cfg.lead_steps, 1), self.lag_steps(agent)
        if lag > window:
            return "slow", f"{lag:.0f} steps behind the others"
        sensor = st.status.get("sensor") if isinstance(st.status.get("sensor"), dict) else {}
        if sensor.get("labels") and st.step - st.sensor_last > window:
            return "slow", f"sensor readings {st.step - st.sensor_last} steps old"
        return None
