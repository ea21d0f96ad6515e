"""Runs across network namespaces: every process on its own host, real IP links.

``socmon up --netns`` puts the recorder, the world, each agent and the monitor in a network
namespace of their own, wired to a bridge in a switch namespace (agent/testbed/netns.py); a
``linkdown`` fault brings a host's bridge port down (a real partition) and up again.
Namespace names carry a prefix unique to the test, and a finalizer deletes whatever is left
under it, also when ``socmon up`` was killed. Skipped, with the reason, where namespaces
cannot be made (not root, no iproute2, no CAP_NET_ADMIN).
"""

import itertools
import json
import os
import socket
import subprocess

import pytest

from agent.testbed import netns
from tests.test_runtime_multiprocess import _socmon

_serial = itertools.count()


@pytest.fixture(scope="module")
def can_make_namespaces():
    why = netns.unavailable_reason()
    if why is not None:
        pytest.skip(f"no network namespaces on this machine: {why}")


@pytest.fixture
def prefix(can_make_namespaces):
    """A namespace prefix of this test only; whatever is left under it is deleted after."""
    p = f"st{os.getpid()}x{next(_serial)}"
    yield p
    netns.remove_testbed(p)


def _root_addresses():
    return subprocess.run(["ip", "-4", "-o", "addr", "show"], capture_output=True,
                          text=True, check=True).stdout


def _connects(tb, src, dst, port, timeout):
    """Whether a TCP connection from host ``src`` to ``dst``:``port`` is accepted."""
    with tb.inside(src):
        s = socket.socket()
    with s:
        s.settimeout(timeout)
        try:
            s.connect((tb.ip(dst), port))
            return True
        except OSError:
            return False


# -- the testbed itself -----------------------------------------------------------------------
def test_testbed_names_are_checked():
    with pytest.raises(ValueError, match="prefix"):
        netns.Testbed(["a"], prefix="Bad_Prefix")
    with pytest.raises(ValueError, match="unique"):
        netns.Testbed(["a", "a"], prefix="ok")
    tb = netns.Testbed(netns.host_names(4), prefix="ok")
    assert tb.ip("recorder") == "10.200.0.1" and tb.ip("monitor") == "10.200.0.7"
    assert tb.namespace("agent-3") == "ok-a3" and tb.port("agent-3") == "p-a3"
    with pytest.raises(KeyError, match="no host 'agent-9'"):
        tb.ip("agent-9")


@pytest.mark.netns
def test_a_downed_link_cuts_a_host_off_and_nothing_is_left_behind(prefix):
    """Hosts reach each other over the bridge; a downed port cuts one host off, bringing it
    up again restores it; the namespace it was made from gains no address, and closing
    removes every namespace."""
    before = _root_addresses()
    with netns.Testbed(["a", "b", "c"], prefix=prefix) as tb:
        assert "10.200." not in _root_addresses()
        with tb.inside("a"):
            server = socket.socket()
        with tb.inside("b"):
            server_b = socket.socket()
        with server, server_b:
            server.bind((tb.ip("a"), 0))
            server.listen(8)
            port = server.getsockname()[1]
            server_b.bind((tb.ip("b"), 0))
            server_b.listen(8)
            port_b = server_b.getsockname()[1]
            assert _connects(tb, "b", "a", port, 5.0)
            tb.set_link("a", up=False)
            assert not _connects(tb, "b", "a", port, 0.5)
            assert _connects(tb, "c", "b", port_b, 5.0)      # the others still reach each other
            tb.set_link("a", up=True)
            assert any(_connects(tb, "c", "a", port, 1.0) for _ in range(10))
    assert not [n for n in netns.list_namespaces() if n.startswith(prefix + "-")]
    assert _root_addresses() == before


