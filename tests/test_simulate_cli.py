"""``socmon simulate``: output, figure and exit status 2 for bad input."""

import json

import numpy as np
import pytest

from agent.cli.main import main
from agent.run.simulate import format_text
from design.gains import gains_meta, save_gains


@pytest.fixture(scope="module")
def gains_file(paper14, paper14_design, tmp_path_factory):
    result = paper14_design
    path = tmp_path_factory.mktemp("g") / "g14.npz"
    save_gains(path, result.G, gains_meta(paper14, "default", paper14.delays, result.rho))
    return str(path)


def test_json_keys_and_plot(gains_file, tmp_path, capsys):
    png = tmp_path / "mse.png"
    rc = main(["simulate", "paper-14", "--gains", gains_file, "--trials", "5", "--steps", "80",
               "--seed", "3", "--delays", "uniform:1", "--drop", "0.1",
               "--fail", "40:2", "--plot", str(png), "--json"])
    out = json.loads(capsys.readouterr().out)
    assert rc == (1 if out["diverged"] else 0)
    for key in ("mse", "mse_steady", "diverged", "trials", "steps", "seed", "mse_p10",
                "mse_p90"):
        assert key in out
    assert len(out["mse"]) == 81 and out["trials"] == 5 and out["seed"] == 3
    assert out["failed"] == [2] and out["fail_step"] == 40
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_same_numbers_as_the_library(gains_file, paper14, capsys):
    from design.gains import load_gains
    from design.simulate import simulate

    assert main(["simulate", "paper-14", "--gains", gains_file, "--trials", "3",
                 "--steps", "30", "--seed", "5", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    res = simulate(paper14, load_gains(gains_file).G, 30, 3, 5)
    np.testing.assert_array_equal(out["mse"], res.mse)


def test_text_output(gains_file, capsys):
    assert main(["simulate", "paper-14", "--gains", gains_file, "--trials", "2",
                 "--steps", "20"]) == 0
    text = capsys.readouterr().out
    assert "steady MSE" in text and "exact steady MSE" in text
    assert main(["simulate", "paper-14", "--gains", gains_file, "--trials", "2",
                 "--steps", "40", "--fail", "20:1"]) == 0
    text = capsys.readouterr().out
    # without recovery the mean covers the agents left: said, as the error can fall
    assert "failure of agent 1 at step 20 (no recovery): from then on the MSE is the mean " \
           "over the agents still running" in text


def test_a_failure_reports_the_exact_level_before_it_as_its_figure_draws_it(
        gains_file, paper14, tmp_path, capsys):
    """With ``--fail`` the run is not one loop: ``mse_steady_exact`` stays null, and the
    exact steady MSE of the loop before the failure is in the JSON and the text under a
    name that says so, the same level the figure draws up to the failure step."""
    from design.closed_loop import exact_performance
    from design.gains import load_gains

    assert main(["simulate", "paper-14", "--gains", gains_file, "--trials", "2",
                 "--steps", "40", "--fail", "20:1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    exact = exact_performance(paper14, load_gains(gains_file).G, paper14.delays).mse
    assert out["mse_steady_exact"] is None
    assert out["mse_steady_exact_before_failure"] == pytest.approx(exact, rel=1e-12)
    assert f"  exact steady MSE before the failure (Lyapunov): {exact:.5g}" in format_text(out)

    from agent.run.simulate import run_simulation, simulate_options, write_figure

    o = simulate_options(paper14, load_gains(gains_file), gains_file, trials=2, steps=40,
                         seed=0, drop=0.0, delays=paper14.delays, delays_spec="scenario",
                         fail=(20, [0]))
    report = run_simulation(o)
    drawn = {}
    write_figure(tmp_path / "f.png", o, report,
                 lambda path, curves, **kw: drawn.update(kw))
    assert drawn["reference"] == [(report.record["mse_steady_exact_before_failure"],
                                   "exact steady MSE before the failure", 0, 20)]
    # with drops the run is not the exact loop before the failure either: no level
    o = simulate_options(paper14, load_gains(gains_file), gains_file, trials=2, steps=40,
                         seed=0, drop=0.1, delays=paper14.delays, delays_spec="scenario",
                         fail=(20, [0]))
    assert run_simulation(o).record["mse_steady_exact_before_failure"] is None


def test_diverging_run_exits_1(paper14, tmp_path, capsys):
    path = tmp_path / "zero.npz"
    save_gains(path, [np.zeros((14, 1))] * 3, {"method": "zero"})
    assert main(["simulate", "paper-14", "--gains", str(path), "--trials", "2",
                 "--steps", "300"]) == 1
    assert "DIVERGED" in capsys.readouterr().out


@pytest.mark.parametrize("flags, message", [
    (["--fail", "x"], "--fail: expected STEP:AGENTS"),
    (["--fail", "10:"], "--fail: give at least one agent"),
    (["--fail", "10:9"], "--fail: no agent 9"),
    (["--fail", "10:4"], "--fail: agent 4 is a standby of the scenario"),
    (["--fail", "0:1"], "--fail STEP"),
    (["--fail", "999:1"], "after the last step"),
    (["--fail", "10:1,2,3"], "every agent fails"),
    (["--drop", "1.5"], "--drop"),
    (["--drop", "often"], "--drop"),
    (["--trials", "0"], "--trials"),
    (["--steps", "ten"], "--steps"),
    (["--seed", "-1"], "--seed"),
    (["--delays", "uniform:-2"], "--delays"),
    (["--recover"], "--recover: needs --fail"),
    (["--time-limit", "5"], "--time-limit: a positive number of seconds, with --recover only"),
    (["--fail", "10:1", "--recover", "--time-limit", "0"], "--time-limit"),
])
def test_bad_flags_exit_2(gains_file, capsys, flags, message):
    rc = main(["simulate", "paper-14", "--gains", gains_file, "--steps", "50"] + flags)
    assert rc == 2
    assert message in capsys.readouterr().err


def test_gains_that_do_not_fit_exit_2(tmp_path, capsys):
    path = tmp_path / "bad.npz"
    save_gains(path, [np.zeros((14, 1))] * 2, {"method": "x"})
    assert main(["simulate", "paper-14", "--gains", str(path)]) == 2
    assert "2 gain arrays for 3 agents" in capsys.readouterr().err
    path2 = tmp_path / "bad2.npz"
    save_gains(path2, [np.zeros((13, 1))] * 3, {"method": "x"})
    assert main(["simulate", "paper-14", "--gains", str(path2)]) == 2
    assert "K1 must be 14 x 1" in capsys.readouterr().err
    assert main(["simulate", "paper-14", "--gains", str(tmp_path / "none.npz")]) == 2
    assert "no such gains file" in capsys.readouterr().err


def test_bad_scenario_exit_2(gains_file, capsys):
    assert main(["simulate", "no-such-scenario", "--gains", gains_file]) == 2
    assert "bad scenario" in capsys.readouterr().err


@pytest.mark.slow
def test_recover_designs_gains_for_the_new_configuration(gains_file, capsys):
    rc = main(["simulate", "paper-14", "--gains", gains_file, "--trials", "4", "--steps",
               "200", "--fail", "100:1", "--recover", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0, out
    assert out["recovered"] is True and out["recovery"]["rho_exact_after_recovery"] < 1
    assert out["recovery"]["replacements"][0]["from"] == "7"
    assert not out["diverged"]
    text = format_text(out)
    exact = out["recovery"]["mse_steady_exact_after_recovery"]
    assert exact > 0 and f"exact steady MSE after recovery (Lyapunov): {exact:.5g}" in text
    before = out["mse_steady_exact_before_failure"]
    assert before > 0 and out["mse_steady_exact"] is None
    assert f"exact steady MSE before the failure (Lyapunov): {before:.5g}" in text
