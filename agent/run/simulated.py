"""The whole runtime in one process under simulated time: world, agents and monitor cores
wired by an event queue, with link latency, crashes, hangs and pauses, and no zenoh.

What runs is what the processes run: :class:`agent.node.core.AgentCore`,
:class:`agent.world.core.WorldCore` and :class:`agent.monitor.core.MonitorCore`, fed with
messages that go through the same codec (:mod:`agent.protocol.wire`, encoded by the sender and
decoded, validation included, at the first receiver; the receivers of one payload share the
message, :class:`_Shared`) at the times the simulated network delivers them. The monitor's
record is :meth:`MonitorCore.new_records`, as the monitor process writes it, and the run is
summarised by :func:`agent.run.summary.summarize`, the code that writes a live run's
``summary.json``: ``recovered``, the rosters in force and the MSE after recovery are read
from what the simulated agents computed, as they are for a live run.

A run of 600 steps of paper-14-live takes well under a second of CPU once the gains it
needs are designed, so thousands of fault schedules can be checked
(``tests/test_sim_runtime.py``, ``scripts/sim_chaos.py``).

The model of the transport: every message takes ``latency_s`` plus a uniform jitter of
``jitter_s`` per link, in order per link (zenoh's links are TCP); a dead process receives
nothing; a paused one receives its messages when it resumes. A liveliness token goes at
once when its process dies (the kernel closes its sockets), ``lease_s`` after it stopped
(zenoh's link lease), and comes back when a paused process resumes. Gains the monitor asks
for come ``design_s`` after the request (a first gain, then its refined gain ``design_s``
later: live, seconds to minutes); the failures of the configuration in force are
precomputed as the monitor's worker does, one every ``precompute_s``, then polished, one
every ``polish_s`` (designed at once in real time and cached across runs by
configuration).

Faults are ``up``'s (:class:`agent.run.local.Fault`, :data:`FAULT_KINDS`): ``crash``
(the agent dies once it published step ``step - 1``, as ``up --kill STEP:AGENT``),
``kill`` (SIGKILL when the world reaches ``step``), ``hang``
(at the world's ``step`` the agent's loop stops for good; its token stays), ``stop``
(SIGSTOP for ``seconds``: the token lapses after ``lease_s`` and comes back, the backlog is
processed at once), and the impairments of ``up --fault`` for ``seconds`` (``sensor``: the
world's link into the agent cut; ``partition``: every link out of it; ``delay``/``drop``:
every link into it delayed by ``value`` steps or dropping a fraction ``value``), sent as
impairment messages the agents apply themselves; and ``slow`` (simulated only: a process
short of CPU, as beside busy loops): for ``seconds``, every message the agent handles costs
``value`` ms of its time, one after the other, so its steps come late once the messages of
a step cost more than the step.

>>> from design.scenario import load_scenario
>>> import numpy as np
>>> s = load_scenario("paper-14-live")
>>> G = [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure]
>>> from agent.run.local import Fault
>>> result = SimRuntime(s, G, s.delays, seed=1, faults=[Fault(150, "crash", 1)]).run(400)
>>> [(f["agent"], f["cause"]) for f in result.summary["failures"]], result.summary["recovered"]
([(1, 'crash')], True)
"""

from __future__ import annotations

import dataclasses
import heapq
import itertools
import math
from dataclasses import dataclass

import numpy as np

from agent.protocol import topics
from broker_free_net.codec import MalformedMessage, MessageStats, decode, try_decode
from broker_free_net.impair import decode_impairment, encode_impairment

from agent.protocol import wire
from agent.node.core import AgentCore, AssignmentError, agent_config
from agent.world.core import WorldCore
from agent.monitor.core import (
    LISTEN_S,
    ROSTER_S,
    TICK_S,
    Assignment,
    GainSource,
    MonitorConfig,
    MonitorCore,
    MonitorSeat,
    RosterUpdate,
)
from agent.protocol.timing import DEFAULT as TIMING
from agent.run.fault_kinds import SCRIPTED_FAULTS, WRONG_KINDS
from agent.run.folder import monitor_name

__all__ = ["SimConfig", "SimRuntime", "SimResult", "FAULT_KINDS", "run_schedules",
           "report_lines"]

#: The kinds of :class:`agent.run.local.Fault` a simulated run applies.
FAULT_KINDS = ("crash", "kill", "hang", "stop", "sensor", "partition", "delay", "drop",
               "slow", "monitor", "monitorstop", "monitorsgone", "lie", "bias")
#: The kinds scripted into an agent at its start (as ``up`` passes them on the command
#: line): its process carries them out at their step.
SCRIPTED = tuple(k for k in SCRIPTED_FAULTS if k in FAULT_KINDS)
#: The kinds that act on the monitors (the acting one, or all for ``monitorsgone``).
MONITOR_FAULTS = ("monitor", "monitorstop", "monitorsgone")


