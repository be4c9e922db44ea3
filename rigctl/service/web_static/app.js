// rigctl web page: status, live IMU and table plots, queue editing, finished runs.
// Everything is served by the daemon itself (no CDN). The token is kept in this tab's
// sessionStorage only; it is sent as "Authorization: Bearer ..." on every request.
"use strict";

const G0 = 9.80665;          // m/s^2 per g (display only)
const DEG = 180 / Math.PI;
const HISTORY_S = 300;       // seconds of live history on the plots
const COLORS = ["#d1453b", "#2f8f46", "#2f62c9"];

let token = "";
const live = { imu: [], table: [], received: 0, lastT: null };
let lastStatus = null;

function $(id) { return document.getElementById(id); }

function loadToken() {
  const m = /(?:^#|&)token=([^&]+)/.exec(location.hash);
  if (m) {
    sessionStorage.setItem("rigctl-token", decodeURIComponent(m[1]));
    history.replaceState(null, "", location.pathname + location.search);  // off the address bar
  }
  token = sessionStorage.getItem("rigctl-token") || "";
}

function headers(json) {
  const h = {};
  if (token) h["Authorization"] = "Bearer " + token;
  if (json) h["Content-Type"] = "application/json";
  return h;
}

async function api(method, path, body) {
  const r = await fetch(path, { method, headers: headers(body !== undefined),
                               body: body !== undefined ? JSON.stringify(body) : undefined });
  let data = {};
  try { data = await r.json(); } catch (e) { data = { ok: false, error: "HTTP " + r.status }; }
  data.httpStatus = r.status;
  return data;
}

function say(text, ok) {
  const m = $("message");
  m.textContent = text;
  m.className = "message" + (ok ? " ok" : "");
}

function fmtDuration(s) {
  if (s === null || s === undefined) return "-";
  s = Math.max(0, Math.round(s));
  const h = Math.floor(s / 3600), m = Math.floor((s % 3600) / 60), sec = s % 60;
  return (h ? h + " h " : "") + (h || m ? m + " min " : "") + sec + " s";
}

// -- status -----------------------------------------------------------------------------------
function showStatus(st) {
  lastStatus = st;
  const state = st.state || "?";
  $("state").textContent = state;
  $("state").className = "state " + state;
  $("st-state").textContent = state + (st.reason ? " (" + st.reason + ")" : "");
  const job = st.job;
  $("st-job").textContent = job ? `${job.id}: ${(job.procedure || job.run_dir || "").split("/").pop()}` : "-";
  $("st-step").textContent = st.step || "-";
  $("st-frac").value = st.step_fraction || 0;
  $("st-eta").textContent = st.remaining_s !== undefined ? "about " + fmtDuration(st.remaining_s) + " left" : "-";
  $("st-samples").textContent = st.imu_samples !== undefined ? st.imu_samples : "-";
  const sus = st.suspenders || {};
  $("st-susp").textContent = (Object.keys(sus).length ? Object.entries(sus).map(([k, v]) => k + ": " + v).join("; ") : "no")
    + (st.deferred_pause ? " (pause requested for the end of this step)" : "");
  $("st-queue").textContent = `${st.queued || 0} queued, queue ${st.queue_running ? "running" : "stopped"}`;
}

// -- live plots -------------------------------------------------------------------------------
function addLive(batch) {
  for (const p of batch.imu || []) live.imu.push(p);
  for (const p of batch.table || []) live.table.push(p);
  live.received += (batch.imu || []).length;
  const tEnd = live.imu.length ? live.imu[live.imu.length - 1].t : null;
  if (tEnd !== null) {
    // a new run restarts IMU time: drop what lies ahead of the newest point
    live.imu = live.imu.filter(p => p.t > tEnd - HISTORY_S && p.t <= tEnd);
    live.lastT = tEnd;
  }
  const tt = live.table.length ? live.table[live.table.length - 1].t : null;
  if (tt !== null) live.table = live.table.filter(p => p.t > tt - HISTORY_S && p.t <= tt);
  document.body.dataset.liveReceived = String(live.received);
  document.body.dataset.liveLastT = String(live.lastT);
  if (live.imu.length) {
    const p = live.imu[live.imu.length - 1];
    const f = p.f.map(v => (v / G0).toFixed(4)).join(", ");
    const w = p.w.map(v => (v * DEG).toFixed(3)).join(", ");
    $("live-values").textContent = `t ${p.t.toFixed(1)} s | f [${f}] g | w [${w}] deg/s`;
    $("live-info").textContent = `(${live.imu.length} points, ${batch.bin_s} s means, last ${HISTORY_S / 60} min)`;
  }
  draw();
}

function plot(canvas, pts, getter, scale, unit, title, labels) {
  const ctx = canvas.getContext("2d");
  const W = canvas.width, H = canvas.height, L = 60, R = 10, T = 18, B = 18;
  ctx.clearRect(0, 0, W, H);
  ctx.font = "12px sans-serif";
  ctx.fillStyle = "#1d2430";
  ctx.fillText(title + " [" + unit + "]", L, 12);
  if (!pts.length) { ctx.fillStyle = "#7b8593"; ctx.fillText("no data yet", L + 10, H / 2); return; }
  const t1 = pts[pts.length - 1].t, t0 = Math.max(pts[0].t, t1 - HISTORY_S);
  let lo = Infinity, hi = -Infinity;
  for (const p of pts) for (const v of getter(p)) if (v !== null) { lo = Math.min(lo, v * scale); hi = Math.max(hi, v * scale); }
  if (!isFinite(lo)) return;
  if (hi - lo < 1e-9) { hi += 0.5; lo -= 0.5; }
  const pad = 0.08 * (hi - lo); lo -= pad; hi += pad;
  const x = t => L + (W - L - R) * (t1 > t0 ? (t - t0) / (t1 - t0) : 1);
  const y = v => T + (H - T - B) * (1 - (v - lo) / (hi - lo));
  ctx.strokeStyle = "#dde2e8"; ctx.fillStyle = "#5b6675";
  for (let i = 0; i <= 4; i++) {
    const v = lo + (hi - lo) * i / 4;
    ctx.beginPath(); ctx.moveTo(L, y(v)); ctx.lineTo(W - R, y(v)); ctx.stroke();
    ctx.fillText(Math.abs(v) < 1e-3 * (hi - lo) ? "0" : v.toPrecision(3), 2, y(v) + 4);
  }
  ctx.fillText(t0.toFixed(0) + " s", L, H - 4);
  ctx.fillText(t1.toFixed(0) + " s", W - R - 50, H - 4);
  for (let k = 0; k < 3; k++) {
    ctx.strokeStyle = COLORS[k]; ctx.lineWidth = 1.2; ctx.beginPath();
    let pen = false;
    for (const p of pts) {
      const v = getter(p)[k];
      if (v === null) { pen = false; continue; }
      if (!pen) { ctx.moveTo(x(p.t), y(v * scale)); pen = true; } else ctx.lineTo(x(p.t), y(v * scale));
    }
    ctx.stroke();
    ctx.fillStyle = COLORS[k];
    ctx.fillText(labels[k], W - R - 150 + 50 * k, 12);
  }
}

function draw() {
  const xyz = ["x", "y", "z"];
  plot($("plot-accel"), live.imu, p => p.f, 1 / G0, "g", "specific force", xyz);
  plot($("plot-gyro"), live.imu, p => p.w, DEG, "deg/s", "angular rate", xyz);
  plot($("plot-table"), live.table, p => p.angle, DEG, "deg", "table angle", ["outer", "middle", "inner"]);
}

// -- server-sent events, read with fetch so the token travels in a header -----------------------
async function stream() {
  for (;;) {
    try {
      const r = await fetch("/api/events", { headers: headers(false) });
      if (r.status === 401) { $("conn").textContent = "token needed for the live view"; await sleep(3000); continue; }
      if (!r.ok) throw new Error("HTTP " + r.status);
      $("conn").textContent = "live";
      const reader = r.body.getReader();
      const dec = new TextDecoder();
      let buf = "";
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        buf += dec.decode(value, { stream: true });
        let i;
        while ((i = buf.indexOf("\n\n")) >= 0) {
          const chunk = buf.slice(0, i); buf = buf.slice(i + 2);
          let ev = "message", data = "";
          for (const line of chunk.split("\n")) {
            if (line.startsWith("event: ")) ev = line.slice(7);
            else if (line.startsWith("data: ")) data += line.slice(6);
          }
          const obj = JSON.parse(data);
          if (ev === "status") showStatus(obj); else if (ev === "live") addLive(obj);
        }
      }
    } catch (e) {
      $("conn").textContent = "disconnected (" + e.message + "), retrying";
    }
    await sleep(2000);
  }
}

