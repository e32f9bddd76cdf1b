"""A Zenoh session to a ROS 2 graph's router (rmw_zenoh's ``rmw_zenohd``): what the live
ROS 2 source reads camera topics through and what ``ros2_out`` publishes through. Not the
cloud's session helpers: this router belongs to the robot's ROS 2, not to the lab."""

from __future__ import annotations

import json
import re

import zenoh

# Where in Zenoh's Rust sources an error was raised: nothing a user can act on.
_RUST_PLACE = re.compile(r"\s+at /\S+\.rs:\d+\.?")


def zenoh_reason(exc: BaseException) -> str:
    """A Zenoh error's own words, without the Rust source file it names."""
    return _RUST_PLACE.sub("", str(exc)).strip()


def open_ros_session(endpoint: str, timeout: float, zenoh_config: str = "",
                     hint: str = "") -> zenoh.Session:
    """A Zenoh client of the ROS 2 router at ``endpoint`` (a file's own settings when
    given), waiting up to ``timeout`` s for it to answer; TimeoutError saying what to
    check (``hint``: which setting names the endpoint). Timestamps are on, as in
    rmw_zenoh's default session config: its transient-local publishers need them."""
    if zenoh_config:
        try:
            config = zenoh.Config.from_file(zenoh_config)
        except zenoh.ZError as exc:
            raise ValueError(f"{zenoh_config}: not a Zenoh config file: {exc}") from None
    else:
        config = zenoh.Config()
        config.insert_json5("mode", json.dumps("client"))
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("listen/endpoints", "[]")
    config.insert_json5("timestamping/enabled", "true")
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("connect/timeout_ms", str(max(1, int(timeout * 1000))))
    config.insert_json5("connect/exit_on_failure", "true")
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        raise TimeoutError(
            f"no ROS 2 Zenoh router answers at {endpoint} after {timeout:.1f} s "
            f"({zenoh_reason(exc)}): is "
            f"the robot's router running there (ros2 run rmw_zenoh_cpp rmw_zenohd)?"
            + (f" {hint}" if hint else "")) from None
