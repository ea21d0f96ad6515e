"""The gap between a failure and the switch, checked against a direct construction."""

import numpy as np
import pytest

from design.closed_loop import ClosedLoop
from design.gap import diverging_gaps, gap_loop, gap_report, own_loop_radius
from design.scenario import load_scenario


def test_the_gap_loop_moves_the_failed_agents_weight_to_each_receivers_own(paper14):
    s = paper14
    G = [0.3 * np.eye(s.n)[:, list(m)] for m in s.measure]
    loop = gap_loop(s, G, s.delays, 0)        # agent 1 gone; W: 1<-2, 2<-3, 3<-1
    W = s.W
    expected_W = np.array([[W[1, 1], W[1, 2]], [W[2, 1], W[2, 2] + W[2, 0]]])
    assert np.allclose(loop.W, expected_W) and np.allclose(loop.W.sum(axis=1), 1)
    assert loop.measure == [tuple(s.measure[1]), tuple(s.measure[2])]
    direct = ClosedLoop(s.A, expected_W, s.delays[1:, 1:], s.measure[1:], G[1:])
    assert loop.spectral_radius() == pytest.approx(direct.spectral_radius(), abs=1e-12)


def test_gap_radius_equals_the_dense_eigenvalues_with_delays():
    s = load_scenario("paper-14-live")
    G = [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure]
    D = np.where(np.eye(3, dtype=bool), 0, 3)
    for g, f in zip(gap_report(s, G, D), range(3)):
        loop = gap_loop(s, G, D, f)
        dense = np.max(np.abs(np.linalg.eigvals(loop.companion())))
        assert g.rho == pytest.approx(dense, abs=1e-9)
        assert g.mse_steady is not None and g.mse_steady > 0


def test_an_agent_alone_on_an_unstable_own_loop_makes_the_gap_diverge():
    A = np.array([[1.2]])
    assert own_loop_radius(A, (0,), np.array([[0.1]])) == pytest.approx(1.08)
    s = load_scenario("paper-14")                   # rho(A) = 1.086
    G = [0.02 * np.eye(s.n)[:, list(m)] for m in s.measure]    # weak corrections
    report = gap_report(s, G, mse=False)
    assert all(not g.stable for g in report)
    lines = diverging_gaps(report)
    assert len(lines) == 3 and lines[0].startswith("agent 1 fails: the others run a loop")


def test_certify_reports_every_gap(capsys, live_gains):
    from agent.cli.main import main

    assert main(["certify", "paper-14-live", "--gains", str(live_gains), "--json"]) == 0
    import json

    out = json.loads(capsys.readouterr().out)
    assert [g["failed"] for g in out["gaps"]] == [1, 2, 3]
    assert all(set(g) == {"failed", "rho_exact", "stable", "mse_steady_exact",
                          "own_loop_radius"} for g in out["gaps"])


# -- a hand example: three agents, two states, delays ---------------------------------

def _three_agents():
    from design.scenario import scenario_from_dict

    return scenario_from_dict({
        "social": {"A": [[0.9, 0.2], [0.1, 0.8]]},
        "agents": {"measure": [["1"], ["2"], ["1"]]},
        "network": {"weights": [[0.5, 0.3, 0.2], [0.25, 0.5, 0.25], [0.4, 0.0, 0.6]],
                    "delays": [[0, 1, 2], [1, 0, 0], [3, 0, 0]]},
    })


G3 = [np.array([[0.5], [0.1]]), np.array([[0.2], [0.7]]), np.array([[0.3], [0.2]])]


def test_a_gap_by_hand_equals_its_direct_construction():
    s = _three_agents()
    loop = gap_loop(s, G3, None, 1)               # agent 2 gone
    # by hand: agent 1 keeps 0.5 + 0.3 on itself and 0.2 on agent 3 (delay 2); agent 3
    # has no link from agent 2: 0.4 on agent 1 (delay 3), 0.6 on itself
    np.testing.assert_allclose(loop.W, [[0.8, 0.2], [0.4, 0.6]])
    np.testing.assert_array_equal(loop.delays, [[0, 2], [3, 0]])
    A = s.A
    L = [np.eye(2) - np.outer(G3[0][:, 0], [1, 0]), np.eye(2) - np.outer(G3[2][:, 0], [1, 0])]
    Ap = [np.linalg.matrix_power(A, r) for r in range(5)]
    # e_k = sum_r blockdiag(L) (W_r (x) A^(r+1)) e_(k-1-r), r = 0..3
    F = [np.zeros((4, 4)) for _ in range(4)]
    F[0][:2, :2] = 0.8 * L[0] @ Ap[1]
    F[0][2:, 2:] = 0.6 * L[1] @ Ap[1]
    F[2][:2, 2:] = 0.2 * L[0] @ Ap[3]
    F[3][2:, :2] = 0.4 * L[1] @ Ap[4]
    M = np.zeros((16, 16))
    M[:4] = np.hstack(F)
    M[4:, :12] = np.eye(12)
    np.testing.assert_allclose(loop.companion(sparse=False), M, atol=1e-15)
    report = gap_report(s, G3, mse=False)
    assert report[1].rho == pytest.approx(np.max(np.abs(np.linalg.eigvals(M))), abs=1e-12)
    # own loops: (I - G_i H_i) A
    assert report[1].own_radius[1] == pytest.approx(
        np.max(np.abs(np.linalg.eigvals(L[0] @ A))), abs=1e-12)


