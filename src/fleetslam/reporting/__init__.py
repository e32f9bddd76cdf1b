"""A finished run's report: ``<run>/report/`` with PNG plots and ``report.html`` showing them
with the summary's tables (``run``: load the folder, ``plots``: the figures, ``html``: the
page). ``fleetslam report RUN_DIR`` rebuilds it."""

from __future__ import annotations

import threading
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from fleetslam.progress import Progress

if TYPE_CHECKING:
    from fleetslam.reporting.run import RunData

# pyplot keeps global state: reports made by threads of one process (the cloud answers each
# merge request on its own thread) take turns.
_LOCK = threading.Lock()


def write_report(folder: Path, ground_truth: bool = True, show_progress: bool = False,
                 groundtruth: Sequence[str] = ()) -> Path:
    """Write ``folder/report/`` (replacing the report's own files) and return the path of
    report.html. ValueError if ``folder`` holds no summary.json. ``ground_truth``: read each
    robot's ground truth for the scores and the plots that need it (the cloud does not);
    ``groundtruth``: ``--groundtruth`` values (reporting.run.load_run)."""
    from fleetslam.reporting.run import load_run

    folder = Path(folder)
    with _LOCK:
        run = load_run(folder, ground_truth, groundtruth)
        return _write(run, folder / "report", show_progress)


def _write(run: RunData, out: Path, show_progress: bool) -> Path:
    from fleetslam.reporting.html import render_page
    from fleetslam.reporting.plots import PLOTS, Figure

    out.mkdir(exist_ok=True)
    figures: list[Figure] = []
    skipped: dict[str, str] = {}
    # Counted as checked: a plot the run has no data for is left out, not written.
    progress = Progress(f"report {out}", len(PLOTS), "plots checked", enabled=show_progress)
    for i, (name, plot) in enumerate(PLOTS):
        path = out / name
        path.unlink(missing_ok=True)  # a plot this run no longer has must not linger
        result = plot(run, path)
        if isinstance(result, str):
            skipped[name] = result
        elif name != "overview.png":  # the overview repeats the others (README picture)
            figures.append(result)
        progress.update(i + 1, f"{i + 1 - len(skipped)} PNG written, {len(skipped)} left out "
                               f"(no data)")
    page = out / "report.html"
    page.write_text(render_page(run, figures, skipped))
    return page
