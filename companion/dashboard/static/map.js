// The top-down map and the scan view. Both draw in metres in NED (x north, y east) inside a
// group that turns x up and y right, so the picture is north-up / forward-up without mirroring.

import { svg } from "./dom.js";

const DEG = 180 / Math.PI;
const MARGIN_M = 0.5;
const VEHICLE_SHAPE = "0.35,0 -0.2,0.22 -0.08,0 -0.2,-0.22"; // nose along body x, metres
const MAX_SCAN_VIEW_M = 10;
const ROOM_WITHOUT_MAP_M = 6; // shown around the vehicle until the map arrives

/** A group in which SVG x, y are NED x (north, up the screen) and y (east, right). */
export function nedGroup(root) {
  return svg("g", { transform: "matrix(0 -1 1 0 0 0)" }, root);
}

/** SVG transform placing a frame at [x, y, yaw rad] of its parent frame. */
export function placeAt([x, y, yaw]) {
  return `translate(${x} ${y}) rotate(${yaw * DEG})`;
}

/** [x, y] of the levelled-body point q in the world, for a pose [x, y, yaw]. */
function toWorld([x, y, yaw], [qx, qy]) {
  const c = Math.cos(yaw), s = Math.sin(yaw);
  return [x + c * qx - s * qy, y + s * qx + c * qy];
}

/** Path data drawing each valid return of a scan as a dot, in the sensor frame (metres). */
function scanDots(scan) {
  const parts = [];
  const ranges = scan.ranges_mm;
  for (let i = 0; i < ranges.length; i++) {
    if (!ranges[i]) continue;
    const r = ranges[i] / 1000, a = scan.angle_min_rad + i * scan.angle_increment_rad;
    parts.push(`M${(r * Math.cos(a)).toFixed(3)} ${(r * Math.sin(a)).toFixed(3)}h0.001`);
  }
  return parts.join("");
}

/** SVG viewBox showing the NED rectangle [minX, minY]-[maxX, maxY] (metres) north-up. */
export function viewBox([minX, minY, maxX, maxY], margin) {
  return `${minY - margin} ${-maxX - margin} ${maxY - minY + 2 * margin} ${maxX - minX + 2 * margin}`;
}

/** A scan with the lines and corners found in it, in the levelled body frame. */
class ScanLayer {
  constructor(parent) {
    this.lines = svg("g", { class: "scan-lines" }, parent);
    this.sensor = svg("g", {}, parent);
    this.dots = svg("path", { class: "scan-points" }, this.sensor);
    this.observed = svg("g", { class: "observed" }, parent);
  }

  /** Remove what was drawn (another vehicle chosen, without a scan yet). */
  clear() {
    this.dots.setAttribute("d", "");
    this.lines.replaceChildren();
    this.observed.replaceChildren();
  }

  /** Draw `scan` (its own sequence's lines and corners only, so the three always agree). */
  draw(scan, lines, corners) {
    this.sensor.setAttribute("transform", placeAt(scan.mount));
    this.dots.setAttribute("d", scanDots(scan));
    const same = (msg) => msg && msg.sequence === scan.sequence && msg.sensor === scan.sensor;
    this.lines.replaceChildren();
    for (const [x1, y1, x2, y2] of same(lines) ? lines.segments_m : []) {
      svg("line", { x1, y1, x2, y2 }, this.lines);
    }
    this.observed.replaceChildren();
    const hits = new Set(same(corners) ? corners.matched.map((m) => m.observed) : []);
    for (const [i, [cx, cy]] of (same(corners) ? corners.observed_m : []).entries()) {
      svg("circle", { cx, cy, r: 0.1, class: hits.has(i) ? "hit" : "" }, this.observed);
    }
    return same(corners) ? corners : null;
  }
}

/** The world map: walls, known corners, trajectory, trail, scan, setpoint and the vehicle. */
export class MapView {
  constructor(root) {
    this.root = root;
    const g = nedGroup(root);
    this.walls = svg("g", { class: "walls" }, g);
    this.corners = svg("g", { class: "corners" }, g);
    this.trajectory = svg("polyline", { class: "trajectory" }, g);
    this.waypoints = svg("g", { class: "waypoints" }, g);
    this.trail = svg("polyline", { class: "trail" }, g);
    this.scanFrame = svg("g", {}, g);
    this.scan = new ScanLayer(this.scanFrame);
    this.matched = svg("g", { class: "matched" }, g);
    this.setpoint = svg("g", { class: "setpoint" }, g);
    svg("circle", { r: 0.15 }, this.setpoint);
    svg("path", { d: "M-0.25 0H0.25M0 -0.25V0.25" }, this.setpoint);
    this.uncertainty = svg("ellipse", { class: "uncertainty" }, g);
    this.vehicle = svg("g", { class: "vehicle", id: "vehicle" }, g);
    svg("polygon", { points: VEHICLE_SHAPE }, this.vehicle);
    this.reset();
  }

  /** Forget what was drawn (another vehicle was selected). */
  reset() {
    this.mapShown = null;
    this.extent = null; // [minX, minY, maxX, maxY] NED metres shown
    for (const node of [this.walls, this.corners, this.waypoints, this.matched]) node.replaceChildren();
    for (const node of [this.trajectory, this.trail]) node.setAttribute("points", "");
    for (const node of [this.scanFrame, this.setpoint, this.uncertainty, this.vehicle]) node.setAttribute("visibility", "hidden");
  }

