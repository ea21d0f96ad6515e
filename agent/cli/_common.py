"""Helpers shared by the subcommands: their flags, scenario/gains loading with clean errors,
JSON."""

from __future__ import annotations

import contextlib
import json
import sys
from pathlib import Path

from agent.protocol.timing import DEFAULT as TIMING
from agent.run.jsonable import to_jsonable, versioned  # noqa: F401 - re-exported for the commands

# the checks of what a user gives live with the runs; the commands take them from here
from agent.run.inputs import (  # noqa: F401 - re-exported for the commands
    EXIT_BAD_INPUT,
    EXIT_NEGATIVE,
    EXIT_OK,
    check_keys_arg,
    check_run_flags,
    gains_for,
    gains_scenario_mismatch,
    load_gains_arg,
    load_scenario_arg,
    timing_arg,
)
from agent.run.inputs import InputError as CommandError


# Each flag that several commands take is defined once here (name, default, metavar, type),
# with a parameter only for what legitimately differs (a default, what the value serves);
# so are the two long groups of flags of `socmon up` alone, which keep up.py a thin command.
def add_scenario_argument(parser, attach: bool = False) -> None:
    """The ``SCENARIO`` argument; with ``attach`` optional (``--attach`` gives the run's)."""
    if attach:
        parser.add_argument("scenario", nargs="?",
                            help="scenario TOML file or built-in name of the run (default with "
                                 "--attach: the run's)")
    else:
        parser.add_argument("scenario", help="scenario TOML file or built-in name (e.g. paper-14)")


def add_manifest_argument(parser, use: str = "refuse to start when the scenario, gains, seed "
                                             "or delays differ from the run's") -> None:
    """``--manifest FILE`` of the processes of a run (agent.protocol.manifest)."""
    parser.add_argument("--manifest", metavar="FILE",
                        help=f"the run's manifest.json (socmon up writes one): {use}")


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


def add_designed_gains_arguments(parser, note: str = "") -> None:
    """``--gains`` of a live run (without it the default gain is designed), ``--force-gains``."""
    parser.add_argument("--gains", help="gains file (.npz); default: design with the default "
                                        f"method{note}")
    add_force_gains_argument(parser)


def add_seed_argument(parser, default: int | None = 0, help: str = "run seed (default 0)") -> None:
    """``--seed``, an integer >= 0 (``help``: what it seeds in this command)."""
    parser.add_argument("--seed", type=int_flag(lo=0), default=default, help=help)


def add_delays_argument(parser, what: str = "link delays injected at start", *,
                        attach: bool = False, metavar: str | None = None) -> None:
    """``--delays``: scenario, none or uniform:T (:func:`design.scenario.resolve_delays`);
    with ``attach`` it defaults to None, the run's with ``--attach``, else scenario."""
    when = ": the run's with --attach, else scenario" if attach else " scenario"
    parser.add_argument("--delays", default=None if attach else "scenario", metavar=metavar,
                        help=f"{what}: scenario, none or uniform:T (default{when})")


def add_step_ms_argument(parser, what: str = "period of one step in ms",
                         default: str = "the scenario's step_ms") -> None:
    """``--step-ms``: the period of one step of the run, in ms."""
    parser.add_argument("--step-ms", type=float, default=None, help=f"{what} (default: {default})")


def add_deadline_argument(parser, note: str = "") -> None:
    """``--deadline-ms``: an agent's wait for late neighbour estimates (``note``: more on
    the default)."""
    parser.add_argument("--deadline-ms", type=float, default=None,
                        help="how long an agent waits after a step's readings for late "
                             f"neighbour estimates (default: the step period{note})")


def add_monitor_arguments(parser) -> None:
    """``--no-monitor``, ``--monitors N`` and ``--no-precompute``: the monitors a local run
    starts."""
    parser.add_argument("--no-monitor", action="store_true",
                        help="run without the monitor (a failed agent is then never replaced)")
    parser.add_argument("--monitors", type=int_flag(lo=1, hi=9), default=None, metavar="N",
                        help="monitors started (default 2): the first acts, the others stand "
                             "by and take over when it dies or is paused")
    parser.add_argument("--no-precompute", action="store_true",
                        help="the monitors design no failure's gains ahead: each failure waits "
                             "for its first gain to be designed on request (less CPU at the "
                             "start and after every switch; slower answers)")


def add_drop_argument(parser) -> None:
    """``--drop P`` of a live run: estimates lost on a link, drawn from the run seed."""
    parser.add_argument("--drop", type=float, default=0.0,
                        help="probability that an estimate is lost on a link, drawn from the run "
                             "seed as the simulator draws it (default 0)")


def add_start_timeout_argument(parser, waits_for: str = "every process to be up") -> None:
    """``--start-timeout S`` (agent.protocol.timing)."""
    parser.add_argument("--start-timeout", type=float, default=TIMING.start_timeout_s,
                        help=f"seconds to wait for {waits_for} "
                             f"(default {TIMING.start_timeout_s:g})")


