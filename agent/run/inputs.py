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


def check_run_scenario(scenario, info) -> None:
    """InputError when ``scenario`` (SCENARIO as given) is not the scenario of the run of
    ``--attach`` (``info``, a :class:`agent.run.folder.RunInfo`): the run's own files (its
    gains, its manifest) would be read for another scenario and refused in their words."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            same = load_scenario(info.scenario_arg).digest() == scenario.digest()
    except (ScenarioError, OSError):         # the run's scenario file is gone: by name
        same = info.scenario == scenario.name
    if not same:
        theirs = info.scenario if info.scenario != scenario.name else \
            f"{info.scenario_arg} (another of the same name)"
        raise InputError(f"SCENARIO: the run in {str(info.folder)!r} (--attach) is of "
                         f"scenario {theirs}, not {scenario.name} (leave SCENARIO out to "
                         "take the run's)")


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
    """The run's :class:`agent.protocol.timing.Timing` from flag values; InputError otherwise,
    naming each flag with the bound it breaks (``fields``: Timing field -> value, None =
    default): the tightest of the runtime's own settings, and only then a bound set by
    another flag; a broken relation that involves no flag is said as it is.

    >>> timing_arg(hang_timeout_s=2.0).hang_timeout_s
    2.0
    >>> timing_arg(hang_timeout_s=0.1)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    agent.run.inputs.InputError: --hang-timeout: 0.1 s must exceed pause_guard_s = 0.5 s (a monitor paused ...)
    """
    import re

    from agent.protocol.timing import DEFAULT

    timing = DEFAULT.replace(**{k: v for k, v in fields.items() if v is not None})
    problems = timing.problems(step_s=step_s, lead_steps=lead_steps)
    if not problems:
        return timing
    # a flag changed from its default is the one named first (the user's to act on)
    flags = {f: _TIMING_FLAGS[f] for f in sorted(
        (f for f in fields if f in _TIMING_FLAGS),
        key=lambda f: getattr(timing, f) == getattr(DEFAULT, f))}
    if "must be a finite number" in problems[0]:    # no relation is checked then
        lines = [f"{flags[f]}: {reason}" if f in flags else line
                 for line in problems for f, _, reason in [line.partition(": ")]]
        raise InputError("; ".join(lines))
    others = [line for line in problems if not any(
        re.search(rf"\b{f}\b", line.split(" (")[0]) for f in flags)]
    raise InputError("; ".join(_flag_bounds(timing, flags) + others))


def _flag_bounds(timing, flags: dict) -> list:
    """For each flag (Timing field -> flag) whose value breaks a bound set by the runtime's
    own settings: the tightest one; when there is none, each relation broken between two
    flags, once."""
    from agent.protocol.timing import HOLDS, WORDS

    def tightest(broken):
        lower = [b for b in broken if b[0] in (">", ">=")]
        if lower:
            return max(lower, key=lambda b: (b[1], b[0] == ">"))
        return min(broken, key=lambda b: (b[1], b[0] != "<"))

    lines = []
    for field, flag in flags.items():
        value = getattr(timing, field)
        broken = [b for b in timing.bounds(field)
                  if b[2] not in flags and not HOLDS[b[0]](value, b[1])]
        if broken:
            op, bound, _, named, why = tightest(broken)
            lines.append(f"{flag}: {value:g} s {WORDS[op]} {named} = {bound:g} s ({why})")
    if lines:
        return lines
    said = set()
    for field, flag in flags.items():
        value = getattr(timing, field)
        for op, bound, other, _, why in timing.bounds(field):
            pair = frozenset((field, other))
            if other in flags and pair not in said and not HOLDS[op](value, bound):
                said.add(pair)
                lines.append(f"{flag}: {value:g} s {WORDS[op]} {flags[other]} = {bound:g} s "
                             f"({why})")
    return lines


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
