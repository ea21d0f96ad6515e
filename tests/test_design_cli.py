"""``socmon design``: files written, JSON record, exit statuses."""

import json
from pathlib import Path

import numpy as np
import pytest

from agent.cli.main import main
from design.closed_loop import ClosedLoop
from design.gains import load_gains
from design.scenario import load_scenario, resolve_delays

PAPER14_TOML = Path(__file__).resolve().parents[1] / "design" / "scenarios" / "paper-14.toml"


def _run(capsys, *argv):
    status = main(["design", *argv])
    out, err = capsys.readouterr()
    return status, out, err


@pytest.mark.slow
def test_json_record_and_gains_file_round_trip(capsys, tmp_path):
    path = tmp_path / "g.npz"
    status, out, err = _run(capsys, "paper-14", "--delays", "uniform:3", "--starts", "1",
                            "--max-iter", "25", "--seed", "2", "--out", str(path), "--json")
    assert status == 0, err
    rec = json.loads(out)
    for key in ("schema_version", "scenario", "method", "objective", "delays", "rho_exact",
                "mse_steady_exact", "rho_delay_free", "seconds", "iterations", "stable"):
        assert key in rec
    assert rec["method"] == "default" and rec["objective"] == "mse" and rec["stable"] is True
    assert g_meta_objective(path) == "mse"        # the default, the gain `up` designs
    s = load_scenario("paper-14")
    D = resolve_delays(s, "uniform:3")
    assert rec["delays"] == D.tolist()
    g = load_gains(path, s)
    rho = ClosedLoop(s.A, s.W, D, s.measure, g.G).spectral_radius()
    assert rec["rho_exact"] == pytest.approx(rho, abs=1e-12) and rho < 1
    assert g.meta["method"] == "default" and g.meta["delays"] == D.tolist()
    assert g.meta["scenario_digest"] == s.digest() and g.meta["seed"] == 2
    assert g.meta["rho_exact"] == pytest.approx(rho, abs=1e-12)
    assert rec["mse_steady_exact"] == pytest.approx(g.meta["mse_steady_exact"])


@pytest.mark.slow
def test_delay_free_ccl_design_is_unstable_at_uniform7_and_writes_nothing(capsys, tmp_path):
    path = tmp_path / "g.npz"
    status, out, err = _run(capsys, "paper-14", "--method", "ccl", "--solver", "scs",
                            "--delays", "uniform:7", "--out", str(path), "--json")
    assert status == 1
    rec = json.loads(out)
    assert rec["stable"] is False and rec["rho_exact"] > 1 and rec["rho_delay_free"] < 1
    assert "no stabilising gain" in err and not path.exists()
    status, out, err = _run(capsys, "paper-14", "--method", "ccl", "--solver", "scs",
                            "--delays", "uniform:7", "--out", str(path), "--force")
    assert status == 1 and path.exists() and "NOT stable" in out
    s = load_scenario("paper-14")
    g = load_gains(path, s)
    assert ClosedLoop(s.A, s.W, resolve_delays(s, "uniform:7"), s.measure, g.G).spectral_radius() > 1
    assert g.meta["stable"] is False


def test_unobservable_scenario_names_the_parent_scc(capsys, tmp_path):
    text = PAPER14_TOML.read_text().replace('measure = [["7"], ["9"], ["12"]]',
                                            'measure = [["7"], ["9"], ["10"]]')
    scen = tmp_path / "blind.toml"
    scen.write_text(text)
    path = tmp_path / "g.npz"
    status, out, err = _run(capsys, str(scen), "--out", str(path))
    assert status == 2
    assert "parent SCC {12, 13, 14} has no sensor" in err
    assert not path.exists()


@pytest.mark.parametrize("argv, message", [
    (["--solver", "SCS"], "--solver applies to --method ccl only"),
    (["--keep-iterating"], "--keep-iterating applies to --method ccl only"),
    (["--method", "ccl", "--objective", "mse"], "--objective mse needs --method default"),
    (["--delays", "uniform:-1"], "uniform:T needs a non-negative integer"),
    (["--max-iter", "0"], "--max-iter: must be a positive integer"),
    (["--target", "1.5"], "--target: a radius in (0, 1]"),
    (["--target", "0"], "--target: a radius in (0, 1]"),
])
def test_bad_flags_exit_2(capsys, tmp_path, argv, message):
    status, out, err = _run(capsys, "paper-14", *argv, "--out", str(tmp_path / "g.npz"))
    assert status == 2 and message in err


def test_an_existing_gains_file_is_refused_unless_overwrite(capsys, tmp_path):
    """As ``up --out`` refuses an earlier run's folder: an existing ``--out`` file is a
    usage error before any design, left as it was; ``--overwrite`` replaces it."""
    path = tmp_path / "g.npz"
    path.write_bytes(b"an earlier design")
    argv = ("paper-14", "--delays", "none", "--max-iter", "5", "--no-gaps", "--out", str(path))
    status, out, err = _run(capsys, *argv)
    assert status == 2 and err == (f"socmon: --out: {str(path)!r} exists: choose another "
                                   "file, or --overwrite to replace it\n")
    assert path.read_bytes() == b"an earlier design"
    status, out, err = _run(capsys, *argv, "--overwrite")
    assert status == 0, err
    assert len(load_gains(path, load_scenario("paper-14")).G) == 3