@dataclass(frozen=True)
class SimConfig:
    """The simulated network and process periods (seconds)."""

    step_s: float = 0.02
    latency_s: float = 0.001
    jitter_s: float = 0.002
    lease_s: float = 1.0
    status_s: float = TIMING.status_s
    tick_s: float = TICK_S               # the monitor's loop
    roster_s: float = ROSTER_S           # the roster re-published
    design_s: float = 0.5                # a gain requested by the monitor comes this late
    precompute_s: float = 0.3            # each precomputed failure's gain takes this long
    polish_s: float = 0.4                # ... and its polish (a few MSE iterations) this
    monitors: int = 2                    # as up: the first acts, the others stand by
    listen_s: float = LISTEN_S           # a (re)started monitor listens before it acts
    restart_s: float = 0.5               # a killed monitor's successor declares its token
    #                                      this late (its start, its precompute: up)
    start_s: float = 0.5                 # the world's first step (agents heard each other)
    precompute: bool = True              # False: as up --no-precompute, every failure's
    #                                      first gain requested when it comes
    deadline_s: float | None = None      # agents' deadline; default one step


@dataclass
class SimResult:
    """A simulated run: the recording (:class:`agent.run.recorder.Recording`), its summary
    (the keys of a live run's ``summary.json``), the MSE per step, and the monitors."""

    recording: object
    summary: dict
    steps: list
    mse: list
    monitors: dict                       # id -> the newest monitor of that id (core, seat)
    config: object = None                # the run as an agent.run.local.RunConfig

    def violations(self, bounds=None) -> list:
        """:func:`agent.run.chaos.check_invariants` of this run (what ``socmon chaos``
        checks on a live run)."""
        from agent.run.chaos import Bounds, check_invariants

        return check_invariants(self.config, self.recording, self.summary, self.steps,
                                self.mse, bounds or Bounds())


#: :func:`agent.run.summary.predicted_mse` by scenario, gains and delays (every run of a
#: batch asks the same)
_PREDICTED: dict = {}


def _configuration_key(roster, *arrays) -> tuple:
    """Everything a :class:`design.roster.Roster` (or a scenario) holds, the scenario's
    fields included, and ``arrays`` (lists of arrays too), as a hashable key."""
    from agent.run.chaos import configuration_key

    if not hasattr(roster, "ids"):
        return configuration_key(roster, *arrays)
    return configuration_key(roster.scenario, roster.ids, roster.standby_ids, roster.table,
                             roster.delays, *arrays)


class _Shared:
    """A payload sent to several receivers (the world's readings, an estimate, a status, a
    roster): decoded by the codec, validation included, at the first receiver, and the same
    message handed to the others, each counted in ``stats``. Every receiver of a live run
    decodes the same bytes to the same message; decoding each copy again took a fifth of a
    simulated run. The cores only read the messages (``AgentCore.on_estimate`` copies the
    estimate; the arrays are read-only), so one message can be shared."""

    __slots__ = ("payload", "schema", "msg", "reason")

    def __init__(self, payload: bytes, schema):
        self.payload, self.schema, self.msg, self.reason = payload, schema, None, None

    def decoded(self) -> tuple:
        """``(message, None)``, or ``(None, reason)`` for a malformed payload; decoded at
        the first call."""
        if self.schema is not None:
            try:
                self.msg = decode(self.payload, self.schema)
            except MalformedMessage as exc:
                self.reason = exc.reason
            self.schema = None
        return self.msg, self.reason

    def decode(self, stats: MessageStats):
        self.decoded()
        if self.msg is None:
            stats.count_dropped(self.reason)
        else:
            stats.count_accepted()
        return self.msg


class _GainDesigns:
    """The monitor's gain worker under simulated time: a request is designed at once (in
    real time, cached by model and configuration across runs) and answered ``design_s``
    later."""

    cache: dict = {}
    plans: dict = {}

    @classmethod
    def plan(cls, roster) -> list:
        """:func:`agent.monitor.gain_worker.plan_failures` of ``roster``, cached across runs
        by configuration like the designs (it is pure, and its rosters are frozen): planning
        was a twentieth of a run, again at every precompute."""
        from agent.monitor.gain_worker import plan_failures

        key = _configuration_key(roster)
        if key not in cls.plans:
            cls.plans[key] = plan_failures(roster)
        return list(cls.plans[key])

    def _design(self, roster, kind, warm=None):
        from agent.monitor.core import design_gains_for

        key = (roster.scenario.A.tobytes(), GainSource.key(roster), kind,
               None if warm is None else b"".join(np.asarray(g).tobytes() for g in warm))
        if key not in self.cache:
            init = self._design(roster, "fast", warm)[0] if kind == "polished" else warm
            if kind == "polished" and init is None:
                self.cache[key] = (None, {})
            else:
                self.cache[key] = design_gains_for(roster, kind, init=init)
        return self.cache[key]

    def __init__(self, runtime):
        self.rt = runtime
        self.ready: list = []
        self.generation = 0

    def _answer(self, roster, kinds, init=None):
        at = 0.0
        for kind in kinds:                     # one after the other, design_s apart
            at += self.rt.config.design_s
            G, info = self._design(roster, kind, init if kind == "fast" else None)
            self.rt.after(at, lambda G=G, info=info: self.ready.append((roster, G, info)))

    def request(self, roster, kinds=("fast", "refined"), init=None):
        # as GainWorker.request: a first gain, then the refined one (an unforeseen
        # configuration's refined gain was never asked for here)
        self._answer(roster, kinds, init)

    def assess(self, roster, G, info):
        pass                                   # the exact MSE of a fast gain: not needed here

    def precompute(self, roster, in_force=None):
        """What the monitor's worker designs ahead for ``roster``
        (:func:`agent.monitor.gain_worker.precompute_queue`: the planned failures' fast
        gains, then their polish where that pays), answered one after the other, a fast
        gain ``precompute_s`` after the one before, a polished one ``polish_s``; a newer
        precompute abandons the rest of an older one."""
        from agent.monitor.gain_worker import precompute_queue

        self.generation += 1
        generation = self.generation
        todo = precompute_queue(roster, in_force, planned=self.plan(roster))
        warm = {GainSource.key(nxt): start for nxt, kind, start, _ in todo if kind == "fast"}
        cfg = self.rt.config
        at = 0.0
        for nxt, kind, _, _ in todo:
            at += cfg.precompute_s if kind == "fast" else cfg.polish_s
            # a polish starts from the fast gain, designed from the same warm start
            G, info = self._design(nxt, kind, warm[GainSource.key(nxt)])
            if G is None and kind == "polished":
                continue
            self.rt.after(at, lambda G=G, info=info, nxt=nxt:
                          generation == self.generation
                          and self.ready.append((nxt, G, info)))

    def stand_down(self):
        """As :meth:`GainWorker.stand_down`: the precompute's answers still due are
        dropped."""
        self.generation += 1

    def poll(self):
        out, self.ready = self.ready, []
        return out


