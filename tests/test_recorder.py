"""The recorder fed by hand, the live view, run.json and --attach (no process started)."""

import io
import json

import numpy as np
import pytest

from agent.protocol import wire
from agent.cli.main import main
from agent.run.setup import check_run_endpoint
from agent.cli._common import CommandError
from agent.run.live_view import LiveView, format_lines
from agent.run.local import RunConfig
from agent.run.recorder import Recorder
from agent.run.folder import InvalidRunFolder, read_run_info, write_run_json
from agent.run.summary import mse_by_step, summarize
from agent.protocol import topics
from broker_free_net.ports import listen_port

RUN = "t"


def _status(agent, step, drops=0, late=0, active=True, epoch=0, links=None):
    return wire.encode_status({
        "agent": agent, "step": step, "active": active, "epoch": epoch, "measure": [],
        "neighbours": {}, "delays": {}, "drops": drops, "late": late, "malformed": 0,
        "malformed_reasons": {}, "impaired": 0, "sensor": {}, "heard": [], "ctl": {},
        "links": links or {}, "overflows": 0})


@pytest.fixture
def fed():
    """Two states, agents 1 and 2 active, 3 standby; steps 0..3, hand-computed errors."""
    r = Recorder(RUN, n=2, N=2, M=3)
    truth = {k: np.array([k, -k], float) for k in range(4)}
    for k, x in truth.items():
        r.feed(topics.truth_key(RUN), wire.encode_truth(k, x))
    # agent 1 is off by (1, 1) at every step, agent 2 by (0, 2); agent 2 misses step 3
    for k, x in truth.items():
        r.feed(topics.est_key(RUN, 1), wire.encode_est(1, k, x + [1, 1], epoch=0, t=0.0))
        if k < 3:
            r.feed(topics.est_key(RUN, 2), wire.encode_est(2, k, x + [0, 2], epoch=0, t=0.0))
    r.feed(topics.status_key(RUN, 1), _status(1, 3, drops=2, late=1))
    r.feed(topics.status_key(RUN, 2), _status(2, 2, drops=1))
    return r


def test_recorder_fed_by_hand_gives_the_mse_of_truth_and_estimates(fed):
    rec = fed.recording
    steps, mse = mse_by_step(rec, 3)
    # agent 1: mean((1, 1)^2) = 1; agent 2: mean((0, 2)^2) = 2; step 3 only agent 1
    assert steps == [0, 1, 2, 3]
    np.testing.assert_allclose(mse, [1.5, 1.5, 1.5, 1.0])
    view = fed.view()
    assert (view["step"], view["mse_step"], view["mse"]) == (3, 3, 1.0)
    assert view["mse_last100"] == pytest.approx((3 * 1.5 + 1.0) / 4)
    assert (view["drops"], view["late"]) == (3, 1)
    assert view["agents"][2]["mse"] == 2.0 and view["agents"][3]["step"] is None


def test_recorder_rosters_assignments_and_monitor_events(fed):
    fed.feed(topics.ctl_key(RUN, 0), wire.encode_roster(1, 2, [1, 3]))
    fed.feed(topics.ctl_key(RUN, 0), wire.encode_roster(1, 2, [1, 2]))   # not newer: ignored
    fed.feed(topics.ctl_key(RUN, 3), wire.encode_ctl(3, 1, 2, ["1"], {1: 0.5}, 0.5,
                                                   np.ones((2, 1)), take_over=2))
    fed.feed(topics.monitor_events_key(RUN), wire.encode_monitor_event(
        {"kind": "verdict", "agent": 2, "cause": "crash", "evidence": "token", "step": 1}))
    rec = fed.recording
    assert rec.rosters == [(0, (1, 2), 0), (2, (1, 3), 1)]
    assert rec.assigns[(3, 1)]["take_over"] == 2
    assert fed.in_force(1) == (1, 2) and fed.in_force(2) == (1, 3)
    view = fed.view()
    assert view["roster"] == [1, 3] and view["epoch"] == 1
    assert view["failures"] == [{"agent": 2, "cause": "crash", "step": 1}]
    # agent 2 came back and passed its probation: no longer shown as failed
    fed.feed(topics.monitor_events_key(RUN), wire.encode_monitor_event(
        {"kind": "rejoin", "agent": 2, "step": 3, "healthy_s": 5.0, "standby": [2]}))
    assert fed.view()["failures"] == []
    # an event whose time is not a number (the wire checks only its kind) breaks nothing
    fed.feed(topics.monitor_events_key(RUN), wire.encode_monitor_event(
        {"kind": "rejoin", "agent": 2, "step": 4, "t": None}))
    fed.feed(topics.monitor_events_key(RUN), wire.encode_monitor_event(
        {"kind": "verdict", "agent": 2, "cause": "hang", "evidence": "x", "step": 5,
         "t": "soon"}))
    assert [f["agent"] for f in fed.view()["failures"]] == []
    assert fed.recording.monitor_events[-1]["step"] == 3          # both refused...
    assert fed.stats.dropped["event"] == 2                        # ...and counted
    # from step 2 the roster is (1, 3): agent 3 sent nothing, so only agent 1 counts
    np.testing.assert_allclose(mse_by_step(rec, 3)[1], [1.5, 1.5, 1.0, 1.0])


