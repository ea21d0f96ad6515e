"""Key material and secure configs (no network): certificates checked with the
``cryptography`` package as an independent verifier, ACL rules against hand-written tables."""

import json
import os
import shutil
import stat

import pytest
import zenoh
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.x509.oid import NameOID

from agent.protocol.topics import (
    access_control,
    identity_name,
    make_run_keys,
    parse_identity,
    put_keys,
    run_identities,
)
from broker_free_net.config import InvalidNetConfig, NetConfig, build_zenoh_config
from broker_free_net.security import InvalidKeys, Permissions, build_access_control, load_fragment, load_key_set


@pytest.fixture(scope="module")
def keyset(tmp_path_factory):
    return make_run_keys(tmp_path_factory.mktemp("k") / "keys", "r1", run_identities(3))


def cert_of(path):
    return x509.load_pem_x509_certificate(path.read_bytes())


def cn(cert):
    return cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value


def test_identities():
    assert run_identities(3) == ("world", "agent-1", "agent-2", "agent-3", "monitor", "operator", "recorder")
    for name in run_identities(3):
        assert identity_name(*parse_identity(name)) == name
    for bad in ("agent-0", "agent-01", "agent", "agent-x", "root", "", "agent-1 "):
        with pytest.raises(InvalidKeys):
            parse_identity(bad)
    with pytest.raises(InvalidKeys, match="id"):
        identity_name("agent", 0)
    with pytest.raises(InvalidKeys, match="agents"):
        run_identities(0)


def test_put_rights_table():
    p = "socmon/r"
    assert put_keys("r", "world") == [f"{p}/sensors", f"{p}/truth", f"{p}/end"]
    assert put_keys("r", "agent-7") == [f"{p}/est/7", f"{p}/status/7"]
    assert put_keys("r", "monitor") == [f"{p}/ctl/*", f"{p}/monitor/**"]
    assert put_keys("r", "operator") == [f"{p}/impair"]
    assert put_keys("r", "recorder") == []


def _allowed(acl, subject, message, flow):
    """Key expressions `subject` is allowed (message, flow) by the policies."""
    rules = {r["id"]: r for r in acl["rules"]}
    out = []
    for pol in acl["policies"]:
        if subject in pol["subjects"]:
            for rid in pol["rules"]:
                r = rules[rid]
                if r["permission"] == "allow" and message in r["messages"] and flow in r["flows"]:
                    out += r["key_exprs"]
    return sorted(out)


def test_access_control_denies_by_default_and_grants_each_its_own():
    names = run_identities(2)
    acl = access_control("r", names)
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert not [r for r in acl["rules"] if r["permission"] != "allow"]
    assert sorted(s["id"] for s in acl["subjects"]) == sorted(names)
    assert all(s["cert_common_names"] == [s["id"]] for s in acl["subjects"])
    for kind in ("rules", "subjects", "policies"):
        ids = [x["id"] for x in acl[kind]]
        assert len(ids) == len(set(ids)), kind
    assert _allowed(acl, "agent-2", "put", "ingress") == ["socmon/r/est/2", "socmon/r/status/2"]
    assert _allowed(acl, "world", "put", "ingress") == ["socmon/r/end", "socmon/r/sensors",
                                                         "socmon/r/truth"]
    assert _allowed(acl, "recorder", "put", "ingress") == []
    assert _allowed(acl, "agent-1", "liveliness_token", "ingress") == ["socmon/r/alive/agent/1/*"]
    for name in names:  # subscriptions in both directions, own puts and tokens out
        assert _allowed(acl, name, "declare_subscriber", "ingress") == ["socmon/r/**"]
        assert _allowed(acl, name, "declare_subscriber", "egress") == ["socmon/r/**"]
        assert _allowed(acl, name, "put", "egress") == ["socmon/r/**"]
        # queries in the run (a late subscriber asks the publishers' caches)...
        assert _allowed(acl, name, "query", "ingress") == ["socmon/r/**/@adv/**"]
        assert _allowed(acl, name, "delete", "ingress") == []
    # ... answered by an agent's own estimate cache only
    assert _allowed(acl, "agent-2", "declare_queryable", "ingress") == [
        "socmon/r/est/2", "socmon/r/est/2/@adv/**"]
    assert _allowed(acl, "agent-2", "reply", "ingress") == ["socmon/r/est/2",
                                                           "socmon/r/est/2/@adv/**"]
    for name in ("world", "monitor", "operator", "recorder"):
        assert _allowed(acl, name, "reply", "ingress") == []
    with pytest.raises(InvalidKeys, match="twice"):
        access_control("r", ["world", "world"])