def test_missing_out_folder_exit_2(capsys, tmp_path):
    status, out, err = _run(capsys, "paper-14", "--out", str(tmp_path / "no" / "g.npz"))
    assert status == 2 and "does not exist" in err


def test_mse_objective_from_the_cli(capsys, tmp_path):
    path = tmp_path / "g.npz"
    status, out, err = _run(capsys, "paper-14", "--delays", "none", "--objective", "mse",
                            "--starts", "1", "--max-iter", "40", "--out", str(path), "--json")
    assert status == 0, err
    rec = json.loads(out)
    s = load_scenario("paper-14")
    g = load_gains(path, s)
    loop = ClosedLoop(s.A, s.W, np.zeros((3, 3), int), s.measure, g.G)
    assert rec["mse_steady_exact"] == pytest.approx(loop.mse_steady(0.05, 0.05), rel=1e-10)
    assert rec["objective"] == "mse" and rec["mse_steady_exact"] < 1.0


def test_progress_line_only_on_a_terminal(monkeypatch):
    import io

    # the line is cut to the terminal's width: the lines below need 200 columns, whatever
    # the terminal (or a pytest-xdist worker) the test runs in
    monkeypatch.setenv("COLUMNS", "200")

    from agent.cli._progress import ProgressLine
    from design.gain_design import DesignProgress

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    p = DesignProgress(stage="start 1 of 3, radius", iteration=4, iterations=4,
                       quantity="rho", value=0.91234, best=None, elapsed=1.5,
                       time_left=58.5, max_iter=200)
    for stream, enabled in ((io.StringIO(), None), (Terminal(), False)):
        line = ProgressLine("design", stream=stream, enabled=enabled, delay=0, interval=0)
        line.design(p)
        line.note("done")
        line.close()
        assert stream.getvalue() == ""                 # a pipe, or --json: nothing
    term = Terminal()
    line = ProgressLine("design", stream=term, delay=0, interval=0)
    line.design(p)
    assert ("design: start 1 of 3, radius: iteration 4/200, rho 0.91234, 1.5 s, "
            "58 s left of --time-limit") in term.getvalue()
    line.design(DesignProgress(stage="certifying (exact radius and steady MSE)",
                               iteration=0, iterations=4, quantity="rho",
                               value=float("nan"), best=None, elapsed=2.0, time_left=None,
                               max_iter=0))
    assert term.getvalue().rstrip().endswith("design: certifying (exact radius and steady MSE)"
                                              ", 2.0 s")
    line.note("designed")
    line.close()
    assert term.getvalue().endswith("designed\n")


def test_design_help_shows_every_budget(capsys):
    try:
        main(["design", "--help"])
    except SystemExit:
        pass
    out = " ".join(capsys.readouterr().out.split())
    for text in ("--time-limit SECONDS", "60 s for --objective rho", "--target RHO",
                 "--max-iter N", "(default 200)", "--window N", "(default 20)",
                 "--rel-tol X", "(default 1e-3)", "--starts K"):
        assert text in out, text


@pytest.mark.slow
def test_a_radius_design_worse_than_no_correction_is_warned(capsys, tmp_path):
    """The starter scenario (stable A): the smallest radius costs more error than zero
    gains; the warning gives both exact steady MSEs, and the default (mse) does not warn."""
    start = tmp_path / "s.toml"
    assert main(["init", str(start)]) == 0
    capsys.readouterr()
    assert main(["design", str(start), "--out", str(tmp_path / "g.npz"), "--objective", "rho",
                 "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    s = load_scenario(str(start))
    D = resolve_delays(s, "scenario")
    zero = ClosedLoop(s.A, s.W, D, s.measure, [np.zeros((s.n, len(m))) for m in s.measure])
    none = zero.mse_steady(s.process_noise, s.measurement_noise)
    assert record["mse_steady_exact"] > none
    (w,) = record["warnings"]
    assert f"above that of no correction at all (zero gains: {none:.6g})" in w
    assert main(["design", str(start), "--out", str(tmp_path / "m.npz"), "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["warnings"] == [] and record["mse_steady_exact"] <= none


def g_meta_objective(path):
    return load_gains(path, load_scenario("paper-14")).meta["objective"]


def test_the_design_text_says_its_certificate_is_for_the_delays_given():
    """A gain certified for 3-step links whose delay-free loop is unstable: the text says
    the certificate holds for those delays exactly and flags the delay-free radius."""
    from agent.run.design_reports import format_design

    record = {"scenario": "s", "method": "default", "objective": "mse",
              "delays": [[0, 3, 3], [3, 0, 3], [3, 3, 0]], "rho_exact": 0.963,
              "stable": True, "rho_delay_free": 1.042, "mse_steady_exact": 5.7,
              "detectability": {"rank": 24, "order": 24, "observable": True},
              "iterations": 161, "seconds": 1.4, "status": "converged", "written": "g.npz"}
    lines = format_design(record).splitlines()
    assert "for the delay matrix given (at most 3 steps on a link; the certificate is for " \
           "these delays exactly)" in lines[0]
    assert lines[2].endswith("1.042000  UNSTABLE: run this gain with the delays it was "
                             "designed for (`socmon certify --taus` checks others)")
    record["rho_delay_free"] = 0.9
    assert format_design(record).splitlines()[2].endswith("0.900000")
