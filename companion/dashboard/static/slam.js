// The EKF-SLAM return to base (the ekf_slam stream), top-down and north up in LOCAL_NED metres:
// the landmarks with their 95 % covariance ellipses, the base, the SLAM pose with its ellipse
// against the autopilot's own position, and the planner's current step (circle, goto, search,
// land, hold). Every field may be missing or null (NaN arrives as null): what is missing is not drawn.
// What was drawn is also in data attributes (each ellipse's axes, the plan kind) for the tests.

import { fmt, svg } from "./dom.js";
import { nedGroup, placeAt, viewBox } from "./map.js";

const DEG = 180 / Math.PI;
const CHI2_2D_95 = 5.991; // chi-square, 2 degrees of freedom, 95 %: the ellipses' scale is its root
const MIN_SPAN_M = 10; // the view never shows less than this across
const MARGIN = 0.12; // of the span, around the fitted points (room for the scale bar)
const MARKER = 0.025; // marker size, of the span
// shapes in marker sizes, north along x: the pose's arrow (nose along the heading), base, autopilot, target
const ARROW = "M1.6 0L-0.8 0.8L-0.3 0L-0.8 -0.8Z";
const SQUARE = "M-1 -1H1V1H-1Z";
const DIAMOND = "M-1 0L0 1L1 0L0 -1Z";
const CROSS = "M-1 0H1M0 -1V1";
const NICE_STEPS = [1, 2, 5];

const finite = (x) => typeof x === "number" && Number.isFinite(x);
const isPoint = (p) => Array.isArray(p) && p.length >= 2 && finite(p[0]) && finite(p[1]);

/**
 * The 95 % ellipse of a 2x2 covariance [[nn, ne], [en, ee]] (m^2): semi-axes `major`, `minor` (m)
 * and the major axis's angle `angle` (rad, clockwise from north, in (-90°, 90°]); null when the
 * matrix is missing, not finite or not positive semi-definite.
 */
export function ellipseOf(cov) {
  const nn = cov?.[0]?.[0], ne = cov?.[0]?.[1], en = cov?.[1]?.[0], ee = cov?.[1]?.[1];
  if (![nn, ne, en, ee].every(finite)) return null;
  const off = (ne + en) / 2, mean = (nn + ee) / 2, half = Math.hypot((nn - ee) / 2, off);
  const big = mean + half, small = mean - half;
  if (small < -1e-9 * Math.max(1, big)) return null;
  return { major: Math.sqrt(CHI2_2D_95 * big), minor: Math.sqrt(CHI2_2D_95 * Math.max(small, 0)),
    angle: 0.5 * Math.atan2(2 * off, nn - ee) };
}

/** The largest 1, 2 or 5 times a power of ten not above `length`. */
function niceLength(length) {
  const power = 10 ** Math.floor(Math.log10(length));
  return power * NICE_STEPS.filter((step) => step * power <= length).pop();
}

/** The corners [minN, minE], [maxN, maxE] of the box around an ellipse centred at `centre`. */
function ellipseBox([n, e], { major, minor, angle }) {
  const c = Math.cos(angle), s = Math.sin(angle);
  const hn = Math.hypot(major * c, minor * s), he = Math.hypot(major * s, minor * c);
  return [[n - hn, e - he], [n + hn, e + he]];
}

/** An ellipse element (NED group coordinates) at `centre`, with its axes in data attributes. */
function drawEllipse(parent, centre, ellipse) {
  return svg("ellipse", { rx: ellipse.major, ry: ellipse.minor,
    transform: placeAt([centre[0], centre[1], ellipse.angle]),
    "data-major-m": ellipse.major, "data-minor-m": ellipse.minor, "data-angle-deg": ellipse.angle * DEG }, parent);
}

