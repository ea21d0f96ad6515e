"""The run folder: never an earlier run's files mixed into a new one; atomic writes."""

import errno
import os

import pytest

from agent.run_folder import InvalidRunFolder, prepare_run_folder, write_atomic


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
    from agent.cli import main

    (tmp_path / "events.jsonl").write_text('{"kind": "verdict", "agent": 1}\n')
    assert main(["up", "paper-14-live", "--steps", "5", "--gains", str(live_gains),
                 "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert f"--out: {str(tmp_path)!r} holds an earlier run (events.jsonl)" in err
    assert "--overwrite" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["events.jsonl"]