function sleep(ms) { return new Promise(r => setTimeout(r, ms)); }

// -- queue, history, runs -----------------------------------------------------------------------
function cell(tr, text) { const td = document.createElement("td"); td.textContent = text; tr.appendChild(td); return td; }

function button(label, onClick, cls) {
  const b = document.createElement("button");
  b.textContent = label; b.type = "button"; if (cls) b.className = cls;
  b.addEventListener("click", onClick);
  return b;
}

async function refreshQueue() {
  const q = await api("GET", "/api/queue");
  if (!q.ok) return;
  const body = $("queue").querySelector("tbody");
  body.textContent = "";
  const byId = Object.fromEntries(q.jobs.map(j => [j.id, j]));
  q.queued.forEach((jid, n) => {
    const j = byId[jid] || { id: jid };
    const tr = document.createElement("tr");
    tr.dataset.job = jid;
    cell(tr, n + 1); cell(tr, jid);
    cell(tr, j.kind === "resume" ? "resume " + (j.run_dir || "").split("/").pop() : (j.procedure || "").split("/").pop());
    cell(tr, Object.entries(j.params || {}).map(([k, v]) => k + "=" + v).join(", "));
    const td = cell(tr, "");
    td.appendChild(button("up", () => control("POST", `/api/queue/${jid}/move`, { position: Math.max(0, n - 1) })));
    td.appendChild(button("down", () => control("POST", `/api/queue/${jid}/move`, { position: n + 1 })));
    td.appendChild(button("remove", () => control("DELETE", `/api/queue/${jid}`), "danger"));
    body.appendChild(tr);
  });
  document.body.dataset.queued = q.queued.join(",");
}

