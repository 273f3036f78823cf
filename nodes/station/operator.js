// The operator's station in the live view: Record (a named session, Start/Stop, live state,
// the per-stream table at Stop) and Review (the sessions, a player per session).
// Talks to /api/record/* and /api/sessions* of the view's own server (same origin).
"use strict";

// recordEpoch: counts this page's starts and stops answered; a state asked before the last of
// them is older than what the page said of it, and is not shown (a poll in flight during a
// Start, answered after it, read "stopped from elsewhere" beside the REC it had started)
const op = window.flowrt.operator = { starts: 0, stops: 0, sessions: [], lastStop: null, error: "", recordEpoch: 0 };
const q = (sel) => document.querySelector(sel);

function td(text, cls) {
  const e = document.createElement("td");
  if (cls) e.className = cls;
  e.textContent = text == null ? "–" : String(text);
  return e;
}
function tr(cells, attrs) {
  const r = document.createElement("tr");
  for (const [k, v] of Object.entries(attrs || {})) r.setAttribute(k, v);
  r.append(...cells);
  return r;
}
function bytes(n) {
  if (n == null) return "–";
  const k = ["B", "KB", "MB", "GB", "TB"];
  let i = 0;
  while (n >= 1000 && i < k.length - 1) { n /= 1000; i += 1; }
  return `${n.toFixed(n >= 100 || i === 0 ? 0 : 1)} ${k[i]}`;
}
const secs = (s) => (s == null ? "–" : `${Number(s).toFixed(1)} s`);

async function api(method, path, body) {
  const r = await fetch(path, {
    method, cache: "no-store",
    headers: body === undefined ? {} : { "Content-Type": "application/json" },
    body: body === undefined ? undefined : JSON.stringify(body),
  });
  const data = r.headers.get("Content-Type")?.startsWith("application/json") ? await r.json() : { error: await r.text() };
  if (!r.ok) throw new Error(data.error || r.statusText);
  return data;
}

// --- Record ----------------------------------------------------------------------------------

function say(text, cls) {
  const e = q("#recmsg");
  e.textContent = text;
  e.className = cls || "muted";
}

async function recordStart() {
  q("#recstart").disabled = true;
  try {
    const a = await api("POST", "api/record/start", { name: q("#recname").value.trim() });
    op.recordEpoch += 1;
    op.starts += 1;
    op.session = a.session;
    if (a.session == null) {  // 202: the recorders start when they can; said once they do
      say(a.error, "warn");
      op.startPending = true;
    } else { say(`recording ${a.session}`, "ok"); op.saidRecording = a.session; }
    q("#recresult").replaceChildren();
  } catch (e) {
    op.recordEpoch += 1;
    op.error = e.message;
    say(`cannot start: ${e.message}`, "bad");
  } finally {
    pollRecord(false);
  }
}

async function recordStop() {
  q("#recstop").disabled = true;
  op.saidRecording = null;  // this page's stop says its own result
  op.startPending = false;
  say("stopping: finishing the files…", "warn");
  try {
    const a = await api("POST", "api/record/stop", {});
    op.recordEpoch += 1;
    op.stops += 1;
    op.lastStop = a;
    if (a.finished === false) {  // 202: stopped, the files still being finished on a slow disk
      say(`${a.session}: stopped; ${a.error}`, "warn");
      pollSessions();
      return;
    }
    say(`${a.session}: ${secs(a.duration_s)}, ${a.lost} lost` + (a.error ? ` · ${a.error}` : ""), a.lost || a.error ? "bad" : "ok");
    showStopTable(a);
    pollSessions();
  } catch (e) {
    op.recordEpoch += 1;
    op.error = e.message;
    say(`cannot stop: ${e.message}`, "bad");
  } finally {
    pollRecord(false);
  }
}

function showStopTable(a) {
  const head = tr(["stream", "Hz", "expected", "received", "written", "lost", "missing", "rate"].map((h) => {
    const th = document.createElement("th"); th.textContent = h; return th;
  }));
  const rows = a.streams.filter((s) => !s.topic.includes("/annotations/")).map((s) => tr([
    td(s.topic), td(s.nominal_hz == null ? null : s.nominal_hz.toFixed(1)), td(s.expected), td(s.received),
    td(s.written), td(s.lost, s.lost ? "bad" : ""), td(s.missing, s.missing ? "warn" : ""),
    td(s.rate_mean == null ? null : s.rate_mean.toFixed(1)),
  ], { "data-topic": s.topic }));
  const t = document.createElement("table");
  t.id = "stoptable";
  const th = document.createElement("thead"); th.append(head);
  const tb = document.createElement("tbody"); tb.append(...rows);
  t.append(th, tb);
  q("#recresult").replaceChildren(t);
}

class Stale extends Error {}  // a record state older than this page's last start or stop

