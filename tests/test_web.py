"""The live page's state (agent.run.web) from a recorder fed by hand, and its server on
loopback: no browser, no zenoh (the browser test is tests/test_web_multiprocess.py)."""

import http.client
import json
import re
import socket
import threading
import time

import numpy as np
import pytest

from agent.protocol import topics, wire
from agent.run.inputs import InputError
from agent.run.recorder import Recorder
from agent.run.web import (
    MAX_STREAMS,
    Board,
    LiveState,
    WebAddressError,
    WebServer,
    open_page,
    parse_web_address,
)
from design.scenario import load_scenario

RUN = "webtest"


# -- --web ----------------------------------------------------------------------------------

@pytest.mark.parametrize("text, expected", [
    ("8765", ("127.0.0.1", 8765)), ("0", ("127.0.0.1", 0)),
    ("127.0.0.2:80", ("127.0.0.2", 80)), ("localhost:9000", ("127.0.0.1", 9000)),
    ("[::1]:8765", ("::1", 8765)), (" 8765 ", ("127.0.0.1", 8765)),
])
def test_web_address_accepted(text, expected):
    assert parse_web_address(text) == expected


@pytest.mark.parametrize("text, words", [
    ("", "empty"), ("http", "port"), ("65536", "0..65535"), ("-1", "port"),
    ("127.0.0.1:", "port"), ("::1:80", "brackets"), ("[::1]80", "[IPV6]:PORT"),
    ("example.com:80", "not an IP address"), ("0.0.0.0:80", "--web-remote"),
    ("192.168.1.5:80", "not a loopback"), ("[::]:80", "not a loopback"), ("8_0", "port"),
])
def test_web_address_refused_with_the_flag_named(text, words):
    with pytest.raises(WebAddressError) as exc:
        parse_web_address(text)
    assert str(exc.value).startswith("--web: ") and words in str(exc.value)


def test_non_loopback_only_with_the_explicit_flag():
    assert parse_web_address("0.0.0.0:8080", allow_remote=True) == ("0.0.0.0", 8080)
    with pytest.raises(InputError, match="--web-remote: only with --web"):
        open_page(None, remote=True)
    assert open_page(None) is None


def test_a_port_in_use_is_bad_input_naming_web():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(InputError) as exc:
            open_page(str(port))
    assert exc.value.status == 2 and f"--web: cannot listen on 127.0.0.1:{port}" in str(exc.value)


def test_commands_refuse_a_bad_web_value_with_exit_2(capsys):
    from agent.cli.main import main

    assert main(["watch", "paper-14-live", "--run", "x", "--connect", "tcp/127.0.0.1:9",
                 "--web", "0.0.0.0:8080"]) == 2
    assert "--web: 0.0.0.0 is not a loopback address" in capsys.readouterr().err
    assert main(["up", "paper-14-live", "--web", "nope"]) == 2
    assert "--web: the port must be" in capsys.readouterr().err


# -- the state --------------------------------------------------------------------------------

class Clock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self):
        return self.t


def _status(agent, step, active=True, epoch=0, delays=None):
    return wire.encode_status({
        "agent": agent, "step": step, "active": active, "epoch": epoch, "measure": [],
        "neighbours": {}, "delays": delays or {}, "drops": 0, "late": 0, "malformed": 0,
        "malformed_reasons": {}, "impaired": 0, "sensor": {}, "heard": [], "ctl": {},
        "links": {}, "overflows": 0})


def _event(r, record):
    r.feed(topics.monitor_events_key(RUN), wire.encode_monitor_event(record))


@pytest.fixture
def run():
    """paper-14-live recorded by hand: steps 0..59, agents 1..3 off by 0.1 per state; then
    agent 1 convicted (crash at 40) and agent 4 measuring node 8 from step 50 (epoch 1)."""
    s = load_scenario("paper-14-live")
    G = [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure]
    clock = Clock()
    r = Recorder(RUN, s.n, s.N, s.N + s.standby)
    board = Board()
    live = LiveState(s, np.zeros((3, 3), int), G, board=board, run_id=RUN, step_ms=20,
                     exact_worker=False, clock=clock)
    live._exact[0] = (0.25, "gains file")

    def steps(a, b, agents):
        for k in range(a, b):
            x = np.full(s.n, float(k))
            r.feed(topics.truth_key(RUN), wire.encode_truth(k, x))
            for i in agents:
                r.feed(topics.est_key(RUN, i), wire.encode_est(i, k, x + 0.1, epoch=0, t=0.0))
        r.truth_at = clock()
        for i in agents:
            r.feed(topics.status_key(RUN, i), _status(i, b - 1, epoch=0 if b <= 50 else 1,
                                                      delays={1: 0, 2: 0, 3: 0}))

    return s, r, live, board, clock, steps


