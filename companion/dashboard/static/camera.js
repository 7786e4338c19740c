// The downward camera's view of the laser-dot pipeline (the laser_dots stream): the floor markers
// and the three laser dots it found in the newest frame, drawn in image pixels (u right, v down;
// integer values at pixel centres, so the image spans -0.5 .. width - 0.5).

import { el, fmt, svg, vector } from "./dom.js";

const DEG = 180 / Math.PI;
const BEAMS = [0, 1, 2];
const DOT_RADIUS = 0.012; // of the image width
const LABEL_SIZE = 0.04; // of the image width

const isPoint = (p) => Array.isArray(p) && p.length === 2 && p.every((x) => typeof x === "number");
const degrees = (angles) => angles?.map((a) => (typeof a === "number" ? a * DEG : null));

/** Per beam: its dot's pixel [u, v] (null when the frame has none) and its length (m). */
function beamsOf(dots) {
  return BEAMS.map((beam) => {
    const px = dots.dots_px?.[beam];
    return { beam, px: dots.dots_found?.[beam] && isPoint(px) ? px : null, length: dots.beam_lengths_m?.[beam] };
  });
}

/** One legend entry: the beam's colour, and where its dot is or that it is missing. */
function legendItem({ beam, px, length }) {
  const text = px ? `beam ${beam} (${px[0]}, ${px[1]}) px, ${fmt(length, 2)} m` : `beam ${beam} missing`;
  return el("span", { class: px ? "beam" : "beam warn", "data-beam": beam }, el("span", { class: `key beam-${beam}` }), text);
}

/** What the frame gave: kind and status, markers, extra spots, and the pose or the tilt. */
function statusLine(dots) {
  const markers = dots.markers ?? [];
  const parts = [`${dots.kind}: ${dots.status || "–"}`,
    `${markers.length} markers${markers.length ? ` (${markers.join(", ")})` : ""}`, `${dots.extra_spots ?? 0} extra spots`];
  if (dots.kind === "pose") {
    parts.push(`position NED ${vector(dots.position_ned_m)} m`, `roll, pitch, yaw ${vector(degrees(dots.euler_rad), 1)} °`);
  } else if (dots.kind === "tilt") {
    const [height, roll, pitch] = dots.tilt ?? [];
    parts.push(`height ${fmt(height, 2)} m`, `roll, pitch ${vector(degrees([roll, pitch]), 1)} °`);
  }
  return parts.join(" · ");
}

/** The image rectangle with the markers' corner quads (labelled with their ids) and the dots. */
export class CameraView {
  constructor(root, legend, status) {
    this.root = root;
    this.legend = legend;
    this.status = status;
    this.image = svg("rect", { class: "image", x: -0.5, y: -0.5 }, root);
    this.markers = svg("g", { class: "markers" }, root);
    this.dots = svg("g", { class: "dots" }, root);
  }

  render(dots) {
    const [width, height] = dots.image_size;
    this.root.setAttribute("viewBox", `-0.5 -0.5 ${width} ${height}`);
    this.image.setAttribute("width", width);
    this.image.setAttribute("height", height);
    for (const layer of [this.markers, this.dots]) layer.setAttribute("font-size", LABEL_SIZE * width);
    const radius = DOT_RADIUS * width;
    this.drawMarkers(dots.markers ?? [], dots.marker_corners_px ?? [], radius / 2);
    const beams = beamsOf(dots);
    this.drawDots(beams, radius);
    this.legend.replaceChildren(...beams.map(legendItem));
    this.status.textContent = statusLine(dots);
  }

  /** Each marker's quad in ArUco corner order (its top-left corner marked), its id in the middle. */
  drawMarkers(ids, corners, markRadius) {
    this.markers.replaceChildren();
    ids.forEach((id, i) => {
      const quad = corners[i];
      if (!Array.isArray(quad) || quad.length !== 4 || !quad.every(isPoint)) return;
      const g = svg("g", { "data-id": id }, this.markers);
      svg("polygon", { points: quad.map(([u, v]) => `${u},${v}`).join(" ") }, g);
      svg("circle", { cx: quad[0][0], cy: quad[0][1], r: markRadius }, g);
      const mean = (k) => quad.reduce((sum, p) => sum + p[k], 0) / 4;
      svg("text", { x: mean(0), y: mean(1) }, g).textContent = String(id);
    });
  }

  /** The dots found, each in its beam's colour with the beam number beside it. */
  drawDots(beams, radius) {
    this.dots.replaceChildren();
    for (const { beam, px } of beams.filter((b) => b.px)) {
      const [u, v] = px;
      svg("circle", { class: `beam-${beam}`, cx: u, cy: v, r: radius, "data-beam": beam }, this.dots);
      svg("text", { class: `beam-${beam}`, x: u + 1.5 * radius, y: v - 1.5 * radius }, this.dots).textContent = String(beam);
    }
  }
}
