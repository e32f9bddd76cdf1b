"""The run report: plots and a page that opens from disk, for runs with and without ground
truth; ``fleetslam report`` on a folder that is not a run."""

from __future__ import annotations

import json
import re
import shutil
from html.parser import HTMLParser
from pathlib import Path

import pytest
from PIL import Image

from conftest import small_scene

from fleetslam.cli import main
from fleetslam.config import Config
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.datasets.recording import open_source
from fleetslam.reporting import write_report
from fleetslam.system import run_fleet

FRAMES = 20


class _Images(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.sources: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        if tag == "img":
            self.sources.append(dict(attrs)["src"] or "")


def check_page(page: Path) -> list[str]:
    """Every image of the page is a file beside it and a valid PNG; nothing from the
    network. Returns the image names."""
    text = page.read_text()
    assert not re.search(r"https?://", text), "the page must open without a network"
    parser = _Images()
    parser.feed(text)
    assert parser.sources
    for src in parser.sources:
        path = page.parent / src
        assert "/" not in src and path.is_file(), src
        with Image.open(path) as image:
            image.verify()
            assert image.format == "PNG"
    for png in page.parent.glob("*.png"):
        with Image.open(png) as image:
            image.verify()
    return parser.sources


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    config = Config()
    config.synthetic.frames_per_robot = FRAMES
    folders = small_scene(tmp_path_factory, FRAMES)
    out = tmp_path_factory.mktemp("runs") / "run"
    robots = [(f"r{i}", str(f), RgbdSequence(f)) for i, f in enumerate(folders)]
    run_fleet(robots, config, out, show_progress=False)
    return out


def test_report_of_a_merged_run_with_ground_truth(run_dir, capsys):
    assert main(["--quiet", "report", str(run_dir)]) == 0
    page = Path(capsys.readouterr().out.strip())
    assert page == run_dir / "report" / "report.html"
    images = check_page(page)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["merge"]["members"] == ["r0", "r1"]
    # Everything but the link (a run in one process has none) is shown.
    assert set(images) == {"trajectories_global.png", "trajectories_own.png",
                           "error_over_time.png", "global_map.png", "stage_times.png",
                           "merge_events.png"}
    assert (run_dir / "report" / "overview.png").is_file()
    text = page.read_text()
    assert "Ground truth (evaluation only" in text and "joint ATE" in text
    # The cloud's report of the same folder: no ground truth read, the rest all there.
    images = check_page(write_report(run_dir, ground_truth=False))
    assert "error_over_time.png" not in images and "global_map.png" in images
    assert not (run_dir / "report" / "error_over_time.png").exists()
    assert "Ground truth: not read" in page.read_text()


def test_report_without_ground_truth(run_dir, tmp_path):
    """A robot whose recording has no groundtruth.txt: every plot that does not need it."""
    source = Path(json.loads((run_dir / "summary.json").read_text())["robots"][0]["source"])
    copy = tmp_path / "no_gt"
    shutil.copytree(source, copy)
    (copy / "groundtruth.txt").unlink()
    out = tmp_path / "run"
    run_fleet([("solo", f"{copy}:0-11", open_source(f"{copy}:0-11"))], Config(), out,
              show_progress=False)
    images = check_page(write_report(out))
    assert "error_over_time.png" not in images and "trajectories_own.png" in images
    assert "stage_times.png" in images
    text = (out / "report" / "report.html").read_text()
    assert "Ground truth: none for this run" in text
    assert "no groundtruth.txt" in text


def test_report_names_a_folder_without_summary(tmp_path, capsys):
    assert main(["--quiet", "report", str(tmp_path)]) == 2
    assert f"{tmp_path}: no summary.json" in capsys.readouterr().err
    assert not (tmp_path / "report").exists()


def test_report_from_another_directory_finds_ground_truth(run_dir, tmp_path, monkeypatch,
                                                          capsys):
    """A run given a relative source, reported from elsewhere: the summary names the source
    absolutely, so the report still reads its ground truth."""
    source = Path(json.loads((run_dir / "summary.json").read_text())["robots"][0]["source"])
    monkeypatch.chdir(source.parent)
    out = tmp_path / "run"
    assert main(["--quiet", "run", "--robot", f"{source.name}:0-11", "--out", str(out)]) == 0
    assert json.loads((out / "summary.json").read_text())["robots"][0]["source"] == \
        f"{source}:0-11"
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    capsys.readouterr()
    assert main(["--quiet", "report", "../run"]) == 0
    text = Path(capsys.readouterr().out.strip()).read_text()
    assert "Ground truth (evaluation only" in text and "Ground truth: none" not in text


def test_report_progress_counts_the_pngs_written(run_dir, capsys):
    """Plots the run has no data for are checked, not written: the progress says which."""
    write_report(run_dir, ground_truth=False, show_progress=True)
    written = len(list((run_dir / "report").glob("*.png")))
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert "8/8 plots checked" in last
    assert last.endswith(f"{written} PNG written, {8 - written} left out (no data)"), last


def test_report_of_an_older_run_with_a_relative_source_says_where_from(run_dir, tmp_path):
    """A run made before sources were stored absolute: the page says why ground truth is
    missing and where to run the command from."""
    old = tmp_path / "old"
    shutil.copytree(run_dir, old)
    summary = json.loads((old / "summary.json").read_text())
    summary["robots"][0]["source"] = "relative/robot_0:0-19"
    (old / "summary.json").write_text(json.dumps(summary))
    text = write_report(old).read_text()
    assert ("relative/robot_0: no such sequence folder; the path is relative to the directory "
            "the run was started in: run `fleetslam report` from there") in text
