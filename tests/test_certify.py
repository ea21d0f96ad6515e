"""Certificates: hand-computed scalar loop, the paper's formula rows, paper-14, CLI."""

import json

import numpy as np
import pytest

from agent.cli.main import main
from design.certificates import CertifyError, certify, find_tau_star, paper_formula
from design.closed_loop import ClosedLoop
from design.errors import GainsError
from design.gains import gains_meta, save_gains
from design.scenario import scenario_from_dict, uniform_delays
from scripts.bench_analysis import radius_descent_gain

# ---------------------------------------------------------------------------------
# the paper's table formula


@pytest.mark.parametrize("rho, tau, table", [
    (0.871, 3, 0.966),      # Table 2 prints 0.970 for 0.871 at tau 3 (NOTES section 3)
    (0.461, 5, 0.879),      # Table 4 (Sampson), tau 5
    (0.461, 20, 0.964),     # Table 4, tau 20
])
def test_paper_formula_rows(rho, tau, table):
    assert paper_formula(rho, tau) == pytest.approx(rho ** (1 / (tau + 1)))
    assert round(paper_formula(rho, tau), 3) == table
    assert paper_formula(rho, 0) == pytest.approx(rho)


# ---------------------------------------------------------------------------------
# a scalar system, two agents, computed by hand


def two_agents(a=1.1, q=0.1, r=0.1):
    return scenario_from_dict({
        "social": {"A": [[a]], "process_noise": q},
        "agents": {"measure": [["1"], ["1"]], "measurement_noise": r},
        "network": {"topology": "complete", "self_weight": 0.5},
    })


G_HALF = [np.array([[0.5]]), np.array([[0.5]])]


def test_scalar_certificate_by_hand():
    s = two_agents()
    c = certify(s, G_HALF, taus=[0, 2, 5])
    # Ahat = (1 - 0.5) * 1.1 * W, W = [[.5, .5], [.5, .5]] has eigenvalues 1, 0
    assert c["rho_delay_free"] == pytest.approx(0.55)
    assert c["rho_exact"] == pytest.approx(0.55)
    # Theorem 1: 0.5 * 1.1^(tau+1) < 1 iff tau + 1 <= 7
    assert c["tau_star"] == 6 and not c["tau_star_capped"]
    for row in c["rows"]:
        tau = row["tau"]
        assert row["theorem1_rho"] == pytest.approx(0.5 * 1.1 ** (tau + 1))
        assert row["paper_formula"] == pytest.approx(0.55 ** (1 / (tau + 1)))
        # exact: sum and difference modes z^(tau+1) - 0.275 z^tau -+ 0.25 * 1.1^(tau+1) = 0
        g = 0.25 * 1.1 ** (tau + 1)
        roots = []
        for sign in (1, -1):
            poly = np.zeros(tau + 2)
            poly[0], poly[1] = 1.0, -0.275
            poly[-1] -= sign * g
            roots.extend(np.roots(poly))
        assert row["rho_exact"] == pytest.approx(max(abs(z) for z in roots), rel=1e-9)
    # MSE: s = e1 + e2 has s_k = 0.55 s + nu - (z1 + z2)/2; d = e1 - e2 = -(z1 - z2)/2
    var_s = (0.1 + 0.5 * 0.1) / (1 - 0.55**2)
    var_d = 0.5 * 0.1
    assert c["mse_steady_delay_free"] == pytest.approx((var_s + var_d) / 4)
    # Phi: ||Ahat|| = 0.55, beta = 1 - 0.3025, alpha1 = alpha2 = 0.25, N = 2
    assert c["norm_Ahat"] == pytest.approx(0.55)
    assert c["phi_beta"] == pytest.approx(0.6975)
    assert c["phi"] == pytest.approx((0.25 * 2 * 0.1 + 0.25 * 0.1) / (2 * 0.6975))


def test_certify_reports_each_stage_and_prints_nothing(capsys):
    """The status line of ``socmon certify`` is fed stage by stage (design prints nothing)."""
    stages = []
    c = certify(two_agents(), G_HALF, taus=[0, 2, 5], tau_cap=10, progress=stages.append)
    assert stages == ["Theorem 1 criterion for tau = 0..10",
                      "tau = 0 (1 of 3): exact radius and steady MSE",
                      "tau = 2 (2 of 3): exact radius and steady MSE",
                      "tau = 5 (3 of 3): exact radius and steady MSE"]
    assert [r["tau"] for r in c["rows"]] == [0, 2, 5]
    assert capsys.readouterr() == ("", "")


