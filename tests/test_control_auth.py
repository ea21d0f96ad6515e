"""Signed control messages, as an agent decodes them from the wire."""

import time

import numpy as np
import pytest

from agent.protocol import wire
from agent.protocol.control_auth import ControlSigner, ControlVerifier, SignatureError


@pytest.fixture
def signer():
    return ControlSigner.generate()


def _assign(signer, run="r", epoch=1, agent=1):
    payload = wire.encode_ctl(agent, epoch, 10, ["7"], {2: 0.5}, 0.5, np.ones((14, 1)),
                              signer=signer, run=run)
    return payload, wire.decode(payload, wire.ctl_schema(14))


def test_a_genuine_assignment_verifies_once(signer):
    v = ControlVerifier(signer.public_bytes(), "r")
    _, msg = _assign(signer)
    v.check(msg)
    with pytest.raises(SignatureError, match="replay"):
        v.check(msg)


@pytest.mark.parametrize("change", [dict(epoch=2**62), dict(agent=2), dict(activate_at=11),
                                    dict(self_weight=0.4), "seq"])
def test_any_changed_field_fails(signer, change):
    v = ControlVerifier(signer.public_bytes(), "r")
    _, msg = _assign(signer)
    if change == "seq":
        change = dict(seq=msg["seq"] + 1)    # re-stamped to look newer
    msg = dict(msg, **change)
    with pytest.raises(SignatureError):
        v.check(msg)


def test_a_changed_gain_fails(signer):
    v = ControlVerifier(signer.public_bytes(), "r")
    _, msg = _assign(signer)
    msg["gain"] = msg["gain"] + 1e-12
    with pytest.raises(SignatureError, match="does not verify"):
        v.check(msg)


def test_another_run_another_key_or_no_signature_fail(signer):
    _, msg = _assign(signer, run="other")
    with pytest.raises(SignatureError, match="does not verify"):
        ControlVerifier(signer.public_bytes(), "r").check(msg)
    _, msg = _assign(ControlSigner.generate())
    with pytest.raises(SignatureError, match="does not verify"):
        ControlVerifier(signer.public_bytes(), "r").check(msg)
    msg = wire.decode(wire.encode_ctl(1, 1, 10, ["7"], {2: 0.5}, 0.5, np.ones((14, 1))),
                      wire.ctl_schema(14))
    with pytest.raises(SignatureError, match="missing"):
        ControlVerifier(signer.public_bytes(), "r").check(msg)


def test_an_agent_that_restarts_rejects_commands_older_than_its_start(signer):
    """A genuine command recorded earlier and replayed to an agent restarted since."""
    _, old = _assign(signer)
    restarted = ControlVerifier(signer.public_bytes(), "r", not_before=time.time() + 60)
    with pytest.raises(SignatureError, match="replay"):
        restarted.check(old)
    _, fresh = _assign(signer, epoch=2)
    ControlVerifier(signer.public_bytes(), "r").check(fresh)


def test_rosters_and_assignments_have_their_own_sequence(signer):
    """An assignment signed before a roster may arrive after it (another key)."""
    v = ControlVerifier(signer.public_bytes(), "r")
    _, asg = _assign(signer)
    roster = wire.decode(wire.encode_roster(1, 10, [1, 2], signer=signer, run="r"),
                         wire.roster_schema())
    v.check(roster)
    v.check(asg)


def test_signed_impairments_verify_and_forged_ones_fail():
    """The operator signs impairment changes on the transport's own wire form."""
    from broker_free_net.impair import decode_impairment, encode_impairment

    op = ControlSigner.generate()
    v = ControlVerifier(op.public_bytes(), "r")
    payload = encode_impairment("set", 2, 1, sign=lambda m: op.sign(m, "r"), drop=0,
                                partition=True)
    v.check(decode_impairment(payload))            # sent as 0, decoded as 0.0: one form
    forged = encode_impairment("set", 2, 1, sign=lambda m: ControlSigner.generate().sign(m, "r"),
                               partition=True)
    with pytest.raises(SignatureError, match="does not verify"):
        v.check(decode_impairment(forged))
    with pytest.raises(SignatureError, match="missing"):
        v.check(decode_impairment(encode_impairment("clear_all")))


def test_an_assignments_residual_tests_are_signed_with_it(signer):
    """The residual tests an assignment carries verify as the monitor signed them; a
    threshold raised by an outsider (to hide a lie) does not."""
    v = ControlVerifier(signer.public_bytes(), "r")
    tests = {"window": 8, "warmup": 40, "tests": [
        {"from": 0, "age": 0, "whiten": np.full((1, 1), 0.5), "alpha": 3e-7,
         "threshold": 27.5},
        {"from": 2, "age": 2, "whiten": np.eye(14)[:12], "alpha": 3e-7, "threshold": 60.1,
         "null": np.eye(14)[:, 12:], "null_floor": 1e-9, "null_threshold": 30.2}]}
    payload = wire.encode_ctl(1, 1, 10, ["7"], {2: 0.5}, 0.5, np.ones((14, 1)),
                              signer=signer, run="r", residuals=tests)
    msg = wire.decode(payload, wire.ctl_schema(14))
    v.check(dict(msg), replay=False)
    msg["residuals"]["tests"][1]["threshold"] = 6.0e9
    with pytest.raises(SignatureError, match="does not verify"):
        v.check(msg)
