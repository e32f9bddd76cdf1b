"""Opening a rerun recording: to a file, to a viewer spawned on this machine's display, or
served over gRPC for a viewer to connect to. rerun is optional; without it every entry point
says how to install it."""

from __future__ import annotations

import os
import shutil
import socket
import sys
from pathlib import Path
from typing import Any

from fleetslam.config import ViewConfig

INSTALL_HINT = "pip install 'fleetslam[view]'"
APPLICATION_ID = "fleetslam"
# The viewer a display would show is spawned listening here (rerun's default).
SPAWN_PORT = 9876


class ViewUnavailable(RuntimeError):
    """The view cannot be opened (rerun missing, no display, port taken)."""


def import_rerun() -> Any:
    try:
        import rerun
    except ImportError as exc:
        raise ViewUnavailable(f"the view needs rerun, which is not installed here: "
                              f"{INSTALL_HINT}") from exc
    return rerun


def _viewer_executable() -> str | None:
    """rerun's viewer: on PATH, or beside this Python (a venv used without activating)."""
    beside = Path(sys.executable).with_name("rerun")
    return shutil.which("rerun") or (str(beside) if beside.exists() else None)


def can_spawn_viewer() -> bool:
    """A viewer window can be opened here: a display (or not Linux) and rerun's viewer."""
    display = not sys.platform.startswith("linux") or bool(
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return display and _viewer_executable() is not None


def grpc_url(config: ViewConfig) -> str:
    host = "127.0.0.1" if config.grpc_bind in ("0.0.0.0", "::") else config.grpc_bind
    return f"rerun+http://{host}:{config.grpc_port}/proxy"


def live_plan(config: ViewConfig, save: Path | None, live: bool) -> list[str]:
    """What a view opened with these options does, one line each (printed by the command
    that opens it, and by the demo for its cloud process)."""
    lines = []
    if save is not None:
        lines.append(f"view: recording to {save} (replay: rerun {save})")
    if live and can_spawn_viewer():
        lines.append("view: spawning a rerun viewer")
    elif live:
        lines.append(f"view: no display to open a viewer on; serving the live view at "
                     f"{grpc_url(config)} (connect: rerun {grpc_url(config)})")
    return lines


def _check_port_free(bind: str, port: int) -> None:
    family = socket.AF_INET6 if ":" in bind else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((bind, port))
        except OSError as exc:
            raise ViewUnavailable(f"cannot serve the view on {bind}:{port}: {exc} (another "
                                  f"viewer or cloud? set [view] grpc_port)") from exc


def open_recording(config: ViewConfig, save: Path | None, live: bool,
                   recording_id: str | None = None) -> Any:
    """A rerun RecordingStream writing to ``save`` (an .rrd file) and, if ``live``, to a
    viewer: spawned when this machine has a display, else served over gRPC on
    ``config.grpc_bind:grpc_port``."""
    rr = import_rerun()
    if save is None and not live:
        raise ValueError("a view needs a file to save to, a viewer, or both")
    sinks = []
    if save is not None:
        save = Path(save)
        save.parent.mkdir(parents=True, exist_ok=True)
        sinks.append(rr.FileSink(str(save)))
    if live and can_spawn_viewer():
        try:
            rr.spawn(port=SPAWN_PORT, connect=False, executable_path=_viewer_executable())
        except Exception as exc:
            raise ViewUnavailable(f"could not spawn a rerun viewer: {exc}") from exc
        sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{SPAWN_PORT}/proxy"))
    elif live:
        _check_port_free(config.grpc_bind, config.grpc_port)
        sinks.append(rr.GrpcServerSink(config.grpc_bind, config.grpc_port,
                                       server_memory_limit=config.server_memory_limit))
    recording = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
    recording.set_sinks(*sinks)
    return recording


def close_recording(recording: Any) -> None:
    """Everything logged reaches its sinks; a file gets its footer (rerun's readers need
    it)."""
    recording.flush()
    recording.disconnect()
