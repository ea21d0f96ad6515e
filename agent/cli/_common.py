"""Helpers shared by the subcommands: scenario/gains loading with clean errors, JSON."""

from __future__ import annotations

import json
import sys

from agent.run.jsonable import to_jsonable, versioned  # noqa: F401 - re-exported for the commands

# the checks of what a user gives live with the runs; the commands take them from here
from agent.run.inputs import (  # noqa: F401 - re-exported for the commands
    EXIT_BAD_INPUT,
    EXIT_NEGATIVE,
    EXIT_OK,
    check_run_flags,
    gains_for,
    gains_scenario_mismatch,
    load_gains_arg,
    load_scenario_arg,
    timing_arg,
)
from agent.run.inputs import InputError as CommandError


def add_scenario_argument(parser) -> None:
    parser.add_argument("scenario", help="scenario TOML file or built-in name (e.g. paper-14)")


def add_manifest_argument(parser) -> None:
    """``--manifest FILE`` of the processes of a run (agent.protocol.manifest)."""
    parser.add_argument("--manifest", metavar="FILE",
                        help="the run's manifest.json (socmon up writes one): refuse to start "
                             "when the scenario, gains, seed or delays differ from the run's")


def add_gains_argument(parser) -> None:
    """The required ``--gains FILE`` flag of the commands that evaluate a given gain."""
    parser.add_argument("--gains", required=True, metavar="FILE",
                        help="gains file (.npz with K1..KN and meta)")
    add_force_gains_argument(parser)


def add_force_gains_argument(parser) -> None:
    """``--force-gains``: accept a gains file designed for another scenario."""
    parser.add_argument("--force-gains", action="store_true",
                        help="accept a gains file whose scenario digest is not this "
                             "scenario's (by default that is an error, exit 2)")


def net_config_arg(args, identity: str):
    """The :class:`broker_free_net.NetConfig` of the transport flags; CommandError (exit 2)
    naming the flag (``--zenoh-config``, ``--listen``, ...) when a value is bad."""
    from broker_free_net.config import InvalidNetConfig, net_config_from_args

    try:
        return net_config_from_args(args, identity=identity)
    except InvalidNetConfig as exc:
        message = str(exc)
        if message.startswith(f"{exc.field}: "):
            message = message[len(exc.field) + 2:]
        raise CommandError(f"--{exc.field.replace('_', '-')}: {message}") from None


def _int_or_reason(text, lo: int, hi: int | None):
    """``(value, None)`` for an ASCII decimal integer in ``lo..hi``, else ``(None, reason)``.

    ``int`` alone also takes '1_000' and non-ASCII digits such as '١'; ``str.isdigit``
    takes '²', which ``int`` rejects: only an optional sign and ASCII digits pass here.
    """
    part = str(text).strip()
    body = part[1:] if part[:1] in ("-", "+") else part
    if not (body.isascii() and body.isdigit()):
        return None, f"expected an integer, got {part!r}"
    value = int(part)
    if value < lo or (hi is not None and value > hi):
        rng = f"{lo}..{hi}" if hi is not None else f">= {lo}"
        return None, f"must be an integer {rng}, got {value}"
    return value, None


def parse_int(text, flag: str, lo: int = 0, hi: int | None = None) -> int:
    """A decimal integer in ``lo..hi`` from a flag; CommandError naming the flag otherwise.

    The one integer parser of the command line (``int_flag`` and ``parse_int_list`` are
    built on it).

    >>> parse_int(" 12 ", "--steps", lo=1)
    12
    >>> parse_int("²", "--steps")
    Traceback (most recent call last):
    ...
    agent.run.inputs.InputError: --steps: expected an integer, got '²'
    >>> parse_int("0", "--trials", lo=1)
    Traceback (most recent call last):
    ...
    agent.run.inputs.InputError: --trials: must be an integer >= 1, got 0
    """
    value, reason = _int_or_reason(text, lo, hi)
    if reason is not None:
        raise CommandError(f"{flag}: {reason}")
    return value


def int_flag(lo: int = 0, hi: int | None = None):
    """An argparse ``type=`` for an integer flag in ``lo..hi`` (argparse names the flag).

    A bad value ends the command with exit status 2 and ``argument --flag: <reason>``.

    >>> int_flag(lo=1)("7")
    7
    """
    import argparse

    def convert(text):
        value, reason = _int_or_reason(text, lo, hi)
        if reason is not None:
            raise argparse.ArgumentTypeError(reason)
        return value

    convert.__name__ = "integer"
    return convert