def test_recorder_counts_and_drops_malformed_messages(fed):
    before = fed.recording.recorder_malformed
    fed.feed(topics.truth_key(RUN), b"\xc1 not msgpack")
    fed.feed(topics.truth_key(RUN), wire.encode_truth(9, np.zeros(3)))          # wrong n
    fed.feed(topics.est_key(RUN, 1), wire.encode_est(7, 9, np.zeros(2), 0, 0.0))  # unknown agent
    fed.feed(topics.monitor_events_key(RUN), wire.encode({"kind": "monitor_event",
                                                        "event": "[not a map]"}))
    fed.feed(topics.monitor_events_key(RUN), wire.encode({"kind": "monitor_event",
                                                        "event": "{bad json"}))
    rec = fed.recording
    assert rec.recorder_malformed == before + 5
    assert 9 not in rec.truth and rec.monitor_events == []
    assert all(9 not in by_step for by_step in rec.est.values())


def test_summary_of_a_watched_recording(fed, tmp_path):
    from design.scenario import load_scenario

    s = load_scenario("paper-14")
    config = RunConfig(scenario=s, scenario_arg="paper-14", G=None, gains_path=None,
                       delays=np.zeros((s.N, s.N), int), delays_spec="none", steps=3, seed=None,
                       step_ms=None, deadline_ms=None, out=None)
    summary, steps, mse = summarize(config, fed.recording, None, None)
    assert summary["steps"] == 3 and summary["drops"] == 3 and summary["late"] == 1
    assert summary["exit_status"] == {} and summary["orphans"] == []
    # the last quarter of 3 steps is the last step: too short for a standard error
    assert summary["mse_steady"] == 1.0
    assert summary["mse_steady_window"] == [3, 3] and summary["mse_steady_se"] is None



def test_an_interrupted_run_averages_the_last_quarter_of_the_steps_it_ran(tmp_path):
    """A run of 3,000 steps asked for, interrupted after step 239: its steady MSE covers
    steps 181-239 (its last 239 // 4 = 59; not 0-239 with the start-up transient)."""
    from design.scenario import load_scenario

    s = load_scenario("paper-14")
    r = Recorder(RUN, n=2, N=1, M=1)
    for k in range(240):
        r.feed(topics.truth_key(RUN), wire.encode_truth(k, np.zeros(2)))
        off = 10.0 if k < 100 else 1.0               # a transient, then an error of 1
        r.feed(topics.est_key(RUN, 1), wire.encode_est(1, k, np.full(2, off), epoch=0, t=0.0))
    config = RunConfig(scenario=s, scenario_arg="paper-14", G=None, gains_path=None,
                       delays=np.zeros((s.N, s.N), int), delays_spec="none", steps=3000,
                       seed=None, step_ms=None, deadline_ms=None, out=None)
    summary, steps, mse = summarize(config, r.recording, None, None)
    assert summary["steps"] == 239 and summary["steps_requested"] == 3000
    assert summary["mse_steady_window"] == [181, 239] and summary["mse_steady"] == 1.0


