"""The dashboard's EKF-SLAM view in headless Chromium: a real ``companion dashboard`` process joined
to two real zenoh peers on loopback (scouting off), one vehicle publishing ``ekf_slam`` (numpy
arrays, NaN, through the real publisher) and the autopilot's own position, the other not.

What was drawn is measured on the screen: the markers' screen positions must be one north-up
scale and offset of their metres (east right, north up), the scale bar that scale, and a
non-diagonal covariance's ellipse must cover the points along its expected axes and not beyond."""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from companion.dashboard.headless import HeadlessChromium
from tests.conftest import REPO
from tests.dashboard_fleet import Publishers, fleet_page, show_vehicle
from tests.test_ekf_slam_pipeline import SOUTH_WEST, Flight

pytestmark = pytest.mark.timeout(120)

ARTIFACTS = REPO / "artifacts"
NAN = math.nan
CHI2_2D_95 = 5.991
AUTOPILOT_NED = [43.0, 29.0, -100.0]  # 5 m from the SLAM pose (3 north, 4 east)
POSE = [40.0, 25.0, math.radians(135.0)]
TILTED_COV = [[36.0, 18.0], [18.0, 16.0]]  # landmark 3: correlated north and east
CIRCLE = {"kind": "circle", "target_ne": (60.0, -10.0), "carrot_ne": (55.0, 15.0), "radius_m": 25.0,
          "reason": "circling landmark 3 to re-observe it", "reference": 3}
RETURNING = {
    "t_s": 812.4, "pose": np.array(POSE),
    "pose_cov": np.array([[2.0, 0.5, 0.01], [0.5, 1.0, 0.0], [0.01, 0.0, 0.0004]]),
    "landmarks": [{"id": 3, "ne": np.array([60.0, -10.0]), "cov_ne": np.array(TILTED_COV), "in_view": True},
                  {"id": 5, "ne": np.array([20.0, 50.0]), "cov_ne": np.eye(2), "in_view": False},
                  {"id": 8, "ne": np.array([-15.0, 30.0]), "cov_ne": np.full((2, 2), NAN), "in_view": False}],
    "returning": True, "trigger": "gnss_lost", "base_ne": (0.0, 0.0), "plan": CIRCLE,
}
PLANS = {  # kind -> (plan, t_s): each later message has its own time, which the status line ends with
    "goto": ({"kind": "goto", "target_ne": (10.0, 5.0), "carrot_ne": (30.0, 18.0), "radius_m": None,
              "reason": "flying to the base", "reference": None}, 813.0),
    "search": ({"kind": "search", "target_ne": (-20.0, 40.0), "carrot_ne": (-5.0, 35.0), "radius_m": None,
                "reason": "no landmark in view: searching", "reference": None}, 814.0),
    "land": ({"kind": "land", "target_ne": (0.0, 0.0), "carrot_ne": (0.0, 0.0), "radius_m": None,
              "reason": "at the base: landing", "reference": None}, 815.0),
    "hold": ({"kind": "hold", "target_ne": (40.0, 25.0), "carrot_ne": None, "radius_m": None,
              "reason": "holding", "reference": None}, 816.0),
}
NOTHING_YET = {"t_s": 1.5, "pose": np.full(3, NAN), "pose_cov": np.full((3, 3), NAN), "landmarks": [],
               "returning": False, "trigger": None, "base_ne": None, "plan": None}