def add_hang_timeout_arguments(parser, with_max: bool = True) -> None:
    """The monitor's ``--hang-timeout S`` and (``with_max``) ``--hang-timeout-max S``."""
    parser.add_argument("--hang-timeout", type=float, default=TIMING.hang_timeout_s,
                        metavar="S",
                        help="the monitor's hang timeout: no progress of an agent for S seconds "
                             "while the others advance is a hang (default "
                             f"{TIMING.hang_timeout_s:g}; lower is faster and risks convicting "
                             f"a slow agent; above twice the status period {TIMING.status_s:g} s)")
    if with_max:
        parser.add_argument("--hang-timeout-max", type=float, default=TIMING.hang_timeout_max_s,
                            metavar="S",
                            help="the hang timeout grows with the statuses' observed pace up to "
                                 f"S seconds (default {TIMING.hang_timeout_max_s:g}; equal to "
                                 "--hang-timeout keeps it fixed; docs/monitor.md)")


def add_run_folder_arguments(parser, default: str) -> None:
    """``--out`` (the run folder, ``default`` its name when not given) and ``--overwrite``."""
    parser.add_argument("--out", help=f"run folder (default {default}); a folder holding an "
                                      "earlier run is refused")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the earlier run in --out (its files only)")


def add_fault_schedule_arguments(parser) -> None:
    """The faults scheduled into a local run (``socmon up``'s alone; checked by
    :func:`agent.run.setup.live_run`): ``--kill``, ``--stop``, ``--kill-monitor``, ``--fault``."""
    parser.add_argument("--kill", action="append", default=[], metavar="STEP:AGENTS",
                        help="scripted crash: agents (e.g. 1,2) publish step STEP-1 and SIGKILL "
                             "themselves (repeatable)")
    parser.add_argument("--stop", action="append", default=[], metavar="STEP:AGENT:SECONDS",
                        help="SIGSTOP agent AGENT once the world reaches STEP, SIGCONT it "
                             "SECONDS later (repeatable)")
    parser.add_argument("--kill-monitor", type=int_flag(lo=1), default=None, metavar="STEP",
                        help="SIGKILL the monitor once the world reaches STEP and start it again")
    parser.add_argument("--fault", action="append", default=[],
                        metavar="KIND:STEP[:AGENT[:SECONDS[:VALUE]]]",
                        help="any scheduled fault (repeatable): kill, stop, hang (the agent's "
                             "loop stops, its token stays), sensor (its readings stop for "
                             "SECONDS), partition, delay (VALUE steps), drop (VALUE "
                             "probability), monitor, linkdown (the agent's host's link down "
                             "for SECONDS; with --netns), worldstop and monitorstop (the "
                             "world or the monitor SIGSTOPped for SECONDS: "
                             "worldstop:STEP::SECONDS), monitorsgone (every monitor "
                             "SIGKILLed for good), lie (the agent publishes its estimates "
                             "VALUE noise std-devs off from STEP: lie:STEP:AGENT:0:VALUE, "
                             "docs/residuals.md), bias, drift, noise (the agent's sensor "
                             "goes wrong from STEP: VALUE noise std-devs added, VALUE "
                             "std-devs more each 100 steps, or its noise VALUE times its "
                             "model: bias:STEP:AGENT:0:VALUE); see docs/monitor.md")


def add_local_transport_arguments(parser) -> None:
    """How the processes of a local run (``socmon up``'s alone) reach each other: ``--run``,
    ``--listen``, ``--secure``, ``--netns``, ``--netns-prefix``, ``--router``."""
    parser.add_argument("--run", default=None, metavar="ID",
                        help="run id (key prefix socmon/<ID>/; default a fresh one); printed "
                             "and written in RUN_FOLDER/run.json")
    parser.add_argument("--listen", default=None, metavar="ENDPOINT",
                        help="the endpoint every process of the run and every attached tool "
                             "connects to: this command's own peer's, the router's with "
                             "--router (default tcp/127.0.0.1:<free port>, tls/ with --secure; "
                             "not with --netns)")
    parser.add_argument("--secure", action="store_true",
                        help="a fresh key set for this run (RUN_FOLDER/keys): mutual TLS between "
                             "every process and access control on every peer "
                             "(docs/security.md)")
    parser.add_argument("--netns", action="store_true",
                        help="each process on its own host: a network namespace per process, "
                             "wired by veth pairs to a bridge in a switch namespace, 10.200.0.x "
                             "addresses; removed after the run (needs root; docs/runtime.md)")
    parser.add_argument("--netns-prefix", default=None, metavar="PREFIX",
                        help="namespace names PREFIX-<host> (default sm<pid>)")
    parser.add_argument("--router", action="store_true",
                        help="start a zenoh router (socmon router) and make every process its "
                             "client: one link per process instead of the peer mesh's "
                             "N(N-1)/2 (docs/transport.md)")