/** The return's status: returning and why, the plan and its reason, the landmarks, SLAM vs autopilot. */
function statusLine(slam, plan, marks, apDistance) {
  const returning = slam.returning ? `returning to base${slam.trigger ? ` (${slam.trigger})` : ""}` : "not returning";
  let planText = "no plan";
  if (plan) {
    const radius = plan.kind === "circle" && finite(plan.radius_m) ? ` r ${fmt(plan.radius_m, 1)} m` : "";
    const around = plan.reference !== null && plan.reference !== undefined ? ` around landmark ${plan.reference}` : "";
    planText = `plan: ${plan.kind ?? "?"}${radius}${around}${plan.reason ? `: ${plan.reason}` : ""}`;
  }
  const yawSigma = finite(slam.pose_cov?.[2]?.[2]) && slam.pose_cov[2][2] >= 0 ? Math.sqrt(slam.pose_cov[2][2]) * DEG : null;
  return [returning, planText, `${marks.length} landmarks, ${marks.filter((m) => m.in_view).length} in view`,
    `SLAM − autopilot ${fmt(apDistance, 2)} m`, `yaw σ ${fmt(yawSigma, 1)} °`, `t ${fmt(slam.t_s, 1)} s`].join(" · ");
}

/** The view: a north-up group in metres, and an unrotated one (x east, y south) for text and the scale bar. */
export class SlamView {
  constructor(root, status) {
    this.root = root;
    this.status = status;
    const g = nedGroup(root);
    this.plan = svg("g", { class: "slam-plan" }, g);
    this.landmarks = svg("g", { class: "slam-landmarks" }, g);
    this.base = svg("path", { class: "slam-base", id: "slam-base", d: SQUARE }, g);
    this.poseEllipse = svg("g", { class: "slam-pose-ellipse" }, g);
    this.autopilot = svg("path", { class: "slam-autopilot", id: "slam-autopilot", d: DIAMOND }, g);
    this.pose = svg("path", { class: "slam-pose", id: "slam-pose", d: ARROW }, g);
    this.labels = svg("g", { class: "slam-labels" }, root);
    this.scale = svg("g", { class: "slam-scale", id: "slam-scale" }, root);
  }

  /** Draw the `ekf_slam` message `slam`, with the autopilot's own position from its `autopilot` message. */
  render(slam, autopilot) {
    const pose = isPoint(slam.pose) ? slam.pose : null;
    const base = isPoint(slam.base_ne) ? slam.base_ne : null;
    const ap = isPoint(autopilot?.local_position_ned_m) ? autopilot.local_position_ned_m : null;
    const marks = (Array.isArray(slam.landmarks) ? slam.landmarks : []).filter((m) => isPoint(m?.ne))
      .map((m) => ({ ...m, ellipse: ellipseOf(m.cov_ne) }));
    const plan = slam.plan && typeof slam.plan === "object" ? slam.plan : null;
    const poseEllipse = pose && ellipseOf(slam.pose_cov);

    // fit the view to every point and the whole of every ellipse and loop
    const points = [pose, base, ap, plan?.target_ne, plan?.carrot_ne, ...marks.map((m) => m.ne)].filter(isPoint);
    for (const m of marks) if (m.ellipse) points.push(...ellipseBox(m.ne, m.ellipse));
    if (poseEllipse) points.push(...ellipseBox(pose, poseEllipse));
    if (plan?.kind === "circle" && isPoint(plan.target_ne) && finite(plan.radius_m)) {
      const [n, e] = plan.target_ne, r = Math.abs(plan.radius_m);
      points.push([n - r, e - r], [n + r, e + r]);
    }
    const { extent, span } = this.fit(points);
    const size = MARKER * span;
    this.root.setAttribute("viewBox", viewBox(extent, MARGIN * span));
    this.labels.setAttribute("font-size", 1.5 * size);
    this.labels.replaceChildren();

    this.drawLandmarks(marks, size);
    this.drawPlan(plan, pose, size);
    this.place(this.base, base, size);
    this.place(this.autopilot, ap, size);
    this.place(this.pose, pose, size, finite(pose?.[2]) ? pose[2] : 0);
    this.poseEllipse.replaceChildren();
    if (poseEllipse) drawEllipse(this.poseEllipse, pose, poseEllipse);
    this.drawScale(extent, span);

    const apDistance = pose && ap ? Math.hypot(pose[0] - ap[0], pose[1] - ap[1]) : null;
    this.status.textContent = statusLine(slam, plan, marks, apDistance);
  }

