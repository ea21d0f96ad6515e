"""The monitor process: feeds an :class:`agent.monitor.core.MonitorCore` from a zenoh peer.

It joins the run as the peer ``monitor/<id>``, reads every agent's liveliness and status,
ticks the core every ``TICK_S``, and publishes what the core decides: assignments on
``ctl/<agent>`` and the roster (the fence) on ``ctl/0``, the roster again every
``ROSTER_S`` so that an agent coming back learns it was replaced. At start-up a
background process precomputes the plan and the gains of every single failure of the
configuration in force (again after every reassignment), so that a foreseen failure is
answered without designing anything; the first monitor joins the run (declares its token,
which a world started with ``--wait-monitor`` waits for) only once every single failure
is foreseen (:func:`foresee_single_failures`). Designs run in the processes of an
:class:`agent.monitor.gain_worker.GainWorker`, never in this loop: a configuration nobody foresaw
waits for its gains while detection goes on, and a fast gain in force is replaced by the
refined one under a new epoch when it comes back.

When the world's token goes, the run is ending: the agents leave with it, so nothing is
convicted while it is gone, and the monitor exits once the agents' tokens are gone too
(:meth:`MonitorCore.run_ended`).

Before it judges anything the monitor that starts a run (``prepare_s`` > 0; one started
again mid-run is not) waits to see the liveliness token of every agent of the
configuration (:func:`reach_every_agent`, at most ``Timing.monitor_reach_s``): on a loaded
host its links to a large run come up one by one, and an agent not reached yet looks like
one that never started.

A monitor listens for :data:`agent.monitor.core.LISTEN_S` before it acts. Several monitors may run on one run:
the one with the smallest id whose token is alive acts (once it has listened: the one
acting until then goes on), the others stay passive and watch;
when the active one's token goes, the next one adopts the configuration in force from the
roster it heard and the agents' statuses and goes on with epochs above every epoch it saw
(:class:`agent.monitor.core.MonitorSeat`, the policy the simulated runtime runs too).
"""

from __future__ import annotations

import json
import signal
import sys
import time

from agent.protocol import topics
from broker_free_net.codec import MessageStats, try_decode

from agent.protocol import wire
from agent.protocol.control_auth import SignatureError
from agent.protocol.timing import DEFAULT as TIMING
from agent.monitor.gain_worker import GainWorker
from agent.shell.memory import TRIM_S, heap_trimmer
from agent.monitor.core import (
    ROSTER_S,
    TICK_S,
    Assignment,
    GainSource,
    MonitorConfig,
    MonitorCore,
    MonitorSeat,
    RosterUpdate,
)

__all__ = ["run_monitor", "TICK_S", "ROSTER_S"]



def foresee_single_failures(worker, gains, roster, stop, limit: float) -> dict:
    """Wait until ``gains`` knows the gains of every single failure of ``roster`` (the
    worker's precompute designs them first), at most ``limit`` seconds or until ``stop``.

    Why: a failure before its gains are precomputed waits for a design (0.6 s of CPU for
    paper-14-live at T = 15, 3.8 s beside two busy loops) and the network runs
    without the failed agent meanwhile; a world started with ``--wait-monitor`` starts its
    clock once this monitor has joined, so every single failure is foreseen from step 0.
    Returns ``foreseen`` / ``planned`` (lists of failed ids), ``seconds`` and ``line``,
    the sentence the monitor prints."""
    from agent.monitor.gain_worker import plan_failures, unforeseen_single_failures

    planned = [(a, nxt) for a, nxt in plan_failures(roster) if len(a) == 1]
    t0 = time.monotonic()
    while True:
        for r, G, info in worker.poll(timeout=0.05):
            gains.put(r, G, info)
        missing = unforeseen_single_failures(gains, planned)
        waited = time.monotonic() - t0
        if not missing or waited > limit or stop.flag:
            break
    ids = [a[0] for a, _ in planned]
    foreseen = [a for a in ids if a not in missing]
    if missing:
        why = "stopped" if stop.flag else f"after {limit:g} s"
        line = (f"foresees the failure of agents {foreseen} of {ids} ({why}; the others get "
                "a first gain designed when they fail)")
    else:
        line = f"foresees the failure of every agent ({ids}) after {waited:.1f} s"
    return {"foreseen": foreseen, "planned": ids, "seconds": round(waited, 3), "line": line}


