"""Key material of a secured run: a CA, one certificate per process, zenoh TLS + ACL configs.

The secure mode uses zenoh's own mechanisms only: TLS links with mutual authentication
(every process presents a certificate signed by the run's CA) and zenoh's ``access_control``
with ``default_permission: "deny"`` on every peer. The subject of a rule is the common name
(CN) of the remote certificate, so a message is accepted only if the process that sent it
over the link holds the credentials of a role allowed to publish that key.

The rights are the caller's: a table of process names (certificate CNs) and, for each, the
key expressions it may put and the liveliness tokens it may declare (:class:`Permissions`),
plus one scope every process may subscribe to and watch (:func:`build_access_control`).
socmon's table is :func:`agent.protocol.topics.permissions`.

Layout of a key directory made by :func:`make_run_keys`::

    DIR/keys.json            manifest: run, names, CA fingerprint, validity, and what the
                             caller records of what the keys are for (``about``)
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
from dataclasses import dataclass, field
from pathlib import Path

__all__ = [
    "CONNECT_TIMEOUT_MS",
    "FRAGMENT_NAME",
    "MANIFEST_NAME",
    "InvalidKeys",
    "KeySet",
    "Permissions",
    "build_access_control",
    "check_run",
    "load_fragment",
    "load_key_set",
    "make_run_keys",
]

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
#: The manifest's own keys; any other key of a manifest is the caller's ``about``.
_MANIFEST_KEYS = ("version", "run", "names", "ca_sha256", "not_after", "hosts", "endpoints")

_RUN_RE = re.compile(r"^[A-Za-z0-9_.\-]+$")
#: A process name (certificate CN, ACL subject, directory name in a key set).
_NAME_RE = re.compile(r"^[A-Za-z0-9_.\-]+$")


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


# --------------------------------------------------------------------------- access control


@dataclass(frozen=True)
class Permissions:
    """What one process (one certificate CN) may send into the mesh.

    Attributes
    ----------
    put : tuple of str
        Key expressions it may put (publish).
    tokens : tuple of str
        Key expressions of the liveliness tokens it may declare.
    serve : tuple of str
        Key expressions it may declare queryables on and reply from: its publishers'
        caches of their last samples (an advanced publisher answers late subscribers'
        history queries under ``<key>/@adv/**``).
    """

    put: tuple[str, ...] = ()
    tokens: tuple[str, ...] = ()
    serve: tuple[str, ...] = ()


def check_run(run) -> str:
    """Check a run id (letters, digits, ``_ . -``) and return it."""
    if not isinstance(run, str) or not _RUN_RE.match(run):
        raise InvalidKeys("run", f"invalid run id {run!r} (letters, digits, '_', '.', '-')")
    return run


def _check_names(names) -> tuple[str, ...]:
    names = tuple(names)
    if not names:
        raise InvalidKeys("names", "no process names")
    for n in names:
        if not isinstance(n, str) or not _NAME_RE.match(n):
            raise InvalidKeys("name", f"{n!r} is not a process name (letters, digits, '_', '.', '-')")
    if len(set(names)) != len(names):
        raise InvalidKeys("names", "a name is listed twice")
    return names


def build_access_control(scope: str, permissions) -> dict:
    """The zenoh ``access_control`` block of every process of a run, from its rights table.

    Default deny in both directions. Ingress: a subject (certificate CN) may put only its
    ``permissions[name].put`` and declare only its ``permissions[name].tokens``; every
    subject may declare subscribers and liveliness subscribers and query liveliness on
    `scope` (without that the publishers would not learn whom to send to), and send queries
    to the publishers' caches (``<scope>/@adv/**``: a late subscriber asking for their last
    samples); a subject may declare queryables and reply only on its
    ``permissions[name].serve`` (its own caches: nobody answers for another's key). Egress:
    everything in `scope` may go to the subjects, so that this process's own puts, tokens,
    subscriptions, queries and replies leave it. Nothing is allowed to or from a link
    without a certificate of the run; deletes are denied.

    Parameters
    ----------
    scope : str
        Key expression of everything the run uses (e.g. ``"app/run7/**"``).
    permissions : mapping of str to Permissions
        Process name (certificate CN) -> its rights, in the order of the subjects.

    Examples
    --------
    >>> acl = build_access_control("app/r/**", {"a": Permissions(put=("app/r/x",))})
    >>> [r["id"] for r in acl["rules"]], acl["default_permission"]
    (['egress-run', 'egress-caches', 'ingress-subscribe', 'ingress-query', 'token-a', 'put-a'], 'deny')
    """
    if not isinstance(scope, str) or not scope:
        raise InvalidKeys("scope", f"expected a key expression, got {scope!r}")
    names = _check_names(permissions)
    # publishers' caches live under "<key>/@adv/...": "@" chunks are matched only verbatim
    # (never by "**"), so the caches' queries and replies are allowed there explicitly
    caches = f"{scope.rstrip('/')}/@adv/**"
    rules = [
        {"id": "egress-run", "permission": "allow", "flows": ["egress"],
         "messages": ["put", "declare_subscriber", "liveliness_token", "liveliness_query",
                      "declare_liveliness_subscriber"],
         "key_exprs": [scope]},
        {"id": "egress-caches", "permission": "allow", "flows": ["egress"],
         "messages": ["query", "declare_queryable", "reply"], "key_exprs": [scope, caches]},
        {"id": "ingress-subscribe", "permission": "allow", "flows": ["ingress"],
         "messages": ["declare_subscriber", "liveliness_query", "declare_liveliness_subscriber"],
         "key_exprs": [scope]},
        {"id": "ingress-query", "permission": "allow", "flows": ["ingress"],
         "messages": ["query"], "key_exprs": [caches]},
    ]
    subjects = [{"id": n, "cert_common_names": [n]} for n in names]
    policies = [{"id": "run", "rules": ["egress-run", "egress-caches", "ingress-subscribe",
                                        "ingress-query"],
                 "subjects": list(names)}]
    for n in names:
        rights = permissions[n]
        if not isinstance(rights, Permissions):
            raise InvalidKeys("permissions", f"{n}: expected Permissions, got {type(rights).__name__}")
        own = [f"token-{n}"]
        rules.append({"id": f"token-{n}", "permission": "allow", "flows": ["ingress"],
                      "messages": ["liveliness_token"], "key_exprs": list(rights.tokens)})
        if rights.put:
            rules.append({"id": f"put-{n}", "permission": "allow", "flows": ["ingress"],
                          "messages": ["put"], "key_exprs": list(rights.put)})
            own.append(f"put-{n}")
        if rights.serve:
            rules.append({"id": f"serve-{n}", "permission": "allow", "flows": ["ingress"],
                          "messages": ["declare_queryable", "reply"],
                          "key_exprs": list(rights.serve)})
            own.append(f"serve-{n}")
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
    about : dict
        What the caller recorded of what the keys are for (e.g. socmon's scenario);
        empty for a key set made without it.
    """

    dir: Path
    run: str
    names: tuple[str, ...]
    ca_fingerprint: str
    not_after: str
    about: dict = field(default_factory=dict)

    @property
    def ca(self) -> Path:
        return self.dir / CA_NAME

    def _member(self, name: str) -> Path:
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


def fragment(acl: dict, ca: Path, cert: Path, key: Path, listen=None, connect=None) -> dict:
    """The zenoh config fragment of one process (a plain dict, JSON-serialisable), with
    the run's access-control block `acl` (:func:`build_access_control`)."""
    frag = {
        "transport": {"link": {"protocols": ["tls"], "tls": _tls_block(ca, cert, key)}},
        "connect": {"timeout_ms": CONNECT_TIMEOUT_MS, "exit_on_failure": True},
        "access_control": acl,
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


def make_run_keys(dir, run: str, permissions, *, scope: str, hosts=("127.0.0.1",),
                  port_base: int | None = None,
                  valid_days: int = DEFAULT_VALID_DAYS, now: _dt.datetime | None = None,
                  about: dict | None = None) -> KeySet:
    """Make a run's CA, one certificate and key per process, and each process's zenoh config.

    Parameters
    ----------
    dir : path
        Directory to create; it must not exist or be empty (a key set is never
        overwritten: make a new one per run).
    run : str
        Run id (letters, digits, ``_ . -``), written in the manifest.
    permissions : mapping of str to Permissions
        Process names (certificate CNs, in order: the first is the one every other
        connects to with `port_base`) and their rights, e.g.
        :func:`agent.protocol.topics.permissions`.
    scope : str
        Key expression every process may subscribe to, e.g. ``socmon/<run>/**``; the
        ACL covers it only (:func:`build_access_control`).
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
    about : dict or None
        The caller's record of what the keys are for (str keys, JSON values), written
        into the manifest beside its own keys (which it may not shadow) and read back as
        :attr:`KeySet.about`; the transport does not interpret it.

    Returns
    -------
    KeySet

    Examples
    --------
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp()) / "keys"
    >>> ks = make_run_keys(d, "demo", {"hub": Permissions(), "a-1": Permissions(put=("app/demo/x",))},
    ...                    scope="app/demo/**")
    >>> ks.names, ks.cert("a-1").name
    (('hub', 'a-1'), 'cert.pem')
    """
    import ipaddress

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    check_run(run)
    acl = build_access_control(scope, permissions)  # validates the names
    names = tuple(permissions)
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
    about = _check_about(about)
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
        frag = fragment(acl, ca_path, sub / CERT_NAME, sub / KEY_NAME, listen, connect)
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
        **about,
    }
    (dir / MANIFEST_NAME).write_text(json.dumps(manifest, indent=2) + "\n")
    return KeySet(dir=dir, run=run, names=names, ca_fingerprint=fingerprint,
                  not_after=manifest["not_after"], about=about)


def _check_about(about) -> dict:
    if about is None:
        return {}
    if not isinstance(about, dict):
        raise InvalidKeys("about", f"expected a dict, got {type(about).__name__}")
    for k in about:
        if not isinstance(k, str) or k in _MANIFEST_KEYS:
            raise InvalidKeys("about", f"{k!r} is not a key of its own (the manifest's: "
                                       f"{', '.join(_MANIFEST_KEYS)})")
    try:
        return json.loads(json.dumps(about))
    except (TypeError, ValueError) as exc:
        raise InvalidKeys("about", f"not JSON: {exc}") from None


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
        run = check_run(manifest.get("run"))
        names = _check_names(manifest.get("names") or ())
    except InvalidKeys as exc:
        raise InvalidKeys("keys", f"{str(path)!r}: {exc}") from None
    if not (dir / CA_NAME).is_file():
        raise InvalidKeys("keys", f"{str(dir)!r} has no {CA_NAME}")
    return KeySet(dir=dir.resolve(), run=run, names=names, ca_fingerprint=str(manifest.get("ca_sha256", "")),
                  not_after=str(manifest.get("not_after", "")),
                  about={k: v for k, v in manifest.items() if k not in _MANIFEST_KEYS})


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
        Process name (certificate CN; socmon's: :func:`agent.protocol.topics.identity_name`).
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
