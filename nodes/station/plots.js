// Health over time on <canvas>: one plot per group of series (CPU per core, memory, disk,
// network, each stream's fps, drops and age), time on x, the alerts as red markers.
// No library and nothing from a CDN: the view serves everything it shows.
"use strict";

const PLOT_COLOURS = ["#6cb6ff", "#5fd38d", "#f2b94b", "#ff6b6b", "#c792ea", "#4dd0e1",
                      "#ffab70", "#a5d6a7", "#f48fb1", "#b0bec5"];
const PLOT_GROUPS = {
  cpu: "CPU per core (%)", memory: "memory, swap, disk use (%)", disk: "disk write",
  network: "network", fps: "stream rate (fps)", drops: "frames dropped per sample",
  age: "stream age (ms)",
};
const ALERT_GROUPS = new Set(["fps", "drops"]);

function humanRate(v, unit) {
  if (unit !== "B/s") return Number(v).toFixed(v >= 100 ? 0 : 1);
  const k = ["B/s", "KB/s", "MB/s", "GB/s"];
  let i = 0;
  while (v >= 1000 && i < k.length - 1) { v /= 1000; i += 1; }
  return `${v.toFixed(v >= 100 ? 0 : 1)} ${k[i]}`;
}

function plotGroup(canvas, data, group) {
  const series = data.series.filter((s) => s.group === group);
  const g = canvas.getContext("2d");
  const dpr = window.devicePixelRatio || 1;
  const w = canvas.clientWidth, h = canvas.clientHeight;
  canvas.width = Math.round(w * dpr); canvas.height = Math.round(h * dpr);
  g.setTransform(dpr, 0, 0, dpr, 0, 0);
  g.clearRect(0, 0, w, h);
  const left = 52, right = 8, top = 18, bottom = 18;
  const t = data.t;
  let points = 0;
  g.font = "11px system-ui, sans-serif";
  g.fillStyle = "#8a93a3";
  const title = PLOT_GROUPS[group] || group;
  g.fillText(title, left, 12);
  let lx = left + g.measureText(title).width + 14;
  if (!t.length || !series.length) { canvas.dataset.points = "0"; return; }
  const t0 = t[0], t1 = Math.max(t[t.length - 1], t0 + 1);
  let hi = series[0].unit === "%" ? 100 : 0;
  for (const s of series) for (const v of s.values) if (v != null && v > hi) hi = v;
  if (hi <= 0) hi = 1;
  hi *= series[0].unit === "%" ? 1 : 1.1;
  const x = (tt) => left + (tt - t0) / (t1 - t0) * (w - left - right);
  const y = (v) => top + (1 - v / hi) * (h - top - bottom);
  g.strokeStyle = "#2c323c"; g.lineWidth = 1;
  for (const f of [0, 0.5, 1]) {
    g.beginPath(); g.moveTo(left, y(hi * f)); g.lineTo(w - right, y(hi * f)); g.stroke();
    g.fillText(humanRate(hi * f, series[0].unit), 2, y(hi * f) + 4);
  }
  g.fillText(`${Math.round(t1 - t0)} s`, w - right - 30, h - 4);
  series.forEach((s, k) => {
    g.strokeStyle = PLOT_COLOURS[k % PLOT_COLOURS.length];
    g.lineWidth = 1.5;
    g.beginPath();
    let pen = false;
    s.values.forEach((v, i) => {
      if (v == null) { pen = false; return; }
      if (pen) g.lineTo(x(t[i]), y(v)); else g.moveTo(x(t[i]), y(v));
      pen = true; points += 1;
    });
    g.stroke();
    const last = [...s.values].reverse().find((v) => v != null);
    g.fillStyle = g.strokeStyle;
    const label = `${s.label} ${last == null ? "–" : humanRate(last, s.unit)}`;
    if (lx < w - 40) g.fillText(label, lx, 12);
    lx += g.measureText(label).width + 12;
  });
  let alerts = 0;
  if (ALERT_GROUPS.has(group)) {
    g.strokeStyle = "#ff6b6b"; g.fillStyle = "#ff6b6b";
    for (const a of data.alerts) {
      if (a.t < t0) continue;
      const ax = x(a.t);
      g.beginPath(); g.moveTo(ax, top); g.lineTo(ax, h - bottom); g.stroke();
      const text = `${a.text} (${a.stream})`;
      const tw = g.measureText(text).width;
      g.fillText(text, ax + 3 + tw < w - right ? ax + 3 : Math.max(left, ax - 3 - tw), top + 12 + 12 * (alerts % 3));
      alerts += 1;
    }
  }
  canvas.dataset.points = String(points);
  canvas.dataset.alerts = String(alerts);
}

function renderPlots(data) {
  const root = document.querySelector("#plots");
  const groups = [...new Set(data.series.map((s) => s.group))];
  for (const group of groups) {
    let c = root.querySelector(`canvas[data-group="${group}"]`);
    if (!c) {
      c = document.createElement("canvas");
      c.dataset.group = group;
      c.className = "plot";
      root.append(c);
    }
    plotGroup(c, data, group);
  }
  const alerts = document.querySelector("#alerts");
  alerts.replaceChildren(...data.alerts.slice(-5).reverse().map((a) => {
    const li = document.createElement("li");
    li.className = "bad";
    li.textContent = `${new Date(a.t * 1000).toLocaleTimeString()} ${a.text}: ${a.stream} ` +
      `at ${a.fps} fps` + (a.usual_fps != null ? ` (usually ${a.usual_fps})` : "") +
      (a.drops ? `, ${a.drops} dropped` : "");
    return li;
  }));
}

async function pollHealth() {
  let ok = false;
  try {
    const seconds = document.querySelector("#healthwindow").value;
    const r = await fetch(`api/health/history?seconds=${seconds}`, { cache: "no-store" });
    if (r.ok) {
      const data = await r.json();
      window.flowrt.health = data;
      renderPlots(data);
      ok = true;
    }
  } catch (e) { /* the next poll tries again, later after each failure */ }
  setTimeout(pollHealth, window.flowrt.later("health", ok, 1000));
}
