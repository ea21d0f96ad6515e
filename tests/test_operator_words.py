"""What the operator reads agrees with what the code does: the README's list of commands
that take ``--json`` against the real parsers, docs/monitor.md's verdict table against the
causes the monitor can produce, and the words of a few messages a new user met (issue
"The operator's view"). No process is started."""

import argparse
import ast
import importlib
import re
from pathlib import Path

import numpy as np
import pytest

from agent.cli.main import COMMANDS, build_parser, main

ROOT = Path(__file__).resolve().parents[1]

#: causes another change is adding to the monitor while this test is written: the table may
#: or may not list them yet, and the code may or may not produce them yet
CAUSES_IN_FLIGHT = {"inconsistent estimates", "sensor bias"}


# -- the README's --json claim ---------------------------------------------------------

def _subparsers(parser):
    return next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)),
                None)


def _json_by_command() -> dict:
    """command -> whether it takes --json, from the parsers; a command with subcommands
    that differ is given per subcommand (``keys init``)."""
    def has_json(p):
        return any("--json" in a.option_strings for a in p._actions)

    out = {}
    for name, p in _subparsers(build_parser()).choices.items():
        sub = _subparsers(p)
        if sub is None:
            out[name] = has_json(p)
            continue
        each = {f"{name} {s}": has_json(q) for s, q in sub.choices.items()}
        if len(set(each.values())) == 1:
            out[name] = next(iter(each.values()))
        else:
            out.update(each)
    return out


def _readme_json_claim() -> tuple:
    """``(take, do_not)``: the commands the README says take ``--json`` and those it says
    do not (the sentence "... take `--json` ...; ... do not")."""
    text = (ROOT / "README.md").read_text()
    start = text.index("take `--json`")
    para_start = text.rindex("\n\n", 0, start) + 2
    para = text[para_start:text.index("\n\n", start)].replace("\n", " ")
    while re.search(r"\([^()]*\)", para):          # asides, nested ones included
        para = re.sub(r"\([^()]*\)", "", para)
    take, rest = para.split("take `--json`", 1)
    do_not = rest.split(";", 1)[1].split(" do not", 1)[0]
    names = lambda part: re.findall(r"`([a-z][a-z -]*)`", part)   # noqa: E731
    return names(take), names(do_not)


def test_the_readme_says_exactly_which_commands_take_json():
    take, do_not = _readme_json_claim()
    real = _json_by_command()
    assert take and do_not and not set(take) & set(do_not)
    assert sorted(take + do_not) == sorted(real), \
        f"the README names {sorted(take + do_not)}, the parsers have {sorted(real)}"
    assert sorted(take) == sorted(c for c, j in real.items() if j)
    assert sorted(do_not) == sorted(c for c, j in real.items() if not j)
    assert set(n.split()[0] for n in real) == set(COMMANDS)


# -- docs/monitor.md's verdict table ------------------------------------------------------

def _table_causes() -> set:
    """The causes listed in the ``| verdict | evidence | ...`` table of docs/monitor.md; a
    row shown as another cause (``unconfirmed`` (shown as ``crash``)) counts as that one."""
    text = (ROOT / "docs" / "monitor.md").read_text()
    table = re.search(r"^\| verdict \| evidence \|.*?\n((?:\|.*\n)+)", text, flags=re.M)
    assert table, "docs/monitor.md has no '| verdict | evidence |' table"
    out = set()
    for row in table.group(1).splitlines()[1:]:         # the separator row first
        first = row.split("|")[1]
        shown = re.search(r"shown as `([^`]+)`", first)
        out.add(shown.group(1) if shown else re.search(r"`([^`]+)`", first).group(1))
    return out


