"""JSON for records and summaries: numpy values made plain, non-finite floats as strings,
bytes (signatures) as hex.

>>> import numpy as np
>>> to_jsonable({1: np.array([1.5, np.inf]), "ok": np.bool_(True)})
{'1': [1.5, 'inf'], 'ok': True}
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["to_jsonable", "versioned", "SCHEMA_VERSION"]

#: Version of the JSON vocabulary (docs/json.md) of every ``--json`` output and of the run
#: files (summary.json, reproduce's results.json); raised when a key changes meaning or name.
SCHEMA_VERSION = 1


def versioned(record: dict) -> dict:
    """``record`` with ``schema_version`` as its first key.

    >>> versioned({"scenario": "paper-14"})
    {'schema_version': 1, 'scenario': 'paper-14'}
    """
    return {"schema_version": SCHEMA_VERSION,
            **{k: v for k, v in record.items() if k != "schema_version"}}


def to_jsonable(obj):
    """numpy-aware conversion; non-finite floats become strings "inf"/"nan"."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (bytes, bytearray)):
        return bytes(obj).hex()
    if isinstance(obj, (np.floating, float)):
        x = float(obj)
        return x if math.isfinite(x) else ("inf" if x > 0 else "-inf" if x < 0 else "nan")
    return obj
