"""The run folder: never an earlier run's files mixed into a new one; atomic writes."""

import errno
import os

import pytest

from agent.run.folder import InvalidRunFolder, prepare_run_folder, write_atomic


def test_a_folder_holding_an_earlier_run_is_refused_naming_what_it_holds(tmp_path):
    (tmp_path / "events.jsonl").write_text('{"kind": "verdict"}\n')
    (tmp_path / "logs").mkdir()
    with pytest.raises(InvalidRunFolder, match=r"holds an earlier run \(events.jsonl, logs\)"):
        prepare_run_folder(tmp_path)
    assert (tmp_path / "events.jsonl").exists() and (tmp_path / "logs").is_dir()


def test_overwrite_removes_the_earlier_run_and_nothing_else(tmp_path):
    for name in ("summary.json", "events.jsonl", "notes.txt"):
        (tmp_path / name).write_text("x")
    (tmp_path / "logs").mkdir()
    (tmp_path / "logs" / "agent-1.log").write_text("x")
    prepare_run_folder(tmp_path, overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_a_new_or_unrelated_folder_is_accepted_and_a_file_is_not(tmp_path):
    assert prepare_run_folder(tmp_path / "a" / "b").is_dir()
    (tmp_path / "mine.txt").write_text("x")
    prepare_run_folder(tmp_path)
    with pytest.raises(InvalidRunFolder, match="is not a folder"):
        prepare_run_folder(tmp_path / "mine.txt")


def test_an_atomic_write_that_fails_keeps_the_old_file_and_leaves_no_temporary(tmp_path,
                                                                               monkeypatch):
    path = tmp_path / "summary.json"
    write_atomic(path, '{"old": 1}')

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(OSError, match="No space left"):
        write_atomic(path, '{"new": 2}')
    assert path.read_text() == '{"old": 1}'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["summary.json"]
    monkeypatch.undo()
    write_atomic(path, b'{"new": 2}')
    assert path.read_text() == '{"new": 2}'


def test_up_refuses_an_earlier_runs_folder_before_doing_anything(tmp_path, capsys, live_gains):
    from agent.cli.main import main

    (tmp_path / "events.jsonl").write_text('{"kind": "verdict", "agent": 1}\n')
    assert main(["up", "paper-14-live", "--steps", "5", "--gains", str(live_gains),
                 "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert f"--out: {str(tmp_path)!r} holds an earlier run (events.jsonl)" in err
    assert "--overwrite" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["events.jsonl"]


def test_a_full_disk_names_the_file_and_what_was_written_whole(tmp_path, monkeypatch):
    """write_run_folder writes the summary first; the disk fills on the second file:
    RunFolderError names that file and the summary, which is whole; no temporary stays."""
    import json

    from agent.run.folder import RunFolderError
    from agent.run.summary import write_run_folder

    calls = {"n": 0}
    real = os.fsync

    def fills_after_one(fd):
        calls["n"] += 1
        if calls["n"] > 1:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(fd)

    monkeypatch.setattr(os, "fsync", fills_after_one)
    summary = {"scenario": "x", "agents": 1, "seed": 0, "failures": []}
    with pytest.raises(RunFolderError) as info:
        write_run_folder(tmp_path, summary, [0, 1], [1.0, 0.5], 0.5)
    assert info.value.path.name == "mse.csv" and info.value.written == ["summary.json"]
    assert str(info.value) == (f"cannot write mse.csv in {str(tmp_path)!r} (No space left on "
                               "device); written whole before it: summary.json")
    assert json.loads((tmp_path / "summary.json").read_text()) == summary
    assert sorted(p.name for p in tmp_path.iterdir()) == ["summary.json"]


def test_a_command_whose_run_folder_cannot_be_written_says_so_in_one_line(capsys):
    from agent.cli._common import run_command
    from agent.run.folder import EXIT_FOLDER, RunFolderError

    def body():
        raise RunFolderError("/r/mse.png", OSError(errno.ENOSPC, "No space left on device"),
                             ["summary.json"])

    assert run_command(body) == EXIT_FOLDER == 3
    assert capsys.readouterr().err == ("socmon: run folder: cannot write mse.png in '/r' (No "
                                       "space left on device); written whole before it: "
                                       "summary.json\n")


def test_a_log_on_a_full_disk_loses_lines_not_the_process():
    """agent.cli.main.LossyStream: writes that fail for want of room are counted and dropped;
    a broken pipe still raises (``socmon certify | head`` stops)."""
    import io

    from agent.cli.main import LossyStream

    class Full(io.StringIO):
        def write(self, text):
            raise OSError(errno.ENOSPC, "No space left on device")

    class Closed(io.StringIO):
        def write(self, text):
            raise BrokenPipeError(errno.EPIPE, "Broken pipe")

    full = LossyStream(Full())
    print("a line", file=full, flush=True)
    assert full.lost == len("a line\n")
    with pytest.raises(BrokenPipeError):
        print("x", file=LossyStream(Closed()))


def test_monitor_logs_say_which_monitor_and_which_life():
    """``logs/monitor.log`` was monitor 1, ``monitor.2.log`` monitor 2 and
    ``monitor-2.log`` monitor 1 started again."""
    from agent.run.folder import monitor_name

    names = [monitor_name(1), monitor_name(2), monitor_name(1, restarts=1),
             monitor_name(1, restarts=2)]
    assert names == ["monitor-1", "monitor-2", "monitor-1.restart-1", "monitor-1.restart-2"]
    assert sorted(names) == ["monitor-1", "monitor-1.restart-1", "monitor-1.restart-2",
                             "monitor-2"]           # a listing of logs/ reads in order
