"""The recorder of a run: what a peer of the mesh hears of the truth, estimates, statuses,
rosters, assignments and the monitor's events, kept by step.

:class:`Recorder` owns the subscriptions (:meth:`Recorder.subscribe`) and the
:class:`Recording`; :meth:`Recorder.feed` takes one ``(key, payload)`` as it came off the
wire, so tests feed it by hand. ``socmon up`` (:class:`agent.run.local.LocalRun`) records
with it, and so does ``socmon watch`` (:func:`watch_run`), attached to any run;
:func:`agent.run.summary.summarize` turns a recording into the summary and the run folder.

Examples
--------
>>> import numpy as np
>>> from agent.protocol import wire
>>> from agent.protocol import topics
>>> r = Recorder("demo", n=2, N=1, M=1)
>>> r.feed(topics.truth_key("demo"), wire.encode_truth(0, [1.0, 2.0]))
>>> r.feed(topics.est_key("demo", 1), wire.encode_est(1, 0, [1.0, 0.0], epoch=0, t=0.0))
>>> r.view()["mse"]                  # ((1-1)^2 + (0-2)^2) / 2
2.0
"""

from __future__ import annotations

import contextlib
import json
import math
import time
from dataclasses import dataclass, field

import numpy as np

from design.metrics import mse_of_step
from design.plausibility import ESTIMATE_MULTIPLE, READING_MULTIPLE

from agent.protocol import topics
from broker_free_net.keys import InvalidKey
from broker_free_net.codec import MalformedMessage, MessageStats, check_context, try_decode

from agent.protocol import wire
from agent.shell.memory import TRIM_S, heap_trimmer
from agent.protocol.timing import DEFAULT as TIMING

__all__ = ["Recording", "Recorder", "kept_step", "watch_run", "WatchEnd"]

#: Most events (the monitor's, heard on the wire, and role drops) a recording keeps.
MAX_EVENTS = 100_000


@dataclass
class Recording:
    """What the recorder saw, by step."""

    run_id: str
    ports: list
    truth: dict = field(default_factory=dict)          # step -> x
    est: dict = field(default_factory=dict)            # agent -> {step: x}
    est_epoch: dict = field(default_factory=dict)      # agent -> {step: epoch}
    status: dict = field(default_factory=dict)         # agent -> last status
    rosters: list = field(default_factory=list)        # (activate_at, ids, epoch)
    assigns: dict = field(default_factory=dict)        # (agent, epoch) -> assignment
    events: list = field(default_factory=list)         # exits, signals, impairments
    monitor_events: list = field(default_factory=list)  # the monitor's, heard on the wire
    recorder_malformed: int = 0
    wall: float = 0.0
    failure: str | None = None
    interrupted: bool = False
    #: an interrupted run's record ends here: the newest step every agent still
    #: publishing had recorded (:meth:`Recorder.last_complete_step`), None otherwise
    complete_step: int | None = None
    children: object = None                            # agent.run.launcher.Children of `up`
    monitors_alive: set = field(default_factory=set)   # monitor ids whose token is up
    monitor_seen: bool = False                         # a monitor's token was ever heard
    no_monitor_since: int | None = None                # step the last monitor token went
    world_silent: dict | None = None                   # {step, seconds}: agents left it


