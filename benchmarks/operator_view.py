"""The operator view during ``tupa demo``: page load to first live frame, and a screenshot.

Starts ``tupa demo`` (one scenario by default) as a child process, reads the page's address
from its output and the one-time token from the file it names, then, in headless Chromium
(Debian's ``chromium`` through Playwright, as tests/e2e/test_operator_view.py):

1. loads the page ``--loads`` times, each in a fresh browser context (no cache), and takes the
   time from the start of navigation to the first live frame (``window.tupaView.firstFrameMs``;
   issue 18's target: at most 1 s on loopback);
2. waits until the served loop's scenario has run ``--frames`` frames with its users on the map,
   and saves a screenshot (``--screenshot``, default docs/operator-view.png).

The token reaches the page as the page's own form would leave it, in the tab's sessionStorage
(an init script), never in a URL. Writes benchmarks/results/operator_view.json.

    .venv/bin/python benchmarks/operator_view.py [--loads 20] [--screenshot docs/operator-view.png]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from closed_loop.processes import TupaProcess  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "operator_view.json"


def first_frame_ms(browser: Any, url: str, token: str) -> float:
    context = browser.new_context(viewport={"width": 1400, "height": 900})
    try:
        context.add_init_script(f"sessionStorage.setItem('tupa.token', {json.dumps(token)})")
        page = context.new_page()
        page.goto(url)
        page.wait_for_function("() => window.tupaView?.frames > 0", timeout=10_000)
        return float(page.evaluate("window.tupaView.firstFrameMs"))
    finally:
        context.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--loads", type=int, default=20, help="page loads timed (default 20)")
    parser.add_argument("--frames", type=int, default=30, help="frames into the scenario")
    parser.add_argument("--steps", type=int, default=60, help="the demo's steps per scenario")
    parser.add_argument("--screenshot", type=Path, default=REPO / "docs" / "operator-view.png")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    from playwright.sync_api import sync_playwright

    chromium = os.environ.get("TUPA_CHROMIUM") or shutil.which("chromium")
    if chromium is None:
        sys.exit("chromium is missing: apt-get install chromium")
    out_dir = Path(tempfile.mkdtemp(prefix="tupa-demo-"))
    demo = TupaProcess(
        ["demo", "--n-scenarios", "1", "--steps", str(args.steps), "--out", str(out_dir)],
        "tupa-demo",
        cwd=REPO,
    )
    try:
        match = demo.wait_for_line(r"operator view: (http://\S+) .* in (\S+)\)", 300.0)
        url, token_file = match.group(1), Path(match.group(2))
        token = token_file.read_text().strip()
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=chromium)
            try:
                times = [first_frame_ms(browser, url, token) for _ in range(args.loads)]
                context = browser.new_context(viewport={"width": 1400, "height": 900})
                context.add_init_script(
                    f"sessionStorage.setItem('tupa.token', {json.dumps(token)})"
                )
                page = context.new_page()
                page.goto(url)
                page.wait_for_function(
                    "() => window.tupaView.frame && window.tupaView.frame.users.length >= 2",
                    timeout=300_000,
                )
                seen = page.evaluate("window.tupaView.frames")
                page.wait_for_function(
                    f"() => window.tupaView.frames >= {seen + args.frames}",
                    timeout=(args.frames + 60) * 1000,
                )
                args.screenshot.parent.mkdir(parents=True, exist_ok=True)
                page.screenshot(path=str(args.screenshot))
            finally:
                browser.close()
    finally:
        demo.stop()
        shutil.rmtree(out_dir, ignore_errors=True)
    ms = np.array(times)
    out = {
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "when": time.strftime("%Y-%m-%d %H:%M:%S"),
        "page_load_to_first_frame_ms": {
            "loads": len(ms),
            "p50": round(float(np.percentile(ms, 50)), 1),
            "p90": round(float(np.percentile(ms, 90)), 1),
            "max": round(float(ms.max()), 1),
        },
        "target_ms": 1000.0,
        "screenshot": str(args.screenshot.relative_to(REPO))
        if args.screenshot.is_relative_to(REPO)
        else str(args.screenshot),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