def test_the_gap_penalty_gradient_matches_finite_differences():
    from design.gradient import GapTerms
    from design.gradient import LoopModel

    s = _three_agents()
    terms = GapTerms(s, s.delays)
    x = LoopModel(s.A, s.W, s.delays, s.measure).pack(G3)
    P, grad, radii = terms.penalty_and_gradient(x, threshold=0.0)
    assert P == pytest.approx(sum(radii.values()))
    assert radii == pytest.approx(terms.radii(x), abs=1e-10)
    h = 1e-6
    for i in range(x.size):
        e = np.zeros(x.size)
        e[i] = h
        fd = (terms.penalty_and_gradient(x + e, 0.0)[0]
              - terms.penalty_and_gradient(x - e, 0.0)[0]) / (2 * h)
        assert grad[i] == pytest.approx(fd, abs=1e-5)


# -- the design keeps the gaps stable -------------------------------------------------

FAST = {"objective": "rho", "target": 0.95, "max_iter": 60, "starts": 2}


@pytest.mark.parametrize("tau", [3, pytest.param(15, marks=pytest.mark.slow)])
def test_the_design_keeps_every_gap_stable_on_paper14_live(tau):
    from design.gain_design import design_gains

    s = load_scenario("paper-14-live")
    plain = design_gains(s, delays=f"uniform:{tau}", gaps=False, **FAST)
    assert plain.stable and max(g["rho_exact"] for g in plain.gaps) > 1   # the premise
    res = design_gains(s, delays=f"uniform:{tau}", **FAST)
    assert res.stable and res.rho < 0.95
    assert res.gap_design["met"] and res.gap_design["iterations"] > 0
    assert res.gap_design["rho_gap_before"] == pytest.approx(
        {str(g["failed"]): g["rho_exact"] for g in plain.gaps}, abs=1e-9)
    check = gap_report(s, res.G, res.delays, mse=False)
    assert [g.rho for g in check] == pytest.approx([g["rho_exact"] for g in res.gaps],
                                                   abs=1e-12)
    assert all(g.rho < res.gap_design["target"] for g in check)
    if tau == 15:
        # agent 3 killed, no recovery: the gap loop runs for good
        from design.simulate import simulate

        runs = [simulate(s, G, steps=400, trials=4, seed=0, delays=res.delays,
                         fail=(150, [2])) for G in (plain.G, res.G)]
        assert runs[0].mse[-1] > 1e3 * runs[0].mse[150]
        assert np.all(np.isfinite(runs[1].mse)) and runs[1].mse[-1] < 5 * runs[1].mse[150]


def test_a_gap_no_gain_can_stabilise_is_named():
    from design.gain_design import design_gains
    from design.scenario import scenario_from_dict

    # two parents, node 2 unstable and measured by agent 2 alone: when agent 2 fails,
    # nobody sees it
    s = scenario_from_dict({"social": {"A": [[0.5, 0.0], [0.0, 1.2]]},
                            "agents": {"measure": [["1"], ["2"]]}})
    res = design_gains(s, delays="none", objective="mse")
    assert res.stable
    assert res.gap_design["impossible"] == [{"failed": 2, "bound": pytest.approx(1.2)}]
    assert not res.gap_design["met"] and "agent 2 fails cannot be stable" in \
        res.gap_design["note"]
    assert [g["stable"] for g in res.gaps] == [True, False]


def test_nothing_changes_when_the_nominal_design_keeps_the_gaps_stable():
    from design.gain_design import design_gains

    s = load_scenario("paper-14-live")
    on = design_gains(s, delays="uniform:3", objective="mse")
    off = design_gains(s, delays="uniform:3", objective="mse", gaps=False)
    assert on.gap_design["iterations"] == 0 and on.gap_design["met"]
    assert all(np.array_equal(a, b) for a, b in zip(on.G, off.G))
    assert off.gap_design == {} and off.gaps == on.gaps


def test_analyze_design_and_certify_speak_of_the_gaps(tmp_path, capsys):
    import json

    from agent.cli.main import main

    out = tmp_path / "g.npz"
    assert main(["design", "paper-14-live", "--delays", "uniform:3", "--target", "0.95",
                 "--starts", "2", "--max-iter", "60", "--out", str(out), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert [g["failed"] for g in d["gaps"]] == [1, 2, 3]
    assert set(d["gaps"][0]) == {"failed", "rho_exact", "stable", "own_loop_radius"}
    assert set(d["gap_design"]) == {"enabled", "target", "met", "rho_gap_before",
                                    "iterations", "impossible", "note"}
    assert d["gap_design"]["met"] and all(g["stable"] for g in d["gaps"])
    assert main(["certify", "paper-14-live", "--gains", str(out), "--taus", "0,3",
                 "--json"]) == 0
    c = json.loads(capsys.readouterr().out)
    assert [sorted(r["gaps_rho_exact"]) for r in c["rows"]] == [["1", "2", "3"]] * 2
    assert c["rows"][1]["gaps_rho_exact"] == pytest.approx(
        {str(g["failed"]): g["rho_exact"] for g in d["gaps"]}, abs=1e-9)
    assert main(["analyze", "paper-14-live", "--gains", str(out), "--json"]) == 0
    a = json.loads(capsys.readouterr().out)
    assert [g["detectable"] for g in a["gap_detectability"]] == [True] * 3
    assert set(a["own_loop_bound"]) == {"1", "2", "3"}
    assert [g["failed"] for g in a["gaps"]] == [1, 2, 3]
    assert main(["analyze", "paper-14-live", "--json"]) == 0
    assert "gaps" not in json.loads(capsys.readouterr().out)
    # without the gap terms: a diverging gap is a warning
    assert main(["design", "paper-14-live", "--delays", "uniform:3", "--target", "0.95",
                 "--starts", "2", "--max-iter", "60", "--out", str(out), "--no-gaps",
                 "--overwrite"]) == 0
    err = capsys.readouterr().err
    assert "if agent 3 fails, the others run a loop of exact radius" in err
