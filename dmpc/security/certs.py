"""Certificates for TLS links with mutual authentication: one CA, one certificate per role.

Roles are ``router``, ``coordinator``, ``plant``, ``agent-<name>`` and ``sensor-<name>`` (the
liveliness role names of ``bus.keys``), ``observer`` for ``dmpc watch`` (it may only listen), and
``operator`` for ``dmpc setpoint`` (it may only request setpoints and hear the answers).
A process that hosts the coordinator and the simulated plant together uses ``coordinator``.
Each certificate's common name is its role: Zenoh's access control binds its
subjects to these names (``cert_common_names``). Every certificate carries the subject
alternative names of the hosts it may be reached at, so that a peer connecting to
``tls/<host>:<port>`` can verify it (a process that listens is a TLS server).

Files in the directory::

    ca.pem                    the certificate authority's certificate
    <role>.pem, <role>.key    one pair per role
    acl.json                  the access control of the run (dmpc.security.acl)

The CA's private key, which can sign a certificate for any role, is never written into the
directory: ``dmpc certs`` writes it apart (:func:`default_ca_key_path`), and ``dmpc run --secure``
does not write it at all (it is dropped once the run's certificates are signed). Every private
key is written with mode 0600, and a directory made here has mode 0700.
"""
from __future__ import annotations

import datetime
import ipaddress
import os
from collections.abc import Iterable, Sequence
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from dmpc.bus.session import TlsFiles
from dmpc.security.acl import scenario_access_control, write_acl
from dmpc.security.files import CA_CERT, CA_KEY, cert_path, key_path, role_names

DEFAULT_HOSTS = ("127.0.0.1", "localhost")
VALID_DAYS = 365


def _san(hosts: Sequence[str]) -> x509.SubjectAlternativeName:
    names: list[x509.GeneralName] = []
    for host in dict.fromkeys(hosts):  # keeps order, drops repeats
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            names.append(x509.DNSName(host))
    return x509.SubjectAlternativeName(names)


def check_host(host: str) -> str:
    """Return ``host`` if it is an IP address or a DNS name; ValueError otherwise."""
    try:
        ipaddress.ip_address(host)
        return host
    except ValueError:
        pass
    labels = host.rstrip(".").split(".")
    if not host or len(host) > 253 or not all(
            0 < len(label) <= 63 and label.replace("-", "").isalnum() and label.isascii()
            and not label.startswith("-") and not label.endswith("-") for label in labels):
        raise ValueError(f"--host {host!r} is neither an IP address nor a DNS name")
    return host


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "dmpc"),
                      x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _write_key(path: Path, key: ec.EllipticCurvePrivateKey) -> None:
    data = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    os.fchmod(fd, 0o600)  # a key file that existed keeps its mode through os.open
    with os.fdopen(fd, "wb") as fh:
        fh.write(data)


def _write_cert(path: Path, cert: x509.Certificate) -> None:
    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def default_ca_key_path(directory: str | Path) -> Path:
    """Where ``dmpc certs DIR`` keeps the CA's private key: ``DIR-ca.key`` beside the directory,
    so that a copy of the directory (or of any of its files) never carries it."""
    directory = Path(directory).resolve()
    return directory.parent / f"{directory.name or 'certs'}-{CA_KEY}"


