"""What ``socmon chaos`` reports: the seeds of ``--simulated A:B``, and the report of a
chaos run as text or JSON, live (:func:`agent.run.chaos.live_chaos`) or under simulated
time (:func:`agent.run.simulated.simulated_chaos`).
"""

from __future__ import annotations

import json

from agent.run.jsonable import to_jsonable, versioned

__all__ = ["NO_FAULT_WARNING", "seed_range", "simulated_report_text", "live_report_text"]

#: said on stderr when the schedule of a live run drew no fault
NO_FAULT_WARNING = ("chaos: warning: no fault was drawn (--rate, --duration): the run tested "
                    "nothing")


def seed_range(text, parse_int) -> range:
    """The seeds of ``--simulated A:B`` (A..B-1; ``A`` alone: seed A); ``parse_int(text,
    flag, lo=...)`` reads each bound (the command line's reader, with its messages).

    >>> seed_range("3:7", lambda text, flag, lo=0: int(text))
    range(3, 7)
    >>> seed_range("5", lambda text, flag, lo=0: int(text))
    range(5, 6)
    """
    first, _, last = str(text).partition(":")
    a = parse_int(first, "--simulated")
    b = parse_int(last, "--simulated A:B, B (the seed after the last)", lo=a + 1) if last \
        else a + 1
    return range(a, b)


def simulated_report_text(report: dict, seeds: range, rate: float,
                          as_json: bool = False) -> str:
    """What ``socmon chaos --simulated`` prints of the report of ``seeds`` (from
    :func:`agent.run.simulated.simulated_chaos`, drawn at ``rate`` faults per 1000
    steps): the report as JSON (without ``scenario_name`` and ``kinds``), or a headline
    and :func:`agent.run.simulated.report_lines`."""
    from agent.run.simulated import report_lines

    name, kinds = report["scenario_name"], report["kinds"]
    record = {k: v for k, v in report.items() if k not in ("scenario_name", "kinds")}
    if as_json:
        return json.dumps(to_jsonable(versioned(record)), indent=2)
    untested = ([f"NO FAULT DRAWN in any schedule (--rate {rate:g}, --duration): the runs "
                 "tested nothing"] if not record.get("faults") else [])
    return "\n".join([f"{name} under simulated time, seeds {seeds.start}..{seeds.stop - 1}, "
                      f"faults {','.join(kinds)}, rate {rate:g}"] + untested
                     + report_lines(record))


def live_report_text(report: dict, as_json: bool = False) -> str:
    """What ``socmon chaos`` prints of the report of a live run (from
    :func:`agent.run.chaos.live_chaos`): the report as JSON, or the counts (the verdicts
    given, any failure without one, the reassignments of roles and the new gains for the
    same roles, from the rosters in force), each violation, the run folder and, after a
    violation or a failure, the command that replays the run.

    A schedule that drew no fault tested nothing, and the headline says so (the exit
    status stays 0: nothing was violated; stderr has :data:`NO_FAULT_WARNING`); a fault
    too short to be convicted is listed with the reason no verdict was due:

    >>> print(live_report_text({"scenario": "paper-14-live", "seed": 0, "faults": [],
    ...     "failures": [], "violations": [], "error": None, "out": "runs/c",
    ...     "replay": "socmon chaos paper-14-live --seed 0"}))
    paper-14-live, seed 0: NO FAULT DRAWN (--rate, --duration): the run tested nothing; 0 verdicts, 0 reassignments, 0 violations
    run folder: runs/c

    A run stopped short (Ctrl-C, or a process that failed) says how far it got and that
    nothing was checked:

    >>> print(live_report_text({"scenario": "paper-14-live", "seed": 11, "faults": [{}] * 6,
    ...     "reached": 448, "injected": 1, "failures": [], "violations": [],
    ...     "error": "interrupted", "out": "runs/c", "replay": "socmon chaos ..."}))
    paper-14-live, seed 11: INTERRUPTED at step 448, invariants NOT CHECKED; 1 of 6 faults injected; 0 verdicts, 0 reassignments
    run folder: runs/c
    replay: socmon chaos ...
    """
    if as_json:
        return json.dumps(to_jsonable(report), indent=2)
    violations = report["violations"]
    drawn = (f"{len(report['faults'])} faults" if report["faults"] else
             "NO FAULT DRAWN (--rate, --duration): the run tested nothing")
    error = report.get("error")
    if error:                # stopped short: what it reached, and nothing checked
        drawn = ("INTERRUPTED" if error == "interrupted" else "FAILED") + \
            f" at step {report.get('reached', -1)}, invariants NOT CHECKED; " + \
            f"{report.get('injected', 0)} of {len(report['faults'])} faults injected"
    verdicts = sum(f.get("detected_step") is not None for f in report["failures"])
    unanswered = len(report["failures"]) - verdicts
    rosters = [r["ids"] for r in report.get("rosters", [])]
    moved = sum(a != b for a, b in zip(rosters, rosters[1:]))
    regained = max(0, len(rosters) - 1 - moved)
    lines = [f"{report['scenario']}, seed {report['seed']}: {drawn}; {verdicts} verdicts"
             + (f" ({unanswered} failures without one)" if unanswered else "")
             + f", {moved} reassignments"
             + (f" (and {regained} new gains for the same roles)" if regained else "")
             + ("" if error else f", {len(violations)} violations")]
    if error and error != "interrupted":
        lines.append(f"  error: {error.splitlines()[0]}")
    if report.get("diverged_at") is not None:
        lines.append(f"  the estimates DIVERGED at step {report['diverged_at']} (exit 1; "
                     "summary.json warnings)")
    lines += [f"  {d['why']}" for d in report.get("no_verdict_due", [])]
    lines += [f"  VIOLATION {v['invariant']} at step {v['step']}: {v['evidence']}"
              for v in violations]
    lines.append(f"run folder: {report['out']}")
    if violations or report["error"]:
        lines.append(f"replay: {report['replay']}")
    return "\n".join(lines)
