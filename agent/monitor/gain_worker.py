"""Gain design for the monitor, in processes of its own: the monitor's loop never designs.

A design takes from a tenth of a second (a first stabilising gain) to seconds (the gain of
least steady MSE); under the GIL a design thread starved the monitor's loop, whose pause
guard then suspended its verdicts, and a design made inside the loop left every agent
waiting (1.9-10 s measured). :class:`GainWorker` runs three processes:

- the *urgent* one designs, on request and nothing else, the first gain of a
  configuration nobody foresaw: a certified gain (stable for the configuration's delays:
  its eigenvalues counted below 0.975, :func:`design.gain_design.counted_bound`, or its
  exact radius < 1), sent at once; its refined gain follows from the precompute process;
- the *precompute* one designs the refined gain of a configuration put in force on a
  fast gain, and a fast gain for every single failure (and pairs, for
  small networks) of the configuration in force, so that a foreseen failure has its first
  gain within seconds even on a loaded machine, then polishes each of them where that
  pays (:func:`refines_ahead`: not for large networks) (a few MSE
  iterations from the fast gain: within 0.5 % of the refined MSE on paper-14-live, where
  the fast gain alone is 1.6-2.4x it and made the error's peak after the switch) (at
  the monitor's priority: niced, it got too little CPU beside two busy loops); it
  pauses at its next design iteration while the urgent one designs a first gain (when both shared one process, a request waited for the
  precompute design in progress: 1.6 s from verdict to roles beside two busy loops);
- the *background* one refines the precomputed ones where that pays (:func:`refines_ahead`)
  (the gain of least steady MSE, seconds each), and
  computes the exact radius and steady MSE of a fast gain put in force
  (:meth:`GainWorker.assess`: the fast design does not compute the MSE, a Lyapunov solve
  of seconds, nor the radius of a gain it counted); a newer
  configuration supersedes the list it works on. It runs at a lower priority (nice 10), so
  that on a loaded machine the monitor's loop, the agents and the urgent designs go first
  (at nice 10 beside two busy loops it got too little CPU to finish even the fast pass
  in the first 3 s of a run).

Results come back as ``(roster, G, info)``, ``info`` as
:func:`agent.monitor.core.design_gains_for` gives it (``kind`` ``"fast"`` or ``"refined"``,
the exact radius, or ``rho_below`` when it was counted, and the steady MSE; G is None
when no stabilising gain was found); the monitor's loop drains them with
:meth:`GainWorker.poll` between ticks and hands them to its
:class:`agent.monitor.core.GainSource`. The processes are started with ``spawn`` (the
monitor's zenoh session and its threads are not forked) and import only ``design``.
"""

from __future__ import annotations

import multiprocessing
import os
import queue
import sys

__all__ = ["GainWorker", "BACKGROUND_NICE", "keep_freed_memory", "precompute_queue",
           "refines_ahead",
           "precompute_single_failures", "refined_gains_from", "unforeseen_single_failures"]

#: Niceness of the background (refining) process.
BACKGROUND_NICE = 10
#: pairs of failures are precomputed too when the configuration has at most this many agents
PAIRS_UP_TO = 4
#: the precompute improves the foreseen failures' fast gains (polish, refinement) when the
#: configuration's estimator has at most this many states (n x agents; :func:`refines_ahead`)
REFINE_AHEAD_MAX_STATES = 256


