"""A whole live run on this machine: its configuration, its processes, its faults, its record.

:class:`RunConfig` is everything a run is (frozen, checked by the command that builds
it); :class:`LocalRun` starts the world, one process per agent and the monitor (each in
its own process group, :class:`agent.run.launcher.Children`), joins the mesh as the
recorder (:class:`agent.run.recorder.Recorder`, which ``socmon watch`` uses too), injects
the scheduled :class:`Fault` s at their steps, and returns a :class:`Recording`;
:func:`agent.run.summary.summarize` turns that into the summary. ``socmon up`` and
``socmon chaos`` are both this.

The run folder gets ``manifest.json`` (what every child checks: the scenario's digest,
the gains file's digest, delays, seed; see :mod:`agent.protocol.manifest`) before the children
start, and ``run.json`` (:mod:`agent.run.folder`: run id, every process's endpoint and
PID, keys) once they are up, so that other tools can attach (``--attach RUN_DIR``).
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import random
import signal
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from agent.protocol import topics
from broker_free_net.config import NetConfig
from broker_free_net.impair import encode_impairment

from broker_free_net.ports import listen_port

from agent.run.folder import MESH_CONFIG, monitor_name
from agent.run.launcher import Children
from agent.testbed.netns import host_names, host_of
from agent.run.recorder import MonitorTokens, Recorder, Recording
from agent.protocol.timing import DEFAULT as TIMING
from agent.run.fault_kinds import (FAULT_KINDS, PROCESS_FAULTS, ROLE_FAULTS,  # noqa: F401
                                   SCRIPTED_FAULTS, WRONG_KINDS)

__all__ = ["Fault", "RunConfig", "Recording", "LocalRun", "RunFailed", "FAULT_KINDS",
           "PROCESS_FAULTS", "live_view"]



@dataclass(frozen=True, order=True)
class Fault:
    step: int
    kind: str
    agent: int = 0
    seconds: float = 0.0
    value: float = 0.0

    def to_dict(self) -> dict:
        return {"step": self.step, "kind": self.kind, "agent": self.agent,
                "seconds": self.seconds, "value": self.value}

    def describe(self) -> str:
        """What a scheduled fault does, for the progress lines.

        >>> Fault(500, "monitor").describe()
        'monitor killed (SIGKILL), started again'
        >>> Fault(300, "delay", 2, 5.0, 3.0).describe()
        'links into agent 2 delayed by 3 steps for 5 s'
        """
        what = {
            "crash": "agent {a} crashes (scripted)",
            "kill": "agent {a} killed (SIGKILL)",
            "hang": "agent {a} loop hung (SIGUSR1)",
            "stop": "agent {a} stopped (SIGSTOP)",
            "sensor": "agent {a} sensor readings cut",
            "monitor": "monitor killed (SIGKILL), started again",
            "partition": "agent {a} partitioned (its outgoing links cut)",
            "delay": "links into agent {a} delayed by {v:g} steps",
            "drop": "links into agent {a} drop a fraction {v:g}",
            "linkdown": "agent {a} host link down",
            "worldstop": "world stopped (SIGSTOP)",
            "monitorstop": "monitor stopped (SIGSTOP)",
            "monitorsgone": "every monitor killed (SIGKILL), none started again",
            "lie": "agent {a} publishes its estimates {v:g} noise std-devs off (scripted)",
            "bias": "agent {a}'s readings biased by {v:g} noise std-devs (scripted)",
            "drift": "agent {a}'s readings drift by {v:g} noise std-devs each 100 steps "
                     "(scripted)",
            "noise": "agent {a}'s sensor noise {v:g} times its model (scripted)",
        }.get(self.kind, self.kind + " agent {a}").format(a=self.agent, v=self.value)
        return what + (f" for {self.seconds:g} s" if self.seconds else "")

    def standby_note(self, agents: int) -> str | None:
        """What to tell of a lie or a sensor fault aimed at a standby of a run whose agents
        1..``agents`` hold the roles at the start (it acts only once the standby holds
        one); None for any other fault.

        >>> print(Fault(150, "lie", 4, 0.0, 3.0).standby_note(3))
        agent 4 is a standby (no role at the start): it lies only once it holds a role, from the later of step 150 and the first step it computes in one (never, if it takes none)
        >>> Fault(150, "lie", 3, 0.0, 3.0).standby_note(3) is None
        True
        """
        if self.kind not in ROLE_FAULTS or self.agent <= agents:
            return None
        what = "it lies" if self.kind == "lie" else \
            f"its sensor fault ({self.kind}) acts"
        return (f"agent {self.agent} is a standby (no role at the start): {what} only once "
                f"it holds a role, from the later of step {self.step} and the first step it "
                "computes in one (never, if it takes none)")


@dataclass(frozen=True, eq=False)
class RunConfig:
    """Everything a local run is; built and checked by the command line."""

    scenario: object
    scenario_arg: str
    G: list
    gains_path: Path
    delays: np.ndarray
    delays_spec: str
    steps: int
    seed: int
    step_ms: float
    deadline_ms: float
    out: Path
    monitor: bool = True
    #: monitors started (ids 1..monitors; the smallest live id acts, the others stand by
    #: and take over when it dies or is paused past the link lease)
    monitors: int = 2
    #: the monitors precompute the gains of the foreseen failures (False: ``--no-precompute``)
    precompute: bool = True
    hang_timeout: float = TIMING.hang_timeout_s
    hang_timeout_max: float = TIMING.hang_timeout_max_s
    drop: float = 0.0
    faults: tuple = ()
    start_timeout: float = TIMING.start_timeout_s
    secure: bool = False
    #: an :class:`agent.testbed.netns.Testbed` (made and removed by the caller) with the hosts of
    #: :func:`agent.testbed.netns.host_names`: each process, the recorder included, on its own host
    testbed: object = None
    run_id: str | None = None        # default: a fresh id
    #: the endpoint every process and attached tool connects to: the recorder's, or the
    #: router's under ``router``
    listen: str | None = None
    #: one ``socmon router`` process; every other process is its client (no peer mesh)
    router: bool = False
    #: the recorder keeps the states of every k-th step (and the last) only (``--record-every``)
    record_every: int = 1

    @property
    def M(self) -> int:
        return self.scenario.N + self.scenario.standby

    @property
    def abort_on_exit(self) -> bool:
        """Without a monitor or scripted faults a dead process ends the run."""
        return not self.monitor and not self.faults


class RunFailed(Exception):
    pass


#: The link lease of the launcher's own session (the recorder): its peers tolerate this
#: long a silence of it. The recorder decodes every estimate of the run and is the busiest
#: Python loop of a loaded host; with the processes' 1 s lease its links lapsed beside
#: two busy loops and it lost 73 steps of the record (and saw every monitor token go)
#: while the run itself went on. Nobody's failure detection reads its token.
RECORDER_LEASE_MS = 5000

#: What a run started here shows of itself as it goes (:func:`live_view`).
_LIVE = contextvars.ContextVar("socmon_live_view", default=None)


@contextlib.contextmanager
def live_view(factory):
    """Within it, a :class:`LocalRun` shows itself through ``factory(config, run_id,
    say)``, called once its recorder is up: an :class:`agent.run.web.LiveState` (``up``'s
    MSE in its progress line, a line per verdict and reassignment, and the page of
    ``--web``; :func:`agent.run.web.live_state_factory`). Without, the progress line is
    the step, drops and late."""
    token = _LIVE.set(factory)
    try:
        yield
    finally:
        _LIVE.reset(token)


class LocalRun:
    """Start, fault, record and stop one run; :meth:`run` returns a :class:`Recording`."""

    def __init__(self, config: RunConfig, say=lambda text: None):
        self.config = config
        self.say = say

    # -- argv of the children ----------------------------------------------------------
    def _argv(self, rec, ep):
        c = self.config
        common = ["--run", rec.run_id, "--connect", ep[0], "--seed", str(c.seed),
                  "--manifest", str((c.out / "manifest.json").resolve()),
                  "--zenoh-config", str((c.out / MESH_CONFIG).resolve())]
        if c.secure:
            common += ["--keys", str((c.out / "keys").resolve())]
        crash_at = {f.agent: f.step for f in c.faults if f.kind == "crash"}
        lie = {f.agent: f for f in c.faults if f.kind == "lie"}
        from design.simulate import SENSOR_FAULT_KINDS
        out = {"world": ["world", c.scenario_arg, *common, "--listen", ep[1],
                         "--steps", str(c.steps), "--step-ms", str(c.step_ms),
                         "--start-timeout", str(c.start_timeout)]
                         + (["--wait-monitor", "1"] if c.monitor else [])}
        for a in range(1, c.M + 1):
            argv = ["agent", c.scenario_arg, "--id", str(a), *common, "--listen", ep[a + 1],
                    *_connect_to(ep[1:a + 1]), "--delays", c.delays_spec,
                    "--deadline-ms", str(c.deadline_ms)]
            if a <= c.scenario.N:
                argv += ["--gains", str(c.gains_path)]
            if c.drop:
                argv += ["--drop", repr(c.drop)]
            if a in crash_at:
                argv += ["--crash-at", str(crash_at[a])]
            if a in lie:
                argv += ["--lie", f"{lie[a].step}:{lie[a].value!r}"]
            for f in c.faults:
                if f.agent == a and f.kind in SENSOR_FAULT_KINDS:
                    argv += ["--sensor-fault", f"{f.kind}:{f.step}:{f.value!r}"]
            out[f"agent-{a}"] = argv
        out["monitor"] = ["monitor", c.scenario_arg, *common, "--listen", ep[c.M + 2],
                          *_connect_to(ep[1:c.M + 2]),
                          "--gains", str(c.gains_path), "--delays", c.delays_spec,
                          "--hang-timeout", str(c.hang_timeout),
                          "--hang-timeout-max", str(c.hang_timeout_max), "--step-ms", str(c.step_ms),
                          "--events", str((c.out / "events.jsonl").resolve()),
                          "--control-key", str((c.out / "control.key").resolve())]
        if not c.precompute:
            out["monitor"].append("--no-precompute")
        return out

    # -- the run -------------------------------------------------------------------------
    def run(self) -> Recording:
        if self.config.testbed is None:
            return self._run()
        with self.config.testbed.inside("recorder"):     # the recorder's peer is there
            return self._run()

    def _host_ip(self, process):
        tb = self.config.testbed
        return "127.0.0.1" if tb is None else tb.ip(host_of(process))

    def _wrap(self, process):
        tb = self.config.testbed
        return () if tb is None else tb.exec_prefix(host_of(process))

    def _run(self) -> Recording:
        from agent.protocol.manifest import write_manifest

        c = self.config
        K, N, M = c.steps, c.scenario.N, c.M
        from agent.protocol.control_auth import ControlSigner
        from design.plausibility import StateScale

        signer = ControlSigner.generate()       # the run's control key: the monitor's
        # the recorder keeps only the rosters and assignments this key signed
        recorder = Recorder(c.run_id or f"up{os.getpid()}x{random.randrange(10**6)}",
                            c.scenario.n, N, M,
                            ports=[listen_port() for _ in range(
                                M + 3 + c.router + max(c.monitors - 1, 0))],
                            control_public=signer.public_bytes(),
                            record_every=c.record_every, last_step=K,
                            scale=StateScale(c.scenario.A, c.scenario.process_noise,
                                             c.scenario.measurement_noise))
        rec = recorder.recording
        scheme = "tls" if c.secure else "tcp"
        # ep[M + 3]: the router's (a routed run's), on its own host with --netns
        ep = [f"{scheme}/{self._host_ip(name)}:{p}"
              for name, p in zip(host_names(M, c.router), rec.ports)]
        # standby monitors: on the monitor's host, after the router's endpoint
        standby_ep = [f"{scheme}/{self._host_ip('monitor')}:{p}"
                      for p in rec.ports[M + 3 + c.router:]]
        if c.listen:         # the run's entry: the router's under --router, else the recorder's
            ep[M + 3 if c.router else 0] = c.listen
        net_extra = {}
        if c.secure:
            from agent.protocol.topics import make_run_keys, run_identities

            make_run_keys(c.out / "keys", rec.run_id, run_identities(M), c.scenario)
            net_extra = {"keys": str((c.out / "keys").resolve()), "identity": "recorder"}
        operator = ControlSigner.generate()     # the operator's (impairments): this run's
        for name, key in (("control.key", signer), ("operator.key", operator)):
            key_path = c.out / name
            key_path.touch(mode=0o600)
            key_path.write_bytes(key.private_bytes())
        write_manifest(c.out / "manifest.json", c.scenario, c.gains_path, c.seed,
                       c.delays_spec, c.delays, rec.run_id, signer.public_bytes(),
                       operator.public_bytes())
        children = rec.children = Children(c.out / "logs")
        mesh_config = _write_mesh_config(c.out)
        argv = self._argv(rec, ep)
        router_ep = ep[M + 3] if c.router else None
        if c.router:
            argv = {name: _through_router(a, router_ep) for name, a in argv.items()}
            net_extra = {"mode": "client", "connect": (router_ep,)}
        pending = sorted(c.faults)
        undo = []                      # (time, action) of faults that end after seconds
        restarts = 0

        def on_term(*_):
            raise KeyboardInterrupt

        old_term = signal.signal(signal.SIGTERM, on_term)
        # Ctrl-C must stop the run even when SIGINT was inherited as ignored (a background
        # job of a non-interactive shell starts that way, and Python keeps an inherited
        # SIG_IGN)
        old_int = signal.signal(signal.SIGINT, signal.default_int_handler)
        t_begin = time.monotonic()
        live = None
        absence_said = False           # up has said no monitor is alive (and not since back)
        try:
            if c.router:        # up before its clients, which try it for 10 s only
                children.start("router", ["router", "--listen", router_ep],
                               self._wrap("router"))
                _wait_listening(children, "router", c.start_timeout)
            with topics.open_peer(NetConfig(run=rec.run_id, lease_ms=RECORDER_LEASE_MS,
                                            zenoh_config=str(mesh_config),
                                            **{"listen": (ep[0],), **net_extra}),
                                  "recorder", 0) as peer:
                recorder.subscribe(peer)
                alive_watch = peer.watch_liveliness()
                tokens = MonitorTokens(recorder)
                impair_key = topics.impair_key(rec.run_id)
                peer.publisher(impair_key, block=True)
                children.start("world", argv["world"], self._wrap("world"))
                for a in range(1, M + 1):
                    children.start(f"agent-{a}", argv[f"agent-{a}"], self._wrap(f"agent-{a}"))
                if c.monitor:
                    children.start(monitor_name(1), argv["monitor"], self._wrap("monitor"))
                    for i, sep in enumerate(standby_ep, start=2):
                        children.start(monitor_name(i), _standby_monitor(
                            argv["monitor"], i, sep,
                            () if c.router else [ep[M + 2], *standby_ep[:i - 2]]),
                                       self._wrap("monitor"))
                self._write_run_json(rec, ep)
                self.say(f"run {rec.run_id} at {self._entry(ep)} (socmon watch or inject "
                         f"--attach {c.out}"
                         + (f"; SECURED: mutual TLS and access control on every process, keys "
                            f"in {c.out / 'keys'}" if c.secure else "") + "): "
                         f"world + {N} agents + {c.scenario.standby} standby"
                         + (f" + {c.monitors} monitors (1 active, {c.monitors - 1} standing "
                            "by)" if c.monitor and c.monitors > 1
                            else " + monitor" if c.monitor else "")
                         + " started; waiting for all to be "
                         f"ready (clock starts then), {K} steps of {c.step_ms:g} ms")

                drain = recorder.drain
                # up's progress words and verdict lines, and its --web page (live_view)
                live = _LIVE.get()(c, rec.run_id, self.say) if _LIVE.get() else None

                def event(**fields):
                    rec.events.append({**fields, "t": time.time()})

                def impair(src, dst, **params):
                    peer.put(impair_key, encode_impairment(
                        "set", src, dst, sign=lambda m: operator.sign(m, rec.run_id), **params))

                def impair_links(agent, outgoing, **params):
                    """Every link out of (``outgoing``) or into ``agent``."""
                    for b in range(1, M + 1):
                        if b != agent:
                            impair(*((agent, b) if outgoing else (b, agent)), **params)

                def inject(f, k_now, now):
                    name = f"agent-{f.agent}"
                    if f.kind == "kill":
                        _signal(children, name, signal.SIGKILL)
                        event(process=name, signal="SIGKILL", step=k_now)
                    elif f.kind == "hang":
                        _signal(children, name, signal.SIGUSR1)
                        event(process=name, signal="SIGUSR1", step=k_now)
                    elif f.kind == "sensor":
                        impair(0, f.agent, partition=True)
                        event(process=name, impair="sensor cut", step=k_now)
                        undo.append((now + f.seconds, f))
                    elif f.kind == "stop":
                        _signal(children, name, signal.SIGSTOP)
                        event(process=name, signal="SIGSTOP", step=k_now)
                        undo.append((now + f.seconds, f))
                    elif f.kind in ("worldstop", "monitorstop"):
                        proc = "world" if f.kind == "worldstop" else monitor_name(1, restarts)
                        _signal(children, proc, signal.SIGSTOP)
                        event(process=proc, signal="SIGSTOP", step=k_now)
                        undo.append((now + f.seconds, f))
                    elif f.kind == "monitorsgone":
                        for ch in children.running():
                            if ch.name.startswith("monitor"):
                                _signal(children, ch.name, signal.SIGKILL)
                                event(process=ch.name, signal="SIGKILL", step=k_now)
                    elif f.kind == "monitor" and c.monitor:
                        _signal(children, monitor_name(1, restarts), signal.SIGKILL)
                        event(process=monitor_name(1, restarts), signal="SIGKILL", step=k_now)
                        undo.append((now, f))        # start it again at once
                    elif f.kind in ("partition", "delay", "drop"):
                        if f.kind == "partition":
                            impair_links(f.agent, True, partition=True)
                        elif f.kind == "delay":
                            impair_links(f.agent, False, delay_steps=int(f.value))
                        else:
                            impair_links(f.agent, False, drop=float(f.value))
                        event(process=name, step=k_now, impair=f.kind if f.kind == "partition"
                              else f"{f.kind} {f.value:g}")
                        undo.append((now + f.seconds, f))
                    elif f.kind == "linkdown":
                        c.testbed.set_link(name, up=False)
                        event(process=name, link="down", step=k_now)
                        undo.append((now + f.seconds, f))
                    self.say(f"step {k_now}: {f.describe()}")

                def end(f, k_now):
                    nonlocal restarts
                    name = f"agent-{f.agent}"
                    if f.kind == "stop":
                        _signal(children, name, signal.SIGCONT)
                        event(process=name, signal="SIGCONT", step=k_now)
                    elif f.kind in ("worldstop", "monitorstop"):
                        proc = "world" if f.kind == "worldstop" else monitor_name(1, restarts)
                        _signal(children, proc, signal.SIGCONT)
                        event(process=proc, signal="SIGCONT", step=k_now)
                    elif f.kind == "monitor":
                        old = monitor_name(1, restarts)
                        if not _wait_exit(children, old, 10.0):
                            raise RunFailed(f"{old} did not exit within 10 s of SIGKILL; "
                                            "not starting a second monitor beside it")
                        restarts += 1
                        # in a run in progress: joins at once (no wait for its precompute)
                        children.start(monitor_name(1, restarts),
                                       argv["monitor"] + ["--prepare-s", "0"],
                                       self._wrap("monitor"))
                        event(process=monitor_name(1, restarts), started=True, step=k_now)
                    elif f.kind == "sensor":
                        impair(0, f.agent, partition=False)
                        event(process=name, impair="sensor restored", step=k_now)
                    elif f.kind == "partition":
                        impair_links(f.agent, True, partition=False)
                        event(process=name, impair="healed", step=k_now)
                    elif f.kind == "linkdown":
                        c.testbed.set_link(name, up=True)
                        event(process=name, link="up", step=k_now)
                    elif f.kind in ("delay", "drop"):
                        from design.roster import link_delay_table

                        table = link_delay_table(c.scenario, c.delays)
                        for b in range(1, M + 1):
                            if b != f.agent:
                                impair(b, f.agent, delay_steps=int(table[f.agent - 1, b - 1]),
                                       drop=0.0)
                        event(process=name, impair="restored", step=k_now)

                world_end = None
                next_progress, disk_warned = time.monotonic() + 1.0, False
                end_of_run = EndOfRun(K)
                silence_said = False
                start_deadline = time.monotonic() + c.start_timeout + 30.0
                while True:
                    peer.wait(timeout=0.05)
                    drain()
                    for child in children.reap():
                        if child.name == "world" and child.returncode == 0 and \
                                recorder.step < 0:
                            # it ran its steps, this recorder heard none: nothing to report
                            raise RunFailed(
                                f"the world ran and ended (exit 0), but this command's "
                                f"recorder heard none of its steps: the processes did not "
                                f"reach it through {self._entry(ep)}; the world's log ends:\n"
                                f"{children.tail('world')}")
                        if child.name == "world" and child.returncode == 0:
                            world_end = time.monotonic()
                        elif child.name in ("world", "router") or (world_end is None
                                                                   and c.abort_on_exit) \
                                or recorder.step < 0:
                            # before the clock starts every child is needed: the world
                            # would wait its whole start timeout for this one
                            when = "the end of the run" if recorder.step >= 0 \
                                else "the clock started"
                            raise RunFailed(f"{child.name} exited with status "
                                            f"{child.returncode} before {when}; "
                                            f"its log ends:\n{children.tail(child.name)}")
                        elif world_end is None and child.name.startswith("agent-") and \
                                child.returncode == 1 and \
                                _world_silent_for(recorder) > TIMING.agent_world_gone_s:
                            # the agents leave a world silent for Timing.world_silent_s
                            silent = _world_silent_for(recorder)
                            rec.world_silent = {"step": recorder.step, "seconds": silent}
                            raise RunFailed(
                                f"the world went silent after step {recorder.step} and stayed "
                                f"so {silent:.0f} s (paused or cut off); {child.name} left it "
                                f"(Timing.world_silent_s = {TIMING.world_silent_s:g} s): the "
                                "run ends there")
                        elif world_end is None:
                            k_now = recorder.step
                            event(process=child.name, exit_status=child.returncode, step=k_now)
                            self.say(f"{child.name} exited with status {child.returncode} "
                                     f"at step {k_now}; the run goes on")
                    for ev in alive_watch.drain():
                        if ev.role == "monitor" and world_end is None and c.monitor:
                            tokens.on_token(ev.id, ev.any_alive)
                    in_view = alive_watch.alive()
                    if world_end is None:
                        tokens.settle(("world", "0") in in_view)
                    recorder.alive = {int(i) for r, i in in_view if r == "agent" and i.isdigit()}
                    # said from the clock's start on (before it no step is missed:
                    # summary._no_monitor_windows), also for a lapse that began before it
                    absent = rec.no_monitor_since is not None and world_end is None
                    if recorder.step >= 0 and absent != absence_said:
                        absence_said = absent
                        self.say(f"WARNING: no monitor alive at step {recorder.step}: a "
                                 "failure from now on is neither detected nor recovered"
                                 if absent else
                                 f"a monitor is alive again at step {recorder.step}")
                    if live is not None:
                        live.tick(recorder, None if live.board is None else recorder.alive)
                        for line in live.news():     # verdicts, reassignments, as heard
                            self.say(f"step {recorder.step}: {line}")
                    now = time.monotonic()
                    k_now = recorder.step
                    while pending and k_now >= pending[0].step:
                        f = pending.pop(0)
                        if f.kind not in SCRIPTED_FAULTS:
                            inject(f, k_now, now)
                    for item in sorted(u for u in undo if u[0] <= now):
                        undo.remove(item)
                        end(item[1], k_now)
                    if recorder.step < 0 and now > start_deadline:
                        raise RunFailed(f"the clock did not start within {c.start_timeout:g} s;"
                                        f" world log:\n{children.tail('world')}")
                    running = {ch.name for ch in children.running()}
                    in_force = set(rec.rosters[-1][1])
                    active = [a for a in range(1, M + 1) if f"agent-{a}" in running
                              and a in in_force and rec.status.get(a, {}).get("active", a <= N)]
                    done = K in rec.truth and all(K in rec.est[a] for a in active)
                    if done or (world_end is not None and now - world_end > TIMING.up_end_s):
                        break
                    if now >= next_progress and recorder.step >= 0:
                        next_progress = now + 1.0
                        silent = _world_silent_for(recorder)
                        if silent > TIMING.agent_world_gone_s and not silence_said:
                            silence_said = True
                            self.say(f"WARNING: the world has been silent since step "
                                     f"{recorder.step} ({silent:.0f} s): paused or cut off; "
                                     f"the agents wait up to {TIMING.world_silent_s:g} s")
                        elif silent < 1.0 and silence_said:
                            silence_said = False
                            self.say(f"the world is back at step {recorder.step}")
                        if c.out is not None and not disk_warned and _disk_full(c.out):
                            disk_warned = True
                            self.say(f"WARNING: the disk of {str(c.out)!r} is full at step "
                                     f"{k_now}: the processes' logs lose lines and the run "
                                     "folder may not be written at the end; the run goes on")
                        def progress():
                            st = rec.status.values()
                            if live is not None:
                                live.refresh(recorder)
                            return (f"step {k_now}/{K}  "
                                    + (f"{live.progress_words()}  " if live is not None
                                       else "")
                                    + f"drops {sum(s['drops'] for s in st)}  "
                                    f"late {sum(s['late'] for s in st)}")

                        for line in end_of_run.lines(k_now, progress, lambda: end_wait_words(
                                K, K in rec.truth, [a for a in active if K not in rec.est[a]],
                                world_end is None)):
                            self.say(line)
                for _, f in list(undo):           # faults still in force end with the run
                    if f.kind != "monitor":
                        end(f, recorder.step)
                # final statuses: ask the processes to stop, then read what they said
                # last (the router last: the final statuses pass through it). The
                # monitors first: an agent's token going while a monitor still watches
                # is a crash to it (seen beside two busy loops: two healthy agents
                # convicted at the last step, before the world's token was seen going)
                last = [ch.name for ch in children.running() if ch.name != "router"]
                watchers = [name for name in last if name.startswith("monitor")]
                exit_said = False
                for group in (watchers, [name for name in last if name not in watchers]):
                    for sig in (signal.SIGCONT, signal.SIGTERM):
                        for name in group:
                            _signal(children, name, sig)
                    begun = time.monotonic()
                    while ((left := {ch.name for ch in children.running()} & set(group))
                           and time.monotonic() < begun + TIMING.up_exit_s):
                        if not exit_said and time.monotonic() > begun + 1.0:
                            exit_said = True
                            self.say(f"waiting up to {TIMING.up_exit_s:g} s for "
                                     f"{', '.join(sorted(left))} to exit (asked to stop)")
                        peer.wait(timeout=0.1)
                        drain()
                drain()
        except KeyboardInterrupt:
            rec.interrupted = True
            rec.failure = "interrupted"
            # stopped mid-step, as a watch is: the truth of the newest steps came, not
            # every estimate (a step without one is no divergence)
            rec.complete_step = recorder.last_complete_step(recorder.alive)
        except RunFailed as exc:
            rec.failure = str(exc)
        finally:
            if live is not None:
                live.finish(recorder, "interrupted" if rec.interrupted else
                            "failed" if rec.failure else "run ended")
            children.signal_all(signal.SIGCONT)      # a stopped child cannot act on SIGTERM
            children.stop_all()
            signal.signal(signal.SIGTERM, old_term)
            signal.signal(signal.SIGINT, old_int)
        rec.wall = time.monotonic() - t_begin
        return rec

    def _entry(self, ep) -> str:
        """The endpoint a process joining the run connects to: the router's (the last)
        under ``--router`` (every other process is its client and listens on nothing),
        else the world's."""
        return ep[-1] if self.config.router else ep[0]

    def _write_run_json(self, rec, ep):
        from agent.run.folder import write_run_json

        c = self.config
        names = [monitor_name(1) if n == "monitor" else n       # the monitor's host: its
                 for n in host_names(c.M, c.router)]             # first process's endpoint
        procs = {name: {"endpoint": ep[i]} for i, name in enumerate(names)
                 if not c.router or name == "router"}     # clients do not listen
        for name, child in rec.children.children.items():
            procs.setdefault(name, {})["pid"] = child.proc.pid
            args = list(child.proc.args)       # socmon's own argv: after ... -m agent.cli
            procs[name]["argv"] = args[args.index("agent.cli") + 1:] if "agent.cli" in args \
                else args
        if c.testbed is not None:         # attach with `ip netns exec NETNS socmon ...`
            for name in procs:
                procs[name]["netns"] = c.testbed.namespace(host_of(name))
        write_run_json(c.out, run=rec.run_id, connect=self._entry(ep),
                       processes=procs, scenario=c.scenario.name, scenario_arg=c.scenario_arg,
                       keys=c.out / "keys" if c.secure else None,
                       operator_key=c.out / "operator.key", control_key=c.out / "control.key",
                       manifest=c.out / "manifest.json", gains=c.gains_path, seed=c.seed,
                       delays=c.delays_spec, steps=c.steps, step_ms=c.step_ms)


