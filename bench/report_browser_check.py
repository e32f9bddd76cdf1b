"""Open run reports in a real headless browser: every image shown, no console error, nothing
fetched from the network.

    .venv/bin/python bench/report_browser_check.py RUN_DIR_or_report.html [...]
        [--chromium /usr/bin/chromium] [--screenshot shot.png]

A check tool, not a dependency of fleetslam: it needs Playwright for Python
(``.venv/bin/pip install playwright``) and a Chromium, e.g. Debian's
(``apt-get install chromium``; used by default from /usr/bin/chromium, so no
``playwright install`` download is needed).

Each page is opened as file:// (as a user double-clicks it). Reported per page: images whose
naturalWidth is 0 (missing or undecodable), console errors and page errors, and any request
that is not file:// (the page must work offline). Exit status 1 if any page has a problem.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def check(page_path: Path, browser, screenshot: Path | None) -> list[str]:
    """Problems of one report page (empty: none)."""
    problems: list[str] = []
    page = browser.new_page(viewport={"width": 1200, "height": 900})
    page.on("console", lambda m: problems.append(f"console {m.type}: {m.text}")
            if m.type == "error" else None)
    page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
    page.on("request", lambda r: problems.append(f"network request: {r.url}")
            if not r.url.startswith("file://") else None)
    page.goto(page_path.resolve().as_uri(), wait_until="load")
    images = page.eval_on_selector_all(
        "img", "els => els.map(e => [e.getAttribute('src'), e.complete, e.naturalWidth,"
               " e.naturalHeight])")
    if not images:
        problems.append("no images on the page")
    for src, complete, width, height in images:
        if not complete or width == 0:
            problems.append(f"image not shown: {src}")
    print(f"{page_path}: {len(images)} images, "
          + ", ".join(f"{src} {w}x{h}" for src, _, w, h in images))
    if screenshot is not None:
        page.screenshot(path=str(screenshot), full_page=True)
    page.close()
    return problems


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("pages", nargs="+", help="report.html files or run folders")
    parser.add_argument("--chromium", default="/usr/bin/chromium",
                        help="the Chromium executable (default /usr/bin/chromium)")
    parser.add_argument("--screenshot", type=Path,
                        help="save a full-page screenshot of the first page here")
    args = parser.parse_args()
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        print("needs Playwright: .venv/bin/pip install playwright", file=sys.stderr)
        return 2
    failed = 0
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=args.chromium, headless=True)
        for i, given in enumerate(args.pages):
            path = Path(given)
            if path.is_dir():
                path = path / "report" / "report.html"
            if not path.is_file():
                print(f"{path}: no such report page", file=sys.stderr)
                failed += 1
                continue
            problems = check(path, browser, args.screenshot if i == 0 else None)
            for problem in problems:
                print(f"  PROBLEM {problem}")
            print(f"  {'OK' if not problems else f'{len(problems)} problems'}")
            failed += bool(problems)
        browser.close()
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