class GainWorker:
    """Two design processes and their queues; :meth:`close` ends them."""

    def __init__(self, start: bool = False, warm_up: bool = False):
        self._ctx = multiprocessing.get_context("spawn")
        self._warm = bool(warm_up)       # the urgent process warms up first (_warm_up)
        self._procs: list = []           # started now, or at the first request (a standby
        self._generation = 0             # monitor that never acts never starts them)
        if start:
            self._start()

    def _start(self) -> None:
        if self._procs:
            return
        ctx = self._ctx
        self._urgent, self._background, self._results = ctx.Queue(), ctx.Queue(), ctx.Queue()
        # kept: a semaphore collected before the children unpickle it is gone for them
        self._fast, self._idle = ctx.Queue(), ctx.Event()
        idle = self._idle
        idle.set()
        self._procs = [
            ctx.Process(target=_serve_urgent, args=(self._urgent, self._results, idle,
                                                    self._warm),
                        name="socmon-gains-urgent", daemon=True),
            ctx.Process(target=_serve_precompute, args=(self._fast, self._results, idle),
                        name="socmon-gains-precompute", daemon=True),
            ctx.Process(target=_serve_background, args=(self._background, self._results),
                        name="socmon-gains-background", daemon=True),
        ]
        for p in self._procs:
            p.start()

    def request(self, roster, kinds=("fast", "refined"), init=None) -> None:
        """Design the gains of ``roster`` now: a fast certified gain (the urgent process,
        from the warm start ``init`` first when given), then a refined one (the precompute
        process, before its fast pass) (``kinds``: only the refined one, for a
        configuration in force on a fast gain)."""
        self._start()
        if "fast" in kinds:
            self._urgent.put(("request", roster, ("fast",),
                              None if init is None else [list(g) for g in init]))
        if "refined" in kinds:
            self._fast.put(("refine", roster))

    def assess(self, roster, G, info) -> None:
        """The exact radius and steady MSE of the gain ``G`` (``info`` its design's) for
        ``roster``, sent back as ``(roster, G, info + rho, mse, assessed)``. The background process computes it
        between two refinements: a solve of up to tens of seconds at large delays must not
        hold an unforeseen failure's first gain back."""
        self._start()
        self._background.put(("assess", roster, list(G), dict(info)))

    def precompute(self, roster, G=None) -> None:
        """Precompute the failures of ``roster`` (the configuration now in force, ``G`` its
        gains: the warm start of each failure's fast gain); any earlier precompute still
        running is abandoned."""
        self._start()
        self._generation += 1
        G = None if G is None else [list(g) for g in G]
        self._fast.put(("precompute", roster, G))
        self._background.put((self._generation, roster, G))

    def stand_down(self) -> None:
        """Drop every precompute, queued or under way (its design in progress ends first;
        a refinement gives way at its next iteration): another monitor acts. Requests
        are still served."""
        if not self._procs:
            return
        self._generation += 1
        self._fast.put(("precompute", None, None))
        self._background.put((self._generation, None, None))

    def poll(self, timeout: float = 0.0) -> list:
        """Every result ready now (waiting up to ``timeout`` s for the first one):
        ``[(roster, G or None, info)]``."""
        out = []
        if not self._procs:
            return out
        if timeout > 0:
            try:
                out.append(self._results.get(timeout=timeout))
            except (queue.Empty, EOFError, OSError):
                return out
        while True:
            try:
                out.append(self._results.get_nowait())
            except (queue.Empty, EOFError, OSError):
                return out

    def alive(self) -> bool:
        return all(p.is_alive() for p in self._procs)

    def close(self) -> None:
        if not self._procs:
            return
        for q in (self._urgent, self._fast, self._background):
            try:
                q.put(None)
            except (OSError, ValueError):
                pass
        for p in self._procs:
            p.join(timeout=1.0)
            if p.is_alive():
                p.terminate()
                p.join(timeout=1.0)
        for q in (self._urgent, self._fast, self._background, self._results):
            q.close()
            q.cancel_join_thread()


def keep_freed_memory() -> None:
    """Make this (design) process reuse the memory it frees rather than hand it back to
    the system: large blocks come from the heap, whose top is trimmed only past 256 MB.

    Why: the impulse sum of an MSE evaluation allocates one nN x (n + p) block a step
    (scipy's sparse products return new arrays) and frees it soon after; with glibc's
    default thresholds those blocks went back to the system and came back as fresh pages:
    about 65,000 page faults (250 MB zeroed by the kernel) per evaluation at
    communities-32, where with these settings there are none after the first. The peak
    is the same; the process keeps what it freed for its next design. A no-op where the C
    library has no ``mallopt`` (not glibc)."""
    import ctypes
    import ctypes.util

    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
    except (OSError, AttributeError):
        return
    M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3       # glibc's <malloc.h>
    mallopt(M_MMAP_THRESHOLD, 16 * 2**20)
    mallopt(M_TRIM_THRESHOLD, 256 * 2**20)


