"""Zenoh session configuration and opening, with errors that name the endpoint.

Every setting goes through ``Config.insert_json5`` on a fresh ``zenoh.Config`` (or one loaded
from a file). Endpoint strings are checked here, before Zenoh sees them, so a typo fails with a
``ValueError`` naming the endpoint instead of a Rust error location.
"""
from __future__ import annotations

import errno
import ipaddress
import json
import re
import socket
import threading
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import zenoh

from dmpc.core.errors import DmpcError

MODES = ("peer", "client", "router")
PROTOCOLS = ("tcp", "tls", "udp", "quic")

# <proto>/<host>:<port>[?metadata][#config]; host is a name, an IPv4 address or [IPv6].
_ENDPOINT = re.compile(
    r"^(?P<proto>[a-z0-9-]+)/(?P<host>\[[0-9A-Fa-f:.%]+\]|[A-Za-z0-9_.-]+):(?P<port>\d{1,5})"
    r"(?P<rest>[?#].*)?$"
)
# Zenoh error messages end in " at /root/.cargo/.../file.rs:123." (noise for users).
_RUST_LOCATION = re.compile(r"\s+at /\S+?\.rs:\d+\.?")
# Zenoh passes the system's error on as Rust prints it: "Address already in use (os error 98)".
_OS_ERROR = re.compile(r"\(os error (\d+)\)")


class BusError(DmpcError, RuntimeError):
    """A transport failure: a session that cannot be opened, or a bus used after close."""


class AddressInUse(BusError):
    """A listen endpoint could not be bound: another socket holds its address (EADDRINUSE)."""


@dataclass(frozen=True)
class TlsFiles:
    """PEM files for TLS/mTLS links: one CA, and this node's certificate and private key.

    The same certificate and key are used when listening and when connecting; the server
    certificate needs a subject alternative name matching the host that peers connect to.

    Attributes
    ----------
    ca : path
        The certificate of the CA that signed every node's certificate.
    cert, key : path
        This node's certificate and its private key."""

    ca: str | Path
    cert: str | Path
    key: str | Path


def check_endpoint(endpoint: str, *, connect: bool = False) -> str:
    """Return ``endpoint`` if it reads ``<proto>/<host>:<port>``; ValueError otherwise.

    Parameters
    ----------
    endpoint : str
        For example ``tcp/127.0.0.1:7447``, ``tls/robot-1.local:7447`` or ``tcp/[::1]:0``.
    connect : bool
        Port 0 ("any free port") only makes sense for listening; it is refused when True.
    """
    if not isinstance(endpoint, str):
        raise ValueError(f"endpoint {endpoint!r} must be a string like 'tcp/127.0.0.1:7447'")
    match = _ENDPOINT.match(endpoint)
    if match is None:
        raise ValueError(
            f"bad Zenoh endpoint {endpoint!r}: expected <protocol>/<host>:<port>, "
            f"e.g. 'tcp/127.0.0.1:7447'"
        )
    if match["proto"] not in PROTOCOLS:
        raise ValueError(
            f"bad Zenoh endpoint {endpoint!r}: protocol {match['proto']!r} is not one of {PROTOCOLS}"
        )
    port = int(match["port"])
    if port > 65535 or (connect and port == 0):
        raise ValueError(f"bad Zenoh endpoint {endpoint!r}: port {port} is not usable here")
    return endpoint


def endpoint_host(endpoint: str) -> str:
    """The host part of a checked endpoint, without IPv6 brackets."""
    match = _ENDPOINT.match(endpoint)
    if match is None:
        raise ValueError(f"bad Zenoh endpoint {endpoint!r}: expected <protocol>/<host>:<port>")
    return match["host"].strip("[]")


def is_loopback(endpoint: str) -> bool:
    """True when the endpoint's host is ``localhost`` or a loopback address."""
    host = endpoint_host(endpoint)
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.split("%")[0]).is_loopback
    except ValueError:
        return False


def _insert(config: zenoh.Config, key: str, value) -> None:
    config.insert_json5(key, json.dumps(value))


def _checked(endpoints: Iterable[str] | str, connect: bool) -> list[str]:
    if isinstance(endpoints, str):  # a lone string would otherwise be split into characters
        endpoints = [endpoints]
    return [check_endpoint(e, connect=connect) for e in endpoints]