class MonitorTokens:
    """The monitors' liveliness tokens as a live recorder takes them (``up``, ``watch``):
    a token that went is handed to :meth:`Recorder.on_monitor_liveliness` (with the step
    it went at) once the world's token stayed in the recorder's view
    ``Timing.recorder_token_settle_s`` after it. Gone together with the world's, it is
    the recorder's own view that lapsed (its links' leases ran out while it was paused or
    cut off, and every token left its view at once): no monitor's absence, and no "NO
    MONITOR ALIVE" window in the record; the lapse is an event of the recorder's.

    >>> r = Recorder("demo", n=1, N=1, M=1)
    >>> t = [0.0]
    >>> tokens = MonitorTokens(r, clock=lambda: t[0])
    >>> _ = r.on_monitor_liveliness("1", True)
    >>> tokens.on_token("1", False); tokens.settle(world_in_view=False)
    >>> r.recording.no_monitor_since is None, r.recording.events[-1]["view_lost"]
    (True, True)
    >>> tokens.on_token("1", False); t[0] = 0.5; tokens.settle(world_in_view=True)
    >>> r.recording.no_monitor_since
    -1
    """

    def __init__(self, recorder: "Recorder", settle_s: float | None = None,
                 clock=time.monotonic):
        self.recorder, self.clock = recorder, clock
        self.settle_s = TIMING.recorder_token_settle_s if settle_s is None else settle_s
        self._went: list = []                 # [(ident, step, when)] not handed on yet

    def on_token(self, ident: str, alive: bool) -> None:
        """A monitor's token event as the liveliness watch gives it."""
        if alive:
            self._went = [w for w in self._went if w[0] != ident]
            self.recorder.on_monitor_liveliness(ident, True)
        else:
            self._went.append((ident, self.recorder.step, self.clock()))

    def settle(self, world_in_view: bool) -> None:
        """Hand on the tokens gone ``settle_s`` ago while the world's stays in view; drop
        those gone with it (an event says the recorder's view lapsed)."""
        if not self._went:
            return
        if not world_in_view:
            self.recorder._event(process="recorder", view_lost=True, step=self._went[0][1],
                                 monitors=sorted({w[0] for w in self._went}))
            self._went = []
            return
        now = self.clock()
        while self._went and now - self._went[0][2] >= self.settle_s:
            ident, step, _ = self._went.pop(0)
            self.recorder.on_monitor_liveliness(ident, False, step=step)


def kept_step(step: int, record_every: int, last_step: int | None) -> bool:
    """Whether a recorder keeping every ``record_every``-th step and the run's last
    (``up --record-every``) keeps the states of ``step``.

    >>> [k for k in range(26) if kept_step(k, 10, 25)]
    [0, 10, 20, 25]
    """
    return step % record_every == 0 or step == last_step


