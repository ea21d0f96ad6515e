"""Gain design: one entry point, :func:`design_gains`, for every method.

Methods
-------
``ccl``
    The paper's Algorithm 1 (:mod:`design.ccl`): LMIs for the *delay-free* loop solved by
    cone-complementarity linearisation. The radius reported is nevertheless the exact
    one for the delays asked, so a delay-free design that the delays destabilise is
    reported unstable.
``default``
    First-order optimisation on the exact delayed closed loop (:mod:`design.gradient`):
    BFGS on the spectral radius of the companion matrix (eigenvalue sensitivities),
    and for ``objective="mse"`` then on the steady MSE (Lyapunov equation and adjoint),
    rejecting unstable steps. Several deterministic starts derived from ``seed``.

Before designing, the distributed pair ``(W (x) A, D_H)`` is checked: a parent SCC
without a sensor raises :class:`NotObservableError` naming it; an unobservable mode
on or outside the unit circle (not detectable) raises it too.

Examples
--------
>>> from design.scenario import load_scenario
>>> res = design_gains(load_scenario("paper-14"), delays="uniform:3", starts=1, max_iter=10)
>>> res.stable, res.rho < 1, len(res.G), res.G[0].shape
(True, True, 3, (14, 1))
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, field, replace

import numpy as np

from .ccl import SolverError, ccl_design
from .closed_loop import ClosedLoop
from .errors import NotObservableError, SocmonError
from .gap import GAP_MARGIN, gap_report
from .gradient import GapTerms, LoopModel, bfgs_minimise
from .graph import influence_structure, unmeasured_parents
from .observability import all_modes_stable, distributed_detectability
from .scenario import resolve_delays

__all__ = [
    "design_gains",
    "DesignResult",
    "DesignProgress",
    "DesignError",
    "blas_threads",
    "SolverError",
    "Detectability",
    "check_detectable",
    "resolve_design_delays",
    "METHODS",
    "OBJECTIVES",
]

METHODS = ("default", "ccl")
OBJECTIVES = ("rho", "mse")

_DEFAULT_OPTIONS = {
    "max_iter": 200,        # BFGS iterations per start and stage (bounds the work)
    "starts": None,         # number of starts (the first is deterministic, the rest from
                            # seed); None: 3 for objective rho, 1 for mse (or with init)
    "time_limit": None,     # optional safety cap in seconds (the best gain so far is
                            # returned); None: the result never depends on the machine
    "margin": 1e-3,         # the MSE stage keeps rho <= 1 - margin
    "smooth": 0.0,          # soft-max temperature over the top eigenvalue moduli
    "init": None,           # an initial gain (list of G_i) tried first, or "delay-free"
    "patience": 20,         # convergence window (iterations) ...
    "patience_tol": 1e-3,   # ... stop when the objective fell by less than this (relative)
    "mse_patience": None,   # the same for the MSE stage alone (None: patience, patience_tol)
    "mse_patience_tol": None,
    "blas_threads": 1,
    "target": None,         # objective rho: stop as soon as rho < target
    "mse": "impulse",       # MSE evaluation: "impulse" (structured) or "lyapunov" (dense)
    "gaps": True,           # keep every single failure's gap loop stable where possible
    "gap_margin": GAP_MARGIN,   # ... with exact radius below 1 - gap_margin
    "report_gaps": True,    # report every gap's exact radius (one eigenvalue problem each)
    "pair_rank": True,      # the distributed pair's rank even when W (x) A is stable (False:
                            # check_detectable(rank=False), the recovery designs)
    "exact_rho": True,      # False (objective rho, a target, init, no gaps, exact_mse False): a warm
                            # start counted below halfway from the target to 1 is taken without
                            # its exact radius (rho None, rho_below), the monitor's first gains
}
_CCL_OPTIONS = {
    "solver": "CLARABEL",
    "max_iter": 50,
    "keep_iterating": False,
    "eps": 1e-6,
    "time_limit": None,
    "solver_options": None,
    "blas_threads": 1,
}


#: The gap stage (:func:`_gap_stage`): soft-maximum temperature of the radii in its second
#: round (the first uses the top moduli; doubled each round), eigenvalues in the soft
#: maxima, rounds.
GAP_SMOOTH = 0.005
GAP_SOFTMAX_K = 6           # per gap loop
NOMINAL_SOFTMAX_K = 12      # the nominal radius (objective rho), see _gap_stage
GAP_ROUNDS = 5


class DesignError(SocmonError):
    """Bad design arguments (unknown method, objective, option or delay matrix)."""


@dataclass(frozen=True)
class DesignProgress:
    """One progress report of a running design (what ``progress=`` callables receive).

    Attributes
    ----------
    stage : str, e.g. ``"start 1 of 3, radius"``, ``"start 1 of 1, MSE"``, ``"ccl"``
    iteration : int, iteration within the stage (0: its starting point)
    iterations : int, iterations of the whole design so far
    quantity : "rho" or "mse", what ``value`` is
    value : float, the stage's current objective (the radius, or the steady MSE as the
        optimiser evaluates it; ``inf`` for an unstable point; ``nan`` in the final
        ``"certifying ..."`` stage, which has no iterations)
    best : float or None, the best objective of the starts already finished
    elapsed : float, seconds since the design began
    time_left : float or None, seconds until ``time_limit`` (None without one)
    max_iter : int, the stage's iteration budget
    """

    stage: str
    iteration: int
    iterations: int
    quantity: str
    value: float
    best: float | None
    elapsed: float
    time_left: float | None
    max_iter: int


@dataclass
class DesignResult:
    """What a design found.

    Attributes
    ----------
    G : list of (n, p_i) arrays
    method, objective : str
    delays : (N, N) int array, the delay matrix designed for and certified against
    rho : float or None, exact spectral radius of the delayed closed loop, recomputed from
        ``G``; None only with the option ``exact_rho`` False when the warm start's
        eigenvalues were counted below a bound (then ``rho_below``, :func:`counted_bound`)
    rho_below : float or None, with ``rho`` None: every eigenvalue of the loop has a
        modulus below this (:meth:`design.closed_loop.ClosedLoop.count_outside`)
    mse_steady : float or None, exact steady MSE ``trace(P)/(nN)`` (None when unstable)
    stable : bool, ``rho < 1`` (or, with ``rho`` None, counted below ``rho_below`` < 1)
    seconds : float, wall time of the design
    iterations : int, optimiser iterations (BFGS) or cone-complementarity iterations
    history : list of dict, one record per iteration / solve (status of every solve)
    status : str, why the design stopped
    gaps : list of dict, for the failure of each agent the gap loop the others run until
        the switch (:func:`design.gap.gap_report`, radii only): ``failed``,
        ``rho_exact``, ``stable``, ``own_loop_radius``
    gap_design : dict, what the gap terms of ``default`` did (empty for ``ccl``):
        ``enabled``, ``target`` (radius every gap is kept below), ``met``,
        ``rho_gap_before`` (gap radii of the nominal design, failed id -> radius),
        ``iterations``, ``impossible`` (gaps no gain can make stable: ``failed`` and
        ``bound``, their largest unobservable modulus), ``note``
    """

    G: list
    method: str
    objective: str
    delays: np.ndarray
    rho: float | None
    mse_steady: float | None
    stable: bool
    seconds: float
    iterations: int
    history: list = field(default_factory=list)
    status: str = ""
    seed: int = 0
    rho_delay_free: float = float("nan")
    detectability: dict = field(default_factory=dict)
    options: dict = field(default_factory=dict)
    gaps: list = field(default_factory=list)
    gap_design: dict = field(default_factory=dict)
    rho_below: float | None = None

    def summary(self) -> dict:
        """JSON-ready record (no gain arrays; ``rho_below`` only when the radius was
        counted, not computed)."""
        out = {
            "method": self.method,
            "objective": self.objective,
            "delays": np.asarray(self.delays).tolist(),
            "rho_exact": None if self.rho is None else float(self.rho),
            "mse_steady_exact": None if self.mse_steady is None else float(self.mse_steady),
            "stable": bool(self.stable),
            "seconds": float(self.seconds),
            "iterations": int(self.iterations),
            "status": self.status,
            "seed": int(self.seed),
            "rho_delay_free": float(self.rho_delay_free),
            "detectability": self.detectability,
            "gaps": list(self.gaps),
            "gap_design": dict(self.gap_design),
        }
        if self.rho_below is not None:
            out["rho_below"] = float(self.rho_below)
        return out


# ---------------------------------------------------------------------------------
# detectability


@dataclass(frozen=True)
class Detectability:
    """Observability of the distributed pair ``(W (x) A, D_H)``.

    ``rank`` of ``order`` = nN; ``unobservable_modes`` are the eigenvalues of the
    unobservable part; ``detectable`` iff all of them lie strictly inside the unit circle.
    ``rank`` and ``unobservable_modes`` are None when not computed (``check_detectable(...,
    rank=False)`` with every mode of W (x) A inside the unit circle).
    """

    rank: int | None
    order: int
    unobservable_modes: tuple | None
    detectable: bool

    @property
    def observable(self) -> bool | None:
        return None if self.rank is None else self.rank == self.order

    def to_dict(self) -> dict:
        if self.unobservable_modes is None:
            top = None
        else:
            top = max((abs(z) for z in self.unobservable_modes), default=0.0)
        return {"rank": self.rank, "order": self.order, "observable": self.observable,
                "detectable": self.detectable, "max_unobservable_modulus": top}


def check_detectable(scenario, rank: bool = True) -> Detectability:
    """Check that a stabilising structured gain can exist; raise if it cannot.

    ``rank=False``: when every mode of W (x) A lies inside the unit circle
    (:func:`design.observability.distributed_detectable`) the pair is detectable whatever
    its rank, which is then not computed (a staircase of order nN: the design's option
    ``pair_rank``, off for the monitor's recovery designs).

    Raises
    ------
    NotObservableError
        Some parent SCC of the influence graph holds no measured node (named by its
        labels), or the distributed pair has an unobservable mode with ``|lambda| >= 1``.

    Examples
    --------
    >>> from design.scenario import load_scenario
    >>> d = check_detectable(load_scenario("paper-14"))
    >>> d.rank, d.order, d.detectable
    (33, 42, True)
    """
    structure = influence_structure(scenario.A)
    measured = sorted({v for m in scenario.measure for v in m})
    missing = unmeasured_parents(structure, measured)
    if missing:
        sccs = [[scenario.labels[v] for v in structure.components[c]] for c in missing]
        names = "; ".join("{" + ", ".join(s) + "}" for s in sccs)
        raise NotObservableError(
            f"not observable: parent SCC{'s' if len(sccs) > 1 else ''} {names} "
            f"{'have' if len(sccs) > 1 else 'has'} no sensor; let an agent measure a node "
            "of each", sccs)

    order = scenario.n * scenario.N
    if not rank and all_modes_stable(scenario.A, scenario.W, scenario.measure):
        return Detectability(rank=None, order=order, unobservable_modes=None, detectable=True)
    p = distributed_detectability(scenario.A, scenario.W, scenario.measure)
    d = Detectability(rank=p.rank, order=p.order,
                      unobservable_modes=tuple(complex(z) for z in p.unobservable_modes),
                      detectable=p.detectable)
    if not d.detectable:
        raise NotObservableError(
            f"not detectable: the distributed pair (W (x) A, D_H) has rank {p.rank} of "
            f"{p.order} and an unobservable mode of modulus "
            f"{p.max_unobservable_modulus:.6g} >= 1; no gain can stabilise the estimator")
    return d


# ---------------------------------------------------------------------------------
# entry point


def design_gains(scenario, delays=None, method: str = "default", objective: str = "rho",
                 seed: int = 0, exact_mse: bool = True, progress=None,
                 **options) -> DesignResult:
    """Design the per-agent gains ``G_i`` for ``scenario``.

    Parameters
    ----------
    scenario : Scenario
    delays : None, str or (N, N) int array
        The delay matrix to design for (``default``) and to certify against (both):
        None = the scenario's, or ``"scenario"``, ``"none"``, ``"uniform:T"``.
    method : "default" or "ccl"
    objective : "rho" (minimise the exact spectral radius) or "mse" (minimise the exact
        steady mean-squared error subject to stability; ``default`` only)
    seed : int, seeds the extra starts of ``default`` (the result is deterministic)
    exact_mse : bool
        Certify the steady MSE of the result by the dense Lyapunov solve (default True;
        False leaves ``mse_steady`` None and saves that solve; the radius is always exact).
    progress : callable or None
        Called with a :class:`DesignProgress` at every optimiser iteration (and every
        conic solve of ``ccl``); it only observes (the design prints nothing itself).
    **options
        ``default``: ``max_iter`` (per start and stage, 200), ``starts`` (3 for
        objective rho; 1 for mse, whose smooth objective gains little from more starts
        (paper-14 uniform:7: 3.3835 from one start, 3.3803 from three), and 1 with
        ``init``),
        ``time_limit`` (s, None: an optional safety cap; without it the result depends
        only on the arguments, never on the machine's speed), ``margin`` (1e-3),
        ``smooth`` (0), ``init`` (a gain to start from, e.g. a neighbouring design or
        :func:`design.reconfigure.initial_gains`; or ``"delay-free"``: first design for
        the delay-free loop and start from it), ``patience``/``patience_tol`` (20, 1e-3:
        a stage stops when its objective fell by less than ``patience_tol`` relative over
        the last ``patience`` iterations; ``mse_patience``/``mse_patience_tol``, None:
        the same, set them for the MSE stage alone, e.g. a shorter window from a start
        near the minimum), ``target`` (objective rho: stop as soon as the
        radius is below it; default None = minimise), ``exact_rho`` (True; False with
        objective rho, a ``target``, ``init``, ``gaps`` and ``exact_mse`` False: a start
        whose eigenvalues are counted below halfway from the target to 1 by the
        argument principle (:func:`counted_bound`: a tenth of a dense eigenvalue
        problem's time at long delays) is the result without its exact radius: ``rho``
        None, ``rho_below`` that bound, ``stable`` True), ``mse`` ("impulse": the MSE and its
        gradient from the loop's impulse response, no dense solve; "lyapunov": two dense
        Lyapunov solves per evaluation, as before).
        ``ccl``: ``solver`` ("CLARABEL"/"SCS"), ``max_iter`` (50), ``keep_iterating``
        (False), ``eps`` (1e-6), ``time_limit`` (None), ``solver_options`` (dict for the
        solver).
        Both: ``blas_threads`` (1; None leaves the BLAS thread pool alone), see
        :func:`blas_threads`.

    Returns
    -------
    DesignResult
        ``stable`` False when no stabilising gain was found (the best gain is returned).

    Raises
    ------
    NotObservableError
        A parent SCC has no sensor, or the pair is not detectable.
    SolverError
        ``ccl``: a conic solve was infeasible, inaccurate or failed.
    DesignError
        Unknown method, objective or option.
    """
    t0 = time.perf_counter()
    if method not in METHODS:
        raise DesignError(f"method: expected one of {', '.join(METHODS)}, got {method!r}")
    if objective not in OBJECTIVES:
        raise DesignError(f"objective: expected one of {', '.join(OBJECTIVES)}, got {objective!r}")
    if method == "ccl" and objective == "mse":
        raise DesignError("objective: method ccl designs for stability (rho) only; use "
                          "method default for objective mse")
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise DesignError(f"seed: must be a non-negative integer, got {seed!r}")
    D = resolve_design_delays(scenario, delays)
    allowed = _DEFAULT_OPTIONS if method == "default" else _CCL_OPTIONS
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise DesignError(f"options {unknown} are not known to method {method} "
                          f"(known: {', '.join(sorted(allowed))})")
    opts = {**allowed, **options}
    if method == "default" and opts["mse"] not in ("impulse", "lyapunov"):
        raise DesignError(f"mse: expected 'impulse' or 'lyapunov', got {opts['mse']!r}")
    if method == "default" and opts["starts"] is None:
        opts["starts"] = 3 if objective == "rho" and opts["init"] is None else 1
    report = _Reporter(progress, t0, opts.get("time_limit"))
    with blas_threads(opts.pop("blas_threads")):
        return _design(scenario, D, method, objective, int(seed), opts, t0, exact_mse, report)


def blas_threads(count):
    """Context limiting the BLAS/LAPACK thread pool to ``count`` threads (None: no limit).

    Dense eigensolvers run one LAPACK call per iteration on matrices of a few hundred
    rows; on a loaded 2-core machine a multi-threaded BLAS spends most of its time
    waiting for its own threads (``scipy.linalg.eig`` of order 672: 0.45 s on one
    thread, 21 s on two contended ones). Uses threadpoolctl when it is installed.
    """
    if count is None:
        return contextlib.nullcontext()
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:          # pragma: no cover - optional dependency
        return contextlib.nullcontext()
    return threadpool_limits(limits=int(count), user_api="blas")


class _Reporter:
    """Turns the optimisers' ``(iteration, value)`` calls into :class:`DesignProgress`."""

    def __init__(self, progress, t0, time_limit):
        self.progress, self.t0 = progress, t0
        self.deadline = None if time_limit is None else t0 + float(time_limit)
        self.done = 0           # iterations of the finished stages
        self.best = None

    def stage(self, name, quantity, max_iter):
        """The callback of one stage (None when nobody listens)."""
        if self.progress is None:
            return None

        def report(iteration, value):
            now = time.perf_counter()
            self.progress(DesignProgress(
                stage=name, iteration=int(iteration), iterations=self.done + int(iteration),
                quantity=quantity, value=float(value),
                best=None if self.best is None else float(self.best),
                elapsed=now - self.t0,
                time_left=None if self.deadline is None else max(self.deadline - now, 0.0),
                max_iter=int(max_iter)))
        return report

    def finished(self, iterations, value=None):
        self.done += int(iterations)
        if value is not None and np.isfinite(value) and (self.best is None or value < self.best):
            self.best = float(value)


def _design(scenario, D, method, objective, seed, opts, t0, exact_mse=True, report=None):
    report = report or _Reporter(None, t0, None)
    detect = check_detectable(scenario, rank=opts.get("pair_rank", True))
    if method == "ccl":
        res = _design_ccl(scenario, D, opts, report)
    else:
        res = _design_default(scenario, D, objective, seed, opts, t0, report, exact_mse)
    G, history, iterations, status, rho_exact, gap_info = res
    # a warm start counted below a radius < 1 (option exact_rho False): stable, no exact
    # radius, MSE or gap report (ccl leaves rho_exact None too: its radius follows)
    below = (next(h["rho_below"] for h in reversed(history) if "rho_below" in h)
             if rho_exact is None and method != "ccl" and not exact_mse else None)
    gaps = []
    if below is not None:
        rho, stable, mse = None, True, None
    else:
        certify = report.stage("certifying (exact radius and steady MSE)", "rho", 0)
        if certify is not None:
            certify(0, float("nan"))    # one dense eigenvalue problem and Lyapunov solve
        # the exact radius of this very gain, computed once (by ClosedLoop) where the
        # design already did: a dense eigenvalue problem of order (taubar + 1) nN, or two
        # ARPACK runs, are not repeated (nor by the MSE's certificate, which needs it)
        loop = ClosedLoop(scenario.A, scenario.W, D, scenario.measure, G, rho=rho_exact)
        rho = loop.spectral_radius()
        stable = bool(rho < 1)
        mse = (loop.mse_steady(scenario.process_noise, scenario.measurement_noise)
               if stable and exact_mse else None)
        known = None
        if gap_info and not gap_info["iterations"]:      # the gains the gap radii were of
            known = {int(f): r for f, r in gap_info["rho_gap_before"].items()}
        gaps = ([g.to_dict() for g in gap_report(scenario, G, D, mse=False, radii=known)]
                if opts.get("report_gaps", True) or known else [])
        for g in gaps:
            g.pop("mse_steady_exact")
    # the delay-free loop: the same one when there are no delays
    rho0 = rho if rho is not None and not np.any(D) else ClosedLoop(
        scenario.A, scenario.W, np.zeros_like(D), scenario.measure, G).spectral_radius()
    shown = {k: v for k, v in opts.items() if k != "init"}
    return DesignResult(
        G=G, method=method, objective=objective, delays=D,
        rho=None if rho is None else float(rho),
        mse_steady=None if mse is None else float(mse), stable=stable,
        seconds=time.perf_counter() - t0, iterations=int(iterations), history=history,
        status=status, seed=int(seed), rho_delay_free=float(rho0),
        detectability=detect.to_dict(), options=shown, gaps=gaps,
        gap_design=gap_info or {}, rho_below=below,
    )


#: :func:`counted_bound`'s sample budget
COUNT_POINTS = 512


def counted_bound(loop, target: float) -> float | None:
    """Halfway from ``target`` to 1 when every eigenvalue of ``loop`` is counted below it
    (:meth:`design.closed_loop.ClosedLoop.count_outside`, no eigenvalue problem); None
    when one is not (or the count does not settle within :data:`COUNT_POINTS` points), or
    when the loop's dense eigenvalues cost as little
    (:attr:`design.closed_loop.ClosedLoop.count_pays`).

    Why halfway, not the target: a first gain must be certified stable, with a margin, at
    once. The carried gains of a failure's configuration often sit within a few % of the
    fast target (Sampson-like: 0.88-0.93 at 3- and 7-step delays, 0.94 at 15, against
    0.95), where a count at the target needs thousands of points (the error falls as
    (radius / circle)^K) and one halfway to 1 a few hundred; and the iterations that
    would bring a radius between the two below the target cost seconds of eigenvalue
    problems of order 1,152. The refined gain follows in any case."""
    if not loop.count_pays:
        return None
    c = (1.0 + float(target)) / 2
    if c < 1 and loop.count_outside(c, max_points=COUNT_POINTS) == 0:
        return c
    return None


def resolve_design_delays(scenario, delays) -> np.ndarray:
    """The (N, N) int delay matrix a design is made for: None (the scenario's), a spec
    string (``"none"``, ``"uniform:T"``...) or a matrix, checked; DesignError naming
    ``delays`` (ScenarioError for a matrix off the links of W)."""
    if delays is None:
        return scenario.delays.copy()
    if isinstance(delays, str):
        return resolve_delays(scenario, delays)
    D = np.asarray(delays)
    if D.shape != (scenario.N, scenario.N) or not np.issubdtype(D.dtype, np.integer):
        raise DesignError(f"delays: must be an {scenario.N} x {scenario.N} integer matrix, "
                          f"got {D.dtype} of shape {D.shape}")
    scenario.replace(delays=D.astype(int))      # validates: raises ScenarioError
    return D.astype(int)


def _design_ccl(scenario, D, opts, report):
    deadline = None if opts["time_limit"] is None else time.perf_counter() + opts["time_limit"]
    out = ccl_design(scenario.A, scenario.W, scenario.measure, solver=opts["solver"],
                     max_iter=int(opts["max_iter"]), keep_iterating=bool(opts["keep_iterating"]),
                     eps=float(opts["eps"]), deadline=deadline,
                     solver_options=opts["solver_options"],
                     callback=report.stage(f"ccl ({opts['solver']}), delay-free radius", "rho",
                                           opts["max_iter"]))
    return out["G"], out["history"], out["iterations"], out["reason"], None, None


def _starts(model, scenario, seed, count, init):
    """``count`` deterministic starting gains: ``init`` if given, then the 'reset' gain
    ``G_i = H_i^T`` (each agent replaces its measured states by the measurement), then
    seeded perturbations of it."""
    reset = model.pack([np.eye(scenario.n)[:, list(m)] for m in scenario.measure])
    starts = []
    if init is not None:
        starts.append(model.pack(init))
    starts.append(reset)
    rng = np.random.default_rng(seed)
    while len(starts) < count:
        starts.append(rng.uniform(0.3, 1.0) * reset + 0.3 * rng.standard_normal(model.size))
    return starts[:max(count, 1)]


def _design_default(scenario, D, objective, seed, opts, t0, report, exact_mse=True):
    model = LoopModel(scenario.A, scenario.W, D, scenario.measure)
    deadline = None if opts["time_limit"] is None else t0 + float(opts["time_limit"])
    smooth = float(opts["smooth"])
    common = dict(max_iter=int(opts["max_iter"]), deadline=deadline,
                  patience=int(opts["patience"]), patience_tol=float(opts["patience_tol"]))
    mse_common = dict(common)
    if opts["mse_patience"] is not None:
        mse_common["patience"] = int(opts["mse_patience"])
    if opts["mse_patience_tol"] is not None:
        mse_common["patience_tol"] = float(opts["mse_patience_tol"])
    init = opts["init"]
    if isinstance(init, str):
        if init != "delay-free":
            raise DesignError(f"init: a list of gains or 'delay-free', got {init!r}")
        sub = {k: v for k, v in opts.items() if k not in ("init", "time_limit")}
        sub["init"], sub["time_limit"] = None, None
        if deadline is not None:
            sub["time_limit"] = max(deadline - time.perf_counter(), 1e-3)
        sub["starts"] = 1
        sub["gaps"] = False         # the gap terms apply to the design for the delays
        warm = _Reporter(None if report.progress is None else
                         (lambda p: report.progress(replace(p, stage="delay-free warm start, "
                                                            + p.stage))), t0, None)
        warm.deadline = deadline
        init = _design_default(scenario, np.zeros_like(D), objective, seed, sub, t0, warm)[0]
        report.done += warm.done
    elif init is not None:
        from .gains import check_gains_fit
        check_gains_fit(list(init), scenario, where="init")
    starts = _starts(model, scenario, seed, int(opts["starts"]), init)
    q, r = scenario.process_noise, scenario.measurement_noise
    rho_max = 1.0 - float(opts["margin"])

    def f_rho(x):
        return model.spectral_radius_and_gradient(x, smooth=smooth)

    lowest = [np.inf]

    def f_mse(x, bound=np.inf):
        # a trial point whose error sum passes 10x the lowest MSE seen, or the line
        # search's sufficient-decrease threshold ``bound``, cannot be accepted: the
        # impulse sum stops there, without the gradient's backward pass (unstable points
        # end early; a step too long for the line search costs a part of the sum)
        J, g = model.mse_and_gradient(x, q, r, rho_max=rho_max, method=opts["mse"],
                                      bound=min(10.0 * lowest[0], bound))
        if g is None:
            return np.inf, np.zeros_like(x)
        lowest[0] = min(lowest[0], J)
        return J, g

    history, iterations = [], 0
    best = None            # (key, x, status)
    for k, x0 in enumerate(starts):
        if k and deadline is not None and time.perf_counter() > deadline:
            history.append({"stage": "stop", "note": f"time limit before start {k}"})
            break
        if (k == 0 and init is not None and objective == "rho"
                and opts["target"] is not None):
            below = (None if opts["exact_rho"] or exact_mse or opts["gaps"]
                     else counted_bound(model.closed_loop(x0), float(opts["target"])))
            if below is not None:
                # the result without any eigenvalue problem (its exact radius follows)
                status = f"the start's eigenvalues are counted below {below:g}"
                history.append({"stage": f"start {k} done", "rho_below": below,
                                "status": status})
                best = (None, x0, status, None)
                break
            rho = model.spectral_radius(x0)        # exact; needed for the result anyway
            if rho < float(opts["target"]):
                # a warm start already below the target: no iteration (one eigenvalue
                # problem instead of the gradient's eigenpairs and then the radius)
                status = "the start is below the target radius"
                history.append({"stage": f"start {k} done", "rho": float(rho),
                                "status": status})
                best = (rho, x0, status, rho)
                break
        label = f"start {k} rho"
        if objective == "mse":
            stop = lambda f: f < rho_max            # noqa: E731
        elif opts["target"] is not None:
            stop = lambda f: f < float(opts["target"])  # noqa: E731
        else:
            stop = None
        where = f"start {k + 1} of {len(starts)}"
        res = bfgs_minimise(f_rho, x0, stop=stop, label=label,
                            callback=report.stage(f"{where}, radius", "rho", common["max_iter"]),
                            **common)
        report.finished(res.iterations, res.f if objective == "rho" else None)
        history += res.history
        iterations += res.iterations
        x, status = res.x, res.reason
        rho = model.spectral_radius(x)
        if objective == "rho":
            key = rho
        else:
            if rho < rho_max:
                lowest[0] = np.inf
                res2 = bfgs_minimise(f_mse, x, label=f"start {k} mse",
                                     callback=report.stage(f"{where}, MSE", "mse",
                                                           common["max_iter"]),
                                     bounded=True, **mse_common)
                history += res2.history
                iterations += res2.iterations
                rho2 = model.spectral_radius(res2.x) if res2.iterations else rho
                if rho2 < 1.0:
                    x, status, rho = res2.x, res2.reason, rho2
                    key = (0, res2.f)
                    report.finished(res2.iterations, res2.f)
                else:
                    # a mode the noise does not reach went unstable: keep the stage-1 gain
                    status = f"{res2.reason}; MSE stage left the stable set, stage-1 gain kept"
                    J0 = model.mse_and_gradient(x, q, r, rho_max=1.0)[0]
                    key = (0, J0)
                    report.finished(res2.iterations, J0)
            else:
                key = (1, rho)      # not stabilised: ranks after every stable start
        history.append({"stage": f"start {k} done", "rho": float(rho), "status": status})
        if best is None or key < best[0]:
            best = (key, x, status, rho)        # rho: exact radius of x (ClosedLoop)
        if objective == "rho" and opts["target"] is not None and rho < float(opts["target"]):
            break
    _, x, status, rho = best
    gap_info = None
    if opts["gaps"]:
        x, status, rho, gap_info = _gap_stage(scenario, D, model, x, status, rho, objective,
                                              opts, common, report, history)
        iterations += gap_info["iterations"]
    return model.unpack(x), history, iterations, status, rho, gap_info


def _gap_stage(scenario, D, model, x, status, rho, objective, opts, common, report, history):
    """Keep the gap loops stable (:mod:`design.gap`).

    Nothing changes when every gap of the nominal design ``x`` has an exact radius below
    ``target = 1 - gap_margin`` (one radius per gap). Else, from ``x``, BFGS minimises
    the nominal objective plus the exact penalty ``mu * sum_f max(0, rho_f - threshold)``
    (``threshold = 1 - 1.5 gap_margin``) over the gaps that can be made stable, in up to
    five rounds until every gap is below the target: each round raises ``mu`` tenfold
    (from ``f(x) / gap_margin``: an excess of one margin costs the objective's own value).
    The first round follows the top eigenvalue moduli; the later ones soft maxima of the
    top few, at a temperature doubled each round: a radius minimised by the nominal
    design sits where many eigenvalues share the top modulus (paper-14 delay-free: more
    than six), and from there the gradient of the top modulus alone is no descent
    direction for the sum, that of a soft maximum over many of them is. With objective
    rho and a ``target``, a round stops as soon as the radius is below it and every
    gap below ``threshold``. Returns ``(x, status, rho, info)``."""
    margin = float(opts["gap_margin"])
    if not 0 < margin < 1:
        raise DesignError(f"gap_margin: must be in (0, 1), got {margin!r}")
    target, threshold = 1.0 - margin, 1.0 - 1.5 * margin
    terms = GapTerms(scenario, D)
    radii = terms.radii(x)
    info = {"enabled": True, "target": target, "iterations": 0,
            "rho_gap_before": {str(f): r for f, r in radii.items()}, "impossible": []}

    def done(x, status, rho, met, note):
        info["impossible"] = [{"failed": f, "bound": b} for f, b in terms.impossible]
        info["met"], info["note"] = bool(met and not terms.impossible), note
        if terms.impossible:
            info["note"] += "; " + ", ".join(
                f"the gap after agent {f} fails cannot be stable (unobservable mode of "
                f"modulus {b:.4g})" for f, b in terms.impossible)
        return x, status, rho, info

    if all(r < target for r in radii.values()):
        return done(x, status, rho, True, "the nominal design already keeps every gap stable")
    terms.drop_impossible(f for f, r in radii.items() if r >= target)
    if not terms.models:
        return done(x, status, rho, False, "no gap above the target can be made stable")
    q, r = scenario.process_noise, scenario.measurement_noise
    rho_max = 1.0 - float(opts["margin"])
    if objective == "mse":
        J0 = model.mse_and_gradient(x, q, r, rho_max=rho_max, method=opts["mse"])[0]

        def nominal(y, temperature):
            J, g = model.mse_and_gradient(y, q, r, rho_max=rho_max, method=opts["mse"],
                                          bound=10.0 * J0)
            return (np.inf, np.zeros_like(y)) if g is None else (J, g)
    else:
        def nominal(y, temperature):
            return model.spectral_radius_and_gradient(y, smooth=temperature,
                                                      k=NOMINAL_SOFTMAX_K)
    mu = max(abs(nominal(x, 0.0)[0]), 1e-6) / margin
    best = None                   # (worst gap radius, x, nominal rho)
    start = x
    seen = {}                     # total value -> (nominal value, penalty, worst gap)
    goal = opts["target"] if objective == "rho" else None
    for k in range(GAP_ROUNDS):
        temperature = 0.0 if k == 0 else GAP_SMOOTH * 2.0 ** (k - 1)

        def total(y, mu=mu, temperature=temperature):
            f, g = nominal(y, temperature)
            if not np.isfinite(f):
                return np.inf, np.zeros_like(y)
            P, gP, radii = terms.penalty_and_gradient(y, threshold, temperature,
                                                      GAP_SOFTMAX_K)
            value = f + mu * P
            seen[value] = (f, P, GapTerms.worst(radii))
            return value, g + mu * gP

        def stop(value):
            # objective rho with a target: stop once it and every gap are met (a soft
            # maximum is above the radius it stands for)
            f, P, _ = seen.get(value, (np.inf, np.inf, np.inf))
            return goal is not None and f < float(goal) and P == 0

        stage = report.stage(f"gap loops, round {k + 1}", "rho", common["max_iter"])
        callback = None if stage is None else (
            lambda it, value, stage=stage: stage(it, seen.get(value, (0, 0, np.inf))[2]))
        res = bfgs_minimise(total, start, label=f"gaps {k}", stop=stop, callback=callback,
                            **common)
        report.finished(res.iterations)
        history += res.history
        info["iterations"] += res.iterations
        mu *= 10.0
        if not res.iterations:
            continue
        rho_k = model.spectral_radius(res.x)
        if not rho_k < (rho_max if objective == "mse" else 1.0):
            continue              # the nominal loop left the stable set
        start = res.x
        worst = max(GapTerms.worst(terms.radii(res.x)), 0.0)
        if best is None or worst < best[0]:
            best = (worst, res.x, rho_k)
        if worst < target:
            break
    if best is None:
        return done(x, status, rho, False, "the gap terms found no better gain: nominal "
                    "design kept")
    worst, x, rho_k = best
    met = worst < target
    note = ("every gap kept below the target" if met else
            f"a gap stays above the target: best worst-gap radius {worst:.4g}")
    return done(x, f"{status}; gaps: {note}", rho_k, met, note)
