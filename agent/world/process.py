"""The world process: the clock of a run.

It waits until every expected agent is ready (the start handshake: each agent's status
says it has heard the status of every other expected agent, so every estimate route is
declared), then every ``step_ms`` publishes every node's state on the sensors key (one
message; each agent reads its own nodes) and on the truth key, both stamped with the
step, and advances the social system (:class:`agent.world.core.WorldCore`). After the last
step it publishes its end (``socmon/<run>/end``: the last step and why), waits (bounded)
until the live agents report that step, then leaves; agents leave once its token goes
*after* its end. A token that goes without an end is a world paused or cut off: agents and
monitor wait for it (``Timing.world_silent_s``). A world that finds itself more than
``Timing.world_rebase_s`` behind its schedule (it was paused, or starved of CPU) says so and
re-bases its clock: the next step comes one period later, not every missed step at once.
"""

from __future__ import annotations

import math
import signal
import sys
import time

import numpy as np

from agent.protocol import topics
from broker_free_net.codec import MessageStats, try_decode

from agent.protocol import wire
from agent.world.core import WorldCore, resolution_step
from agent.protocol.timing import DEFAULT as TIMING

__all__ = ["run_world", "StartTimeout"]

RESOLUTION_DIGITS = 6.0


class StartTimeout(RuntimeError):
    """Not every expected agent became ready in time."""


class _Stop:
    def __init__(self):
        self.flag = False

    def __call__(self, *_):
        self.flag = True


def _warn_resolution(scenario, world, steps, log) -> int | None:
    rho = scenario.rho_A
    x0 = float(np.linalg.norm(world.x, np.inf))
    k0 = resolution_step(rho, x0, digits=0.0)
    k6 = resolution_step(rho, x0, digits=RESOLUTION_DIGITS)
    if k6 is None:
        return None
    horizon = "" if steps is None else f" (this run: {steps} steps)"
    if steps is None or steps >= k6:
        print(f"world: warning: rho(A) = {rho:.4f} > 1: the state grows like rho^k; an error of "
              f"order one keeps fewer than {RESOLUTION_DIGITS:g} significant digits in float64 "
              f"from about step {k6} and none from about step {k0}{horizon}. Use a scenario "
              "with rho(A) < 1 for long live runs (e.g. paper-14-live).", file=log)
    return k6


#: While the start handshake lasts, the world says whom it waits for this often.
START_WORD_S = 5.0


def start_wait(expected, heard, monitor=None) -> str:
    """Whom the start waits for, in words: the agents not heard at all, and for each agent
    heard, the agents it has not heard yet (a route that does not exist yet); ``monitor``:
    the id of the monitor waited for, while it has not joined.

    >>> start_wait({1, 2, 3, 4}, {1: {2}, 2: {1}})
    'waiting for agents [3, 4] (no status heard: not started, or cannot reach the world); agent 1 has not heard [3, 4]; agent 2 has not heard [3, 4]'
    >>> start_wait({1, 2}, {1: {2}, 2: {1}})
    'every agent ready'
    >>> start_wait({1, 2}, {1: {2}, 2: {1}}, monitor=1)
    'monitor 1 has not joined (it joins once it foresees every single failure)'
    """
    parts = []
    silent = sorted(a for a in expected if a not in heard)
    if silent:
        parts.append(f"waiting for agents {silent} (no status heard: not started, or cannot "
                     "reach the world)")
    for a in sorted(a for a in expected if a in heard):
        lacking = sorted(expected - {a} - set(heard[a]))
        if lacking:
            parts.append(f"agent {a} has not heard {lacking}")
    if monitor is not None:
        parts.append(f"monitor {monitor} has not joined (it joins once it foresees every "
                     "single failure)")
    return "; ".join(parts) or "every agent ready"


