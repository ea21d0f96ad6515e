"""A whole live run on this machine: its configuration, its processes, its faults, its record.

:class:`RunConfig` is everything a run is (frozen, checked by the command that builds
it); :class:`LocalRun` starts the world, one process per agent and the monitor (each in
its own process group, :class:`agent.launcher.Children`), joins the mesh as the
recorder, injects the scheduled :class:`Fault` s at their steps, and returns a
:class:`Recording`; :func:`agent.run_summary.summarize` turns that into the summary.
``socmon up`` and ``socmon chaos`` are both this.

The run folder gets ``manifest.json`` (what every child checks: the scenario's digest,
the gains file's digest, delays, seed; see :mod:`agent.manifest`) before the children
start, and ``run.json`` (run id, every process's endpoint and PID) once they are up, so
that other tools can attach.
"""

from __future__ import annotations

import json
import os
import random
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from broker_free_net import keys
from broker_free_net.codec import MessageStats, try_decode
from broker_free_net.config import NetConfig
from broker_free_net.impair import encode_impairment
from broker_free_net.peer import Peer

from . import wire
from broker_free_net.ports import listen_port

from .launcher import Children

__all__ = ["Fault", "RunConfig", "Recording", "LocalRun", "RunFailed", "FAULT_KINDS"]

#: crash: the agent SIGKILLs itself after publishing step STEP-1 (reproducible);
#: kill: SIGKILL from outside at STEP; stop: SIGSTOP for ``seconds`` then SIGCONT;
#: monitor: SIGKILL the monitor and start it again; partition: every link out of the
#: agent cut for ``seconds``; delay: ``value`` steps of delay on every link into the
#: agent for ``seconds``; drop: drop probability ``value`` on every link into the agent
#: for ``seconds``.
#: hang: the agent's loop stops for good (SIGUSR1) while its token stays; sensor: the
#: agent's sensor readings stop (the world's link into it cut) for ``seconds``.
FAULT_KINDS = ("crash", "kill", "stop", "hang", "sensor", "monitor", "partition", "delay",
               "drop")


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
    hang_timeout: float = 1.0
    drop: float = 0.0
    faults: tuple = ()
    start_timeout: float = 60.0
    secure: bool = False
    #: one ``socmon router`` process; every other process is its client (no peer mesh)
    router: bool = False

    @property
    def M(self) -> int:
        return self.scenario.N + self.scenario.standby

    @property
    def abort_on_exit(self) -> bool:
        """Without a monitor or scripted faults a dead process ends the run."""
        return not self.monitor and not self.faults


class RunFailed(Exception):
    pass


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
    recorder_malformed: int = 0
    wall: float = 0.0
    failure: str | None = None
    interrupted: bool = False
    children: Children | None = None