@pytest.mark.netns
def test_every_host_of_a_32_agent_mesh_reaches_every_other(prefix):
    """The 35 hosts of a 32-agent run (and the router's 36th): every pair connects. They
    need 1,190 neighbour entries and the kernel learns at most 1,024 for all namespaces
    together; before the testbed gave each host permanent ones, connections of a few pairs
    stayed in SYN-SENT and one agent of a 32-agent mesh never started."""
    hosts = netns.host_names(32, router=True)
    with netns.Testbed(hosts, prefix=prefix) as tb:
        servers = []
        for h in hosts:
            with tb.inside(h):
                server = socket.socket()
            server.bind((tb.ip(h), 0))
            server.listen(len(hosts))
            servers.append(server)
        try:
            failed = [(a, b) for a in hosts for b, server in zip(hosts, servers)
                      if a != b and not _connects(tb, a, b, server.getsockname()[1], 5.0)]
        finally:
            for server in servers:
                server.close()
        assert failed == []
        neigh = subprocess.run(["ip", "-n", tb.namespace("agent-7"), "neigh", "show",
                                tb.ip("agent-31")], capture_output=True, text=True,
                               check=True).stdout
        assert tb.mac("agent-31") in neigh and "PERMANENT" in neigh
    assert not [n for n in netns.list_namespaces() if n.startswith(prefix + "-")]


@pytest.mark.netns
def test_a_prefix_in_use_is_refused_before_anything_is_written(prefix, tmp_path, capsys):
    """Namespaces of the prefix exist: ``up`` says so before it designs a gain or makes
    the run folder, so that the same command runs once they are deleted."""
    from agent.cli.main import main

    subprocess.run(["ip", "netns", "add", f"{prefix}-a1"], check=True)
    assert main(["up", "paper-14-live", "--netns", "--netns-prefix", prefix,
                 "--out", str(tmp_path / "run")]) == 1
    assert f"--netns: namespaces named {prefix}-* exist already" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


# -- whole runs -------------------------------------------------------------------------------
def _up(tmp_path, gains, prefix, *flags, steps):
    code, out, err = _socmon("up", "paper-14-live", "--steps", str(steps), "--gains",
                             str(gains), "--out", str(tmp_path / "run"), "--json",
                             "--step-ms", "20", "--netns", "--netns-prefix", prefix, *flags)
    assert code == 0, err
    assert not [n for n in netns.list_namespaces() if n.startswith(prefix + "-")], \
        "socmon up left namespaces behind"
    return json.loads(out)


@pytest.mark.multiprocess
@pytest.mark.netns
@pytest.mark.slow
def test_a_run_across_namespaces_equals_the_simulator(tmp_path, live_gains, prefix):
    """Recorder, world, four agents and the monitor, each on its own host (its endpoint an
    address that exists only in its namespace); the estimates equal design.simulate's."""
    s = _up(tmp_path, live_gains, prefix, "--check-simulator", steps=150)
    assert s["max_rel_diff_vs_simulator"] <= 1e-9 and s["malformed"] == 0
    assert s["simulator_compared"].startswith("estimates")
    procs = json.loads((tmp_path / "run" / "run.json").read_text())["processes"]
    names = [n if n != "monitor" else "monitor-1" for n in netns.host_names(4)]
    assert [procs[n]["endpoint"].split(":")[0] for n in names] == \
        [f"tcp/10.200.0.{i}" for i in range(1, 8)]
    assert len({procs[n]["netns"] for n in names}) == 7
    assert all(procs[n]["netns"].startswith(prefix + "-") for n in names)


@pytest.mark.multiprocess
@pytest.mark.netns
@pytest.mark.slow
def test_a_routed_run_across_namespaces_recovers_a_crash(tmp_path, live_gains, prefix):
    """``--router --netns``: the zenoh router on a host of its own, every other process its
    client from its own host; agent 2 killed, the standby takes its role, and the
    estimates equal design.simulate's with the recovery."""
    s = _up(tmp_path, live_gains, prefix, "--router", "--kill", "100:2", "--check-simulator",
            steps=300)
    assert s["max_rel_diff_vs_simulator"] <= 1e-9 and s["malformed"] == 0
    (f,) = s["failures"]
    assert f["agent"] == 2 and f["replacement"]["agent"] == 4 and s["recovered"], f
    procs = json.loads((tmp_path / "run" / "run.json").read_text())["processes"]
    assert procs["router"]["endpoint"].startswith("tcp/10.200.0.8:")   # after the monitor's
    hosts = {name: p["netns"] for name, p in procs.items()}
    assert hosts["router"] == f"{prefix}-rtr"
    # a host each but the standby monitor's (the monitor's) and the recorder's (up's own,
    # not a child)
    assert len(set(hosts.values())) == len(netns.host_names(4, router=True)) - 1
    assert all("endpoint" not in p for name, p in procs.items() if name != "router")


