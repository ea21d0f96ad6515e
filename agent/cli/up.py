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

HELP = "run world + one process per agent on this machine, record, and write a run folder"


def add_arguments(parser) -> None:
    from agent.cli import _common as c

    c.add_scenario_argument(parser)
    parser.add_argument("--steps", type=c.int_flag(lo=1), default=200,
                        help="steps to run (default 200)")
    c.add_designed_gains_arguments(parser)
    c.add_seed_argument(parser)
    c.add_run_folder_arguments(parser, "runs/<scenario>-<time>-s<seed>")
    parser.add_argument("--check-simulator", action="store_true",
                        help="compare with design.simulate (same seed); exit 1 if they differ")
    parser.add_argument("--record-every", type=c.int_flag(lo=1), default=1, metavar="K",
                        help="the recorder keeps the truth and the estimates of every K-th "
                             "step (and the last) only: the MSE, its plot, the check against "
                             "the simulator and estimates.npz are over those steps; the "
                             "rosters, failures and message counts over every step "
                             "(default 1: every step; for large or long runs, "
                             "docs/runtime.md)")
    c.add_json_argument(parser, "print the summary as JSON")
    c.add_delays_argument(parser)
    c.add_step_ms_argument(parser)
    c.add_deadline_argument(parser, "; 30000 with --check-simulator, so that nothing is dropped")
    c.add_start_timeout_argument(parser)
    c.add_quiet_argument(parser)
    c.add_monitor_arguments(parser)
    c.add_drop_argument(parser)
    c.add_fault_schedule_arguments(parser)
    c.add_hang_timeout_arguments(parser)
    c.add_local_transport_arguments(parser)
    c.add_web_arguments(parser)


def run(args) -> int:
    return run_command(lambda: _up(args))


def _up(args) -> int:
    from agent.cli._common import served_page
    from agent.cli._progress import ProgressLine
    from agent.run.setup import live_run
    from agent.run.terminal import finished_run_text, say_on_stderr
    from agent.run.local import live_view
    from agent.run.web import live_state_factory

    line = ProgressLine("up", enabled=not (args.quiet or args.json))
    try:
        with served_page(args, "up") as page, live_view(live_state_factory(page)):
            done = live_run(args, say_on_stderr("up", args.quiet),
                            design_progress=line.design, on_designed=line.close)
    finally:
        line.close()
    for warning in done.summary.get("warnings", []):
        print(f"warning: {warning}", file=sys.stderr)
    print(finished_run_text(done, as_json=args.json))
    for problem in done.problems:
        print(f"socmon up: {problem}", file=sys.stderr)
    return done.status
