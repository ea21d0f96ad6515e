"""The gains file: an ``.npz`` with arrays ``K1..KN`` and a ``meta`` JSON string.

``K<i>`` is agent i's ``G_i = K^i H_i^T`` (n x p_i), its columns in the order of the nodes
agent i measures. ``meta`` records the scenario (name and digest), the method, the delay
matrix designed for and the radius found.

A gains file is read at a bounded cost, whatever it holds: it must be a regular file of
at most :data:`MAX_GAINS_BYTES`; the zip directory is read first (at most
:data:`MAX_MEMBERS` entries), then the ``.npy`` header of each array, whose shape and
dtype are checked (against the scenario's ``n x p_i`` when it is given) with the sizes the
directory declares, before any of its data is decompressed; the data read stops at the
declared size. Nothing is unpickled.

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
import math
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.lib import format as npy_format

from .errors import GainsError
from .files import UnreadableFile, human_bytes, open_bounded

__all__ = ["Gains", "save_gains", "load_gains", "gains_meta", "check_gains_fit", "gain_digest",
           "MAX_GAINS_BYTES", "MAX_META_BYTES", "MAX_MEMBERS"]

#: Largest gains file, and largest total of its arrays once decompressed. The gains of the
#: largest scenario (n <= 2000 and n N <= 3000, so n x sum p_i <= 2000 x 3000 doubles)
#: take 48 MB.
MAX_GAINS_BYTES = 128 << 20
#: Largest ``meta`` once decompressed (a JSON string; numpy stores it as UCS-4).
MAX_META_BYTES = 16 << 20
#: Most entries of the zip directory (K1..KN of at most 200 agents, meta, a few more).
MAX_MEMBERS = 256
#: Largest ``.npy`` header read (numpy's own default bound).
_MAX_HEADER = 10_000


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
    try:
        f, size = open_bounded(path, MAX_GAINS_BYTES)
    except UnreadableFile as exc:
        if str(exc) == "no such file":
            raise GainsError(f"{path}: no such gains file") from None
        raise GainsError(f"{path}: cannot read the gains file: {exc}") from None
    try:
        with f:
            entries = _zip_entries(f, size)
            if entries is not None and entries > MAX_MEMBERS:
                raise GainsError(f"{path}: {entries} entries in the zip directory, above the "
                                 f"most a gains file may hold, {MAX_MEMBERS}")
            with zipfile.ZipFile(f) as z:
                G, meta = _read_npz(z, size, scenario, path)
    except GainsError:
        raise
    except (OSError, ValueError, EOFError, RuntimeError, NotImplementedError,
            zipfile.BadZipFile, zipfile.LargeZipFile) as exc:
        if isinstance(exc, zipfile.BadZipFile) and "File is not a zip file" in str(exc):
            # np.load would take it as .npy or pickle and answer with advice on allow_pickle
            raise GainsError(f"{path}: not a .npz gains file (not a zip archive; "
                             "`socmon design --out FILE.npz` writes one)") from None
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


def _zip_entries(f, size: int):
    """The number of entries the end-of-directory record of a zip file declares (None when
    there is no such record: zipfile then reports it), read before zipfile builds one
    object per entry."""
    tail = min(size, 22 + 0xFFFF)            # the record, and a comment of at most 64 KiB
    f.seek(size - tail)
    buf = f.read(tail)
    at = buf.rfind(b"PK\x05\x06")
    if at < 0 or at + 22 > len(buf):
        return None
    entries = int.from_bytes(buf[at + 10:at + 12], "little")
    if entries == 0xFFFF and at >= 20 and buf[at - 20:at - 16] == b"PK\x06\x07":
        # zip64: the locator before the record gives where the zip64 record is
        offset = int.from_bytes(buf[at - 12:at - 4], "little")
        if offset + 40 <= size:
            f.seek(offset)
            rec = f.read(40)
            if rec[:4] == b"PK\x06\x06":
                entries = int.from_bytes(rec[32:40], "little")
    f.seek(0)
    return entries


def _read_npz(z: zipfile.ZipFile, size: int, scenario, path) -> tuple:
    """``(G, meta)`` from an open gains archive, each array checked by its header first
    (against the scenario's ``n x p_i`` when ``scenario`` is given)."""
    shapes = None if scenario is None else [(scenario.n, len(m)) for m in scenario.measure]
    infos = {}
    for info in z.infolist():
        if info.compress_size > size:
            raise GainsError(f"{path}: {info.filename}: the zip directory says "
                             f"{info.compress_size} compressed bytes in a file of {size}")
        name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
        infos[name] = info
    ks = sorted((f for f in infos if f.startswith("K") and f[1:].isdigit()),
                key=lambda f: int(f[1:]))
    if not ks:
        raise GainsError(f"{path}: no arrays K1..KN in the gains file")
    expected = [f"K{i}" for i in range(1, len(ks) + 1)]
    if ks != expected:
        raise GainsError(f"{path}: gain arrays must be K1..K{len(ks)}, found {_few(ks)}")
    if scenario is not None and len(ks) != scenario.N:
        raise GainsError(f"{path}: {len(ks)} gain arrays for {scenario.N} agents of scenario "
                         f"{scenario.name!r}")
    budget = [MAX_GAINS_BYTES]
    G = []
    for i, k in enumerate(ks):
        want = shapes[i] if shapes is not None else None
        g = _read_array(z, infos[k], k, path, budget, kinds="biuf", want=want, agent=i + 1)
        G.append(np.array(g, dtype=float))
    meta = {}
    if "meta" in infos:
        budget = [MAX_META_BYTES]
        m = _read_array(z, infos["meta"], "meta", path, budget, kinds="U", want=())
        try:
            meta = json.loads(str(m[()]))
        except (ValueError, TypeError) as exc:
            raise GainsError(f"{path}: meta is not a JSON string: {exc}") from None
        if not isinstance(meta, dict):
            raise GainsError(f"{path}: meta must be a JSON object")
    return G, meta


def _read_array(z, info, key, path, budget, kinds, want=None, agent=None) -> np.ndarray:
    """One ``.npy`` member: its header read and checked (dtype kind in ``kinds``, shape
    ``want`` or 2-d, data size against the directory's and against ``budget[0]`` bytes,
    which it then spends) before its data is decompressed."""
    where = f"{path}: {key}"
    if not info.filename.endswith(".npy"):
        raise GainsError(f"{where}: not a .npy array (member {info.filename!r})")
    if info.file_size > budget[0] + _MAX_HEADER:
        raise GainsError(f"{where}: {info.file_size} bytes once decompressed (zip directory), "
                         f"above the {human_bytes(budget[0])} left for it")
    with z.open(info) as fp:
        version = npy_format.read_magic(fp)
        if version == (1, 0):
            shape, fortran, dtype = npy_format.read_array_header_1_0(fp, _MAX_HEADER)
        elif version == (2, 0):
            shape, fortran, dtype = npy_format.read_array_header_2_0(fp, _MAX_HEADER)
        else:
            raise GainsError(f"{where}: .npy format version {version} is not supported "
                             "(1.0 and 2.0 are)")
        if dtype.hasobject or dtype.fields is not None or dtype.subdtype is not None \
                or dtype.kind not in kinds:
            what = "real numbers" if kinds == "biuf" else "a string"
            raise GainsError(f"{where} must hold {what}, got dtype {dtype}")
        if want is not None and tuple(shape) != want:
            if agent is not None:
                raise GainsError(f"{path}: {key} must be {want[0]} x {want[1]} (n x nodes "
                                 f"agent {agent} measures), got {tuple(shape)}")
            raise GainsError(f"{where}: must have shape {want}, got {tuple(shape)}")
        if want is None and len(shape) != 2:
            raise GainsError(f"{where} must be 2-d (n x p_{agent}), got shape {tuple(shape)}")
        nbytes = math.prod(shape) * dtype.itemsize
        if nbytes > budget[0]:
            raise GainsError(f"{where}: shape {tuple(shape)} of {dtype} is {nbytes} bytes, "
                             f"above the {human_bytes(budget[0])} left for it")
        held = info.file_size - fp.tell()
        if held != nbytes:
            raise GainsError(f"{where}: its header says {nbytes} bytes of data, the zip "
                             f"directory {held}")
        budget[0] -= nbytes
        data = fp.read(nbytes)
        if len(data) != nbytes:
            raise GainsError(f"{where}: truncated ({len(data)} of {nbytes} bytes)")
    return np.frombuffer(data, dtype=dtype).reshape(shape, order="F" if fortran else "C")


def _few(items, k: int = 10) -> str:
    more = f" and {len(items) - k} more" if len(items) > k else ""
    return f"{items[:k]}{more}"


def gain_digest(G) -> str:
    """A short digest of one agent's gain matrix: what an agent's start status says it
    runs, for the monitor to check against its own (the same ``--gains`` file).

    >>> gain_digest(np.eye(2)) == gain_digest([[1.0, 0.0], [0.0, 1.0]])
    True
    >>> gain_digest(np.eye(2)) == gain_digest(2 * np.eye(2)), len(gain_digest(np.eye(2)))
    (False, 16)
    """
    import hashlib

    # to 1e-9: the default gain designed by each process alone may differ in its last bits
    a = np.ascontiguousarray(np.round(np.asarray(G, dtype=float), 9) + 0.0, dtype="<f8")
    return hashlib.sha256(repr(a.shape).encode() + a.tobytes()).hexdigest()[:16]


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
