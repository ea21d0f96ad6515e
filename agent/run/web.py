"""A live web page of a run: ``socmon watch --web [HOST:]PORT`` and ``socmon up --web ...``.

Three parts, each with one job:

* :class:`LiveState`, fed in the recorder's own thread (``watch``'s loop, ``up``'s loop):
  at most every :data:`TICK_S` it reads the :class:`agent.run.recorder.Recorder` (its
  :meth:`~agent.run.recorder.Recorder.view`, the rosters, assignments and the monitor's
  events it heard) and builds one JSON snapshot, :meth:`LiveState.snapshot`: the social
  graph's SCCs (parents marked), the configuration in force (who measures what, who
  listens to whom, each link's delay), each agent's state (``active``, ``standby``,
  ``suspected``, ``convicted``, ``fenced``, with why), the events (faults, verdicts,
  reassignments, ...) and the MSE beside the exact steady MSE of the configuration in
  force. It also gives ``up`` its progress words (:meth:`LiveState.progress_words`,
  :meth:`LiveState.news`). Nothing here blocks: the exact MSE of a configuration is the
  monitor's (its ``reassign`` and ``gains`` events), or the gains file's, or computed
  in a process of its own (:class:`_ExactWorker`), never in the recorder's thread.
* :class:`Board`: the newest snapshot as bytes and a version number. The page's streams
  only ever read the newest one (no queue per browser): a slow or vanished browser holds
  no memory but the one snapshot, and the recorder never waits for it.
* :class:`WebServer`: :class:`http.server.ThreadingHTTPServer` in a daemon thread:
  ``/`` the page (``web_page.html``: inline JS, CSS and SVG, nothing fetched from
  elsewhere), ``/state.json`` the newest snapshot, ``/events`` a Server-Sent Events
  stream of snapshots (the page falls back to polling ``/state.json``). At most
  :data:`MAX_STREAMS` streams at once, a socket timeout on every connection, the
  ``Host`` header checked on a loopback server (DNS rebinding), and a malformed request
  answered 4xx, never raised into the run.

``up`` reaches :class:`agent.run.local.LocalRun` through :func:`agent.run.local.live_view`
and :func:`live_state_factory` (a context variable: the page is the caller's, the run only
feeds it).

Examples
--------
>>> parse_web_address("8765")
('127.0.0.1', 8765)
>>> parse_web_address("[::1]:0")
('::1', 0)
>>> parse_web_address("0.0.0.0:8765")
Traceback (most recent call last):
...
agent.run.web.WebAddressError: --web: 0.0.0.0 is not a loopback address: the page shows the run to anyone who can reach it; add --web-remote to serve it there anyway
"""

from __future__ import annotations

import contextlib
import ipaddress
import json
import math
import threading
import textwrap
import time
from collections import deque
from pathlib import Path

__all__ = ["WebAddressError", "parse_web_address", "Board", "WebServer", "LiveState",
           "LivePage", "live_state_factory", "event_text", "TICK_S", "MAX_STREAMS"]

#: Seconds between two snapshots (the page is at most this late, plus the browser's draw).
TICK_S = 0.2
#: Seconds between two reads of the recorder's view when nobody passes one (``up``).
VIEW_S = 1.0
#: Server-Sent Events streams served at once; more are answered 503.
MAX_STREAMS = 8
#: A connection whose reads or writes block this long is dropped (a vanished browser).
SOCKET_TIMEOUT_S = 10.0
#: A stream sends a comment this often when nothing changed (proxies, dead peers).
HEARTBEAT_S = 5.0
#: At most this many points of MSE for the whole run (block means of 1, 2, 4, ... steps).
SERIES_BLOCKS = 1500
#: Events the page lists (the newest ones).
PAGE_EVENTS = 200
#: The MSE of a step is recomputed until this many steps are newer (late estimates).
SETTLE_STEPS = 30
#: Largest request line or header the server reads.
MAX_LINE = 8192

PAGE_FILE = Path(__file__).with_name("web_page.html")


class WebAddressError(ValueError):
    """A bad ``--web`` value; the message names the flag and what is wrong."""


def parse_web_address(text: str, allow_remote: bool = False) -> tuple:
    """``[HOST:]PORT`` (an IPv6 host in brackets) as ``(host, port)``; the host defaults to
    127.0.0.1, port 0 picks a free one. A host that is not a loopback address is refused
    unless ``allow_remote`` (``--web-remote``), since the page shows the run to whoever
    reaches it. Host names other than ``localhost`` are refused (they may resolve to
    anything): give an address."""
    text = str(text).strip()
    if not text:
        raise WebAddressError("--web: expected [HOST:]PORT (e.g. 8765 or 127.0.0.1:8765), "
                              "got an empty value")
    host, port = "127.0.0.1", text
    if text.startswith("["):
        close = text.find("]")
        if close < 0 or text[close + 1:close + 2] != ":":
            raise WebAddressError(f"--web: expected [IPV6]:PORT, got {text!r}")
        host, port = text[1:close], text[close + 2:]
    elif ":" in text:
        host, _, port = text.rpartition(":")
        if ":" in host:
            raise WebAddressError(f"--web: an IPv6 host goes in brackets ([::1]:8765), "
                                  f"got {text!r}")
    if not (port.isascii() and port.isdigit()) or not 0 <= int(port) <= 65535:
        raise WebAddressError(f"--web: the port must be a whole number in 0..65535 (0: any "
                              f"free port), got {port!r} in {text!r}")
    if host == "localhost":
        host = "127.0.0.1"
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        raise WebAddressError(f"--web: {host!r} is not an IP address (give 127.0.0.1, ::1, "
                              f"or with --web-remote the address of an interface)") from None
    if not address.is_loopback and not allow_remote:
        raise WebAddressError(f"--web: {host} is not a loopback address: the page shows the "
                              "run to anyone who can reach it; add --web-remote to serve it "
                              "there anyway")
    return str(address), int(port)


