"""The dashboard's camera view of the laser-dot pipeline in headless Chromium: a real
``companion dashboard`` process joined to two real zenoh peers on loopback (scouting off), one
vehicle publishing ``laser_dots``, the other not."""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from dataclasses import dataclass

import pytest

from companion.dashboard.headless import HeadlessChromium
from tests.conftest import REPO
from tests.dashboard_fleet import Publishers, fleet_page, show_vehicle

pytestmark = pytest.mark.timeout(120)

ARTIFACTS = REPO / "artifacts"
WIDTH, HEIGHT = 640, 480
DOTS_PX = [[320, 240], [401, 251], [330, 333]]
MARKERS = [7, 12]
MARKER_CORNERS_PX = [[[100, 100], [160, 100], [160, 160], [100, 160]],
                     [[500, 300], [560, 305], [555, 365], [495, 360]]]
POSE = {"t_capture": 12.5, "kind": "pose", "status": "3 dots, 2 markers", "image_size": [WIDTH, HEIGHT],
        "dots_px": DOTS_PX, "dots_found": [True, True, True], "beam_lengths_m": [1.21, 1.25, 1.3], "extra_spots": 1,
        "markers": MARKERS, "marker_corners_px": MARKER_CORNERS_PX,
        "floor_dots_m": [[1.0, 2.0], [1.3, 2.1], [1.0, 2.4]], "candidates": 2, "position_ned_m": [1.0, 2.0, -1.2],
        "euler_rad": [math.radians(2.0), math.radians(-1.0), math.radians(90.0)], "tilt": None}
NAN = float("nan")  # the publisher sends it as null, as the pipeline's missing dot
ONE_MISSING = {**POSE, "kind": "none", "status": "2 of 3 dots seen", "dots_px": [DOTS_PX[0], [NAN, NAN], DOTS_PX[2]],
               "dots_found": [True, False, True], "beam_lengths_m": [1.21, NAN, 1.3], "markers": [],
               "marker_corners_px": None, "floor_dots_m": None, "candidates": 0, "position_ned_m": None,
               "euler_rad": None}
TILT = {**POSE, "kind": "tilt", "status": "no floor marker in view: height and tilt only", "markers": [],
        "marker_corners_px": None, "floor_dots_m": None, "candidates": 0, "position_ned_m": None, "euler_rad": None,
        "tilt": [1.2, math.radians(3.0), math.radians(-1.5)]}

PANEL_HIDDEN = "document.getElementById('camera-panel').hidden"
STATUS = "document.getElementById('camera-status').textContent"
LEGEND = "document.getElementById('camera-legend').textContent"
# each dot: its beam, its SVG centre, and its centre on the screen mapped back to image pixels
# through the image rectangle's screen box; and that box's aspect ratio
DRAWN = f"""(() => {{
  const image = document.querySelector('#camera .image').getBoundingClientRect();
  const toImage = (box) => [(box.x + box.width / 2 - image.x) * {WIDTH} / image.width - 0.5,
                            (box.y + box.height / 2 - image.y) * {HEIGHT} / image.height - 0.5];
  return {{
    aspect: image.width / image.height,
    dots: [...document.querySelectorAll('#camera .dots circle')].map((c) => [Number(c.dataset.beam),
      [c.cx.baseVal.value, c.cy.baseVal.value], toImage(c.getBoundingClientRect())]),
    markers: [...document.querySelectorAll('#camera .markers g')].map((g) => [g.dataset.id,
      g.querySelector('text').textContent, g.querySelector('polygon').getAttribute('points')]),
  }};
}})()"""


@dataclass
class CameraPage:
    browser: HeadlessChromium
    payloads: dict[int, dict]  # sysid -> the laser_dots payload it publishes (10 Hz), absent: none

    def show(self, sysid: int) -> None:
        """Select vehicle ``sysid`` and wait until its streams are rendered."""
        show_vehicle(self.browser, sysid)

    def publish(self, sysid: int, payload: dict) -> str:
        """Publish ``payload`` from ``sysid`` from now on; its status text once the page shows it."""
        self.payloads[sysid] = payload
        head = json.dumps(f"{payload['kind']}: {payload['status']}")
        return self.browser.wait_for(f"!{PANEL_HIDDEN} && {STATUS}.startsWith({head}) && {STATUS}", 10,
                                     f"the camera view of a {payload['kind']!r} frame")