def _state(board):
    return json.loads(board.latest()[1])


def test_state_before_and_after_a_kill_and_its_replacement(run):
    s, r, live, board, clock, steps = run
    steps(0, 40, (1, 2, 3))
    r.feed(topics.status_key(RUN, 4), _status(4, 39, active=False))
    live.tick(r, alive={1, 2, 3, 4}, force=True)
    st = _state(board)
    assert st["kind"] == "page" and st["run"] == RUN and st["step"] == 39
    assert [(a["id"], a["state"], a["measures"]) for a in st["agents"]] == [
        (1, "active", ["7"]), (2, "active", ["9"]), (3, "active", ["12"]), (4, "standby", [])]
    # who listens to whom, with the link's delay (the run's table: 0 here)
    assert st["agents"][0]["listens"] == [{"from": 2, "weight": 0.5, "delay": 0,
                                           "learned": 0.0}]
    assert [c["nodes"] for c in st["graph"]["sccs"] if c["parent"]] == [
        ["6", "7", "8"], ["9", "10", "11"], ["12", "13", "14"]]
    assert st["mse"]["last100"] == pytest.approx(0.01) and st["mse"]["exact"] == 0.25
    assert st["series"]["steps"] == list(range(40)) and st["series"]["block"] == 1
    assert st["events"] == [] and live.news() == []

    # agent 1 dies: its token goes (suspected until the verdict)
    clock.t += 0.5
    steps(40, 45, (2, 3))
    live.tick(r, alive={2, 3, 4}, force=True)
    a1 = _state(board)["agents"][0]
    assert (a1["state"], a1["why"]) == ("suspected", "liveliness token gone, no verdict yet")

    # the verdict, the reassignment (monitor events), the roster and agent 4's role
    _event(r, {"kind": "verdict", "t": 1.0, "agent": 1, "cause": "crash", "step": 44,
               "evidence": "liveliness token deleted"})
    _event(r, {"kind": "reassign", "t": 1.0, "epoch": 1, "activate_at": 50, "failed": [1],
               "ids": [4, 2, 3], "replacements": [{"failed": 1, "by": 4, "from": "7",
                                                   "to": "8"}],
               "added_links": [], "gains": "refined", "gains_mse": 0.3})
    r.feed(topics.ctl_key(RUN, 0), wire.encode_roster(1, 50, [4, 2, 3]))
    r.feed(topics.ctl_key(RUN, 4), wire.encode_ctl(4, 1, 50, ["8"], {2: 0.5}, 0.5,
                                                   np.zeros((s.n, 1)), take_over=1))
    r.feed(topics.ctl_key(RUN, 3), wire.encode_ctl(3, 1, 50, ["12"], {4: 0.5}, 0.5,
                                                   np.zeros((s.n, 1))))
    seen = time.time()
    live.tick(r, alive={2, 3, 4}, force=True)
    st = _state(board)
    assert [e["kind"] for e in st["events"]] == ["verdict", "reassign"]
    assert st["events"][0]["text"] == ("agent 1 convicted: crash at step 44 (liveliness "
                                       "token deleted)")
    assert st["events"][1]["text"].startswith("epoch 1 from step 50: agent 4 measures "
                                              "node 8 for agent 1 (was node 7)")
    assert all(abs(e["seen"] - seen) < 1.0 for e in st["events"])
    assert st["agents"][0]["state"] == "convicted"
    assert st["epoch"] == 0 and st["pending"] == {"epoch": 1, "activate_at": 50,
                                                  "ids": [4, 2, 3]}
    assert live.news() == [e["text"] for e in st["events"]] and live.news() == []

    # from step 50 the new configuration is in force, with the monitor's exact MSE
    clock.t += 0.5
    steps(45, 60, (2, 3, 4))
    live.tick(r, alive={2, 3, 4}, force=True)
    st = _state(board)
    assert st["epoch"] == 1 and st["roster"] == [4, 2, 3] and st["pending"] is None
    assert [(a["id"], a["state"], a["measures"]) for a in st["agents"]] == [
        (1, "convicted", []), (2, "active", ["9"]), (3, "active", ["12"]),
        (4, "active", ["8"])]
    assert st["agents"][2]["listens"][0]["from"] == 4        # 3 now listens to 4
    assert (st["mse"]["exact"], st["mse"]["exact_source"]) == (0.3, "monitor")
    assert [(g["from"], g["epoch"], g["exact"]) for g in st["segments"]] == [
        (0, 0, 0.25), (50, 1, 0.3)]
    assert live.progress_words() == "mse 0.01 over the last 60 steps (exact 0.3)"

    # agent 1 comes back (a status 0.5 s after its verdict): fenced, not convicted
    clock.t += 1.0
    r.feed(topics.status_key(RUN, 1), _status(1, 44, active=False))
    live.tick(r, alive={1, 2, 3, 4}, force=True)
    assert _state(board)["agents"][0]["state"] == "fenced"


