"""Where the benchmarks find the real data: ../shared/data beside the project root."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SEVEN_SCENES = DATA / "7scenes_redkitchen_seq01_f0000-0599"
TUM_RPY = DATA / "tum_fr1_rpy_f000-149"
# The tracked sequences, by the name the benchmark tables use.
SEQUENCES = {
    "7scenes_redkitchen_0-599": SEVEN_SCENES,
    "tum_fr1_rpy_0-149": TUM_RPY,
}


def present_sequences() -> Iterator[tuple[str, Path]]:
    """(name, folder) of every tracked sequence that is there; says which are skipped."""
    for name, folder in SEQUENCES.items():
        if folder.exists():
            yield name, folder
        else:
            print(f"skip {name}: {folder} missing")
