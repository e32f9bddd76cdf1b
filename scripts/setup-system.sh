#!/bin/sh
# System packages fleetslam needs: a Python 3.11+ with venv and pip, and libusb for the
# pyrealsense2 wheel (the realsense extra; its wheel links libusb-1.0.so.0 but does not ship
# it), and etcd for many cloud workers (Debian's etcd-server). Everything else comes from PyPI
# wheels (OpenCV headless, small_gicp, ...), which need no system libraries.
set -e
PYTHON="${1:-python3}"
need_install=0
if ! command -v "$PYTHON" >/dev/null 2>&1; then
    need_install=1
elif ! "$PYTHON" -c 'import sys, venv, ensurepip; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
    need_install=1
fi
if [ "$need_install" = 1 ]; then
    if command -v apt-get >/dev/null 2>&1; then
        SUDO=""
        [ "$(id -u)" = 0 ] || SUDO="sudo"
        $SUDO apt-get update -qq
        $SUDO apt-get install -y -qq python3 python3-venv python3-pip
    else
        echo "fleetslam needs Python >= 3.11 with venv; install it and rerun" >&2
        exit 1
    fi
fi
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
    if command -v apt-get >/dev/null 2>&1; then
        SUDO=""
        [ "$(id -u)" = 0 ] || SUDO="sudo"
        # Not fatal: without it only a RealSense cannot be opened (its tests skip).
        { $SUDO apt-get update -qq && $SUDO apt-get install -y -qq libusb-1.0-0; } ||
            echo "could not install libusb-1.0: a RealSense cannot be opened here" >&2
    else
        echo "pyrealsense2 (the realsense extra) needs libusb-1.0; install it for RealSense" >&2
    fi
fi
# etcd, the coordination service many cloud workers agree on robot ownership through
# (cloud/coordination/coordination_service.py; `fleetslam demo --workers N` starts one per run). The
# package's own service is not needed (each run starts its own etcd on loopback).
if ! command -v etcd >/dev/null 2>&1; then
    if command -v apt-get >/dev/null 2>&1; then
        SUDO=""
        [ "$(id -u)" = 0 ] || SUDO="sudo"
        # Not fatal: a single cloud process never needs it (the many-worker tests skip).
        if { $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq etcd-server; }; then
            # Debian enables and starts its own etcd.service (plain HTTP on 2379, at every
            # boot): fleetslam runs its own, so the one we installed is stopped and disabled
            # where systemd runs (/run/systemd/system: systemd is PID 1; not in a container).
            if command -v systemctl >/dev/null 2>&1 && [ -d /run/systemd/system ]; then
                $SUDO systemctl disable --now etcd.service ||
                    echo "could not disable Debian's etcd.service: an etcd listens on 2379" >&2
            fi
        else
            echo "could not install etcd-server: many cloud workers cannot run here" >&2
        fi
    else
        echo "many cloud workers need etcd (3.4+) on PATH; install it for them" >&2
    fi
fi
