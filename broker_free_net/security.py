"""Key material of a secured run: a CA, one certificate per process, zenoh TLS + ACL configs.

The secure mode uses zenoh's own mechanisms only: TLS links with mutual authentication
(every process presents a certificate signed by the run's CA) and zenoh's ``access_control``
with ``default_permission: "deny"`` on every peer. The subject of a rule is the common name
(CN) of the remote certificate, so a message is accepted only if the process that sent it
over the link holds the credentials of a role allowed to publish that key.

Processes and their names (the CN of their certificate)::

    world        puts socmon/<run>/sensors, socmon/<run>/truth, socmon/<run>/end
    agent-<i>    puts socmon/<run>/est/<i>, socmon/<run>/status/<i>
    monitor      puts socmon/<run>/ctl/*, socmon/<run>/monitor/**
    operator     puts socmon/<run>/impair          (socmon inject)
    recorder     puts nothing                       (socmon up's recorder, socmon watch)

Everyone may subscribe to any key of the run and watch liveliness; a process may declare
only its own liveliness token (``socmon/<run>/alive/<role>/<id>/<zid>`` of its role; the
last chunk is the declaring session's zid, any value the identity chooses).

Layout of a key directory made by :func:`make_run_keys`::

    DIR/keys.json            manifest: run, names, CA fingerprint, validity
    DIR/ca.pem               the run's CA certificate (its private key is never written)
    DIR/<name>/cert.pem      certificate of <name>, CN = <name>, signed by the CA
    DIR/<name>/key.pem       its private key (PKCS#8, mode 0600)
    DIR/<name>/zenoh.json5   the zenoh config fragment of <name>: TLS, mTLS, ACL, connect policy

This module makes and reads files only; it never opens a zenoh session and does not
import zenoh (the caller turns the fragment into a ``zenoh.Config``).
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

__all__ = [
    "CONNECT_TIMEOUT_MS",
    "FRAGMENT_NAME",
    "MANIFEST_NAME",
    "ROLES",
    "InvalidKeys",
    "KeySet",
    "access_control",
    "identity_name",
    "load_fragment",
    "load_key_set",
    "make_run_keys",
    "parse_identity",
    "put_keys",
    "run_identities",
]

#: The process roles of a run (the CN of a certificate is the role, or ``agent-<i>``).
ROLES = ("world", "agent", "monitor", "operator", "recorder")
#: How long a secured process keeps trying its connect endpoints before ``zenoh.open``
#: fails (``connect/timeout_ms``, with ``connect/exit_on_failure: true``). zenoh's peer
#: default is to retry forever in the background and run disconnected.
CONNECT_TIMEOUT_MS = 10_000
MANIFEST_NAME = "keys.json"
FRAGMENT_NAME = "zenoh.json5"
CA_NAME = "ca.pem"
CERT_NAME = "cert.pem"
KEY_NAME = "key.pem"
#: Validity of the certificates of a run (keys are made per run).
DEFAULT_VALID_DAYS = 30
MANIFEST_VERSION = 1

_AGENT_RE = re.compile(r"^agent-([1-9][0-9]{0,8})$")
_RUN_RE = re.compile(r"^[A-Za-z0-9_.\-]+$")
#: Liveliness roles (``Peer(net, role, id)``) each identity may declare a token for.
_TOKEN_ROLES = {"world": ("world",), "monitor": ("monitor",), "operator": ("inject", "operator"),
                "recorder": ("recorder", "watch")}


class InvalidKeys(ValueError):
    """Key material is missing, malformed or does not match the run.

    Attributes
    ----------
    field : str
        What is wrong (``"keys"``, ``"name"``, ``"run"``, ``"agents"``, ...).
    """

    def __init__(self, field: str, message: str):
        self.field = field
        super().__init__(f"{field}: {message}")


# --------------------------------------------------------------------------- identities


def identity_name(role: str, id=None) -> str:
    """The certificate name of a process: ``"agent-3"`` for an agent, else the role.

    >>> identity_name("agent", 3), identity_name("world"), identity_name("operator")
    ('agent-3', 'world', 'operator')
    """
    if role not in ROLES:
        raise InvalidKeys("role", f"{role!r} is not one of {', '.join(ROLES)}")
    if role == "agent":
        if isinstance(id, bool) or not isinstance(id, int) or id < 1:
            raise InvalidKeys("id", f"an agent needs a positive int id, got {id!r}")
        return f"agent-{id}"
    return role


def parse_identity(name: str) -> tuple[str, int | None]:
    """``"agent-3"`` -> ``("agent", 3)``; ``"world"`` -> ``("world", None)``.

    >>> parse_identity("agent-12"), parse_identity("monitor")
    (('agent', 12), ('monitor', None))
    """
    if not isinstance(name, str):
        raise InvalidKeys("name", f"expected str, got {type(name).__name__}")
    m = _AGENT_RE.match(name)
    if m:
        return "agent", int(m.group(1))
    if name in ROLES and name != "agent":
        return name, None
    raise InvalidKeys("name", f"{name!r} is not a process name (world, agent-<i>, monitor, operator, recorder)")


def run_identities(n_agents: int) -> tuple[str, ...]:
    """Every process name of a run with agents 1..`n_agents` (active and standby).

    >>> run_identities(2)
    ('world', 'agent-1', 'agent-2', 'monitor', 'operator', 'recorder')
    """
    if isinstance(n_agents, bool) or not isinstance(n_agents, int) or n_agents < 1:
        raise InvalidKeys("agents", f"expected a positive int, got {n_agents!r}")
    return ("world", *(f"agent-{i}" for i in range(1, n_agents + 1)), "monitor", "operator", "recorder")


def _check_run(run) -> str:
    if not isinstance(run, str) or not _RUN_RE.match(run):
        raise InvalidKeys("run", f"invalid run id {run!r} (letters, digits, '_', '.', '-')")
    return run


def put_keys(run: str, name: str) -> list[str]:
    """Key expressions process `name` may put (publish) in run `run`.

    >>> put_keys("r", "agent-2")
    ['socmon/r/est/2', 'socmon/r/status/2']
    >>> put_keys("r", "recorder")
    []
    """
    _check_run(run)
    role, i = parse_identity(name)
    p = f"socmon/{run}"
    return {
        "world": [f"{p}/sensors", f"{p}/truth", f"{p}/end"],
        "agent": [f"{p}/est/{i}", f"{p}/status/{i}"],
        "monitor": [f"{p}/ctl/*", f"{p}/monitor/**"],
        "operator": [f"{p}/impair"],
        "recorder": [],
    }[role]


def token_keys(run: str, name: str) -> list[str]:
    """Liveliness tokens process `name` may declare.

    >>> token_keys("r", "agent-2"), token_keys("r", "operator")
    (['socmon/r/alive/agent/2/*'], ['socmon/r/alive/inject/*/*', 'socmon/r/alive/operator/*/*'])
    """
    _check_run(run)
    role, i = parse_identity(name)
    if role == "agent":
        return [f"socmon/{run}/alive/agent/{i}/*"]
    return [f"socmon/{run}/alive/{r}/*/*" for r in _TOKEN_ROLES[role]]


def access_control(run: str, names) -> dict:
    """The zenoh ``access_control`` block of every process of a run.

    Default deny in both directions. Ingress: a subject (certificate CN) may put only its
    :func:`put_keys` and declare only its :func:`token_keys`; every subject of the run may
    declare subscribers and liveliness subscribers and query liveliness on ``socmon/<run>/**``
    (without that the publishers would not learn whom to send to). Egress: everything of
    the run may go to the subjects of the run, so that this process's own puts, tokens and
    subscriptions leave it. Nothing is allowed to or from a link without a certificate of
    the run; queries, replies and deletes are denied.
    """
    _check_run(run)
    names = list(names)
    if not names:
        raise InvalidKeys("names", "no process names")
    for n in names:
        parse_identity(n)
    if len(set(names)) != len(names):
        raise InvalidKeys("names", "a name is listed twice")
    run_ke = f"socmon/{run}/**"
    rules = [
        {"id": "egress-run", "permission": "allow", "flows": ["egress"],
         "messages": ["put", "declare_subscriber", "liveliness_token", "liveliness_query",
                      "declare_liveliness_subscriber"],
         "key_exprs": [run_ke]},
        {"id": "ingress-subscribe", "permission": "allow", "flows": ["ingress"],
         "messages": ["declare_subscriber", "liveliness_query", "declare_liveliness_subscriber"],
         "key_exprs": [run_ke]},
    ]
    subjects = [{"id": n, "cert_common_names": [n]} for n in names]
    policies = [{"id": "run", "rules": ["egress-run", "ingress-subscribe"], "subjects": list(names)}]
    for n in names:
        own = [f"token-{n}"]
        rules.append({"id": f"token-{n}", "permission": "allow", "flows": ["ingress"],
                      "messages": ["liveliness_token"], "key_exprs": token_keys(run, n)})
        keys_ = put_keys(run, n)
        if keys_:
            rules.append({"id": f"put-{n}", "permission": "allow", "flows": ["ingress"],
                          "messages": ["put"], "key_exprs": keys_})
            own.append(f"put-{n}")
        policies.append({"id": f"own-{n}", "rules": own, "subjects": [n]})
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}


# --------------------------------------------------------------------------- key material


@dataclass(frozen=True)
class KeySet:
    """The key material of one run, as laid out in a directory.

    Attributes
    ----------
    dir : Path
        The key directory.
    run : str
        Run id the keys and the ACL are for.
    names : tuple of str
        Process names that have a certificate.
    ca_fingerprint : str
        SHA-256 of the CA certificate (hex), to compare key sets across machines.
    not_after : str
        Expiry of the certificates (ISO 8601, UTC).
    """

    dir: Path
    run: str
    names: tuple[str, ...]
    ca_fingerprint: str
    not_after: str

    @property
    def ca(self) -> Path:
        return self.dir / CA_NAME

    def _member(self, name: str) -> Path:
        parse_identity(name)
        if name not in self.names:
            raise InvalidKeys("name", f"no credentials for {name!r} in {self.dir} "
                                      f"(has {', '.join(self.names)})")
        return self.dir / name

    def cert(self, name: str) -> Path:
        """Certificate of process `name`."""
        return self._member(name) / CERT_NAME

    def key(self, name: str) -> Path:
        """Private key of process `name`."""
        return self._member(name) / KEY_NAME

    def config(self, name: str) -> Path:
        """zenoh json5 config fragment of process `name`."""
        return self._member(name) / FRAGMENT_NAME


def _tls_block(ca: Path, cert: Path, key: Path) -> dict:
    return {
        "root_ca_certificate": str(ca),
        "listen_private_key": str(key),
        "listen_certificate": str(cert),
        "connect_private_key": str(key),
        "connect_certificate": str(cert),
        "enable_mtls": True,
        # Every certificate of the run is signed by the run's own CA and names a process,
        # not a host; which process may do what is decided by the ACL on the CN. Checking
        # the peer's address against the certificate would tie a key set to the machines'
        # addresses (and to every address a peer advertises by gossip) for no added trust.
        "verify_name_on_connect": False,
        "close_link_on_expiration": True,
    }


def fragment(run: str, names, name: str, ca: Path, cert: Path, key: Path,
             listen=None, connect=None) -> dict:
    """The zenoh config fragment of process `name` (a plain dict, JSON-serialisable)."""
    frag = {
        "transport": {"link": {"protocols": ["tls"], "tls": _tls_block(ca, cert, key)}},
        "connect": {"timeout_ms": CONNECT_TIMEOUT_MS, "exit_on_failure": True},
        "access_control": access_control(run, names),
    }
    if listen:
        frag["listen"] = {"endpoints": list(listen)}
    if connect:
        frag["connect"]["endpoints"] = list(connect)
    return frag


def _write_private(path: Path, data: bytes) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def make_run_keys(dir, run: str, names, *, hosts=("127.0.0.1",), port_base: int | None = None,
                  valid_days: int = DEFAULT_VALID_DAYS, now: _dt.datetime | None = None) -> KeySet:
    """Make a run's CA, one certificate and key per process, and each process's zenoh config.

    Parameters
    ----------
    dir : path
        Directory to create; it must not exist or be empty (a key set is never
        overwritten: make a new one per run).
    run : str
        Run id; the ACL covers ``socmon/<run>/**`` only.
    names : sequence of str
        Process names, e.g. :func:`run_identities` ``(M)``.
    hosts : sequence of str
        Addresses written into the certificates' subjectAltName (informational: the
        configs do not verify names, see :func:`fragment`), and with `port_base` the host
        of the endpoints.
    port_base : int or None
        If given, process k of `names` listens on ``tls/<hosts[0]>:<port_base + k>`` and
        every process connects to the first one (the world), so that the fragment alone
        starts a process. If None, the endpoints come from flags.
    valid_days : int
        Validity of the certificates.

    Returns
    -------
    KeySet

    Examples
    --------
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp()) / "keys"
    >>> ks = make_run_keys(d, "demo", run_identities(2))
    >>> ks.names[:3], ks.cert("agent-2").name
    (('world', 'agent-1', 'agent-2'), 'cert.pem')
    """
    import ipaddress

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    _check_run(run)
    names = tuple(names)
    access_control(run, names)  # validates the names
    if isinstance(valid_days, bool) or not isinstance(valid_days, int) or not 1 <= valid_days <= 3650:
        raise InvalidKeys("valid_days", f"expected an int in 1..3650, got {valid_days!r}")
    hosts = tuple(hosts)
    if not hosts:
        raise InvalidKeys("hosts", "give at least one host")
    sans = []
    for h in hosts:
        if not isinstance(h, str) or not h or any(c.isspace() for c in h):
            raise InvalidKeys("hosts", f"invalid host {h!r}")
        try:
            sans.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            sans.append(x509.DNSName(h))
    if port_base is not None:
        if isinstance(port_base, bool) or not isinstance(port_base, int) or not 1 <= port_base <= 65535 - len(names):
            raise InvalidKeys("port_base", f"expected an int in 1..{65535 - len(names)}, got {port_base!r}")
    dir = Path(dir)
    if dir.exists() and (not dir.is_dir() or any(dir.iterdir())):
        raise InvalidKeys("dir", f"{dir} exists and is not an empty directory (make a new key set per run)")
    dir.mkdir(parents=True, exist_ok=True)
    dir = dir.resolve()

    now = now or _dt.datetime.now(_dt.timezone.utc)
    not_before = now - _dt.timedelta(minutes=5)  # tolerate small clock skew between machines
    not_after = now + _dt.timedelta(days=valid_days)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"socmon run {run} CA")])
    ca_ski = x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key())
    ca_cert = (
        x509.CertificateBuilder()
        .subject_name(ca_name).issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(not_before).not_valid_after(not_after)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False,
                                     key_encipherment=False, data_encipherment=False,
                                     key_agreement=False, key_cert_sign=True, crl_sign=True,
                                     encipher_only=False, decipher_only=False), critical=True)
        .add_extension(ca_ski, critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    ca_path = dir / CA_NAME
    ca_path.write_bytes(ca_cert.public_bytes(serialization.Encoding.PEM))

    endpoints = {}
    if port_base is not None:
        host = hosts[0] if ":" not in hosts[0] else f"[{hosts[0]}]"
        endpoints = {n: f"tls/{host}:{port_base + k}" for k, n in enumerate(names)}
    for name in names:
        key = ec.generate_private_key(ec.SECP256R1())
        cert = (
            x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
            .issuer_name(ca_name)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(not_before).not_valid_after(not_after)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False,
                                         key_encipherment=False, data_encipherment=False,
                                         key_agreement=False, key_cert_sign=False, crl_sign=False,
                                         encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                  ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
            .add_extension(x509.SubjectAlternativeName(sans), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_subject_key_identifier(ca_ski),
                           critical=False)
            .sign(ca_key, hashes.SHA256())
        )
        sub = dir / name
        sub.mkdir()
        os.chmod(sub, 0o700)
        (sub / CERT_NAME).write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        _write_private(sub / KEY_NAME, key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()))
        listen = [endpoints[name]] if endpoints else None
        connect = [endpoints[names[0]]] if endpoints and name != names[0] else None
        frag = fragment(run, names, name, ca_path, sub / CERT_NAME, sub / KEY_NAME, listen, connect)
        header = (f"// zenoh config of {name} in socmon run {run} (made by socmon keys init).\n"
                  f"// Usable as is with --zenoh-config; socmon --keys re-bases the paths below.\n")
        (sub / FRAGMENT_NAME).write_text(header + json.dumps(frag, indent=2) + "\n")
    fingerprint = ca_cert.fingerprint(hashes.SHA256()).hex()
    manifest = {
        "version": MANIFEST_VERSION,
        "run": run,
        "names": list(names),
        "ca_sha256": fingerprint,
        "not_after": not_after.isoformat(timespec="seconds"),
        "hosts": list(hosts),
        "endpoints": endpoints,
    }
    (dir / MANIFEST_NAME).write_text(json.dumps(manifest, indent=2) + "\n")
    return KeySet(dir=dir, run=run, names=names, ca_fingerprint=fingerprint,
                  not_after=manifest["not_after"])


def load_key_set(dir) -> KeySet:
    """Read the manifest of a key directory made by :func:`make_run_keys`.

    Raises
    ------
    InvalidKeys
        (field ``"keys"``) if the directory, the manifest or the CA is missing or malformed.
    """
    dir = Path(dir)
    path = dir / MANIFEST_NAME
    if not dir.is_dir():
        raise InvalidKeys("keys", f"no such directory {str(dir)!r}")
    try:
        manifest = json.loads(path.read_text())
    except FileNotFoundError:
        raise InvalidKeys("keys", f"{str(dir)!r} has no {MANIFEST_NAME} (make one with socmon keys init)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InvalidKeys("keys", f"cannot read {str(path)!r}: {exc}") from None
    if not isinstance(manifest, dict) or manifest.get("version") != MANIFEST_VERSION:
        raise InvalidKeys("keys", f"{str(path)!r} is not a version-{MANIFEST_VERSION} socmon key manifest")
    try:
        run = _check_run(manifest.get("run"))
        names = tuple(manifest.get("names") or ())
        access_control(run, names)
    except InvalidKeys as exc:
        raise InvalidKeys("keys", f"{str(path)!r}: {exc}") from None
    if not (dir / CA_NAME).is_file():
        raise InvalidKeys("keys", f"{str(dir)!r} has no {CA_NAME}")
    return KeySet(dir=dir.resolve(), run=run, names=names, ca_fingerprint=str(manifest.get("ca_sha256", "")),
                  not_after=str(manifest.get("not_after", "")))


def _strip_comments(text: str) -> str:
    return "\n".join(line for line in text.splitlines() if not line.lstrip().startswith("//"))


def load_fragment(dir, name: str, run: str | None = None) -> dict:
    """The zenoh config fragment of process `name` from key directory `dir`.

    The certificate paths are re-based on `dir` (the directory may have been copied to
    another machine or path); everything else is as written by :func:`make_run_keys`.

    Parameters
    ----------
    dir : path
    name : str
        Process name (:func:`identity_name`).
    run : str or None
        If given, the key set must have been made for this run.

    Raises
    ------
    InvalidKeys
        (field ``"keys"``) naming what is missing or does not match.
    """
    ks = load_key_set(dir)
    if run is not None and run != ks.run:
        raise InvalidKeys("keys", f"{str(ks.dir)!r} holds the keys of run {ks.run!r}, not of run {run!r}")
    try:
        path = ks.config(name)
    except InvalidKeys as exc:
        raise InvalidKeys("keys", str(exc)) from None
    for p in (path, ks.cert(name), ks.key(name)):
        if not p.is_file():
            raise InvalidKeys("keys", f"missing {str(p)!r}")
    try:
        frag = json.loads(_strip_comments(path.read_text()))
        tls = frag["transport"]["link"]["tls"]
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as exc:
        raise InvalidKeys("keys", f"cannot read {str(path)!r}: {exc}") from None
    tls.update({k: v for k, v in _tls_block(ks.ca, ks.cert(name), ks.key(name)).items()
                if k.endswith(("_key", "_certificate"))})
    return frag