class _Stop:
    def __init__(self):
        self.flag = False

    def __call__(self, *_):
        self.flag = True




def reach_every_agent(watch, ids, monitor_id, stop, log,
                      limit: float = TIMING.monitor_reach_s) -> list:
    """Wait until ``watch`` sees the liveliness token of every agent of ``ids``, at most
    ``limit`` seconds or until ``stop``; returns the agents not seen (and says so): the
    detector's clock starts after this, so an agent whose link is not up yet is not taken
    for one that never started (:data:`agent.protocol.timing.Timing.monitor_reach_s`)."""
    want = {("agent", str(i)) for i in ids}
    start = time.monotonic()
    seen, grew_at = 0, start
    while not stop.flag:
        if watch.wait_until(lambda alive: want <= alive, 0.25):
            return []
        now = time.monotonic()
        count = len(want & watch.alive())
        if count > seen:
            seen, grew_at = count, now
        # every agent's link not up after the limit, or none new for REACH_SETTLE_S while
        # some are (the others are most likely dead: a restarted monitor)
        if now - start >= limit or (seen and now - grew_at >= REACH_SETTLE_S):
            break
    missing = sorted(int(i) for role, i in want - watch.alive())
    if missing:
        print(f"monitor {monitor_id}: agents {missing} not seen after "
              f"{time.monotonic() - start:.1f} s; judging from now on", file=log, flush=True)
    return missing


#: :func:`reach_every_agent` stops waiting once no new agent was seen for this long.
REACH_SETTLE_S = 3.0


