"""``socmon simulate``: one Monte-Carlo run of given gains, checked, reported and drawn.

Not the simulated runtime (:mod:`agent.run.simulated`): this runs the vectorised simulator
:func:`design.simulate.simulate` (timeline and conventions in docs/simulation.md) and
reports it beside the exact figures of its loop (:mod:`design.simulation_report`).

The steps, in the order the command takes them: :func:`simulate_options` checks the flags
that go together, :func:`design_recovery` designs the recovery of ``--recover``,
:func:`run_simulation` runs the trials and builds the record, :func:`write_figure` draws
it, :func:`format_text` says it. Bad input is an InputError naming the flag (exit 2); a
failure with no recovery, or no stabilising gain for it, exits 1.
"""

from __future__ import annotations

from dataclasses import dataclass

from agent.run.inputs import EXIT_NEGATIVE, EXIT_OK, InputError

__all__ = ["SimulateOptions", "SimulationReport", "simulate_options", "design_recovery",
           "run_simulation", "write_figure", "format_text"]


@dataclass(frozen=True, eq=False)
class SimulateOptions:
    """What one ``socmon simulate`` runs, parsed from its flags."""

    scenario: object
    gains: object                     # design.gains.Gains
    gains_file: str
    trials: int
    steps: int
    seed: int
    drop: float
    delays: object                    # (N, N) int array
    delays_spec: str
    fail: tuple | None = None         # (step, [0-based rows])
    recover: bool = False
    time_limit: float | None = None


@dataclass
class SimulationReport:
    record: dict                      # the --json record
    result: object                    # design.simulate.SimulationResult
    before: object                    # exact performance before any failure, or None

    @property
    def status(self) -> int:
        """Exit status: 1 when the run diverged or its loop is unstable, else 0."""
        return EXIT_NEGATIVE if self.record["diverged"] or self.record["unstable"] \
            else EXIT_OK


def simulate_options(scenario, gains, gains_file, *, trials, steps, seed, drop, delays,
                     delays_spec, fail=None, recover=False, time_limit=None):
    """A :class:`SimulateOptions`, the flags that go together checked (InputError)."""
    if recover and fail is None:
        raise InputError("--recover: needs --fail STEP:AGENTS")
    if fail is not None and not recover and len(fail[1]) == scenario.N:
        raise InputError("--fail: every agent fails; nothing is left to estimate "
                         "(use --recover)")
    if time_limit is not None and not (recover and time_limit > 0):
        raise InputError("--time-limit: a positive number of seconds, with --recover only")
    return SimulateOptions(scenario, gains, str(gains_file), trials, steps, seed, drop,
                           delays, delays_spec, fail, recover, time_limit)


def design_recovery(o: SimulateOptions, progress=None):
    """``(Recovery, info)`` of ``--recover`` (:func:`design.simulation_report.recovery_for`);
    no recovery or no stabilising gain for it is an InputError with status 1."""
    from design.reconfigure import RecoveryDesignError
    from design.simulation_report import recovery_for

    try:
        return recovery_for(o.scenario, o.gains, o.fail[1], o.delays_spec, o.seed,
                            time_limit=o.time_limit, progress=progress)
    except RecoveryDesignError as exc:
        raise InputError(f"--recover: {exc}", status=EXIT_NEGATIVE) from None


def run_simulation(o: SimulateOptions, recovery=(None, None),
                   progress=None) -> SimulationReport:
    """Simulate ``o`` (with ``recovery``, :func:`design_recovery`'s pair, from the failure
    step) and report it; ``progress(done, total)`` follows the trials."""
    from design.errors import SocmonError
    from design.simulate import simulate
    from design.simulation_report import simulation_record

    recover, recovery_info = recovery
    try:
        result = simulate(o.scenario, o.gains.G, steps=o.steps, trials=o.trials, seed=o.seed,
                          delays=o.delays, drop=o.drop, fail=o.fail, recover=recover,
                          progress=progress)
    except SocmonError as exc:
        raise InputError(str(exc)) from None
    except MemoryError:
        raise InputError(f"--steps/--trials: {o.trials} trials x {o.steps} steps do not fit "
                         "in memory; run fewer") from None
    record, before = simulation_record(o.scenario, o.gains.G, result, o.delays,
                                       gains_file=o.gains_file, delays_spec=o.delays_spec,
                                       recovery_info=recovery_info)
    return SimulationReport(record, result, before)