PANEL_HIDDEN = "document.getElementById('slam-panel').hidden"
STATUS = "document.getElementById('slam-status').textContent"
# Screen positions (viewport pixels) of what was drawn: points through each element's own screen
# transform, so they are where the browser paints them.
DRAWN = """(() => {
  const root = document.getElementById('slam');
  root.scrollIntoView();
  const at = (node, x, y) => { const p = new DOMPoint(x, y).matrixTransform(node.getScreenCTM()); return [p.x, p.y]; };
  const visible = (node) => node.getAttribute('visibility') !== 'hidden';
  const base = document.getElementById('slam-base'), ap = document.getElementById('slam-autopilot');
  const pose = document.getElementById('slam-pose'), scale = document.querySelector('#slam-scale path');
  const box = (node) => { const b = node.getBoundingClientRect(); return [b.x, b.y, b.width, b.height]; };
  const centre = (node) => { const b = node.getBoundingClientRect(); return [b.x + b.width / 2, b.y + b.height / 2]; };
  return {
    svg: box(root),
    plan: document.querySelector('#slam .slam-plan').dataset.kind,
    landmarks: [...document.querySelectorAll('#slam .landmark')].map((g) => ({
      id: g.dataset.id, inView: g.classList.contains('in-view'), at: centre(g.querySelector('circle')),
      ellipse: g.querySelector('ellipse') && Object.fromEntries(['majorM', 'minorM', 'angleDeg'].map(
        (k) => [k, Number(g.querySelector('ellipse').dataset[k])])),
    })),
    labels: [...document.querySelectorAll('#slam .slam-labels text')].map((t) => t.textContent),
    base: visible(base) ? centre(base) : null,
    autopilot: visible(ap) ? centre(ap) : null,
    pose: visible(pose) ? at(pose, 0, 0) : null,
    poseNose: visible(pose) ? at(pose, 1, 0) : null,
    poseEllipses: document.querySelectorAll('#slam .slam-pose-ellipse ellipse').length,
    scale: { width: scale.getBoundingClientRect().width, lengthM: Number(scale.parentNode.dataset.lengthM),
             label: scale.parentNode.querySelector('text').textContent },
    loops: [...document.querySelectorAll('#slam .slam-plan .loop')].map(box),
    legs: [...document.querySelectorAll('#slam .slam-plan .leg')].map((l) => [
      at(l, l.x1.baseVal.value, l.y1.baseVal.value), at(l, l.x2.baseVal.value, l.y2.baseVal.value)]),
    targets: [...document.querySelectorAll('#slam .slam-plan .target')].map((t) => t.getAttribute('class')),
    carrots: [...document.querySelectorAll('#slam .slam-plan .carrot')].map(centre),
  };
})()"""


def hit(x: float, y: float) -> str:
    """JS: what is painted at viewport pixel (x, y): the landmark id and tag of the element, or ''."""
    return (f"(() => {{ const e = document.elementFromPoint({x}, {y}); const g = e && e.closest('#slam .landmark');"
            " return g ? `${g.dataset.id} ${e.tagName}` : ''; })()")


@dataclass
class Screen:
    """The north-up mapping fitted to the drawn markers: pixel = (x0 + k east, y0 - k north)."""

    x0: float
    y0: float
    k: float

    @staticmethod
    def fit(pairs: list[tuple[list[float], list[float]]]) -> Screen:
        """Least-squares fit of one scale and offset to (ne metres, screen pixels) pairs; asserts
        that every pair lies on it within half a pixel (no mirroring, no stretch between axes)."""
        ne = np.array([p for p, _ in pairs], dtype=float)
        px = np.array([s for _, s in pairs], dtype=float)
        a = np.zeros((2 * len(pairs), 3))
        a[0::2, 0], a[0::2, 2] = 1.0, ne[:, 1]  # x = x0 + k e
        a[1::2, 1], a[1::2, 2] = 1.0, -ne[:, 0]  # y = y0 - k n
        solution, *_ = np.linalg.lstsq(a, px.reshape(-1), rcond=None)
        screen = Screen(*solution)
        assert screen.k > 0
        for p, s in pairs:
            assert screen.at(p) == pytest.approx(s, abs=0.5), f"{p} drawn at {s}"
        return screen

    def at(self, ne: list[float] | tuple[float, ...]) -> list[float]:
        return [self.x0 + self.k * ne[1], self.y0 - self.k * ne[0]]


@dataclass
class SlamPage:
    browser: HeadlessChromium
    payloads: dict[int, dict]  # sysid -> the ekf_slam payload it publishes (10 Hz), absent: none
    autopilot_ned: list[float]  # the autopilot's own position, every vehicle's

    def show(self, sysid: int) -> None:
        """Select vehicle ``sysid`` and wait until its streams are rendered."""
        show_vehicle(self.browser, sysid)

    def publish(self, sysid: int, payload: dict) -> str:
        """Publish ``payload`` from ``sysid`` from now on; the status line once the page shows it."""
        self.payloads[sysid] = payload
        tail = json.dumps(f" · t {payload['t_s']:.1f} s")
        return self.browser.wait_for(f"!{PANEL_HIDDEN} && {STATUS}.endsWith({tail}) && {STATUS}", 10,
                                     f"the EKF-SLAM view at t {payload['t_s']}")

    def drawn(self) -> dict[str, Any]:
        drawn = self.browser.evaluate(DRAWN)
        assert self.browser.evaluate("window.pageErrors") == []  # nothing missing or null threw
        return drawn


