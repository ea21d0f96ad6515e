"""The run folder: ``run.json`` (what another tool needs to attach to a run, and
``--attach RUN_DIR``), a clean folder for each run, and atomic writes.

A run never writes into a folder that holds an earlier run's files (:data:`RUN_ENTRIES`):
:func:`prepare_run_folder` refuses it, naming the folder and what it holds, unless told to
overwrite, which removes exactly those entries first (an appended ``events.jsonl`` made a
clean second run report the first run's failure). :func:`write_atomic` writes a file so
that a reader never sees it half-written and a full disk leaves the old version intact.

``socmon up`` writes ``run.json`` in its run folder once its processes are started: the
run id, the endpoint to connect to (the recorder's), every process's endpoint and PID,
and the paths of what a peer of the run needs: the key directory of a secure run, the
operator key that signs impairments, the control key, the manifest, the scenario, the
gains. ``socmon inject|watch|monitor --attach RUN_DIR`` read it with
:func:`read_run_info`; a flag given on the command line wins over the folder's value.

Examples
--------
>>> import tempfile, pathlib
>>> d = pathlib.Path(tempfile.mkdtemp())
>>> write_run_json(d, run="demo", connect="tcp/127.0.0.1:7447", processes={},
...                scenario="paper-14", scenario_arg="paper-14")
>>> info = read_run_info(d)
>>> info.run, info.connect, info.keys
('demo', 'tcp/127.0.0.1:7447', None)
"""

from __future__ import annotations

import contextlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

__all__ = ["RUN_JSON", "RUN_ENTRIES", "RunInfo", "InvalidRunFolder", "RunFolderError",
           "EXIT_FOLDER", "write_run_json", "read_run_info", "prepare_run_folder",
           "write_atomic", "monitor_name"]

RUN_JSON = "run.json"
RUN_JSON_VERSION = 1


#: The zenoh configuration file ``up`` writes in the run folder for its children and its
#: recorder (:func:`agent.run.local._write_mesh_config`).
MESH_CONFIG = "zenoh-mesh.json5"
#: What a run (``up``, ``watch --out``, ``chaos``) writes in its folder.
RUN_ENTRIES = ("run.json", "summary.json", "events.jsonl", "mse.json", "mse.csv", "mse.png",
               "estimates.npz", "assignments.json", "gains.npz", "manifest.json",
               "control.key", "operator.key", "keys", "logs", "schedule.json",
               "invariants.json", "timeline.json", "timeline.png", MESH_CONFIG)


def monitor_name(monitor_id: int, restarts: int = 0) -> str:
    """A monitor's process name, which names its log (``logs/<name>.log``), its row of
    ``exit_status`` and ``cpu_s`` and its events: ``monitor-1`` the first, ``monitor-2``
    and on the standbys (``--monitors``), ``monitor-1.restart-1`` monitor 1 started
    again after ``--kill-monitor``.

    >>> monitor_name(1), monitor_name(2), monitor_name(1, restarts=1)
    ('monitor-1', 'monitor-2', 'monitor-1.restart-1')
    """
    return f"monitor-{monitor_id}" + (f".restart-{restarts}" if restarts else "")


class InvalidRunFolder(ValueError):
    """A run folder without a readable, well-formed ``run.json``, or one that cannot hold a
    new run; the message names the folder and why."""


def prepare_run_folder(folder, overwrite: bool = False) -> Path:
    """Make ``folder`` ready for a new run and return it.

    Made if missing; refused (:class:`InvalidRunFolder`) when it is not a folder, or when
    it holds an earlier run's entries and ``overwrite`` is false; with ``overwrite`` those
    entries (and nothing else) are removed first.

    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp()) / "run"
    >>> _ = prepare_run_folder(d); (d / "summary.json").write_text("{}")
    2
    >>> prepare_run_folder(d)
    Traceback (most recent call last):
    ...
    agent.run.folder.InvalidRunFolder: ... holds an earlier run (summary.json): choose another folder, or --overwrite to replace that run
    >>> sorted(p.name for p in prepare_run_folder(d, overwrite=True).iterdir())
    []
    """
    import shutil

    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InvalidRunFolder(f"{str(folder)!r} is not a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InvalidRunFolder(f"cannot make the run folder {str(folder)!r}: "
                               f"{exc.strerror}") from None
    held = [name for name in RUN_ENTRIES if (folder / name).exists()
            or (folder / name).is_symlink()]
    if held and not overwrite:
        raise InvalidRunFolder(f"{str(folder)!r} holds an earlier run ({', '.join(held)}): "
                               "choose another folder, or --overwrite to replace that run")
    for name in held:
        path = folder / name
        try:
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            else:
                path.unlink()
        except OSError as exc:
            raise InvalidRunFolder(f"cannot remove the earlier run's {str(path)!r}: "
                                   f"{exc.strerror}") from None
    return folder