def _code_causes() -> set:
    """Every cause a ``Verdict(agent, cause, ...)`` of the monitor can carry: the string
    literals, and the names (module constants or imported ones) resolved to their value."""
    out = set()
    for module in ("agent.monitor.detector", "agent.monitor.core"):
        mod = importlib.import_module(module)
        tree = ast.parse(Path(mod.__file__).read_text())
        imported = {a.asname or a.name: node.module for node in ast.walk(tree)
                    if isinstance(node, ast.ImportFrom) and node.module
                    for a in node.names}
        for node in ast.walk(tree):
            if not (isinstance(node, ast.Call) and getattr(node.func, "id", None) == "Verdict"):
                continue
            arg = node.args[1] if len(node.args) > 1 else next(
                (k.value for k in node.keywords if k.arg == "cause"), None)
            if isinstance(arg, ast.Constant):
                out.add(arg.value)
            elif isinstance(arg, ast.Name):
                source = importlib.import_module(imported[arg.id]) \
                    if arg.id in imported else mod
                out.add(getattr(source, arg.id))
            else:
                pytest.fail(f"{module}: a Verdict whose cause is not a literal or a name "
                            f"(line {node.lineno}): this test cannot read it")
    return out


def test_the_verdict_table_lists_exactly_the_causes_the_monitor_gives():
    code, table = _code_causes(), _table_causes()
    assert {"crash", "hang", "sensor", "silent", "delay"} <= code
    assert code - CAUSES_IN_FLIGHT == table - CAUSES_IN_FLIGHT, (
        f"produced, not in the table: {sorted(code - table - CAUSES_IN_FLIGHT)}; "
        f"in the table, never produced: {sorted(table - code - CAUSES_IN_FLIGHT)}")


# -- the words of a few messages -----------------------------------------------------------

def test_inject_takes_the_operator_key_and_the_old_flag_still_works_with_a_warning(
        tmp_path, capsys):
    missing = str(tmp_path / "none.key")
    base = ["inject", "clear-all", "--run", "r1", "--connect", "tcp/127.0.0.1:9"]
    assert main(base + ["--operator-key", missing]) == 2
    err = capsys.readouterr().err
    assert "--operator-key: cannot read" in err and "deprecated" not in err
    assert main(base + ["--control-key", missing]) == 2
    err = capsys.readouterr().err
    assert "warning: --control-key is deprecated for inject: use --operator-key" in err
    assert "--control-key: cannot read" in err
    other = str(tmp_path / "other.key")
    assert main(base + ["--control-key", missing, "--operator-key", other]) == 2
    assert "give --operator-key alone" in capsys.readouterr().err


def test_a_gone_agent_is_said_with_what_it_was(paper14):
    """"agent N gone": a standby, or an agent convicted earlier (not "standby agent N")."""
    from agent.monitor.core import MonitorConfig, MonitorCore

    G = [0.5 * np.eye(14)[:, list(m)] for m in paper14.measure]
    core = MonitorCore(MonitorConfig(hang_timeout_s=1.0, settle_s=0.0, step_s=0.02), paper14,
                       G, paper14.delays)
    for a in (1, 2, 3, 4):
        core.on_liveliness("agent", a, True, 0.0)

    def status(a, step):
        return {"agent": a, "step": step, "epoch": 0, "active": a <= 3, "ctl": {"pending": 0},
                "sensor": {"last_step": step}}

    t = 0.0
    while t <= 3.0:     # agent 2's loop (and its statuses) stop at 1 s, its token stays
        for a in (1, 2, 3, 4):
            if a != 2 or t <= 1.0:
                core.on_status(status(a, int(50 * t)), t)
        core.tick(t)
        t += 0.1
    assert [(v.agent, v.cause) for v in core.verdicts] == [(2, "hang")]
    core.on_liveliness("agent", 2, False, 3.05)
    said = [e for e in core.events if "gone (its token went)" in e]
    assert said and said[-1].startswith("agent 2 gone (its token went): convicted earlier "
                                        "(hang), out of the configuration since")


