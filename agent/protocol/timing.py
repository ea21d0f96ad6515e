"""Every period and timeout of the runtime, on one object, with the relations between them.

The runtime's processes (world, agents, monitor, the launcher and the chaos checker) read
their periods and timeouts from one :class:`Timing`; :meth:`Timing.validate` says which
relation between them a combination breaks, so that a flag that would silently change what
the monitor concludes (``--hang-timeout 0.3`` with statuses every 0.2 s turns stuck sensors
into hangs) is refused with the relation named. This is the habit of memberlist's
``DefaultLANConfig`` and PySyncObj's ``SyncObjConf.validate()``. The transport's link lease
(how soon a silent peer's liveliness token is withdrawn) is the transport's own setting:
``broker_free_net.config.DEFAULT_LEASE_MS`` and ``--lease-ms``.

Examples
--------
>>> Timing().problems()
[]
>>> Timing(hang_timeout_s=0.3).problems()[0].split(":")[0]
'hang_timeout_s'
>>> Timing(status_s=0.6).validate()
Traceback (most recent call last):
...
agent.protocol.timing.TimingError: hang_timeout_s: 1 s must exceed 2 x status_s = 1.2 s (the monitor tells a stuck sensor from a hung loop by a status younger than hang_timeout_s / 2)
"""

from __future__ import annotations

import dataclasses
import math
import operator
from dataclasses import dataclass

__all__ = ["Timing", "TimingError", "DEFAULT"]


class TimingError(ValueError):
    """A combination of periods and timeouts breaks a relation; the message names it."""


@dataclass(frozen=True)
class Timing:
    """The runtime's periods and timeouts (seconds unless the name says otherwise).

    Each field's comment is its rationale; :data:`RELATIONS` lists the relations between
    them, :meth:`problems` says which are broken.
    """

    #: An agent's status period: the heartbeat of its loop (a liveliness token proves the
    #: process, a status proves the loop), also what the monitor reads ages and steps from.
    status_s: float = 0.2
    #: Status period before the clock starts (the start handshake: every agent heard).
    prestart_status_s: float = 0.1
    #: No progress of an agent's step for this long while the others advance is a hang;
    #: lower detects faster, and under it a slow agent risks conviction.
    hang_timeout_s: float = 1.0
    #: The hang timeout adapts to the statuses' observed pace (phi accrual over the whole
    #: network's status intervals) but never beyond this: a loaded machine delays
    #: detection by at most this much, and a flood of late statuses cannot blind it.
    hang_timeout_max_s: float = 5.0
    #: Suspicion level of the adaptive timeout: a healthy loop's status gap exceeds it
    #: with probability 10^-hang_phi under the pace observed (Pekko's default is 8).
    hang_phi: float = 8.0
    #: A gap this long between two monitor ticks means the monitor itself was paused: its
    #: progress clocks are stale and hang-like verdicts wait for fresh evidence.
    pause_guard_s: float = 0.5
    #: Re-send unconfirmed assignments this often.
    resend_s: float = 0.25
    #: A replacement that has not confirmed its role by then is treated as failed.
    confirm_timeout_s: float = 3.0
    #: Probation: a convicted agent that came back rejoins the standbys once healthy this
    #: long without a break (statuses moving, sensor fresh, no impaired link).
    rejoin_s: float = 5.0
    #: Epochs heard (statuses, rosters) above the highest seen plus this are refused: a
    #: monitor adds one per reassignment, re-issue or gain upgrade, a few per failure.
    epoch_jump_max: int = 64
    #: A status whose step is further ahead than this (at the run's step period) of every
    #: other agent's, extrapolated, is refused: no honest agent is ahead of the world, and
    #: one agent alone cannot ratchet the monitor's clock (activate_at) up.
    step_ahead_s: float = 2.0
    #: The world must stay gone this long before an agent with nothing left to do leaves.
    world_grace_s: float = 5.0
    #: Once the world has left, an agent exits after this long even if messages keep coming.
    agent_world_gone_s: float = 10.0
    #: Once the world has left, the monitor says the run is over after this long (it must
    #: outlast the agents' own wait, or it would convict agents that are leaving).
    monitor_world_gone_s: float = 15.0
    #: A world whose token went *without* its end message (paused, cut off, crashed) is
    #: waited for this long by the agents, which say so; then they leave with status 1.
    world_silent_s: float = 60.0
    #: ... and by the monitor, which convicts nobody meanwhile (it outlasts the agents).
    monitor_world_silent_s: float = 75.0
    #: A world this far behind its schedule (it was paused or starved) re-bases its clock
    #: and goes on one step a period, instead of publishing every missed step at once.
    world_rebase_s: float = 0.5
    #: A recorder takes a monitor's token that went for its absence once the world's token
    #: stayed in its view this long after it: when its own links lapse (it was paused or
    #: cut off) every token goes from its view within a few tens of ms, the world's too.
    recorder_token_settle_s: float = 0.3
    #: A scripted crash waits this long after its last put so that the transport sends it.
    crash_flush_s: float = 0.3
    #: The world waits this long for every agent's first status before the clock starts.
    start_timeout_s: float = 60.0
    #: The first monitor joins a run once it has gains for every single failure, or after
    #: this long (it says how many it foresees): a world that waits for it (``socmon world
    #: --wait-monitor``) starts its clock then, so that a failure soon after the start is
    #: answered at once instead of waiting seconds for a design on a loaded machine.
    monitor_prepare_s: float = 20.0
    #: A monitor that joins waits up to this long to see the liveliness token of every
    #: agent of the configuration before it judges any: its links to a large run's
    #: processes come up one by one (seconds on a loaded host), and an agent not reached
    #: yet looks like one that never started (16 agents at load 10: 9 healthy agents were
    #: convicted ``crash`` at the start). A restarted monitor with a dead agent in the
    #: configuration starts judging after this long.
    monitor_reach_s: float = 10.0
    #: After its last step the world waits this long for the agents' last estimates.
    end_timeout_s: float = 5.0
    #: After the world ended, ``up`` waits this long for the last estimates of the agents
    #: in force (one may be paused or cut off), then stops the processes.
    up_end_s: float = 5.0
    #: At the end ``up`` asks the monitors, then the other processes, to stop (SIGTERM)
    #: and waits this long for each group to exit before it goes on.
    up_exit_s: float = 5.0

    def problems(self, step_s: float | None = None, lead_steps: int | None = None) -> list:
        """Every broken relation, one line each naming the field (empty when consistent).

        ``step_s`` and ``lead_steps`` are the run's own (the step period and the monitor's
        head start for an assignment, in steps): given, the relation that involves them is
        checked too.
        """
        out = []
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or v <= 0:
                out.append(f"{f.name}: must be a finite number > 0, got {v!r}")
        if out:
            return out
        for a, op, factor, b, why in RELATIONS:
            va, vb = getattr(self, a), factor * getattr(self, b)
            if not HOLDS[op](va, vb):
                times = f"{factor:g} x " if factor != 1 else ""
                out.append(f"{a}: {va:g} s {WORDS[op]} {times}{b} = {vb:g} s ({why})")
        t = self
        if step_s is not None and step_s + t.status_s >= t.confirm_timeout_s:
            # an agent confirms an assignment by the status that shows it pending (sent
            # at once), whatever the head start; one that has not confirmed and shows no
            # new step for confirm_timeout_s is taken for failed, so a healthy agent must
            # show a new step within it
            out.append(f"step_s: the step period ({step_s:g} s, --step-ms or the scenario's "
                       f"runtime.step_ms) plus status_s = {step_s + t.status_s:g} s must stay "
                       f"below confirm_timeout_s = {t.confirm_timeout_s:g} s (an agent that "
                       "has not confirmed its assignment and shows no new step for that "
                       "long is taken for failed): the longest period is "
                       f"{1e3 * (t.confirm_timeout_s - t.status_s):g} ms")
        return out

    def bounds(self, field: str) -> list:
        """Each relation of :data:`RELATIONS` that involves ``field``, seen from it: ``(op,
        bound, other, named, why)``, ``field op bound`` where ``bound`` is ``named`` (e.g.
        ``2 x status_s``) at the other field's value.

        >>> [b[:4] for b in Timing().bounds("start_timeout_s")]
        [('>', 20.0, 'monitor_prepare_s', 'monitor_prepare_s')]
        """
        out = []
        for a, op, factor, b, why in RELATIONS:
            if a == field:
                named = f"{factor:g} x {b}" if factor != 1 else b
                out.append((op, factor * getattr(self, b), b, named, why))
            elif b == field:
                named = f"{a} / {factor:g}" if factor != 1 else a
                out.append((_FLIP[op], getattr(self, a) / factor, a, named, why))
        return out

    def validate(self, step_s: float | None = None, lead_steps: int | None = None) -> "Timing":
        """``self`` if consistent; else :class:`TimingError` naming every broken relation."""
        problems = self.problems(step_s, lead_steps)
        if problems:
            raise TimingError("; ".join(problems))
        return self

    def replace(self, **changes) -> "Timing":
        """A copy with ``changes`` (not validated: call :meth:`validate`)."""
        return dataclasses.replace(self, **changes)