def test_mse_with_scenario_delays_is_the_exact_delayed_one():
    s = two_agents().replace(delays=np.array([[0, 2], [1, 0]]))
    c = certify(s, G_HALF, taus=[0])
    loop = ClosedLoop(s.A, s.W, s.delays, s.measure, G_HALF)
    assert c["rho_exact"] == pytest.approx(loop.spectral_radius())
    assert c["scenario_taubar"] == 2 and c["stable"]
    assert c["mse_steady_exact"] == pytest.approx(loop.mse_steady(0.1, 0.1))
    assert c["mse_steady_exact"] != pytest.approx(c["mse_steady_delay_free"])


def test_every_row_has_the_exact_mse_at_its_delay():
    s = two_agents()
    c = certify(s, G_HALF, taus=[0, 1, 4])
    assert c["rows"][0]["mse_steady_exact"] == pytest.approx(c["mse_steady_delay_free"])
    for row in c["rows"]:
        loop = ClosedLoop(s.A, s.W, uniform_delays(s.W, row["tau"]), s.measure, G_HALF)
        assert row["stable"]
        assert row["mse_steady_exact"] == pytest.approx(loop.mse_steady(0.1, 0.1), rel=1e-10)
    assert c["rows"][2]["mse_steady_exact"] > c["rows"][0]["mse_steady_exact"]
    unstable = certify(two_agents(a=3.0), G_HALF, taus=[0, 2])
    assert [r["mse_steady_exact"] for r in unstable["rows"]] == [None, None]


def test_unstable_loop_has_no_mse_and_phi_undefined():
    s = two_agents(a=3.0)
    c = certify(s, G_HALF, taus=[0, 1])
    assert c["rho_delay_free"] == pytest.approx(1.5)
    assert c["mse_steady_delay_free"] is None and c["mse_steady_exact"] is None
    assert c["phi"] is None and "Phi is undefined" in c["phi_note"]
    assert c["tau_star"] is None


def test_tau_star_search_stops_at_the_cap_for_stable_A():
    s = two_agents(a=0.9)
    assert find_tau_star(s.A, s.W, s.measure, G_HALF, cap=12) == (12, True)
    c = certify(s, G_HALF, taus=[0], tau_cap=12)
    assert c["tau_star"] == 12 and c["tau_star_capped"] and c["tau_star_cap"] == 12


def test_bad_requests():
    s = two_agents()
    with pytest.raises(CertifyError, match="taus: each tau must be a non-negative integer, got -1"):
        certify(s, G_HALF, taus=[0, -1])
    with pytest.raises(CertifyError, match="tau_cap"):
        find_tau_star(s.A, s.W, s.measure, G_HALF, cap=-2)
    with pytest.raises(GainsError, match="K2 must be 1 x 1"):
        certify(s, [np.array([[0.5]]), np.zeros((2, 1))])
    with pytest.raises(GainsError, match="1 gain arrays for 2 agents"):
        certify(s, [np.array([[0.5]])])


# ---------------------------------------------------------------------------------
# paper-14


@pytest.fixture(scope="module")
def paper14_gain(paper14):
    rho, G = radius_descent_gain(paper14, steps=300)
    assert rho < 0.8
    return G


def test_paper14_certificate_is_consistent(paper14, paper14_gain):
    c = certify(paper14, paper14_gain, taus=[0, 1, 2, 3])
    assert c["rho_delay_free"] < 0.8 and c["stable_delay_free"]
    ts = c["tau_star"]
    assert ts is not None and not c["tau_star_capped"]
    for row in c["rows"]:
        assert row["theorem1_holds"] == (row["tau"] <= ts)
    assert c["rows"][0]["rho_exact"] == pytest.approx(c["rho_delay_free"])
    # NOTES 3: a delay-free design loses stability once the delays reach ~3 steps
    assert c["rows"][3]["rho_exact"] > 1.0 and c["rows"][3]["paper_formula"] < 1.0
    assert c["mse_steady_delay_free"] > 0