def run_world(scenario, net, seed: int, steps=None, step_ms=None, wait_agents=None,
              start_timeout: float = TIMING.start_timeout_s,
              end_timeout: float = TIMING.end_timeout_s, log=sys.stderr,
              stop=None, rebase_s: float = TIMING.world_rebase_s,
              wait_monitor: int | None = None) -> int:
    """Run the world. ``steps=None`` runs until stopped; ``wait_agents`` = ids to wait for;
    ``wait_monitor``: the id of a monitor whose token must be alive before the clock starts
    (it declares it once its gains for every single failure are ready: a failure soon after
    the start is then answered at once, see :func:`agent.monitor.process.run_monitor`)."""
    stop = stop or _Stop()
    if isinstance(stop, _Stop):
        signal.signal(signal.SIGTERM, stop)
        signal.signal(signal.SIGINT, stop)
    run = net.run
    step_s = (step_ms if step_ms is not None else scenario.step_ms) / 1000.0
    M = scenario.N + scenario.standby
    expected = set(range(1, M + 1)) if wait_agents is None else set(wait_agents)
    world = WorldCore(scenario.A, seed, scenario.process_noise)
    k_warn = _warn_resolution(scenario, world, steps, log)
    stats = MessageStats()
    with topics.open_peer(net, "world", 0) as peer:
        # a second world would run a second clock and a second truth on the same keys
        peer.claim(say=lambda text: print(f"world: {text}", file=log, flush=True),
                   stop=lambda: stop.flag)
        status_in = peer.subscribe(topics.any_agent_pattern(run, "status"))
        watch = peer.watch_liveliness()
        sensors_key, truth_key = topics.sensors_key(run), topics.truth_key(run)
        end_key = topics.end_key(run)
        for key in (sensors_key, truth_key, end_key):
            peer.publisher(key)

        def publish_end(reason):
            peer.put(end_key, wire.encode_end(world.step, reason))
        ready: dict = {}
        heard: dict = {}                   # agent -> the agents its last status heard
        other_seed: set = set()            # agents started with another --seed (said once)
        last_step: dict = {}

        def read_statuses(timeout=0.0):
            item = status_in.get(timeout=timeout) if timeout > 0 else None
            items = ([item] if item is not None else []) + status_in.drain()
            for it in items:
                msg = try_decode(it.payload, wire.STATUS_SCHEMA, stats)
                if msg is None:
                    continue
                if "heard" in msg:            # (sent until the agent's clock starts)
                    heard[msg["agent"]] = set(msg["heard"])
                    ready[msg["agent"]] = heard[msg["agent"]] >= (expected - {msg["agent"]})
                if msg.get("seed", seed) != seed and msg["agent"] not in other_seed:
                    other_seed.add(msg["agent"])
                    print(f"world: warning: agent {msg['agent']} was started with --seed "
                          f"{msg['seed']}, this world with --seed {seed}: its measurement "
                          "noise and first estimate are not the run's (a replay differs)",
                          file=log, flush=True)
                last_step[msg["agent"]] = msg["step"]

        def monitor_missing():
            return wait_monitor is not None and ("monitor", str(wait_monitor)) not in \
                watch.alive()

        print(f"world: waiting for agents {sorted(expected)} (each must hear every other "
              "one)" + ("" if wait_monitor is None else f" and for monitor {wait_monitor}")
              + f"; up to {start_timeout:g} s", file=log, flush=True)
        started = time.monotonic()
        deadline = started + start_timeout
        next_word = started + START_WORD_S
        while not all(ready.get(a) for a in expected) or monitor_missing():
            if stop.flag:
                publish_end("stopped")
                return 130
            now = time.monotonic()
            if now > deadline or now >= next_word:
                wait = start_wait(expected, heard,
                                  wait_monitor if monitor_missing() else None)
                if now > deadline:
                    print(f"world: not ready after {start_timeout:g} s: {wait}", file=log)
                    return 1
                print(f"world: after {now - started:.0f} s, {wait}", file=log, flush=True)
                next_word = now + START_WORD_S
            read_statuses(timeout=0.05)
            running = {a: k for a, k in last_step.items() if k >= 0}
            if running:
                # agents of a run under way (its world killed, and this one started again):
                # a new clock and a new state would not be theirs
                print(f"world: agents {sorted(running)} of run {run} are at step "
                      f"{max(running.values())}: their clock started with another world; a "
                      "world cannot join a run under way (its state and clock would start "
                      "over). Start a new run (another --run) with all its processes",
                      file=log, flush=True)
                return 1
        print(f"world: {len(expected)} agents ready; clock starts, step {step_s * 1e3:g} ms",
              file=log)
        # the statuses serve the start and the end only: while the clock runs, N agents'
        # statuses (5 a second each) would cost this loop a decode each
        status_in.close()
        status_in.drain()
        t0 = time.monotonic()
        warned = False
        worst_lag = 0.0
        while not stop.flag:
            k = world.step
            worst_lag = max(worst_lag, time.monotonic() - (t0 + k * step_s))
            peer.put(sensors_key, wire.encode_sensors(k, world.x))
            peer.put(truth_key, wire.encode_truth(k, world.x))
            if k_warn is not None and k >= k_warn and not warned:
                warned = True
                print(f"world: warning: step {k}: |x| = {np.abs(world.x).max():.3g}; an O(1) "
                      f"error now has fewer than {RESOLUTION_DIGITS:g} significant digits",
                      file=log)
            if steps is not None and k >= steps:
                break
            world.advance()
            due = t0 + world.step * step_s
            behind = time.monotonic() - due
            if behind > rebase_s:
                # paused (SIGSTOP) or starved: go on one step a period from now
                print(f"world: {behind:.2f} s behind the schedule at step {world.step} "
                      "(paused or starved); the clock is re-based", file=log, flush=True)
                t0 += behind
                due += behind
            while not stop.flag:
                left = due - time.monotonic()
                if left <= 0:
                    break
                time.sleep(min(left, 0.05))
            if not math.isfinite(float(np.abs(world.x).max())):
                print(f"world: the state overflowed float64 at step {world.step}", file=log)
                publish_end("overflow")
                return 1
        if stop.flag:
            publish_end("stopped")
            return 0
        publish_end("steps")
        # wait (bounded) until the live agents have used the last readings (each publishes
        # a status 5 times a second)
        status_in = peer.subscribe(topics.any_agent_pattern(run, "status"))
        deadline = time.monotonic() + end_timeout
        while time.monotonic() < deadline and not stop.flag:
            alive = {int(i) for role, i in watch.alive() if role == "agent" and i.isdigit()}
            if all(last_step.get(a, -1) >= world.step for a in expected & alive):
                break
            read_statuses(timeout=0.05)
        print(f"world: done after step {world.step}; worst lag {1e3 * worst_lag:.1f} ms "
              "behind the schedule", file=log)
    return 0