class RunFolderError(OSError):
    """A run-folder file could not be written (a full disk): names the file, the reason,
    and the files written whole before it."""

    def __init__(self, path, exc: OSError, written):
        self.path, self.written = Path(path), list(written)
        self.strerror = exc.strerror or str(exc)
        super().__init__(exc.errno, f"cannot write {self.path.name} in {str(self.path.parent)!r}"
                                    f" ({self.strerror}); "
                         + (f"written whole before it: {', '.join(self.written)}"
                            if self.written else "nothing of the run folder was written"))

    def __str__(self):
        return self.args[1]


EXIT_FOLDER = 3
"""Exit status of a command whose run folder could not be written (a full disk)."""


def write_atomic(path, data) -> None:
    """Write ``data`` (str or bytes) to ``path`` through a temporary file in the same
    folder, flushed and renamed over it: a reader sees the old file or the whole new one,
    and a write that fails (a full disk) leaves the old one and no temporary behind."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    raw = data.encode() if isinstance(data, str) else bytes(data)
    try:
        with open(tmp, "wb") as f:
            f.write(raw)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


@dataclass(frozen=True)
class RunInfo:
    """The contents of ``run.json``; paths are absolute, or None when the run has none."""

    folder: Path
    run: str
    connect: str
    processes: dict
    scenario: str
    scenario_arg: str
    keys: Path | None = None
    operator_key: Path | None = None
    control_key: Path | None = None
    manifest: Path | None = None
    gains: Path | None = None
    seed: int | None = None
    delays: str | None = None
    steps: int | None = None
    step_ms: float | None = None


_PATHS = ("keys", "operator_key", "control_key", "manifest", "gains")


def write_run_json(folder, *, run: str, connect: str, processes: dict, scenario: str,
                   scenario_arg: str, **extra) -> None:
    """Write ``folder/run.json`` (atomically); ``extra``: the optional fields of
    :class:`RunInfo`."""
    folder = Path(folder)
    unknown = set(extra) - set(RunInfo.__dataclass_fields__)
    if unknown:
        raise TypeError(f"write_run_json: unknown fields {sorted(unknown)}")
    data = {"version": RUN_JSON_VERSION, "run": run, "connect": connect,
            "scenario": scenario, "scenario_arg": scenario_arg, "out": str(folder.resolve()),
            "processes": processes}
    for name, value in extra.items():
        data[name] = str(Path(value).resolve()) if name in _PATHS and value is not None \
            else value
    # atomically: a tool polling for run.json never reads it half-written
    write_atomic(folder / RUN_JSON, json.dumps(data, indent=2) + "\n")


def read_run_info(folder) -> RunInfo:
    """The :class:`RunInfo` of a run folder; :class:`InvalidRunFolder` naming what is wrong."""
    folder = Path(folder)
    path = folder / RUN_JSON
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise InvalidRunFolder(f"{str(folder)!r} has no {RUN_JSON} (is it the folder of a "
                               f"running `socmon up`?)") from None
    except OSError as exc:
        raise InvalidRunFolder(f"cannot read {str(path)!r}: {exc.strerror}") from None
    except ValueError as exc:
        raise InvalidRunFolder(f"{str(path)!r} is not JSON: {exc}") from None
    if not isinstance(data, dict):
        raise InvalidRunFolder(f"{str(path)!r}: expected a JSON object")
    problems = [f"{k} missing or not a string" for k in ("run", "connect", "scenario",
                                                         "scenario_arg")
                if not isinstance(data.get(k), str)]
    if not isinstance(data.get("processes", {}), dict):
        problems.append("processes is not an object")
    for k in _PATHS + ("delays",):
        if data.get(k) is not None and not isinstance(data[k], str):
            problems.append(f"{k} is not a string")
    for k in ("seed", "steps"):
        if data.get(k) is not None and (isinstance(data[k], bool) or
                                         not isinstance(data[k], int)):
            problems.append(f"{k} is not an integer")
    if data.get("step_ms") is not None and not isinstance(data["step_ms"], (int, float)):
        problems.append("step_ms is not a number")
    if problems:
        raise InvalidRunFolder(f"{str(path)!r}: " + "; ".join(problems))
    fields = {k: data.get(k) for k in RunInfo.__dataclass_fields__ if k != "folder"}
    fields["processes"] = data.get("processes", {})
    for k in _PATHS:
        if fields[k] is not None:
            fields[k] = Path(fields[k])
    return RunInfo(folder=folder, **fields)