class LocalRun:
    """Start, fault, record and stop one run; :meth:`run` returns a :class:`Recording`."""

    def __init__(self, config: RunConfig, say=lambda text: None):
        self.config = config
        self.say = say

    # -- argv of the children ----------------------------------------------------------
    def _argv(self, rec, ep):
        c = self.config
        common = ["--run", rec.run_id, "--connect", ep[0], "--seed", str(c.seed),
                  "--manifest", str((c.out / "manifest.json").resolve())]
        if c.secure:
            common += ["--keys", str((c.out / "keys").resolve())]
        crash_at = {f.agent: f.step for f in c.faults if f.kind == "crash"}
        out = {"world": ["world", c.scenario_arg, *common, "--listen", ep[1],
                         "--steps", str(c.steps), "--step-ms", str(c.step_ms),
                         "--start-timeout", str(c.start_timeout)]}
        for a in range(1, c.M + 1):
            argv = ["agent", c.scenario_arg, "--id", str(a), *common, "--listen", ep[a + 1],
                    "--connect", ep[1], "--delays", c.delays_spec,
                    "--deadline-ms", str(c.deadline_ms)]
            if a <= c.scenario.N:
                argv += ["--gains", str(c.gains_path)]
            if c.drop:
                argv += ["--drop", repr(c.drop)]
            if a in crash_at:
                argv += ["--crash-at", str(crash_at[a])]
            out[f"agent-{a}"] = argv
        out["monitor"] = ["monitor", c.scenario_arg, *common, "--listen", ep[c.M + 2],
                          "--gains", str(c.gains_path), "--delays", c.delays_spec,
                          "--hang-timeout", str(c.hang_timeout), "--step-ms", str(c.step_ms),
                          "--events", str((c.out / "events.jsonl").resolve()),
                          "--control-key", str((c.out / "control.key").resolve())]
        return out

    # -- the run -------------------------------------------------------------------------
    def run(self) -> Recording:
        from agent.manifest import write_manifest

        c = self.config
        K, N, M = c.steps, c.scenario.N, c.M
        rec = Recording(run_id=f"up{os.getpid()}x{random.randrange(10**6)}",
                        ports=[listen_port() for _ in range(M + 3 + c.router)])
        rec.est = {a: {} for a in range(1, M + 1)}
        rec.est_epoch = {a: {} for a in range(1, M + 1)}
        rec.rosters = [(0, tuple(range(1, N + 1)), 0)]
        scheme = "tls" if c.secure else "tcp"
        ep = [f"{scheme}/127.0.0.1:{p}" for p in rec.ports]
        net_extra = {}
        if c.secure:
            from broker_free_net.security import make_run_keys, run_identities

            make_run_keys(c.out / "keys", rec.run_id, run_identities(M))
            net_extra = {"keys": str((c.out / "keys").resolve()), "identity": "recorder"}
        from agent.control_auth import ControlSigner

        signer = ControlSigner.generate()       # the run's control key: the monitor's
        operator = ControlSigner.generate()     # the operator's (impairments): this run's
        for name, key in (("control.key", signer), ("operator.key", operator)):
            key_path = c.out / name
            key_path.touch(mode=0o600)
            key_path.write_bytes(key.private_bytes())
        write_manifest(c.out / "manifest.json", c.scenario, c.gains_path, c.seed,
                       c.delays_spec, c.delays, rec.run_id, signer.public_bytes(),
                       operator.public_bytes())
        children = rec.children = Children(c.out / "logs")
        stats = MessageStats()
        n = c.scenario.n
        est_schema, truth_schema = wire.est_schema(n), wire.truth_schema(n)
        roster_schema, ctl_schema = wire.roster_schema(), wire.ctl_schema(n)
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
        try:
            if c.router:        # up before its clients, which try it for 10 s only
                children.start("router", ["router", "--listen", router_ep])
                _wait_listening(children, "router", c.start_timeout)
            with Peer(NetConfig(run=rec.run_id, **{"listen": (ep[0],), **net_extra}),
                      "recorder", 0) as peer:
                truth_in = peer.subscribe(keys.truth_key(rec.run_id), maxlen=1 << 16)
                ctl_in = peer.subscribe(keys.any_agent_pattern(rec.run_id, "ctl"),
                                        maxlen=1 << 12)
                est_in = peer.subscribe(keys.any_agent_pattern(rec.run_id, "est"),
                                        maxlen=1 << 16)
                status_in = peer.subscribe(keys.any_agent_pattern(rec.run_id, "status"))
                impair_key = keys.impair_key(rec.run_id)
                peer.publisher(impair_key, block=True)
                children.start("world", argv["world"])
                for a in range(1, M + 1):
                    children.start(f"agent-{a}", argv[f"agent-{a}"])
                if c.monitor:
                    children.start("monitor", argv["monitor"])
                self._write_run_json(rec, ep)
                self.say(f"run {rec.run_id}: world + {N} agents + {c.scenario.standby} standby"
                         f"{' + monitor' if c.monitor else ''} started; waiting for all to be "
                         f"ready (clock starts then), {K} steps of {c.step_ms:g} ms")

                def drain():
                    for item in truth_in.drain():
                        m = try_decode(item.payload, truth_schema, stats)
                        if m is not None:
                            rec.truth[m["step"]] = np.array(m["x"])
                    for item in est_in.drain():
                        m = try_decode(item.payload, est_schema, stats, senders=set(rec.est))
                        if m is not None:
                            rec.est[m["agent"]][m["step"]] = np.array(m["x"])
                            rec.est_epoch[m["agent"]][m["step"]] = m["epoch"]
                    for item in status_in.drain():
                        m = try_decode(item.payload, wire.STATUS_SCHEMA, stats)
                        if m is not None:
                            rec.status[m["agent"]] = m
                    for item in ctl_in.drain():
                        if item.key == keys.ctl_key(rec.run_id, 0):
                            m = try_decode(item.payload, roster_schema, stats)
                            if m is not None and m["epoch"] > rec.rosters[-1][2]:
                                rec.rosters.append((m["activate_at"], tuple(m["ids"]),
                                                    m["epoch"]))
                        else:
                            m = try_decode(item.payload, ctl_schema, stats)
                            if m is not None:
                                rec.assigns.setdefault((m["agent"], m["epoch"]), m)

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
                    elif f.kind == "monitor" and c.monitor:
                        _signal(children, "monitor" if not restarts else
                                f"monitor-{restarts + 1}", signal.SIGKILL)
                        event(process="monitor", signal="SIGKILL", step=k_now)
                        undo.append((now, f))        # start it again at once
                    elif f.kind in ("partition", "delay", "drop"):
                        if f.kind == "partition":
                            impair_links(f.agent, True, partition=True)
                        elif f.kind == "delay":
                            impair_links(f.agent, False, delay_steps=int(f.value))
                        else:
                            impair_links(f.agent, False, drop=float(f.value))
                        event(process=name, impair=f"{f.kind} {f.value:g}", step=k_now)
                        undo.append((now + f.seconds, f))
                    self.say(f"step {k_now}: {f.kind}"
                             + (f" agent {f.agent}" if f.agent else "")
                             + (f" for {f.seconds:g} s" if f.seconds else ""))

                def end(f, k_now):
                    nonlocal restarts
                    name = f"agent-{f.agent}"
                    if f.kind == "stop":
                        _signal(children, name, signal.SIGCONT)
                        event(process=name, signal="SIGCONT", step=k_now)
                    elif f.kind == "monitor":
                        old = "monitor" if not restarts else f"monitor-{restarts + 1}"
                        _wait_exit(children, old, 10.0)
                        restarts += 1
                        children.start(f"monitor-{restarts + 1}", argv["monitor"])
                        event(process=f"monitor-{restarts + 1}", started=True, step=k_now)
                    elif f.kind == "sensor":
                        impair(0, f.agent, partition=False)
                        event(process=name, impair="sensor restored", step=k_now)
                    elif f.kind == "partition":
                        impair_links(f.agent, True, partition=False)
                        event(process=name, impair="healed", step=k_now)
                    elif f.kind in ("delay", "drop"):
                        from design.roster import link_delay_table

                        table = link_delay_table(c.scenario, c.delays)
                        for b in range(1, M + 1):
                            if b != f.agent:
                                impair(b, f.agent, delay_steps=int(table[f.agent - 1, b - 1]),
                                       drop=0.0)
                        event(process=name, impair="restored", step=k_now)

                world_end = None
                next_progress = time.monotonic() + 1.0
                start_deadline = time.monotonic() + c.start_timeout + 30.0
                while True:
                    peer.wait(timeout=0.05)
                    drain()
                    for child in children.reap():
                        if child.name == "world" and child.returncode == 0:
                            world_end = time.monotonic()
                        elif child.name in ("world", "router") or (world_end is None
                                                                   and c.abort_on_exit):
                            raise RunFailed(f"{child.name} exited with status "
                                            f"{child.returncode} before the end of the run; "
                                            f"its log ends:\n{children.tail(child.name)}")
                        elif world_end is None:
                            k_now = max(rec.truth) if rec.truth else -1
                            event(process=child.name, exit_status=child.returncode, step=k_now)
                            self.say(f"{child.name} exited with status {child.returncode} "
                                     f"at step {k_now}; the run goes on")
                    now = time.monotonic()
                    k_now = max(rec.truth) if rec.truth else -1
                    while pending and k_now >= pending[0].step:
                        f = pending.pop(0)
                        if f.kind != "crash":
                            inject(f, k_now, now)
                    for item in sorted(u for u in undo if u[0] <= now):
                        undo.remove(item)
                        end(item[1], k_now)
                    if not rec.truth and now > start_deadline:
                        raise RunFailed(f"the clock did not start within {c.start_timeout:g} s;"
                                        f" world log:\n{children.tail('world')}")
                    running = {ch.name for ch in children.running()}
                    in_force = set(rec.rosters[-1][1])
                    active = [a for a in range(1, M + 1) if f"agent-{a}" in running
                              and a in in_force and rec.status.get(a, {}).get("active", a <= N)]
                    done = K in rec.truth and all(K in rec.est[a] for a in active)
                    if done or (world_end is not None and now - world_end > 5.0):
                        break
                    if now >= next_progress and rec.truth:
                        next_progress = now + 1.0
                        st = rec.status.values()
                        self.say(f"step {k_now}/{K}  drops {sum(s['drops'] for s in st)}  "
                                 f"late {sum(s['late'] for s in st)}")
                for _, f in list(undo):           # faults still in force end with the run
                    if f.kind != "monitor":
                        end(f, max(rec.truth) if rec.truth else -1)
                # final statuses: ask the agents to stop, then read what they said last
                # (the router last: the final statuses pass through it)
                last = [ch.name for ch in children.running() if ch.name != "router"]
                for sig in (signal.SIGCONT, signal.SIGTERM):
                    for name in last:
                        _signal(children, name, sig)
                deadline = time.monotonic() + 5.0
                while ({ch.name for ch in children.running()} - {"router"}
                       and time.monotonic() < deadline):
                    peer.wait(timeout=0.1)
                    drain()
                drain()
        except KeyboardInterrupt:
            rec.interrupted = True
            rec.failure = "interrupted"
        except RunFailed as exc:
            rec.failure = str(exc)
        finally:
            children.signal_all(signal.SIGCONT)      # a stopped child cannot act on SIGTERM
            children.stop_all()
            signal.signal(signal.SIGTERM, old_term)
            signal.signal(signal.SIGINT, old_int)
        rec.wall = time.monotonic() - t_begin
        rec.recorder_malformed = stats.total_dropped
        return rec

    def _write_run_json(self, rec, ep):
        c = self.config
        names = ["recorder", "world"] + [f"agent-{a}" for a in range(1, c.M + 1)] + ["monitor"]
        if c.router:
            names.append("router")
        procs = {name: {"endpoint": ep[i]} for i, name in enumerate(names)
                 if not c.router or name == "router"}     # clients do not listen
        for name, child in rec.children.children.items():
            procs.setdefault(name, {})["pid"] = child.proc.pid
            procs[name]["argv"] = list(child.proc.args[3:])       # after python -m agent.cli
        (c.out / "run.json").write_text(json.dumps({
            "run": rec.run_id, "scenario": c.scenario.name, "out": str(c.out.resolve()),
            "connect": ep[-1] if c.router else ep[0], "processes": procs}, indent=2) + "\n")


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
