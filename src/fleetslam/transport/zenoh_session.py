"""Opening Zenoh sessions the way fleetslam needs them: the cloud listens on one endpoint,
robots connect to it and keep retrying, so either side may start (or restart) first."""

from __future__ import annotations

import json
import logging

import zenoh

log = logging.getLogger("fleetslam.transport")

# Reconnection pace after the cloud goes away (ms): quick first retry, capped.
_RETRY = "{period_init_ms: 200, period_max_ms: 1000, period_increase_factor: 2}"


def _base_config() -> zenoh.Config:
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    # Robots find the cloud through the configured endpoint, never by multicast: a lab
    # network full of other fleets must not join by accident.
    config.insert_json5("scouting/multicast/enabled", "false")
    return config


def open_listening(endpoint: str) -> zenoh.Session:
    config = _base_config()
    config.insert_json5("listen/endpoints", json.dumps([endpoint]))
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        raise RuntimeError(f"cannot listen on {endpoint}: {exc}") from exc


def open_connecting(endpoint: str) -> zenoh.Session:
    """Connect to ``endpoint``; blocks until the cloud is reachable, and reconnects after."""
    config = _base_config()
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("connect/exit_on_failure", "false")
    config.insert_json5("connect/timeout_ms", "-1")
    config.insert_json5("connect/retry", _RETRY)
    config.insert_json5("listen/endpoints", "[]")
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        raise RuntimeError(f"cannot connect to {endpoint}: {exc}") from exc


def put(session: zenoh.Session, key: str, data: bytes) -> None:
    """Publish without Zenoh dropping it under a burst: the emulated link decides losses,
    the transport must not add its own."""
    session.put(key, data, congestion_control=zenoh.CongestionControl.BLOCK)