def session_config(
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast: bool = False,
    config_file: str | Path | None = None,
    lease_ms: int | None = None,
    tls: TlsFiles | None = None,
    acl: dict | None = None,
) -> zenoh.Config:
    """Build a Zenoh configuration.

    Parameters
    ----------
    mode : {"peer", "client", "router"}
        Agents run as peers (direct links) or clients (everything through one router).
    listen, connect : sequence of str
        Endpoints such as ``tcp/127.0.0.1:7447``. A peer given no listen endpoint listens on
        an ephemeral port so that other peers can link to it directly (a router does not relay
        between peers since Zenoh 1.9): on ``127.0.0.1`` when multicast is off and every
        connect endpoint is loopback, on ``0.0.0.0`` otherwise.
    multicast : bool
        Multicast scouting; off by default so that only explicit endpoints are used.
    config_file : path, optional
        A Zenoh JSON5 configuration used as the base; the other arguments are applied on top
        (mode and multicast always, the rest only when given).
    lease_ms : int, optional
        Link lease (``transport/link/tx/lease``): how long a hung peer's liveliness tokens
        survive it.
    tls : TlsFiles, optional
        CA, certificate and key for ``tls/`` endpoints, with mutual authentication. With it,
        every endpoint must be ``tls/`` and no other protocol is accepted or opened.
    acl : dict, optional
        An ``access_control`` section (see ``dmpc.security.acl``); enforced on what this
        node's links bring in.

    Returns
    -------
    zenoh.Config

    Raises
    ------
    ValueError
        Unknown mode, a malformed endpoint (named in the message), a non-positive lease.
    """
    if mode not in MODES:
        raise ValueError(f"mode {mode!r} must be one of {MODES}")
    listen = _checked(listen, connect=False)
    connect = _checked(connect, connect=True)
    if tls is not None:
        plain = [e for e in listen + connect if not e.startswith("tls/")]
        if plain:
            raise ValueError(f"endpoint {plain[0]!r} is not a tls/ endpoint: with TLS every link must use tls/")
    if lease_ms is not None and lease_ms <= 0:
        raise ValueError(f"lease_ms must be positive, got {lease_ms}")

    config = zenoh.Config.from_file(str(config_file)) if config_file else zenoh.Config()
    _insert(config, "mode", mode)
    _insert(config, "scouting/multicast/enabled", bool(multicast))
    if connect:
        _insert(config, "connect/endpoints", connect)
    if listen:
        _insert(config, "listen/endpoints", listen)
    elif mode == "peer" and not _explicit_listen(config):
        local = not multicast and all(is_loopback(e) for e in connect)
        proto = "tls" if tls is not None else "tcp"
        _insert(config, "listen/endpoints", [f"{proto}/127.0.0.1:0" if local else f"{proto}/0.0.0.0:0"])
    if not config_file:
        _compact_transport(config)
    if lease_ms is not None:
        _insert(config, "transport/link/tx/lease", int(lease_ms))
    if tls is not None:
        _insert_tls(config, tls)
        _insert(config, "transport/link/protocols", ["tls"])
    if acl is not None:
        try:
            _insert(config, "access_control", acl)
        except zenoh.ZError as exc:
            raise ValueError(f"access control: {_RUST_LOCATION.sub('', str(exc)).strip()}") from None
    return config


def _compact_transport(config: zenoh.Config) -> None:
    """Transport buffers sized for this protocol's messages (well under 16 KiB each).

    Zenoh's defaults (64 KiB batches, two per priority queue on every link, a 16 MiB shared
    memory pool) cost several MB per process in a mesh of agents. Batch sizes are negotiated
    per link, so a peer with default settings still talks to these processes.
    """
    _insert(config, "transport/link/tx/batch_size", 16384)
    _insert(config, "transport/link/tx/queue/size", {"control": 1, "real_time": 2, "interactive_high": 1,
                                                      "interactive_low": 1, "data_high": 1, "data": 2,
                                                      "data_low": 1, "background": 1})
    _insert(config, "transport/shared_memory/enabled", False)


