// The tables of the page: autopilot, mission, health, streams, system, alerts.

import { el, fmt, setRows, vector } from "./dom.js";

const SEVERITY = ["EMERG", "ALERT", "CRIT", "ERROR", "WARN", "NOTICE", "INFO", "DEBUG"];
const yesNo = (value) => (value === undefined || value === null ? ["–"] : [value ? "yes" : "no", value ? "" : "warn"]);

/** Autopilot state and the MAVLink link to it. */
export function autopilot(tbody, ap, link) {
  setRows(tbody, [
    ["mode", ap?.mode ?? "–"],
    ["armed", ap ? (ap.armed ? "ARMED" : "disarmed") : "–"],
    ["EKF using external nav", yesNo(ap?.external_nav_in_use)],
    ["EKF origin confirmed", yesNo(ap?.origin_confirmed)],
    ["EKF flags", ap?.ekf_flags === undefined || ap?.ekf_flags === null ? "–" : `0x${ap.ekf_flags.toString(16)}`],
    ["autopilot position NED (m)", vector(ap?.local_position_ned_m)],
    ["autopilot link", yesNo(link?.connected)],
    ["autopilot", link?.autopilot ?? "–"],
    ["heartbeat age (s)", fmt(link?.heartbeat_age_s, 1)],
    ["messages rx / tx", link ? `${link.messages_rx} / ${link.messages_tx}` : "–"],
    ["reconnects / reboots", link ? `${link.reconnects} / ${link.autopilot_reboots}` : "–"],
  ]);
}

/** Mission progress: the bar shows `progress` when published, else the step count. */
export function mission(tbody, bar, m) {
  const fraction = typeof m?.progress === "number" ? m.progress : m?.steps ? (m.step ?? 0) / m.steps : 0;
  bar.style.width = `${Math.round(Math.min(Math.max(fraction, 0), 1) * 100)}%`;
  setRows(tbody, [
    ["mission", m?.name ?? "none"],
    ["state", [m?.state ?? "–", m?.state === "failed" || m?.state === "aborted" ? "warn" : ""]],
    ["step", m?.steps ? `${Math.min((m.step ?? 0) + 1, m.steps)} / ${m.steps}${m.step_kind ? ` (${m.step_kind})` : ""}` : "–"],
    ["progress", typeof m?.progress === "number" ? `${Math.round(m.progress * 100)} %` : "–"],
    ["tracking error (m)", fmt(m?.tracking_error_m, 3)],
    ["failsafe", m?.failsafe ? [m.failsafe, "warn"] : "none"],
    ["reason", m?.reason || "–"],
  ]);
}

/** One row per component: state, reason, and how long it has been in that state. */
export function health(tbody, h) {
  const components = Object.entries(h?.components ?? {});
  setRows(tbody, components.map(([name, c]) => [
    name, [c.state, `state ${c.state}`], c.reason, `${fmt(h.t - c.since, 0)} s`,
  ]).concat(Object.entries(h?.tasks ?? {}).filter(([, t]) => t.restarts > 0).map(([name, t]) => [
    `task ${name}`, ["restarted", "state degraded"], `${t.restarts} restarts; last: ${t.last_error}`, "",
  ])));
}

/** Per stream: what this page receives (hub status) and what the daemon reports (rates). */
export function streams(tbody, received, rates) {
  const names = [...new Set([...Object.keys(received ?? {}), ...Object.keys(rates?.streams ?? {})])].sort();
  setRows(tbody, names.filter((n) => received?.[n] || rates?.streams?.[n]?.offered).map((name) => {
    const rx = received?.[name], pub = rates?.streams?.[name];
    const lossy = (value) => [value ?? "–", value ? "num warn" : "num"];
    return [name, [fmt(rx?.rate_hz, 1), "num"], [fmt(rx?.age_s, 1), "num"], [fmt(pub?.rate_hz, 1), "num"],
      lossy(pub?.dropped), [pub?.rate_limited ?? "–", "num"], lossy(pub?.errors)];
  }));
}

/** CPU, memory, nav loop lateness, per-stage timings and every pipeline's counters. */
export function system(tbody, s) {
  const rows = [
    ["CPU (% of one core)", fmt(s?.cpu_percent, 1)],
    ["memory (MB)", fmt(s?.rss_mb, 0)],
    ["uptime (s)", fmt(s?.uptime_s, 0)],
    ["nav loop lateness p50 / p99", `${fmt(s?.loop_jitter_ms?.p50, 2)} / ${fmt(s?.loop_jitter_ms?.p99, 2)}`],
  ];
  for (const [stage, t] of Object.entries(s?.stage_ms ?? {})) rows.push([`${stage} p50 / p99`, `${fmt(t.p50, 2)} / ${fmt(t.p99, 2)}`]);
  for (const [pipeline, counters] of Object.entries(s?.pipelines ?? {})) {
    for (const [name, value] of Object.entries(counters ?? {})) {
      if (typeof value === "number" && !name.endsWith("_t")) rows.push([`${pipeline}: ${name.replaceAll("_", " ")}`, fmt(value, 1)]);
    }
  }
  rows.push(["setpoints sent", s?.setpoints_sent ?? "–"]);
  setRows(tbody, rows);
}

/** The pose sources in priority order: which one feeds the autopilot, and where each one puts the vehicle. */
export function sources(tbody, src) {
  setRows(tbody, (src?.priority ?? []).map((name) => {
    const s = src.sources?.[name] ?? {};
    const role = name === src.active ? [src.pinned === name ? "active (commanded)" : "active", "state ok"]
      : [s.fresh ? "standby" : "stale", s.fresh ? "" : "state lost"];
    return [name, role, fmt(s.age_s, 2), vector(s.position_ned_m), fmt(typeof s.yaw_rad === "number" ? s.yaw_rad * 180 / Math.PI : null, 1)];
  }));
}

/** Newest first, with the hub's arrival time as "s ago". */
export function alerts(list, items, now) {
  list.replaceChildren(...items.map((a) => el("li", {},
    el("span", { class: `sev sev-${a.severity}` }, SEVERITY[a.severity] ?? String(a.severity)),
    `${a.text} `, el("small", {}, `${fmt(now - a.rx, 0)} s ago`))));
}