@pytest.fixture(scope="module")
def slam_page(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SlamPage]:
    payloads: dict[int, dict] = {1: RETURNING}  # vehicle 1 runs the EKF-SLAM pipeline, vehicle 2 does not
    autopilot_ned = list(AUTOPILOT_NED)

    def tick(publishers: Publishers) -> None:  # the pose's north is the sysid, so the page says which vehicle it shows
        for sysid, publisher in publishers.items():
            publisher.publish("pose", {"position_ned_m": [float(sysid), 0.0, -1.0], "euler_rad": [0.0, 0.0, 0.0]})
            publisher.publish("autopilot", {"mode": "GUIDED", "armed": True, "local_position_ned_m": np.array(autopilot_ned)})
            if sysid in payloads:
                publisher.publish("ekf_slam", payloads[sysid])

    with fleet_page(tmp_path_factory.mktemp("slam"), (1, 2), tick, {1: ("ekf_slam",)}) as browser:
        browser.evaluate("(() => { window.pageErrors = [];"
                         " window.addEventListener('error', (e) => window.pageErrors.push(String(e.message)));"
                         " window.addEventListener('unhandledrejection', (e) => window.pageErrors.push(String(e.reason))); })()")
        yield SlamPage(browser, payloads, autopilot_ned)


def expected_ellipse(cov: list[list[float]]) -> tuple[float, float, float]:
    """95 % semi-axes (m) and the major axis's angle (degrees clockwise from north, -90..90)."""
    values, vectors = np.linalg.eigh(np.array(cov))
    n, e = vectors[:, 1]
    angle = math.degrees(math.atan2(e, n))
    angle = (angle + 90.0) % 180.0 - 90.0
    return math.sqrt(CHI2_2D_95 * values[1]), math.sqrt(CHI2_2D_95 * values[0]), angle


