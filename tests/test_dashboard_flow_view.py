"""The dashboard's GNSS + optic-flow view in headless Chromium: a real ``companion dashboard`` process
joined to two real zenoh peers on loopback (scouting off). Vehicle 1 publishes what a daemon running
the ``gnss_flow`` pipeline with a flow sensor and a camera publishes (tests/gnss_flow_telemetry.py:
the real pipeline's ``gnss_flow`` and ``gnss_flow_images``, the real cross-check's
``attitude_check`` and ``health``); vehicle 2 none of it.

What was drawn is measured on the screen: each arrow's start mapped back through the image
rectangle's screen box must be its flow point, the FOE's centre the pipeline's FOE."""

from __future__ import annotations

import json
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from companion.dashboard.headless import HeadlessChromium
from tests.conftest import REPO
from tests.dashboard_fleet import Publishers, fleet_page, show_vehicle
from tests.gnss_flow_telemetry import FlowTelemetry, flight

pytestmark = pytest.mark.timeout(120)

ARTIFACTS = REPO / "artifacts"
FLOW_JS = REPO / "companion" / "dashboard" / "static" / "flow.js"
STREAMS = ("gnss_flow", "gnss_flow_images")
PANEL_HIDDEN = "document.getElementById('flow-panel').hidden"
STATUS = "document.getElementById('flow-status').textContent"
CHECK = "document.getElementById('flow-check')"
# What the view drew: the image rectangle (its SVG frame and screen box), each arrow (its path's
# start mapped back to the frame's units through that box, its path data, class and painted
# colour), the FOE's centre the same way, the selector, the attitude table and the cross-check.
DRAWN = """(() => {
  const root = document.getElementById('flow');
  root.scrollIntoView();
  const rect = root.querySelector('.image'), box = rect.getBoundingClientRect();
  const frame = ['x', 'y', 'width', 'height'].map((k) => Number(rect.getAttribute(k)));
  const toFrame = (node, p) => { const s = new DOMPoint(p.x, p.y).matrixTransform(node.getScreenCTM());
    return [frame[0] + (s.x - box.x) * frame[2] / box.width, frame[1] + (s.y - box.y) * frame[3] / box.height]; };
  const foe = document.getElementById('flow-foe');
  return {
    frame, aspect: box.width / box.height,
    gain: Number(root.querySelector('.flow-arrows').dataset.gain),
    arrows: [...root.querySelectorAll('.flow-arrows path')].map((a) => ({ start: toFrame(a, a.getPointAtLength(0)),
      d: a.getAttribute('d'), cls: a.getAttribute('class'), stroke: getComputedStyle(a).stroke })),
    foe: foe.getAttribute('visibility') === 'hidden' ? null : toFrame(foe, new DOMPoint(0, 0)),
    options: [...document.querySelectorAll('#flow-stream option')].map((o) => [o.value, o.textContent]),
    attitudes: [...document.querySelectorAll('#flow-attitudes tr')].map((tr) => [...tr.cells].map((c) => c.textContent)),
    check: [document.getElementById('flow-check').textContent, document.getElementById('flow-check').dataset.state],
    legend: document.getElementById('flow-legend').textContent,
    status: document.getElementById('flow-status').textContent,
  };
})()"""


def degrees(angles: Any) -> list[str]:
    """Angles (rad) as the view prints them: degrees with one decimal, "–" for none."""
    return ["–" if a is None else f"{math.degrees(a):.1f}" for a in (angles or [None] * 3)]


@dataclass
class FlowPage:
    browser: HeadlessChromium
    published: dict[int, FlowTelemetry]  # sysid -> what it publishes (10 Hz), absent: none

    def show(self, sysid: int) -> None:
        """Select vehicle ``sysid`` and wait until its streams are rendered."""
        show_vehicle(self.browser, sysid)

    def publish(self, sysid: int, telemetry: FlowTelemetry, stream: str = "gnss_flow") -> dict:
        """Publish ``telemetry`` from ``sysid`` from now on, choose ``stream`` in the view; what it
        drew once it shows that stream with the cross-check state of ``telemetry``."""
        self.published[sysid] = telemetry
        self.browser.evaluate("(() => { const s = document.getElementById('flow-stream');"
                              f" if (s.value !== '{stream}') {{ s.value = '{stream}';"
                              " s.dispatchEvent(new Event('change')); } })()")
        state = "lost" if "degraded" in json.dumps(telemetry.health) else "ok"
        status = json.dumps(f"{stream}: {telemetry.streams[stream]['status']}")
        self.browser.wait_for(f"!{PANEL_HIDDEN} && {STATUS}.startsWith({status}) && {CHECK}.dataset.state === '{state}'",
                              10, f"the flow view of {stream} with the cross-check {state}")
        return self.browser.evaluate(DRAWN)


