"""What a user gives a run, loaded and checked: scenarios, gains files, timing, flags.

Every problem is an :class:`InputError` whose message names the flag or file and what is
wrong with it; the command line (:mod:`agent.cli`) prints it and exits with its status.
"""

from __future__ import annotations

import math
import sys
import warnings

from design.errors import GainsError, ScenarioError
from design.gains import load_gains
from design.scenario import load_scenario

EXIT_OK, EXIT_NEGATIVE, EXIT_BAD_INPUT = 0, 1, 2


class InputError(Exception):
    """Bad input (a flag, a file): its message names what is wrong; ``status`` is the exit
    status of the command that got it (2 = bad input, 1 = a negative result)."""

    def __init__(self, message: str, status: int = EXIT_BAD_INPUT):
        super().__init__(message)
        self.status = status


def load_scenario_arg(spec):
    """Load a scenario; a ScenarioError becomes a InputError (exit 2).

    Warnings (e.g. rank-deficient A) are printed to stderr, not raised.
    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            scenario = load_scenario(spec)
        except ScenarioError as exc:
            raise InputError(f"bad scenario: {exc}") from None
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    return scenario


def load_gains_arg(path, scenario, force: bool = False, flag: str = "--gains"):
    """Load the gains file of ``flag`` for ``scenario``; InputError (exit 2) naming the flag
    when it cannot be read, does not fit, or was designed for another scenario (its meta's
    ``scenario_digest`` is not ``scenario.digest()``) unless ``force`` (``--force-gains``),
    which prints a warning instead. A file without a digest (written by hand) is accepted."""
    try:
        gains = load_gains(path, scenario)
    except GainsError as exc:
        raise InputError(f"{flag}: {exc}") from None
    problem = gains_scenario_mismatch(gains.meta, scenario)
    if problem is not None:
        if not force:
            raise InputError(f"{flag}: {path}: {problem} (--force-gains to use it anyway)")
        print(f"warning: {flag}: {path}: {problem}", file=sys.stderr)
    return gains


def gains_scenario_mismatch(meta: dict, scenario) -> str | None:
    """Why the gains of ``meta`` were not designed for ``scenario``, or None when they were
    (or when the file does not say)."""
    digest = meta.get("scenario_digest")
    if digest is None or digest == scenario.digest():
        return None
    return (f"gains designed for scenario {meta.get('scenario', '?')!s} (digest {digest}), "
            f"not for scenario {scenario.name} (digest {scenario.digest()})")


def check_keys_arg(keys, scenario) -> None:
    """InputError naming ``--keys`` unless the key set in directory ``keys`` (None: no
    keys, nothing to check) was made for ``scenario``; a key set made before key sets
    recorded their scenario is used with a warning on stderr."""
    if keys is None:
        return
    from agent.protocol.topics import key_set_mismatch
    from broker_free_net.security import InvalidKeys, load_key_set

    try:
        ks = load_key_set(keys)
    except InvalidKeys as exc:
        raise InputError(f"--keys: {str(exc).removeprefix('keys: ')}") from None
    problem = key_set_mismatch(ks, scenario)
    if problem:
        raise InputError(f"--keys: {ks.dir} was {problem} (make a key set for this scenario "
                         "with socmon keys init)")
    if problem == "":
        print(f"warning: --keys: {ks.dir} does not record the scenario it was made for (made "
              f"before key sets recorded theirs): not checked against scenario "
              f"{scenario.name}; make a new key set with socmon keys init", file=sys.stderr)


def timing_arg(step_s: float | None = None, lead_steps: int | None = None, **fields):
    """The run's :class:`agent.protocol.timing.Timing` from flag values; InputError naming the flag
    and the broken relation otherwise (``fields``: Timing field -> value, None = default).

    >>> timing_arg(hang_timeout_s=2.0).hang_timeout_s
    2.0
    >>> timing_arg(hang_timeout_s=0.4)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    agent.run.inputs.InputError: --hang-timeout: 0.4 s must exceed 2 x status_s = 0.4 s (...); pause_guard_s: 0.5 s must be below hang_timeout_s = 0.4 s (...)
    """
    from agent.protocol.timing import DEFAULT

    timing = DEFAULT.replace(**{k: v for k, v in fields.items() if v is not None})
    problems = timing.problems(step_s=step_s, lead_steps=lead_steps)
    if problems:
        lines = []
        for line in problems:
            field, _, reason = line.partition(": ")
            flag = _TIMING_FLAGS.get(field)
            lines.append(f"{flag}: {reason}" if flag and field in fields else line)
        raise InputError("; ".join(lines))
    return timing


#: Timing fields set by a flag of some command (the rest are the runtime's constants).
_TIMING_FLAGS = {"hang_timeout_s": "--hang-timeout", "hang_timeout_max_s": "--hang-timeout-max",
                 "start_timeout_s": "--start-timeout"}


def check_run_flags(args) -> None:
    """Flags shared by the live-run commands: ``--seed`` >= 0, ``--start-timeout`` > 0."""
    seed = getattr(args, "seed", None)
    if seed is not None and seed < 0:
        raise InputError(f"--seed: must be a non-negative integer, got {seed}")
    timeout = getattr(args, "start_timeout", None)
    if timeout is not None and not (math.isfinite(timeout) and timeout > 0):
        raise InputError(f"--start-timeout: must be a positive number of seconds, got {timeout}")


#: the objective of the default gain, the one ``up``, ``agent`` and ``design`` all design
DEFAULT_OBJECTIVE = "mse"


def gains_for(scenario, gains_path, delays, force: bool = False, progress=None):
    """Load ``gains_path`` (``force``: even when designed for another scenario) or design the
    default gain (:func:`default_design`); InputError when impossible."""
    if gains_path:
        return load_gains_arg(gains_path, scenario, force=force).G
    return list(default_design(scenario, delays, progress).G)


def default_design(scenario, delays, progress=None):
    """The default gain's design (:class:`design.gain_design.DesignResult`): the steady MSE
    minimised on the exact delayed loop, certified stable, bounded by iterations and not by
    the clock, so that every process of a run designs the same gain (``progress``: as for
    :func:`design.gain_design.design_gains`). InputError when the scenario has none."""
    from design.errors import SocmonError
    from design.gain_design import design_gains

    try:
        result = design_gains(scenario, delays=delays, objective=DEFAULT_OBJECTIVE,
                              progress=progress)
    except SocmonError as exc:   # not observable / not detectable, bad delays
        raise InputError(f"gain design: {exc}") from None
    if not result.rho < 1:
        raise InputError(f"gain design found no stabilising gain (rho = {result.rho:.4g})",
                         status=1)
    return result
