import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.protocol import topics
from broker_free_net.keys import InvalidKey


def test_builders():
    assert topics.est_key("r", 3) == "socmon/r/est/3"
    assert topics.ctl_key("r", 0) == "socmon/r/ctl/0"
    assert topics.status_key("r", 12) == "socmon/r/status/12"
    assert topics.sensors_key("r") == "socmon/r/sensors"
    assert topics.truth_key("r") == "socmon/r/truth"
    assert topics.impair_key("r") == "socmon/r/impair"
    assert topics.alive_key("r", "agent", 4, "z1") == "socmon/r/alive/agent/4/z1"
    assert topics.alive_key("r", "world", "w", "z2") == "socmon/r/alive/world/w/z2"
    assert topics.alive_pattern("r") == "socmon/r/alive/**"
    assert topics.any_agent_pattern("r", "est") == "socmon/r/est/*"
    with pytest.raises(InvalidKey):
        topics.any_agent_pattern("r", "sensor")


@pytest.mark.parametrize("bad", ["", "a*", "a$b", "a/b", "#", "x?", "@x", "a b", "a\nb", 5, None])
def test_bad_chunks(bad):
    with pytest.raises(InvalidKey) as info:
        topics.alive_key("r", bad, 1, "z")
    assert info.value.field == "role"
    with pytest.raises(InvalidKey) as info:
        topics.alive_key("r", "agent", 1, bad)
    assert info.value.field == "session"
    with pytest.raises(InvalidKey) as info:
        topics.truth_key(bad)
    assert info.value.field == "run"


@pytest.mark.parametrize("bad", [-1, True, "3", 1.0])
def test_bad_agent_ids(bad):
    with pytest.raises(InvalidKey) as info:
        topics.est_key("r", bad)
    assert info.value.field == "agent"


def test_parsers():
    assert topics.parse_agent_key("r", "est", "socmon/r/est/7") == 7
    assert topics.parse_alive_key("r", "socmon/r/alive/agent/7/ab") == ("agent", "7", "ab")


@pytest.mark.parametrize("key", [
    "socmon/r/est", "socmon/r/est/", "socmon/r/est/07", "socmon/r/est/-1", "socmon/r/est/x",
    "socmon/r/est/1/2", "socmon/other/est/1", "soc/r/est/1", "socmon/r/ctl/1", "socmon/r/est/*",
    "socmon/r/est/1234567890", "socmon/r/est/\u0663",
])
def test_parse_agent_rejects(key):
    with pytest.raises(InvalidKey):
        topics.parse_agent_key("r", "est", key)


@pytest.mark.parametrize("key", [
    "socmon/r/alive/agent", "socmon/r/alive/agent/1", "socmon/r/alive/agent/1/x/y",
    "socmon/r/alive//1/x", "socmon/r/alive/agent/*/x", "socmon/r/alive/agent/1/*",
    "socmon/r/alive/agent/@1/x", "socmon/q/alive/agent/1/x", "socmon/r/est/agent/1/x",
])
def test_parse_alive_rejects(key):
    with pytest.raises(InvalidKey):
        topics.parse_alive_key("r", key)


@given(agent=st.integers(0, 10**9 - 1))
@settings(deadline=None)
def test_agent_round_trip(agent):
    for kind in topics.AGENT_KINDS:
        assert topics.parse_agent_key("run1", kind, topics.agent_key("run1", kind, agent)) == agent


@given(text=st.text(max_size=20))
@settings(deadline=None)
def test_parse_never_raises_other_errors(text):
    for parse in (lambda k: topics.parse_alive_key("r", k), lambda k: topics.parse_agent_key("r", "est", k)):
        try:
            parse("socmon/r/" + text)
        except InvalidKey:
            pass


def test_token_keys_take_the_callers_prefix():
    """The transport lays out liveliness tokens under any prefix; socmon's is alive_prefix."""
    from broker_free_net.keys import parse_token_key, token_key, token_pattern

    assert token_key("app/x/live", "node", 2, "z") == "app/x/live/node/2/z"
    assert token_pattern("app/x/live") == "app/x/live/**"
    assert parse_token_key("app/x/live", "app/x/live/node/2/z") == ("node", "2", "z")
    for bad in ("app/x/live/node/2", "app/y/live/node/2/z", "app/x/live/node/2/z/w"):
        with pytest.raises(InvalidKey):
            parse_token_key("app/x/live", bad)
    assert topics.alive_prefix("r") == "socmon/r/alive"
    assert token_key(topics.alive_prefix("r"), "agent", 4, "z1") == topics.alive_key("r", "agent", 4, "z1")