class EndOfRun:
    """Which progress lines a live run of ``steps`` steps says around its end: every
    line before its last step; the line of the last step once (it was said every second
    while ``up`` waited, about ten times); then, if ``up`` still waits a tick later, once
    what for.

    >>> end = EndOfRun(600)
    >>> end.lines(590, lambda: "step 590/600", lambda: "agent 3")
    ['step 590/600']
    >>> end.lines(600, lambda: "step 600/600", lambda: "agent 3")
    ['step 600/600']
    >>> end.lines(600, lambda: "step 600/600", lambda: "agent 3")
    ['waiting for agent 3']
    >>> end.lines(600, lambda: "step 600/600", lambda: "agent 3")
    []
    """

    def __init__(self, steps: int):
        self.steps = steps
        self.said_last = self.said_waiting = False

    def lines(self, step: int, progress, waiting) -> list:
        """The lines to say at a progress tick at ``step``: ``progress()`` is the
        progress line, ``waiting()`` what the run waits for once its last step is past."""
        if step < self.steps:
            return [progress()]
        if not self.said_last:
            self.said_last = True
            return [progress()]
        if not self.said_waiting:
            self.said_waiting = True
            return [f"waiting for {waiting()}"]
        return []


def end_wait_words(K: int, has_truth: bool, missing, world_running: bool) -> str:
    """What ``up`` waits for once its last step ``K`` has come: the world's step ``K``
    (``has_truth`` False), the estimates of step ``K`` of the agents in force ``missing``,
    the world's end; and how long at most.

    >>> end_wait_words(600, True, [3, 7], True)  # doctest: +NORMALIZE_WHITESPACE
    "the estimates of step 600 of agents 3, 7 and the world to end (it waits up to 5 s
    for the agents' last statuses); at most 10 s, then up stops the processes"
    >>> end_wait_words(600, True, [3], False)
    'the estimate of step 600 of agent 3; at most 5 s, then up stops the processes'
    """
    parts = [] if has_truth else [f"the world's step {K}"]
    if missing:
        many = len(missing) > 1
        parts.append(f"the estimate{'s' if many else ''} of step {K} of "
                     f"agent{'s' if many else ''} {', '.join(map(str, missing))}")
    if world_running:
        parts.append(f"the world to end (it waits up to {TIMING.end_timeout_s:g} s for the "
                     "agents' last statuses)")
    most = TIMING.up_end_s + (TIMING.end_timeout_s if world_running else 0.0)
    return (" and ".join(parts or ["the processes' last words"])
            + f"; at most {most:g} s, then up stops the processes")