def parse_int_list(text, flag: str, lo: int = 0, hi: int | None = None, *,
                   what: str = "expected comma-separated integers", item: str = "value",
                   out_of_range: str | None = None, unique: bool = False,
                   allow_empty: bool = False) -> list:
    """``"1, 2,3"`` -> ``[1, 2, 3]``: comma-separated ASCII integers in ``lo..hi``.

    Messages name the flag: a token that is not a non-negative integer gives
    ``"{flag}: {what}, got 'x'"``; a value out of range ``out_of_range`` (formatted with
    ``value``, ``lo``, ``hi``); a repeated one (``unique``) ``"{item} V listed twice"``;
    an empty list (unless ``allow_empty``) ``"give at least one {item}"``.

    >>> parse_int_list("3, 1", "--taus", hi=10)
    [3, 1]
    >>> parse_int_list("1,1", "--fail", lo=1, item="agent", unique=True)
    Traceback (most recent call last):
    ...
    agent.run.inputs.InputError: --fail: agent 1 listed twice
    """
    out = []
    for part in str(text).split(","):
        part = part.strip()
        if not part:
            continue
        if not (part.isascii() and part.isdigit()):
            raise CommandError(f"{flag}: {what}, got {part!r}")
        value = int(part)
        if value < lo or (hi is not None and value > hi):
            rng = f"{lo}..{hi}" if hi is not None else f">= {lo}"
            msg = (out_of_range or "{value} is not in {rng}").format(
                value=value, lo=lo, hi=hi, rng=rng)
            raise CommandError(f"{flag}: {msg}")
        if unique and value in out:
            raise CommandError(f"{flag}: {item} {value} listed twice")
        out.append(value)
    if not out and not allow_empty:
        raise CommandError(f"{flag}: give at least one {item}")
    return out


def parse_agent_list(text: str, scenario, flag: str = "--fail") -> list:
    """``"1,2"`` -> ``[0, 1]`` (0-based rows), checking each id names an active agent."""
    ids = parse_int_list(text, flag, lo=1, hi=scenario.N, unique=True, item="agent",
                         what="agent ids are positive integers",
                         out_of_range="no agent {value} (agents are 1..{hi})")
    return [a - 1 for a in ids]


def print_json(obj) -> None:
    """Print a command's ``--json`` record (with ``schema_version``, docs/json.md)."""
    json.dump(to_jsonable(versioned(obj) if isinstance(obj, dict) else obj), sys.stdout,
              indent=2)
    sys.stdout.write("\n")


def load_signer(path, flag: str = "--control-key"):
    """An :class:`agent.protocol.control_auth.ControlSigner` from a 32-byte key file; CommandError
    (exit 2) naming ``flag`` when it cannot be read or is not a key."""
    from agent.protocol.control_auth import ControlSigner

    try:
        with open(path, "rb") as f:
            return ControlSigner(f.read())
    except OSError as exc:
        raise CommandError(f"{flag}: cannot read {str(path)!r}: {exc.strerror}") from None
    except ValueError:
        raise CommandError(f"{flag}: {str(path)!r} is not a 32-byte Ed25519 private key") \
            from None


def run_command(body):
    """Run ``body()`` and turn a CommandError into its message and exit status, and a
    run folder that could not be written (:class:`agent.run.folder.RunFolderError`) into
    one line and :data:`agent.run.folder.EXIT_FOLDER`."""
    from agent.run.folder import EXIT_FOLDER, RunFolderError

    try:
        return body()
    except CommandError as exc:
        print(f"socmon: {exc}", file=sys.stderr)
        return exc.status
    except RunFolderError as exc:      # a full disk: one line, the files written stay whole
        print(f"socmon: run folder: {exc}", file=sys.stderr)
        return EXIT_FOLDER


def add_attach_argument(parser, takes: str = "") -> None:
    """``--attach RUN_DIR``: a run's coordinates from its ``run.json`` (agent.run.folder)."""
    parser.add_argument("--attach", metavar="RUN_DIR",
                        help="the folder of a running `socmon up`: take the run id, the "
                             "endpoint to connect to and, for a --secure run, the keys "
                             f"from its run.json{takes}; a flag given here wins")


def attach_run(args):
    """Fill ``--run``, ``--connect`` and ``--keys`` not given from ``--attach RUN_DIR``;
    returns the :class:`agent.run.folder.RunInfo` (None without ``--attach``)."""
    if not getattr(args, "attach", None):
        return None
    from agent.run.folder import InvalidRunFolder, read_run_info

    try:
        info = read_run_info(args.attach)
    except InvalidRunFolder as exc:
        raise CommandError(f"--attach: {exc}") from None
    if args.run is None:
        args.run = info.run
    if not args.connect:
        args.connect = [info.connect]
    if getattr(args, "keys", None) is None and info.keys is not None:
        args.keys = str(info.keys)
    return info



def parse_drop(text) -> float:
    try:
        p = float(str(text).strip())
    except ValueError:
        raise CommandError(f"--drop: expected a probability in [0, 1), got {text!r}") from None
    if not 0.0 <= p < 1.0:
        raise CommandError(f"--drop: expected a probability in [0, 1), got {text!r}")
    return p


def parse_fail(text, scenario, steps) -> tuple:
    """``"150:1,2"`` -> ``(150, [0, 1])`` (agents 0-based)."""
    step_text, sep, agents_text = str(text).partition(":")
    if not sep:
        raise CommandError(f"--fail: expected STEP:AGENTS (e.g. 150:1,2), got {text!r}")
    step = parse_int(step_text, "--fail STEP", lo=1)
    if step > steps:
        raise CommandError(f"--fail: step {step} is after the last step ({steps})")
    rows = parse_agent_list(agents_text, scenario, flag="--fail")
    return step, rows


def resolve_delays_arg(scenario, spec):
    from design.errors import ScenarioError
    from design.scenario import resolve_delays

    try:
        return resolve_delays(scenario, spec)
    except ScenarioError as exc:
        raise CommandError(str(exc)) from None