class _SimMonitor:
    """One monitor process of a simulated run: its core, gain worker and seat."""

    def __init__(self, runtime, monitor_id: int, listen_s: float):
        self.id = int(monitor_id)
        self.name = f"monitor-{self.id}"
        self.designs = _GainDesigns(runtime)
        self.gains = GainSource(worker=self.designs)
        self.core = MonitorCore(runtime.monitor_config, runtime.s, runtime.G,
                                runtime.delays, gains=self.gains)
        self.seat = MonitorSeat(self.core, self.id, runtime.now, listen_s=listen_s)
        self.roster_at = 0.0
        self.session = f"{self.id}-{runtime.now:.6f}"    # its token's session: one a start


#: each agent's residual tests of a run's initial configuration, by configuration: the
#: runs of a batch of schedules start from the same one
_INITIAL_TESTS: dict = {}


def _agent_config(scenario, a, G, seed, delays, deadline, skewed):
    """:func:`agent.node.core.agent_config` of agent ``a``, with the lie and sensor bias
    of ``skewed`` (faults of kinds ``lie``, ``bias``) scripted into the agents they name,
    as ``up`` passes them (``--lie``, ``--sensor-fault``), and the residual tests on when
    there are any."""
    from design.residuals import AgentResiduals, configuration_tests
    from design.simulate import Fault as AgentFault

    config = agent_config(scenario, a, G, seed, delays, deadline,
                          lie=next((AgentFault("lie", a - 1, f.step, f.value) for f in skewed
                                    if f.kind == "lie" and f.agent == a), None),
                          sensor_faults=[AgentFault("bias", a - 1, f.step, f.value)
                                         for f in skewed if f.kind == "bias" and f.agent == a])
    if not skewed:
        return config
    key = _configuration_key(scenario, G, delays)
    if key not in _INITIAL_TESTS:
        _INITIAL_TESTS[key] = configuration_tests(scenario, G, delays)
    tests = _INITIAL_TESTS[key].get(a) if a <= scenario.N else None
    return dataclasses.replace(config, test_residuals=True,
                               residuals=None if tests is None else AgentResiduals(tests))


