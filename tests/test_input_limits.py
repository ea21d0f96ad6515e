"""Limits and malformed input found in review: each gets a clear error, never a traceback."""

import json

import numpy as np
import pytest
import scipy.linalg as sla

from agent.cli.main import main
from design.closed_loop import ClosedLoop
from design.errors import GainsError, ScenarioError
from design.gains import load_gains, save_gains
from design.scenario import MAX_DELAY, resolve_delays, scenario_from_dict


def _gain(s, scale=0.3, seed=0):
    rng = np.random.default_rng(seed)
    return [scale * rng.normal(size=(s.n, len(m))) for m in s.measure]


@pytest.fixture()
def gains_file(tmp_path, paper14):
    path = tmp_path / "g.npz"
    save_gains(path, _gain(paper14), {"method": "hand"})
    return path


@pytest.mark.slow
def test_radius_of_a_large_companion_matches_dense_eigenvalues(paper14):
    """Order 2058 > the dense threshold: ARPACK (or its dense fallback) must be exact."""
    loop = ClosedLoop(paper14.A, paper14.W, resolve_delays(paper14, "uniform:48"),
                      paper14.measure, _gain(paper14))
    assert loop.order > 2000
    dense = float(np.max(np.abs(sla.eigvals(loop.companion(sparse=False)))))
    assert loop.spectral_radius() == pytest.approx(dense, rel=1e-9)


def test_delays_above_the_limit_are_rejected(paper14):
    with pytest.raises(ScenarioError, match="largest delay"):
        resolve_delays(paper14, f"uniform:{MAX_DELAY + 1}")
    with pytest.raises(ScenarioError, match="non-negative integer"):
        resolve_delays(paper14, "uniform:²")
    data = {"social": {"A": [[0.5, 0.1], [0.2, 0.5]]},
            "agents": {"measure": [["1"], ["2"]]},
            "network": {"delays": [[0, 10**30], [0, 0]]}}
    with pytest.raises(ScenarioError, match="network.delays"):
        scenario_from_dict(data)
    data["network"] = {"max_delay": MAX_DELAY + 1}
    with pytest.raises(ScenarioError, match="network.max_delay"):
        scenario_from_dict(data)


def test_huge_standby_and_huge_entries_are_rejected():
    base = {"social": {"A": [[0.5, 0.1], [0.2, 0.5]]}, "agents": {"measure": [["1"], ["2"]]}}
    with pytest.raises(ScenarioError, match="agents.standby"):
        scenario_from_dict({**base, "agents": {"measure": [["1"], ["2"]], "standby": 2**62}})
    with pytest.raises(ScenarioError, match="below 1e150"):
        scenario_from_dict({**base, "social": {"A": [[1e308, 0.1], [0.2, 0.5]]}})


def test_edges_file_not_utf8_and_huge_ids(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_bytes(b"listener,influencer\n1,2\n\xff\xfe,1\n")
    big = tmp_path / "big.csv"
    big.write_text("listener,influencer\n1,2\n2,999999999999\n")
    for path, match in ((bad, "not UTF-8"), (big, "largest supported")):
        data = {"social": {"edges": str(path)}, "agents": {"measure": [["1"]]}}
        with pytest.raises(ScenarioError, match=match):
            scenario_from_dict(data)


def test_complex_gains_are_rejected(tmp_path, paper14):
    path = tmp_path / "c.npz"
    arrays = {f"K{i + 1}": g.astype(complex) for i, g in enumerate(_gain(paper14))}
    np.savez(path, **arrays, meta=np.array(json.dumps({})))
    with pytest.raises(GainsError, match="K1 must hold real numbers"):
        load_gains(path, paper14)


@pytest.mark.parametrize("argv, match", [
    (["plan", "paper-14", "--fail", "²"], "--fail"),
    (["certify", "paper-14", "--gains", "GAINS", "--taus", "99999999"], "--taus"),
    (["certify", "paper-14", "--gains", "GAINS", "--taus", "²"], "--taus"),
    (["simulate", "paper-14", "--gains", "GAINS", "--fail", "3:²"], "--fail"),
    (["world", "paper-14", "--seed", "-1", "--steps", "1"], "--seed"),
    (["world", "paper-14", "--steps", "\u0661"], "--steps"),           # Arabic-Indic one
    (["world", "paper-14", "--wait-agents", "1,9"], "--wait-agents: no agent 9"),
    (["analyze", "paper-14", "--max-subsets", "1_000"], "--max-subsets"),
    (["design", "paper-14", "--starts", "0", "--out", "FILE"], "--starts"),
    (["certify", "paper-14", "--gains", "GAINS", "--tau-cap", "-2"], "--tau-cap"),
    (["inject", "drop", "x", "1", "0.5"], "argument src: expected an integer"),
    (["simulate", "paper-14", "--gains", "GAINS", "--fail", "\u00b2:1"], "--fail STEP"),
    (["world", "paper-14", "--start-timeout", "nan", "--steps", "1"], "--start-timeout"),
    (["up", "paper-14", "--gains", "GAINS", "--out", "FILE", "--steps", "2"], "--out"),
])
def test_cli_bad_flags_exit_2(argv, match, gains_file, tmp_path, capsys):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    argv = [str(gains_file) if a == "GAINS" else str(blocker) if a == "FILE" else a
            for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert match in err and "Traceback" not in err


def test_simulate_calls_a_certified_unstable_loop_unstable(gains_file, capsys):
    """The exact radius decides, not only the growth seen in a short run."""
    code = main(["simulate", "paper-14", "--gains", str(gains_file), "--trials", "2",
                 "--steps", "20", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert out["rho_exact"] > 1 and out["unstable"] is True
    assert code == 1


def test_simulate_too_many_steps_is_a_clear_error(gains_file, capsys):
    assert main(["simulate", "paper-14", "--gains", str(gains_file),
                 "--steps", "99999999999999"]) == 2
    assert "do not fit in memory" in capsys.readouterr().err