def make_ca(directory: Path, name: str = "dmpc CA", days: int = VALID_DAYS,
            key_file: Path | None = None) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    """A self-signed CA (ECDSA P-256) named ``name``, valid for ``days`` days, its certificate written
    to ``ca.pem`` in ``directory``; its private key to ``key_file`` if given (mode 0600), else nowhere."""
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder()
            .subject_name(_name(name)).issuer_name(_name(name))
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5)).not_valid_after(now + datetime.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                         content_commitment=False, key_encipherment=False, data_encipherment=False,
                                         key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    _write_cert(directory / CA_CERT, cert)
    if key_file is not None:
        Path(key_file).parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        _write_key(Path(key_file), key)
    return cert, key


def issue(directory: Path, role: str, ca_cert: x509.Certificate, ca_key: ec.EllipticCurvePrivateKey,
          hosts: Sequence[str] = DEFAULT_HOSTS, days: int = VALID_DAYS) -> TlsFiles:
    """A certificate for ``role`` (common name = role) signed by the CA (``ca_cert``, ``ca_key``), for
    server and client use, valid for ``hosts`` (subject alternative names) and ``days`` days; written
    with its private key to ``directory``."""
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder()
            .subject_name(_name(role)).issuer_name(ca_cert.subject)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5)).not_valid_after(now + datetime.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=False, crl_sign=False,
                                         content_commitment=False, key_encipherment=False, data_encipherment=False,
                                         key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(_san(hosts), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256()))
    _write_cert(cert_path(directory, role), cert)
    _write_key(key_path(directory, role), key)
    return TlsFiles(ca=directory / CA_CERT, cert=cert_path(directory, role), key=key_path(directory, role))


def make_certificates(directory: str | Path, roles: Iterable[str], hosts: Sequence[str] = DEFAULT_HOSTS,
                      days: int = VALID_DAYS, ca_key: str | Path | None = None) -> dict[str, TlsFiles]:
    """A new CA and one certificate per role in ``directory`` (created, mode 0700).

    Parameters
    ----------
    directory : path
    roles : iterable of str
        Common names, e.g. from :func:`role_names`.
    hosts : sequence of str
        IP addresses and DNS names every certificate is valid for.
    days : int
        Validity.
    ca_key : path, optional
        Where to write the CA's private key (mode 0600). None: nowhere; once these
        certificates are signed, no other can be made with this CA.

    Returns
    -------
    dict role -> TlsFiles
    """
    hosts = [check_host(h) for h in hosts]
    directory = Path(directory)
    directory.mkdir(mode=0o700, parents=True, exist_ok=True)
    ca_cert, ca_private = make_ca(directory, days=days, key_file=None if ca_key is None else Path(ca_key))
    return {role: issue(directory, role, ca_cert, ca_private, hosts, days) for role in roles}


def make_run_security(directory: str | Path, system, hosts: Sequence[str] = DEFAULT_HOSTS, run_id: str = "*",
                      days: int = VALID_DAYS, force: bool = False, ca_key: str | Path | None = None) -> list[str]:
    """Certificates for every role of ``system`` and its ``acl.json`` in ``directory``.

    Parameters
    ----------
    system : CoupledSystem
    hosts : sequence of str
        The host names and addresses the certificates are valid for.
    run_id : str
        Binds the access control to one run; ``*`` for any run of this scenario.
    days : int
        How long the certificates are valid.
    force : bool
        Replace a directory's existing CA, and an existing ``ca_key`` file; refused otherwise.
    ca_key : path, optional
        Where to keep the CA's private key (mode 0600), outside ``directory`` as
        :func:`default_ca_key_path`; None: it is not kept (``dmpc run --secure``).

    Returns
    -------
    list of str
        The roles written.

    Raises
    ------
    ValueError
        The directory already holds a CA (without ``force``), a host or run id is malformed, or
        the directory cannot be written.
    """
    directory = Path(directory)
    if (directory / CA_CERT).exists() and not force:
        raise ValueError(f"{directory} already holds certificates ({CA_CERT}): choose another directory "
                         "or pass --force to replace them")
    if ca_key is not None and Path(ca_key).exists() and not force:
        raise ValueError(f"{ca_key} already holds a CA key: choose another place with --ca-key "
                         "or pass --force to replace it")
    acl = scenario_access_control(system, run_id)
    roles = role_names(s.name for s in system.subsystems)
    try:
        make_certificates(directory, roles, hosts, days, ca_key=ca_key)
        write_acl(directory, acl)
    except OSError as exc:
        raise ValueError(f"{directory}: cannot write the certificates ({exc.strerror or exc})") from None
    return roles