@pytest.mark.multiprocess
@pytest.mark.netns
@pytest.mark.slow
def test_a_host_cut_off_is_replaced_and_fenced_when_its_link_returns(tmp_path, live_gains,
                                                                    prefix):
    """Agent 2's link is down for 2 s: the monitor convicts it while it is cut off (its
    statuses stop, then its token's lease expires), the standby takes its role; when the
    link is up again agent 2 reconnects, its estimates are rejected by the receivers
    (older epoch) and it drops its role on hearing the roster."""
    # 300 steps (6 s) after the link returns: the old agent hears the roster once the
    # monitor's session reaches it again (about 1 s when reconnection is prompt)
    s = _up(tmp_path, live_gains, prefix, "--fault", "linkdown:100:2:2", steps=500)
    down, up = (e for e in s["events"] if e.get("link"))
    assert (down["link"], up["link"]) == ("down", "up")
    f, *others = s["failures"]
    assert f["agent"] == 2 and f["cause"] in {"hang", "crash"}, f
    assert 0 < f["detection_ms"] < 1e3 * (up["t"] - down["t"])
    assert down["step"] <= f["detected_step"] < up["step"]
    assert f["replacement"]["agent"] == 4 and s["recovered"]
    # no healthy agent is convicted: before the linger guard (broker_free_net/linger.py)
    # the receive threads of the other hosts slept in close() until the link returned,
    # and the monitor convicted a survivor in 4 of 22 runs
    assert others == [], others
    # the first reassignment hands agent 2's role to the standby
    assert 2 not in s["rosters"][1]["ids"] and 4 in s["rosters"][1]["ids"]
    verdicts = [json.loads(line) for line in
                (tmp_path / "run" / "events.jsonl").read_text().splitlines()]
    assert [v["agent"] for v in verdicts if v.get("kind") == "verdict"][0] == 2
    final = s["final_roles"]
    assert all(2 not in r["ids"] for r in s["rosters"][1:])
    assert final["2"]["active"] is False and final["2"]["epoch"] >= f["epoch"]
    assert 2 not in s["rosters"][-1]["ids"] and 4 in s["rosters"][-1]["ids"]
    assert final["4"]["active"] is True
    assert f["fenced_ms"] >= 0            # dropped its role after the link came back
    assert s["fenced"] > 0                # its estimates were rejected meanwhile
    assert s["exit_status"]["agent-2"] == 0 and s["orphans"] == []


@pytest.mark.multiprocess
@pytest.mark.netns
@pytest.mark.slow
def test_a_run_whose_recorder_heard_no_step_fails_and_says_why(tmp_path, live_gains, prefix,
                                                               monkeypatch, capsys):
    """The recorder's endpoint an address of its own namespace that no other host reaches
    (what ``--listen 127.0.0.1`` did with ``--netns`` before it was refused): the world
    runs its steps and ends, nobody told the recorder. That run reports no step and exits
    1 with the reason, not 0 with "-1 steps, mse nan"."""
    import dataclasses

    from agent.cli.main import main
    from agent.run import setup
    from broker_free_net.ports import listen_port

    unreachable = f"tcp/127.0.0.1:{listen_port()}"
    config_of = setup.run_config
    monkeypatch.setattr(setup, "run_config", lambda *a, **k: dataclasses.replace(
        config_of(*a, **k), listen=unreachable))
    assert main(["up", "paper-14-live", "--steps", "40", "--gains", str(live_gains),
                 "--out", str(tmp_path / "run"), "--step-ms", "20", "--no-monitor",
                 "--netns", "--netns-prefix", prefix]) == 1
    out, err = capsys.readouterr()
    assert out.splitlines()[0] == "paper-14-live: no step recorded"
    assert ("the world ran and ended (exit 0), but this command's recorder heard none of "
            f"its steps: the processes did not reach it through {unreachable}") in err
    assert "world: done after step 40" in err       # the world's log, quoted
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["steps"] == -1 and "recorder heard none" in summary["error"]
    assert not [n for n in netns.list_namespaces() if n.startswith(prefix + "-")]


