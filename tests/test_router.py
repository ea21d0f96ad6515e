"""The router: client mode, broker_free_net.router, ``socmon router`` and ``socmon up --router``.

Loopback only, ports from ``listen_port()``, waits on conditions with deadlines; children
in their own process groups and always stopped.
"""

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest

from agent.cli.main import main
from agent.run.launcher import ROOT, Children
from agent.run.local import RunFailed, _through_router, _wait_listening
from agent.protocol import topics
from broker_free_net.config import (
    CLIENT_CONNECT_TIMEOUT_MS,
    InvalidNetConfig,
    NetConfig,
    build_zenoh_config,
)
from broker_free_net.ports import listen_port
from broker_free_net.router import Router, router_config, serve_router
from agent.protocol.topics import make_run_keys, run_identities
from tests.test_runtime_multiprocess import _socmon

DEADLINE = 60.0


def _get(conf, key):
    return json.loads(conf.get_json(key))


def test_client_mode_listens_nowhere_and_waits_for_its_router():
    net = NetConfig(mode="client", connect=("tcp/127.0.0.1:7447",))
    assert net.listen == ()
    conf = build_zenoh_config(net)
    assert _get(conf, "mode") == "client"
    assert _get(conf, "connect/timeout_ms") == CLIENT_CONNECT_TIMEOUT_MS
    several = build_zenoh_config(NetConfig(mode="client", connect=("tcp/a:1", "tcp/b:2")))
    assert _get(several, "connect/timeout_ms") != CLIENT_CONNECT_TIMEOUT_MS     # zenoh's
    peer = build_zenoh_config(NetConfig())
    assert _get(peer, "connect/timeout_ms") != CLIENT_CONNECT_TIMEOUT_MS   # zenoh's own
    assert NetConfig().listen == ("tcp/127.0.0.1:0",)


def test_client_mode_and_router_refuse_keys(tmp_path):
    make_run_keys(tmp_path / "k", "r", run_identities(1))
    with pytest.raises(InvalidNetConfig, match="^mode: client mode cannot be used with keys"):
        NetConfig(mode="client", keys=tmp_path / "k", identity="agent-1")
    with pytest.raises(InvalidNetConfig, match="^keys: a router cannot run with keys"):
        router_config(NetConfig(keys=tmp_path / "k", identity="world"))
    with pytest.raises(InvalidNetConfig, match="^mode: a router is not a client"):
        router_config(NetConfig(mode="client"))
    assert _get(router_config(NetConfig()), "mode") == "router"


def test_through_router_drops_listen_and_connects_to_the_router_only():
    argv = ["agent", "s", "--id", "2", "--run", "r", "--connect", "tcp/a:1", "--listen",
            "tcp/b:2", "--connect", "tcp/c:3", "--seed", "0"]
    assert _through_router(argv, "tcp/r:9") == [
        "agent", "s", "--id", "2", "--run", "r", "--seed", "0",
        "--mode", "client", "--connect", "tcp/r:9"]


@pytest.mark.parametrize("argv, message", [
    (["router", "--keys", "x"], "--keys: a router cannot run with keys"),
    (["router", "--mode", "client"], "--mode: a router is not a client"),
    (["router", "--listen", "nowhere"], "--listen: invalid endpoint 'nowhere'"),
    (["up", "paper-14", "--router", "--secure"], "--router: not with --secure"),
])
def test_bad_router_flags_exit_2_with_one_line(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"socmon: {message}") and "\n" not in err


def test_two_clients_talk_and_see_liveliness_through_an_in_process_router():
    ep = f"tcp/127.0.0.1:{listen_port()}"
    stop = threading.Event()
    ready = threading.Event()
    seen = {}

    def on_ready(router):
        seen["endpoints"] = router.endpoints()
        ready.set()

    thread = threading.Thread(target=serve_router, args=(NetConfig(listen=(ep,)), on_ready,
                                                         stop))
    thread.start()
    try:
        assert ready.wait(DEADLINE) and seen["endpoints"] == [ep]
        client = dict(run="rt", mode="client", connect=(ep,))
        with topics.open_peer(NetConfig(**client), "agent", 1) as a, \
                topics.open_peer(NetConfig(**client), "agent", 2) as b:
            watch = b.watch_liveliness()
            assert watch.wait_until(lambda alive: ("agent", "1") in alive, DEADLINE)
            inbox = b.subscribe(topics.est_key("rt", 1))
            deadline = time.monotonic() + DEADLINE
            item = None
            while item is None and time.monotonic() < deadline:
                a.put(topics.est_key("rt", 1), b"hello")   # until b's subscription is known
                item = inbox.get(timeout=0.2)
            assert item is not None and item.payload == b"hello"
            a.close()
            assert watch.wait_until(lambda alive: ("agent", "1") not in alive, DEADLINE)
    finally:
        stop.set()
        thread.join(DEADLINE)
    assert not thread.is_alive()