class Recorder:
    """Subscriptions and decoding of everything a run publishes, into a :class:`Recording`.

    Parameters
    ----------
    run_id : str
    n : int
        States of the scenario (the length of the truth and of each estimate).
    N, M : int
        Active agents (the initial roster is 1..N) and all agents (active + standby).
    ports : list
        Kept in the recording (``up``'s listen ports).
    keep_steps : int or None
        Keep the truth and estimates of the newest ``keep_steps`` steps only (a watcher of
        an endless run must not grow without bound); None keeps all (``up``: K is known).
    clock : callable
        The time stamped on the events it records (default ``time.time``).
    scale : design.plausibility.StateScale, optional
        The model's scale: a truth or an estimate far beyond it (the agents' own rule) is
        not recorded but counted (``stats`` reason ``implausible``), so a forged 1e300
        cannot make the run's MSE infinite.
    record_every, last_step : int
        Keep the truth and the estimates' states of every ``record_every``-th step only
        (and of ``last_step``, the run's last): a large or long run's record grows by a
        state per agent a step otherwise (``up --record-every``). Every message is still
        decoded and checked, and every estimate's epoch kept: the steps the rosters came
        into force are read from them.
    """

    def __init__(self, run_id: str, n: int, N: int, M: int, ports=(),
                 keep_steps: int | None = None, control_public: bytes | None = None,
                 scale=None, clock=time.time, record_every: int = 1,
                 last_step: int | None = None):
        if not (isinstance(record_every, int) and record_every >= 1):
            raise ValueError(f"record_every: expected an integer >= 1, got {record_every!r}")
        self.record_every, self.last_step = record_every, last_step
        rec = self.recording = Recording(run_id=run_id, ports=list(ports))
        rec.est = {a: {} for a in range(1, M + 1)}
        rec.est_epoch = {a: {} for a in range(1, M + 1)}
        rec.rosters = [(0, tuple(range(1, N + 1)), 0)]
        self.N, self.M = N, M
        self.stats = MessageStats()
        self._schemas = {"truth": wire.truth_schema(n), "est": wire.est_schema(n),
                         "roster": wire.roster_schema(), "ctl": wire.ctl_schema(n)}
        self._roster_key = topics.ctl_key(run_id, 0)
        self._truth_key = topics.truth_key(run_id)
        self._inboxes = ()
        self.keep_steps = keep_steps
        self.scale = scale
        self.clock = clock       # the time of the events it records (a simulated run's own)
        self._trim, self._trimmed = heap_trimmer(), (0.0, 0)
        self._verifier = None            # with the run's control key: unsigned ctl dropped
        if control_public is not None:
            from agent.protocol.control_auth import ControlVerifier

            self._verifier = ControlVerifier(control_public, run_id, not_before=0.0)
        self._newest = -1
        self.truth_at = None     # when the newest step of the truth came (monotonic)
        self._epoch_seen = 0     # the highest epoch taken (statuses, signed rosters)
        self.alive = set()     # agent ids whose liveliness token is up (set by watch_run)
        self.estimates_received = 0

    def _plausible(self, m: dict, multiple: float) -> bool:
        return self.scale is None or self.scale.plausible(m["x"], m["step"], multiple)

    # -- liveliness ----------------------------------------------------------------------
    def on_monitor_liveliness(self, ident: str, alive: bool,
                              step: int | None = None) -> str | None:
        """A monitor's token came (``alive``) or went (at ``step``, default the newest);
        returns ``"none"`` when the last monitor token went (from then on a failure is
        neither detected nor recovered), ``"back"`` when one returned after that, else
        None; both are events. A live recorder feeds them through
        :class:`MonitorTokens`, which tells a monitor's absence from its own lapse.

        >>> r = Recorder("demo", n=1, N=1, M=1)
        >>> r.on_monitor_liveliness("1", True), r.on_monitor_liveliness("1", False)
        (None, 'none')
        >>> r.recording.no_monitor_since, r.on_monitor_liveliness("2", True)
        (-1, 'back')
        """
        rec = self.recording
        was = bool(rec.monitors_alive)
        (rec.monitors_alive.add if alive else rec.monitors_alive.discard)(ident)
        rec.monitor_seen |= alive
        if was and not rec.monitors_alive:
            rec.no_monitor_since = self.step if step is None else step
            self._event(process="monitor", monitors_alive=0, step=rec.no_monitor_since)
            return "none"
        if alive and not was and rec.no_monitor_since is not None:
            self._event(process="monitor", monitors_alive=len(rec.monitors_alive),
                        step=self.step, absent_since=rec.no_monitor_since)
            rec.no_monitor_since = None
            return "back"
        return None

    def _event(self, **fields) -> None:
        if len(self.recording.events) < MAX_EVENTS:
            self.recording.events.append({**fields, "t": self.clock()})

    # -- the wire -----------------------------------------------------------------------
    def subscribe(self, peer) -> None:
        """Declare the subscriptions on ``peer`` (a :class:`broker_free_net.peer.Peer`)."""
        run = self.recording.run_id
        truth = peer.subscribe(topics.truth_key(run), maxlen=1 << 16)
        est = peer.subscribe(topics.any_agent_pattern(run, "est"), maxlen=1 << 16)
        status = peer.subscribe(topics.any_agent_pattern(run, "status"))
        # estimates and statuses do not wake the owner's loop: they are drained at the
        # next truth (one wake-up a step instead of one per message) or timeout
        est.wakes = status.wakes = False
        self._inboxes = (
            truth, est, status,
            peer.subscribe(topics.any_agent_pattern(run, "ctl"), maxlen=1 << 12),
            peer.subscribe(topics.monitor_events_key(run), maxlen=1 << 12),
        )

    def drain(self) -> None:
        """Feed everything received since the last call (truth first, then estimates);
        after a burst of malformed input, give the freed heap back to the OS (at most
        every :data:`agent.shell.memory.TRIM_S`)."""
        for inbox in self._inboxes:
            for item in inbox.drain():
                self.feed(item.key, item.payload)
        self.recording.recorder_malformed = dropped = self.stats.total_dropped
        at, seen = self._trimmed
        if dropped - seen > 1000 and time.monotonic() - at > TRIM_S:
            self._trim()
            self._trimmed = (time.monotonic(), dropped)

    def feed(self, key: str, payload: bytes, decoded=None) -> None:
        """One message as received on ``key``; a malformed one is counted and dropped.
        ``decoded``: for an estimate another receiver decoded already (the simulated
        runtime's), a function giving ``(message, None)`` or ``(None, reason)``: checked
        here as this recorder's own decode would (senders, stamp window)."""
        rec = self.recording
        kind = str(key).split("/")[2] if str(key).count("/") >= 2 else ""
        if key == self._truth_key:
            m = try_decode(payload, self._schemas["truth"], self.stats, **self._window())
            if m is not None and not self._plausible(m, READING_MULTIPLE):
                self.stats.count_dropped("implausible")
            elif m is not None:
                if self.records(m["step"]):
                    rec.truth[m["step"]] = np.array(m["x"])
                if m["step"] > self._newest:
                    self.truth_at = time.monotonic()
                self._newest = max(self._newest, m["step"])
                # trimmed in batches of keep_steps // 8 (one pass over the dicts each)
                if self.keep_steps is not None and \
                        len(rec.truth) > self.keep_steps + self.keep_steps // 8:
                    self._forget_oldest()
        elif kind == "est":
            m = self._decode(payload, self._schemas["est"], decoded, senders=rec.est.keys(),
                             **self._window())
            if m is not None and self._sender_of(key) != m["agent"]:
                self.stats.count_dropped("sender")      # agent j's key, agent i's estimate
            elif m is not None and not self._plausible(m, ESTIMATE_MULTIPLE):
                self.stats.count_dropped("implausible")
            elif m is not None:
                if self.records(m["step"]):
                    rec.est[m["agent"]][m["step"]] = np.array(m["x"])
                rec.est_epoch[m["agent"]][m["step"]] = m["epoch"]
                self.estimates_received += 1
        elif kind == "status":
            m = try_decode(payload, wire.STATUS_SCHEMA, self.stats)
            if m is not None and self._sender_of(key, "status") != m["agent"]:
                self.stats.count_dropped("sender")
            elif m is not None and m["epoch"] > self._epoch_seen + TIMING.epoch_jump_max:
                self.stats.count_dropped("epoch")       # the monitor's rule (MonitorCore)
            elif m is not None and m["agent"] in rec.est:
                self._epoch_seen = max(self._epoch_seen, m["epoch"])
                was = rec.status.get(m["agent"])
                if was is not None and was["active"] and not m["active"] and \
                        len(rec.events) < MAX_EVENTS:    # an agent dropped its role (fenced)
                    rec.events.append({"process": f"agent-{m['agent']}", "role": "dropped",
                                       "epoch": m["epoch"], "step": m["step"], "t": self.clock()})
                links = m.get("links", {})
                if links != (was or {}).get("links", {}) and len(rec.events) < MAX_EVENTS:
                    # the impairments in force on the links into it changed: by this run's
                    # faults, `socmon inject` or anyone with the operator key
                    rec.events.append({"process": f"agent-{m['agent']}", "links": links,
                                       "step": m["step"], "t": self.clock()})
                rec.status[m["agent"]] = m
        elif key == self._roster_key:
            m = self._authentic(try_decode(payload, self._schemas["roster"], self.stats))
            if m is not None and m["epoch"] > rec.rosters[-1][2]:
                rec.rosters.append((m["activate_at"], tuple(m["ids"]), m["epoch"]))
                self._epoch_seen = max(self._epoch_seen, m["epoch"])
        elif kind == "ctl":
            m = self._authentic(try_decode(payload, self._schemas["ctl"], self.stats))
            if m is not None and len(rec.assigns) < MAX_EVENTS:
                rec.assigns.setdefault((m["agent"], m["epoch"]), m)
        elif kind == "monitor":
            m = try_decode(payload, wire.MONITOR_EVENT_SCHEMA, self.stats)
            if m is not None:
                try:
                    event = json.loads(m["event"])
                except ValueError:
                    event = None
                if isinstance(event, dict) and isinstance(event.get("kind"), str) and \
                        _plain_times(event) and len(rec.monitor_events) < MAX_EVENTS:
                    rec.monitor_events.append(event)
                else:
                    self.stats.count_dropped("event")
        self.recording.recorder_malformed = self.stats.total_dropped

    def _decode(self, payload, schema, decoded, **context):
        """:func:`broker_free_net.codec.try_decode` of ``payload``, or of the message
        ``decoded()`` gives (see :meth:`feed`) with this recorder's checks; counted."""
        if decoded is None:
            return try_decode(payload, schema, self.stats, **context)
        msg, reason = decoded()
        try:
            if msg is None:
                raise MalformedMessage(reason, "decoded by another receiver")
            check_context(msg, schema, **context)
        except MalformedMessage as exc:
            self.stats.count_dropped(exc.reason)
            return None
        self.stats.count_accepted()
        return msg

    def records(self, step: int) -> bool:
        """Whether the states of ``step`` are kept (:func:`kept_step`)."""
        return kept_step(step, self.record_every, self.last_step)

    def _authentic(self, msg):
        """``msg`` if it is not a control message or carries the run's control signature
        (known when the recorder was given the key); else None, counted."""
        if msg is None or self._verifier is None:
            return msg
        from agent.protocol.control_auth import SignatureError

        try:
            self._verifier.check(msg, replay=False)
        except SignatureError:
            self.stats.count_dropped("signature")
            return None
        return msg

    def _window(self) -> dict:
        """The stamp window of truth and estimates: as an agent's, around the newest step."""
        return {"now_step": self._newest, "window": wire.STAMP_WINDOW} if self._newest >= 0 else {}

    def _sender_of(self, key, kind: str = "est"):
        try:
            return topics.parse_agent_key(self.recording.run_id, kind, key)
        except InvalidKey:
            return None

    def _forget_oldest(self) -> None:
        """Drop every step more than ``keep_steps`` before the newest (by value: an entry
        stamped ahead never holds older ones in place)."""
        rec = self.recording
        cutoff = self.step - self.keep_steps
        for by_step in (rec.truth, *rec.est.values(), *rec.est_epoch.values()):
            for k in [k for k in by_step if k <= cutoff]:
                del by_step[k]

    # -- what it shows ------------------------------------------------------------------
    @property
    def step(self) -> int:
        """The newest step of the truth heard (-1 before the clock starts)."""
        return self._newest

    def in_force(self, k: int) -> tuple:
        """The agent ids of the roster in force at step ``k`` (the first before step 0)."""
        return [ids for at, ids, _ in self.recording.rosters if at <= max(k, 0)][-1]

    def last_complete_step(self, alive=()) -> int | None:
        """The newest step every agent still publishing has recorded: the smallest newest
        estimate among the agents in force whose liveliness token is up (``alive``);
        with none of them, the newest step with an estimate of an agent in force (None
        before any). A watch stopped mid-step ends its record there, so that the last
        step is not a mean over fewer agents."""
        rec = self.recording
        newest = [max(rec.est[a]) for a in self.in_force(self.step)
                  if a in alive and rec.est.get(a)]
        if newest and min(newest) in rec.truth:
            return min(newest)
        return self.view()["mse_step"]

    def view(self) -> dict:
        """A snapshot for a live view: the newest step with an estimate of an agent in
        force and its MSE (mean over those agents, as :func:`agent.run.summary.mse_by_step`)
        with its mean over the last 100 steps (``mse_last100``, over ``mse_last100_steps``
        steps, fewer early in a run: of ``mse_last100_samples`` of them, fewer under
        ``record_every`` or where no agent in force estimated), the sums over the agents' last statuses, the verdicts,
        and one row per agent."""
        rec = self.recording
        k = next((k for k in range(self.step, max(-1, self.step - 10_000), -1)
                  if k in rec.truth and any(k in rec.est[a] for a in self.in_force(k))),
                 None)
        def mse_at(k):
            return mse_of_step([rec.est[a][k] for a in self.in_force(k) if k in rec.est[a]],
                               rec.truth[k])

        mse = mse_at(k) if k is not None else None
        first = 0 if k is None else max(0, k - 99)
        # every step's, or every kept step's under --record-every
        recent = [] if k is None else [m for m in (mse_at(j) for j in range(first, k + 1)
                                                   if j in rec.truth) if m is not None]
        agents = {}
        for a in range(1, self.M + 1):
            st = rec.status.get(a)
            last = max(rec.est[a]) if rec.est[a] else None
            err = None
            if last is not None and last in rec.truth:
                err = mse_of_step([rec.est[a][last]], rec.truth[last])
            agents[a] = {"step": st["step"] if st else last, "active": st["active"] if st
                         else None, "epoch": st["epoch"] if st else None, "mse": err,
                         "drops": st["drops"] if st else 0, "late": st["late"] if st else 0,
                         "malformed": st["malformed"] if st else 0}
        # the verdicts on agents not back since (one that passed probation rejoined)
        verdicts = [e for e in rec.monitor_events if e.get("kind") == "verdict" and not any(
            r.get("kind") == "rejoin" and r.get("agent") == e.get("agent")
            and r.get("t", 0.0) >= e.get("t", 0.0) for r in rec.monitor_events)]
        return {"run": rec.run_id, "step": self.step, "mse_step": k, "mse": mse,
                "mse_last100": float(np.mean(recent)) if recent else None,
                "mse_last100_steps": 0 if k is None else k - first + 1,  # fewer early on
                "mse_last100_samples": len(recent),
                "drops": sum(r["drops"] for r in agents.values()),
                "late": sum(r["late"] for r in agents.values()),
                "malformed": sum(r["malformed"] for r in agents.values()),
                "roster": list(rec.rosters[-1][1]), "epoch": rec.rosters[-1][2],
                "monitors_alive": len(rec.monitors_alive) if rec.monitor_seen else None,
                "no_monitor_since": rec.no_monitor_since,
                "failures": [{"agent": v.get("agent"), "cause": v.get("cause"),
                              "step": v.get("step")} for v in verdicts],
                "agents": agents}


