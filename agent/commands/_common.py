"""Helpers shared by the subcommands: scenario/gains loading with clean errors, JSON."""

from __future__ import annotations

import json
import math
import sys
import warnings

import numpy as np

EXIT_OK, EXIT_NEGATIVE, EXIT_BAD_INPUT = 0, 1, 2


class CommandError(Exception):
    """Abort a command with a message and an exit status (2 = bad input)."""

    def __init__(self, message: str, status: int = EXIT_BAD_INPUT):
        super().__init__(message)
        self.status = status


def add_scenario_argument(parser) -> None:
    parser.add_argument("scenario", help="scenario TOML file or built-in name (e.g. paper-14)")


def add_gains_argument(parser) -> None:
    """The required ``--gains FILE`` flag of the commands that evaluate a given gain."""
    parser.add_argument("--gains", required=True, metavar="FILE",
                        help="gains file (.npz with K1..KN and meta)")


def load_scenario_arg(spec):
    """Load a scenario; a ScenarioError becomes a CommandError (exit 2).

    Warnings (e.g. rank-deficient A) are printed to stderr, not raised.
    """
    from design.errors import ScenarioError
    from design.scenario import load_scenario

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            scenario = load_scenario(spec)
        except ScenarioError as exc:
            raise CommandError(f"bad scenario: {exc}") from None
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    return scenario


def load_gains_arg(path, scenario):
    from design.errors import GainsError
    from design.gains import load_gains

    try:
        return load_gains(path, scenario)
    except GainsError as exc:
        raise CommandError(f"bad gains file: {exc}") from None


def parse_count(text: str, flag: str, lo: int = 0, hi: int | None = None) -> int:
    """A decimal integer in ``lo..hi`` from a flag; CommandError naming the flag otherwise.

    ``str.isdigit`` accepts characters such as '²' that ``int`` rejects: only ASCII digits
    are taken here.
    """
    part = str(text).strip()
    body = part[1:] if part.startswith("-") else part
    if not (body.isascii() and body.isdigit()):
        raise CommandError(f"{flag}: expected an integer, got {part!r}")
    value = int(part)
    if value < lo or (hi is not None and value > hi):
        rng = f"{lo}..{hi}" if hi is not None else f">= {lo}"
        raise CommandError(f"{flag}: must be {rng}, got {value}")
    return value


def check_run_flags(args) -> None:
    """Flags shared by the live-run commands: ``--seed`` >= 0, ``--start-timeout`` > 0."""
    seed = getattr(args, "seed", None)
    if seed is not None and seed < 0:
        raise CommandError(f"--seed: must be a non-negative integer, got {seed}")
    timeout = getattr(args, "start_timeout", None)
    if timeout is not None and not (math.isfinite(timeout) and timeout > 0):
        raise CommandError(f"--start-timeout: must be a positive number of seconds, got {timeout}")


def parse_agent_list(text: str, scenario, flag: str = "--fail") -> list:
    """``"1,2"`` -> ``[0, 1]`` (0-based), checking each id names an active agent."""
    ids = []
    for part in str(text).split(","):
        part = part.strip()
        if not part:
            continue
        if not (part.isascii() and part.isdigit()):
            raise CommandError(f"{flag}: agent ids are positive integers, got {part!r}")
        a = int(part)
        if not 1 <= a <= scenario.N:
            raise CommandError(f"{flag}: no agent {a} (agents are 1..{scenario.N})")
        if a - 1 in ids:
            raise CommandError(f"{flag}: agent {a} listed twice")
        ids.append(a - 1)
    if not ids:
        raise CommandError(f"{flag}: give at least one agent id")
    return ids


def to_jsonable(obj):
    """numpy-aware conversion; non-finite floats become strings "inf"/"nan"."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        x = float(obj)
        return x if math.isfinite(x) else ("inf" if x > 0 else "-inf" if x < 0 else "nan")
    return obj


def print_json(obj) -> None:
    json.dump(to_jsonable(obj), sys.stdout, indent=2)
    sys.stdout.write("\n")


def run_command(body):
    """Run ``body()`` and turn a CommandError into its message and exit status."""
    try:
        return body()
    except CommandError as exc:
        print(f"socmon: {exc}", file=sys.stderr)
        return exc.status