def test_a_stuck_agent_is_suspected_only_while_the_world_moves(run):
    s, r, live, board, clock, steps = run
    steps(0, 20, (1, 2, 3))
    live.tick(r, force=True)
    clock.t += 2.0
    steps(20, 30, (2, 3))        # agent 1's statuses stop, the world goes on
    r.feed(topics.status_key(RUN, 2), _status(2, 29))
    live.tick(r, force=True)
    a1 = _state(board)["agents"][0]
    assert a1["state"] == "suspected" and a1["why"] == "no status for 2.0 s"
    r.truth_at = clock() - 5.0   # the world is silent: nobody is suspected for it
    live.tick(r, force=True)
    assert _state(board)["agents"][0]["state"] == "active"
    live.finish(r, "the world ended")
    assert _state(board)["ended"] == "the world ended"


def test_state_is_strict_json_and_bounded(run):
    """No NaN or inf in the JSON (a browser's JSON.parse refuses them); the MSE of a long
    run is kept as block means of at most SERIES_BLOCKS points, the events as the newest
    PAGE_EVENTS."""
    from agent.run import web

    s, r, live, board, clock, steps = run
    web_blocks = web.SERIES_BLOCKS
    web.SERIES_BLOCKS = 50
    try:
        for a in range(0, 400, 40):
            steps(a, a + 40, (1, 2, 3))
            live.tick(r, force=True)
    finally:
        web.SERIES_BLOCKS = web_blocks
    st = _state(board)
    assert st["series"]["block"] > 1 and len(st["series"]["steps"]) <= 50 + web.SETTLE_STEPS
    assert st["series"]["mse"][0] == pytest.approx(0.01)
    for i in range(300):
        _event(r, {"kind": "residual_alert", "agent": 2, "fault": "sensor bias",
                   "score": float("nan"), "step": i})
    live.tick(r, force=True)
    st = _state(board)
    assert len(st["events"]) == web.PAGE_EVENTS and st["events"][-1]["step"] == 299
    assert "score ?" not in st["events"][-1]["text"]     # nan said as nan, not dropped
    json.loads(board.latest()[1], parse_constant=lambda c: pytest.fail(f"{c} in the JSON"))


def test_hostile_event_text_is_data_not_markup(run):
    """A monitor event's words reach the page as JSON strings; the page escapes them
    (esc() on every text put in innerHTML)."""
    s, r, live, board, clock, steps = run
    _event(r, {"kind": "verdict", "agent": 2, "cause": "<img src=x onerror=alert(1)>",
               "step": 1, "evidence": "</script>"})
    live.tick(r, force=True)
    text = _state(board)["events"][0]["text"]
    assert "<img" in text                      # carried as data ...
    page = (web_page_text())
    assert "${esc(e.text)}" in page            # ... and escaped where it is drawn


def test_a_page_bug_stops_the_page_not_the_run(run):
    s, r, live, board, clock, steps = run
    said = []
    live.on_error = said.append
    live.snapshot = lambda *a, **k: 1 / 0
    assert live.tick(r, force=True) is False and live.tick(r, force=True) is False
    assert said == ["the live page stopped: ZeroDivisionError: division by zero"]