# ---------------------------------------------------------------------------------------
# The board: the newest snapshot, and who is waiting for the next one


class Board:
    """The newest snapshot (bytes) and its version; thread-safe, one writer.

    >>> b = Board()
    >>> b.publish({"step": 3}); b.latest()
    (1, b'{"step": 3}')
    >>> b.wait_newer(1, timeout=0.01)
    (1, b'{"step": 3}')
    """

    def __init__(self):
        self._cond = threading.Condition()
        self._version = 0
        self._payload = b'{"schema_version": 1, "kind": "waiting"}'
        self.closed = False

    def publish(self, state: dict) -> None:
        data = json.dumps(state, allow_nan=False, separators=(", ", ": ")).encode()
        with self._cond:
            self._version += 1
            self._payload = data
            self._cond.notify_all()

    def latest(self) -> tuple:
        with self._cond:
            return self._version, self._payload

    def wait_newer(self, version: int, timeout: float) -> tuple:
        """The newest ``(version, payload)`` once it is newer than ``version``, or after
        ``timeout`` seconds (then possibly the same), or at once when closed."""
        with self._cond:
            self._cond.wait_for(lambda: self._version != version or self.closed, timeout)
            return self._version, self._payload

    def close(self) -> None:
        with self._cond:
            self.closed = True
            self._cond.notify_all()


# ---------------------------------------------------------------------------------------
# The server


def _handler_class(board: Board, page: bytes, check_host, streams: threading.Semaphore):
    from http.server import BaseHTTPRequestHandler

    class Handler(BaseHTTPRequestHandler):
        server_version = "socmon-web"
        sys_version = ""
        protocol_version = "HTTP/1.1"
        timeout = SOCKET_TIMEOUT_S

        def log_message(self, *args):       # the run's terminal is not an access log
            pass

        def handle_one_request(self):
            try:
                super().handle_one_request()
            except (ConnectionError, TimeoutError, OSError):
                self.close_connection = True

        def _send(self, code: int, body: bytes, ctype: str, head: bool = False) -> None:
            self.send_response(code)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.send_header("X-Content-Type-Options", "nosniff")
            # nothing but this server: no CDN, no frame around it
            self.send_header("Content-Security-Policy",
                             "default-src 'self'; script-src 'unsafe-inline'; "
                             "style-src 'unsafe-inline'; img-src 'self' data:; "
                             "frame-ancestors 'none'")
            self.end_headers()
            if not head:
                self.wfile.write(body)

        def _error(self, code: int, text: str, head: bool = False) -> None:
            self._send(code, (text + "\n").encode(), "text/plain; charset=utf-8", head)

        def do_HEAD(self):
            self.do_GET(head=True)

        def do_GET(self, head: bool = False):
            if not check_host(self.headers.get("Host")):
                self._error(421, "this page is served on a loopback address only: open it as "
                                 "http://127.0.0.1:PORT/ (Host header refused)", head)
                return
            path = self.path.split("?", 1)[0]
            if path in ("/", "/index.html"):
                self._send(200, page, "text/html; charset=utf-8", head)
            elif path == "/state.json":
                self._send(200, board.latest()[1], "application/json", head)
            elif path == "/events" and not head:
                self._stream()
            else:
                self._error(404, f"not found: {path[:200]} (the page is /, its state "
                                 "/state.json and /events)", head)

        def _stream(self):
            if not streams.acquire(blocking=False):
                self._error(503, f"at most {MAX_STREAMS} live pages at once; the state is "
                                 "also at /state.json")
                return
            try:
                self.close_connection = True
                self.send_response(200)
                self.send_header("Content-Type", "text/event-stream")
                self.send_header("Cache-Control", "no-store")
                self.send_header("Connection", "close")
                self.end_headers()
                self.wfile.write(b"retry: 1000\n\n")
                version = -1
                while not board.closed:
                    new, payload = board.wait_newer(version, HEARTBEAT_S)
                    if new != version:
                        version = new
                        self.wfile.write(b"data: " + payload + b"\n\n")
                    else:
                        self.wfile.write(b": alive\n\n")
                    self.wfile.flush()
            except (ConnectionError, TimeoutError, OSError):
                pass                          # the browser went away
            finally:
                streams.release()

    return Handler