@pytest.fixture(scope="module")
def flow_page(tmp_path_factory: pytest.TempPathFactory) -> Iterator[FlowPage]:
    published = {1: flight(0.0)}  # vehicle 1 runs the gnss_flow pipeline, vehicle 2 does not

    def tick(publishers: Publishers) -> None:  # the pose's north is the sysid, so the page says which vehicle it shows
        for sysid, publisher in publishers.items():
            publisher.publish("pose", {"position_ned_m": [float(sysid), 0.0, -1.0], "euler_rad": [0.0, 0.0, 0.0]})
            telemetry = published.get(sysid)
            if telemetry is not None:
                for stream, payload in telemetry.streams.items():
                    publisher.publish(stream, payload)
                for check in telemetry.checks:  # the two sources' checks of one instant, back to back
                    publisher.publish("attitude_check", check)
                publisher.publish("health", telemetry.health)

    with fleet_page(tmp_path_factory.mktemp("flow"), (1, 2), tick, {1: STREAMS}) as browser:
        browser.evaluate("(() => { window.pageErrors = [];"
                         " window.addEventListener('error', (e) => window.pageErrors.push(String(e.message))); })()")
        yield FlowPage(browser, published)


def check_arrows(drawn: dict, points: np.ndarray, flows: np.ndarray, tolerance: float) -> None:
    """One arrow per finite flow point, starting there (on the screen, within ``tolerance`` in the
    frame's units) and its shaft ending at the point plus the flow times the legend's gain."""
    finite = np.all(np.isfinite(points), axis=1) & np.all(np.isfinite(flows), axis=1)
    assert len(drawn["arrows"]) == int(finite.sum()) > 100
    for arrow, point, flow in zip(drawn["arrows"], points[finite], flows[finite]):
        assert arrow["start"] == pytest.approx(point.tolist(), abs=tolerance)
        shaft = [float(x) for x in re.findall(r"-?[\d.]+(?:e-?\d+)?", arrow["d"])[:4]]
        assert shaft[2:] == pytest.approx((point + drawn["gain"] * flow).tolist(), rel=1e-6, abs=1e-9)
    assert f"arrows × {drawn['gain']:g}" in drawn["legend"]


def with_unknown_depths(telemetry: FlowTelemetry, stream: str, every: int = 9) -> FlowTelemetry:
    """``telemetry`` with every ``every``-th shown depth of ``stream`` unknown (NaN), as the pipeline
    publishes a point too near the FOE to give one: whether the turn's newest pair has such a point
    depends on where its FOE falls on the grid."""
    message = telemetry.streams[stream]
    depth = np.array(message["flow_depth_m"], dtype=float)
    depth[::every] = np.nan
    return FlowTelemetry({**telemetry.streams, stream: {**message, "flow_depth_m": depth}}, telemetry.checks,
                         telemetry.health)