# ---------------------------------------------------------------------------------
# CLI

CERT_KEYS = {"rho_delay_free", "rho_exact", "tau_star", "rows", "mse_steady_delay_free",
             "mse_steady_exact", "phi", "tau_star_cap"}


def test_cli_certify_paper14(tmp_path, paper14, paper14_gain, capsys):
    path = tmp_path / "g.npz"
    save_gains(path, paper14_gain, gains_meta(paper14, "radius-descent", paper14.delays, 0.78))
    assert main(["certify", "paper-14", "--gains", str(path), "--taus", "0,3", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert CERT_KEYS <= set(d)
    assert [r["tau"] for r in d["rows"]] == [0, 3]
    assert {"tau", "rho_exact", "paper_formula", "theorem1_holds"} <= set(d["rows"][0])
    assert main(["certify", "paper-14", "--gains", str(path), "--taus", "0"]) == 0
    out = capsys.readouterr().out
    assert "paper's formula" in out and "Theorem 1" in out


def test_cli_certify_unstable_gain_exits_1(tmp_path, paper14, capsys):
    path = tmp_path / "zero.npz"
    save_gains(path, [np.zeros((14, 1))] * 3, {"method": "zero"})
    assert main(["certify", "paper-14", "--gains", str(path), "--taus", "0", "--json"]) == 1
    d = json.loads(capsys.readouterr().out)
    assert d["rho_exact"] > 1 and d["mse_steady_delay_free"] is None


@pytest.mark.parametrize("taus, message", [
    ("0,x", "--taus: expected comma-separated non-negative integers, got 'x'"),
    ("-1", "--taus: expected comma-separated non-negative integers, got '-1'"),
    ("1.5", "got '1.5'"),
    (",", "--taus: give at least one delay"),
])
def test_cli_certify_bad_taus(tmp_path, capsys, taus, message):
    path = tmp_path / "zero.npz"
    save_gains(path, [np.zeros((14, 1))] * 3, {"method": "zero"})
    assert main(["certify", "paper-14", "--gains", str(path), f"--taus={taus}"]) == 2
    assert message in capsys.readouterr().err


def test_cli_certify_bad_gains_files(tmp_path, capsys):
    missing = tmp_path / "none.npz"
    assert main(["certify", "paper-14", "--gains", str(missing)]) == 2
    assert "no such gains file" in capsys.readouterr().err
    junk = tmp_path / "junk.npz"
    junk.write_text("not a zip")
    assert main(["certify", "paper-14", "--gains", str(junk)]) == 2
    assert "not a .npz gains file" in capsys.readouterr().err
    wrong = tmp_path / "wrong.npz"
    save_gains(wrong, [np.zeros((14, 2))] * 3, {"method": "wrong"})
    assert main(["certify", "paper-14", "--gains", str(wrong)]) == 2
    assert "K1 must be 14 x 1" in capsys.readouterr().err
    few = tmp_path / "few.npz"
    save_gains(few, [np.zeros((14, 1))] * 2, {"method": "few"})
    assert main(["certify", "paper-14", "--gains", str(few)]) == 2
    assert "2 gain arrays for 3 agents" in capsys.readouterr().err


def test_the_sparse_spectral_radius_is_the_dense_one_on_clustered_spectra(monkeypatch):
    """Long uniform delays give many eigenvalues of nearly equal modulus, where one
    Arnoldi run can settle just inside the radius: the answer must still be exact and
    the same on every call."""
    import scipy.linalg as sla

    import design.closed_loop as cl
    from design.scenario import load_scenario, uniform_delays

    s = load_scenario("paper-14-live")
    G = [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure]
    M = cl.closed_loop_for(s, G, uniform_delays(s.W, 12)).companion(sparse=True)
    dense = float(np.max(np.abs(sla.eigvals(M.toarray()))))
    monkeypatch.setattr(cl, "DENSE_EIG_MAX_ORDER", 10)     # the sparse path at order 546
    got = [cl.spectral_radius(M) for _ in range(3)]
    assert got == [got[0]] * 3
    assert got[0] == pytest.approx(dense, rel=1e-10)