class WebServer:
    """The page's HTTP server on ``(host, port)`` in a daemon thread (:meth:`start`);
    :meth:`close` ends the streams and the server. A port in use is an OSError naming it."""

    def __init__(self, board: Board, host: str = "127.0.0.1", port: int = 0,
                 allow_remote: bool = False):
        import socket
        from http.server import ThreadingHTTPServer

        try:
            page = PAGE_FILE.read_bytes()
        except OSError as exc:
            raise OSError(f"the page {PAGE_FILE} cannot be read ({exc.strerror}): is the "
                          "package installed with its data files?") from None
        self.board = board
        loopback = ipaddress.ip_address(host).is_loopback
        names = {"localhost", "127.0.0.1", "[::1]", host, f"[{host}]"}

        def check_host(value):
            if value is None:
                return True                   # HTTP/1.0 without Host: not a browser
            if not loopback and allow_remote:
                return True
            name = value.strip().lower()
            name = name.rsplit(":", 1)[0] if not name.endswith("]") else name
            return name in names

        self._streams = threading.Semaphore(MAX_STREAMS)

        class Server(ThreadingHTTPServer):
            daemon_threads = True
            allow_reuse_address = True
            address_family = socket.AF_INET6 if ":" in host else socket.AF_INET
            request_queue_size = 16

            def handle_error(self, request, client_address):   # never a traceback
                pass

        try:
            self.httpd = Server((host, port), _handler_class(board, page, check_host,
                                                              self._streams))
        except OSError as exc:
            raise OSError(f"--web: cannot listen on {host}:{port}: {exc.strerror}") from None
        self.host, self.port = host, self.httpd.server_address[1]
        self._thread = threading.Thread(target=self.httpd.serve_forever,
                                        kwargs={"poll_interval": 0.2},
                                        name="socmon-web", daemon=True)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    def start(self) -> "WebServer":
        self._thread.start()
        return self

    def close(self) -> None:
        self.board.close()
        self.httpd.shutdown()
        self.httpd.server_close()
        self._thread.join(timeout=2.0)


# ---------------------------------------------------------------------------------------
# The words of an event (the page's list and up's progress lines)


def _f(x, digits: int = 4) -> str:
    return "?" if x is None else f"{x:.{digits}g}"


def event_text(e: dict) -> str | None:
    """One line for a monitor event (``events.jsonl``) or a recorder event (a fault of
    ``up``, an exit, a role dropped); None for what is not worth a line.

    >>> event_text({"kind": "verdict", "agent": 1, "cause": "crash", "step": 170,
    ...             "evidence": "liveliness token deleted"})
    'agent 1 convicted: crash at step 170 (liveliness token deleted)'
    >>> event_text({"kind": "reassign", "epoch": 1, "activate_at": 181, "failed": [1],
    ...             "replacements": [{"failed": 1, "by": 4, "from": "7", "to": "8"}],
    ...             "added_links": [], "gains": "refined", "gains_mse": 0.2712})
    'epoch 1 from step 181: agent 4 measures node 8 for agent 1 (was node 7); refined gains, exact MSE 0.2712'
    >>> event_text({"process": "agent-1", "signal": "SIGKILL", "step": 150})
    'fault: agent 1 sent SIGKILL'
    """
    kind = e.get("kind")
    if kind == "verdict":
        who = "the network" if e.get("agent") == 0 else f"agent {e.get('agent')}"
        return (f"{who} convicted: {e.get('cause')} at step {e.get('step')}"
                + (f" ({textwrap.shorten(str(e.get('evidence')), 160, placeholder=' ...')})"
                   if e.get("evidence") else ""))
    if kind == "reassign":
        reps = [f"agent {r.get('by')} measures node {r.get('to')} for agent {r.get('failed')}"
                f" (was node {r.get('from')})" for r in e.get("replacements") or []]
        links = [f"{a}->{b}" for a, b in e.get("added_links") or []]
        what = "; ".join(reps) if reps else (e.get("reason") or "new gains, same roles")
        return (f"epoch {e.get('epoch')} from step {e.get('activate_at')}: {what}"
                + (f"; links added {', '.join(links)}" if links else "")
                + f"; {e.get('gains', '?')} gains, exact MSE "
                + (_f(e.get("gains_mse")) if e.get("gains_mse") is not None else "pending"))
    if kind == "reissue":
        return (f"epoch {e.get('epoch')}: roles re-issued from step {e.get('activate_at')} "
                f"({e.get('reason', '')})")
    if kind == "gains":
        return (f"epoch {e.get('epoch')}: {e.get('gains', '?')} gains in force, exact MSE "
                f"{_f(e.get('gains_mse'))}")
    if kind == "confirmed":
        return f"epoch {e.get('epoch')}: every agent runs its roles"
    if kind == "rejoin":
        return (f"agent {e.get('agent')} rejoined as a standby after "
                f"{_f(e.get('healthy_s'), 2)} s of probation")
    if kind == "residual_alert":
        return (f"alert (no conviction): agent {e.get('agent')} {e.get('fault')} "
                f"(score {_f(e.get('score'), 3)})")
    if kind == "evidence_refused":
        return (f"evidence refused ({e.get('reason')}) about agent {e.get('agent')}")
    if kind == "active":
        return f"monitor {e.get('monitor')} acts (epoch {e.get('epoch')})"
    if kind == "passive":
        return f"monitor {e.get('monitor')} stands by: monitor {e.get('to')} acts"
    if kind == "prepared":
        return (f"monitor foresees the failure of agents {e.get('foreseen')} "
                f"({_f(e.get('seconds'), 2)} s)")
    if kind == "liveliness":
        if e.get("process") == "world":
            return "the world's token went"
        return f"agent {e.get('agent')}: liveliness token gone (seen by the monitor)"
    if kind is not None:
        return f"monitor: {kind}"
    name = str(e.get("process", ""))
    who = f"agent {name.split('-', 1)[1]}" if name.startswith("agent-") else name or "?"
    if e.get("signal"):
        return f"fault: {who} sent {e['signal']}"
    if e.get("impair"):
        return f"fault: {who}: {e['impair']}"
    if e.get("link"):
        return f"fault: {who} host link {e['link']}"
    if e.get("exit_status") is not None:
        return f"{who} exited with status {e['exit_status']}"
    if e.get("role") == "dropped":
        return f"{who} dropped its role (fenced: not in the roster of epoch {e.get('epoch')})"
    if e.get("liveliness") is False:
        return f"{who}: liveliness token gone"
    if e.get("liveliness") is True:
        return f"{who}: liveliness token back"
    if e.get("started"):
        return f"{who} started"
    if "monitors_alive" in e:
        return ("NO MONITOR ALIVE: failures are neither detected nor recovered"
                if not e["monitors_alive"] else f"a monitor is alive again ({who})")
    if "links" in e:
        return f"{who}: links impaired {e['links']}" if e["links"] else \
            f"{who}: links restored"
    return None