async function pollRecord(again = true) {
  const epoch = op.recordEpoch;
  let ok = false;
  try {
    const s = await api("GET", "api/record");
    ok = true;
    if (epoch !== op.recordEpoch) throw new Stale();  // asked before this page's start or stop
    op.state = s;
    const none = !s.recorders.length;
    q("#recstart").disabled = none || s.recording;
    q("#recstop").disabled = none || !s.recording;
    q("#recstate").textContent = none
      ? "no recorder in this graph (flowrt run GRAPH --recordings DIR adds one)"
      : s.recording ? `● REC ${s.session} · ${secs(s.elapsed_s)} · ${bytes(s.size_bytes)}` : "stopped";
    q("#recstate").className = s.recording ? "bad" : "muted";
    if (op.startPending && s.recording) {  // a late start (202) said in the same words
      say(`recording ${s.session}`, "ok");
      op.saidRecording = s.session;
      op.startPending = false;
    }
    if (op.saidRecording && !(s.recording && s.session === op.saidRecording)) {
      // another page (or flowrt ctl) stopped it: "recording X" beside "stopped" misled
      say(`${op.saidRecording}: stopped from elsewhere`, "muted");
      op.saidRecording = null;
    }
    q("#reclive").replaceChildren(...s.streams.filter((x) => !x.topic.includes("/annotations/"))
      .map((x) => {
        const e = document.createElement("span");
        e.dataset.topic = x.topic;
        e.textContent = `${x.topic} ${x.rate.toFixed(1)}/s`;
        return e;
      }));
  } catch (e) {
    if (!(e instanceof Stale)) {
      // the runtime gone (or the token changed): nothing can be started or stopped from here,
      // and "recording X" no longer knows
      q("#recstate").textContent = `record state unavailable (${e.message})`;
      q("#recstart").disabled = q("#recstop").disabled = true;
      if (op.saidRecording) say(`${op.saidRecording}: state unknown (${e.message})`, "warn");
      op.saidRecording = null;
    }
  }
  if (again) setTimeout(pollRecord, window.flowrt.later("record", ok, 1000));
}

// --- Review ----------------------------------------------------------------------------------

async function pollSessions() {
  try {
    const data = await api("GET", "api/sessions");
    op.sessions = data.sessions;
    q("#sessions tbody").replaceChildren(...data.sessions.map((s) => {
      const open = document.createElement("button");
      open.textContent = "open";
      open.disabled = s.recording;
      open.addEventListener("click", () => openSession(s.name));
      const streams = s.streams.filter((x) => !x.topic.includes("/annotations/"));
      const summary = streams.map((x) => `${x.topic} ${x.frames ?? "–"} @ ${x.rate ?? "–"}`).join(", ");
      const cell = td(summary, "l streams"); cell.title = summary;
      return tr([td(s.name), td(s.start ? new Date(s.start).toLocaleString() : "–", "l"),
        td(secs(s.duration_s)), td(bytes(s.size_bytes)), cell,
        td(s.recording ? "recording" : s.lost, s.lost ? "bad" : ""), (() => { const c = document.createElement("td"); c.append(open); return c; })()],
        { "data-session": s.name });
    }));
    q("#nosessions").hidden = data.sessions.length > 0;
    q("#nosessions").textContent = data.folders.length
      ? `no session yet in ${data.folders.join(", ")}` : "no recordings folder (flowrt run GRAPH --recordings DIR)";
  } catch (e) { /* shown as an empty list; the next poll tries again */ }
}

const player = op.player = { name: null, t: 0, duration: 0, playing: false, speed: 1, cameras: [], shown: 0, busy: 0 };

async function openSession(name) {
  const d = await api("GET", `api/sessions/${encodeURIComponent(name)}`);
  Object.assign(player, { name, t: 0, duration: d.duration_s, cameras: d.cameras, playing: false, detail: d });
  q("#player").hidden = false;
  q("#playername").textContent = `${name} · ${new Date(d.start).toLocaleString()} · ${secs(d.duration_s)}`;
  q("#scrub").max = String(d.duration_s);
  q("#scrub").value = "0";
  q("#playerviews").replaceChildren(...d.cameras.map((c) => {
    const img = document.createElement("img");
    img.dataset.topic = c;
    img.alt = c;
    const fig = document.createElement("figure");
    const cap = document.createElement("figcaption");
    cap.textContent = c;
    fig.append(img, cap);
    return fig;
  }));
  q("#playerstreams tbody").replaceChildren(...d.streams.filter((s) => !s.topic.includes("/annotations/")).map((s) => {
    const gaps = s.gaps.length ? `${s.gaps.length}: ` + s.gaps.slice(0, 4).map((g) => `${g.at.toFixed(1)} s (${(g.length * 1000).toFixed(0)} ms)`).join(", ") : "0";
    return tr([td(s.topic), td(s.frames), td(s.rate), td(s.expected), td(s.received), td(s.written),
      td(s.lost, s.lost ? "bad" : ""), td(gaps, s.gaps.length ? "l warn" : "l")], { "data-topic": s.topic });
  }));
  showAt(0);
}

function frameUrl(topic, t) {
  return `api/sessions/${encodeURIComponent(player.name)}/frame?topic=${encodeURIComponent(topic)}&t=${t.toFixed(3)}`;
}