def test_the_transport_builds_the_acl_from_the_callers_table():
    acl = build_access_control("app/r/**", {"hub": Permissions(tokens=("app/r/alive/hub/*",)),
                                            "n-1": Permissions(put=("app/r/x/1",))})
    assert _allowed(acl, "n-1", "put", "ingress") == ["app/r/x/1"]
    assert _allowed(acl, "hub", "put", "ingress") == []
    assert _allowed(acl, "hub", "liveliness_token", "ingress") == ["app/r/alive/hub/*"]
    assert _allowed(acl, "n-1", "declare_subscriber", "ingress") == ["app/r/**"]
    assert [p["id"] for p in acl["policies"]] == ["run", "own-hub", "own-n-1"]
    with pytest.raises(InvalidKeys, match="names"):
        build_access_control("app/r/**", {})
    with pytest.raises(InvalidKeys, match="name"):
        build_access_control("app/r/**", {"a b": Permissions()})


def test_certificates_are_signed_by_the_run_ca_and_name_the_process(keyset):
    ca = cert_of(keyset.ca)
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca is True
    for name in keyset.names:
        cert = cert_of(keyset.cert(name))
        assert cn(cert) == name
        cert.verify_directly_issued_by(ca)  # raises if not signed by the CA
        assert cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca is False
        key = serialization.load_pem_private_key(keyset.key(name).read_bytes(), password=None)
        assert key.public_key().public_numbers() == cert.public_key().public_numbers()
        assert stat.S_IMODE(os.stat(keyset.key(name)).st_mode) == 0o600
    assert not list(keyset.dir.glob("ca*key*"))  # the CA's private key is not kept


def test_another_run_ca_does_not_vouch_for_these_certificates(keyset, tmp_path):
    other = make_run_keys(tmp_path / "other", "r1", run_identities(1))
    with pytest.raises(Exception):
        cert_of(keyset.cert("agent-1")).verify_directly_issued_by(cert_of(other.ca))


def test_manifest_and_fragments(keyset):
    ks = load_key_set(keyset.dir)
    assert ks == keyset
    for name in keyset.names:
        text = keyset.config(name).read_text()
        frag = load_fragment(keyset.dir, name, "r1")
        tls = frag["transport"]["link"]["tls"]
        assert tls["enable_mtls"] is True
        assert tls["listen_certificate"] == str(keyset.cert(name)) == tls["connect_certificate"]
        assert tls["root_ca_certificate"] == str(keyset.ca)
        assert frag["transport"]["link"]["protocols"] == ["tls"]
        assert frag["connect"]["exit_on_failure"] is True and frag["connect"]["timeout_ms"] > 0
        assert frag["access_control"] == access_control("r1", keyset.names)
        zenoh.Config.from_json5(text)  # the file as written is a valid zenoh config
    with pytest.raises(InvalidKeys, match="run 'r1'"):
        load_fragment(keyset.dir, "world", "r2")
    with pytest.raises(InvalidKeys, match="agent-9"):
        load_fragment(keyset.dir, "agent-9")


def test_copied_key_set_uses_its_own_paths(keyset, tmp_path):
    copy = tmp_path / "elsewhere"
    shutil.copytree(keyset.dir, copy)
    tls = load_fragment(copy, "agent-2")["transport"]["link"]["tls"]
    for k in ("root_ca_certificate", "listen_private_key", "listen_certificate",
              "connect_private_key", "connect_certificate"):
        assert tls[k].startswith(str(copy.resolve())), k


def test_make_refuses_to_overwrite_and_checks_arguments(keyset, tmp_path):
    with pytest.raises(InvalidKeys, match="dir"):
        make_run_keys(keyset.dir, "r1", run_identities(1))
    for kwargs, field in (({"run": "a/b"}, "run"), ({"port_base": 0}, "port_base"),
                          ({"valid_days": 0}, "valid_days"), ({"hosts": ()}, "hosts")):
        args = {"run": "r", **kwargs}
        with pytest.raises(InvalidKeys) as info:
            make_run_keys(tmp_path / field, args.pop("run"), run_identities(1), **args)
        assert info.value.field == field
        assert not (tmp_path / field).exists()


def test_port_base_writes_endpoints(tmp_path):
    ks = make_run_keys(tmp_path / "k", "r", run_identities(1), port_base=7400)
    assert load_fragment(ks.dir, "world")["listen"]["endpoints"] == ["tls/127.0.0.1:7400"]
    agent = load_fragment(ks.dir, "agent-1")
    assert agent["listen"]["endpoints"] == ["tls/127.0.0.1:7401"]
    assert agent["connect"]["endpoints"] == ["tls/127.0.0.1:7400"]
    net = NetConfig(keys=ks.dir, identity="agent-1")
    assert net.listen == ("tls/127.0.0.1:7401",) and net.connect == ("tls/127.0.0.1:7400",)


