"""Why nothing answers at an endpoint, as far as a client can tell: what the hint and the
error of a wait say.

What Zenoh lets a client see, and what it does not (eclipse-zenoh 1.x):

- A session that cannot open fails with the same "Timeout!" whether nothing listens, the
  TLS handshake was refused (a certificate of another lab, none of its own) or the
  listener speaks another protocol; the reason is only in Zenoh's debug log (RUST_LOG=debug,
  which ``fleetslam`` turns on when set). A plain TCP connection to the same port tells
  "nothing listens" (refused) from "something listens but no session opens" (a TLS or
  protocol refusal) from "no reply" (a host down, a firewall): :func:`session_not_opened`.
- Access control refuses nothing visibly: a denied message is dropped by the router, the
  client's put succeeds and no error ever comes back. A robot (or operator) whose
  certificate the cloud's ACL does not admit for its keys sees an open session and
  silence, exactly as when no fleetslam cloud serves behind that router:
  :func:`no_answer`.
"""

from __future__ import annotations

import re
import socket

# The TCP-based protocols a plain connection can probe (QUIC and UDP cannot be).
from fleetslam.validation.endpoints import STREAM_PROTOCOLS

ZENOH_LOG = "RUST_LOG=debug shows Zenoh's own reason"


def _host_port(endpoint: str) -> tuple[str, str, int] | None:
    protocol, _, address = endpoint.partition("/")
    if protocol not in STREAM_PROTOCOLS:
        return None
    host, _, port = re.split(r"[?#]", address, maxsplit=1)[0].rpartition(":")
    return protocol, host.strip("[]"), int(port)


def tcp_state(endpoint: str, timeout_s: float = 1.0) -> str | None:
    """"refused" (nothing listens), "listening" or "silent" (no reply within
    ``timeout_s``: a host down, a firewall); None for a protocol a TCP probe cannot test."""
    where = _host_port(endpoint)
    if where is None:
        return None
    _, host, port = where
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            return "listening"
    except ConnectionRefusedError:
        return "refused"
    except OSError:
        return "silent"


def session_not_opened(endpoint: str, zenoh_config: str | None) -> str:
    """What to check when no Zenoh session opens to ``endpoint``."""
    where = _host_port(endpoint)
    state = tcp_state(endpoint)
    if where is None or state is None:
        return f"is the cloud running there? ({ZENOH_LOG})"
    protocol, host, port = where
    if state == "refused":
        return (f"nothing listens at {host}:{port} (connection refused): is the cloud "
                f"running, and is this its endpoint (--connect)?")
    if state == "silent":
        return (f"{host}:{port} does not reply (connection timed out): is the host up, and "
                f"does its firewall let port {port} through?")
    if protocol == "tls":
        return (f"something listens at {host}:{port} but refuses a Zenoh session: most "
                f"likely the TLS handshake: is --zenoh-config {zenoh_config} from the "
                f"cloud's lab (fleetslam certs), with a certificate of its own? "
                f"({ZENOH_LOG})")
    return (f"something listens at {host}:{port} but refuses a Zenoh session: is it a "
            f"tls/ endpoint (then tls/{host}:{port} with --zenoh-config from the lab), or no "
            f"Zenoh router at all? ({ZENOH_LOG})")


def no_answer(endpoint: str, zenoh_config: str | None, robot: str | None = None) -> str:
    """What to check when a session to ``endpoint`` is open but no cloud answers: no cloud
    behind that router, or (with a lab's certificates) its access control dropping our
    messages, which Zenoh does not report."""
    if not zenoh_config:
        return ("a Zenoh router answers there but no fleetslam cloud does: is a cloud "
                "serving behind it (`fleetslam cloud`, or workers of `fleetslam router`)?")
    if robot is None:
        whose = ("only the operator's certificate (client.json5 of the lab) may ask the "
                 "cloud")
    else:
        whose = (f"a robot may use only its own keys: is it robot {robot}'s certificate "
                 f"(robot-{robot}.json5 of the lab), and was the cloud restarted after "
                 f"`fleetslam certs --robot {robot}`?")
    return (f"the session is open (TLS accepted) but no cloud answers: either none serves "
            f"behind that endpoint, or its access control drops our messages, which Zenoh "
            f"does not report: {whose} (--zenoh-config {zenoh_config})")