def _world_silent_for(recorder) -> float:
    """Seconds since the newest step of the truth came (0 before the clock starts)."""
    at = recorder.truth_at
    return 0.0 if at is None else time.monotonic() - at


def _disk_full(folder, room: int = 1 << 20) -> bool:
    """True when the file system of ``folder`` has less than ``room`` bytes free."""
    try:
        st = os.statvfs(folder)
    except OSError:
        return False
    return st.f_bavail * st.f_frsize < room


def _through_router(argv, router_ep):
    """The argv of a child of a routed run: no --listen, one --connect (the router)."""
    out, skip = [], False
    for arg in argv:
        if skip:
            skip = False
        elif arg in ("--listen", "--connect"):
            skip = True
        else:
            out.append(arg)
    return out + ["--mode", "client", "--connect", router_ep]


def _wait_listening(children, name, timeout):
    """Wait until child ``name`` logs that it listens (``socmon router`` prints it)."""
    child = children.children[name]
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        children.reap()
        if "listening on" in child.log_path.read_text(errors="replace"):
            return
        if child.returncode is not None:
            raise RunFailed(f"{name} exited with status {child.returncode} before it listened;"
                            f" its log ends:\n{children.tail(name)}")
        time.sleep(0.05)
    raise RunFailed(f"{name} did not listen within {timeout:g} s; its log ends:\n"
                    f"{children.tail(name)}")


