"""Behaviour unchanged? Run the same cases with an earlier commit's code and with this work
tree's, side by side, and compare what they wrote: every .tum, .ply and .bt byte for byte,
summary.json equal with its timing keys left out.

    .venv/bin/python scripts/compare_run.py --base e3850b6
    .venv/bin/python scripts/compare_run.py --base e3850b6 --case fr1_rpy

The base commit is checked out into a temporary git worktree and run with this venv's
Python (its ``src`` first on the path), so both sides use the same libraries. The cases
read ``../shared/data``. Exit status 0: every case identical; 1: a difference (listed).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT.parent / "shared" / "data"
REDKITCHEN = DATA / "7scenes_redkitchen_seq01_f0000-0599"
CASES: dict[str, list[str]] = {
    "fr1_rpy": ["--robot", str(DATA / "tum_fr1_rpy_f000-149")],
    "redkitchen_2": ["--robot", f"{REDKITCHEN}:0-299", "--robot", f"{REDKITCHEN}:400-599"],
}
BYTE_EXACT = (".tum", ".ply", ".bt")
# With more than one thread small_gicp sums in a run-dependent order (registration/fshicp.py),
# so the same code differs from itself in the last bits; one thread makes a run repeatable.
REPEATABLE = "[fshicp]\nnum_threads = 1\n"
# Keys whose values are measured times or rates (they differ run to run by nature); the
# run's settings (under "config") are compared whole.
TIMING_KEYS = {"ms", "seconds", "fps", "tracking_fps", "wall_time_s"}


def is_timing(key: str) -> bool:
    return key in TIMING_KEYS or "_ms" in key or key.endswith("_seconds")


def without_timing(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: v if k == "config" else without_timing(v) for k, v in value.items()
                if not is_timing(k)}
    if isinstance(value, list):
        return [without_timing(v) for v in value]
    return value


def run_case(src: Path, args: list[str], out: Path, config: Path) -> None:
    env = dict(os.environ, PYTHONPATH=str(src))
    cmd = [sys.executable, "-m", "fleetslam", "run", "--quiet", "--config", str(config), *args,
           "--out", str(out)]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=1800)
    if done.returncode != 0:
        raise SystemExit(f"{src}: {' '.join(cmd)} failed ({done.returncode}):\n"
                         f"{done.stderr[-2000:]}")


def json_differences(a: Any, b: Any, where: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = [f"{where}/{k}: only in base" for k in a.keys() - b.keys()]
        out += [f"{where}/{k}: only in head" for k in b.keys() - a.keys()]
        for k in sorted(a.keys() & b.keys()):
            out += json_differences(a[k], b[k], f"{where}/{k}")
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b))
                for d in json_differences(x, y, f"{where}[{i}]")]
    return [] if a == b else [f"{where}: base {a!r} != head {b!r}"]


def compare(base: Path, head: Path) -> tuple[int, list[str]]:
    """Files compared and the differences found between two run folders."""
    problems: list[str] = []
    names = {p.relative_to(base) for p in base.rglob("*") if p.suffix in BYTE_EXACT}
    names |= {p.relative_to(head) for p in head.rglob("*") if p.suffix in BYTE_EXACT}
    for name in sorted(names):
        a, b = base / name, head / name
        if not a.exists() or not b.exists():
            problems.append(f"{name}: only in {'head' if b.exists() else 'base'}")
        elif a.read_bytes() != b.read_bytes():
            problems.append(f"{name}: bytes differ ({a.stat().st_size} vs {b.stat().st_size})")
    sa = without_timing(json.loads((base / "summary.json").read_text()))
    sb = without_timing(json.loads((head / "summary.json").read_text()))
    problems += [f"summary.json{d}" for d in json_differences(sa, sb)]
    return len(names) + 1, problems


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", required=True, help="the commit to compare against")
    parser.add_argument("--case", choices=sorted(CASES), action="append",
                        help="a case to run (default: all)")
    parser.add_argument("--keep", type=Path, help="keep both sides' run folders here")
    args = parser.parse_args()
    if not DATA.is_dir():
        raise SystemExit(f"{DATA}: the shared data is not there")
    failed = False
    with tempfile.TemporaryDirectory(prefix="compare-run-") as tmp:
        work = args.keep or Path(tmp)
        tree = Path(tmp) / "base-tree"
        config = Path(tmp) / "repeatable.toml"
        config.write_text(REPEATABLE)
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-q",
                        str(tree), args.base], check=True)
        try:
            for case in args.case or sorted(CASES):
                base_out, head_out = work / f"{case}-base", work / f"{case}-head"
                run_case(tree / "src", CASES[case], base_out, config)
                run_case(ROOT / "src", CASES[case], head_out, config)
                n, problems = compare(base_out, head_out)
                failed |= bool(problems)
                print(f"{case}: {n} files compared, "
                      + ("identical" if not problems else f"{len(problems)} differences"))
                for p in problems:
                    print(f"  {p}")
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force",
                            str(tree)], check=False)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