class SimRuntime:
    """One run of ``scenario`` with gains ``G`` and link ``delays`` (steps), ``faults``
    applied, in simulated time. :meth:`run` returns a :class:`SimResult`."""

    def __init__(self, scenario, G, delays, seed: int = 0, faults=(), config: SimConfig = None,
                 monitor: MonitorConfig | None = None):
        self.s = scenario
        self.G = [np.asarray(g, dtype=float) for g in G]
        self.delays = np.asarray(delays, dtype=int)
        self.seed = int(seed)
        self.faults = sorted(faults)
        for f in self.faults:
            on_agent = f.kind not in MONITOR_FAULTS
            if f.kind not in FAULT_KINDS or (
                    on_agent and not 1 <= f.agent <= scenario.N + scenario.standby):
                raise ValueError(f"a simulated run applies {FAULT_KINDS}, the agent ones to "
                                 f"an agent, got {f}")
        self._crash_at = {f.agent: f.step for f in self.faults if f.kind == "crash"}
        self.config = config or SimConfig()
        c = self.config
        self.M = scenario.N + scenario.standby
        self.now = 0.0
        self._queue: list = []
        self._seq = itertools.count()
        self._rng = np.random.default_rng([self.seed, 7])
        self._jitter: list = []                # the link jitters, drawn 1024 at a time
        self._jitter_at = 0
        self._link_free: dict = {}
        deadline = c.step_s if c.deadline_s is None else c.deadline_s
        # agents that lie or whose sensor is biased run the residual tests, all of them
        # (the initial configuration's from its start, the later ones' as assigned)
        skewed = [f for f in self.faults if f.kind in WRONG_KINDS]
        self.agents = {a: AgentCore(_agent_config(scenario, a, self.G, self.seed, self.delays,
                                                  deadline, skewed))
                       for a in range(1, self.M + 1)}
        self._names = {a: f"agent-{a}" for a in self.agents}     # their process names
        self._agent_of = {name: a for a, name in self._names.items()}
        self.world = WorldCore(scenario.A, self.seed, scenario.process_noise)
        self.dead: set = set()                 # processes that died ("agent-3", ...)
        self.hung: set = set()
        self.paused_until: dict = {}           # name -> resume time
        self._backlog: dict = {}               # name -> [callables] held while paused
        self._wake_at: dict = {}
        self.slow: dict = {}                   # name -> (until, seconds a message costs)
        self._busy_until: dict = {}
        self.monitor_config = monitor or MonitorConfig.from_timing(TIMING, step_s=c.step_s,
                                                                         lease_s=c.lease_s)
        self.monitors: dict = {}               # id -> _SimMonitor (the newest of that id)
        self._planned = None                   # monitor 1's single failures, at the start
        self.monitors_alive: set = set()       # ids whose token is up
        self._token_gone: set = set()          # agents whose token is down
        self._restarts = {}          # monitor id -> times started again (its name says it)
        self.stats = MessageStats()
        self._schemas = {"est": wire.est_schema(scenario.n), "ctl": wire.ctl_schema(scenario.n),
                         "roster": wire.roster_schema(),
                         "sensors": wire.sensors_schema(scenario.n)}
        from agent.run.recorder import Recorder

        self.run_id = f"sim{self.seed}"
        # the keys published on every step, formed (and checked) once
        self._keys = {"truth": topics.truth_key(self.run_id),
                      **{("est", a): topics.est_key(self.run_id, a) for a in self.agents},
                      **{("status", a): topics.status_key(self.run_id, a) for a in self.agents}}
        self.recorder = Recorder(self.run_id, scenario.n, scenario.N, self.M,
                                 clock=lambda: self.now)
        self.rec = self.recorder.recording
        self.rec.monitor_seen = True
        self._roster_at = 0.0

    def _record(self, src: str, key: str, payload: bytes, shared=None) -> None:
        """The recorder (``up``'s) hears ``payload`` on ``key``, as on the wire (the
        message decoded once with the other receivers', when ``shared``)."""
        decoded = None if shared is None else shared.decoded
        self._send(src, "recorder", lambda: self.recorder.feed(key, payload, decoded))

    # -- the event queue -------------------------------------------------------------
    # an event is (time, sequence number, function, its arguments)
    def after(self, dt: float, fn) -> None:
        heapq.heappush(self._queue, (self.now + dt, next(self._seq), fn, ()))

    def _send(self, src: str, dst: str, handle) -> None:
        """Deliver ``handle()`` at ``dst`` after the link's latency, in order per link."""
        i = self._jitter_at
        if i == len(self._jitter):
            # one draw of 1024 gives the numbers of 1024 draws of one, in the same order
            self._jitter, i = self._rng.random(1024).tolist(), 0
        self._jitter_at = i + 1
        c = self.config
        at = self.now + c.latency_s + c.jitter_s * self._jitter[i]
        link = (src, dst)
        free = self._link_free.get(link, 0.0)
        if free > at:
            at = free
        self._link_free[link] = at
        heapq.heappush(self._queue, (at, next(self._seq), self._arrive, (dst, handle)))

    def _arrive(self, dst: str, handle) -> None:
        if dst in self.dead:
            return
        cost = self.slow.get(dst) if self.slow else None
        if cost is not None:             # short of CPU: messages are served one at a time
            until, per = cost
            if self.now < until:
                start = max(self.now, self._busy_until.get(dst, 0.0))
                self._busy_until[dst] = start + per
                heapq.heappush(self._queue, (start + per, next(self._seq), self._serve,
                                             (dst, handle)))
                return
        self._serve(dst, handle)

    def _serve(self, dst: str, handle) -> None:
        if dst in self.dead:
            return
        if dst in self.hung or self.paused_until.get(dst, -1.0) > self.now:
            self._backlog.setdefault(dst, []).append(handle)
            if dst in self.hung and len(self._backlog[dst]) > 10_000:
                del self._backlog[dst][0]
            return
        handle()
        a = self._agent_of.get(dst)
        if a is not None:
            self._agent_poll(a)

    def _alive(self, name: str) -> bool:
        return name not in self.dead and name not in self.hung and \
            self.paused_until.get(name, -1.0) <= self.now

    # -- the world -------------------------------------------------------------------
    def _start_world(self) -> None:
        """The clock starts once monitor 1 foresees every single failure (bounded by
        ``Timing.monitor_prepare_s``), as ``up``'s world waits for the live monitor's
        token (:func:`agent.monitor.process.foresee_single_failures`)."""
        from agent.monitor.gain_worker import unforeseen_single_failures

        m = self.monitors.get(1)
        if m is not None and self._planned is None:
            self._planned = _GainDesigns.plan(m.core.roster)
        if (m is not None and self.now < self.config.start_s + TIMING.monitor_prepare_s
                and unforeseen_single_failures(m.gains, self._planned)):
            self.after(self.config.tick_s, self._start_world)
            return
        # the run's end counts from the clock's start, however long the monitor prepared
        self._end_at = self.now + (self._steps + 20) * self.config.step_s + 2.0
        self._world_step()

    def _world_step(self) -> None:
        w = self.world
        k = w.step
        self._record("world", self._keys["truth"], wire.encode_truth(k, w.x))
        shared = _Shared(wire.encode_sensors(k, w.x), self._schemas["sensors"])
        for a in self.agents:
            self._send("world", self._names[a], lambda a=a: self._on_sensors(a, shared))
        for f in [f for f in self.faults if f.step == k and f.kind not in SCRIPTED]:
            self._fault(f)
        if k < self._steps:
            w.advance()
            self.after(self.config.step_s, self._world_step)

    # -- the agents ------------------------------------------------------------------
    def _on_sensors(self, a: int, shared: _Shared) -> None:
        msg = shared.decode(self.stats)
        if msg is not None:
            self.agents[a].on_sensors(msg["step"], msg["x"], now=self.now)

    def _impair(self, src: int, dst: int, **params) -> None:
        """An impairment change of link ``src -> dst`` (0: the world's), published by
        ``up`` (the operator) to every agent, as ``up --fault`` does."""
        payload = encode_impairment("set", src, dst, **params)
        for a in self.agents:
            self._send("up", f"agent-{a}", lambda a=a: self._on_impairment(a, payload))

    def _on_impairment(self, a: int, payload: bytes) -> None:
        if self.agents[a].on_impairment(decode_impairment(payload)):
            self._agent_status(a)

    def _on_est(self, a: int, shared: _Shared) -> None:
        msg = shared.decode(self.stats)
        if msg is not None:
            self.agents[a].on_estimate(msg["agent"], msg["step"], msg["x"], self.now)

    def _on_ctl(self, a: int, payload: bytes) -> None:
        msg = try_decode(payload, self._schemas["ctl"], self.stats)
        if msg is None:
            return
        try:
            self.agents[a].on_assignment(msg)
        except AssignmentError:
            pass
        self._agent_status(a)

    def _on_roster(self, a: int, shared: _Shared) -> None:
        msg = shared.decode(self.stats)
        if msg is not None and self.agents[a].on_roster(msg):
            self._agent_status(a)

    def _agent_poll(self, a: int) -> None:
        name = self._names[a]
        if not self._alive(name):
            return
        core = self.agents[a]
        crash_at = self._crash_at.get(a)
        for step, x, epoch in core.poll(self.now):
            payload = wire.encode_est(a, step, x, epoch, self.now)
            shared = _Shared(payload, self._schemas["est"])
            self._record(name, self._keys["est", a], payload, shared)
            for b in self.agents:
                if b != a:
                    self._send(name, self._names[b],
                               lambda b=b, shared=shared: self._on_est(b, shared))
            for m in self.monitors.values():    # the monitor's own observation: the key
                self._send(name, m.name, lambda m=m, a=a: m.core.on_estimate_seen(a, self.now))
            if crash_at is not None and step >= crash_at - 1 and core.active:
                break
        if crash_at is not None and core.step >= crash_at - 1:
            self._agent_status(a)                # the scripted crash's last status
            self._crash(a, crash_at)
            return
        wake = core.next_wakeup(self.now)
        if wake is not None and wake > self.now and self._wake_at.get(a, math.inf) > wake:
            self._wake_at[a] = wake
            heapq.heappush(self._queue, (wake, next(self._seq), self._woken, (a, wake)))

    def _woken(self, a: int, at: float) -> None:
        if self._wake_at.get(a) == at:
            del self._wake_at[a]
        self._agent_poll(a)

    def _agent_status(self, a: int) -> None:
        name = self._names[a]
        if not self._alive(name):
            return
        st = self.agents[a].status()
        st.update(malformed=0, malformed_reasons={}, overflows=0)
        payload = wire.encode_status(st)
        shared = _Shared(payload, wire.STATUS_SCHEMA)
        for m in self.monitors.values():
            self._send(name, m.name, lambda m=m: self._on_status(m, shared))
        self._record(name, self._keys["status", a], payload)

    def _status_loop(self, a: int) -> None:
        if f"agent-{a}" in self.dead:
            return
        self._agent_status(a)
        self.after(self.config.status_s, lambda: self._status_loop(a))

    # -- liveliness and faults ---------------------------------------------------------
    def _token(self, a: int, alive: bool) -> None:
        """Agent ``a``'s token went (or came back): every other process learns it."""
        (self._token_gone.discard if alive else self._token_gone.add)(a)
        for m in self.monitors.values():
            if self._alive(m.name):
                m.core.on_liveliness("agent", a, alive, self.now)
        for b, core in self.agents.items():
            if b != a:
                core.set_alive(a, alive)
        if not alive:
            self.rec.events.append({"process": f"agent-{a}", "liveliness": False,
                                    "step": self.world.step, "t": self.now})

    def _crash(self, a: int, step: int) -> None:
        name = f"agent-{a}"
        self.dead.add(name)
        self.rec.events.append({"process": name, "exit_status": -9, "step": self.world.step,
                                "t": self.now})
        # the kernel closes a killed process's sockets: its peers see its links (and its
        # token) go at once; the lease matters only for a stopped process
        self.after(2 * self.config.latency_s, lambda: self._token(a, False))

    def _fault(self, f) -> None:
        if f.kind in MONITOR_FAULTS:
            self._monitor_fault(f)
            return
        name = f"agent-{f.agent}"
        lease = self.config.lease_s
        if f.kind == "kill":
            if name not in self.dead:
                self._crash(f.agent, f.step)
        elif f.kind in ("sensor", "partition", "delay", "drop"):
            self._impairment(f, True)
            self.after(f.seconds, lambda: self._impairment(f, False))
        elif f.kind == "slow":
            self.slow[name] = (self.now + f.seconds, f.value / 1000.0)
            self.rec.events.append({"process": name, "slow_ms": f.value, "step": f.step,
                                    "t": self.now})
        elif f.kind == "hang":
            self.hung.add(name)
            self.rec.events.append({"process": name, "signal": "SIGUSR1", "step": f.step, "t": self.now})
        else:
            self.paused_until[name] = self.now + f.seconds
            self.rec.events.append({"process": name, "signal": "SIGSTOP", "step": f.step, "t": self.now})
            if f.seconds > lease:
                self.after(lease, lambda: self._token(f.agent, False))
            self.after(f.seconds, lambda: self._resume(f.agent, f.seconds > lease))

    def _impairment(self, f, on: bool) -> None:
        """Impairment faults as ``up`` injects them (agent.run.local): ``sensor`` cuts the
        world's link into the agent, ``partition`` every link out of it, ``delay`` and
        ``drop`` impair every link into it; at the end the scenario's delays come back."""
        a, M = f.agent, self.M
        others = [b for b in range(1, M + 1) if b != a]
        name = f"agent-{a}"
        if f.kind == "sensor":
            self._impair(0, a, partition=on)
            what = "sensor cut" if on else "sensor restored"
        elif f.kind == "partition":
            for b in others:
                self._impair(a, b, partition=on)
            what = "partition" if on else "healed"
        elif on:
            for b in others:
                self._impair(b, a, **({"delay_steps": int(f.value)} if f.kind == "delay"
                                      else {"drop": float(f.value)}))
            what = f"{f.kind} {f.value:g}"
        else:
            from design.roster import link_delay_table

            table = link_delay_table(self.s, self.delays)
            for b in others:
                self._impair(b, a, delay_steps=int(table[a - 1, b - 1]), drop=0.0)
            what = "restored"
        self.rec.events.append({"process": name, "impair": what, "step": self.world.step,
                                "t": self.now})

    def _resume(self, a: int, token_lapsed: bool) -> None:
        name = f"agent-{a}"
        if name in self.dead:
            return
        self.rec.events.append({"process": name, "signal": "SIGCONT",
                                "step": self.world.step, "t": self.now})
        if token_lapsed:
            self._token(a, True)
        for handle in self._backlog.pop(name, []):
            handle()
        self._agent_poll(a)
        self._agent_status(a)

    # -- the monitors ------------------------------------------------------------------
    def _start_monitor(self, monitor_id: int, listen_s: float) -> None:
        """A monitor process (a fresh one when restarted): its core, its gain worker and
        its seat (:class:`MonitorSeat`: which monitor acts, what it adopts)."""
        m = _SimMonitor(self, monitor_id, listen_s)
        self.monitors[monitor_id] = m
        self.dead.discard(m.name)
        m.core.on_liveliness("world", "1", True, self.now)
        for a in self.agents:
            alive = f"agent-{a}" not in self.dead and a not in self._token_gone
            m.core.on_liveliness("agent", a, alive, self.now)
        self._monitor_token(monitor_id, True)
        self.after(0.0, lambda: self._monitor_tick(m))

    def _monitor_token(self, monitor_id: int, alive: bool) -> None:
        (self.monitors_alive.add if alive else self.monitors_alive.discard)(monitor_id)
        self.recorder.on_monitor_liveliness(str(monitor_id), alive)

    def _on_status(self, m, shared: _Shared) -> None:
        msg = shared.decode(self.stats)
        if msg is not None:
            m.core.on_status(msg, self.now, sender=msg["agent"])

    def _on_monitor_roster(self, m, shared: _Shared) -> None:
        msg = shared.decode(self.stats)
        if msg is not None:
            m.seat.on_roster(msg)

    def _publish(self, src, msg) -> None:
        if isinstance(msg, Assignment):
            payload = msg.encode()
            self._record(src.name, topics.ctl_key(self.run_id, msg.agent), payload)
            self._send(src.name, f"agent-{msg.agent}",
                       lambda a=msg.agent: self._on_ctl(a, payload))
        elif isinstance(msg, RosterUpdate):
            self._roster_out(src, msg)

    def _roster_out(self, src, msg) -> None:
        payload = wire.encode_roster(msg.epoch, msg.activate_at, msg.ids,
                                     probation=msg.probation, barred=msg.barred)
        self._record(src.name, topics.ctl_key(self.run_id, 0), payload)
        shared = _Shared(payload, self._schemas["roster"])
        for a in self.agents:
            self._send(src.name, f"agent-{a}", lambda a=a: self._on_roster(a, shared))
        for other in self.monitors.values():
            if other is not src:
                self._send(src.name, other.name,
                           lambda o=other: self._on_monitor_roster(o, shared))
        src.roster_at = self.now + self.config.roster_s

    def _monitor_event(self, src, kind: str, fields: dict) -> None:
        self._record(src.name, topics.monitor_events_key(self.run_id),
                     wire.encode_monitor_event({"kind": kind, "t": self.now, **fields}))

    def _monitor_tick(self, m) -> None:
        if self.monitors.get(m.id) is not m or m.name in self.dead:
            return                                   # killed (perhaps started again)
        if self.now < self._end_at:
            self.after(self.config.tick_s, lambda: self._monitor_tick(m))
        if not self._alive(m.name):
            return                                   # stopped: its ticks resume after
        for roster, G, info in m.designs.poll():
            m.gains.put(roster, G, info)
        state = m.seat.decide(self.now, [(i, self.monitors[i].session)
                                         for i in self.monitors_alive])
        for kind, fields in m.seat.records:
            self._monitor_event(m, kind, fields)
        m.seat.records.clear()
        m.seat.lines.clear()
        if m.seat.precompute:
            m.seat.precompute = False
            if self.config.precompute:
                m.designs.precompute(m.core.roster, m.core.G)
        if m.seat.stand_down:
            m.seat.stand_down = False
            m.designs.stand_down()
        if state != "act":
            m.core.events.clear()
            return
        for msg in m.core.tick(self.now):
            self._publish(m, msg)
        m.core.events.clear()
        for kind, fields in m.core.new_records():
            self._monitor_event(m, kind, fields)
            if kind == "reassign" and self.config.precompute:
                m.designs.precompute(m.core.roster, m.core.G)
        if self.now >= m.roster_at:
            roster = m.core.roster_message
            if roster is not None:
                self._roster_out(m, roster)

    def _monitor_fault(self, f) -> None:
        """``monitor``: the acting monitor killed and started again at once (as ``up``
        does); ``monitorstop``: it is stopped ``seconds``; ``monitorsgone``: every one
        killed for good."""
        acting = min(self.monitors_alive, default=None)
        if f.kind == "monitorsgone":
            targets = list(self.monitors_alive)
        else:
            targets = [] if acting is None else [acting]
        for monitor_id in targets:
            m = self.monitors[monitor_id]
            if f.kind == "monitorstop":
                self.paused_until[m.name] = self.now + f.seconds
                self.rec.events.append({"process": self._life(m), "signal": "SIGSTOP",
                                        "step": f.step, "t": self.now})
                if f.seconds > self.config.lease_s:
                    self.after(self.config.lease_s,
                               lambda i=monitor_id: self._monitor_token(i, False))
                self.after(f.seconds, lambda m=m: self._monitor_resume(m))
                continue
            self.dead.add(m.name)
            self.rec.events.append({"process": self._life(m), "signal": "SIGKILL",
                                    "step": f.step, "t": self.now})
            self._monitor_token(monitor_id, False)
            if f.kind == "monitor":
                self._restarts[monitor_id] = self._restarts.get(monitor_id, 0) + 1
                self.rec.events.append({"process": monitor_name(monitor_id,
                                                                self._restarts[monitor_id]),
                                        "started": True, "step": f.step, "t": self.now})
                self.after(self.config.restart_s,
                           lambda i=monitor_id: self._start_monitor(i, self.config.listen_s))

    def _life(self, m) -> str:
        """The process name of monitor ``m``'s current life, as a live run names it."""
        return monitor_name(m.id, self._restarts.get(m.id, 0))

    def _monitor_resume(self, m) -> None:
        if m.name in self.dead or self.monitors.get(m.id) is not m:
            return
        self.rec.events.append({"process": self._life(m), "signal": "SIGCONT",
                                "step": self.world.step, "t": self.now})
        self._monitor_token(m.id, True)
        for handle in self._backlog.pop(m.name, []):
            handle()

    # -- the run -------------------------------------------------------------------------
    def run(self, steps: int) -> SimResult:
        """Run ``steps`` steps of the world (and the agents until they computed them)."""
        from agent.run.local import RunConfig
        from agent.run.summary import predicted_mse, summarize

        c = self.config
        self._steps = int(steps)
        self._end_at = math.inf            # set when the world's clock starts
        for monitor_id in range(1, c.monitors + 1):
            # the first acts at once (the run's start: nothing to adopt), the others stand by
            self._start_monitor(monitor_id, 0.0 if monitor_id == 1 else c.listen_s)
        for a in self.agents:
            self.after(0.01 * a / self.M, lambda a=a: self._status_loop(a))
        self.after(c.start_s, self._start_world)
        while self._queue:
            t, _, fn, args = heapq.heappop(self._queue)
            if t > self._end_at:
                break
            self.now = t
            fn(*args)
        key = _configuration_key(self.s, self.G, self.delays)
        if key not in _PREDICTED:
            _PREDICTED[key] = predicted_mse(self.s, self.G, self.delays)
        rho, predicted = _PREDICTED[key]
        config = RunConfig(scenario=self.s, scenario_arg=self.s.name, G=self.G,
                           gains_path=None, delays=self.delays, delays_spec="sim",
                           steps=self._steps, seed=self.seed, step_ms=1e3 * c.step_s,
                           deadline_ms=None, out=None, monitor=True, drop=0.0,
                           run_id=self.rec.run_id, faults=tuple(self.faults),
                           hang_timeout=self.monitor_config.hang_timeout_s)
        summary, steps_done, mse = summarize(config, self.rec, rho, predicted)
        return SimResult(self.rec, summary, steps_done, mse, self.monitors, config)


