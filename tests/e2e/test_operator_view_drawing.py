"""The operator view's drawing in a real browser (headless Chromium through Playwright), fed one
hand-made frame: no service, no autopilot. Every request of the page is answered here
(``page.route``): the page and its files from ``api/static/``, and the live stream as one
Server-Sent Event carrying the frame.

What issue 42 found on the page: the utility chart had no values on its y axis and drew
straight lines across the minutes without a report; big user circles spilled past the area, and
the labels of users close together overlapped.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from tests.e2e.test_operator_view import chromium
from tests.tiers import needs

STATIC = Path(__file__).resolve().parents[2] / "api" / "static"
TYPES = {".html": "text/html", ".js": "text/javascript", ".css": "text/css"}


def _history() -> list[list[float]]:
    """Reports every second for 20 s, none for 40 s, then every second for 20 s."""
    points = [*range(0, 21), *range(60, 81)]
    return [[float(t), 0.8, 0.5, 0.2, 0.1] for t in points]


def _user(user_id: str, x_m: float, y_m: float, offered_bps: float) -> dict[str, Any]:
    return {"id": user_id, "x_m": x_m, "y_m": y_m, "offered_bps": offered_bps,
            "throughput_bps": offered_bps / 2, "delay_s": 0.05, "plr": 0.01,
            "served": 0.5}  # fmt: skip


def _frame(time_s: float = 80.0) -> dict[str, Any]:
    users = [
        _user("corner", 5.0, 5.0, 100e6),  # a radius of 40 m, at the area's corner
        _user("edge", 497.0, 250.0, 1e6),  # its label would run past the area's east edge
        *(_user(f"crowd-{i}", 250.0 + 3 * i, 300.0 + 2 * i, 2e6) for i in range(6)),
    ]
    return {
        "format": "tupa-live/1", "seq": 1, "time_s": time_s, "decision_period_s": 1.0,
        "area": {"size_x_m": 500, "size_y_m": 500, "zone_m": 25, "z_min_m": 25, "z_max_m": 100},
        "geofence": {"x_m": [0, 500], "y_m": [0, 500], "z_m": [25, 100]},
        "envelopes": [{
            "inclusion": [[0, 0], [500, 0], [500, 500], [0, 500]], "floor_m": 25,
            "ceiling_m": 100, "clearance_m": 5,
            "exclusions": [{"name": "helipad", "polygon": [[210, 210], [240, 210], [240, 240],
                                                           [210, 240]],
                            "floor_m": 0, "ceiling_m": 60}],
        }],
        "policy": {"name": "oracle", "spec": "oracle"},
        "vehicles": [{
            "id": "uav1", "link": "up", "mode": "OFFBOARD", "armed": True, "flavour": "px4",
            "streaming": True, "control": {"holder": "service", "reason": ""},
            "heartbeat_age_s": 0.2, "position_m": [200.0, 200.0, 30.0], "heading_deg": None,
            "target_m": [250.0, 250.0, 30.0], "track_m": [[250.0, 250.0, 25.0]],
            "decision": None, "envelope": 0,
            "route": {"kind": "around", "hold_reason": None,
                      "waypoints_m": [[204.5, 245.5, 30.0], [250.0, 250.0, 30.0]]},
            "battery": {"remaining_pct": 83.0, "return_at_pct": 27.4},
        }],
        "users": users,
        "report": {"timestamp": 1.0, "age_s": 0.5, "stale": False},
        "utility": {"t_s": 80.0, "value": 0.8, "throughput": 0.5, "delay": 0.2, "loss": 0.1,
                    "delay_ref_s": 1.0},
        "utility_history": _history(),
    }  # fmt: skip


@pytest.fixture
@needs("browser")
def page() -> Any:
    """A page showing :func:`_frame`, every request answered here."""
    from playwright.sync_api import sync_playwright

    body = f"event: frame\ndata: {json.dumps(_frame())}\n\n"

    def answer(route: Any) -> None:
        path = route.request.url.split("tupa.test", 1)[1].split("?")[0]
        if path == "/v1/live/events":
            route.fulfill(status=200, body=body, headers={"Content-Type": "text/event-stream"})
            return
        name = "index.html" if path in ("/", "/ui") else path.removeprefix("/ui/")
        file = STATIC / name
        if not file.is_file():
            route.fulfill(status=404, body="")
            return
        route.fulfill(status=200, body=file.read_bytes(),
                      headers={"Content-Type": TYPES[file.suffix]})  # fmt: skip

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=chromium())
        context = browser.new_context(viewport={"width": 1400, "height": 900})
        context.add_init_script("sessionStorage.setItem('tupa.token', 'test')")
        context.route("**/*", answer)
        page = context.new_page()
        page.goto("http://tupa.test/ui")
        page.wait_for_function("() => window.tupaView && window.tupaView.frames > 0")
        try:
            yield page
        finally:
            browser.close()


def test_the_utility_chart_has_y_values_and_breaks_at_gaps_without_reports(page: Any) -> None:
    ticks = page.eval_on_selector_all("#chart text.chart-tick", "ts => ts.map(t => t.textContent)")
    assert ticks == ["0", "0.25", "0.5", "0.75", "1"], ticks
    # The 40 s without a report: no line across it, the gap shaded and said.
    assert page.locator("#chart polyline.s-value").count() == 2
    gaps = page.locator("#chart rect.chart-gap")
    assert gaps.count() == 1
    assert "no report for 40 s" in gaps.first.text_content()
    # Each line stays on its side of the gap.
    spans = page.eval_on_selector(
        "#chart rect.chart-gap",
        """gap => {
            const xs = (p) => p.getAttribute('points').split(' ').map(q => Number(q.split(',')[0]));
            const x = Number(gap.getAttribute('x'));
            const lines = [...document.querySelectorAll('#chart polyline.s-value')].map(xs);
            return [x, x + Number(gap.getAttribute('width')), ...lines];
        }""",
    )
    gap_start, gap_end, before, after = spans
    assert max(before) <= gap_start + 0.1 and min(after) >= gap_end - 0.1


def test_user_circles_are_clipped_to_the_area_and_labels_do_not_overlap(page: Any) -> None:
    clip = page.eval_on_selector(
        "#layer-users",
        """g => {
            const id = (g.getAttribute('clip-path') || '').match(/url\\(#(.+)\\)/);
            const rect = id && document.querySelector(`#${id[1]} rect`);
            return rect && ['x', 'y', 'width', 'height'].map(k => Number(rect.getAttribute(k)));
        }""",
    )
    assert clip == [0, 0, 500, 500]
    boxes = page.eval_on_selector_all(
        "text.user-label",
        """ts => ts.filter(t => t.textContent && t.style.display !== 'none').map(t => {
            const b = t.getBBox();
            return [t.textContent, b.x, b.y, b.x + b.width, b.y + b.height];
        })""",
    )
    shown = {b[0] for b in boxes}
    assert {"corner", "edge"} <= shown and len(shown) >= 4, shown
    for i, a in enumerate(boxes):
        assert a[1] >= 0 and a[3] <= 500 and a[2] >= 0 and a[4] <= 500, a  # inside the area
        for b in boxes[i + 1 :]:
            overlap = a[1] < b[3] and b[1] < a[3] and a[2] < b[4] and b[2] < a[4]
            assert not overlap, (a, b)
    # A label left out still names its user: the circle's tooltip.
    titles = page.eval_on_selector_all("circle.user title", "ts => ts.map(t => t.textContent)")
    assert all(any(t.startswith(f"crowd-{i}:") for t in titles) for i in range(6))


def test_the_envelope_the_route_and_the_battery_are_shown(page: Any) -> None:
    """Issue 39: the no-fly volume drawn and named with its top, the altitude band in the
    legend, the bent route drawn instead of the straight line, the battery on the card."""
    zone = page.locator("#layer-envelope polygon.exclusion[data-name='helipad']")
    assert zone.count() == 1
    assert "helipad: no flight 0–60 m" in zone.locator("title").text_content()
    assert page.locator("#layer-envelope polygon.inclusion").count() == 1
    legend = page.locator("#envelope-legend").text_content()
    assert "altitude 25–100 m" in legend and "1 no-fly volume" in legend, legend
    route = page.locator("polyline.route")
    assert route.get_attribute("data-kind") == "around" and route.is_visible()
    assert route.get_attribute("points").split(" ")[0] == "200,300"  # from the vehicle (y flipped)
    assert not page.locator("line.target-line").is_visible()
    assert page.locator("[data-testid='route-uav1']").text_content() == "around, 2 waypoints left"
    assert page.locator("[data-testid='battery-uav1']").text_content() == "83 % · home at 27 %"