def test_the_flow_sensors_field_is_drawn_with_its_foe_depth_colours_and_both_attitudes(flow_page: FlowPage) -> None:
    telemetry = with_unknown_depths(flight(0.0), "gnss_flow")
    message = telemetry.streams["gnss_flow"]
    flow_page.show(1)
    flow_page.publish(1, telemetry)
    unknown = int(np.isnan(message["flow_depth_m"]).sum())  # the same status as the unaltered pair's: wait for these
    flow_page.browser.wait_for(f"document.querySelectorAll('#flow .flow-arrows path.no-depth').length === {unknown}",
                               10, f"{unknown} arrows without a depth")
    drawn = flow_page.browser.evaluate(DRAWN)
    assert drawn["options"] == [["gnss_flow", "gnss_flow (flow sensor)"], ["gnss_flow_images", "gnss_flow_images (camera)"]]
    points = np.asarray(message["flow_points_n"])
    half = np.abs(points).max(axis=0)  # normalised units: framed by the points' span about the optical axis
    assert drawn["frame"] == pytest.approx([-half[0], -half[1], 2 * half[0], 2 * half[1]])
    assert drawn["aspect"] == pytest.approx(half[0] / half[1], rel=0.01)
    check_arrows(drawn, points, np.asarray(message["flow_n"]), tolerance=0.005)
    assert drawn["foe"] == pytest.approx(list(message["foe_n"]), abs=0.005)

    # depth colours: log-spaced bins from the nearest shown point (0) to the farthest (4), none: grey
    depth = np.asarray(message["flow_depth_m"])
    classes = np.array([a["cls"] for a in drawn["arrows"]])
    assert list(classes[np.isnan(depth)]) == ["no-depth"] * int(np.isnan(depth).sum()) != []
    known = ~np.isnan(depth)
    bins = np.array([int(c.removeprefix("depth-")) for c in classes[known]])
    order = np.argsort(depth[known])
    assert bins[order][0] == 0 and bins[order][-1] == 4 and np.all(np.diff(bins[order]) >= 0)
    strokes = {a["cls"]: a["stroke"] for a in drawn["arrows"]}
    assert len(set(strokes.values())) == len(strokes) >= 3  # each bin its own painted colour
    assert f"{np.nanmin(depth):.0f}–" in drawn["legend"]

    # the pipeline's true and pseudo attitude beside the autopilot's ATTITUDE, and the difference
    check = next(c for c in telemetry.checks if c["source"] == "gnss_flow")
    own, pseudo = degrees(message["euler_rad"]), degrees(message["pseudo_euler_rad"])
    autopilot = degrees(check["autopilot_euler_rad"])
    difference = [f"{math.degrees(a - b):.1f}" for a, b in zip(check["euler_rad"], check["autopilot_euler_rad"])]
    assert drawn["attitudes"] == [[axis, own[i], pseudo[i], autopilot[i], difference[i]]
                                  for i, axis in enumerate(("roll", "pitch", "yaw"))]
    assert drawn["check"] == [f"cross-check: ok: attitude agrees with the autopilot's · largest difference"
                              f" {check['difference_deg']:.1f} ° at t 0.35 s", "ok"]
    m, depth_m = message, message["depth_m"]
    assert drawn["status"] == (
        f"gnss_flow: {m['status']} · {len(points)} of {m['flow_count']} vectors shown"
        f" · FOE ({m['foe_n'][0]:.3f}, {m['foe_n'][1]:.3f}) · inliers {round(100 * m['foe_inlier_fraction'])} %"
        f" · pitch offset {math.degrees(m['pitch_offset_rad']):.1f} ° · drift {math.degrees(m['drift_angle_rad']):.1f} °"
        f" · coordinated · depth {depth_m['min']:.1f} / {depth_m['median']:.1f} / {depth_m['max']:.1f} m"
        f" · AGL {m['agl_m']:.1f} m · rates {m['rates_source']} · t 0.35 s")
    print(f"screenshot: {flow_page.browser.screenshot(ARTIFACTS / 'dashboard-gnss-flow.png')}")
    flow_page.publish(1, flight(0.0))


def test_the_camera_path_is_chosen_in_the_selector_and_drawn_in_image_pixels(flow_page: FlowPage) -> None:
    telemetry = flight(0.0)
    message = telemetry.streams["gnss_flow_images"]
    flow_page.show(1)
    drawn = flow_page.publish(1, telemetry, "gnss_flow_images")
    width, height = message["image_size"]
    assert drawn["frame"] == [-0.5, -0.5, width, height]
    check_arrows(drawn, np.asarray(message["flow_points_px"]), np.asarray(message["flow_px"]), tolerance=0.5)
    foe = message["foe_px"]
    assert drawn["foe"] == pytest.approx(list(foe), abs=0.5)
    assert f" · FOE ({foe[0]:.1f}, {foe[1]:.1f}) px · " in drawn["status"]
    check = next(c for c in telemetry.checks if c["source"] == "gnss_flow.images")  # this path's own cross-check
    assert [row[3] for row in drawn["attitudes"]] == degrees(check["autopilot_euler_rad"])
    assert drawn["attitudes"][0][1] == degrees(message["euler_rad"])[0]
    assert f"largest difference {check['difference_deg']:.1f} °" in drawn["check"][0]
    print(f"screenshot: {flow_page.browser.screenshot(ARTIFACTS / 'dashboard-gnss-flow-images.png')}")
    flow_page.publish(1, telemetry, "gnss_flow")  # back to the flow sensor's