def write_figure(path, o: SimulateOptions, report: SimulationReport, plot_mse) -> None:
    """Draw the MSE of ``report`` into ``path`` with ``plot_mse`` (``agent.cli._plot``):
    the failure as an event, the exact steady MSE (before the failure and after the
    recovery, when known) as references; the record then names the figure."""
    out, s = report.record, o.scenario
    events = []
    if o.fail is not None:
        who = _agents(a + 1 for a in o.fail[1])
        events.append((o.fail[0], f"failure of {who}" + (" + recovery" if report.result.recovered
                                                         else "; MSE of the agents left")))
    ref = [(out["mse_steady_exact"], "exact steady MSE (Lyapunov)")]
    if out["mse_steady_exact_before_failure"] is not None:
        ref = [(out["mse_steady_exact_before_failure"], "exact steady MSE before the failure",
                0, o.fail[0])]
        after = out.get("recovery", {}).get("mse_steady_exact_after_recovery")
        if after is not None:
            ref.append((after, "exact steady MSE after recovery", o.fail[0], o.steps))
    try:
        plot_mse(path, [(f"{s.name}, {o.trials} trials", report.result)],
                 title=f"{s.name} (delays: {o.delays_spec})"
                       + (f", drop {o.drop:g}" if o.drop else ""),
                 events=events, reference=ref)
    except OSError as exc:
        raise InputError(f"--plot: cannot write {path!r}: {exc.strerror}") from None
    out["plot"] = str(path)


def _agents(ids) -> str:
    """``agent 1`` or ``agents 1, 2``."""
    ids = [str(a) for a in ids]
    return ("agent " if len(ids) == 1 else "agents ") + ", ".join(ids)


def _f(x, digits=5) -> str:
    if x is None:
        return "-"
    return f"{x:.{digits}g}" if isinstance(x, float) else str(x)


def format_text(d: dict) -> str:
    """The text ``socmon simulate`` prints for the record ``d``."""
    mse = d["mse"]
    lines = [
        f"scenario {d['scenario']}, gains {d['gains_file']}: {d['trials']} trials x "
        f"{d['steps']} steps, seed {d['seed']}"
        + (f", drop {d['drop']:g}" if d["drop"] else ""),
    ]
    if d["fail_step"] is not None:
        lines.append(f"failure of {_agents(d['failed'])} at step {d['fail_step']}"
                     + (" with recovery" if d["recovered"] else " (no recovery)")
                     + ": from then on the MSE is the mean over the agents still running "
                       "(a failed agent's error is not counted)")
        if d.get("mse_steady_exact_before_failure") is not None:
            lines.append("  exact steady MSE before the failure (Lyapunov): "
                         f"{_f(d['mse_steady_exact_before_failure'])}")
    if "recovery" in d:
        r = d["recovery"]
        for rep in r["replacements"]:
            lines.append(f"  node {rep['from']} of agent {rep['failed']} -> node {rep['to']} "
                         f"measured by agent {rep['by']}")
        if r["added_links"]:
            lines.append("  added links: " + ", ".join(
                f"{x['from']} -> {x['to']}" for x in r["added_links"]))
        lines.append(f"  exact radius after recovery: {r['rho_exact_after_recovery']:.6g}")
        if r.get("mse_steady_exact_after_recovery") is not None:
            lines.append("  exact steady MSE after recovery (Lyapunov): "
                         f"{_f(r['mse_steady_exact_after_recovery'])}"
                         + (" (without the drops)" if d["drop"] else ""))
    lines.append(f"MSE at step 0: {_f(mse[0] if isinstance(mse[0], float) else mse[0])}, "
                 f"at step {d['steps']}: {_f(mse[-1] if isinstance(mse[-1], float) else mse[-1])}")
    lines.append(f"steady MSE (mean over the last quarter): {_f(d['mse_steady'])}")
    if d.get("mse_steady_exact") is not None:
        lines.append(f"exact steady MSE (Lyapunov):            {_f(d['mse_steady_exact'])}")
    if d.get("rho_exact") is not None:
        lines.append(f"exact radius of the loop:               {d['rho_exact']:.6g}")
    if d.get("unstable"):
        lines.append("UNSTABLE: the exact radius is >= 1, so the error grows without bound "
                     "(a short run may not show it yet)")
    lines.append("DIVERGED" if d["diverged"] else "bounded over this run (did not diverge)")
    if d.get("plot"):
        lines.append(f"figure: {d['plot']}")
    return "\n".join(lines)