def test_live_view_forms():
    r = Recorder(RUN, n=1, N=1, M=1)
    r.feed(topics.truth_key(RUN), wire.encode_truth(0, [2.0]))
    r.feed(topics.est_key(RUN, 1), wire.encode_est(1, 0, [1.0], epoch=0, t=0.0))
    out = io.StringIO()
    view = LiveView(out, "json", interval=0)
    view.show(r.view())
    view.show(r.view())                  # unchanged: no second line
    line = json.loads(out.getvalue())
    assert line["kind"] == "view" and line["mse"] == 1.0 and line["step"] == 0
    out = io.StringIO()
    tty = LiveView(out, "tty", interval=0)
    tty.show(r.view())
    tty.show(r.view())
    lines = format_lines(r.view())
    # the second drawing goes back over the lines of the first
    assert out.getvalue().count(f"\x1b[{len(lines)}F") == 1
    with pytest.raises(ValueError, match="mode"):
        LiveView(out, "fancy", 1)


def test_run_json_round_trip_and_errors(tmp_path):
    write_run_json(tmp_path, run="r1", connect="tcp/127.0.0.1:7447", processes={},
                   scenario="paper-14", scenario_arg="paper-14", keys=tmp_path / "keys",
                   operator_key=tmp_path / "operator.key", seed=3, steps=10, step_ms=20.0)
    info = read_run_info(tmp_path)
    assert info.keys == (tmp_path / "keys").resolve() and info.seed == 3
    (tmp_path / "run.json").write_text('{"run": 5}')
    with pytest.raises(InvalidRunFolder, match="run missing or not a string"):
        read_run_info(tmp_path)
    (tmp_path / "run.json").write_text("{")
    with pytest.raises(InvalidRunFolder, match="is not JSON"):
        read_run_info(tmp_path)


