"""Opening Zenoh sessions the way fleetslam needs them: the cloud listens on one endpoint,
robots connect to it and keep retrying, so either side may start (or restart) first."""

from __future__ import annotations

import json
import logging
import time

import zenoh

from fleetslam.transport.reachability import session_not_opened, tcp_state
from fleetslam.validation.endpoints import check_endpoint

log = logging.getLogger("fleetslam.transport")

# Reconnection pace after the cloud goes away (ms): quick first retry, capped.
_RETRY = "{period_init_ms: 200, period_max_ms: 1000, period_increase_factor: 2}"


def _base_config(path: str | None = None, mode: str = "client") -> zenoh.Config:
    """Zenoh's settings: a lab's own Zenoh config file (TLS, authentication, access control,
    routers) when given, else fleetslam's defaults: whoever listens is a router, everyone
    else its client (liveliness tokens, which cloud workers agree through, need routers).
    The endpoint is fleetslam's to set."""
    if path:
        try:
            return zenoh.Config.from_file(str(path))
        except zenoh.ZError as exc:
            raise ValueError(f"{path}: not a Zenoh config file: {exc}") from None
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    # Robots find the cloud through the configured endpoint, never by multicast: a lab
    # network full of other fleets must not join by accident.
    config.insert_json5("scouting/multicast/enabled", "false")
    return config


def _router_config(zenoh_config: str | None, block_s: float | None) -> zenoh.Config:
    config = _base_config(zenoh_config, "router")
    if block_s is not None:  # transport.router_block_s says why
        config.insert_json5("transport/link/tx/queue/congestion_control/block/"
                            "wait_before_close", str(int(block_s * 1e6)))
    return config


def _open_listener(config: zenoh.Config, endpoint: str) -> zenoh.Session:
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        # Taken since the command line checked it (check_listenable): one line, not Zenoh's.
        if "Address already in use" in str(exc):
            raise RuntimeError(f"cannot listen on {endpoint}: its port is taken (another "
                               f"Zenoh router? ROS 2's rmw_zenohd uses 7447): choose another "
                               f"with --listen") from None
        raise RuntimeError(f"cannot listen on {endpoint}: {exc}") from exc


def open_listening(endpoint: str, zenoh_config: str | None = None,
                   block_s: float | None = None) -> zenoh.Session:
    """A router listening on ``endpoint`` (a lone cloud, or ``fleetslam router``);
    ``block_s``: ``transport.router_block_s``."""
    # The command line checked its flags already; this covers every other caller.
    check_endpoint(endpoint, "endpoint", zenoh_config)
    config = _router_config(zenoh_config, block_s)
    config.insert_json5("listen/endpoints", json.dumps([endpoint]))
    return _open_listener(config, endpoint)


def open_router(endpoint: str, others: list[str] | None = None,
                zenoh_config: str | None = None, block_s: float | None = None
                ) -> zenoh.Session:
    """A router of its own on ``endpoint``, joined to the ``others`` (kept retrying);
    ``block_s``: ``transport.router_block_s``."""
    for each in [endpoint, *(others or [])]:
        check_endpoint(each, "endpoint", zenoh_config)
    config = _router_config(zenoh_config, block_s)
    config.insert_json5("listen/endpoints", json.dumps([endpoint]))
    if others:
        config.insert_json5("connect/endpoints", json.dumps(others))
        config.insert_json5("connect/exit_on_failure", "false")
        config.insert_json5("connect/timeout_ms", "-1")
        config.insert_json5("connect/retry", _RETRY)
    return _open_listener(config, endpoint)


def _probe_config(endpoint: str, deadline_s: float, attempt_s: float,
                  zenoh_config: str | None) -> zenoh.Config:
    probe = _base_config(zenoh_config)
    probe.insert_json5("connect/endpoints", json.dumps([endpoint]))
    probe.insert_json5("connect/exit_on_failure", "true")
    probe.insert_json5("connect/timeout_ms", str(int(min(attempt_s, max(deadline_s, 0.1))
                                                     * 1000)))
    probe.insert_json5("listen/endpoints", "[]")
    return probe