def add_web_arguments(parser, what: str = "the run") -> None:
    """``--web [HOST:]PORT`` and ``--web-remote``: a live page of the run
    (:mod:`agent.run.web`)."""
    parser.add_argument("--web", metavar="[HOST:]PORT",
                        help=f"serve a live web page of {what} (network, agents' states, "
                             "verdicts and reassignments, MSE against its exact level) on "
                             "http://HOST:PORT/; HOST defaults to 127.0.0.1 (loopback only), "
                             "PORT 0 picks a free one; nothing is fetched from elsewhere")
    parser.add_argument("--web-remote", action="store_true",
                        help="allow --web on an address other than loopback (anyone who "
                             "reaches it sees the run; no authentication)")


def add_operator_key_arguments(parser) -> None:
    """``--attach``, ``--operator-key`` (and its deprecated name ``--control-key``),
    ``--timeout`` and ``--no-confirm``: how ``socmon inject`` signs a change and waits for
    the agents to confirm it."""
    add_attach_argument(parser, takes=", and its operator key (RUN_FOLDER/operator.key) to "
                                      "sign the change")
    parser.add_argument("--operator-key", metavar="FILE",
                        help="the run's operator key (socmon up writes RUN_FOLDER/operator.key): "
                             "sign the change, as agents started with the run's manifest "
                             "require")
    parser.add_argument("--control-key", dest="deprecated_control_key", metavar="FILE",
                        help="deprecated name of --operator-key (still works, with a warning): "
                             "this is the operator key, not the control key monitor "
                             "--control-key takes")
    parser.add_argument("--timeout", type=float, default=10.0,
                        help="seconds to wait for the agents to confirm (default 10)")
    parser.add_argument("--no-confirm", action="store_true",
                        help="publish and exit without waiting for confirmation")


@contextlib.contextmanager
def served_page(args, command: str):
    """The live page of ``--web``/``--web-remote`` (None without them) for the ``with``
    block, its address said on stderr as ``<command>: ...`` (even with ``--quiet``: it is
    what was asked for)."""
    from agent.run.web import open_page, page_words

    page = open_page(args.web, args.web_remote)
    with page or contextlib.nullcontext():
        if page is not None:
            print(f"{command}: {page_words(page)}", file=sys.stderr, flush=True)
        yield page


def add_json_argument(parser, help: str = "print JSON instead of text") -> None:
    """``--json``: the command's record on stdout as JSON (docs/json.md)."""
    parser.add_argument("--json", action="store_true", help=help)


def add_quiet_argument(parser) -> None:
    """``--quiet``: no progress lines on stderr."""
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")


def net_config_arg(args, identity: str):
    """The :class:`broker_free_net.NetConfig` of the transport flags; CommandError (exit 2)
    naming the flag (``--zenoh-config``, ``--listen``, ...) when a value is bad."""
    from broker_free_net.config import InvalidNetConfig, net_config_from_args

    try:
        return net_config_from_args(args, identity=identity)
    except InvalidNetConfig as exc:
        raise CommandError(exc.as_flag()) from None


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
    """``"1,2"`` -> ``[0, 1]`` (0-based rows), checking each id names an active agent (a
    standby's failure is ``up``'s and ``chaos``'s: here it would change no estimate)."""
    N = scenario.N
    ids = parse_int_list(text, flag, lo=1, hi=N + scenario.standby, unique=True, item="agent",
                         what="agent ids are positive integers",
                         out_of_range=f"no agent {{value}} (agents are 1..{N})")
    for a in ids:
        if a > N:
            raise CommandError(f"{flag}: agent {a} is a standby of the scenario, which "
                               f"estimates nothing here: fail active agents (1..{N})")
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


def operator_signer(args, warn):
    """The signer of ``socmon inject``'s change: ``--operator-key`` (or its deprecated name,
    ``warn(text)`` saying so), else the operator key of the ``--attach``-ed run, else None
    (the change goes unsigned). The key flags are checked before ``--attach`` is read
    (:func:`attach_run`, which fills ``--run`` and the transport from the run)."""
    from agent.run.inject import operator_key_arg

    key, flag = operator_key_arg(args.operator_key, args.deprecated_control_key, warn=warn)
    info = attach_run(args)
    if key is None and info is not None and info.operator_key is not None:
        key, flag = str(info.operator_key), "--attach"
    return load_signer(key, flag) if key else None


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
    except Exception as exc:
        # a zenoh session that could not be opened (an endpoint not reached in time, a
        # port taken) or an id another process of the run holds: one line; the transport
        # is loaded only by the commands that open one
        peer = sys.modules.get("broker_free_net.peer")
        if peer is None or not isinstance(exc, (peer.SessionError, peer.IdInUse)):
            raise
        print(f"socmon: {exc}", file=sys.stderr)
        return 1


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
    if (Path(args.attach) / "summary.json").exists():    # written as the run ends
        raise CommandError(f"--attach: the run in {args.attach!r} has ended (its summary.json "
                           "is written): no process of it is left to reach")
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