def test_the_view_draws_landmarks_base_pose_autopilot_and_the_circle_north_up(slam_page: SlamPage) -> None:
    slam_page.show(1)
    status = slam_page.publish(1, RETURNING)
    assert status == ("returning to base (gnss_lost) · plan: circle r 25.0 m around landmark 3: circling landmark 3"
                      " to re-observe it · 3 landmarks, 1 in view · SLAM − autopilot 5.00 m · yaw σ 1.1 ° · t 812.4 s")
    drawn = slam_page.drawn()
    marks = {m["id"]: m for m in drawn["landmarks"]}
    assert sorted(marks) == ["3", "5", "8"] and sorted(drawn["labels"]) == ["3", "5", "8"]
    assert [marks[i]["inView"] for i in ("3", "5", "8")] == [True, False, False]
    assert marks["8"]["ellipse"] is None  # its covariance arrived as nulls: the point only
    assert drawn["plan"] == "circle" and drawn["poseEllipses"] == 1

    # one north-up scale and offset places every marker
    screen = Screen.fit([(lm["ne"].tolist(), marks[str(lm["id"])]["at"]) for lm in RETURNING["landmarks"]]
                        + [([0.0, 0.0], drawn["base"]), (AUTOPILOT_NED[:2], drawn["autopilot"]), (POSE[:2], drawn["pose"])])
    nose = np.subtract(drawn["poseNose"], drawn["pose"])  # heading 135°: south-east is right and down
    assert math.degrees(math.atan2(nose[0], -nose[1])) == pytest.approx(135.0, abs=0.5)
    # auto-fit: everything inside the view, the circle's extent filling most of one of its sides
    x, y, width, height = drawn["svg"]
    [(lx, ly, lw, lh)] = drawn["loops"]
    assert lw / 2 == pytest.approx(25.0 * screen.k, rel=0.02) and lh == pytest.approx(lw, rel=0.02)
    assert [lx + lw / 2, ly + lh / 2] == pytest.approx(screen.at(CIRCLE["target_ne"]), abs=0.5)
    bottom, right = screen.at([-15.0, 0.0])[1], screen.at([0.0, 50.0])[0]  # landmark 8 south, 5 east
    assert y <= ly and bottom <= y + height and x <= lx and right <= x + width
    assert (bottom - ly) > 0.7 * height or (right - lx) > 0.7 * width
    assert drawn["carrots"] == [pytest.approx(screen.at(CIRCLE["carrot_ne"]), abs=0.5)]
    # the scale bar is the same scale, a round length
    assert drawn["scale"]["lengthM"] in (10, 20, 50)
    assert drawn["scale"]["width"] == pytest.approx(drawn["scale"]["lengthM"] * screen.k, rel=0.02)
    assert drawn["scale"]["label"] == f"{drawn['scale']['lengthM']} m"

    # the tilted ellipse: its axes from the covariance, and painted along them
    major, minor, angle = expected_ellipse(TILTED_COV)
    assert marks["3"]["ellipse"] == pytest.approx({"majorM": major, "minorM": minor, "angleDeg": angle}, rel=1e-6)
    assert (major, minor, angle) == pytest.approx((16.71, 5.69, 30.47), abs=0.01)
    assert marks["5"]["ellipse"] == pytest.approx({"majorM": math.sqrt(CHI2_2D_95), "minorM": math.sqrt(CHI2_2D_95),
                                                   "angleDeg": 0.0}, abs=1e-9)
    centre = np.array([60.0, -10.0])
    along = {"major": (major, math.radians(angle)), "minor": (minor, math.radians(angle + 90.0))}
    for axis, (semi, direction) in along.items():
        unit = np.array([math.cos(direction), math.sin(direction)])  # north, east
        for side in (1.0, -1.0):
            inside = screen.at(centre + side * 0.75 * semi * unit)
            outside = screen.at(centre + side * (semi + 6.0 / screen.k) * unit)  # 6 px beyond the edge
            assert slam_page.browser.evaluate(hit(*inside)) == "3 ellipse", f"{axis} axis, inside"
            assert slam_page.browser.evaluate(hit(*outside)) == "", f"{axis} axis, outside"
    # and not the ellipse mirrored (tilted the other way): there the true one is narrow
    wrong = screen.at(centre + 0.75 * major * np.array([math.cos(-math.radians(angle)), math.sin(-math.radians(angle))]))
    assert slam_page.browser.evaluate(hit(*wrong)) == ""
    print(f"screenshot: {slam_page.browser.screenshot(ARTIFACTS / 'dashboard-ekf-slam.png')}")


@pytest.mark.parametrize("kind", list(PLANS))
def test_each_plan_kind_is_drawn_with_its_reason(slam_page: SlamPage, kind: str) -> None:
    plan, t_s = PLANS[kind]
    slam_page.show(1)
    status = slam_page.publish(1, {**RETURNING, "t_s": t_s, "plan": plan})
    assert f"· plan: {kind}: {plan['reason']} ·" in status and status.startswith("returning to base (gnss_lost) ·")
    drawn = slam_page.drawn()
    assert drawn["plan"] == kind
    marks = {m["id"]: m["at"] for m in drawn["landmarks"]}
    screen = Screen.fit([(lm["ne"].tolist(), marks[str(lm["id"])]) for lm in RETURNING["landmarks"]]
                        + [([0.0, 0.0], drawn["base"]), (POSE[:2], drawn["pose"])])
    assert drawn["loops"] == []
    x, y, width, height = drawn["svg"]  # auto-fit: landmark 3's whole ellipse in view, not only its centre
    top = screen.at([60.0 + math.sqrt(CHI2_2D_95 * TILTED_COV[0][0]), -10.0 - math.sqrt(CHI2_2D_95 * TILTED_COV[1][1])])
    assert x <= top[0] and y <= top[1]
    if kind == "goto":
        [(start, end)] = drawn["legs"]
        assert start == pytest.approx(drawn["pose"], abs=0.5)
        assert end == pytest.approx(screen.at(plan["target_ne"]), abs=0.5)
        assert drawn["targets"] == ["target goto"]
    else:
        assert drawn["legs"] == []
        assert drawn["targets"] == [f"target {kind}"] * 2  # the cross and the ring
        assert kind in drawn["labels"]
    carrot = plan["carrot_ne"]
    assert drawn["carrots"] == ([] if carrot is None else [pytest.approx(screen.at(carrot), abs=0.5)])


