// The GNSS + optic-flow pipeline's view (streams gnss_flow, gnss_flow_images: one per flow path).
// The newest pair's flow vectors as arrows over the image frame, coloured by each point's depth,
// and the focus of expansion; beside it the pipeline's attitude (true and pseudo), the autopilot's
// ATTITUDE and the attitude cross-check's state. A camera path is drawn in image pixels (u right,
// v down, pixel centres at integers: the image spans -0.5 .. width - 0.5); a flow sensor's in
// normalised image coordinates (x right, y down, the optical axis at 0), framed by the span of its
// points. Angles shown in degrees, depths in metres.

import { el, fmt, setRows, svg } from "./dom.js";

const DEG = 180 / Math.PI;
export const FLOW_STREAMS = ["gnss_flow", "gnss_flow_images"];
const DEPTH_BINS = 5; // colours from near (0) to far, log-spaced between the shown depths' extremes
const ARROW_SHARE = 1 / 15; // the longest arrows (90th percentile) drawn about this share of the frame's width
const HEAD = 0.3; // arrowhead length, of the arrow's
const FOE_SIZE = 0.04; // of the frame's width
const MARGIN = 0.03; // of the frame's width, around the frame and the FOE

const finite = (x) => typeof x === "number" && Number.isFinite(x);
const isPoint = (p) => Array.isArray(p) && p.length >= 2 && finite(p[0]) && finite(p[1]);
const degrees = (angles) => (Array.isArray(angles) ? angles.map((a) => (finite(a) ? a * DEG : null)) : [null, null, null]);

/** The path's vectors in its units (`camera`: pixels, else normalised): [{at [x, y], flow [dx, dy],
 *  depth m or null}], the valid ones. */
function vectorsOf(data, camera) {
  const points = (camera ? data.flow_points_px : data.flow_points_n) ?? [];
  const flows = (camera ? data.flow_px : data.flow_n) ?? [];
  const depth = Array.isArray(data.flow_depth_m) ? data.flow_depth_m : [];
  return points.map((at, i) => ({ at, flow: flows[i], depth: finite(depth[i]) && depth[i] > 0 ? depth[i] : null }))
    .filter((v) => isPoint(v.at) && isPoint(v.flow));
}

/** The image frame [x0, y0, x1, y1] in the path's units: the camera's image, or the span of a flow sensor's points. */
function frameOf(data, vectors) {
  if (Array.isArray(data.image_size) && data.image_size.every(finite)) {
    return [-0.5, -0.5, data.image_size[0] - 0.5, data.image_size[1] - 0.5];
  }
  const x = Math.max(1e-3, ...vectors.map((v) => Math.abs(v.at[0])));
  const y = Math.max(1e-3, ...vectors.map((v) => Math.abs(v.at[1])));
  return [-x, -y, x, y];
}

/** 1, 2 or 5 times a power of ten, the nearest at or below `x` (> 0). */
function roundDown(x) {
  const power = 10 ** Math.floor(Math.log10(x));
  return [5, 2, 1].map((m) => m * power).find((v) => v <= x) ?? power;
}

/** The arrows' gain: their 90th-percentile length drawn about ARROW_SHARE of the frame's `width`, a round number. */
function gainOf(vectors, width) {
  const lengths = vectors.map((v) => Math.hypot(v.flow[0], v.flow[1])).sort((a, b) => a - b);
  const p90 = lengths[Math.floor(0.9 * (lengths.length - 1))];
  return p90 > 0 ? roundDown((ARROW_SHARE * width) / p90) : 1;
}

/** The depth bin (0 near .. DEPTH_BINS - 1 far) of `depth` within [lo, hi] m, log-spaced; null without a depth. */
function binOf(depth, lo, hi) {
  if (depth === null) return null;
  if (!(hi > lo)) return 0;
  return Math.min(DEPTH_BINS - 1, Math.floor((DEPTH_BINS * Math.log(depth / lo)) / Math.log(hi / lo)));
}

/** The arrow's path: a shaft from the point along its flow times `gain`, and a two-stroke head. */
function arrowPath([x, y], [dx, dy], gain) {
  const ex = x + gain * dx, ey = y + gain * dy;
  const hx = -HEAD * gain * dx, hy = -HEAD * gain * dy; // back along the shaft
  const c = Math.cos(0.45), s = Math.sin(0.45);
  return `M${x} ${y}L${ex} ${ey}M${ex + c * hx - s * hy} ${ey + s * hx + c * hy}L${ex} ${ey}`
    + `L${ex + c * hx + s * hy} ${ey - s * hx + c * hy}`;
}

