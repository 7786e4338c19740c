// The dashboard page: one server-sent event stream in, the selected vehicle's state drawn out.
// Event formats: companion/dashboard/hub.py. Times ("rx", "now") are the hub's clock, seconds:
// playing a recording, the recording's daemon clock, which runs at the playback's speed.

import { CameraView } from "./camera.js";
import { setBadge } from "./dom.js";
import { FLOW_STREAMS, FlowView } from "./flow.js";
import { MapView, ScanView } from "./map.js";
import { TimePlot } from "./plots.js";
import * as panels from "./panels.js";
import { PlaybackBar } from "./playback.js";
import { SlamView } from "./slam.js";

const WINDOW_S = 60; // time plots
const LINK_LOST_S = 3; // no message from the vehicle for this long: telemetry link lost
const TRAIL_STEP_M = 0.02;
const TRAIL_POINTS = 5000;
const ALERTS_KEPT = 100;
const RENDER_PERIOD_MS = 100;
const DEG = 180 / Math.PI;
const MAP_STREAMS = ["map", "trajectory", "pose", "scan", "lines", "corners", "setpoint"];
const PANEL_STREAMS = ["autopilot", "link", "mission", "health", "system", "rates", "alerts", "sources", "laser_dots", "ekf_slam",
  ...FLOW_STREAMS, "attitude_check"];

/** Append a time row and drop the rows older than the plot window. */
function pushRow(rows, row) {
  rows.push(row);
  while (rows.length && rows[0][0] < row[0] - WINDOW_S) rows.shift();
}

const sigma = (variance) => (typeof variance === "number" && variance >= 0 ? Math.sqrt(variance) : NaN);

/** What the page keeps of one vehicle: the last message per stream, trail, plot rows, alerts. */
class Vehicle {
  constructor(sysid) {
    this.sysid = sysid;
    this.latest = {}; // stream -> {rx, data}
    this.trail = []; // [north, east] m
    this.position = []; // [rx, north, east, down]
    this.setpoints = []; // [rx, north, east, down]
    this.sigmas = []; // [rx, sigma north m, east m, down m, yaw deg]
    this.alerts = []; // newest first
    this.checks = {}; // attitude source -> {rx, data} of its newest attitude_check (the stream interleaves the sources)
    this.lastAlertRx = -Infinity;
    this.changed = new Set([...MAP_STREAMS, ...PANEL_STREAMS]);
  }

  apply({ stream, rx, data }) {
    if (stream === "alerts") {
      if (rx <= this.lastAlertRx) return; // replayed after a reconnect
      this.lastAlertRx = rx;
      this.alerts.unshift({ rx, ...data });
      this.alerts.length = Math.min(this.alerts.length, ALERTS_KEPT);
    } else if (stream === "attitude_check" && typeof data.source === "string") {
      if (this.checks[data.source] && rx <= this.checks[data.source].rx) return; // one source's, replayed
      this.checks[data.source] = { rx, data };
    } else {
      if (this.latest[stream] && rx <= this.latest[stream].rx) return;
      this.latest[stream] = { rx, data };
      if (stream === "pose") this.addPose(rx, data);
      if (stream === "setpoint" && data.position_ned_m) pushRow(this.setpoints, [rx, ...data.position_ned_m]);
    }
    this.changed.add(stream);
  }

  addPose(rx, pose) {
    const p = pose.position_ned_m;
    if (!p || p.some((v) => typeof v !== "number")) return;
    const last = this.trail[this.trail.length - 1];
    if (!last || Math.hypot(p[0] - last[0], p[1] - last[1]) >= TRAIL_STEP_M) {
      this.trail.push([p[0], p[1]]);
      if (this.trail.length > TRAIL_POINTS) this.trail.shift();
    }
    pushRow(this.position, [rx, ...p]);
    pushRow(this.sigmas, [rx, ...(pose.position_variance_m2 ?? []).map(sigma), sigma(pose.yaw_variance_rad2) * DEG]);
  }

  data(stream) {
    return this.latest[stream]?.data;
  }
}