function showAt(t) {
  // One request per camera at a time: a player that asks faster than frames come back
  // skips positions instead of queueing them.
  player.t = Math.max(0, Math.min(t, player.duration));
  q("#scrub").value = String(player.t);
  q("#playtime").textContent = `${player.t.toFixed(2)} / ${player.duration.toFixed(2)} s`;
  if (player.busy) return;
  const imgs = [...document.querySelectorAll("#playerviews img")];
  player.busy = imgs.length;
  for (const img of imgs) {
    const next = new Image();
    next.onload = () => { img.src = next.src; player.shown += 1; img.dataset.t = String(player.t); player.busy -= 1; };
    next.onerror = () => { player.busy -= 1; };
    next.src = frameUrl(img.dataset.topic, player.t);
  }
}

function tick(last) {
  if (!player.playing) return;
  const now = performance.now();
  const t = player.t + (now - last) / 1000 * player.speed;
  if (t >= player.duration) { player.playing = false; q("#play").textContent = "▶ play"; showAt(player.duration); return; }
  showAt(t);
  requestAnimationFrame(() => tick(now));
}

// --- Robots (a base station: their state and recorders over Zenoh) ---------------------------

async function robotRecord(name, action) {
  const msg = q("#robotmsg");
  msg.textContent = `${name}: ${action}…`;
  msg.className = "warn";
  try {
    const body = action === "start" ? { name: q("#recname").value.trim() } : {};
    const a = await api("POST", `api/robots/${encodeURIComponent(name)}/record/${action}`, body);
    op.robotAnswers = (op.robotAnswers || 0) + 1;
    op.lastRobot = a;
    msg.textContent = action === "start" ? `${name}: recording ${a.session}`
      : `${name}: ${a.session} · ${secs(a.duration_s)} · ${a.lost} lost · ` +
        a.streams.filter((x) => !x.topic.includes("/annotations/")).map((x) => `${x.topic} ${x.written}/${x.expected ?? "–"}`).join(", ");
    msg.className = action === "stop" && a.lost ? "bad" : "ok";
  } catch (e) {
    msg.textContent = `${name}: ${e.message}`;
    msg.className = "bad";
  }
  pollRobots(false);
}

async function pollRobots(again = true) {
  let ok = false;
  try {
    const data = await api("GET", "api/robots");
    op.robots = data.robots;
    q("#robotspanel").hidden = !data.robots.length;
    q("#robots tbody").replaceChildren(...data.robots.map((r) => {
      const sessions = Object.values(r.recording || {}).filter((x) => x);
      const buttons = document.createElement("td");
      for (const action of ["start", "stop"]) {
        const b = document.createElement("button");
        b.textContent = action === "start" ? "● Start" : "■ Stop";
        b.dataset.action = action;
        b.disabled = !r.reachable || (action === "start" ? sessions.length > 0 : !sessions.length);
        b.addEventListener("click", () => robotRecord(r.name, action));
        buttons.append(b, " ");
      }
      const h = r.health;
      const health = h ? `cpu ${h.cpu_percent.toFixed(0)} % · mem ${h.memory_percent.toFixed(0)} %` : "–";
      const streams = (r.streams || []).map((x) => `${x.name} ${x.fps == null ? "–" : x.fps.toFixed(1)} fps`).join(", ");
      return tr([td(r.name), td(r.reachable ? (r.failed.length ? `in error: ${r.failed.join(", ")}` : "ok") : r.error, r.reachable && !r.failed.length ? "l ok" : "l bad"),
        td(r.graph, "l"), td(secs(r.uptime)), td(r.loop_lag_ms == null ? null : `${r.loop_lag_ms.toFixed(2)} ms`),
        td(streams || "–", "l"), td(health, "l"),
        td(sessions.length ? `● REC ${sessions.map((x) => x.split("/").pop()).join(", ")}` : "stopped", sessions.length ? "l bad" : "l muted"),
        buttons], { "data-robot": r.name, "data-reachable": String(r.reachable) });
    }));
    ok = true;
  } catch (e) { /* the next poll tries again, later after each failure */ }
  if (again) setTimeout(pollRobots, window.flowrt.later("robots", ok, 2000));
}

function setupOperator() {
  q("#recstart").addEventListener("click", recordStart);
  q("#recstop").addEventListener("click", recordStop);
  q("#recname").addEventListener("keydown", (ev) => { if (ev.key === "Enter") recordStart(); });
  q("#scrub").addEventListener("input", (ev) => showAt(Number(ev.target.value)));
  q("#speed").addEventListener("change", (ev) => { player.speed = Number(ev.target.value); });
  q("#play").addEventListener("click", () => {
    player.playing = !player.playing;
    q("#play").textContent = player.playing ? "❚❚ pause" : "▶ play";
    if (player.playing) {
      if (player.t >= player.duration) player.t = 0;
      requestAnimationFrame(() => tick(performance.now()));
    }
  });
  pollRecord();
  pollRobots();
  pollSessions();
  setInterval(pollSessions, 5000);
  pollHealth();
}