def test_an_autopilot_attitude_off_by_10_deg_of_roll_shows_the_cross_check_alarm(flow_page: FlowPage) -> None:
    telemetry = flight(10.0)
    flow_page.show(1)
    drawn = flow_page.publish(1, telemetry)
    check = next(c for c in telemetry.checks if c["source"] == "gnss_flow")
    assert drawn["check"] == [f"cross-check: ALARM: attitude differs from the autopilot's by {check['difference_deg']:.1f} deg"
                              f" · largest difference {check['difference_deg']:.1f} ° at t 0.35 s", "lost"]
    roll = drawn["attitudes"][0]
    assert roll[3] == degrees(check["autopilot_euler_rad"])[0]
    assert roll[4] == f"{math.degrees(check['euler_rad'][0] - check['autopilot_euler_rad'][0]):.1f}"  # about -10
    assert flow_page.browser.evaluate(f"getComputedStyle({CHECK}).backgroundColor") == "rgb(198, 40, 40)"  # --lost
    print(f"screenshot: {flow_page.browser.screenshot(ARTIFACTS / 'dashboard-gnss-flow-alarm.png')}")
    flow_page.publish(1, flight(0.0))


def test_a_pair_without_a_focus_of_expansion_draws_its_flow_without_errors(flow_page: FlowPage) -> None:
    """The keys of a pair the pipeline refused before the FOE (null FOE, offsets, attitude, depths)."""
    telemetry = flight(0.0)
    refused = {**telemetry.streams["gnss_flow"], "status": "no focus of expansion: 193 flow vectors", "flow_depth_m": None,
               "foe_n": None, "foe_inlier_fraction": None, "foe_rms_deg": None, "pitch_offset_rad": None,
               "drift_angle_rad": None, "coordinated": None, "lateral_rad": None, "euler_rad": None, "depth_m": None,
               "agl_m": None}
    flow_page.show(1)
    drawn = flow_page.publish(1, FlowTelemetry({**telemetry.streams, "gnss_flow": refused}, telemetry.checks,
                                               telemetry.health))
    assert drawn["foe"] is None and {a["cls"] for a in drawn["arrows"]} == {"no-depth"}
    assert len(drawn["arrows"]) == len(refused["flow_n"])
    assert [row[1] for row in drawn["attitudes"]] == ["–"] * 3
    assert (" · FOE none · inliers – % · pitch offset – ° · drift – ° · coordination ? · depth – / – / – m · AGL – m"
            in drawn["status"])
    assert flow_page.browser.evaluate("window.pageErrors") == []
    flow_page.publish(1, telemetry)


def test_a_vehicle_without_the_streams_shows_no_flow_view(flow_page: FlowPage) -> None:
    flow_page.show(1)
    flow_page.publish(1, flight(0.0))
    flow_page.show(2)
    flow_page.browser.wait_for(PANEL_HIDDEN, 5, "vehicle 2 without the flow view")
    assert flow_page.browser.evaluate("document.getElementById('flow-panel').getBoundingClientRect().height") == 0
    flow_page.show(1)  # and back: vehicle 1's view again
    flow_page.browser.wait_for(f"!{PANEL_HIDDEN}", 5, "vehicle 1's flow view")
    assert flow_page.browser.evaluate("window.pageErrors") == []


def test_the_view_reads_only_keys_the_pipeline_and_the_cross_check_publish() -> None:
    """A key renamed in the pipeline, companion/crosscheck.py or the health message fails here."""
    telemetry = flight(0.0)
    source = FLOW_JS.read_text()
    camera, sensor = (set(telemetry.streams[s]) for s in ("gnss_flow_images", "gnss_flow"))
    read = set(re.findall(r"\bdata\.(\w+)", source))
    assert read <= camera | sensor and {"flow_points_px", "flow_px", "foe_px", "image_size"} <= read - sensor
    assert {"flow_points_n", "flow_n", "foe_n", "flow_depth_m", "euler_rad", "pseudo_euler_rad"} <= read & sensor
    assert set(re.findall(r"\bcheck\??\.(\w+)", source)) <= set(telemetry.checks[0])
    assert set(re.findall(r"\bcomponent\??\.(\w+)", source)) <= set(next(iter(telemetry.health["components"].values())))
    assert set(re.findall(r"\bd\?\.(\w+)", source)) <= set(telemetry.streams["gnss_flow"]["depth_m"])