const $ = (id) => document.getElementById(id);
const page = {
  map: new MapView($("map")),
  scan: new ScanView($("scan")),
  camera: new CameraView($("camera"), $("camera-legend"), $("camera-status")),
  slam: new SlamView($("slam"), $("slam-status")),
  flow: new FlowView({ select: $("flow-stream"), root: $("flow"), legend: $("flow-legend"), status: $("flow-status"),
    attitudes: $("flow-attitudes"), badge: $("flow-check") }, () => vehicles.get(selected)?.changed.add(FLOW_STREAMS[0])),
  positionPlots: ["north", "east", "down"].map((axis) => new TimePlot($("position-plots"), axis, "m")),
  sigmaPlots: [new TimePlot($("sigma-plots"), "position σ (north, east, down)", "m"),
    new TimePlot($("sigma-plots"), "yaw σ", "°")],
  playback: new PlaybackBar({ bar: $("playback-bar"), toggle: $("playback-toggle"), seek: $("playback-seek"),
    time: $("playback-time"), speed: $("playback-speed"), file: $("playback-file") }),
};
const vehicles = new Map();
let selected = null;
let status = null; // the hub's last status event
let statusAt = 0; // performance.now() when it arrived
let serverUp = false;
let lastPlotRender = 0;

function vehicle(sysid) {
  if (!vehicles.has(sysid)) vehicles.set(sysid, new Vehicle(sysid));
  return vehicles.get(sysid);
}

/** The hub's clock (s) elapsed since its last status (a playback's runs at its speed, not when paused). */
function sinceStatus() {
  return ((performance.now() - statusAt) / 1000) * page.playback.rate();
}

/** The hub's clock now (s), from its last status and the time since. */
function hubNow() {
  return status ? status.now + sinceStatus() : 0;
}

/** A playback seeked: forget every vehicle's state, the samples that follow rebuild it. */
function forgetVehicles() {
  vehicles.clear();
  if (selected !== null) choose(selected);
}

function onEvent(event) {
  if (event.type === "status") {
    status = event;
    statusAt = performance.now();
    for (const id of Object.keys(event.vehicles)) vehicle(Number(id));
    page.playback.update(event.playback);
  } else if (event.type === "sample") {
    vehicle(event.sysid).apply(event);
  } else if (event.type === "reset") {
    forgetVehicles();
  }
}

function connect() {
  const source = new EventSource("/events");
  source.onopen = () => { serverUp = true; };
  source.onmessage = (message) => onEvent(JSON.parse(message.data));
  source.onerror = () => {
    serverUp = false;
    if (source.readyState === EventSource.CLOSED) setTimeout(connect, 1000); // else it retries by itself
  };
}

function updateSelector() {
  const select = $("vehicle-select");
  const ids = [...vehicles.keys()].sort((a, b) => a - b);
  if (select.options.length !== ids.length || ids.some((id, i) => select.options[i].value !== String(id))) {
    select.replaceChildren(...ids.map((id) => new Option(`sysid ${id}`, String(id))));
  }
  if (selected === null && ids.length) choose(ids[0]);
  select.value = String(selected ?? "");
}

function choose(sysid) {
  selected = sysid;
  page.map.reset();
  vehicle(sysid).changed = new Set([...MAP_STREAMS, ...PANEL_STREAMS]);
}

function renderBadges(v) {
  setBadge($("server-badge"), serverUp ? "dashboard: connected" : "dashboard: reconnecting", serverUp ? "ok" : "lost");
  const seen = status?.vehicles?.[String(selected)];
  const age = seen ? seen.age_s + sinceStatus() : Infinity;
  if (!serverUp || !seen) {
    setBadge($("link-badge"), "telemetry: waiting", "unknown");
  } else {
    setBadge($("link-badge"), age > LINK_LOST_S ? `telemetry: LOST (${age.toFixed(0)} s)` : "telemetry: ok",
      age > LINK_LOST_S ? "lost" : "ok");
  }
  document.body.classList.toggle("stale", age > LINK_LOST_S);
  const overall = v?.data("health")?.overall;
  setBadge($("health-badge"), `health: ${overall ?? "?"}`, overall ?? "unknown");
  const ap = v?.data("autopilot");
  setBadge($("mode-badge"), `mode: ${ap?.mode ?? "?"}`, ap?.mode ? "ok" : "unknown");
  setBadge($("armed-badge"), ap ? (ap.armed ? "ARMED" : "disarmed") : "?", ap?.armed ? "degraded" : "unknown");
}