/** The cross-check of `stream`'s source (stream = source with "." as "_"): its newest message among
 *  the attitude_check messages `checks` and its health component, either possibly null. */
function crossCheckOf(stream, checks, health) {
  const ofStream = (source) => source.replaceAll(".", "_") === stream;
  const check = checks.find((c) => typeof c?.source === "string" && ofStream(c.source)) ?? null;
  const entry = Object.entries(health?.components ?? {})
    .find(([name]) => name.startsWith("crosscheck:") && ofStream(name.slice("crosscheck:".length)));
  return { check, component: entry ? entry[1] : null };
}

/** The status line: what the pair gave, its flow, FOE, offsets, coordination, depths, height and time. */
function statusLine(stream, data, shown, foeText) {
  const coordinated = { true: "coordinated", false: "UNCOORDINATED" }[data.coordinated] ?? "coordination ?";
  const d = data.depth_m;
  return [`${stream}: ${data.status || "?"}`, `${shown} of ${data.flow_count ?? "?"} vectors shown`,
    `FOE ${foeText}`, `inliers ${finite(data.foe_inlier_fraction) ? Math.round(100 * data.foe_inlier_fraction) : "–"} %`,
    `pitch offset ${fmt(finite(data.pitch_offset_rad) ? data.pitch_offset_rad * DEG : null, 1)} °`,
    `drift ${fmt(finite(data.drift_angle_rad) ? data.drift_angle_rad * DEG : null, 1)} °`, coordinated,
    `depth ${fmt(d?.min, 1)} / ${fmt(d?.median, 1)} / ${fmt(d?.max, 1)} m`, `AGL ${fmt(data.agl_m, 1)} m`,
    `rates ${data.rates_source || "–"}`, `t ${fmt(data.t_capture, 2)} s`].join(" · ");
}

/** The view: a stream selector, the flow picture, its depth legend and status, the attitude table and the cross-check. */
export class FlowView {
  /** `nodes`: {select, root (svg), legend, status, attitudes (tbody), badge (the cross-check)};
   *  `onSelect` is called when the user picks a stream. */
  constructor(nodes, onSelect) {
    Object.assign(this, nodes);
    this.chosen = null;
    this.select.addEventListener("change", () => { this.chosen = this.select.value; onSelect(); });
    this.frame = svg("rect", { class: "image" }, this.root);
    this.arrows = svg("g", { class: "flow-arrows" }, this.root);
    this.foe = svg("g", { class: "flow-foe", id: "flow-foe" }, this.root);
  }

  /** Draw the chosen one of `payloads` ({stream: its newest message}, at least one) with its
   *  cross-check, from `checks` (the newest attitude_check of each source) and the `health` message. */
  render(payloads, checks, health) {
    const streams = FLOW_STREAMS.filter((s) => payloads[s]);
    if (!streams.includes(this.chosen)) this.chosen = streams[0];
    this.updateSelect(streams, payloads);
    const data = payloads[this.chosen];
    const camera = Array.isArray(data.image_size);
    const vectors = vectorsOf(data, camera);
    const frame = frameOf(data, vectors);
    const foe = isPoint(camera ? data.foe_px : data.foe_n) ? (camera ? data.foe_px : data.foe_n) : null;
    this.drawFrame(frame, foe);
    const depths = vectors.map((v) => v.depth).filter((d) => d !== null);
    const [lo, hi] = depths.length ? [Math.min(...depths), Math.max(...depths)] : [null, null];
    const gain = gainOf(vectors, frame[2] - frame[0]);
    this.drawArrows(vectors, gain, lo, hi);
    this.drawFoe(foe, frame[2] - frame[0]);
    this.drawLegend(lo, hi, gain, camera);
    const digits = camera ? 1 : 3;
    const foeText = foe ? `(${fmt(foe[0], digits)}, ${fmt(foe[1], digits)})${camera ? " px" : ""}` : "none";
    this.status.textContent = statusLine(this.chosen, data, vectors.length, foeText);
    this.drawAttitudes(data, crossCheckOf(this.chosen, checks, health));
  }

  updateSelect(streams, payloads) {
    const label = (s) => `${s} (${Array.isArray(payloads[s].image_size) ? "camera" : "flow sensor"})`;
    if ([...this.select.options].map((o) => o.text).join() !== streams.map(label).join()) {
      this.select.replaceChildren(...streams.map((s) => new Option(label(s), s)));
    }
    this.select.value = this.chosen;
  }