def test_two_routers_carry_samples_between_their_clients_and_a_client_skips_a_dead_one():
    a, b, dead = (f"tcp/127.0.0.1:{listen_port()}" for _ in range(3))
    with Router(NetConfig(listen=(a,))) as ra, \
            Router(NetConfig(listen=(b,), connect=(a,))) as rb:
        with topics.open_peer(NetConfig(run="rt", mode="client", connect=(a,)), "agent", 1) as p1, \
                topics.open_peer(NetConfig(run="rt", mode="client", connect=(dead, b)), "agent", 2) as p2:
            assert p2.watch_liveliness().wait_until(lambda s: ("agent", "1") in s, DEADLINE)
            inbox = p2.subscribe(topics.est_key("rt", 1))
            deadline = time.monotonic() + DEADLINE
            item = None
            while item is None and time.monotonic() < deadline:
                p1.put(topics.est_key("rt", 1), b"across")
                item = inbox.get(timeout=0.2)
            assert item is not None and item.payload == b"across"
            assert ra.sessions() == 2 and rb.sessions() == 2     # a client and the other router


def test_router_reports_the_port_the_os_chose():
    with Router(NetConfig(listen=("tcp/127.0.0.1:0",))) as router:
        (endpoint,) = router.endpoints()
        assert endpoint.startswith("tcp/127.0.0.1:") and not endpoint.endswith(":0")
        assert router.sessions() == 0


@pytest.mark.multiprocess
def test_socmon_router_prints_its_endpoint_and_stops_on_sigterm():
    port = listen_port()
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "agent.cli", "router", "--listen",
                             f"tcp/127.0.0.1:{port}", "--json"], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        line = proc.stdout.readline()         # the router prints once it listens
        assert json.loads(line)["endpoints"] == [f"tcp/127.0.0.1:{port}"], proc.stderr.read()
        os.killpg(proc.pid, signal.SIGTERM)
        assert proc.wait(DEADLINE) == 0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        proc.stdout.close()
        proc.stderr.close()
    with socket.socket() as sock:             # the port is free again
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(("127.0.0.1", port))


@pytest.mark.multiprocess
def test_a_router_that_cannot_start_fails_the_run_with_its_log(tmp_path):
    children = Children(tmp_path / "logs")
    try:
        children.start("router", ["router", "--listen", "tcp/127.0.0.1:1", "--keys", "k"])
        with pytest.raises(RunFailed, match="router exited with status 2 before it listened;"
                                            "(.|\n)*--keys: a router cannot run with keys"):
            _wait_listening(children, "router", DEADLINE)
    finally:
        children.stop_all()


@pytest.mark.multiprocess
@pytest.mark.slow
def test_up_through_a_router_equals_the_simulator(tmp_path):
    import numpy as np

    from design.gains import save_gains
    from design.scenario import load_scenario

    s = load_scenario("paper-14")
    rng = np.random.default_rng(0)
    gains = tmp_path / "g.npz"
    save_gains(gains, [0.3 * rng.normal(size=(s.n, len(m))) for m in s.measure],
               {"method": "fixed random"})
    from broker_free_net.ports import listen_port

    entry = f"tcp/127.0.0.1:{listen_port()}"       # --listen: the router's, the run's entry
    code, stdout, stderr = _socmon("up", "paper-14", "--router", "--steps", "60", "--gains",
                                   str(gains), "--seed", "3", "--delays", "uniform:2",
                                   "--listen", entry,
                                   "--out", str(tmp_path / "r"), "--check-simulator",
                                   "--json", "--step-ms", "20")
    assert code == 0, stderr
    summary = json.loads(stdout)
    assert summary["steps"] == 60 and summary["drops"] == 0 and summary["malformed"] == 0
    assert summary["max_rel_diff_vs_simulator"] <= 1e-9
    assert summary["exit_status"]["router"] == 0 and summary["orphans"] == []
    assert set(summary["exit_status"].values()) == {0}
    run = json.loads((tmp_path / "r" / "run.json").read_text())
    assert run["connect"] == run["processes"]["router"]["endpoint"] == entry
    # the start line names the endpoint a joining process connects to: the router's
    assert f"run {run['run']} at {run['connect']} (" in stderr
    assert all("endpoint" not in p for name, p in run["processes"].items() if name != "router")
    for name, p in run["processes"].items():      # every other process is its client
        if name != "router":
            assert p["argv"][-4:] == ["--mode", "client", "--connect", run["connect"]]
            assert "--listen" not in p["argv"]