@pytest.mark.parametrize("flags, message", [
    (["--fault", "linkdown:100:2:2"], "linkdown brings a host's link down and needs --netns"),
    (["--netns", "--fault", "linkdown:100:2"], "linkdown needs SECONDS > 0"),
    (["--netns-prefix", "abc"], "--netns-prefix: only with --netns"),
    (["--netns", "--listen", "tcp/127.0.0.1:7447"], "--listen: not with --netns: each "
     "process is on a host of its own"),
    (["--netns", "--netns-prefix", "a-b"], "--netns-prefix: prefix: expected 1-12 lower-case"),
])
def test_netns_flags_are_checked_before_anything_starts(tmp_path, capsys, flags, message):
    from agent.cli.main import main

    assert main(["up", "paper-14-live", "--out", str(tmp_path / "run"), *flags]) == 2
    assert message in capsys.readouterr().err


@pytest.mark.multiprocess
@pytest.mark.netns
@pytest.mark.slow
def test_a_terminated_run_removes_its_testbed_and_its_processes(tmp_path, live_gains, prefix):
    """SIGTERM to ``up --netns`` while it runs: exit 130, no child left, no namespace."""
    import signal

    from tests.test_runtime_multiprocess import _kill_long_up, _processes_with, _start_long_up

    gains = {"paper-14-live": (live_gains, None, None)}
    proc, marker = _start_long_up(tmp_path, gains, "--netns", "--netns-prefix", prefix)
    try:
        assert any(n.startswith(prefix + "-") for n in netns.list_namespaces())
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 130, err
    finally:
        _kill_long_up(proc, marker)
    assert _processes_with(marker) == []
    assert not [n for n in netns.list_namespaces() if n.startswith(prefix + "-")]


@pytest.mark.multiprocess
@pytest.mark.netns
@pytest.mark.scale
def test_thirty_two_agents_on_hosts_of_their_own_recover_a_crash_through_the_router(
        tmp_path, prefix):
    """communities-32 with every process on a namespace host of its own (36 hosts, the
    router's included) at 80 ms steps: agent 5 killed at step 150 is convicted and
    replaced, nobody else is convicted, the run recovers and each agent that was never a
    standby heard only its sources (docs/transport.md, "32 agents on namespace hosts").
    Behind the ``scale`` marker: 36 processes on two cores take about a minute to start."""
    from tests.test_recovery_multiprocess import _heard_only_their_sources

    code, out, err = _socmon("up", "communities-32", "--steps", "400", "--step-ms", "80",
                             "--kill", "150:5", "--netns", "--netns-prefix", prefix,
                             "--router", "--start-timeout", "600",
                             "--out", str(tmp_path / "run"), "--json", timeout=1500)
    assert code == 0, err
    assert not [n for n in netns.list_namespaces() if n.startswith(prefix + "-")], \
        "socmon up left namespaces behind"
    s = json.loads(out)
    assert [(f["agent"], f["cause"]) for f in s["failures"]] == [(5, "crash")], s["failures"]
    assert s["recovered"] is True and s["diverged_at"] is None
    assert 5 not in s["rosters"][-1]["ids"]
    procs = json.loads((tmp_path / "run" / "run.json").read_text())["processes"]
    assert procs["router"]["netns"] == f"{prefix}-rtr"
    assert len({p["netns"] for p in procs.values() if "netns" in p}) >= 34
    _heard_only_their_sources(s, tmp_path / "run", "communities-32")