  render(vehicle) {
    const latest = (stream) => vehicle.latest[stream]?.data;
    this.drawMap(latest("map"));
    this.drawTrajectory(latest("trajectory"));
    this.trail.setAttribute("points", vehicle.trail.map(([x, y]) => `${x},${y}`).join(" "));
    this.drawScan(latest("scan"), latest("lines"), latest("corners"));
    this.drawSetpoint(latest("setpoint"));
    this.drawVehicle(latest("pose"));
    this.root.setAttribute("viewBox", viewBox(this.extent ?? [-5, -5, 5, 5], MARGIN_M));
  }

  drawMap(map) {
    if (!map || map === this.mapShown) return;
    this.mapShown = map;
    this.walls.replaceChildren();
    this.corners.replaceChildren();
    for (const [x1, y1, x2, y2] of map.walls_ned_m) svg("line", { x1, y1, x2, y2 }, this.walls);
    for (const [cx, cy] of map.corners_ned_m) svg("circle", { cx, cy, r: 0.08 }, this.corners);
    this.extent = null;
    for (const [x1, y1, x2, y2] of map.walls_ned_m) {
      this.include([x1, y1], 0);
      this.include([x2, y2], 0);
    }
  }

  drawTrajectory(trajectory) {
    const points = trajectory?.points_ned_m ?? [];
    this.trajectory.setAttribute("points", points.map(([x, y]) => `${x},${y}`).join(" "));
    this.waypoints.replaceChildren();
    for (const [cx, cy] of trajectory?.waypoints_ned_m ?? []) svg("circle", { cx, cy, r: 0.12 }, this.waypoints);
  }

  drawScan(scan, lines, corners) {
    this.matched.replaceChildren();
    if (!scan || !scan.pose) {
      this.scanFrame.setAttribute("visibility", "hidden");
      return;
    }
    this.scanFrame.setAttribute("visibility", "visible");
    this.scanFrame.setAttribute("transform", placeAt(scan.pose));
    const agreeing = this.scan.draw(scan, lines, corners);
    for (const { observed, map_ned_m: [mx, my] } of agreeing?.matched ?? []) {
      const [ox, oy] = toWorld(scan.pose, agreeing.observed_m[observed]);
      svg("line", { x1: ox, y1: oy, x2: mx, y2: my }, this.matched);
      svg("circle", { cx: mx, cy: my, r: 0.14 }, this.matched);
    }
  }

  drawSetpoint(setpoint) {
    const p = setpoint?.position_ned_m;
    this.setpoint.setAttribute("visibility", p ? "visible" : "hidden");
    if (p) this.setpoint.setAttribute("transform", `translate(${p[0]} ${p[1]})`);
  }

  drawVehicle(pose) {
    const p = pose?.position_ned_m;
    const visible = p && p[0] !== null && p[1] !== null;
    for (const node of [this.vehicle, this.uncertainty]) node.setAttribute("visibility", visible ? "visible" : "hidden");
    if (!visible) return;
    const yaw = pose.euler_rad?.[2] ?? 0;
    this.vehicle.setAttribute("transform", placeAt([p[0], p[1], yaw]));
    this.vehicle.dataset.north = p[0];
    this.vehicle.dataset.east = p[1];
    const [vx, vy] = pose.position_variance_m2 ?? [0, 0];
    this.uncertainty.setAttribute("cx", p[0]);
    this.uncertainty.setAttribute("cy", p[1]);
    this.uncertainty.setAttribute("rx", 2 * Math.sqrt(Math.max(vx ?? 0, 0)));
    this.uncertainty.setAttribute("ry", 2 * Math.sqrt(Math.max(vy ?? 0, 0)));
    if (!this.mapShown) this.include(p, ROOM_WITHOUT_MAP_M);
  }

  /** Grow the shown extent to hold point [x, y] with `room` metres around it. */
  include([x, y], room) {
    const e = this.extent ?? [x, y, x, y];
    this.extent = [Math.min(e[0], x - room), Math.min(e[1], y - room), Math.max(e[2], x + room), Math.max(e[3], y + room)];
  }
}

/** The latest scan around the vehicle, forward up, with 1 m range rings. */
export class ScanView {
  constructor(root) {
    this.root = root;
    const g = nedGroup(root);
    this.rings = svg("g", { class: "rings" }, g);
    this.layer = new ScanLayer(g);
    svg("polygon", { points: VEHICLE_SHAPE }, svg("g", { class: "vehicle" }, g));
    this.radius = 0;
  }

  /** Nothing to show: an empty view. */
  clear() {
    this.layer.clear();
  }

  /** Draw the scan; returns its corners message when it belongs to the scan (else null). */
  render(scan, lines, corners) {
    const farthest = Math.max(1, ...scan.ranges_mm) / 1000;
    const radius = Math.min(Math.ceil(farthest), MAX_SCAN_VIEW_M);
    if (radius !== this.radius) {
      this.radius = radius;
      this.rings.replaceChildren();
      for (let r = 1; r <= radius; r++) svg("circle", { r }, this.rings);
      this.root.setAttribute("viewBox", viewBox([-radius, -radius, radius, radius], 0.2));
    }
    return this.layer.draw(scan, lines, corners);
  }
}
