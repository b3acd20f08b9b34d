"""Where a certificate directory keeps each role's files (no cryptography imported here).

``dmpc certs`` writes the directory; a process started with ``--tls DIR`` reads the CA, its
role's certificate and key, and the access control file from it.
"""
from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from dmpc.bus import keys
from dmpc.bus.session import TlsFiles
from dmpc.security.acl import read_acl

CA_CERT = "ca.pem"
CA_KEY = "ca.key"


def role_names(agent_names: Iterable[str]) -> list[str]:
    """``router``, ``coordinator``, ``plant``, ``agent-<name>`` and ``sensor-<name>`` for every
    subsystem of ``agent_names``, ``observer`` and ``operator``, in that order."""
    names = list(agent_names)
    return (["router", keys.COORDINATOR_ROLE, keys.PLANT_ROLE] + [keys.agent_role(name) for name in names]
            + [keys.sensor_role(name) for name in names] + ["observer", keys.OPERATOR_ROLE])


def cert_path(directory: str | Path, role: str) -> Path:
    """The certificate of ``role`` in the certificate directory ``directory``."""
    return Path(directory) / f"{role}.pem"


def key_path(directory: str | Path, role: str) -> Path:
    """The private key of ``role`` in the certificate directory ``directory``."""
    return Path(directory) / f"{role}.key"


def tls_files(directory: str | Path, role: str) -> TlsFiles:
    """The CA, certificate and key of ``role`` in ``directory``.

    Raises
    ------
    ValueError
        A file is missing; the message names it and the command that makes it.
    """
    files = TlsFiles(ca=Path(directory) / CA_CERT, cert=cert_path(directory, role), key=key_path(directory, role))
    for path in (files.ca, files.cert, files.key):
        if not Path(path).is_file():
            raise ValueError(f"--tls {directory}: no {Path(path).name} for role {role!r} "
                             f"(make the certificates with 'dmpc certs {directory} --scenario SCENARIO')")
    return files


def node_security(directory: str | Path, role: str) -> tuple[TlsFiles, dict | None]:
    """TLS files of ``role`` and the directory's access control (None without ``acl.json``).

    Raises
    ------
    ValueError
        A missing file or a malformed ``acl.json``, named in the message.
    """
    if not Path(directory).is_dir():
        raise ValueError(f"--tls {directory}: no such directory "
                         f"(make it with 'dmpc certs {directory} --scenario SCENARIO')")
    return tls_files(directory, role), read_acl(directory)