  /** The NED rectangle [minN, minE, maxN, maxE] around `points`, at least MIN_SPAN_M across; and its span. */
  fit(points) {
    const ns = points.map((p) => p[0]), es = points.map((p) => p[1]);
    const [minN, maxN, minE, maxE] = points.length ? [Math.min(...ns), Math.max(...ns), Math.min(...es), Math.max(...es)] : [0, 0, 0, 0];
    const span = Math.max(maxN - minN, maxE - minE, MIN_SPAN_M);
    const grow = (lo, hi) => { const pad = Math.max(0, MIN_SPAN_M - (hi - lo)) / 2; return [lo - pad, hi + pad]; };
    const [n0, n1] = grow(minN, maxN), [e0, e1] = grow(minE, maxE);
    return { extent: [n0, e0, n1, e1], span };
  }

  /** Show marker `node` at [north, east] `where` turned by `yaw` (rad), or hide it when `where` is null. */
  place(node, where, size, yaw = 0) {
    node.setAttribute("visibility", where ? "visible" : "hidden");
    if (where) node.setAttribute("transform", `${placeAt([where[0], where[1], yaw])} scale(${size})`);
  }

  /** Each landmark: its 95 % ellipse, its point and its id; those in view highlighted. */
  drawLandmarks(marks, size) {
    this.landmarks.replaceChildren();
    for (const mark of marks) {
      const g = svg("g", { class: mark.in_view ? "landmark in-view" : "landmark", "data-id": mark.id ?? "" }, this.landmarks);
      if (mark.ellipse) drawEllipse(g, mark.ne, mark.ellipse);
      svg("circle", { cx: mark.ne[0], cy: mark.ne[1], r: 0.6 * size }, g);
      if (mark.id !== null && mark.id !== undefined) {
        svg("text", { x: mark.ne[1] + size, y: -mark.ne[0] - size }, this.labels).textContent = String(mark.id);
      }
    }
  }

  /** The planner's step: a circle's loop, a goto's line from the pose, the target and the carrot. */
  drawPlan(plan, pose, size) {
    this.plan.replaceChildren();
    this.plan.dataset.kind = plan?.kind ?? "";
    if (!plan) return;
    const target = isPoint(plan.target_ne) ? plan.target_ne : null;
    if (target && plan.kind === "circle" && finite(plan.radius_m)) {
      svg("circle", { class: "loop", cx: target[0], cy: target[1], r: Math.abs(plan.radius_m) }, this.plan);
    }
    if (target && pose && plan.kind === "goto") {
      svg("line", { class: "leg", x1: pose[0], y1: pose[1], x2: target[0], y2: target[1] }, this.plan);
    }
    if (target) {
      svg("path", { class: `target ${plan.kind}`, d: CROSS, transform: `translate(${target[0]} ${target[1]}) scale(${size})` }, this.plan);
      if (plan.kind === "land" || plan.kind === "hold" || plan.kind === "search") {
        svg("circle", { class: `target ${plan.kind}`, cx: target[0], cy: target[1], r: 1.5 * size }, this.plan);
        svg("text", { class: "plan-label", x: target[1] + 2 * size, y: -target[0] + 2 * size }, this.labels).textContent = plan.kind;
      }
    }
    if (isPoint(plan.carrot_ne)) svg("circle", { class: "carrot", cx: plan.carrot_ne[0], cy: plan.carrot_ne[1], r: 0.5 * size }, this.plan);
  }

  /** A bar of a round length, bottom left in the margin, labelled in metres. */
  drawScale([minN, minE], span) {
    const length = niceLength(span / 4);
    const x = minE, y = -minN + 0.6 * MARGIN * span, tick = 0.15 * MARGIN * span;
    this.scale.replaceChildren();
    this.scale.dataset.lengthM = length;
    svg("path", { d: `M${x} ${y - tick}V${y}H${x + length}V${y - tick}` }, this.scale);
    svg("text", { x: x + length + tick, y, "font-size": 2 * MARKER * span }, this.scale).textContent = `${length} m`;
  }
}