@pytest.fixture(scope="module")
def camera_page(tmp_path_factory: pytest.TempPathFactory) -> Iterator[CameraPage]:
    payloads: dict[int, dict] = {1: POSE}  # vehicle 1 runs the laser-dot pipeline, vehicle 2 does not

    def tick(publishers: Publishers) -> None:  # the pose's north is the sysid, so the page says which vehicle it shows
        for sysid, publisher in publishers.items():
            publisher.publish("pose", {"position_ned_m": [float(sysid), 0.0, -1.0], "euler_rad": [0.0, 0.0, 0.0]})
            if sysid in payloads:
                publisher.publish("laser_dots", payloads[sysid])

    with fleet_page(tmp_path_factory.mktemp("camera"), (1, 2), tick, {1: ("laser_dots",)}) as browser:
        yield CameraPage(browser, payloads)


def test_the_camera_view_shows_the_dots_the_marker_quads_and_the_pose(camera_page: CameraPage) -> None:
    camera_page.show(1)
    status = camera_page.publish(1, POSE)
    drawn = camera_page.browser.evaluate(DRAWN)
    assert drawn["aspect"] == pytest.approx(WIDTH / HEIGHT, rel=0.01)  # the image rectangle's shape
    assert [beam for beam, _, _ in drawn["dots"]] == [0, 1, 2]
    for beam, svg_at, screen_at in drawn["dots"]:
        assert svg_at == DOTS_PX[beam]
        assert screen_at == pytest.approx(DOTS_PX[beam], abs=0.5)  # scaled with the image, not shifted
    assert [(marker_id, label) for marker_id, label, _ in drawn["markers"]] == [("7", "7"), ("12", "12")]
    assert drawn["markers"][1][2] == "500,300 560,305 555,365 495,360"
    assert status == ("pose: 3 dots, 2 markers · 2 markers (7, 12) · 1 extra spots · position NED 1.00, 2.00, -1.20 m"
                      " · roll, pitch, yaw 2.0, -1.0, 90.0 °")
    legend = camera_page.browser.evaluate(LEGEND)
    assert "beam 1 (401, 251) px, 1.25 m" in legend and "missing" not in legend
    print(f"screenshot: {camera_page.browser.screenshot(ARTIFACTS / 'dashboard-laser-dots.png')}")


def test_a_missing_dot_is_named_in_the_legend_not_drawn(camera_page: CameraPage) -> None:
    camera_page.show(1)
    status = camera_page.publish(1, ONE_MISSING)
    drawn = camera_page.browser.evaluate(DRAWN)
    assert [beam for beam, _, _ in drawn["dots"]] == [0, 2]
    assert drawn["markers"] == []
    assert status == "none: 2 of 3 dots seen · 0 markers · 1 extra spots"
    missing = camera_page.browser.evaluate("[...document.querySelectorAll('#camera-legend .warn')].map((s) => s.textContent)")
    assert missing == ["beam 1 missing"]


def test_a_tilt_frame_shows_the_height_and_the_tilt(camera_page: CameraPage) -> None:
    camera_page.show(1)
    status = camera_page.publish(1, TILT)
    assert status == ("tilt: no floor marker in view: height and tilt only · 0 markers · 1 extra spots · height 1.20 m"
                      " · roll, pitch 3.0, -1.5 °")
    assert len(camera_page.browser.evaluate(DRAWN)["dots"]) == 3


def test_a_vehicle_without_the_stream_shows_no_camera_view(camera_page: CameraPage) -> None:
    camera_page.show(2)
    assert camera_page.browser.evaluate(PANEL_HIDDEN) is True
    assert camera_page.browser.evaluate("document.getElementById('camera-panel').getBoundingClientRect().height") == 0
    camera_page.show(1)  # and back: vehicle 1's view again
    camera_page.browser.wait_for(f"!{PANEL_HIDDEN}", 5, "vehicle 1's camera view")
