"""The run manifest: what every process of a run must agree on, checked at start-up.

``socmon up`` writes ``manifest.json`` in the run folder before it starts the children;
each child (``world``, ``agent``, ``monitor``, also when started by hand with
``--manifest FILE``) checks that the scenario it loaded, the gains file it was given,
its seed and its delays are the run's. A mismatch (another scenario file on another
host, gains designed for another scenario) is a clear error (exit 2), not a silent
divergence of the estimates.

Examples
--------
>>> import tempfile, pathlib
>>> from design.scenario import load_scenario
>>> s = load_scenario("paper-14")
>>> path = pathlib.Path(tempfile.mkdtemp()) / "manifest.json"
>>> write_manifest(path, s, None, 3, "none", s.delays * 0, "demo")
>>> check_manifest(path, s, None, 3, "none")["run"]
'demo'
>>> check_manifest(path, load_scenario("paper-14-live"), None, 3, "none")
Traceback (most recent call last):
...
agent.protocol.manifest.ManifestMismatch: --manifest: scenario paper-14-live (digest ...) is not the run's scenario paper-14 (digest ...)
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

__all__ = ["write_manifest", "check_manifest", "ManifestMismatch", "file_digest", "public_key"]


class ManifestMismatch(ValueError):
    """A process's scenario, gains, seed or delays differ from the run's manifest."""


def file_digest(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()[:16]


def write_manifest(path, scenario, gains_path, seed: int, delays_spec: str, delays,
                   run: str, control_public: bytes | None = None,
                   operator_public: bytes | None = None) -> None:
    data = {
        "run": run,
        "scenario": scenario.name,
        "scenario_digest": scenario.digest(),
        "agents": scenario.N,
        "standby": scenario.standby,
        "gains": None if gains_path is None else str(Path(gains_path).resolve()),
        "gains_digest": None if gains_path is None else file_digest(gains_path),
        "seed": int(seed),
        "delays_spec": delays_spec,
        "delays": np.asarray(delays, dtype=int).tolist(),
        # agents verify control messages with it (agent.protocol.control_auth)
        "control_public_key": None if control_public is None else bytes(control_public).hex(),
        "operator_public_key": None if operator_public is None else bytes(operator_public).hex(),
    }
    Path(path).write_text(json.dumps(data, indent=2) + "\n")


def check_manifest(path, scenario, gains_path, seed, delays_spec: str | None) -> dict:
    """Raise :class:`ManifestMismatch` naming every difference; return the manifest."""
    try:
        data = json.loads(Path(path).read_text())
    except OSError as exc:
        raise ManifestMismatch(f"--manifest: cannot read {str(path)!r}: {exc.strerror}") from None
    except ValueError as exc:
        raise ManifestMismatch(f"--manifest: {str(path)!r} is not JSON: {exc}") from None
    problems = []
    if data.get("scenario_digest") != scenario.digest() or \
            data.get("standby") != scenario.standby:
        problems.append(f"scenario {scenario.name} (digest {scenario.digest()}) is not the "
                        f"run's scenario {data.get('scenario')} (digest "
                        f"{data.get('scenario_digest')})")
    if gains_path is not None and data.get("gains_digest") not in (None, file_digest(gains_path)):
        problems.append(f"gains file {str(gains_path)!r} is not the run's "
                        f"({data.get('gains')}, digest {data.get('gains_digest')})")
    if seed is not None and data.get("seed") != int(seed):
        problems.append(f"--seed {seed} is not the run's seed {data.get('seed')}")
    if delays_spec is not None and data.get("delays_spec") != delays_spec:
        problems.append(f"--delays {delays_spec} is not the run's {data.get('delays_spec')}")
    if problems:
        raise ManifestMismatch("--manifest: " + "; ".join(problems))
    return data


def public_key(manifest: dict, field: str) -> bytes | None:
    """The Ed25519 public key ``field`` (``control_public_key``, ``operator_public_key``)
    of a manifest read by :func:`check_manifest`; None when the run has none.

    >>> public_key({"control_public_key": "ab" * 32}, "control_public_key") == bytes([0xab]) * 32
    True
    """
    value = manifest.get(field)
    if not value:
        return None
    try:
        key = bytes.fromhex(value)
    except (TypeError, ValueError):
        key = b""
    if len(key) != 32:
        raise ManifestMismatch(f"--manifest: {field} is not a 32-byte Ed25519 public key "
                               "in hex")
    return key
