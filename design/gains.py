"""The gains file: an ``.npz`` with arrays ``K1..KN`` and a ``meta`` JSON string.

``K<i>`` is agent i's ``G_i = K^i H_i^T`` (n x p_i), its columns in the order of the nodes
agent i measures. ``meta`` records the scenario (name and digest), the method, the delay
matrix designed for and the radius found. The file is read with ``allow_pickle=False``.

Examples
--------
>>> import numpy as np, tempfile, os
>>> path = os.path.join(tempfile.mkdtemp(), "g.npz")
>>> save_gains(path, [np.ones((2, 1))], {"method": "hand"})
>>> g = load_gains(path)
>>> g.G[0].shape, g.meta["method"]
((2, 1), 'hand')
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import GainsError

__all__ = ["Gains", "save_gains", "load_gains", "gains_meta", "check_gains_fit"]


@dataclass(frozen=True, eq=False)
class Gains:
    """Per-agent gains ``G[i]`` (n x p_i, 0-based agents) and the file's metadata."""

    G: list
    meta: dict = field(default_factory=dict)

    def __len__(self):
        return len(self.G)

    def __getitem__(self, i):
        return self.G[i]


def gains_meta(scenario, method: str, delays, rho: float, **extra) -> dict:
    """The standard ``meta`` record for gains designed for ``scenario``."""
    meta = {
        "scenario": scenario.name,
        "scenario_digest": scenario.digest(),
        "measure": [scenario.agent_labels(i) for i in range(scenario.N)],
        "method": method,
        "delays": np.asarray(delays).tolist(),
        "rho_exact": float(rho),
    }
    meta.update(extra)
    return meta


def save_gains(path, G, meta: dict) -> None:
    """Write ``G`` (list of n x p_i arrays) and ``meta`` to ``path`` (.npz)."""
    arrays = {}
    for i, g in enumerate(G, start=1):
        g = np.asarray(g, dtype=float)
        if g.ndim != 2 or not np.all(np.isfinite(g)):
            raise GainsError(f"gains: K{i} must be a finite 2-d array, got shape {g.shape}")
        arrays[f"K{i}"] = g
    arrays["meta"] = np.array(json.dumps(meta, default=_json_default))
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, **arrays)
    tmp.replace(path)


def load_gains(path, scenario=None) -> Gains:
    """Read a gains file; with ``scenario``, also check that it fits (shapes).

    Raises
    ------
    GainsError
        Naming the file and what is wrong: unreadable, missing ``K<i>``, bad ``meta``,
        wrong shape or non-finite entries.
    """
    path = Path(path)
    if path.is_file() and not zipfile.is_zipfile(path):
        # np.load would take it as .npy or pickle and answer with advice on allow_pickle
        raise GainsError(f"{path}: not a .npz gains file (not a zip archive; "
                         "`socmon design --out FILE.npz` writes one)")
    try:
        with np.load(path, allow_pickle=False) as data:
            files = set(data.files)
            ks = sorted((f for f in files if f.startswith("K") and f[1:].isdigit()),
                        key=lambda f: int(f[1:]))
            if not ks:
                raise GainsError(f"{path}: no arrays K1..KN in the gains file")
            expected = [f"K{i}" for i in range(1, len(ks) + 1)]
            if ks != expected:
                raise GainsError(f"{path}: gain arrays must be K1..K{len(ks)}, found {ks}")
            raw = [data[k] for k in ks]
            for k, g in zip(ks, raw):
                if np.iscomplexobj(g) or g.dtype.kind not in "biuf":
                    raise GainsError(f"{path}: {k} must hold real numbers, got dtype {g.dtype}")
            G = [np.array(g, dtype=float) for g in raw]
            meta = {}
            if "meta" in files:
                try:
                    meta = json.loads(str(data["meta"]))
                except (ValueError, TypeError) as exc:
                    raise GainsError(f"{path}: meta is not a JSON string: {exc}") from None
                if not isinstance(meta, dict):
                    raise GainsError(f"{path}: meta must be a JSON object")
    except GainsError:
        raise
    except FileNotFoundError:
        raise GainsError(f"{path}: no such gains file") from None
    except IsADirectoryError:
        raise GainsError(f"{path}: is a directory, not a gains file") from None
    except (OSError, ValueError, zipfile.BadZipFile, KeyError) as exc:
        raise GainsError(f"{path}: not a readable .npz gains file ({exc})") from None
    for i, g in enumerate(G, start=1):
        if g.ndim != 2:
            raise GainsError(f"{path}: K{i} must be 2-d (n x p_{i}), got shape {g.shape}")
        if not np.all(np.isfinite(g)):
            raise GainsError(f"{path}: K{i} has non-finite entries")
    gains = Gains(G=G, meta=meta)
    if scenario is not None:
        check_gains_fit(gains, scenario, where=str(path))
    return gains


def check_gains_fit(gains, scenario, where: str = "gains") -> None:
    """Raise GainsError unless ``gains`` has one n x p_i block per agent of ``scenario``."""
    G = gains.G if isinstance(gains, Gains) else list(gains)
    if len(G) != scenario.N:
        raise GainsError(
            f"{where}: {len(G)} gain arrays for {scenario.N} agents of scenario "
            f"{scenario.name!r}"
        )
    for i, g in enumerate(G):
        p = len(scenario.measure[i])
        if np.shape(g) != (scenario.n, p):
            raise GainsError(
                f"{where}: K{i + 1} must be {scenario.n} x {p} (n x nodes agent {i + 1} "
                f"measures), got {np.shape(g)}"
            )


def _json_default(obj):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.floating,)):
        return float(obj)
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