function renderScan(v) {
  const scan = v.data("scan");
  if (!scan) {  // e.g. a vehicle without a horizontal lidar: show nothing rather than another's scan
    page.scan.clear();
    $("scan-info").textContent = "no scan from this vehicle";
    return;
  }
  const corners = page.scan.render(scan, v.data("lines"), v.data("corners"));
  const lines = v.data("lines")?.sequence === scan.sequence ? v.data("lines").segments_m.length : "?";
  $("scan-info").textContent = `${scan.sensor} #${scan.sequence}: ${scan.ranges_mm.filter((r) => r).length} returns, `
    + `${lines} lines, ${corners ? `${corners.observed_m.length} corners, ${corners.matched.length} matched (${corners.state ?? "no pose"})` : "corners ?"}`;
}

function renderCamera(v) {
  const dots = v.data("laser_dots");
  $("camera-panel").hidden = !dots; // only a vehicle running the laser-dot pipeline has the view
  if (dots) page.camera.render(dots);
}

function renderSlam(v) {
  const slam = v.data("ekf_slam");
  $("slam-panel").hidden = !slam; // only a vehicle running the EKF-SLAM pipeline has the view
  if (slam) page.slam.render(slam, v.data("autopilot")); // against the autopilot's own position
}

function renderFlow(v) {
  const payloads = Object.fromEntries(FLOW_STREAMS.filter((s) => v.data(s)).map((s) => [s, v.data(s)]));
  const present = Object.keys(payloads).length > 0;
  $("flow-panel").hidden = !present; // only a vehicle running the gnss_flow pipeline has the view
  if (present) page.flow.render(payloads, Object.values(v.checks).map((c) => c.data), v.data("health"));
}

function renderPlots(v, now) {
  page.positionPlots.forEach((plot, axis) => plot.render([
    { rows: v.position, column: axis + 1, color: "#0d47a1" },
    { rows: v.setpoints, column: axis + 1, color: "#d81b60", dashed: true },
  ], now, WINDOW_S));
  page.sigmaPlots[0].render([1, 2, 3].map((column, i) => ({ rows: v.sigmas, column, color: ["#0d47a1", "#2e7d32", "#6d4c41"][i] })), now, WINDOW_S);
  page.sigmaPlots[1].render([{ rows: v.sigmas, column: 4, color: "#8e24aa" }], now, WINDOW_S);
}

function render() {
  page.playback.render();
  updateSelector();
  const v = vehicles.get(selected);
  renderBadges(v);
  if (!v) return;
  const changed = v.changed;
  v.changed = new Set();
  const any = (...streams) => streams.some((s) => changed.has(s));
  const now = hubNow();
  if (any(...MAP_STREAMS)) page.map.render(v);
  if (any("scan", "lines", "corners")) renderScan(v);
  if (any("pose", "setpoint") || performance.now() - lastPlotRender > 1000) {
    lastPlotRender = performance.now();
    renderPlots(v, now);
  }
  if (any("autopilot", "link")) panels.autopilot($("autopilot-table").tBodies[0], v.data("autopilot"), v.data("link"));
  if (any("mission")) panels.mission($("mission-table").tBodies[0], $("mission-progress"), v.data("mission"));
  if (any("health")) panels.health($("health-table").tBodies[0], v.data("health"));
  if (any("system")) panels.system($("system-table").tBodies[0], v.data("system"));
  if (any("sources")) panels.sources($("sources-table").tBodies[0], v.data("sources"));
  if (any("rates", "health")) panels.streams($("streams-table").tBodies[0], status?.vehicles?.[String(selected)]?.streams, v.data("rates"));
  if (any("alerts", "health")) panels.alerts($("alerts"), v.alerts, now);
  if (any("laser_dots")) renderCamera(v);
  if (any("ekf_slam", "autopilot")) renderSlam(v);
  if (any(...FLOW_STREAMS, "attitude_check", "health")) renderFlow(v);
}

$("vehicle-select").addEventListener("change", (e) => choose(Number(e.target.value)));
connect();
setInterval(render, RENDER_PERIOD_MS);