def _explicit_listen(config: zenoh.Config) -> bool:
    # Zenoh's default is a per-mode dict; a list means a config file set the endpoints.
    value = json.loads(config.get_json("listen/endpoints"))
    return isinstance(value, list) and len(value) > 0


def _insert_tls(config: zenoh.Config, tls: TlsFiles) -> None:
    for name in ("ca", "cert", "key"):
        path = Path(getattr(tls, name))
        if not path.is_file():
            raise ValueError(f"TLS {name} file {str(path)!r} does not exist")
    _insert(config, "transport/link/tls/root_ca_certificate", str(tls.ca))
    _insert(config, "transport/link/tls/listen_certificate", str(tls.cert))
    _insert(config, "transport/link/tls/listen_private_key", str(tls.key))
    _insert(config, "transport/link/tls/connect_certificate", str(tls.cert))
    _insert(config, "transport/link/tls/connect_private_key", str(tls.key))
    _insert(config, "transport/link/tls/enable_mtls", True)


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (for tests and local runs)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _endpoints(config: zenoh.Config, key: str) -> list[str]:
    value = json.loads(config.get_json(key))
    return value if isinstance(value, list) else []


OPEN_POLL = 0.05
"""How often the main thread checks for Ctrl-C or SIGTERM while a session opens."""
_abandoned_opens: list[threading.Thread] = []


def opens_abandoned() -> bool:
    """True if an interrupted :func:`open_session` left a session opening in the background.

    Such a process must end with ``os._exit``: an interpreter exit would tear the thread down
    inside Zenoh's native code.
    """
    return bool(_abandoned_opens)


def _open_interruptibly(config: zenoh.Config) -> zenoh.Session:
    """``zenoh.open`` on a helper thread, so that Ctrl-C and SIGTERM reach the main thread at once.

    ``zenoh.open`` blocks in native code for as long as it keeps trying the connect endpoints,
    and Python runs signal handlers only between bytecodes of the main thread.
    """
    result: dict = {}

    def target() -> None:
        try:
            result["session"] = zenoh.open(config)
        except BaseException as exc:  # noqa: BLE001 - handed to the main thread
            result["error"] = exc

    thread = threading.Thread(target=target, name="zenoh-open", daemon=True)
    thread.start()
    try:
        while thread.is_alive():
            thread.join(OPEN_POLL)
    except KeyboardInterrupt:
        _abandoned_opens.append(thread)
        raise
    if "error" in result:
        raise result["error"]
    return result["session"]


def open_session(config: zenoh.Config, timeout: float = 10.0) -> zenoh.Session:
    """Open a session, failing with BusError when a connect endpoint is not reachable in time.

    Zenoh's own behaviour is to keep retrying in the background (peer, router) or to give up
    at once (client). Here ``connect/timeout_ms`` and ``connect/exit_on_failure`` are set on
    ``config`` (which is modified) so that every mode retries for ``timeout`` seconds and then
    fails.

    Parameters
    ----------
    config : zenoh.Config
        Typically from :func:`session_config`.
    timeout : float
        Seconds to keep trying the connect endpoints.

    Raises
    ------
    BusError
        The endpoints could not be reached, or a listen endpoint could not be bound; the
        message names the endpoints. :class:`AddressInUse` when a listen address is taken.
    """
    if timeout <= 0:
        raise ValueError(f"timeout must be positive, got {timeout}")
    connect = _endpoints(config, "connect/endpoints")
    if connect:
        _insert(config, "connect/timeout_ms", max(1, int(timeout * 1000)))
        _insert(config, "connect/exit_on_failure", True)
    try:
        return _open_interruptibly(config)
    except zenoh.ZError as exc:
        mode = json.loads(config.get_json("mode")) or "peer"
        reason = _RUST_LOCATION.sub("", str(exc)).strip()
        listen = _endpoints(config, "listen/endpoints")
        in_use = listen and any(int(code) == errno.EADDRINUSE for code in _OS_ERROR.findall(reason))
        raise (AddressInUse if in_use else BusError)(
            f"cannot open a Zenoh {mode} session (connect={connect}, listen={listen}, "
            f"timeout={timeout:g} s): {reason}"
        ) from exc