def run_monitor(scenario, G, delays, net, monitor_id: int = 1, config: MonitorConfig = None,
                log=sys.stderr, stop=None, events_out=None, precompute: bool = True,
                signer=None, prepare_s: float = TIMING.monitor_prepare_s) -> int:
    """Run the monitor until stopped (SIGTERM/SIGINT). Returns the exit status.

    ``events_out``: a path; every verdict and reassignment is appended as one JSON line.
    The first monitor (``monitor_id`` 1) joins the run (declares its token) once it has
    gains for every single failure, or after ``prepare_s`` (:func:`foresee_single_failures`).
    """
    stop = stop or _Stop()
    if isinstance(stop, _Stop):
        signal.signal(signal.SIGTERM, stop)
        signal.signal(signal.SIGINT, stop)
    # the first monitor starts its design processes at once (their imports overlap its
    # listening time and the start handshake; the urgent one warms up, gain_worker._warm_up,
    # with or without the precompute); a standby monitor when it first acts
    worker = GainWorker(start=monitor_id == 1,
                        warm_up=monitor_id == 1 and prepare_s > 0)
    gains = GainSource(worker=worker)
    core = MonitorCore(config or MonitorConfig(), scenario, G, delays, gains=gains)
    stats = MessageStats()
    run = net.run
    ctl_schema = wire.roster_schema()
    # a roster heard is adopted only with the run's control signature (the monitors share
    # the control key) and within the epoch bound (MonitorCore.accept_roster)
    verifier = None
    if signer is not None:
        from agent.protocol.control_auth import ControlVerifier

        verifier = ControlVerifier(signer.public_bytes(), run, not_before=0.0)
    status_sender = topics.AgentKeyCache(run, "status", core.agents)
    estimate_sender = topics.AgentKeyCache(run, "est", core.agents)
    trim_heap, trimmed = heap_trimmer(), [0.0, 0]   # time, messages dropped at the last trim
    out_file = open(events_out, "a") if events_out else None
    files = [out_file]                   # [the events file, None once a write failed]
    publish = []              # the peer's put, once it is open: watchers hear every event

    def record(kind, **fields):
        event = {"kind": kind, "t": time.time(), **fields}
        if files[0] is not None:
            try:
                files[0].write(json.dumps(event) + "\n")
                files[0].flush()
            except OSError as exc:       # a full disk: the events go on on the wire only
                files[0] = None
                print(f"monitor {monitor_id}: warning: cannot write {events_out}: "
                      f"{exc.strerror}; events are published only from now on", file=log,
                      flush=True)
        for put in publish:
            put(topics.monitor_events_key(run), wire.encode_monitor_event(event))

    precomputing = [None]

    def precompute_for(roster):
        if precompute and precomputing[0] is not roster:
            precomputing[0] = roster
            worker.precompute(roster, core.G if roster is core.roster else None)

    if monitor_id == 1:
        precompute_for(core.roster)  # the scenario's configuration: at once, not once active

    try:
        if monitor_id == 1 and precompute and prepare_s > 0:
            foreseen = foresee_single_failures(worker, gains, core.roster, stop, prepare_s)
            print(f"monitor {monitor_id}: {foreseen['line']}; joining the run", file=log,
                  flush=True)
            record("prepared", **{k: v for k, v in foreseen.items() if k != "line"})
        with topics.open_peer(net, "monitor", monitor_id) as peer:
            peer.publisher(topics.monitor_events_key(run))    # declared now, not at a verdict
            publish.append(peer.put)
            status_in = peer.subscribe(topics.any_agent_pattern(run, "status"))
            # the monitor's own observation of who is heard (MonitorCore.on_estimate_seen,
            # weighed against a lone listener's word): the key and arrival time only, never
            # decoded; estimates go with congestion control DROP, so a paused monitor loses
            # its own copies and holds no agent back (measured: docs/security.md)
            estimates_in = peer.subscribe(topics.any_agent_pattern(run, "est"), maxlen=256)
            # neither wakes the loop: both are stamped on arrival and read at the next tick
            # (TICK_S). Woken by each, the loop ran once per estimate or so, its tick
            # included: with 32 agents at 20 ms steps 1,600 estimates a second
            status_in.wakes = estimates_in.wakes = False
            roster_in = peer.subscribe(topics.ctl_key(run, 0))
            end_in = peer.subscribe(topics.end_key(run), maxlen=16)
            watch = peer.watch_liveliness()
            if prepare_s > 0:
                # a monitor that starts the run (one started again mid-run is told
                # --prepare-s 0: its configuration is stale and an agent may be dead, and
                # it must not wait before it listens and adopts)
                reach_every_agent(watch, core.roster.ids, monitor_id, stop, log)
            seat = MonitorSeat(core, monitor_id, time.monotonic())
            next_roster = 0.0
            print(f"monitor {monitor_id}: watching run {run}", file=log, flush=True)
            while not stop.flag:
                for roster, G_new, info in worker.poll():
                    gains.put(roster, G_new, info)
                now = time.monotonic()
                # the events file is written by one monitor: the smallest live id (the one
                # that acts, or will once it has listened)
                first = not any(role == "monitor" and i.isdigit() and int(i) < monitor_id
                                for role, i in watch.alive())
                for ev in watch.drain():
                    if ev.role == "agent" and ev.id.isdigit():
                        own = core.on_liveliness("agent", int(ev.id), ev.alive, ev.arrival,
                                                 session=ev.session)
                        if own is False and first:
                            record("liveliness", agent=int(ev.id), alive=False)
                    elif ev.role == "world":
                        core.on_liveliness("world", ev.id, ev.any_alive, ev.arrival)
                        if not ev.any_alive and first:
                            record("liveliness", process="world", alive=False,
                                   step=core.last_step_reported)
                if stats.total_dropped - trimmed[1] > 1000 and now - trimmed[0] > TRIM_S:
                    trim_heap()          # after a burst of malformed input: memory back
                    trimmed[:] = [now, stats.total_dropped]
                for item in status_in.drain():
                    msg = try_decode(item.payload, wire.STATUS_SCHEMA, stats)
                    if msg is None:
                        continue
                    sender = status_sender.agent_of(item.key)
                    if sender is None:
                        stats.count_dropped("key")
                        continue
                    # stamped when it arrived, as the estimates seen and the tokens are: a
                    # loop that lags would make a queued status look recent (a token that
                    # went after it, with its process, was then taken for a lapse)
                    core.on_status(msg, item.arrival, sender=sender)
                for item in estimates_in.drain():
                    sender = estimate_sender.agent_of(item.key)
                    if sender is not None:
                        core.on_estimate_seen(sender, item.arrival)
                for item in end_in.drain():
                    msg = try_decode(item.payload, wire.END_SCHEMA, stats)
                    if msg is not None:
                        core.on_world_end(msg["step"])
                for item in roster_in.drain():
                    msg = try_decode(item.payload, ctl_schema, stats)
                    if msg is None:
                        continue
                    if verifier is not None:
                        try:
                            verifier.check(msg, replay=False)
                        except SignatureError as exc:
                            core.reject("signature", 0, f"a roster (epoch {msg['epoch']}) "
                                        f"without the run's control signature ({exc})")
                            continue
                    seat.on_roster(msg)
                state = seat.decide(now, [(int(i), z) for role, i in watch.alive()
                                          if role == "monitor" and i.isdigit()
                                          for z in watch.sessions(role, i)])
                for line in seat.lines:
                    print(f"monitor {monitor_id}: {line}", file=log, flush=True)
                for kind, fields in seat.records:
                    record(kind, **fields)
                if seat.precompute:
                    precompute_for(core.roster)
                if seat.stand_down:
                    worker.stand_down()
                    precomputing[0] = None
                seat.lines.clear()
                seat.records.clear()
                seat.precompute = seat.stand_down = False
                if state != "act":
                    for line in core.events:     # what a passive monitor's detector saw
                        print(f"monitor {monitor_id}: {line}", file=log, flush=True)
                    core.events.clear()
                if state == "wait":
                    peer.wait(timeout=0.05)
                    continue
                active = state == "act"
                if active:
                    for m in core.tick(now):
                        if isinstance(m, Assignment):
                            peer.put(topics.ctl_key(run, m.agent),
                                     m.encode(signer=signer, run=run))
                        elif isinstance(m, RosterUpdate):
                            peer.put(topics.ctl_key(run, 0), wire.encode_roster(
                                m.epoch, m.activate_at, m.ids, signer=signer, run=run,
                                probation=m.probation, barred=m.barred))
                            next_roster = now + ROSTER_S
                    for line in core.events:
                        print(f"monitor {monitor_id}: {line}", file=log, flush=True)
                    core.events.clear()
                    for kind, fields in core.new_records():
                        if kind == "verdict":      # wall-clock time of the detection
                            fields["detected_t"] = time.time() - (time.monotonic()
                                                                  - fields["mono"])
                        record(kind, **fields)
                        if kind == "reassign":
                            precompute_for(core.roster)
                    if core.roster_message is not None and now >= next_roster:
                        m = core.roster_message
                        peer.put(topics.ctl_key(run, 0), wire.encode_roster(
                            m.epoch, m.activate_at, m.ids, signer=signer, run=run,
                            probation=m.probation, barred=m.barred))
                        next_roster = now + ROSTER_S
                if core.run_ended(now):
                    for line in core.events:
                        print(f"monitor {monitor_id}: {line}", file=log, flush=True)
                    print(f"monitor {monitor_id}: the world left after step {core.last_step_reported} "
                          "and the agents with it; exiting", file=log, flush=True)
                    break
                peer.wait(timeout=TICK_S)
    finally:
        worker.close()
        if out_file is not None:
            try:
                out_file.close()
            except OSError:              # the last buffered line did not fit either
                pass
    return 0

