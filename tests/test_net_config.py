import argparse
import json

import pytest

from broker_free_net.config import (
    DEFAULT_LISTEN,
    InvalidNetConfig,
    NetConfig,
    add_net_arguments,
    build_zenoh_config,
    net_config_from_args,
)


def get(conf, key):
    return json.loads(conf.get_json(key))


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"run": ""}, "run"),
        ({"run": "a/b"}, "run"),
        ({"run": "a*"}, "run"),
        ({"run": 3}, "run"),
        ({"listen": "tcp/127.0.0.1:1"}, "listen"),
        ({"listen": ["127.0.0.1:7447"]}, "listen"),
        ({"connect": [None]}, "connect"),
        ({"connect": 5}, "connect"),
        ({"multicast": "yes"}, "multicast"),
        ({"lease_ms": 10}, "lease_ms"),
        ({"lease_ms": 1.5}, "lease_ms"),
        ({"lease_ms": True}, "lease_ms"),
        ({"config_file": "/nonexistent/zenoh.json5"}, "config_file"),
    ],
)
def test_invalid_field_is_named(kwargs, field):
    with pytest.raises(InvalidNetConfig) as info:
        NetConfig(**kwargs)
    assert info.value.field == field
    assert str(info.value).startswith(field)
    assert isinstance(info.value, ValueError)


def test_defaults_and_lists_become_tuples():
    net = NetConfig(connect=["tcp/127.0.0.1:7447"])
    assert net.listen == DEFAULT_LISTEN
    assert net.connect == ("tcp/127.0.0.1:7447",)
    hash(net)  # frozen, hashable


def test_build_overrides():
    net = NetConfig(run="r1", listen=("tcp/127.0.0.1:7001",), connect=("tcp/127.0.0.1:7002",), lease_ms=1500)
    conf = build_zenoh_config(net)
    assert get(conf, "mode") == "peer"
    assert get(conf, "listen/endpoints") == ["tcp/127.0.0.1:7001"]
    assert get(conf, "connect/endpoints") == ["tcp/127.0.0.1:7002"]
    assert get(conf, "scouting/multicast/enabled") is False
    assert get(conf, "scouting/gossip/enabled") is True
    assert get(conf, "transport/link/tx/lease") == 1500
    assert get(conf, "transport/link/tx/keep_alive") == 4
    assert get(conf, "transport/link/rx/max_message_size") == 1 << 20
    assert get(build_zenoh_config(NetConfig(multicast=True)), "scouting/multicast/enabled") is True


def test_config_file_passes_through_and_is_overridden(tmp_path):
    path = tmp_path / "z.json5"
    path.write_text("""{
      // a comment: json5
      mode: "client",
      transport: { unicast: { max_links: 2 } },
      scouting: { multicast: { enabled: true } },
    }""")
    conf = build_zenoh_config(NetConfig(config_file=str(path)))
    assert get(conf, "transport/unicast/max_links") == 2  # passed through
    assert get(conf, "mode") == "peer"  # overridden
    assert get(conf, "scouting/multicast/enabled") is False


def test_bad_config_file_names_field(tmp_path):
    path = tmp_path / "bad.json5"
    path.write_text("{ this is not json5")
    with pytest.raises(InvalidNetConfig) as info:
        build_zenoh_config(NetConfig(config_file=str(path)))
    assert info.value.field == "config_file"


def test_build_requires_netconfig():
    with pytest.raises(TypeError):
        build_zenoh_config({"run": "x"})


def test_argparse_helpers():
    parser = add_net_arguments(argparse.ArgumentParser())
    args = parser.parse_args(["--run", "exp1", "--listen", "tcp/127.0.0.1:7447",
                              "--connect", "tcp/127.0.0.1:7448", "--connect", "tcp/127.0.0.1:7449",
                              "--multicast", "--lease-ms", "2000"])
    net = net_config_from_args(args)
    assert net == NetConfig(run="exp1", listen=("tcp/127.0.0.1:7447",),
                            connect=("tcp/127.0.0.1:7448", "tcp/127.0.0.1:7449"), multicast=True, lease_ms=2000)
    default = net_config_from_args(parser.parse_args([]))
    assert default == NetConfig()
    with pytest.raises(InvalidNetConfig) as info:
        net_config_from_args(parser.parse_args(["--run", "a/b"]))
    assert info.value.field == "run"
