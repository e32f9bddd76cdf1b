"""Every measured number in the README and docs/ says where it comes from: a bench (or the
`fleetslam` command, or a test that prints it) that measures it and the commit it was
measured at, in its paragraph or at the head of its section. A number without a source
drifts unseen (the docs quoted 30 fps for one worker long after it sustained several times
that). docs/benchmarks.md (the benches
themselves), docs/decisions.md (each decision dated with its commit) and the generated
docs/config.md are left out.

Measurements are numbers in fps, ms, MB, MiB, kB or cm. Seconds are not scanned: nearly
every "N s" in the docs is a setting or a deadline (`transport.silence_hint_s` (3 s)), which
only a list of settings could tell from a measured one. A setting's value is not a
measurement either: "`key` (20 ms)" or "key = 20 ms".
"""

from __future__ import annotations

import re
from pathlib import Path

PROJECT = Path(__file__).resolve().parents[1]
LEFT_OUT = {"benchmarks.md", "decisions.md", "config.md"}

MEASURE = re.compile(r"(?<![\w.])\d+(?:\.\d+)?(?:\s*[-–]\s*\d+(?:\.\d+)?)?\s*"
                     r"(?:fps|ms|MB|MiB|kB|cm)\b")
_UNIT = r"\d+(?:\.\d+)?\s*(?:fps|ms|MB|MiB|kB|cm)\b"
SETTING = re.compile(rf"`[^`]+`\s*\(\s*{_UNIT}\s*\)|=\s*{_UNIT}")
SOURCE = re.compile(r"bench/\w+\.py|docs/benchmarks\.md|tests/test_\w+\.py|`fleetslam [^`]+`")
# A commit: 7 to 40 hex digits with a digit and a letter among them (not a word, not a number).
COMMIT = re.compile(r"\b(?=[0-9a-f]*\d)(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}\b")
# Numbers that are not measurements, each with why: (file, the phrase holding it).
NOT_MEASURED = {
    ("docs/sources.md", "at 30 fps, depth aligned"),  # the rate a RealSense is asked for
    ("docs/ros2.md", "within its 5 ms target"),  # the target, measured beside it
}
# Paragraphs measured once with no bench to run again: the phrase naming the commit.
UNBENCHED = {
    ("docs/live-view.md", "at 83b94af, by a script not kept"),
    ("docs/ros2.md", "20 ms a solve at 70 keyframes at 8d77089"),
}


def paragraphs(text: str) -> list[tuple[str, str]]:
    """(the section's caption: its heading and first paragraph, the paragraph) for every
    paragraph and list item outside code blocks."""
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    out, caption = [], ""
    for section in re.split(r"\n(?=#)", text):
        parts = [p for p in re.split(r"\n\s*\n|\n(?=\s*[-*] )", section) if p.strip()]
        caption = "\n".join(parts[:2])
        out.extend((caption, part) for part in parts)
    return out


def unsourced(name: str, text: str) -> list[str]:
    found = []
    for caption, para in paragraphs(text):
        flat = " ".join(para.split())
        if any(file == name and phrase in flat for file, phrase in UNBENCHED):
            continue
        for file, phrase in NOT_MEASURED:
            if file == name:
                para = " ".join(para.split()).replace(phrase, "")
        numbers = MEASURE.findall(SETTING.sub("", para))
        if not numbers:
            continue
        if not any(SOURCE.search(where) and COMMIT.search(where) for where in (para, caption)):
            said = ", ".join(" ".join(n.split()) for n in numbers)
            found.append(f"{name}: {said} in: {' '.join(para.split())[:120]}")
    return found


def documents() -> list[Path]:
    return [PROJECT / "README.md"] + sorted(
        p for p in (PROJECT / "docs").glob("*.md") if p.name not in LEFT_OUT)


def test_every_measured_number_in_the_docs_names_its_bench_and_commit():
    found = [line for path in documents()
             for line in unsourced(str(path.relative_to(PROJECT)), path.read_text())]
    assert not found, ("numbers without a source (a bench or `fleetslam` command and a "
                       "commit in the paragraph or at the head of its section):\n"
                       + "\n".join(found))


def test_the_scan_tells_a_sourced_number_from_an_unsourced_one():
    text = """# Title

On a 2-core machine (`bench/worker_scaling.py`, 8 robots) one worker sustains 30 fps.

At fbc1234 (`bench/inter_coding.py`): 2.5 ms a frame.

Frames are paired within `[source] pair_tolerance_s` (20 ms); a lease of 2 s.

## Latency (`bench/ros2_out.py`)

Commit 404822d, 2 runs.

| loopback | 1.09 ms |
"""
    found = unsourced("x.md", text)
    assert len(found) == 1 and "30 fps" in found[0], found