def test_missing_fields_and_nulls_draw_what_there_is_without_errors(slam_page: SlamPage) -> None:
    slam_page.show(1)
    status = slam_page.publish(1, NOTHING_YET)
    assert status == "not returning · no plan · 0 landmarks, 0 in view · SLAM − autopilot – m · yaw σ – ° · t 1.5 s"
    drawn = slam_page.drawn()
    assert drawn["landmarks"] == [] and drawn["plan"] == "" and drawn["base"] is None and drawn["pose"] is None
    assert drawn["autopilot"] is not None and drawn["poseEllipses"] == 0
    # a bare message, a plan of nulls, a landmark without a position or covariance
    bare = {"t_s": 2.5, "landmarks": [{"id": 1, "ne": None}, {"id": 2, "ne": [1.0, 2.0]}], "returning": True,
            "trigger": "commanded", "plan": {"kind": "circle", "target_ne": None, "carrot_ne": None,
                                             "radius_m": None, "reason": "", "reference": None}}
    status = slam_page.publish(1, bare)
    assert status == ("returning to base (commanded) · plan: circle · 1 landmarks, 0 in view · SLAM − autopilot – m"
                      " · yaw σ – ° · t 2.5 s")
    drawn = slam_page.drawn()
    assert [(m["id"], m["ellipse"]) for m in drawn["landmarks"]] == [("2", None)]
    assert drawn["loops"] == [] and drawn["targets"] == [] and drawn["carrots"] == []


def test_a_vehicle_without_the_stream_shows_no_slam_view(slam_page: SlamPage) -> None:
    slam_page.show(1)
    slam_page.publish(1, RETURNING)
    slam_page.show(2)
    slam_page.browser.wait_for(PANEL_HIDDEN, 5, "vehicle 2 without the EKF-SLAM view")
    assert slam_page.browser.evaluate("document.getElementById('slam-panel').getBoundingClientRect().height") == 0
    slam_page.show(1)  # and back: vehicle 1's view again
    slam_page.browser.wait_for(f"!{PANEL_HIDDEN}", 5, "vehicle 1's EKF-SLAM view")
    assert slam_page.browser.evaluate("window.pageErrors") == []


def test_the_pipelines_own_message_is_drawn(slam_page: SlamPage) -> None:
    """The payload of EkfSlamPipeline.telemetry() itself, after a GNSS loss 200 m out (as
    tests/test_ekf_slam_pipeline.py flies it), published as the daemon does."""
    flight = Flight(SOUTH_WEST)
    flight.fly(40.0)
    flight.gnss = False
    flight.fly(20.0)
    message = flight.pipeline.telemetry(True)["ekf_slam"]
    assert message["returning"] and message["plan"] is not None
    slam_page.show(1)
    slam_page.autopilot_ned[:] = [float(x) for x in flight.position]
    try:
        status = slam_page.publish(1, message)
        drawn = slam_page.drawn()
    finally:
        slam_page.autopilot_ned[:] = AUTOPILOT_NED
    plan = message["plan"]
    assert status.startswith(f"returning to base ({message['trigger']}) · plan: {plan['kind']}")
    assert plan["reason"] in status
    in_view = sum(bool(m["in_view"]) for m in message["landmarks"])
    assert f"· {len(message['landmarks'])} landmarks, {in_view} in view ·" in status
    error = math.hypot(*(np.asarray(message["pose"])[:2] - flight.position[:2]))
    assert f"SLAM − autopilot {error:.2f} m" in status
    assert drawn["plan"] == plan["kind"]
    at = {int(m["id"]): m["at"] for m in drawn["landmarks"]}
    assert sorted(at) == sorted(m["id"] for m in message["landmarks"])
    assert all(m["ellipse"] is not None for m in drawn["landmarks"])
    assert drawn["pose"] is not None and drawn["base"] is not None and drawn["poseEllipses"] == 1
    Screen.fit([(list(m["ne"]), at[m["id"]]) for m in message["landmarks"]]
               + [(list(message["base_ne"]), drawn["base"]), (list(message["pose"][:2]), drawn["pose"])])
    print(f"screenshot: {slam_page.browser.screenshot(ARTIFACTS / 'dashboard-ekf-slam-pipeline.png')}")
