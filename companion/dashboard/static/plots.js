// Small time plots: a few series over the last minute, in the hub's clock (seconds).

import { el, fmt, svg } from "./dom.js";

const PAD = { left: 54, right: 6, top: 6, bottom: 16 }; // pixels

/** One plot: series are {rows, column, color, dashed}; rows are [t, v0, v1, ...] arrays. */
export class TimePlot {
  constructor(container, title, unit) {
    this.unit = unit;
    this.root = svg("svg", { role: "img", "aria-label": title });
    container.append(el("div", { class: "plot" }, el("div", { class: "title" }, title), this.root));
  }

  /** Draw `series` over [now - windowS, now] (s); the y range fits the visible values. */
  render(series, now, windowS) {
    const width = this.root.clientWidth || 300, height = this.root.clientHeight || 120;
    this.root.setAttribute("viewBox", `0 0 ${width} ${height}`);
    const start = now - windowS;
    const visible = series.map((s) => s.rows.filter((row) => row[0] >= start && Number.isFinite(row[s.column])));
    const values = visible.flatMap((rows, i) => rows.map((row) => row[series[i].column]));
    let lo = Math.min(...values), hi = Math.max(...values);
    if (!values.length) [lo, hi] = [0, 1];
    if (hi - lo < 1e-3) [lo, hi] = [lo - 0.05, hi + 0.05];
    const x = (t) => PAD.left + ((t - start) / windowS) * (width - PAD.left - PAD.right);
    const y = (v) => height - PAD.bottom - ((v - lo) / (hi - lo)) * (height - PAD.top - PAD.bottom);
    this.root.replaceChildren();
    svg("path", { class: "axis", d: `M${PAD.left} ${PAD.top}V${height - PAD.bottom}H${width - PAD.right}` }, this.root);
    const digits = Math.max(2, Math.ceil(-Math.log10(hi - lo)) + 1);
    this.label(4, PAD.top + 8, `${fmt(hi, digits)} ${this.unit}`);
    this.label(4, height - PAD.bottom, `${fmt(lo, digits)} ${this.unit}`);
    this.label(PAD.left, height - 3, `-${windowS} s`);
    this.label(width - PAD.right - 22, height - 3, "now");
    visible.forEach((rows, i) => {
      const { column, color, dashed } = series[i];
      const points = rows.map((row) => `${x(row[0]).toFixed(1)},${y(row[column]).toFixed(1)}`).join(" ");
      svg("polyline", { points, class: dashed ? "plot-line dashed" : "plot-line", stroke: color }, this.root);
    });
  }

  label(px, py, text) {
    svg("text", { x: px, y: py }, this.root).textContent = text;
  }
}