def test_attach_errors_are_one_line_exit_2(tmp_path, capsys):
    assert main(["inject", "clear-all", "--attach", str(tmp_path)]) == 2
    assert main(["watch", "--attach", str(tmp_path)]) == 2
    assert main(["monitor", "--attach", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all("--attach" in e and "has no run.json" in e for e in err)
    assert main(["watch", "paper-14", "--run", "r"]) == 2
    assert "--connect" in capsys.readouterr().err
    # a run that has ended (its summary written): said at once, not after a timeout
    write_run_json(tmp_path, run="r", connect="tcp/127.0.0.1:9", processes={},
                   scenario="paper-14", scenario_arg="paper-14")
    (tmp_path / "summary.json").write_text("{}")
    assert main(["inject", "clear-all", "--attach", str(tmp_path)]) == 2
    assert main(["watch", "--attach", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all("has ended (its summary.json is written)" in e for e in err)


def test_up_run_and_listen_checked():
    assert check_run_endpoint("demo", None, False) == ("demo", None)
    with pytest.raises(CommandError, match="--run: invalid run id"):
        check_run_endpoint("a/b", None, False)
    with pytest.raises(CommandError, match="expected tls/HOST:PORT"):
        check_run_endpoint(None, "tcp/127.0.0.1:7447", True)
    port = listen_port()
    assert check_run_endpoint(None, f"tcp/127.0.0.1:{port}", False)[1].endswith(str(port))
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen()
        busy = sock.getsockname()[1]
        with pytest.raises(CommandError, match="--listen: cannot listen"):
            check_run_endpoint(None, f"tcp/127.0.0.1:{busy}", False)


def test_recorder_keeps_the_newest_steps_only():
    r = Recorder(RUN, n=1, N=1, M=1, keep_steps=5)
    for k in range(20):
        r.feed(topics.truth_key(RUN), wire.encode_truth(k, [float(k)]))
        r.feed(topics.est_key(RUN, 1), wire.encode_est(1, k, [k + 1.0], epoch=0, t=0.0))
    rec = r.recording
    assert sorted(rec.truth) == list(range(15, 20)) and r.step == 19
    assert sorted(rec.est[1]) == list(range(15, 20))
    assert r.view()["mse"] == 1.0 and mse_by_step(rec, 19)[0] == list(range(15, 20))


def test_a_stamp_far_ahead_or_a_wrong_sender_is_dropped_and_trimming_goes_on():
    r = Recorder(RUN, n=1, N=2, M=2, keep_steps=5)
    r.feed(topics.truth_key(RUN), wire.encode_truth(0, [0.0]))
    r.feed(topics.est_key(RUN, 1), wire.encode_est(1, 10**6, [1.0], epoch=0, t=0.0))  # future
    r.feed(topics.est_key(RUN, 2), wire.encode_est(1, 0, [9.0], epoch=0, t=0.0))  # not agent 2's
    assert r.recording.recorder_malformed == 2 and r.recording.est[1] == {}
    for k in range(1, 40):
        r.feed(topics.truth_key(RUN), wire.encode_truth(k, [float(k)]))
        r.feed(topics.est_key(RUN, 1), wire.encode_est(1, k, [k + 1.0], epoch=0, t=0.0))
    assert sorted(r.recording.est[1]) == list(range(35, 40))


def test_last_complete_step_ignores_agents_that_stopped(fed):
    # agent 2 stopped at step 2: with its token up the record ends at 2, without it at 3
    assert fed.last_complete_step(alive={1, 2}) == 2
    assert fed.last_complete_step(alive={1}) == 3
    assert fed.last_complete_step() == 3


def test_with_the_run_control_key_only_signed_rosters_are_recorded():
    from agent.protocol.control_auth import ControlSigner

    signer, other = ControlSigner.generate(), ControlSigner.generate()
    r = Recorder(RUN, n=1, N=1, M=2, control_public=signer.public_bytes())
    key = topics.ctl_key(RUN, 0)
    r.feed(key, wire.encode_roster(2**40, 5, [2]))                          # unsigned
    r.feed(key, wire.encode_roster(2**40, 5, [2], signer=other, run=RUN))   # another key
    genuine = wire.encode_roster(1, 5, [2], signer=signer, run=RUN)
    r.feed(key, genuine)
    r.feed(key, genuine)                       # a re-send of the same roster is no forgery
    assert r.recording.rosters[-1] == (5, (2,), 1)
    assert r.recording.recorder_malformed == 2


def test_watch_takes_the_control_key_from_the_runs_manifest(tmp_path):
    """``watch --manifest`` (or ``--attach``): the recorder drops rosters not signed with the
    manifest's control key; a manifest of another scenario is refused by name."""
    from agent.run.watch import control_key as _control_key
    from agent.protocol.control_auth import ControlSigner
    from agent.protocol.manifest import write_manifest
    from design.scenario import load_scenario

    s, other = load_scenario("paper-14-live"), load_scenario("paper-14")
    signer = ControlSigner.generate()
    path = tmp_path / "manifest.json"
    write_manifest(path, s, None, 0, "scenario", s.delays, "r1",
                   control_public=signer.public_bytes())
    public = _control_key(path, s, None)
    assert public == signer.public_bytes() and _control_key(None, s, None) is None
    with pytest.raises(CommandError, match="is not the run's scenario"):
        _control_key(path, other, None)
    bad = json.loads(path.read_text())
    bad["control_public_key"] = "ab" * 31
    path.write_text(json.dumps(bad))
    with pytest.raises(CommandError, match="control_public_key is not a 32-byte"):
        _control_key(path, s, None)
    rec = Recorder("r1", n=s.n, N=s.N, M=s.N + s.standby, control_public=public)
    roster = {"kind": "roster", "epoch": 1, "activate_at": 5, "ids": [1, 3, 4]}
    assert rec._authentic(dict(roster)) is None                       # unsigned: dropped
    signed = signer.sign(dict(roster), "r1")
    assert rec._authentic(signed) is signed


def test_link_impairments_taking_effect_are_recorded_as_events(fed):
    """Whatever set them (the run's faults, `socmon inject`), the impairments in force on
    an agent's links are recorded when its status shows them changed, and when lifted."""
    fed.feed(topics.status_key(RUN, 1), _status(1, 4))                       # unchanged
    fed.feed(topics.status_key(RUN, 1), _status(1, 5, links={"2": {"partition": True}}))
    fed.feed(topics.status_key(RUN, 1), _status(1, 6, links={"2": {"partition": True}}))
    fed.feed(topics.status_key(RUN, 1), _status(1, 9))
    changes = [(e["process"], e["step"], e["links"]) for e in fed.recording.events
               if "links" in e]
    assert changes == [("agent-1", 5, {"2": {"partition": True}}), ("agent-1", 9, {})]


def test_a_status_with_an_epoch_far_above_any_seen_is_not_recorded():
    from agent.run.recorder import Recorder
    from agent.protocol.timing import DEFAULT as TIMING
    from agent.protocol import wire as w
    from agent.protocol import topics as k

    r = Recorder("demo", n=2, N=1, M=1)
    status = {"agent": 1, "step": 3, "active": True, "epoch": 2 ** 61, "measure": ["1"],
              "neighbours": {}, "delays": {}, "drops": 0, "late": 0, "malformed": 0,
              "malformed_reasons": {}, "impaired": 0, "sensor": {}, "heard": [], "ctl": {},
              "links": {}, "overflows": 0}
    r.feed(k.status_key("demo", 1), w.encode_status(status))
    assert 1 not in r.recording.status and r.stats.total_dropped == 1
    r.feed(k.status_key("demo", 1), w.encode_status({**status,
                                                     "epoch": TIMING.epoch_jump_max}))
    assert r.recording.status[1]["epoch"] == TIMING.epoch_jump_max


def test_up_no_precompute_reaches_every_monitor(tmp_path, live_gains):
    """``up --no-precompute`` makes RunConfig.precompute False, which puts the flag on the
    first monitor's command line and on the standby monitors' built from it; by default
    it is on none."""
    import types

    from agent.cli.main import build_parser
    from agent.run.local import LocalRun, _standby_monitor
    from agent.run.setup import run_config
    from design.scenario import load_scenario

    for flags, want in (([], True), (["--no-precompute"], False)):
        args = build_parser().parse_args(["up", "paper-14-live", "--gains", str(live_gains),
                                          "--out", str(tmp_path / f"run-{want}"), *flags])
        assert run_config(args, lambda text: None).precompute is want
    s = load_scenario("paper-14-live")
    ep = [f"tcp/127.0.0.1:{7000 + i}" for i in range(len(s.measure) + 8)]
    rec = types.SimpleNamespace(run_id="r1")
    lines = {}
    for precompute in (True, False):
        config = RunConfig(scenario=s, scenario_arg="paper-14-live", G=None,
                           gains_path=tmp_path / "g.npz", delays=s.delays, delays_spec="scenario",
                           steps=10, seed=0, step_ms=20.0, deadline_ms=20.0, out=tmp_path,
                           precompute=precompute)
        lines[precompute] = LocalRun(config)._argv(rec, ep)["monitor"]
    assert "--no-precompute" in lines[False] and "--no-precompute" not in lines[True]
    assert lines[False][:len(lines[True])] == lines[True]
    standby = {p: _standby_monitor(lines[p], 2, "tcp/127.0.0.1:7999") for p in lines}
    assert "--no-precompute" in standby[False] and "--no-precompute" not in standby[True]


def test_a_recorder_keeping_every_kth_step_keeps_every_epoch():
    """``record_every=3, last_step=7``: the states of steps 0, 3, 6 and 7 only, the epoch
    of every estimate (the rosters in force are read from them), the newest step from
    every truth; the MSE over the kept steps is their own."""
    r = Recorder(RUN, n=2, N=1, M=1, record_every=3, last_step=7)
    for k in range(8):
        x = np.array([k, -k], float)
        r.feed(topics.truth_key(RUN), wire.encode_truth(k, x))
        r.feed(topics.est_key(RUN, 1), wire.encode_est(1, k, x + [k, 0], epoch=0, t=0.0))
    rec = r.recording
    assert sorted(rec.truth) == sorted(rec.est[1]) == [0, 3, 6, 7]
    assert sorted(rec.est_epoch[1]) == list(range(8)) and r.step == 7
    assert r.estimates_received == 8
    steps, mse = mse_by_step(rec, 7)
    assert steps == [0, 3, 6, 7]
    np.testing.assert_allclose(mse, [k * k / 2 for k in steps])
    with pytest.raises(ValueError, match="record_every"):
        Recorder(RUN, n=2, N=1, M=1, record_every=0)


def test_the_mean_of_the_last_100_steps_says_the_steps_and_the_samples_it_covers():
    """``up --record-every 5`` at step 300: 20 kept steps over the last 100; the progress
    line said "over the last 20 steps"."""
    from agent.run.live_view import over_last

    r = Recorder(RUN, n=2, N=1, M=1, record_every=5, last_step=300)
    for k in range(301):
        x = np.array([k, -k], float)
        r.feed(topics.truth_key(RUN), wire.encode_truth(k, x))
        r.feed(topics.est_key(RUN, 1), wire.encode_est(1, k, x + [1, 1], epoch=0, t=0.0))
    view = r.view()
    assert (view["mse_step"], view["mse_last100_steps"], view["mse_last100_samples"]) == \
        (300, 100, 20)
    assert over_last(view) == "over the last 100 steps (20 samples)"
    r = Recorder(RUN, n=2, N=1, M=1)
    for k in range(12):
        r.feed(topics.truth_key(RUN), wire.encode_truth(k, np.zeros(2)))
        r.feed(topics.est_key(RUN, 1), wire.encode_est(1, k, np.ones(2), epoch=0, t=0.0))
    assert over_last(r.view()) == "over the last 12 steps"


@pytest.mark.parametrize("value", ["0", "-2", "x"])
def test_up_record_every_is_checked(tmp_path, capsys, value):
    assert main(["up", "paper-14-live", "--out", str(tmp_path / "run"), "--record-every",
                 value]) == 2
    assert "--record-every" in capsys.readouterr().err


def test_watch_says_the_prediction_for_the_configuration_in_force():
    """After a recovery the watch's last line compares the MSE with the prediction of the
    configuration in force, as ``up``'s does, not with the first configuration's."""
    from types import SimpleNamespace

    from agent.run.watch import WatchResult, summary_lines

    config = SimpleNamespace(scenario=SimpleNamespace(name="paper-14-live"),
                             net=SimpleNamespace(run="r"))
    summary = {"steps": 1000, "mse_steady": 0.2083, "mse_steady_se": 0.021,
               "mse_steady_window": [751, 1000], "mse_steady_exact": 0.271,
               "mse_steady_exact_in_force": 0.2107, "drops": 0, "late": 0, "malformed": 0}

    def first_line(**changes):
        result = WatchResult(None, {**summary, **changes}, [], np.zeros(0), "world ended")
        return summary_lines(result, config)[0]

    assert "(predicted 0.2107 for the configuration in force)" in first_line()
    assert "(predicted n/a: the window spans a switch)" in \
        first_line(mse_steady_exact_in_force=None)
    assert "(no --gains: no prediction)" in \
        first_line(mse_steady_exact=None, mse_steady_exact_in_force=None)


def test_an_interrupted_run_ends_at_the_last_step_every_agent_published():
    """Stopped mid-step, the truth of step 224 came and no estimate of it: the record ends
    at 223 (the recorder's last complete step), with no divergence to report."""
    from design.scenario import load_scenario

    s = load_scenario("paper-14")
    r = Recorder(RUN, n=2, N=2, M=2)
    for k in range(225):
        r.feed(topics.truth_key(RUN), wire.encode_truth(k, np.zeros(2)))
        for a in (1, 2):
            if k < 224 - (a == 2):          # agent 2 is a step behind agent 1
                r.feed(topics.est_key(RUN, a), wire.encode_est(a, k, np.ones(2), epoch=0, t=0))
    rec = r.recording
    rec.interrupted, rec.complete_step = True, r.last_complete_step({1, 2})
    assert rec.complete_step == 222
    config = RunConfig(scenario=s, scenario_arg="paper-14", G=None, gains_path=None,
                       delays=np.zeros((s.N, s.N), int), delays_spec="none", steps=1500,
                       seed=None, step_ms=None, deadline_ms=None, out=None)
    summary, steps, mse = summarize(config, rec, None, None)
    assert steps[-1] == 222 and summary["steps"] == 222 and summary["steps_requested"] == 1500
    assert summary["diverged_at"] is None and np.isfinite(mse).all()


@pytest.mark.parametrize("dead, recovered", [(4, None), (2, False)])
def test_the_death_of_a_standby_alone_loses_no_role(dead, recovered):
    """A standby killed, no verdict, no roles moved: nothing to recover (the key stays
    unset, the line says it held no role); an agent in force killed so: not recovered."""
    from design.scenario import load_scenario

    from agent.run.summary import failure_lines

    s = load_scenario("paper-14")
    r = Recorder(RUN, n=s.n, N=s.N, M=s.N + s.standby)
    for k in range(40):
        r.feed(topics.truth_key(RUN), wire.encode_truth(k, np.zeros(s.n)))
        for a in (1, 2, 3):
            if a != dead or k < 20:
                r.feed(topics.est_key(RUN, a), wire.encode_est(a, k, np.ones(s.n), 0, 0.0))
    rec = r.recording
    rec.events.append({"process": f"agent-{dead}", "exit_status": -9, "step": 20, "t": 1.0})
    G = [np.zeros((s.n, len(m))) for m in s.measure]
    config = RunConfig(scenario=s, scenario_arg="paper-14", G=G, gains_path=None,
                       delays=np.zeros((s.N, s.N), int), delays_spec="none", steps=39,
                       seed=0, step_ms=20.0, deadline_ms=None, out=None)
    summary, steps, mse = summarize(config, rec, 0.9, 1.0)
    assert summary.get("recovered") is recovered
    [f] = summary["failures"]
    assert (f["agent"], f["detected"], f["role"]) == (dead, False,
                                                      "standby" if dead == 4 else "active")
    line = failure_lines(summary)[0]
    assert line.endswith("a standby, it held no role" if dead == 4 else "not recovered")


def test_a_watch_of_a_run_whose_clock_never_started_says_so_and_exits_1():
    from types import SimpleNamespace

    from agent.run.watch import WatchResult, exit_status, summary_lines

    config = SimpleNamespace(scenario=SimpleNamespace(name="paper-14-live"),
                             net=SimpleNamespace(run="r"))
    never = WatchResult(None, {"steps": -1}, [], np.zeros(0), "world ended")
    assert exit_status(never) == 1
    assert "before its clock started: no step recorded" in summary_lines(never, config)[0]
    ran = WatchResult(None, {"steps": 150}, [], np.zeros(0), "world ended")
    assert exit_status(ran) == 0
    # its world killed mid-run: its token went without its end message
    lost = WatchResult(None, {"steps": 441, "mse_steady": 0.3, "mse_steady_se": None,
                              "mse_steady_window": None, "mse_steady_exact": None, "drops": 0,
                              "late": 0, "malformed": 0}, [], np.zeros(0), "world lost")
    assert exit_status(lost) == 1
    assert summary_lines(lost, config)[0].startswith(
        "paper-14-live: run r LOST ITS WORLD (its token went without its end: killed, paused "
        "past its lease or cut off), last step 441")
    nothing = WatchResult(None, {"steps": -1}, [], np.zeros(0), "interrupted")
    assert summary_lines(nothing, config)[0].endswith("no step recorded (nothing of the run "
                                                      "heard)")
    assert exit_status(WatchResult(None, {"steps": -1}, [], np.zeros(0), "interrupted")) == 130


def test_a_watch_whose_steps_are_behind_the_run_says_so_and_exits_2(monkeypatch):
    """``watch --steps 50`` joining a run at step 126: nothing of steps 0..50 is left to
    hear; said as such (exit 2), not as a world that gave up before its clock started."""
    from types import SimpleNamespace

    from agent.run import watch as watch_module
    from agent.run.inputs import InputError
    from agent.run.watch import WatchConfig, steps_behind_text, watch
    from design.scenario import load_scenario

    assert steps_behind_text(50, 126) == (
        "--steps: 50 is behind the run (at step 126 when the watch joined): give a later "
        "step, or leave --steps out to watch until the world ends")

    def joined_at_126(net, recorder, *, steps, **_):
        recorder.recording.truth[126] = np.zeros(14)
        return "behind"

    monkeypatch.setattr(watch_module, "watch_run", joined_at_126)
    scenario = load_scenario("paper-14-live")
    config = WatchConfig(scenario=scenario, scenario_arg="paper-14-live",
                         net=SimpleNamespace(run="r", connect=("tcp/127.0.0.1:9",)),
                         delays=np.zeros((3, 3), dtype=int), delays_spec="scenario", steps=50)
    view = SimpleNamespace(show=lambda v: None, close=lambda: None)
    with pytest.raises(InputError) as info:
        watch(config, view)
    assert str(info.value) == steps_behind_text(50, 126) and info.value.status == 2
