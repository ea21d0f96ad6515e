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
    from agent.cli import main

    assert main(["certify", "paper-14-live", "--gains", str(live_gains), "--json"]) == 0
    import json

    out = json.loads(capsys.readouterr().out)
    assert [g["failed"] for g in out["gaps"]] == [1, 2, 3]
    assert all(set(g) == {"failed", "rho_exact", "stable", "mse_steady_exact",
                          "own_loop_radius"} for g in out["gaps"])