def test_a_fault_too_short_to_convict_says_that_no_verdict_was_due():
    from agent.run.local import Fault
    from agent.run.summary import conviction_bound_s, failure_lines, no_verdict_due

    faults = [Fault(150, "stop", 3, 0.5), Fault(400, "stop", 2, 3.0),
              Fault(600, "partition", 1, 1.0), Fault(800, "drop", 1, 2.0, 0.3)]
    failures = [{"agent": 2, "cause": "hang", "detected_step": 460}]
    notes = no_verdict_due(faults, failures, 1.0, 0.02, 3)
    assert [d["fault"]["step"] for d in notes] == [150, 600]
    assert "not longer than the hang timeout (1 s)" in notes[0]["why"]
    # no verdict for the long stop: none is said to be due, the chaos check requires one
    assert no_verdict_due(faults, [], 1.0, 0.02, 3)[1]["fault"]["step"] == 600
    assert 3.0 > conviction_bound_s("stop", 1.0, 0.02, 3)
    lines = failure_lines({"failures": [], "no_verdict_due": notes})
    assert lines[0].startswith("  stop of agent 3 for 0.5 s at step 150: no verdict, and "
                               "none was due")


def test_a_chaos_run_that_drew_no_fault_says_it_tested_nothing():
    from agent.run.chaos_report import live_report_text

    report = {"scenario": "s", "seed": 1, "faults": [], "failures": [], "violations": [],
              "error": None, "out": "runs/c", "replay": "socmon chaos s --seed 1"}
    assert "NO FAULT DRAWN" in live_report_text(report)
    report["faults"] = [{"step": 100, "kind": "stop"}]
    report["no_verdict_due"] = [{"why": "stop of agent 1 for 0.5 s at step 100: no verdict"}]
    text = live_report_text(report)
    assert "1 faults" in text and "NO FAULT" not in text and "stop of agent 1" in text


def test_a_chaos_run_counts_the_verdicts_given_and_the_roles_moved():
    """A killed standby that no verdict followed is a failure without one, not a verdict;
    an epoch that only changed the gains is no reassignment."""
    from agent.run.chaos_report import live_report_text

    report = {"scenario": "s", "seed": 0, "violations": [], "error": None, "out": "runs/c",
              "replay": "socmon chaos s", "faults": [{"step": 100, "kind": "kill"}] * 3,
              "failures": [{"agent": 1, "detected_step": 110}, {"agent": 2, "detected_step": 300},
                           {"agent": 4, "detected": False, "detected_step": None}],
              "rosters": [{"ids": [1, 2, 3]}, {"ids": [4, 2, 3]}, {"ids": [4, 2, 3]},
                          {"ids": [4, 3]}]}
    head = live_report_text(report).splitlines()[0]
    assert head == ("s, seed 0: 3 faults; 2 verdicts (1 failures without one), 2 reassignments "
                    "(and 1 new gains for the same roles), 0 violations")


def test_a_failure_line_says_every_node_the_replacement_measures_and_the_links_added():
    from agent.run.summary import failure_lines

    f = {"agent": 1, "cause": "crash", "detected_step": 162, "activate_at": 174,
         "replacement": {"agent": 2, "node": "8", "measures": ["9", "8"]},
         "added_links": [{"from": 2, "to": 3}]}
    assert failure_lines({"failures": [f]}) == [
        "  failure: agent 1 crash at step 162; agent 2 measures 9 and 8 (node 8 new) from "
        "step 174; link added: 3 listens to 2"]
    g = {**f, "replacement": {"agent": 4, "node": "8", "measures": ["8"]}, "added_links": []}
    assert failure_lines({"failures": [g]}) == [
        "  failure: agent 1 crash at step 162; agent 4 measures 8 from step 174"]
    h = {**g, "cause": "silent", "links_impaired": ["1->3 cut", "2->1 drop 0.5"]}
    assert failure_lines({"failures": [h]}) == [
        "  failure: agent 1 silent at step 162; agent 4 measures 8 from step 174 (links "
        "impaired then: 1->3 cut, 2->1 drop 0.5)"]


def test_analyze_gives_the_reason_of_each_tolerance(paper14):
    from agent.run.design_reports import analysis_report, format_analysis

    text = format_analysis(analysis_report(paper14))
    assert ("failure tolerance without replacement (paper's Remark 5): 0; e.g. agent 1 "
            "failing is not recoverable: without agent 1 no agent left measures the parent "
            "SCC {6, 7, 8}") in text
    assert "agents 1 and 2 failing together is not recoverable: without agents 1 and 2 the " \
           "agents left are not strongly connected" in text
    assert "not observable but detectable" in text