  /** The image rectangle, and a view box around it and `foe` (outside the image when the travel is). */
  drawFrame([x0, y0, x1, y1], foe) {
    this.frame.setAttribute("x", x0);
    this.frame.setAttribute("y", y0);
    this.frame.setAttribute("width", x1 - x0);
    this.frame.setAttribute("height", y1 - y0);
    const pad = MARGIN * (x1 - x0);
    const [a, b, c, d] = foe ? [Math.min(x0, foe[0]), Math.min(y0, foe[1]), Math.max(x1, foe[0]), Math.max(y1, foe[1])]
      : [x0, y0, x1, y1];
    this.root.setAttribute("viewBox", `${a - pad} ${b - pad} ${c - a + 2 * pad} ${d - b + 2 * pad}`);
  }

  drawArrows(vectors, gain, lo, hi) {
    this.arrows.replaceChildren();
    this.arrows.dataset.gain = gain;
    for (const v of vectors) {
      const bin = binOf(v.depth, lo, hi);
      svg("path", { d: arrowPath(v.at, v.flow, gain), class: bin === null ? "no-depth" : `depth-${bin}`,
        "data-x": v.at[0], "data-y": v.at[1], "data-depth-m": v.depth ?? "" }, this.arrows);
    }
  }

  /** A ring and a cross at the focus of expansion, or nothing without one. */
  drawFoe(foe, width) {
    this.foe.replaceChildren();
    this.foe.setAttribute("visibility", foe ? "visible" : "hidden");
    if (!foe) return;
    const r = FOE_SIZE * width;
    this.foe.setAttribute("transform", `translate(${foe[0]} ${foe[1]})`);
    svg("circle", { r }, this.foe);
    svg("path", { d: `M${-2 * r} 0H${2 * r}M0 ${-2 * r}V${2 * r}` }, this.foe);
  }

  /** The depth colours with their ranges (m), the arrows' gain and the units. */
  drawLegend(lo, hi, gain, camera) {
    const items = [];
    const metres = (x) => fmt(x, x < 10 ? 1 : 0);
    if (lo !== null) {
      const edge = (k) => (hi > lo ? lo * (hi / lo) ** (k / DEPTH_BINS) : lo);
      for (let k = 0; k < (hi > lo ? DEPTH_BINS : 1); k += 1) {
        items.push(el("span", { class: "bin" }, el("span", { class: `key depth-${k}` }),
          hi > lo ? `${metres(edge(k))}–${metres(edge(k + 1))} m` : `${metres(lo)} m`));
      }
    }
    items.push(el("span", { class: "bin" }, el("span", { class: "key no-depth" }), "no depth"),
      el("span", { class: "bin" }, el("span", { class: "key foe" }), "FOE"),
      ` · arrows × ${gain} (${camera ? "pixels" : "normalised image units"}), depth along the optical axis`);
    this.legend.replaceChildren(...items);
  }

  /** Roll, pitch, yaw: the pipeline's true and pseudo attitude, the autopilot's ATTITUDE, their difference; the alarm. */
  drawAttitudes(data, { check, component }) {
    const own = degrees(data.euler_rad), pseudo = degrees(data.pseudo_euler_rad);
    const autopilot = degrees(check?.autopilot_euler_rad);
    const checked = degrees(check?.euler_rad);
    const wrapped = (a) => ((a + 540) % 360) - 180; // degrees, -180 .. 180
    const difference = (i) => (finite(checked[i]) && finite(autopilot[i]) ? wrapped(checked[i] - autopilot[i]) : null);
    setRows(this.attitudes, ["roll", "pitch", "yaw"].map((axis, i) => [axis, [fmt(own[i], 1), "num"],
      [fmt(pseudo[i], 1), "num"], [fmt(autopilot[i], 1), "num"], [fmt(difference(i), 1), "num"]]));
    const alarm = component?.state === "degraded" || component?.state === "lost";
    const state = !component ? "unknown" : alarm ? "lost" : "ok";
    const text = !component ? "cross-check: no comparison yet (no autopilot attitude or no estimate)"
      : `cross-check: ${alarm ? "ALARM" : "ok"}: ${component.reason}`;
    const tail = check ? ` · largest difference ${fmt(check.difference_deg, 1)} ° at t ${fmt(check.t_capture, 2)} s` : "";
    this.badge.textContent = text + tail;
    this.badge.className = `badge ${state}`;
    this.badge.dataset.state = state;
  }
}