def test_the_exact_mse_of_the_first_configuration_is_computed_off_thread():
    """Without the gains file's value, in a process of its own (not the recorder's: a
    Lyapunov solve holds the GIL for seconds), by the summary's own function."""
    from agent.run.summary import predicted_mse

    s = load_scenario("paper-14-live")
    G = [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure]
    D = np.zeros((3, 3), int)
    r = Recorder(RUN, s.n, s.N, s.N + s.standby)
    live = LiveState(s, D, G, board=Board(), exact_worker=True)
    try:
        t0 = time.monotonic()
        live.tick(r, force=True)
        assert time.monotonic() - t0 < 0.5            # the tick does not wait for it
        assert live.exact(0) == (None, "computing")
        deadline = time.monotonic() + 60
        while live.exact(0)[0] is None and time.monotonic() < deadline:
            time.sleep(0.05)
            live.tick(r, force=True)
        assert live.exact(0) == (pytest.approx(predicted_mse(s, G, D)[1], rel=1e-12),
                                 "computed")
    finally:
        live.close()


# -- the server ---------------------------------------------------------------------------------

def web_page_text():
    from agent.run.web import PAGE_FILE

    return PAGE_FILE.read_text()


@pytest.fixture
def server():
    board = Board()
    srv = WebServer(board, "127.0.0.1", 0).start()
    try:
        yield srv
    finally:
        srv.close()


def _get(srv, path, host=None):
    c = http.client.HTTPConnection("127.0.0.1", srv.port, timeout=5)
    c.request("GET", path, headers={"Host": host} if host else {})
    resp = c.getresponse()
    body = resp.read()
    c.close()
    return resp.status, resp.getheader("Content-Type"), body


def test_page_is_self_contained():
    """Works offline: no script, style, font or image from another origin."""
    page = web_page_text()
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", page)
    assert not re.search(r"@import|url\(\s*['\"]?(https?:)?//", page)
    assert "https://" not in page and "http://" not in page


def test_server_serves_page_state_and_refuses_the_rest(server):
    server.board.publish({"kind": "page", "step": 7})
    status, ctype, body = _get(server, "/")
    assert status == 200 and ctype.startswith("text/html") and b"<svg id=\"net\"" in body
    status, ctype, body = _get(server, "/state.json?x=1")
    assert (status, ctype, json.loads(body)) == (200, "application/json",
                                                 {"kind": "page", "step": 7})
    assert _get(server, "/nothing")[0] == 404
    # a page of a loopback server is only served under a loopback name (DNS rebinding)
    status, _, body = _get(server, "/state.json", host="evil.example:80")
    assert status == 421 and b"loopback" in body
    assert _get(server, "/", host=f"localhost:{server.port}")[0] == 200
    c = http.client.HTTPConnection("127.0.0.1", server.port, timeout=5)
    c.request("POST", "/state.json", body=b"x")
    assert c.getresponse().status == 501
    c.close()


def test_malformed_requests_never_stop_the_server(server):
    for junk in (b"\x00\xff\x10garbage\r\n\r\n", b"GET /" + b"a" * 70000 + b" HTTP/1.1\r\n\r\n",
                 b"GET / HTTP/9.9\r\n\r\n", b"GET / HTTP/1.1\r\nHost: " + b"h" * 70000 + b"\r\n\r\n",
                 b"GET"):
        with socket.create_connection(("127.0.0.1", server.port), timeout=5) as s:
            s.sendall(junk)
            s.shutdown(socket.SHUT_WR)
            try:
                answer = s.recv(200)
            except (ConnectionResetError, TimeoutError):
                answer = b""
        # (an HTTP/0.9-looking line gets the error page without a status line)
        assert answer == b"" or re.search(rb"^HTTP/1\.[01] (400|414|431|505)|Error code: (400|505)",
                                          answer), answer
    assert _get(server, "/")[0] == 200