#: The relations between the fields, each ``(a, op, factor, b, why)``: ``a op factor x b``
#: must hold, for the reason ``why``.
RELATIONS = (
    ("hang_timeout_s", ">", 2, "status_s", "the monitor tells a stuck sensor from a hung "
     "loop by a status younger than hang_timeout_s / 2"),
    ("prestart_status_s", "<=", 1, "status_s", "the start handshake is the faster heartbeat"),
    ("hang_timeout_max_s", ">=", 1, "hang_timeout_s", "the adaptive timeout starts there and "
     "only grows"),
    ("pause_guard_s", "<", 1, "hang_timeout_s", "a monitor paused longer than a hang would "
     "convict on stale clocks"),
    ("resend_s", "<", 1, "confirm_timeout_s", "an assignment is re-sent before its addressee "
     "is given up"),
    ("rejoin_s", ">", 1, "hang_timeout_s", "an agent may not rejoin before a verdict about it "
     "could be reached again"),
    ("monitor_prepare_s", "<", 1, "start_timeout_s", "a world waiting for the monitor would "
     "give up first"),
    ("agent_world_gone_s", ">", 1, "world_grace_s", "the hard bound follows the grace period"),
    ("monitor_world_gone_s", ">", 1, "agent_world_gone_s", "the monitor outlasts the agents' "
     "own wait for a world that left"),
    ("world_silent_s", ">", 1, "agent_world_gone_s", "a world that went silent is waited for "
     "longer than one that ended"),
    ("monitor_world_silent_s", ">", 1, "world_silent_s", "the monitor outlasts the agents' "
     "wait for a silent world"),
    ("step_ahead_s", ">", 2, "status_s", "two honest agents' statuses are up to a status "
     "period apart"),
    ("crash_flush_s", "<", 1, "hang_timeout_s", "a scripted crash must not look like a hang "
     "first"),
)
#: How a relation's operator reads, and what it checks.
WORDS = {">": "must exceed", ">=": "must be at least", "<": "must be below",
          "<=": "must not exceed"}
HOLDS = {">": operator.gt, ">=": operator.ge, "<": operator.lt, "<=": operator.le}
_FLIP = {">": "<", ">=": "<=", "<": ">", "<=": ">="}

#: The runtime's defaults (consistent: checked by the test suite).
DEFAULT = Timing()