def _connect_to(endpoints) -> list:
    """``--connect`` flags for ``endpoints``: each child of a run connects to every child
    started before it (the world, the agents of smaller ids, the monitors before it), and
    finds no link by gossip (:data:`agent.run.folder.MESH_CONFIG`). zenoh opens and retries the links it
    is told to make, one per pair, and opens one again when it closes; a link found by
    gossip that lapsed (one end paused or starved past the lease) was seen never to come
    back while both ends kept their other links: gossip told neither end of the other
    again (a standby lost to the monitor for the rest of a run after a 1.2 s pause of the
    monitor; a paused monitor's reassignments never reaching agent 2)."""
    return [flag for e in endpoints for flag in ("--connect", e)]


def _write_mesh_config(folder: Path) -> Path:
    """The zenoh configuration file of ``up``'s children and its recorder
    (:data:`agent.run.folder.MESH_CONFIG`): gossip tells who is on the mesh, but nobody
    connects on its word (every link is a configured one, :func:`_connect_to`; a watcher
    or an operator joining later still connects by gossip, its own configuration)."""
    path = folder / MESH_CONFIG
    path.write_text('{ scouting: { gossip: { autoconnect: { peer: [], router: [] } } } }\n')
    return path


def _standby_monitor(argv, monitor_id: int, listen: str, monitors=()) -> list:
    """The argv of standby monitor ``monitor_id``: the monitor's, with its own id and
    listen endpoint, connecting also to the ``monitors`` started before it (a router run
    rewrites it like every other child's)."""
    out = list(argv)
    if "--listen" in out:
        out[out.index("--listen") + 1] = listen
    return out[:2] + ["--id", str(monitor_id)] + out[2:] + _connect_to(monitors)


def _signal(children, name, sig):
    child = children.children.get(name)
    if child is not None and child.returncode is None:
        try:
            os.killpg(child.proc.pid, sig)
        except (ProcessLookupError, PermissionError):
            pass


def _wait_exit(children, name, timeout):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        children.reap()
        child = children.children.get(name)
        if child is None or child.returncode is not None:
            return True
        time.sleep(0.01)
    return False
