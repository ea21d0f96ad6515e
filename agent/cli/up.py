"""``socmon up SCENARIO``: a whole live run on this machine, recorded into a run folder.

The flags checked together, the run, its check and its folder:
:func:`agent.run.setup.live_run`; what is said on the terminal: :mod:`agent.run.terminal`.
Exit status: 0 done, 1 a negative result (a failure, a divergence, a role lost, the
simulator check), 2 bad input, 130 interrupted, or the run folder could not be written
(:data:`agent.run.folder.EXIT_FOLDER`).
"""

from __future__ import annotations

import sys

from agent.cli._common import run_command
from agent.protocol.timing import DEFAULT as TIMING

HELP = "run world + one process per agent on this machine, record, and write a run folder"


def add_arguments(parser) -> None:
    from agent.cli._common import add_force_gains_argument, add_scenario_argument, int_flag

    add_scenario_argument(parser)
    parser.add_argument("--steps", type=int, default=200, help="steps to run (default 200)")
    parser.add_argument("--gains", help="gains file (.npz); default: design with the default method")
    add_force_gains_argument(parser)
    parser.add_argument("--seed", type=int, default=0, help="run seed (default 0)")
    parser.add_argument("--out", help="run folder (default runs/<scenario>-<time>-s<seed>); "
                             "a folder holding an earlier run is refused")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the earlier run in --out (its files only)")
    parser.add_argument("--check-simulator", action="store_true",
                        help="compare with design.simulate (same seed); exit 1 if they differ")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--delays", default="scenario",
                        help="link delays injected at start: scenario, none or uniform:T")
    parser.add_argument("--step-ms", type=float, default=None,
                        help="period of one step (default: the scenario's step_ms)")
    parser.add_argument("--deadline-ms", type=float, default=None,
                        help="agents' wait for late estimates (default: one step; "
                             "30000 with --check-simulator, so that nothing is dropped)")
    parser.add_argument("--start-timeout", type=float, default=TIMING.start_timeout_s,
                        help="seconds allowed for every process to be up "
                             f"(default {TIMING.start_timeout_s:g})")
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")
    parser.add_argument("--no-monitor", action="store_true",
                        help="run without the monitor (a failed agent is then never replaced)")
    parser.add_argument("--monitors", type=int_flag(lo=1, hi=9), default=2, metavar="N",
                        help="monitors started (default 2): the first acts, the others stand "
                             "by and take over when it dies or is paused")
    parser.add_argument("--drop", type=float, default=0.0,
                        help="probability that an estimate is lost on a link, drawn from the "
                             "seed as the simulator draws it (default 0)")
    parser.add_argument("--kill", action="append", default=[], metavar="STEP:AGENTS",
                        help="scripted crash: agents (e.g. 1,2) publish step STEP-1 and SIGKILL "
                             "themselves (repeatable)")
    parser.add_argument("--stop", action="append", default=[], metavar="STEP:AGENT:SECONDS",
                        help="SIGSTOP agent AGENT once the world reaches STEP, SIGCONT it "
                             "SECONDS later (repeatable)")
    parser.add_argument("--kill-monitor", type=int, default=None, metavar="STEP",
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
                             "docs/residuals.md); see docs/monitor.md")
    parser.add_argument("--hang-timeout", type=float, default=TIMING.hang_timeout_s,
                        metavar="S", help="the monitor's hang timeout (default "
                        f"{TIMING.hang_timeout_s:g} s; above twice the status period "
                        f"{TIMING.status_s:g} s)")
    parser.add_argument("--hang-timeout-max", type=float, default=TIMING.hang_timeout_max_s,
                        metavar="S",
                        help="the hang timeout grows with the statuses' observed pace up to S "
                             f"seconds (default {TIMING.hang_timeout_max_s:g}; equal to "
                             "--hang-timeout keeps it fixed; docs/monitor.md)")
    parser.add_argument("--run", default=None, metavar="ID",
                        help="run id (key prefix socmon/<ID>/; default a fresh one); printed "
                             "and written in RUN_FOLDER/run.json")
    parser.add_argument("--listen", default=None, metavar="ENDPOINT",
                        help="endpoint of this command's own peer, the one every process of "
                             "the run and every attached tool connects to (default "
                             "tcp/127.0.0.1:<free port>, tls/ with --secure)")
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


def run(args) -> int:
    return run_command(lambda: _up(args))


def _up(args) -> int:
    from agent.cli._progress import ProgressLine
    from agent.run.setup import live_run
    from agent.run.terminal import finished_run_text, say_on_stderr

    line = ProgressLine("up", enabled=not (args.quiet or args.json))
    try:
        done = live_run(args, say_on_stderr("up", args.quiet), design_progress=line.design,
                        on_designed=line.close)
    finally:
        line.close()
    for warning in done.summary.get("warnings", []):
        print(f"warning: {warning}", file=sys.stderr)
    print(finished_run_text(done, as_json=args.json))
    for problem in done.problems:
        print(f"socmon up: {problem}", file=sys.stderr)
    return done.status