def wait_until_reachable(endpoint: str, deadline_s: float, attempt_s: float = 2.0,
                         zenoh_config: str | None = None,
                         setting: str = "transport.reach_deadline_s",
                         refused_ends: bool = False) -> None:
    """Block until something answers at ``endpoint``, saying so at once and on every failed
    attempt (the first time with what to check, and ``setting``, the wait's name);
    RuntimeError after ``deadline_s`` seconds, naming what to check; ValueError at once for
    an endpoint that cannot work (its form, an unknown host, TLS without certificates).
    ``refused_ends``: a refused connection (nothing listens) is the answer, at once: an
    operator's command, where a robot's wait is for a cloud starting after it."""
    check_endpoint(endpoint, "endpoint", zenoh_config)
    probe = _probe_config(endpoint, deadline_s, attempt_s, zenoh_config)
    start = time.monotonic()
    attempt = 0
    # Known in milliseconds, where Zenoh's attempt says only "Timeout!" after attempt_s.
    if tcp_state(endpoint) == "refused":
        attempt = 1
        why = session_not_opened(endpoint, zenoh_config)
        if refused_ends:
            raise RuntimeError(f"no cloud at {endpoint}: {why}")
        log.warning("no cloud answers at %s yet; retrying for up to %.0f s (%s): %s",
                    endpoint, deadline_s, setting, why)
    while True:
        attempt += 1
        try:
            zenoh.open(probe).close()
            if attempt > 1:
                log.warning("%s answers now (attempt %d)", endpoint, attempt)
            return
        except zenoh.ZError:  # Zenoh says only "Timeout!", whatever the cause
            waited = time.monotonic() - start
            if waited >= deadline_s:
                raise RuntimeError(f"nothing answers at {endpoint} after {waited:.0f} s "
                                   f"({attempt} attempt{'s' if attempt > 1 else ''}, "
                                   f"{setting}): "
                                   f"{session_not_opened(endpoint, zenoh_config)}") from None
            if attempt == 1:
                log.warning("no cloud answers at %s yet; retrying for up to %.0f s (%s): %s",
                            endpoint, deadline_s, setting,
                            session_not_opened(endpoint, zenoh_config))
            else:
                log.warning("nothing answers at %s yet (attempt %d, %.0f s of %.0f); "
                            "retrying", endpoint, attempt, waited, deadline_s)


def open_connecting(endpoint: str, deadline_s: float = 600.0,
                    zenoh_config: str | None = None, lease_s: float | None = None,
                    setting: str = "transport.reach_deadline_s", refused_ends: bool = False
                    ) -> zenoh.Session:
    """Connect to ``endpoint`` once something answers there (saying so while it waits, up to
    ``deadline_s``, ``setting``; ``refused_ends``: as :func:`wait_until_reachable`); the
    session then reconnects by itself if the cloud restarts. ``lease_s``: the lease this
    session announces (None: Zenoh's, 10 s): the router drops the link that long after it
    last heard from this session."""
    wait_until_reachable(endpoint, deadline_s, zenoh_config=zenoh_config, setting=setting,
                         refused_ends=refused_ends)
    config = _base_config(zenoh_config)
    if lease_s is not None:
        config.insert_json5("transport/link/tx/lease", str(int(lease_s * 1000)))
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("connect/exit_on_failure", "false")
    config.insert_json5("connect/timeout_ms", "-1")
    config.insert_json5("connect/retry", _RETRY)
    config.insert_json5("listen/endpoints", "[]")
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        raise RuntimeError(f"cannot connect to {endpoint}: {exc}") from exc


def put(session: zenoh.Session, key: str, data: bytes, droppable: bool = False) -> None:
    """Publish without Zenoh dropping it under a burst: the emulated link decides losses,
    the transport must not add its own. ``droppable``: a message its receiver can do
    without (it recovers it otherwise): dropped rather than waited for behind a full queue.
    A router forwards a message that may not be dropped by waiting on each receiver's
    queue, so one unreachable receiver would hold up its sender's other messages."""
    session.put(key, data, congestion_control=zenoh.CongestionControl.DROP if droppable
                else zenoh.CongestionControl.BLOCK)
