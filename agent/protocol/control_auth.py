"""Signed control messages: only the holder of the run's control key can command agents.

The monitor signs every ``assign`` and ``roster`` it publishes with Ed25519 (the
``cryptography`` package); an agent given the run's public key (from the run's
manifest) verifies the signature before any state changes, and rejects what fails
(counted ``signature``). The signature covers the run id and every field of the message
in a canonical form (so a genuine command re-stamped with another epoch, or sent to
another agent or run, fails), plus ``seq``: microseconds of the signer's clock, which
only grow. An agent rejects a ``seq`` not above the last one it accepted of the same kind,
and one older than its own start minus :data:`MAX_SKEW_S` (a genuine old command replayed to an agent
that restarted). An epoch far ahead is accepted from nobody but the key holder, so no
one can lock the control plane.

Examples
--------
>>> signer = ControlSigner.generate()
>>> verifier = ControlVerifier(signer.public_bytes(), run="demo", not_before=0)
>>> msg = signer.sign({"kind": "roster", "epoch": 1, "activate_at": 5, "ids": [1, 2]}, "demo")
>>> verifier.check(msg)
>>> verifier.check(dict(msg, epoch=9))
Traceback (most recent call last):
...
agent.protocol.control_auth.SignatureError: signature: does not verify
"""

from __future__ import annotations

import math
import struct
import time

import msgpack
import numpy as np

__all__ = ["ControlSigner", "ControlVerifier", "SignatureError", "canonical", "MAX_SKEW_S"]

#: how much older than an agent's start a signed command may be (clock skew allowance)
MAX_SKEW_S = 5.0


class SignatureError(ValueError):
    """A control message is unsigned, badly signed, replayed or from another run."""

    def __init__(self, message: str):
        super().__init__(f"signature: {message}")


def _norm(value):
    if isinstance(value, np.ndarray):
        arr = np.ascontiguousarray(value, dtype="<f8")
        return ["f8", list(arr.shape), arr.tobytes()]
    if isinstance(value, dict):
        return [[_norm(k), _norm(v)] for k, v in sorted(value.items(), key=lambda kv: str(kv[0]))]
    if isinstance(value, (list, tuple)):
        return [_norm(v) for v in value]
    if isinstance(value, bool) or value is None:
        return value
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        x = float(value)
        # a number field may be sent as 0 and decoded as 0.0: integral values below 2^53
        # are one form; everything else is its exact float64 bytes
        if math.isfinite(x) and x.is_integer() and abs(x) < 2**53:
            return int(x)
        return struct.pack("<d", x)
    return str(value)


def canonical(msg: dict, run: str) -> bytes:
    """The bytes a signature covers: the run id and every field but ``sig``, normalised
    (sorted keys, float64 bytes, arrays as dtype/shape/bytes), as the receiver decodes
    them."""
    body = {k: v for k, v in msg.items() if k not in ("sig", "v")}
    return msgpack.packb(["socmon-control-1", run, _norm(body)], use_bin_type=True)


class ControlSigner:
    """The monitor's (or operator's) Ed25519 private key."""

    def __init__(self, private_bytes: bytes):
        from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

        self._key = Ed25519PrivateKey.from_private_bytes(bytes(private_bytes))
        self._last = 0

    @classmethod
    def generate(cls) -> "ControlSigner":
        from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
        from cryptography.hazmat.primitives.serialization import (
            Encoding,
            NoEncryption,
            PrivateFormat,
        )

        raw = Ed25519PrivateKey.generate().private_bytes(Encoding.Raw, PrivateFormat.Raw,
                                                         NoEncryption())
        return cls(raw)

    def private_bytes(self) -> bytes:
        from cryptography.hazmat.primitives.serialization import (
            Encoding,
            NoEncryption,
            PrivateFormat,
        )

        return self._key.private_bytes(Encoding.Raw, PrivateFormat.Raw, NoEncryption())

    def public_bytes(self) -> bytes:
        from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

        return self._key.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)

    def sign(self, msg: dict, run: str) -> dict:
        """``msg`` with ``seq`` (growing microseconds) and ``sig`` (64 bytes) added."""
        seq = max(int(time.time() * 1e6), self._last + 1)
        self._last = seq
        out = dict(msg, seq=seq)
        out["sig"] = self._key.sign(canonical(out, run))
        return out


class ControlVerifier:
    """An agent's check of signed control messages (``public`` raw 32 bytes)."""

    def __init__(self, public_bytes: bytes, run: str, not_before: float | None = None):
        from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

        self._key = Ed25519PublicKey.from_public_bytes(bytes(public_bytes))
        self.run = run
        start = time.time() if not_before is None else not_before
        self.floor = int(max(0.0, start - MAX_SKEW_S) * 1e6)
        self.last: dict = {}              # kind -> last seq accepted

    def check(self, msg: dict, replay: bool = True) -> None:
        """Raise :class:`SignatureError` unless ``msg`` is signed, fresh and not replayed;
        then remember its ``seq``. With ``replay=False`` only the signature is checked (a
        recorder, which keeps the newest epoch anyway, also hears genuine re-sends)."""
        from cryptography.exceptions import InvalidSignature

        sig, seq = msg.get("sig"), msg.get("seq")
        if not isinstance(sig, (bytes, bytearray)) or len(sig) != 64:
            raise SignatureError("missing or not 64 bytes")
        if isinstance(seq, bool) or not isinstance(seq, int) or not 0 < seq < 2**62:
            raise SignatureError("seq missing or out of range")
        try:
            self._key.verify(bytes(sig), canonical(msg, self.run))
        except InvalidSignature:
            raise SignatureError("does not verify") from None
        if not replay:
            return
        kind = msg.get("kind")
        last = self.last.get(kind, 0)
        if seq <= last or seq < self.floor:
            raise SignatureError(f"seq {seq} is a replay (last {kind} accepted {last}, not "
                                 f"before {self.floor})")
        self.last[kind] = seq

    @staticmethod
    def age_s(msg: dict) -> float:
        seq = msg.get("seq")
        return math.inf if not isinstance(seq, int) else time.time() - seq / 1e6
