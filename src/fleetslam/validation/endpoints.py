"""Whether a Zenoh endpoint (``tcp/host:port``) can work, said before Zenoh sees it: Zenoh
itself answers a malformed one with a traceback, and an unknown host with retries until
the reach deadline."""

from __future__ import annotations

import errno
import ipaddress
import json
import re
import socket

# Protocols that take host:port; unixsock-stream takes a socket file's path.
HOST_PORT_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
PATH_PROTOCOLS = ("unixsock-stream",)
# Protocols over TCP: a plain socket tells whether their port is free or answers.
STREAM_PROTOCOLS = ("tcp", "tls", "ws")
# These need certificates from a Zenoh config file (transport/link/tls).
TLS_PROTOCOLS = ("tls", "quic")
_LABEL = re.compile(r"(?!-)[A-Za-z0-9-]{1,63}(?<!-)")
_TLS_FILES = ("root_ca_certificate", "listen_certificate", "connect_certificate")


def host_problem(host: str) -> str | None:
    """What is wrong with ``host`` as an IP address or a DNS name (RFC 1123), or None."""
    try:
        ipaddress.ip_address(host)
        return None
    except ValueError:
        pass
    if 0 < len(host) <= 253 and all(_LABEL.fullmatch(p) for p in host.split(".")):
        return None
    return f"{host!r} is not a host name or an IP address"


def http_endpoint_problem(url: str) -> str | None:
    """What is wrong with ``url`` as an etcd endpoint ``http(s)://HOST:PORT``, or None."""
    scheme, sep, address = url.partition("://")
    if scheme not in ("http", "https") or not sep:
        return "not http://HOST:PORT or https://HOST:PORT"
    host, colon, port = address.rstrip("/").rpartition(":")
    if not colon or not host:
        return "not http://HOST:PORT or https://HOST:PORT"
    if not (port.isdigit() and 1 <= int(port) <= 65535):
        return f"port {port!r} is not a number in 1..65535"
    return host_problem(host.strip("[]"))


def endpoint_problem(endpoint: str) -> str | None:
    """What is wrong with the form of ``endpoint``, or None."""
    protocol, slash, address = endpoint.partition("/")
    known = HOST_PORT_PROTOCOLS + PATH_PROTOCOLS
    if not slash or protocol not in known:
        return f"not PROTOCOL/ADDRESS with a protocol of {', '.join(known)}"
    address = re.split(r"[?#]", address, maxsplit=1)[0]  # Zenoh's metadata and config
    if protocol in PATH_PROTOCOLS:
        return None if address else "no socket path after the protocol"
    host, colon, port = address.rpartition(":")
    if not colon or not host:
        return "not PROTOCOL/HOST:PORT"
    if not (port.isdigit() and 1 <= int(port) <= 65535):
        return f"port {port!r} is not a number in 1..65535"
    if host.startswith("[") and host.endswith("]"):  # IPv6
        try:
            ipaddress.IPv6Address(host[1:-1])
            return None
        except ValueError:
            return f"{host!r} is not an IPv6 address"
    if ":" in host:  # the port would be ambiguous
        return f"an IPv6 address is written in brackets: [{host}]:{port}"
    return host_problem(host)


def check_endpoint(endpoint: str, name: str, zenoh_config: str | None = None) -> str:
    """``endpoint`` itself, or ValueError naming ``name`` (the flag or setting): its form,
    TLS without the Zenoh config file that holds the certificates, a host name that does
    not resolve (at once, instead of retrying until the reach deadline)."""
    problem = endpoint_problem(endpoint)
    if problem:
        raise ValueError(f"{name} {endpoint!r}: {problem}")
    protocol, _, address = endpoint.partition("/")
    if protocol in TLS_PROTOCOLS and not _has_tls(zenoh_config):
        raise ValueError(f"{name} {endpoint!r}: {protocol} needs a Zenoh config file with the "
                         f"lab's TLS certificates (--zenoh-config FILE, from fleetslam certs)")
    if protocol in HOST_PORT_PROTOCOLS:
        host = re.split(r"[?#]", address, maxsplit=1)[0].rpartition(":")[0].strip("[]")
        try:
            socket.getaddrinfo(host, None)
        except socket.gaierror as exc:
            raise ValueError(f"{name} {endpoint!r}: host {host!r} does not resolve "
                             f"({exc.strerror})") from None
    return endpoint


def check_listenable(endpoint: str, name: str) -> str:
    """``endpoint`` itself, or ValueError naming ``name`` when this machine cannot listen
    there: its port taken (a ROS 2 robot's rmw_zenohd holds Zenoh's 7447) or its address
    not this machine's. Said before the store or any worker is made: Zenoh says it in a
    long line of its source paths, after the cloud built everything. A TCP-based endpoint
    only (QUIC and UDP cannot be told this way); a form check_endpoint accepted."""
    protocol, _, address = endpoint.partition("/")
    if protocol not in STREAM_PROTOCOLS:
        return endpoint
    host, _, port = re.split(r"[?#]", address, maxsplit=1)[0].rpartition(":")
    family, kind, proto, _, where = socket.getaddrinfo(host.strip("[]"), int(port),
                                                        type=socket.SOCK_STREAM)[0]
    with socket.socket(family, kind, proto) as probe:
        # As Zenoh's listener (tokio) binds: a connection of a stopped cloud lingering in
        # TIME_WAIT does not make the port taken, a listening socket does.
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(where)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise ValueError(f"{name} {endpoint!r}: port {port} is taken (another Zenoh "
                                 f"router? ROS 2's rmw_zenohd uses 7447): choose another "
                                 f"with --listen") from None
            raise ValueError(f"{name} {endpoint!r}: cannot listen there "
                             f"({exc.strerror})") from None
    return endpoint


def _has_tls(zenoh_config: str | None) -> bool:
    if not zenoh_config:
        return False
    import zenoh  # here: loading config.py (endpoint forms) must not load Zenoh

    try:
        tls = json.loads(zenoh.Config.from_file(str(zenoh_config)).get_json("transport/link/tls"))
    except zenoh.ZError as exc:
        raise ValueError(f"{zenoh_config}: not a Zenoh config file: {exc}") from None
    return any(tls.get(key) for key in _TLS_FILES)