def run_schedules(scenario, G, delays, seeds, steps: int, kinds, rate: float,
                  config: SimConfig | None = None, progress=None) -> dict:
    """Chaos under simulated time: for each seed, a schedule drawn by
    :func:`agent.run.chaos.draw_schedule`, run by :class:`SimRuntime` and checked by
    :func:`agent.run.chaos.check_invariants`. Returns the report (``report_lines`` prints it):
    runs and CPU seconds, faults by kind, verdicts by cause, detection steps after stop,
    hang, kill and lie faults and switch steps after the verdicts (median, min, max), the
    residual alerts by what they name, and every violation with its seed.
    ``progress(seed, violations)`` is called after each run."""
    import time
    from collections import Counter

    from agent.run.chaos import draw_schedule

    faults, verdicts, broken, runs_s = Counter(), Counter(), [], []
    detection = {k: [] for k in ("kill", "hang", "stop", "lie")}
    alerts = Counter()           # residual alerts: on an agent that lies or is biased, or not
    switch = []
    for seed in seeds:
        schedule = draw_schedule(scenario, seed, steps, kinds=kinds, rate=rate)
        t = time.process_time()
        result = SimRuntime(scenario, G, delays, seed=seed, faults=schedule,
                            config=config).run(steps)
        runs_s.append(time.process_time() - t)
        faults.update(f.kind for f in schedule)
        found = result.violations()
        broken += [{"seed": seed, **v.to_dict()} for v in found]
        for f in result.summary.get("failures", []):
            verdicts[f.get("cause")] += 1
            if f.get("detected_step") is None:
                continue
            fault = max((g for g in schedule if g.agent == f["agent"]
                         and g.step <= f["detected_step"] + 5), key=lambda g: g.step,
                        default=None)
            if fault is not None and fault.kind in detection:
                # a verdict's step is the newest the run had reported then: a kill at
                # step S convicted before anyone reported step S is 0 steps late, not -1
                detection[fault.kind].append(max(0, f["detected_step"] - fault.step))
            if f.get("activate_at") is not None:
                switch.append(f["activate_at"] - f["detected_step"])
        for alert in result.summary.get("residual_alerts", []):
            on = {g.kind for g in schedule if g.agent == alert["agent"]
                  and g.step <= alert["step"] and g.kind in WRONG_KINDS}
            alerts[f"{alert['fault']} on an agent that "
                   + ("lies" if "lie" in on else "is biased" if on else "does neither")] += 1
        if progress is not None:
            progress(seed, found)

    def spread(values):
        return [float(np.median(values)), min(values), max(values)] if values else None

    return {"scenario": scenario.name, "seeds": [min(seeds), max(seeds) + 1], "steps": steps,
            "kinds": list(kinds), "rate": rate, "runs": len(runs_s),
            "cpu_s": float(np.sum(runs_s)), "cpu_s_median": float(np.median(runs_s)),
            "faults": dict(faults), "verdicts": dict(verdicts),
            "detection_steps": {k: spread(v) for k, v in detection.items() if v},
            "switch_steps": spread(switch), "residual_alerts": dict(alerts),
            "violations": broken}