def test_a_child_scc_agent_nobody_replaces_is_the_reason_given(paper14):
    """An agent measuring only a child SCC's node has no equivalent: no standby takes its
    place, and without it the cycle of agents breaks (tolerance 0 without new links)."""
    from agent.run.design_reports import analysis_report

    W = np.array([[0.5, 0, 0, 0.5], [0.5, 0.5, 0, 0], [0, 0.5, 0.5, 0], [0, 0, 0.5, 0.5]])
    s = paper14.replace(measure=(*paper14.measure, (paper14.labels.index("3"),)), W=W,
                        delays=np.zeros((4, 4), dtype=int))
    d = analysis_report(s)
    assert d["failure_tolerance"] == 0 and d["failure_tolerance_witness"] == [4]
    assert d["failure_tolerance_why"].startswith(
        "agent 4 measures only nodes of child SCCs (no equivalent, not needed")


def test_the_gains_file_says_how_it_was_designed_where_it_is_read(paper14, tmp_path, capsys):
    from design.gains import gains_meta, save_gains

    G = [0.5 * np.eye(14)[:, list(m)] for m in paper14.measure]
    path = tmp_path / "g.npz"
    save_gains(path, G, gains_meta(paper14, "default", paper14.delays, 0.9,
                                   objective="mse", mse_steady_exact=0.25))
    main(["certify", "paper-14", "--gains", str(path), "--taus", "0"])
    first = capsys.readouterr().out.splitlines()[0]
    assert first.endswith("(method default, objective mse; as designed (taubar "
                          f"{int(paper14.delays.max())}): exact radius 0.9, exact steady MSE "
                          "0.25)")


def test_a_steady_mse_is_printed_with_its_standard_error_and_its_window():
    """``up`` and ``watch`` print the steady MSE with its batch-means standard error and
    the steps it covers (a 300-step run's MSE alone read as more certain than it is)."""
    from agent.run.summary import failure_lines, steady_text
    from design.metrics import batch_means_se

    rng = np.random.default_rng(3)
    window = list(1.0 + 0.2 * rng.standard_normal(100))
    se = batch_means_se(window)
    assert 0.01 < se < 0.04                 # 0.2 / sqrt(100) = 0.02 for white noise
    summary = {"mse_steady_after_recovery": 0.2983, "mse_steady_after_recovery_se": se,
               "mse_steady_after_recovery_window": [344, 400],
               "mse_steady_exact_after_recovery": 0.2712, "failures": []}
    (line,) = failure_lines(summary)
    assert line == f"  after recovery: mse_steady 0.2983 ± {se:.2g} over steps 344-400 " \
                   "(predicted 0.2712)"
    assert steady_text({"m": 1.0, "m_se": None, "m_window": [3, 3]}, "m") == \
        "1 over steps 3-3 (too few for a standard error)"
    # refined gains late in the run: the window since the roles, its prediction theirs
    summary.update({"mse_steady_after_recovery_window": [320, 350],
                    "after_recovery_gains": [
                        {"epoch": 1, "from": 320, "steps": 26, "mse_steady_exact": 0.28},
                        {"epoch": 2, "from": 346, "steps": 5, "mse_steady_exact": 0.2712}],
                    "mse_steady_exact_over_after_recovery_window": 0.2786})
    (line,) = failure_lines(summary)
    assert line == f"  after recovery: mse_steady 0.2983 ± {se:.2g} over steps 320-350 " \
                   "(predicted 0.2786 over it: the gains of epoch 1, then of epoch 2 from " \
                   "step 346)"