#: Monitor events said as progress lines by ``up``.
NEWS_KINDS = ("verdict", "reassign", "reissue", "rejoin", "residual_alert")

#: The kind of a page event, for its colour and its mark on the MSE chart.
def _event_class(e: dict) -> str:
    kind = e.get("kind")
    if kind == "verdict":
        return "verdict"
    if kind in ("reassign", "reissue", "gains", "confirmed"):
        return "reassign"
    if kind in ("residual_alert", "evidence_refused"):
        return "alert"
    if kind is not None:
        return "monitor"
    if e.get("signal") or e.get("impair") or e.get("link"):
        return "fault"
    return "info"


# ---------------------------------------------------------------------------------------
# The exact MSE of a configuration, in a process of its own


def _exact_job(conn, scenario, G, delays, rosters, assigns, epoch):
    """In the worker process: the exact steady MSE of ``epoch``'s configuration, by the
    functions the summary uses (:func:`agent.run.summary.predicted_mse` for the first,
    :func:`agent.run.summary.specs_in_force` + :func:`design.roster.roster_from_specs` +
    :func:`design.closed_loop.exact_performance` after a reassignment)."""
    try:
        import os
        import signal

        signal.signal(signal.SIGINT, signal.SIG_IGN)     # Ctrl-C is the parent's to answer
        os.nice(10)
        from agent.run.summary import predicted_mse, specs_in_force
        from design.closed_loop import exact_performance
        from design.roster import link_delay_table, roster_from_specs

        if epoch == 0:
            value = predicted_mse(scenario, G, delays)[1]
        else:
            ids, specs = specs_in_force(rosters, assigns, scenario, G, epoch=epoch)
            new, Gs, D = roster_from_specs(scenario, link_delay_table(scenario, delays),
                                           ids, specs)
            value = exact_performance(new, Gs, D).mse_or_inf
        conn.send((epoch, float(value)))
    except Exception as exc:          # noqa: BLE001 - said on the page, the run goes on
        conn.send((epoch, f"{type(exc).__name__}: {exc}"))
    finally:
        conn.close()


class _ExactWorker:
    """One job at a time in a spawned process (a Lyapunov solve of the delayed loop takes
    seconds and holds the GIL: measured 1.8 s stalls of a thread beside it)."""

    def __init__(self):
        self._proc = self._conn = None
        self.epoch = None
        self.closed = False

    @property
    def busy(self) -> bool:
        return self._proc is not None

    def start(self, epoch, *args) -> None:
        import multiprocessing

        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(target=_exact_job, args=(child, *args, epoch),
                                 name="socmon-web-exact", daemon=True)
        self._proc.start()
        child.close()
        self.epoch = epoch

    def poll(self):
        """``(epoch, value or error text)`` when the job is done, else None."""
        if self._proc is None:
            return None
        try:
            if self._conn.poll():
                out = self._conn.recv()
            elif not self._proc.is_alive():
                out = (self.epoch, f"the exact MSE worker exited ({self._proc.exitcode})")
            else:
                return None
        except (EOFError, OSError):
            out = (self.epoch, "the exact MSE worker exited")
        self._reap()
        return out

    def _reap(self):
        if self._proc is not None:
            self._proc.join(timeout=0.5)
            if self._proc.is_alive():
                self._proc.kill()
                self._proc.join(timeout=1.0)
            self._conn.close()
        self._proc = self._conn = None

    def close(self):
        self.closed = True
        if self._proc is not None and self._proc.is_alive():
            self._proc.kill()
        self._reap()


# ---------------------------------------------------------------------------------------
# The state


def _num(x):
    """A finite float, else None (JSON has no inf or nan)."""
    try:
        x = float(x)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def social_graph(scenario) -> dict:
    """The static part of the page: the social graph's nodes, SCCs (parents marked) and
    influence edges (``[j, i]``: i listens to j, as ``A[i, j] != 0``; capped at 2,000).

    >>> from design.scenario import load_scenario
    >>> g = social_graph(load_scenario("paper-14"))
    >>> [(c["nodes"], c["parent"]) for c in g["sccs"]][:2]
    [(['1', '2', '3', '4', '5'], False), (['6', '7', '8'], True)]
    """
    import numpy as np

    from design.graph import influence_structure

    s = scenario
    st = influence_structure(s.A)
    parents = set(int(p) for p in st.parents)
    A = np.asarray(s.A)
    src, dst = np.nonzero((A != 0).T)          # A[i, j] != 0: j -> i
    edges = [[s.labels[int(j)], s.labels[int(i)]] for j, i in zip(src, dst) if i != j]
    return {"nodes": list(s.labels),
            "sccs": [{"index": c, "nodes": [s.labels[v] for v in comp],
                      "parent": c in parents} for c, comp in enumerate(st.components)],
            "edges": edges[:2000], "edges_total": len(edges)}