def report_lines(report: dict) -> list:
    """The lines of a :func:`run_schedules` report, for terminals."""
    lines = [f"{report['runs']} schedules of {report['steps']} steps, {report['cpu_s']:.1f} s "
             f"of CPU ({report['cpu_s_median']:.2f} s a run, median)",
             f"faults injected: {report['faults']}; verdicts: {report['verdicts']}"]
    for kind, (median, low, high) in report["detection_steps"].items():
        lines.append(f"  {kind}: detected {median:.0f} steps after the fault (median), "
                     f"{low} to {high}")
    if report["switch_steps"]:
        median, low, high = report["switch_steps"]
        lines.append(f"  roles in force {median:.0f} steps after the verdict (median), "
                     f"{low} to {high}")
    if report.get("residual_alerts"):
        lines.append(f"residual alerts (not convictions): {report['residual_alerts']}")
    broken = report["violations"]
    lines.append(f"violations: {len(broken)}, in {len({v['seed'] for v in broken})} of "
                 f"{report['runs']} runs")
    lines += [f"  seed {v['seed']}: {v['invariant']} at step {v['step']}: {v['evidence']}"
              for v in broken[:30]]
    return lines


def simulated_chaos(args, seeds) -> dict:
    """``socmon chaos --simulated A:B``: the schedules of ``seeds`` under simulated time
    (:func:`agent.run.simulated.run_schedules`), one report."""
    from design.errors import ScenarioError
    from design.scenario import resolve_delays

    from agent.run.chaos import check_schedule_flags
    from agent.run.inputs import InputError, gains_for, load_scenario_arg

    check_schedule_flags(args)
    kinds = tuple(k.strip() for k in args.faults.split(",") if k.strip())
    bad = [k for k in kinds if k not in FAULT_KINDS or k == "crash"]
    if bad or not kinds:
        raise InputError(f"--faults: {bad} cannot be simulated (simulated: "
                           f"{', '.join(k for k in FAULT_KINDS if k != 'crash')})"
                           if bad else "--faults: give at least one kind")
    scenario = load_scenario_arg(args.scenario)
    try:
        delays = resolve_delays(scenario, args.delays)
    except ScenarioError as exc:
        raise InputError(str(exc)) from None
    G = gains_for(scenario, args.gains, delays, args.force_gains)
    report = run_schedules(scenario, G, delays, seeds, args.duration, kinds, args.rate)
    return {**report, "delays": delays, "scenario_name": scenario.name, "kinds": kinds}