def test_a_record_that_began_after_a_recovery_does_not_invent_a_late_switch():
    """A watch joined at step 1018 of a run whose epoch 1 came into force at step 788: its
    estimates are under epoch 1 from its first step. The summary keeps epoch 1 from 788
    (no "not run by all its agents" warning), and, the assignments never heard, says the
    roles and their prediction are unknown instead of "not recovered" or "the window
    spans a switch"."""
    from types import SimpleNamespace

    import numpy as np

    from agent.run.summary import _failures, headline_lines
    from design.scenario import load_scenario

    s = load_scenario("paper-14-live")
    steps = list(range(1018, 1200))
    rec = SimpleNamespace(
        events=[], assigns={}, monitor_events=[],
        rosters=[(0, (1, 2, 3), 0), (788, (4, 2, 3), 1)],
        est_epoch={1: {}, 2: {k: 1 for k in steps}, 3: {k: 1 for k in steps[1:]},
                   4: {k: 1 for k in steps}})
    out = _failures(None, rec, s, np.zeros((3, 3), int), steps, [0.3] * len(steps),
                    G0=object())
    assert out["rosters"] == [{"activate_at": 0, "ids": [1, 2, 3], "epoch": 0},
                              {"activate_at": 788, "ids": [4, 2, 3], "epoch": 1}]
    assert out["rosters_not_in_force"] == []
    assert out["recovered"] is None and out["roles_unheard_before"] == 1018
    assert out["warnings"] == [
        "epoch 1 was in force before this record began (step 1018) and its assignments "
        "were not heard: the roles in force and their exact predictions are unknown; "
        "recovery is not evaluated"]
    summary = {**out, "steps": 1199, "mse_steady": 0.3, "mse_steady_se": 0.01,
               "mse_steady_window": [1150, 1199], "mse_steady_exact": 0.27,
               "mse_steady_exact_in_force": None, "drops": 0, "late": 0, "malformed": 0,
               "out": "x"}
    assert "(predicted n/a: the roles in force were assigned before the record began)" in \
        headline_lines(summary, s)[0]


@pytest.mark.parametrize("spoke_at, back_event, dead", [
    (600, False, False),       # a status of a later step: it was paused, not dead
    (180, True, False),        # its token came back
    (180, False, True),        # neither: it died
    (350, "again", True),      # it came back, then its token went for good at step 400
])
def test_a_standby_whose_token_went_and_came_back_is_not_reported_dead(spoke_at, back_event,
                                                                      dead):
    """A watch sees a paused standby's token go (its lease lapsed) at step 191: unless
    the agent spoke again (a status of a later step, or its token back), that is not a
    death "never convicted"."""
    from types import SimpleNamespace

    import numpy as np

    from agent.run.summary import _failures
    from design.scenario import load_scenario

    s = load_scenario("paper-14-live")
    steps = list(range(0, 700))
    events = [{"process": "agent-4", "liveliness": False, "step": 191, "t": 10.0}]
    if back_event:
        events.append({"process": "agent-4", "liveliness": True, "step": 340, "t": 13.0})
    if back_event == "again":
        events.append({"process": "agent-4", "liveliness": False, "step": 400, "t": 15.0})
    rec = SimpleNamespace(events=events, assigns={}, monitor_events=[],
                          rosters=[(0, (1, 2, 3), 0)], status={4: {"step": spoke_at}},
                          est_epoch={a: {k: 0 for k in steps} for a in (1, 2, 3)} | {4: {}})
    out = _failures(None, rec, s, np.zeros((3, 3), int), steps, [0.3] * len(steps),
                    G0=object())
    assert [(f["agent"], f["died_step"], f["role"]) for f in out["failures"]] == \
        ([(4, 400 if back_event == "again" else 191, "standby")] if dead else [])


def test_the_failure_lines_say_rejoins_residual_alerts_and_refused_evidence():
    """What the summary holds beside the failures is said too (up and watch print these
    lines): an agent that rejoined, a residual alert, evidence refused."""
    from agent.run.summary import failure_lines

    summary = {"failures": [], "rejoins": [{"agent": 2, "step": 720, "healthy_s": 5.02,
                                            "standby": [2]}],
               "residual_alerts": [{"agent": 1, "fault": "inconsistent estimates",
                                    "step": 3530, "score": 51.83}],
               "evidence_refused": [{"reason": "contested", "agent": 3, "detail": "x"}] * 2}
    assert failure_lines(summary) == [
        "  rejoined: agent 2 at step 720, healthy 5.02 s on probation",
        "  residual alert: agent 1 inconsistent estimates at step 3530 (level 51.8)",
        "  evidence refused: 2 (summary.json evidence_refused: forged or contested tokens, "
        "statuses)"]