def _quiet_signals():
    """A design process ends with its queue's sentinel or its parent, not with the
    terminal's Ctrl-C (the monitor handles that and closes the worker)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _warm_up(design_gains_for) -> None:
    """Import what a design needs and run one small design, before the first request:
    in a cold process the first unforeseen failure's gain waited for them (the roster's
    unpickling imports the scenario and roster modules, the first design sets up scipy's
    lazy parts: 1.1 s from verdict to gains beside two busy loops, for a 25 ms design).
    It runs while the monitor waits for the precompute of the single failures before
    joining (:func:`agent.monitor.process.foresee_single_failures`): it delays that join,
    never a foreseen failure's answer (before that gate it did, and a crash at step 100
    found its failure not precomputed yet under load). Only then: a monitor started again
    in a run in progress joins at once, and its warm-up beside the new precompute made it
    miss a partition 130 steps later (chaos seed 103: 3 runs of 3 with it, 0 of 1
    without). With ``--no-precompute`` the monitor joins at once and the warm-up runs at
    the run's start: a failure in its first second queues behind it, which costs that
    request the warm-up's one small design (about 25 ms), the imports being what the
    request would pay cold anyway."""
    try:
        from design.roster import Roster
        from design.scenario import load_scenario

        design_gains_for(Roster.initial(load_scenario("paper-14")), "fast")
    except Exception:       # noqa: BLE001 - a warm-up only: the requests are served anyway
        pass


def _serve_urgent(requests, results, idle, warm_up: bool = False) -> None:
    """Requests only: a configuration nobody foresaw is designed at once (no precompute
    design is ahead of it in this process). ``idle`` is clear while a request is being
    designed: the precompute process waits at its next iteration meanwhile."""
    from agent.monitor.core import design_gains_for

    _quiet_signals()
    keep_freed_memory()
    if warm_up:
        _warm_up(design_gains_for)
    while True:
        item = requests.get()
        if item is None:
            idle.set()
            return
        _, roster, kinds, init = item
        for kind in kinds:
            if kind == "fast":          # a first gain: the precompute waits meanwhile
                idle.clear()
            try:
                results.put((roster, *design_gains_for(roster, kind,
                                                       init=init if kind == "fast" else None)))
            finally:
                idle.set()


def _serve_precompute(requests, results, idle) -> None:
    """At the monitor's priority, pausing at every design iteration while the urgent
    process designs a first gain (``idle`` clear): the fast gains of the single failures
    of the newest precompute first (so that the next failure is foreseen within a second
    or two of a switch), then the refined gain of a configuration put in force on a fast
    one, then the rest of the fast pass (pairs) and the polish pass (each fast gain given
    a few MSE iterations, which replaces it); a newer configuration supersedes both
    passes, and a refinement in progress gives way to it (it is started again after the
    newer single failures). Before, the refinement came first: at T = 15 it holds the
    process for seconds, and a second failure 96 steps after the first switch found its
    gains not designed (2.8 s from verdict to gains)."""
    from collections import deque

    from agent.monitor.core import GainSource, design_gains_for

    _quiet_signals()
    keep_freed_memory()
    refine, fast = deque(), deque()    # configurations still to design
    first = {}                         # key -> the fast gain its polish starts from
    arrived = deque()                  # requests read while a refinement was in progress
    designing = [None]                 # the kind of the design in progress

    def between_iterations(_progress) -> None:
        """Wait while the urgent process designs a first gain; a refinement gives way to
        a newer precompute (it starts again after that one's single failures)."""
        while not idle.wait(timeout=1.0):
            pass
        if designing[0] != "refined":
            return
        while True:
            try:
                arrived.append(requests.get_nowait())
            except queue.Empty:
                break
        if any(it is None or it[0] == "precompute" for it in arrived):
            raise _GiveWay

    while True:
        try:
            if arrived:
                item = arrived.popleft()
            else:
                item = requests.get() if not (refine or fast) else requests.get_nowait()
        except queue.Empty:
            idle.wait()
            init = None
            if refine and not (fast and fast[0][3]):
                nxt, kind = refine.popleft(), "refined"
            else:
                nxt, kind, init, _ = fast.popleft()
                if kind == "polished":
                    init = first.pop(GainSource.key(nxt), None)
            designing[0] = kind
            try:
                G, info = design_gains_for(nxt, kind, progress=between_iterations, init=init)
            except _GiveWay:
                refine.appendleft(nxt)
                continue
            finally:
                designing[0] = None
            if kind == "fast" and G is not None:
                first[GainSource.key(nxt)] = G
            elif kind == "fast":               # no stabilising gain: nothing to polish
                key = GainSource.key(nxt)
                fast = deque(e for e in fast if GainSource.key(e[0]) != key
                             or e[1] != "polished")
            results.put((nxt, G, info))
            continue
        if item is None:
            return
        if item[0] == "refine":
            refine.append(item[1])
        elif item[1] is None:                      # stand down (GainWorker.stand_down)
            refine, fast, first = deque(), deque(), {}
        else:
            fast, first = deque(precompute_queue(item[1], item[2])), {}


def precompute_queue(roster, G=None, planned=None) -> list:
    """What the precompute process designs for the configuration in force ``roster``
    (``G``: its gains, the warm start of each failure's fast gain; ``planned``: its
    :func:`plan_failures`, when the caller has it already), in order:
    ``[(configuration, kind, warm start, a single failure's first gain)]``: the fast gain
    of each planned failure (:func:`plan_failures`: singles first, then pairs), then
    their polish where that pays (:func:`refines_ahead`).

    >>> from design.roster import Roster
    >>> from design.scenario import load_scenario
    >>> [(kind, single) for _, kind, _, single
    ...  in precompute_queue(Roster.initial(load_scenario("paper-14-live")))][:4]
    [('fast', True), ('fast', True), ('fast', True), ('fast', False)]
    """
    from design.roster import carried_gains

    planned = plan_failures(roster) if planned is None else planned
    return ([(nxt, "fast", None if G is None else carried_gains(roster, G, nxt), len(a) == 1)
             for a, nxt in planned]
            + [(nxt, "polished", None, False) for _, nxt in planned if refines_ahead(nxt)])


class _GiveWay(Exception):
    """A refinement in progress gives way to a newer precompute."""


def performance_of(roster, G):
    """The exact radius and steady MSE of gain ``G`` on the configuration ``roster`` with
    its delays (:func:`design.closed_loop.exact_performance`)."""
    import numpy as np

    from design.closed_loop import exact_performance

    return exact_performance(roster.scenario, [np.asarray(g, dtype=float) for g in G],
                             np.asarray(roster.delays))


def _assess(item, results) -> None:
    _, roster, G, info = item
    perf = performance_of(roster, G)
    results.put((roster, G, {**info, "rho": perf.rho, "mse": perf.mse, "assessed": True}))


def plan_failures(roster) -> list:
    """``[(failed ids, next configuration)]`` for the failure of each single agent of
    ``roster`` (and of each pair when it has at most :data:`PAIRS_UP_TO` agents)."""
    import itertools

    from design.errors import SocmonError
    from design.roster import replan

    sets = [[a] for a in roster.ids]
    if len(roster.ids) <= PAIRS_UP_TO:
        sets += [list(p) for p in itertools.combinations(roster.ids, 2)]
    planned = []
    for a in sets:
        try:
            _, nxt = replan(roster, a, numerical=False)
        except SocmonError:
            continue
        if nxt is not None:
            planned.append((a, nxt))
    return planned


def refines_ahead(roster) -> bool:
    """Whether the precompute improves the fast gains of the failures it foresees for a
    configuration like ``roster`` (at most :data:`REFINE_AHEAD_MAX_STATES` estimator
    states): the precompute process's polish of each, the background process's
    refinement of each. Above the bound a foreseen failure switches to its fast gain and
    the configuration then in force is refined on request, once. The live worker and the
    simulated runtime both ask this.

    Why: improving ahead pays where the fast gain is far from the refined one and the
    refined design slow (paper-14-live: the fast gain's MSE 1.6-2.4x the refined one's,
    its polish 0.1-0.5 s of CPU, the refined design seconds to minutes). A large
    network's fast gain is the gains in force carried over, near the refined level
    already (communities-32's single failures: 2 % above the polished MSE;
    communities-16's 2.3 %), and improving it costs a network's worth of designs: a
    polish 4.7 s of CPU each at communities-32 (communities-16: 0.4-0.5 s, and its
    refinement 0.9-1.0 s), 300 s for the 32 failures (22 s for the 16), run beside the
    agents on two cores in the run's first seconds (the refinement niced even to 19),
    and their estimates came late: 2.9-3.0 % of them with the monitor, 0.4-1.2 % with
    neither pass (``scripts/bench_scale.py --sizes 32 --step-ms 20 --transports router
    --monitor``). 256 states keeps the small networks, where the gap is wide or the
    designs cost hundredths of a second (sampson-like, 72 states: 1.4 % for 0.03 s).

    >>> from design.roster import Roster
    >>> from design.scenario import load_scenario
    >>> [refines_ahead(Roster.initial(load_scenario(s)))
    ...  for s in ("paper-14-live", "communities-16", "communities-32")]
    [True, False, False]
    """
    return roster.scenario.n * len(roster.ids) <= REFINE_AHEAD_MAX_STATES


def unforeseen_single_failures(gains, planned) -> list:
    """The ids whose single failure in ``planned`` (:func:`plan_failures`) has no gains
    known to ``gains`` (a :class:`agent.monitor.core.GainSource`) yet: the first monitor
    joins a run once there are none (the live monitor and the simulated runtime both ask
    this)."""
    return [a[0] for a, nxt in planned if len(a) == 1 and not gains.known(nxt)]


def precompute_single_failures(roster, gains, stop=lambda: False, log=None,
                               passes=(False, True), G=None) -> int:
    """Plan (:func:`plan_failures`) and design gains for the failures of ``roster``.

    Two passes: a fast stabilising gain for every set first (tenths of a second each, so
    that a failure soon after start-up is already foreseen on a loaded machine), then the
    MSE-refined gain for every set, which replaces it (``passes``: which of the two,
    ``False`` for the fast one). ``G``: the gains in force on ``roster``; each refined
    design then starts from them (:func:`refined_gains_from`), else from the reset gain
    (``gains.design``)."""
    from design.roster import carried_gains

    planned = plan_failures(roster)
    done = 0
    for refined in passes:
        for a, nxt in planned:
            if stop():
                return done
            if not refined and gains.has(nxt):
                continue
            if refined and G is not None:
                G_nxt, info = refined_gains_from(nxt, carried_gains(roster, G, nxt))
            else:
                G_nxt, info = gains.design(nxt, refined=refined)
            gains.put(nxt, G_nxt, info)
            if G_nxt is not None:
                done += refined
            if log is not None and (refined or G_nxt is None):
                print(f"monitor: precomputed the failure of agents {a}: "
                      f"{'refined gains ready' if G_nxt is not None else 'no stabilising gain'}",
                      file=log, flush=True)
    return done


def refined_gains_from(roster, init, progress=None):
    """``(G, info)`` of the refined gain of ``roster`` (least steady MSE) as
    :func:`agent.monitor.core.design_gains_for` gives it (kind ``"refined"``), designed
    from ``init``: the gains in force carried over (:func:`design.roster.carried_gains`).
    Without a stable result, the design from the reset gain (and its fallbacks).

    Why: a single failure's configuration differs from the one in force by a row or two,
    and the gains in force (usually the MSE-designed gains of the configuration in
    force: its initial or refined ones) carried over start the MSE stage within a fraction
    of a percent of its minimum (communities-32: 0.3 % above it, against 1.9 % from the
    reset gain). From there the default stop rule (less than 1e-3 relative over 20
    iterations) cannot fire before 20 iterations: every warm design ended on "no
    decrease" after 8 to 17; the same mean rate judged over 5 iterations
    (:data:`design.reconfigure.WARM_PATIENCE`) stops after 6 to 8, with an
    exact steady MSE within 4e-6 (relative) of the design from the reset gain for each of
    communities-32's 32 single failures (README, "Gains for large networks")."""
    from agent.monitor.core import design_gains_for, with_residual_tests
    from design.errors import SocmonError
    from design.reconfigure import WARM_PATIENCE, WARM_PATIENCE_TOL, refined_recovery_gains

    try:
        res = refined_recovery_gains(roster.scenario, roster.delays, init=init,
                                     progress=progress, mse_patience=WARM_PATIENCE,
                                     mse_patience_tol=WARM_PATIENCE_TOL)
    except SocmonError:
        res = None
    if res is None or not res.stable:
        return design_gains_for(roster, "refined", progress)
    return with_residual_tests(roster, list(res.G), {
        "kind": "refined", "rho": float(res.rho),
        "mse": None if res.mse_steady is None else float(res.mse_steady),
        "seconds": float(res.seconds)})


class _Sink:
    """What :func:`precompute_single_failures` designs into: results go
    back to the monitor as they come."""

    def __init__(self, results):
        self.results = results
        self.sent: set = set()

    def has(self, roster) -> bool:
        from agent.monitor.core import GainSource

        return GainSource.key(roster) in self.sent

    def design(self, roster, refined: bool = False):
        from agent.monitor.core import design_gains_for

        return design_gains_for(roster, "refined" if refined else "fast")

    def put(self, roster, G, info=None) -> None:
        from agent.monitor.core import GainSource

        self.sent.add(GainSource.key(roster))
        self.results.put((roster, G, info or {}))


def _serve_background(requests, results) -> None:
    _quiet_signals()
    keep_freed_memory()
    try:
        os.nice(BACKGROUND_NICE)
    except OSError:
        pass
    nothing = object()             # no request read ahead (None is the close sentinel)
    pending = nothing
    while True:
        item = pending if pending is not nothing else requests.get()
        pending = nothing
        if item is None:
            return
        if item[0] == "assess":
            _assess(item, results)
            continue
        generation, roster, G = item
        if roster is None:                         # stand down (GainWorker.stand_down)
            continue
        if not refines_ahead(roster):              # a large network: see refines_ahead
            continue

        def superseded() -> bool:
            nonlocal pending
            while True:
                try:
                    newer = requests.get_nowait()
                except queue.Empty:
                    return False
                if newer is not None and newer[0] == "assess":
                    _assess(newer, results)        # between two refinements
                    continue
                pending = newer
                return True

        precompute_single_failures(roster, _Sink(results), stop=superseded, log=sys.stderr,
                                   passes=(True,), G=G)