class LiveState:
    """What the page shows, built from a recorder in the recorder's thread.

    Parameters
    ----------
    scenario, delays, G : the run's scenario, link delays (by row) and gains (None: no
        exact prediction of the first configuration unless the gains file says it)
    board : Board or None
        Where snapshots go (None: only ``up``'s progress words are wanted).
    gains_path : the gains file (its ``meta`` may carry the exact MSE for these delays)
    step_ms, hang_timeout_s : the run's step period and hang timeout (suspicion)
    exact_worker : compute missing exact MSEs in a process of their own (the page only)
    """

    def __init__(self, scenario, delays, G=None, *, board: Board | None = None,
                 run_id: str = "", gains_path=None, step_ms=None, hang_timeout_s=None,
                 exact_worker: bool = True, clock=time.monotonic, wall=time.time,
                 on_error=lambda text: None):
        import numpy as np

        from agent.protocol.timing import DEFAULT as TIMING
        from design.roster import link_delay_table

        self.s, self.delays, self.G = scenario, np.asarray(delays), G
        self.board, self.run_id, self.step_ms = board, run_id, step_ms
        self.hang_timeout_s = hang_timeout_s or TIMING.hang_timeout_s
        self.clock, self.wall = clock, wall
        self.M = scenario.N + scenario.standby
        self.table = link_delay_table(scenario, delays)
        self.graph = social_graph(scenario) if board is not None else None
        self._exact = {}             # epoch -> (value or None, source)
        self._exact_from_file(gains_path)
        self._worker = _ExactWorker() if exact_worker and board is not None else None
        self._errors = {}            # epoch -> why no exact value
        self._announced = set()      # epochs the monitor's events named
        self.epoch_in_force = 0
        self._mon_seen = 0           # monitor events read
        self._rec_seen = 0           # recorder events read
        self._events = deque(maxlen=PAGE_EVENTS)
        self._news = deque(maxlen=1000)
        self._verdict_at = {}        # agent -> (when seen (clock), step, cause)
        self._rejoined_at = {}       # agent -> when seen (clock)
        self._dropped_at = {}        # agent -> when its role-dropped event was seen
        self._status_obj = {}        # agent -> the last status object seen
        self._status_at = {}         # agent -> when (clock) it changed
        self._token_seen = set()
        self._blocks = {}            # block index -> [sum of MSE, steps] (settled steps)
        self._block = 1              # steps a block
        self._settled = None         # the newest step in the blocks
        self._recent = {}            # step -> MSE of the newest steps not final
        self._final = set()          # steps in the blocks, newer than _settled
        self._config_key = None
        self._config = None
        self._next_tick = 0.0
        self._next_view = 0.0
        self._seq = 0
        self.view = None
        self.ended = None
        self.broken = None           # why the page stopped (a bug), or None
        self.on_error = on_error

    # -- the exact MSE by configuration ------------------------------------------------
    def _exact_from_file(self, gains_path) -> None:
        import numpy as np

        if gains_path is None:
            return
        try:
            from design.gains import load_gains

            meta = load_gains(gains_path).meta
        except Exception:        # noqa: BLE001 - the run checked it; nothing said here
            return
        designed = meta.get("delays")
        if designed is not None and "mse_steady_exact" in meta and \
                np.array_equal(np.asarray(designed), self.delays):
            self._exact[0] = (_num(meta["mse_steady_exact"]), "gains file")

    def _learn_exact(self, e: dict) -> None:
        """The monitor's exact MSE of the configuration it put in force."""
        epoch = e.get("epoch")
        if not isinstance(epoch, int):
            return
        self._announced.add(epoch)
        if e.get("kind") in ("reassign", "gains") and e.get("gains_mse") is not None:
            self._exact[epoch] = (_num(e["gains_mse"]), "monitor")
        elif e.get("kind") == "reissue":      # the same roles and gains, a later epoch
            older = [k for k in self._exact if k < epoch]
            if older:
                self._exact.setdefault(epoch, self._exact[max(older)])

    def exact(self, epoch: int):
        """``(value or None, source or why not)`` of the configuration of ``epoch``."""
        if epoch in self._exact:
            return self._exact[epoch]
        if epoch in self._errors:
            return None, self._errors[epoch]
        if self._worker is not None and self._worker.busy and self._worker.epoch == epoch:
            return None, "computing"
        return None, "pending"

    def _feed_worker(self, rec, epoch: int) -> None:
        """Start the exact MSE of ``epoch`` in the worker when nobody else gives it: the
        first configuration without the gains file's value, a later one whose monitor
        record this recorder did not hear (it attached after it)."""
        w = self._worker
        if w is None:
            return
        done = w.poll()
        if done is not None:
            ep, value = done
            if isinstance(value, str):
                self._errors[ep] = value
            else:
                self._exact.setdefault(ep, (_num(value), "computed"))
        if w.busy or epoch in self._exact or epoch in self._errors:
            return
        if self.G is None:
            self._errors[epoch] = "no gains given"
            return
        if epoch > 0 and (epoch in self._announced or
                          not any(e == epoch for (_, e) in rec.assigns)):
            return       # the monitor's gains note will say it; or no roles heard yet
        w.start(epoch, self.s, list(self.G), self.delays, list(rec.rosters),
                dict(rec.assigns))

    # -- the tick ------------------------------------------------------------------------
    def tick(self, recorder, alive=None, force: bool = False, view=None) -> bool:
        """Read ``recorder``'s events; every :data:`TICK_S`, at once after new events (at
        most every 50 ms), or when ``force``, also its view (``view``: one just taken) and,
        with a board, publish a snapshot.
        ``alive``: the agent ids whose liveliness token is up (None: not known). Returns
        True when it took a view. A failure of the page is said once (``on_error``) and
        ends the page, never the run."""
        if self.broken:
            return False
        try:
            news = self._read_events(recorder.recording)
            now = self.clock()
            # an event (a fault, a verdict, new roles) goes out at once, not at the next tick
            due = now >= self._next_tick or (news and now >= self._next_tick - TICK_S + 0.05)
            if not force and (self.board is None or not due):
                return False
            self._next_tick = now + TICK_S
            if view is not None:
                self.view = view
            elif self.view is None or now >= self._next_view or self.board is None:
                # the watcher's view (the agents' rows, the MSE of the last 100 steps): at
                # most every VIEW_S here (tens of ms on a loaded machine); the verdicts,
                # states and chart are read at every tick
                self.view = recorder.view()
                self._next_view = now + VIEW_S
            self._epoch_now(recorder)
            if self.board is not None:
                self.board.publish(self.snapshot(recorder, alive))
            return True
        except Exception as exc:         # noqa: BLE001 - the page, not the run
            self._break(exc)
            return False

    def refresh(self, recorder) -> None:
        """Take the recorder's view now (``up``'s progress line, once a second)."""
        if self.broken:
            return
        try:
            self._read_events(recorder.recording)
            self.view = recorder.view()
            self._next_view = self.clock() + VIEW_S
            self._epoch_now(recorder)
        except Exception as exc:         # noqa: BLE001 - the page, not the run
            self._break(exc)

    def _epoch_now(self, recorder) -> None:
        k = max(recorder.step, 0)
        self.epoch_in_force = int([r for r in recorder.recording.rosters if r[0] <= k][-1][2])

    def _break(self, exc) -> None:
        self.broken = f"{type(exc).__name__}: {exc}"
        self.on_error(f"the live page stopped: {self.broken}")

    def finish(self, recorder, ended: str) -> None:
        """The run or the watch ended (``ended`` says how): the last snapshot."""
        self.ended = ended
        if self.board is not None:
            self.tick(recorder, None, force=True)
        self.close()

    def close(self) -> None:
        if self._worker is not None:
            self._worker.close()

    def _read_events(self, rec) -> None:
        """The monitor's and the recorder's new events, in the order they happened (their
        wall times ``t``), into the page's list; what they say of the agents' states."""
        wall, now = self.wall(), self.clock()
        new = []
        mon = rec.monitor_events
        for e in mon[self._mon_seen:]:
            self._learn_exact(e)
            kind = e.get("kind")
            a = e.get("agent")
            if kind == "verdict" and isinstance(a, int):
                self._verdict_at[a] = (now, e.get("step"), e.get("cause"))
            elif kind == "rejoin" and isinstance(a, int):
                self._rejoined_at[a] = now
            text = event_text(e)
            if text is not None:
                new.append({"t": _num(e.get("t")), "seen": wall,
                            "step": e.get("step", e.get("activate_at")),
                            "class": _event_class(e), "kind": kind, "agent": a,
                            "text": text, "mark": f"verdict: agent {a} {e.get('cause')}"
                            if kind == "verdict" else None})
        self._mon_seen = len(mon)
        for e in rec.events[self._rec_seen:]:
            name = str(e.get("process", ""))
            if e.get("liveliness") is False and rec.monitor_events:
                continue           # the monitor's own record says it
            if name.startswith("agent-") and e.get("role") == "dropped":
                with contextlib.suppress(ValueError):
                    self._dropped_at[int(name.split("-")[1])] = now
            text = event_text(e)
            if text is not None:
                fault = _event_class(e) == "fault"
                what = e.get("signal") or e.get("impair") or \
                    (f"link {e['link']}" if e.get("link") else None)
                new.append({"t": _num(e.get("t")), "seen": wall, "step": e.get("step"),
                            "class": _event_class(e), "kind": "fault" if fault else "recorder",
                            "agent": _agent_of(name), "text": text,
                            "mark": f"{name.replace('agent-', 'agent ')}: {what}"
                            if fault else None})
        self._rec_seen = len(rec.events)
        new.sort(key=lambda e: math.inf if e["t"] is None else e["t"])
        self._events.extend(new)
        self._news.extend(e["text"] for e in new if e["kind"] in NEWS_KINDS)
        return len(new)

    def news(self) -> list:
        """The lines of verdicts, reassignments, re-issues, rejoins and alerts heard since
        the last call (``up`` says each)."""
        out = list(self._news)
        self._news.clear()
        return out

    def progress_words(self) -> str:
        """``mse M over the last 100 steps (exact E)`` for ``up``'s progress line, from the
        newest tick's view (:func:`agent.run.live_view.over_last`); the exact MSE is the
        configuration in force's, when known.

        >>> from design.scenario import load_scenario
        >>> live = LiveState(load_scenario("paper-14"), [[0] * 3] * 3)
        >>> live.view = {"mse_last100": 0.29}; live._exact[0] = (0.27, "monitor")
        >>> live.progress_words()
        'mse 0.29 over the last 100 steps (exact 0.27)'
        """
        from agent.run.live_view import over_last

        v = self.view
        if v is None or v.get("mse_last100") is None:
            return "mse -"
        value, why = self.exact(self.epoch_in_force)
        return (f"mse {v['mse_last100']:.4g} {over_last(v)}"
                + (f" (exact {value:.4g})" if value is not None else
                   " (exact pending)" if why in ("pending", "computing") else ""))

    # -- the snapshot ----------------------------------------------------------------------
    def _configuration(self, rec, epoch: int) -> dict:
        """Who measures what and who listens to whom in ``epoch`` (cached)."""
        import numpy as np

        from agent.run.summary import specs_in_force

        key = (epoch, len(rec.rosters), len(rec.assigns))
        if key == self._config_key:
            return self._config
        s = self.s
        G0 = self.G if self.G is not None else [np.zeros((s.n, len(m))) for m in s.measure]
        try:
            ids, specs = specs_in_force(rec.rosters, rec.assigns, s, G0, epoch=epoch)
            roles = {a: {"measures": [str(x) for x in specs[a].measure],
                         "listens": {int(b): float(w) for b, w in specs[a].neighbours.items()}}
                     for a in ids if a in specs}
        except (StopIteration, KeyError, ValueError, TypeError):
            ids, roles = [], {}
        self._config_key, self._config = key, {"ids": [int(a) for a in ids], "roles": roles}
        return self._config

    def snapshot(self, recorder, alive=None) -> dict:
        """The page's state (docs/monitor.md, "The live page")."""
        rec = recorder.recording
        now, wall = self.clock(), self.wall()
        view = self.view if self.view is not None else recorder.view()
        k = recorder.step
        in_force = [r for r in rec.rosters if r[0] <= max(k, 0)][-1]
        epoch = int(in_force[2])
        pending = rec.rosters[-1] if rec.rosters[-1][2] != epoch else None
        self._feed_worker(rec, epoch)
        config = self._configuration(rec, epoch)
        ids = config["ids"] or list(in_force[1])
        world_fresh = (recorder.truth_at is not None and now - recorder.truth_at < 1.0
                       and self.ended is None)
        if alive is not None:
            self._token_seen |= set(alive)
        agents = []
        for a in range(1, self.M + 1):
            st = rec.status.get(a)
            if st is not None and st is not self._status_obj.get(a):
                self._status_obj[a], self._status_at[a] = st, now
            state, why = self._agent_state(a, st, ids, alive, now, world_fresh)
            row = view["agents"].get(a, {})
            role = config["roles"].get(a, {})
            learned = (st or {}).get("delays", {}) or {}
            agents.append({
                "id": a, "state": state, "why": why, "in_force": a in ids,
                "measures": role.get("measures", []),
                "listens": [{"from": b, "weight": _num(w),
                             "delay": int(self.table[a - 1, b - 1]),
                             "learned": _num(learned.get(str(b), learned.get(b)))}
                            for b, w in sorted(role.get("listens", {}).items())],
                "token": None if alive is None else a in alive,
                "step": row.get("step"), "epoch": row.get("epoch"),
                "mse": _num(row.get("mse")), "drops": row.get("drops", 0),
                "late": row.get("late", 0)})
        self._update_series(recorder)
        value, source = self.exact(epoch)
        segments = []
        for at, r_ids, ep in rec.rosters:
            v, src = self.exact(int(ep))
            segments.append({"from": int(at), "epoch": int(ep), "exact": v, "source": src})
        self._seq += 1
        return {
            "schema_version": 1, "kind": "page", "seq": self._seq, "updated": wall,
            "run": rec.run_id or self.run_id, "scenario": self.s.name, "step": k,
            "step_ms": self.step_ms, "ended": self.ended,
            "world_fresh": bool(world_fresh),
            "epoch": epoch, "roster": [int(a) for a in in_force[1]],
            "pending": None if pending is None else {"epoch": int(pending[2]),
                                                     "activate_at": int(pending[0]),
                                                     "ids": [int(a) for a in pending[1]]},
            "monitors_alive": view.get("monitors_alive"),
            "no_monitor_since": view.get("no_monitor_since"),
            "drops": view["drops"], "late": view["late"], "malformed": view["malformed"],
            "mse": {"step": view["mse_step"], "now": _num(view["mse"]),
                    "last100": _num(view.get("mse_last100")), "exact": value,
                    "exact_source": source, "exact_epoch": epoch},
            "graph": self.graph, "agents": agents,
            "events": list(self._events),
            "series": self._series_out(),
            "segments": segments,
        }

    def _agent_state(self, a, st, ids, alive, now, world_fresh) -> tuple:
        verdict = self._verdict_at.get(a)
        rejoined = self._rejoined_at.get(a)
        if verdict is not None and (rejoined is None or rejoined < verdict[0]):
            seen, step, cause = verdict
            # heard from after its verdict (a status 0.5 s later: not one in flight), or it
            # said it dropped its role: back, and outside the roster
            if self._status_at.get(a, -math.inf) > seen + 0.5 or \
                    self._dropped_at.get(a, -math.inf) > seen:
                return "fenced", (f"convicted ({cause}, step {step}), back and outside the "
                                  "roster: its estimates are ignored")
            return "convicted", f"{cause} at step {step}"
        if world_fresh:
            if alive is not None and a in self._token_seen and a not in alive:
                return "suspected", "liveliness token gone, no verdict yet"
            at = self._status_at.get(a)
            if at is not None and now - at > self.hang_timeout_s:
                return "suspected", f"no status for {now - at:.1f} s"
        if a in ids:
            return "active", "in the configuration in force"
        if st is not None and st.get("active"):
            return "active", "runs a role (the roster in force does not name it yet)"
        return "standby", "not in the configuration: a replacement in waiting"

    def _update_series(self, recorder) -> None:
        """The MSE by step for the chart, over the whole run in bounded memory: a step is
        final once every agent in force at it has published (or once it is
        :data:`SETTLE_STEPS` old) and goes into a block mean of ``_block`` steps (doubled
        whenever there would be more than :data:`SERIES_BLOCKS` blocks); the newest steps
        not final are recomputed at each tick (their late estimates)."""
        from design.metrics import mse_of_step

        rec = recorder.recording
        newest = recorder.step
        if newest < 0 or not rec.truth:
            return
        if self._settled is None:
            self._settled = min(rec.truth) - 1
        first = max(self._settled + 1, newest - 10 * SERIES_BLOCKS)
        recent = {}
        for j in range(first, newest + 1):
            if j in self._final or j not in rec.truth:
                continue
            ids = recorder.in_force(j)
            held = [rec.est[a][j] for a in ids if j in rec.est[a]]
            m = _num(mse_of_step(held, rec.truth[j]))
            if m is None:
                continue
            if len(held) == len(ids) or j <= newest - SETTLE_STEPS:
                self._final.add(j)
                b = self._blocks.setdefault(j // self._block, [0.0, 0])
                b[0] += m
                b[1] += 1
            else:
                recent[j] = m
        self._recent = recent
        # the oldest step not final yet: the next tick starts there
        while self._settled + 1 in self._final or (self._settled + 1 <= newest - SETTLE_STEPS):
            self._settled += 1
            self._final.discard(self._settled)
        while len(self._blocks) > SERIES_BLOCKS:          # coarser blocks, same memory
            merged = {}
            for i, (total, count) in self._blocks.items():
                b = merged.setdefault(i // 2, [0.0, 0])
                b[0] += total
                b[1] += count
            self._blocks, self._block = merged, self._block * 2

    def _series_out(self) -> dict:
        blocks = sorted(self._blocks)
        steps = [i * self._block for i in blocks]
        values = [self._blocks[i][0] / self._blocks[i][1] for i in blocks]
        recent = sorted(j for j in self._recent if j > (steps[-1] if steps else -1))
        return {"block": self._block, "steps": steps + recent,
                "mse": [float(f"{v:.5g}") for v in values + [self._recent[j] for j in recent]]}


def _agent_of(name: str):
    if name.startswith("agent-"):
        with contextlib.suppress(ValueError):
            return int(name.split("-", 1)[1])
    return None


# ---------------------------------------------------------------------------------------
# The page of a command: server + board, handed to the run that feeds it


class LivePage:
    """The server of ``--web`` and its board; :meth:`state_for` makes the
    :class:`LiveState` a run feeds. A context manager: closed on the way out."""

    def __init__(self, host: str, port: int, allow_remote: bool = False):
        self.board = Board()
        self.server = WebServer(self.board, host, port, allow_remote).start()
        self.state = None

    @property
    def url(self) -> str:
        return self.server.url

    def state_for(self, scenario, delays, G=None, **kwargs) -> LiveState:
        self.state = LiveState(scenario, delays, G, board=self.board, **kwargs)
        return self.state

    def close(self) -> None:
        if self.state is not None:
            self.state.close()
        self.server.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def live_state_factory(page: LivePage | None = None):
    """``factory(config, run_id, say)`` for :func:`agent.run.local.live_view`: the
    :class:`LiveState` of a local run (its ``RunConfig``), feeding ``page`` when given
    (else only the progress words and lines: no board, no worker)."""
    def make(config, run_id, say):
        c = config
        kwargs = dict(run_id=run_id, gains_path=c.gains_path, step_ms=c.step_ms,
                      hang_timeout_s=c.hang_timeout, on_error=say)
        if page is None:
            return LiveState(c.scenario, c.delays, c.G, exact_worker=False, **kwargs)
        return page.state_for(c.scenario, c.delays, c.G, **kwargs)

    return make


def open_page(web: str | None, remote: bool = False) -> LivePage | None:
    """The :class:`LivePage` of the flags ``--web`` and ``--web-remote`` (None without
    ``--web``), serving; a bad value or a port that cannot be had is an
    :class:`agent.run.inputs.InputError` naming ``--web`` (exit 2)."""
    from agent.run.inputs import InputError

    if web is None:
        if remote:
            raise InputError("--web-remote: only with --web [HOST:]PORT")
        return None
    try:
        host, port = parse_web_address(web, remote)
        return LivePage(host, port, remote)
    except (WebAddressError, OSError) as exc:
        raise InputError(str(exc)) from None


def page_words(page: LivePage) -> str:
    """What a command says of its page."""
    remote = not ipaddress.ip_address(page.server.host).is_loopback
    return (f"live page: {page.url}" + (" (NOT loopback: anyone who reaches this address "
                                        "sees the run)" if remote else ""))


__all__ += ["open_page", "page_words"]
