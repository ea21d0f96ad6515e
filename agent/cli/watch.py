"""``socmon watch [SCENARIO] --run R --connect E``: attach to any run, show it live, record it.

Its flags become a :class:`agent.run.watch.WatchConfig` (:func:`agent.run.watch.watch_config`).

Examples::

    socmon watch paper-14-live --run demo --connect tcp/127.0.0.1:7447 --gains g.npz
    socmon watch --attach runs/paper-14-live-20261123-101500-s0 --out watched/
    socmon watch paper-14-live --run demo --connect tcp/127.0.0.1:7447 --json | jq .mse
"""

from __future__ import annotations

import sys

from agent.cli._common import CommandError, attach_run, run_command

HELP = "attach to a running deployment: live step, MSE, drops, failures; record a run folder"


def add_arguments(parser) -> None:
    from broker_free_net.config import add_net_arguments

    from agent.cli import _common as c

    c.add_scenario_argument(parser, attach=True)
    c.add_attach_argument(parser, takes=", and the scenario, gains, delays, seed and step "
                                        "period of the run")
    parser.add_argument("--gains", metavar="FILE",
                        help="the run's gains file, for the predicted MSE and recovery figures "
                             "(default with --attach: the run's; else none shown)")
    c.add_delays_argument(parser, "the run's link delays, for the prediction", attach=True)
    c.add_manifest_argument(parser, "rosters and assignments count only when signed with its "
                                    "control key, and the scenario and gains must be the run's "
                                    "(default with --attach: the run's)")
    c.add_seed_argument(parser, default=None, help="the run's seed, written in the summary "
                                                   "(default: the run's with --attach)")
    c.add_step_ms_argument(parser, "the run's period of one step in ms, written in the summary",
                           default="the run's with --attach")
    parser.add_argument("--steps", type=c.int_flag(lo=0), default=None,
                        help="stop once step STEPS is recorded (default: until the world "
                             "leaves, or Ctrl-C/SIGTERM)")
    parser.add_argument("--out", metavar="DIR",
                        help="write the run folder `socmon up` writes (summary.json, mse.csv, "
                             "mse.png, estimates.npz, ...) when the watch ends")
    parser.add_argument("--keep-steps", type=c.int_flag(lo=1), default=100_000, metavar="N",
                        help="keep the newest N steps' truth and estimates only (the run "
                             "folder covers them; default 100000, 1.5 kB a step at n=14, M=4)")
    c.add_json_argument(parser, "JSON lines on stdout: {\"kind\": \"view\", ...} while "
                                "running, then {\"kind\": \"summary\", ...}")
    parser.add_argument("--interval", type=float, default=None, metavar="S",
                        help="seconds between updates (default 0.25 on a terminal, else 1)")
    parser.add_argument("--timeout", type=float, default=60.0, metavar="S",
                        help="exit 1 if nothing of the run is heard within S s (default 60)")
    c.add_web_arguments(parser, "the watched run")
    add_net_arguments(parser)


def run(args) -> int:
    return run_command(lambda: _watch(args))


def _watch(args) -> int:
    from agent.cli._common import served_page
    from agent.run.watch import (NoWorld, exit_status, live_view_for, start_line,
                                 summary_json, summary_lines, watch, watch_config)

    config = watch_config(args, attach_run(args))
    with served_page(args, "watch") as page:
        if not args.json:
            print(start_line(config, args.out), file=sys.stderr, flush=True)
        try:
            result = watch(config, live_view_for(sys.stdout, args.json, args.interval), page)
        except NoWorld as exc:
            raise CommandError(str(exc), status=1) from None
    for warning in result.summary.get("warnings", []):      # as up says them
        print(f"warning: {warning}", file=sys.stderr)
    if args.json:
        print(summary_json(result), flush=True)
    else:
        print("\n".join(summary_lines(result, config, args.out)))
    return exit_status(result)