def test_netconfig_with_keys(keyset):
    net = NetConfig(keys=keyset.dir, identity="agent-2")
    assert net.run == "r1"  # from the key set
    assert net.listen == ("tls/127.0.0.1:0",)
    conf = build_zenoh_config(net)

    def get(key):
        return json.loads(conf.get_json(key))

    assert get("access_control/enabled") is True
    assert get("access_control/default_permission") == "deny"
    assert get("transport/link/tls/enable_mtls") is True
    assert get("transport/link/tls/listen_certificate") == str(keyset.cert("agent-2"))
    assert get("transport/link/protocols") == ["tls"]
    assert get("connect/exit_on_failure") is True
    assert get("listen/endpoints") == ["tls/127.0.0.1:0"]
    assert get("mode") == "peer"
    for kwargs, field in (({"listen": ["tcp/127.0.0.1:7000"]}, "listen"),
                          ({"connect": ["tcp/127.0.0.1:7000"]}, "connect"),
                          ({"run": "r2"}, "keys"),
                          ({"identity": "agent-4"}, "keys"),
                          ({"identity": "root"}, "keys"),
                          ({"identity": None}, "identity")):
        with pytest.raises(InvalidNetConfig) as info:
            NetConfig(**{"keys": keyset.dir, "identity": "agent-2", **kwargs})
        assert info.value.field == field, kwargs


def test_keys_cli(tmp_path, capsys):
    from agent.cli.main import main

    assert main(["keys", "init", str(tmp_path / "k"), "--scenario", "paper-14", "--run", "demo", "--json"]) == 0
    manifest = json.loads(capsys.readouterr().out)
    from design.scenario import load_scenario

    sc = load_scenario("paper-14")
    M = sc.N + sc.standby
    assert manifest["names"] == list(run_identities(M)) and manifest["run"] == "demo"
    assert main(["keys", "show", str(tmp_path / "k")]) == 0
    assert "run demo" in capsys.readouterr().out
    assert main(["keys", "init", str(tmp_path / "k"), "--scenario", "paper-14"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("socmon: DIR:") and err.count("\n") == 1
    assert main(["keys", "show", str(tmp_path / "none")]) == 2
    assert capsys.readouterr().err.startswith("socmon: DIR: no such directory")


def _agent_options(argv):
    import argparse

    from agent.cli import _common
    from agent.cli.agent_cmd import add_arguments
    from agent.run.agent_options import agent_options

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return agent_options(parser.parse_args(argv), net_config_arg=_common.net_config_arg,
                         parse_int=_common.parse_int)


def test_a_key_set_records_its_scenario_and_refuses_another(tmp_path, capsys):
    """Keys made for paper-14 start paper-14's agents, not paper-14-live's (same agents,
    another A): the error names both scenarios."""
    from agent.cli.main import main
    from agent.run.inputs import InputError

    keys = tmp_path / "k"
    assert main(["keys", "init", str(keys), "--scenario", "paper-14", "--run", "demo", "--json"]) == 0
    manifest = json.loads(capsys.readouterr().out)
    assert manifest["scenario"] == "paper-14" and manifest["agents"] == 3
    assert main(["keys", "show", str(keys)]) == 0
    assert "made for scenario paper-14 (digest " in capsys.readouterr().out
    # the standby agent (id 4): no gain to design before the keys are read
    options = _agent_options(["paper-14", "--id", "4", "--keys", str(keys)])
    assert options.net.keys == str(keys.resolve())
    assert capsys.readouterr().err == ""
    with pytest.raises(InputError, match=r"^--keys: .* was made for scenario paper-14 \(digest "
                                         r".*\), not for scenario paper-14-live \(digest "):
        _agent_options(["paper-14-live", "--id", "4", "--keys", str(keys)])


def test_a_key_set_without_its_scenario_is_used_with_a_warning(tmp_path, capsys):
    """A key set made before key sets recorded their scenario still starts a process, and
    stderr says it was not checked."""
    ks = make_run_keys(tmp_path / "k", "demo", run_identities(4))
    assert load_key_set(ks.dir).about == {}
    options = _agent_options(["paper-14-live", "--id", "4", "--keys", str(ks.dir)])
    assert options.net.keys == str(ks.dir)
    err = capsys.readouterr().err
    assert err.startswith("warning: --keys: ") and "scenario paper-14-live" in err
    assert "socmon keys init" in err and err.count("\n") == 1
