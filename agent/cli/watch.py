"""``socmon watch [SCENARIO] --run R --connect E``: attach to any run, show it live, record it.

Examples::

    socmon watch paper-14-live --run demo --connect tcp/127.0.0.1:7447 --gains g.npz
    socmon watch --attach runs/paper-14-live-20261123-101500-s0 --out watched/
    socmon watch paper-14-live --run demo --connect tcp/127.0.0.1:7447 --json | jq .mse
"""

from __future__ import annotations

HELP = "attach to a running deployment: live step, MSE, drops, failures; record a run folder"


def add_arguments(parser) -> None:
    from broker_free_net.config import add_net_arguments

    from agent.cli._common import add_attach_argument, int_flag

    parser.add_argument("scenario", nargs="?",
                        help="scenario TOML file or built-in name of the run (default with "
                             "--attach: the run's)")
    add_attach_argument(parser, takes=", and the scenario, gains, delays, seed and step "
                                      "period of the run")
    parser.add_argument("--gains", metavar="FILE",
                        help="the run's gains file: the predicted steady MSE and the "
                             "recovery figures need it (default with --attach: the run's; "
                             "else none is shown)")
    parser.add_argument("--delays", default=None,
                        help="the run's link delays, for the prediction: scenario, none or "
                             "uniform:T (default: the run's with --attach, else scenario)")
    parser.add_argument("--manifest", metavar="FILE",
                        help="the run's manifest.json: rosters and assignments count only when "
                             "signed with its control key, and the scenario and gains must be "
                             "the run's (default with --attach: the run's)")
    parser.add_argument("--seed", type=int_flag(lo=0), default=None,
                        help="the run's seed, written in the summary (default: the run's "
                             "with --attach)")
    parser.add_argument("--step-ms", type=float, default=None,
                        help="the run's step period, written in the summary")
    parser.add_argument("--steps", type=int_flag(lo=0), default=None,
                        help="stop once step STEPS is recorded (default: until the world "
                             "leaves, or Ctrl-C/SIGTERM)")
    parser.add_argument("--out", metavar="DIR",
                        help="write the run folder `socmon up` writes (summary.json, mse.csv, "
                             "mse.png, estimates.npz, ...) when the watch ends")
    parser.add_argument("--keep-steps", type=int_flag(lo=1), default=100_000, metavar="N",
                        help="keep the truth and estimates of the newest N steps only (the "
                             "run folder then covers them; default 100000, about 1.5 kB "
                             "per step for 14 states and 4 agents)")
    parser.add_argument("--json", action="store_true",
                        help="JSON lines on stdout: {\"kind\": \"view\", ...} while running, "
                             "then {\"kind\": \"summary\", ...}")
    parser.add_argument("--interval", type=float, default=None, metavar="S",
                        help="seconds between updates (default 0.25 on a terminal, else 1)")
    parser.add_argument("--timeout", type=float, default=60.0, metavar="S",
                        help="give up (exit 1) when nothing of the run is heard within S "
                             "seconds (default 60)")
    add_net_arguments(parser)


def run(args) -> int:
    from agent.cli._common import run_command

    return run_command(lambda: _watch(args))


def _watch(args) -> int:
    import json
    import math
    import sys
    from pathlib import Path

    from broker_free_net.config import InvalidNetConfig, net_config_from_args
    from design.errors import ScenarioError
    from design.scenario import resolve_delays

    from agent.run.live_view import LiveView
    from agent.run.summary import failure_lines
    from agent.run.watch import NoWorld, WatchConfig, watch
    from agent.cli._common import (CommandError, attach_run, load_gains_arg, load_scenario_arg,
                          to_jsonable, versioned)

    info = attach_run(args)
    scenario_arg = args.scenario or (info.scenario_arg if info else None)
    if scenario_arg is None:
        raise CommandError("SCENARIO: give the run's scenario (or --attach RUN_DIR)")
    scenario = load_scenario_arg(scenario_arg)
    delays_spec = args.delays or (info.delays if info and info.delays else "scenario")
    try:
        delays = resolve_delays(scenario, delays_spec)
    except ScenarioError as exc:
        raise CommandError(f"--delays: {exc}") from None
    gains = args.gains or (str(info.gains) if info and info.gains else None)
    G = list(load_gains_arg(gains, scenario).G) if gains else None
    control_public = _control_key(args.manifest or (info.manifest if info else None),
                                  scenario, gains)
    for flag, value in (("--interval", args.interval), ("--timeout", args.timeout),
                        ("--step-ms", args.step_ms)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise CommandError(f"{flag}: must be a positive number, got {value}")
    try:
        net = net_config_from_args(args, identity="recorder")
    except InvalidNetConfig as exc:
        raise CommandError(f"--{exc.field.replace('_', '-')}: {exc}") from None
    if not net.connect and not net.multicast:
        raise CommandError("--connect: give the endpoint of a process of the run "
                           "(or --attach RUN_DIR, or --multicast on a LAN)")
    config = WatchConfig(
        scenario=scenario, scenario_arg=scenario_arg, net=net, delays=delays,
        delays_spec=delays_spec, G=G, gains_path=Path(gains).resolve() if gains else None,
        seed=args.seed if args.seed is not None else (info.seed if info else None),
        steps=args.steps,
        step_ms=args.step_ms if args.step_ms is not None else (info.step_ms if info else None),
        out=Path(args.out) if args.out else None, timeout=args.timeout,
        keep_steps=args.keep_steps, control_public=control_public)
    tty = sys.stdout.isatty()
    mode = "json" if args.json else ("tty" if tty else "plain")
    interval = args.interval if args.interval is not None else (0.25 if tty else 1.0)
    if not args.json:
        print(f"watch: run {net.run} via {', '.join(net.connect) or 'multicast'}; Ctrl-C "
              f"ends the watch" + (f" and writes {args.out}" if args.out else ""),
              file=sys.stderr, flush=True)
    try:
        result = watch(config, LiveView(sys.stdout, mode, interval))
    except NoWorld as exc:
        raise CommandError(str(exc), status=1) from None
    summary = result.summary
    if args.json:
        print(json.dumps(to_jsonable(versioned({"kind": "summary", **summary}))), flush=True)
    else:
        pred = summary.get("mse_steady_exact")
        how = {"steps": "recorded up to --steps", "world ended": "ended with its world",
               "interrupted": "watched until interrupted"}.get(result.ended, result.ended)
        print(f"{scenario.name}: run {net.run} {how}, last step {summary['steps']}: "
              f"mse_steady {summary['mse_steady']:.4g}"
              + (f" (predicted {pred:.4g})" if pred is not None else " (no --gains: no "
                 "prediction)")
              + f", drops {summary['drops']}, late {summary['late']}, malformed "
                f"{summary['malformed']}")
        for line in failure_lines(summary):
            print(line)
        if args.out:
            print(f"run folder: {args.out}")
    return 130 if result.ended == "interrupted" else 0


def _control_key(manifest, scenario, gains) -> bytes | None:
    """The run's control public key from its manifest (None without one); the manifest's
    scenario and gains must be the ones given."""
    if manifest is None:
        return None
    from agent.protocol.manifest import ManifestMismatch, check_manifest, public_key
    from agent.cli._common import CommandError

    try:
        return public_key(check_manifest(manifest, scenario, gains, None, None),
                          "control_public_key")
    except ManifestMismatch as exc:
        raise CommandError(str(exc)) from None
