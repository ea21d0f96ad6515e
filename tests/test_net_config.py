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
        ({"listen": ["tcp/127.0.0.1:99999"]}, "listen"),
        ({"connect": ["tls/10.0.0.5:70000#iface=eth0"]}, "connect"),
        ({"connect": [None]}, "connect"),
        ({"connect": 5}, "connect"),
        ({"multicast": "yes"}, "multicast"),
        ({"lease_ms": 10}, "lease_ms"),
        ({"lease_ms": 1.5}, "lease_ms"),
        ({"lease_ms": True}, "lease_ms"),
        ({"zenoh_config": "/nonexistent/zenoh.json5"}, "zenoh_config"),
        ({"mode": "router"}, "mode"),
        ({"identity": "agent-1"}, "keys"),
        ({"keys": "/nonexistent/keys"}, "identity"),
        ({"keys": "/nonexistent/keys", "identity": "agent-1"}, "keys"),
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
    assert get(conf, "transport/shared_memory/enabled") is False
    assert get(build_zenoh_config(NetConfig(multicast=True)), "scouting/multicast/enabled") is True


def test_config_file_passes_through_and_is_overridden(tmp_path):
    path = tmp_path / "z.json5"
    path.write_text("""{
      // a comment: json5
      mode: "client",
      transport: { unicast: { max_links: 2 } },
      scouting: { multicast: { enabled: true } },
    }""")
    conf = build_zenoh_config(NetConfig(zenoh_config=str(path), mode="peer", multicast=False))
    assert get(conf, "transport/unicast/max_links") == 2  # passed through
    assert get(conf, "mode") == "peer"  # overridden: given
    assert get(conf, "scouting/multicast/enabled") is False


FILE_WITH_ENDPOINTS = """{
  mode: "client",
  listen: { endpoints: ["tcp/127.0.0.1:7001"] },
  connect: { endpoints: { client: ["tcp/127.0.0.1:7002"], peer: ["tcp/127.0.0.1:7009"] } },
  scouting: { multicast: { enabled: true }, gossip: { enabled: false } },
  transport: { link: { tx: { lease: 3000, keep_alive: 2 } } },
}"""


def test_config_file_values_are_kept_where_no_flag_is_given(tmp_path):
    path = tmp_path / "z.json5"
    path.write_text(FILE_WITH_ENDPOINTS)
    net = NetConfig(zenoh_config=str(path))
    # the fields hold what the session will use: the file's values
    assert net.mode == "client"
    assert net.listen == ("tcp/127.0.0.1:7001",)
    assert net.connect == ("tcp/127.0.0.1:7002",)  # the entry of the file's mode
    assert net.multicast is True and net.lease_ms == 3000
    conf = build_zenoh_config(net)
    assert get(conf, "mode") == "client"
    assert get(conf, "listen/endpoints") == ["tcp/127.0.0.1:7001"]
    assert get(conf, "connect/endpoints") == ["tcp/127.0.0.1:7002"]
    assert get(conf, "transport/link/tx/lease") == 3000
    assert get(conf, "transport/link/tx/keep_alive") == 2  # socmon's 4 only where unset
    assert get(conf, "scouting/gossip/enabled") is False
    assert get(conf, "transport/link/rx/max_message_size") == 1 << 20  # unset in the file


def test_flags_override_the_file_only_where_given(tmp_path):
    path = tmp_path / "z.json5"
    path.write_text(FILE_WITH_ENDPOINTS)
    parser = add_net_arguments(argparse.ArgumentParser())
    net = net_config_from_args(parser.parse_args(["--zenoh-config", str(path), "--listen", "tcp/127.0.0.1:7100"]))
    assert net.listen == ("tcp/127.0.0.1:7100",)  # given
    assert net.connect == ("tcp/127.0.0.1:7002",) and net.mode == "client" and net.lease_ms == 3000  # kept
    net = net_config_from_args(parser.parse_args(["--zenoh-config", str(path), "--lease-ms", "500"]))
    assert net.lease_ms == 500 and net.listen == ("tcp/127.0.0.1:7001",)


def test_file_endpoint_errors_name_the_file(tmp_path):
    path = tmp_path / "z.json5"
    path.write_text('{ listen: { endpoints: ["127.0.0.1:7001"] } }')
    with pytest.raises(InvalidNetConfig) as info:
        NetConfig(zenoh_config=str(path))
    assert info.value.field == "zenoh_config"
    assert "127.0.0.1:7001" in str(info.value) and "line 1" in str(info.value)
    assert ".rs:" not in str(info.value)


@pytest.mark.parametrize("text", ["{ this is not json5", "{ mode: \"peer\", ", "[1, 2"])
def test_bad_config_file_is_named_at_construction_in_one_line(tmp_path, text):
    path = tmp_path / "bad.json5"
    path.write_text(text)
    with pytest.raises(InvalidNetConfig) as info:
        NetConfig(zenoh_config=str(path))
    assert info.value.field == "zenoh_config"
    assert "\n" not in str(info.value) and str(path) in str(info.value)
    assert ".rs:" not in str(info.value)  # no location inside zenoh's sources


@pytest.mark.parametrize("content", [None, "{ nope"])
def test_cli_reports_zenoh_config_in_one_line_exit_2(tmp_path, capsys, content):
    from agent.cli.main import main

    path = tmp_path / "z.json5"
    if content is not None:
        path.write_text(content)
    status = main(["inject", "clear-all", "--connect", "tcp/127.0.0.1:9", "--zenoh-config", str(path)])
    err = capsys.readouterr().err
    assert status == 2
    assert err.startswith("socmon: --zenoh-config:") and err.count("\n") == 1, err
    assert "Traceback" not in err


def test_help_says_which_keys_socmon_sets(capsys):
    parser = add_net_arguments(argparse.ArgumentParser())
    text = parser.format_help()
    for key in ("mode", "listen/endpoints", "connect/endpoints", "scouting/multicast/enabled",
                "transport/link/tx/lease", "scouting/gossip/enabled", "transport/link/tx/keep_alive",
                "transport/link/rx/max_message_size", "--keys"):
        assert key in " ".join(text.split()), key


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


def test_keys_flag_needs_an_identity(tmp_path):
    from agent.protocol.topics import make_run_keys, run_identities

    ks = make_run_keys(tmp_path / "k", "r9", run_identities(1))
    parser = add_net_arguments(argparse.ArgumentParser())
    args = parser.parse_args(["--keys", str(ks.dir)])
    with pytest.raises(InvalidNetConfig) as info:
        net_config_from_args(args)
    assert info.value.field == "keys"
    net = net_config_from_args(args, identity="agent-1")
    assert (net.run, net.identity, net.listen) == ("r9", "agent-1", ("tls/127.0.0.1:0",))


def test_a_tls_endpoint_without_keys_is_refused_naming_the_flag():
    """Without keys (or a zenoh config file of the user's) nothing gives the session a
    certificate: a tls/ endpoint could never link, and zenoh would retry it in silence."""
    with pytest.raises(InvalidNetConfig) as caught:
        NetConfig(run="r", connect=("tls/127.0.0.1:7447",))
    assert caught.value.as_flag() == ("--connect: 'tls/127.0.0.1:7447': a tls/ endpoint needs "
                                      "the run's keys (--keys DIR, or --attach of a --secure "
                                      "run)")