def _stream(server):
    s = socket.create_connection(("127.0.0.1", server.port), timeout=5)
    s.sendall(b"GET /events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    return s


def _read_until(s, marker, limit=1 << 20):
    data = b""
    while marker not in data and len(data) < limit:
        chunk = s.recv(65536)
        if not chunk:
            break
        data += chunk
    return data


def test_stream_sends_the_newest_snapshot_and_ends_with_the_server():
    board = Board()
    srv = WebServer(board, "127.0.0.1", 0).start()
    try:
        board.publish({"kind": "page", "seq": 1})
        s = _stream(srv)
        assert b'data: {"kind": "page", "seq": 1}' in _read_until(s, b'"seq": 1}')
        board.publish({"kind": "page", "seq": 2})
        assert b'"seq": 2}' in _read_until(s, b'"seq": 2}')
    finally:
        t0 = time.monotonic()
        srv.close()
    assert time.monotonic() - t0 < 2.0            # an open stream does not hold it
    _read_until(s, b"\x00never")                  # returns once the server closed it
    assert s.recv(10) == b""
    s.close()


def test_slow_or_vanished_browsers_cost_one_snapshot(server):
    """Streams that never read: publishing never blocks and keeps no backlog (the
    board has one payload); beyond MAX_STREAMS a stream is refused, /state.json still
    served; a closed stream frees its place."""
    board = server.board
    streams = [_stream(server) for _ in range(MAX_STREAMS)]
    time.sleep(0.2)
    extra = _stream(server)
    assert b"503" in _read_until(extra, b"\r\n")
    extra.close()
    big = {"kind": "page", "pad": "x" * 200_000}
    t0 = time.monotonic()
    for i in range(200):
        board.publish({**big, "seq": i})
    assert time.monotonic() - t0 < 5.0
    assert board.latest()[0] >= 200 and json.loads(board.latest()[1])["seq"] == 199
    assert _get(server, "/state.json")[0] == 200
    streams.pop().close()
    deadline = time.monotonic() + 15
    while True:                                   # its thread notices at its next write
        board.publish({"kind": "page", "seq": -1})
        s = _stream(server)
        head = _read_until(s, b"\r\n")
        s.close()
        if b"200" in head or time.monotonic() > deadline:
            break
        time.sleep(0.2)
    assert b"200" in head
    for s in streams:
        s.close()


def test_board_waiters_wake_on_publish_and_close():
    board = Board()
    got = []
    t = threading.Thread(target=lambda: got.append(board.wait_newer(0, timeout=10)))
    t.start()
    board.publish({"a": 1})
    t.join(5)
    assert got == [(1, b'{"a": 1}')]
    t = threading.Thread(target=lambda: got.append(board.wait_newer(1, timeout=10)))
    t.start()
    board.close()
    t.join(5)
    assert not t.is_alive() and got[-1][0] == 1


def test_up_without_a_page_gets_its_progress_words_and_lines(run):
    """``up`` without ``--web``: no board, no worker, no snapshot; the verdict and the
    reassignment as lines once each, the MSE of the last 100 steps beside the exact MSE
    of the configuration in force (pending while the monitor has not said it)."""
    s, r, _, _, clock, steps = run
    live = LiveState(s, np.zeros((3, 3), int), None, run_id=RUN, clock=clock)
    assert live.board is None and live._worker is None
    steps(0, 30, (1, 2, 3))
    assert live.tick(r) is False                    # events read, nothing published
    live.refresh(r)
    assert live.progress_words() == "mse 0.01 over the last 30 steps (exact pending)"
    _event(r, {"kind": "verdict", "agent": 1, "cause": "hang", "step": 29, "evidence": "e"})
    _event(r, {"kind": "reassign", "epoch": 1, "activate_at": 35, "failed": [1],
               "replacements": [{"failed": 1, "by": 4, "from": "7", "to": "8"}],
               "added_links": [[2, 4]], "gains": "fast", "gains_mse": None})
    _event(r, {"kind": "confirmed", "epoch": 1})
    live.tick(r)
    assert live.news() == [
        "agent 1 convicted: hang at step 29 (e)",
        "epoch 1 from step 35: agent 4 measures node 8 for agent 1 (was node 7); links "
        "added 2->4; fast gains, exact MSE pending"]
    r.feed(topics.ctl_key(RUN, 0), wire.encode_roster(1, 35, [4, 2, 3]))
    steps(30, 40, (2, 3, 4))
    _event(r, {"kind": "gains", "epoch": 1, "gains": "fast", "gains_mse": 0.31})
    live.refresh(r)
    assert live.progress_words() == "mse 0.01 over the last 40 steps (exact 0.31)"
    assert live.news() == []                        # a gains note is not a line


def test_chart_marks_name_the_fault_and_the_verdict(run):
    s, r, live, board, clock, steps = run
    r.recording.events.append({"process": "agent-2", "signal": "SIGSTOP", "step": 5, "t": 1.0})
    r.recording.events.append({"process": "agent-2", "exit_status": -9, "step": 6, "t": 1.0})
    _event(r, {"kind": "verdict", "agent": 2, "cause": "hang", "step": 9, "evidence": "e"})
    live.tick(r, force=True)
    assert [(e["class"], e["mark"]) for e in _state(board)["events"]] == [
        ("fault", "agent 2: SIGSTOP"), ("info", None), ("verdict", "verdict: agent 2 hang")]