def _plain_times(event: dict) -> bool:
    """Whether a monitor event heard has its times, step and agent (when present) as
    numbers: what the summary and the live view compare and order them by."""
    for name in ("t", "mono", "detected_t"):
        t = event.get(name)
        if name in event and not (isinstance(t, (int, float)) and not isinstance(t, bool)
                                  and math.isfinite(t)):
            return False
    return all(name not in event or (isinstance(event[name], int)
                                     and not isinstance(event[name], bool))
               for name in ("step", "agent", "epoch"))


class WatchEnd(Exception):
    """Raised by the SIGTERM handler of :func:`watch_run` to end the watch."""


@contextlib.contextmanager
def _drained_at_exit(recorder):
    """On the way out, even when interrupted, record what was received and not yet read
    (estimates and statuses wait for the next truth to be drained)."""
    try:
        yield
    finally:
        recorder.drain()


def watch_run(net, recorder: Recorder, *, steps: int | None = None, timeout: float = 60.0,
              on_view=lambda view: None, interval: float = 0.25, grace: float = 5.0) -> str:
    """Attach to a run as a peer and record it until it ends; returns why it ended.

    Ends when step ``steps`` is recorded for the truth and every agent in force (with
    ``steps``); when the world's liveliness token goes, then once the agents' tokens go
    or no estimate came for ``grace`` seconds (``"world ended"`` after its end message,
    ``"world lost"`` without it: killed, paused or cut off); on SIGTERM or Ctrl-C (``"interrupted"``);
    when no truth was heard within ``timeout`` seconds (``"no world"``); or, with
    ``steps``, when the first step of the truth heard is already past it (``"behind"``:
    nothing of steps 0..``steps`` is left to record). ``on_view`` gets
    :meth:`Recorder.view` every ``interval`` seconds and once at the end.

    Returns
    -------
    str
        ``"steps"``, ``"world ended"``, ``"world lost"``, ``"interrupted"``, ``"no world"``
        or ``"behind"``.
    """
    import os
    import signal


    rec = recorder.recording

    def on_term(*_):
        raise WatchEnd

    old_term = signal.signal(signal.SIGTERM, on_term)
    old_int = signal.signal(signal.SIGINT, signal.default_int_handler)
    t_begin = time.monotonic()
    why = "interrupted"
    try:
        with topics.open_peer(net, "watch", f"p{os.getpid()}") as peer, _drained_at_exit(recorder):
            recorder.subscribe(peer)
            # the world's end: agents leave once they hear it, and their tokens going then
            # are the run's end, not deaths (the world's own token may go after theirs)
            end_in = peer.subscribe(topics.end_key(rec.run_id), maxlen=16)
            world_ended = False
            gone = set()                               # agents whose token went
            alive_watch = peer.watch_liveliness()
            tokens = MonitorTokens(recorder)
            world_seen = False
            world_gone = None
            heard, last_heard = 0, time.monotonic()    # estimates, and when the last came
            first_heard = None                         # the first step of the truth heard
            next_view = 0.0
            while True:
                peer.wait(timeout=0.05)
                recorder.drain()
                world_ended = world_ended or bool(end_in.drain())
                now = time.monotonic()
                alive = alive_watch.alive()
                for ev in alive_watch.drain():
                    if ev.role == "monitor":
                        # the monitors leave at the world's end, as the agents do: their
                        # tokens going then leaves no failure unanswered (as ``up`` reads it)
                        if world_gone is None and not world_ended:
                            tokens.on_token(ev.id, ev.any_alive)
                    elif ev.role == "agent" and not ev.any_alive and world_gone is None \
                            and not world_ended:
                        recorder._event(process=f"agent-{ev.id}", liveliness=False,
                                        step=recorder.step)
                        gone.add(ev.id)
                    elif ev.role == "agent" and ev.any_alive and ev.id in gone:
                        # back (paused past its lease, a link that lapsed): not dead
                        gone.discard(ev.id)
                        recorder._event(process=f"agent-{ev.id}", liveliness=True,
                                        step=recorder.step)
                tokens.settle(("world", "0") in alive_watch.alive())   # (after the drain)
                if ("world", "0") in alive:
                    world_seen, world_gone = True, None
                elif world_seen and world_gone is None:
                    world_gone = now
                if now >= next_view:
                    on_view(recorder.view())
                    next_view = now + interval
                k = recorder.step
                if steps is not None and rec.truth and first_heard is None:
                    first_heard = min(rec.truth)
                if steps is not None and first_heard is not None and first_heard > steps:
                    why = "behind"          # joined after step `steps`: none of it to record
                    break
                agents_alive = {int(i) for r, i in alive if r == "agent" and i.isdigit()}
                recorder.alive = agents_alive
                in_force = [a for a in recorder.in_force(k) if a in agents_alive]
                if steps is not None and k >= steps and all(
                        max(rec.est[a], default=-1) >= steps for a in in_force):
                    why = "steps"
                    break
                if recorder.estimates_received != heard:
                    heard, last_heard = recorder.estimates_received, now
                # after the world: until the agents leave (their last statuses come
                # first) or stop publishing; an agent still catching up keeps the watch
                if world_gone is not None and (not agents_alive or
                                               now - max(world_gone, last_heard) > grace):
                    # its token went without its end: killed, paused past its lease or
                    # cut off (the agents wait for it, then leave)
                    why = "world ended" if world_ended else "world lost"
                    break
                if not rec.truth and not world_seen and now - t_begin > timeout:
                    why = "no world"
                    break
            recorder.drain()
    except (KeyboardInterrupt, WatchEnd):
        rec.interrupted = True
        why = "interrupted"
    finally:
        signal.signal(signal.SIGTERM, old_term)
        signal.signal(signal.SIGINT, old_int)
    rec.wall = time.monotonic() - t_begin
    on_view(recorder.view())
    return why