async function refreshHistory() {
  const h = await api("GET", "/api/history?limit=20");
  if (h.ok) {
    const body = $("history").querySelector("tbody");
    body.textContent = "";
    for (const j of h.jobs) {
      const tr = document.createElement("tr");
      cell(tr, j.id); cell(tr, j.state);
      cell(tr, (j.procedure || j.run_dir || "").split("/").pop());
      cell(tr, (j.ended_utc || "").slice(0, 19).replace("T", " ")); cell(tr, j.message || "");
      body.appendChild(tr);
    }
  }
  const r = await api("GET", "/api/runs");
  if (r.ok) {
    const body = $("runs").querySelector("tbody");
    body.textContent = "";
    for (const run of r.runs.slice(0, 30)) {
      const tr = document.createElement("tr");
      // a complete recording whose analysis did not end: say so ("complete, analysis interrupted")
      const analysis = run.analysis && run.analysis !== "done" ? ", analysis " + run.analysis : "";
      cell(tr, run.id); cell(tr, run.procedure || ""); cell(tr, (run.status || "") + analysis);
      const td = cell(tr, "");
      if (run.status && run.status !== "running") td.appendChild(button("open report", () => openReport(run.id)));
      body.appendChild(tr);
    }
  }
}

async function openReport(run) {
  const w = window.open("", "_blank");
  const t = await api("POST", `/api/runs/${encodeURIComponent(run)}/ticket`);
  if (!t.ok) { say(t.error || "no report", false); if (w) w.close(); return; }
  if (w) w.location = t.url; else location.href = t.url;
}

async function loadProcedures() {
  const p = await api("GET", "/api/procedures");
  const sel = $("add-proc");
  sel.textContent = "";
  for (const name of (p.procedures || [])) {
    const o = document.createElement("option"); o.value = o.textContent = name; sel.appendChild(o);
  }
}

async function control(method, path, body) {
  const r = await api(method, path, body);
  if (r.ok) say(`${path.replace("/api/", "")}: done` + (r.note ? " (" + r.note + ")" : ""), true);
  else say(`${path.replace("/api/", "")}: refused (${r.httpStatus}): ${r.error}`, false);
  document.body.dataset.lastControl = String(r.httpStatus);
  refreshQueue(); refreshHistory();
  return r;
}

function parseParams(text) {
  const out = {};
  for (const part of text.split(/[;\n]/)) {
    const s = part.trim();
    if (!s) continue;
    const i = s.indexOf("=");
    if (i < 1) throw new Error(`parameter "${s}" is not NAME=VALUE`);
    out[s.slice(0, i).trim()] = s.slice(i + 1).trim();
  }
  return out;
}

function setup() {
  loadToken();
  $("token").value = token ? "********" : "";
  $("token-form").addEventListener("submit", e => {
    e.preventDefault();
    const v = $("token").value.trim();
    if (v && v !== "********") { token = v; sessionStorage.setItem("rigctl-token", v); $("token").value = "********"; }
    loadProcedures(); refreshQueue(); refreshHistory();
  });
  for (const b of document.querySelectorAll("button[data-cmd]")) {
    b.addEventListener("click", () => control("POST", "/api/" + b.dataset.cmd,
                                              b.dataset.body ? JSON.parse(b.dataset.body) : undefined));
  }
  $("add-form").addEventListener("submit", e => {
    e.preventDefault();
    let params;
    try { params = parseParams($("add-params").value); } catch (err) { say(err.message, false); return; }
    const body = { procedure: $("add-proc").value, params };
    const pos = $("add-pos").value;
    if (pos) body.position = Math.max(0, parseInt(pos, 10) - 1);
    control("POST", "/api/queue", body);
  });
  loadProcedures(); refreshQueue(); refreshHistory();
  setInterval(() => { refreshQueue(); refreshHistory(); }, 3000);
  stream();
}

document.addEventListener("DOMContentLoaded", setup);
