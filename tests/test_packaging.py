"""The built wheel is what a `pip install` outside a checkout gets: it must build without
deprecation warnings, hold every file of the package (modules and any package data), declare
the `fleetslam` command, and import and run from another directory with nothing of the
checkout on the path.

This builds the wheel (pip, ~7 s) but does not make a venv and install the cloud extra (over
a minute): scripts/check-wheel.sh does that and runs `fleetslam demo --in-process` from
another directory.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from conftest import PROJECT

PACKAGE = PROJECT / "src" / "fleetslam"


def _package_files() -> set[str]:
    """Every file of the source package, as a wheel names it (bytecode left out)."""
    return {p.relative_to(PACKAGE.parent).as_posix() for p in PACKAGE.rglob("*")
            if p.is_file() and "__pycache__" not in p.parts and p.suffix != ".pyc"}


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> tuple[Path, str]:
    """(the wheel built from a copy of the project, the build's output). A copy: the build
    writes build/ and *.egg-info beside the sources."""
    root = tmp_path_factory.mktemp("wheel")
    copy = root / "project"
    copy.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(PROJECT / name, copy / name)
    shutil.copytree(PROJECT / "src", copy / "src",
                    ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(copy), "--no-deps", "--no-cache-dir",
         "-w", str(root / "dist")], capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stdout + build.stderr
    wheels = list((root / "dist").glob("fleetslam-*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0], build.stdout + build.stderr


def test_wheel_builds_without_deprecation_warnings(wheel):
    # setuptools names the date a deprecated pyproject form stops building.
    _, log = wheel
    assert "Warning" not in log and "deprecated" not in log, log


def test_wheel_holds_the_whole_package_and_the_command(wheel):
    path, _ = wheel
    with zipfile.ZipFile(path) as z:
        names = set(z.namelist())
        entry_points = next(z.read(n).decode() for n in names
                            if n.endswith(".dist-info/entry_points.txt"))
    missing = _package_files() - names
    assert not missing, f"not in the wheel: {sorted(missing)}"
    assert "fleetslam = fleetslam.cli:main" in entry_points
    # Nothing of the checkout besides the package (tests, bench, scripts stay out).
    version = path.name.split("-")[1]
    assert {n.split("/")[0] for n in names} == {"fleetslam", f"fleetslam-{version}.dist-info"}


def test_unpacked_wheel_imports_and_runs_from_another_directory(wheel, tmp_path):
    """Every module imports from the unpacked wheel alone (no checkout on the path, the
    working directory elsewhere), and the command answers."""
    path, _ = wheel
    site = tmp_path / "site"
    with zipfile.ZipFile(path) as z:
        z.extractall(site)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site)}
    check = (
        "import importlib, pkgutil, fleetslam, sys\n"
        f"assert fleetslam.__file__.startswith({str(site)!r}), fleetslam.__file__\n"
        "for m in pkgutil.walk_packages(fleetslam.__path__, 'fleetslam.'):\n"
        "    if m.name != 'fleetslam.__main__':  # it runs the command\n"
        "        importlib.import_module(m.name)\n"
        "outside = [n for n, m in sys.modules.items() if n.startswith('fleetslam')\n"
        f"           and not (m.__file__ or '').startswith({str(site)!r})]\n"
        "assert not outside, outside\n")
    # -I would drop PYTHONPATH too: -P keeps the working directory off the path instead.
    result = subprocess.run([sys.executable, "-P", "-c", check], cwd=elsewhere, env=env,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    result = subprocess.run([sys.executable, "-P", "-m", "fleetslam", "--help"],
                            cwd=elsewhere, env=env, capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 0 and "demo" in result.stdout, result.stderr
