// The operator view: one EventSource from lathed-web, six panels redrawn at most 4 times a second,
// all on one 1920x1080 screen (app.css); charts fit the room their panel gives them.
"use strict";
const META = JSON.parse(document.getElementById("meta").textContent);
const $ = (sel) => document.querySelector(sel);
const S = { hist: {}, units: {}, latest: {}, status: null, events: [], vib: {}, views: {}, connected: false,
            error: null, lastFrame: 0, parts: [] };
const HISTORY = 600;
let dirty = true, drawQueued = false, recordsDirty = true, partsDirty = true;

// -- data --------------------------------------------------------------------------------
function addSample(key, t, v, unit) {
  const h = S.hist[key] || (S.hist[key] = [[], []]);
  if (h[0].length && h[0][h[0].length - 1] >= t) return;
  h[0].push(t); h[1].push(v);
  if (h[0].length > HISTORY) { h[0].shift(); h[1].shift(); }
  S.latest[key] = v;
  if (unit !== undefined) S.units[key] = unit;
}
// An array the daemon packed (lathed.display.packed: {"f32": base64 of little-endian float32}),
// as numbers; NaN (a gap) as null, which uPlot draws as a gap.
function unpack(v) {
  if (!v || typeof v !== "object" || typeof v.f32 !== "string") return v;
  const bin = atob(v.f32), bytes = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
  return Array.from(new Float32Array(bytes.buffer), (x) => (Number.isFinite(x) ? x : null));
}
function unpackAll(views) {
  for (const v of Object.values(views || {})) if (v && typeof v === "object") for (const k of Object.keys(v)) v[k] = unpack(v[k]);
  return views || {};
}
function onInit(m) {
  S.hist = {}; S.latest = {}; S.units = m.units || {};
  for (const [k, [ts, vs]] of Object.entries(m.history || {})) ts.forEach((t, i) => addSample(k, t, vs[i]));
  S.status = m.status; S.events = m.events || []; S.vib = unpackAll(m.vibration); S.views = unpackAll(m.views);
  recordsDirty = true; eventsShown = { filter: null, last: -1 };
  setLink(m.connected, m.error);
}
function onFrame(m) {
  for (const [k, [t, v, unit]] of Object.entries(m.samples || {})) addSample(k, t, v, unit);
  if (m.status) S.status = m.status;
  // a view in a frame carries only its changed keys (null: gone); null for a whole view replaces it
  const merge = (to, from) => { for (const [k, v] of Object.entries(from || {})) {
    if (v && typeof v === "object" && to[k] && typeof to[k] === "object") {
      const o = Object.assign({}, to[k], v);
      for (const [kk, vv] of Object.entries(v)) if (vv === null) delete o[kk];
      to[k] = o;
    } else to[k] = v;
  } };
  merge(S.vib, unpackAll(m.vibration));
  merge(S.views, unpackAll(m.views));
  if (m.events && m.events.length) { S.events = S.events.concat(m.events).slice(-500); recordsDirty = true; refreshParts(); }
  S.lastFrame = Date.now();
  if (!S.connected) setLink(true, null);
}
function setLink(ok, err) {
  S.connected = ok; S.error = err; S.lastFrame = Date.now();
  const el = $("#link");
  el.textContent = ok ? "live" : "disconnected: " + (err || "no daemon");
  el.className = "badge " + (ok ? "ok" : "bad");
  dirty = true;
}
function connect() {
  const es = new EventSource("/events");
  S.es = es;
  es.onmessage = (e) => {
    const m = JSON.parse(e.data);
    if (m.type === "init") onInit(m);
    else if (m.type === "frame") onFrame(m);
    else if (m.type === "link") setLink(m.connected, m.error);
    dirty = true;
    if (!drawQueued) { drawQueued = true; requestAnimationFrame(() => { drawQueued = false; draw(); }); }
  };
  es.onerror = async () => {
    if (es.readyState !== EventSource.CLOSED) { setLink(false, "lathed-web is not reachable"); return; }
    // refused (too many live pages open) or gone for good: say which, and try again later
    let why = "lathed-web ended the live stream";
    try {
      const h = await (await fetch("/api/health")).json();
      if (h.live && h.live.pages >= h.live.max_pages) why = `refused: ${h.live.pages} of ${h.live.max_pages} live pages are open; trying again every 10 s`;
    } catch (e) { why = "lathed-web is not reachable"; }
    setLink(false, why);
    setTimeout(connect, 10000);
  };
}

// -- helpers -------------------------------------------------------------------------------
const fmt = (v, d = 1) => v === undefined || v === null ? "-" : (typeof v === "number" ? v.toFixed(d) : String(v));
const analyzer = (plugin) => (S.status && S.status.analyzers || []).find((a) => a.plugin === plugin);
const esc = (s) => String(s).replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" })[c]);
// one formatter for all: toLocaleTimeString makes a new one per call (a tenth of a millisecond each)
const TIME = new Intl.DateTimeFormat([], { hour: "2-digit", minute: "2-digit", second: "2-digit", hour12: false });
const hhmmss = (t) => TIME.format(t * 1000);
function note(sel, text, err) { const el = $(sel); el.textContent = text; el.title = text; el.classList.toggle("err", !!err); }
// A confirmation or a refusal of what the operator did: stays until read (the OK button), never
// overwritten by the next redraw
function confirmed(sel, text, err) {
  const el = $(sel);
  el.querySelector("span").textContent = `${hhmmss(Date.now() / 1000)}  ${text}`;
  el.classList.toggle("err", !!err);
  el.hidden = false;
}
document.querySelectorAll(".confirm .ok").forEach((b) => b.addEventListener("click", () => { b.parentElement.hidden = true; }));

// Histories of several keys on one time axis (null where a key has no point)
function joined(keys) {
  const xs = [...new Set(keys.flatMap((k) => (S.hist[k] || [[]])[0]))].sort((a, b) => a - b);
  const idx = new Map(xs.map((x, i) => [x, i]));
  return [xs, ...keys.map((k) => {
    const col = new Array(xs.length).fill(null), h = S.hist[k];
    if (h) h[0].forEach((t, i) => { col[idx.get(t)] = h[1][i]; });
    return col;
  })];
}

const COLORS = ["#58a6ff", "#f0883e", "#3fb950", "#d2a8ff", "#ff7b72", "#e3b341", "#39c5cf", "#8b949e"];
const charts = {};
const lastIdx = (u) => u.data[0].length - 1;
function lastValue(col, upto) {
  for (let i = Math.min(upto, col.length - 1); i >= 0; i--) if (col[i] !== null && col[i] !== undefined) return col[i];
  return null;
}
function num(v, d) {
  if (v === null || v === undefined) return "-";
  const a = Math.abs(v);
  if (a !== 0 && a < 1) return v.toPrecision(Math.max(2, d));
  return a >= 1000 ? v.toFixed(0) : a >= 100 ? v.toFixed(Math.min(d, 1)) : v.toFixed(d);
}
// The room a chart has: its cell, less its legend (which may wrap to two lines)
function chartSize(el, u) {
  const legend = u && u.root.querySelector(".u-legend");
  return { width: Math.max(150, el.clientWidth), height: Math.max(50, el.clientHeight - (legend ? legend.offsetHeight : 22) - 2) };
}
const sizer = new ResizeObserver((entries) => {
  for (const e of entries) { const c = charts[e.target.id]; if (c) c.u.setSize(chartSize(e.target, c.u)); }
  dirty = true;
});
function chart(id, series, opts = {}) {
  // (re)made when its series change; otherwise only its data is set (chart(...).set(data))
  const el = document.getElementById(id);
  const sig = JSON.stringify(series);
  let c = charts[id];
  if (c && c.sig === sig) return c;
  if (c) c.u.destroy();
  const axis = { stroke: "#8b95a3", grid: { stroke: "#2c333d" }, ticks: { stroke: "#2c333d" } };
  const time = opts.time !== false;
  // with no cursor on the chart, the legend shows each series' latest value (or the
  // chart's own choice, opts.idle: the spectrum's peak), never "--"
  const idle = (u) => (u.data[0].length ? (opts.idle ? opts.idle(u) : lastIdx(u)) : null);
  const showIdle = (u) => {
    if (u.cursor.idx === null || u.cursor.idx === undefined) { const i = idle(u); if (i !== null) u.setLegend({ idx: i }); }
  };
  const u = new uPlot({
    ...chartSize(el, null), legend: { show: true, live: true },
    scales: { x: { time }, ...(opts.scales || {}) },
    // a time axis in hh:mm:ss only: uPlot's date line under it costs a chart's height
    axes: [{ ...axis, ...(time ? { values: (u, ts) => ts.map((t) => hhmmss(t)), space: 75 } : {}), ...(opts.xaxis || {}) },
           { ...axis, size: 50, ...(opts.yaxis || {}) }],
    series: [{ label: opts.xlabel || "time",
               value: (u, v) => (v === null || v === undefined ? "-" : time ? hhmmss(v) : num(v, 0) + (opts.xunit ? " " + opts.xunit : "")) },
             ...series.map((s, i) => ({ label: s.label, stroke: s.stroke || COLORS[i % COLORS.length], width: 1.5,
                                        spanGaps: true, dash: s.dash, points: { show: false },
                                        value: (u, v, si, di) => num(v ?? lastValue(u.data[si], di ?? lastIdx(u)), s.digits ?? 2)
                                                                 + (s.unit ? " " + s.unit : "") }))],
    hooks: { setCursor: [showIdle], draw: [showIdle] },
  }, null, el);
  u.setSize(chartSize(el, u));
  sizer.observe(el);
  c = charts[id] = { u, sig, set: (data) => { u.setData(data); showIdle(u); } };
  return c;
}
window.__charts = charts;
// The index chart's top: the threshold stays in view whatever one spike does (a spike is
// drawn clipped and its height said above the chart): at least twice the threshold, at most
// ten times it, else what 95 % of the points reach
function indexTop(index, threshold) {
  const xs = index.filter((v) => v !== null && v !== undefined && Number.isFinite(v)).sort((a, b) => a - b);
  if (!threshold || threshold <= 0 || !xs.length) return null;
  const q95 = xs[Math.floor(0.95 * (xs.length - 1))];
  return Math.min(10 * threshold, Math.max(2 * threshold, 1.15 * q95));
}
function canvas(id) {
  const c = document.getElementById(id), r = window.devicePixelRatio || 1;
  const w = c.clientWidth, h = c.clientHeight;
  if (c.width !== w * r || c.height !== h * r) { c.width = w * r; c.height = h * r; }
  const g = c.getContext("2d");
  g.setTransform(r, 0, 0, r, 0, 0);
  g.clearRect(0, 0, w, h);
  g.font = "11px system-ui"; g.fillStyle = "#8b95a3"; g.strokeStyle = "#2c333d";
  return [g, w, h];
}

// -- panels ---------------------------------------------------------------------------------
function drawMachines() {
  const rows = (S.status && S.status.machines || []).map((m) => {
    const v = (q) => S.latest[m.name + "/" + q];
    const axes = ["x_mm", "y_mm", "z_mm", "b_deg"].filter((q) => v(q) !== undefined)
      .map((q) => `<span class="ax">${q[0].toUpperCase()} ${fmt(v(q), 1)}</span>`).join(" ");
    const stale = m.state !== "connected" || (m.age_s !== null && m.age_s > 3);
    const prog = v("program_number") !== undefined ? "O" + fmt(v("program_number"), 0) : (v("program") !== undefined ? "P" + fmt(v("program"), 0) : "-");
    const pstate = v("program_state") !== undefined ? ["idle", "running", "hold", "alarm"][v("program_state")] || v("program_state") : "";
    const kind = m.kind && m.kind !== m.name ? ` <small>${esc(m.kind)}</small>` : "";
    const data = m.state !== "connected" ? `<span class="badge bad">${esc(m.state)}</span>`
      : `<span class="badge ${stale ? "warn" : "ok"}">${stale ? "stale" : "live"}</span>`;
    return `<tr><td>${esc(m.name)}${kind}</td>
      <td>${m.spindle_rpm === null || m.spindle_rpm === undefined ? "-" : fmt(m.spindle_rpm, 0) + " r/min"}</td>
      <td>${axes || (v("j1_deg") !== undefined ? "6 joints" : "-")}</td><td>${prog} <small>${esc(pstate)}</small></td>
      <td>${fmt(v("part_count") ?? v("cycle_count"), 0)}${v("cycle_time_s") !== undefined ? ", " + fmt(v("cycle_time_s"), 1) + " s" : ""}</td>
      <td title="last data ${m.age_s === null || m.age_s === undefined ? "-" : fmt(m.age_s, 1) + " s ago"}">${data}</td></tr>`;
  });
  $("#machines tbody").innerHTML = rows.join("");
}

function drawLobes() {
  const [g, w, h] = canvas("lobes");
  const sup = analyzer("suppression"), view = sup && S.views[sup.name];
  if (!view || !view.rpm) { g.fillText("no stability lobes (no suppression analyzer with a modal model)", 10, 20); return; }
  const minB = Math.min(...view.blim_mm), depth = view.now_depth_mm || 0;
  const ymax = Math.max(3 * minB, 1.4 * depth, 0.1), x0 = view.rpm[0], x1 = view.rpm[view.rpm.length - 1];
  const L = 45, B = 20, X = (n) => L + (n - x0) / (x1 - x0) * (w - L - 8), Y = (b) => h - B - Math.min(b, ymax) / ymax * (h - B - 8);
  g.beginPath(); g.moveTo(X(x0), Y(ymax));
  view.rpm.forEach((n, i) => g.lineTo(X(n), Y(view.blim_mm[i])));
  g.lineTo(X(x1), Y(ymax)); g.closePath(); g.fillStyle = "rgba(248,81,73,.18)"; g.fill();   // unstable above
  g.beginPath(); view.rpm.forEach((n, i) => (i ? g.lineTo : g.moveTo).call(g, X(n), Y(view.blim_mm[i])));
  g.strokeStyle = "#f0883e"; g.lineWidth = 1.5; g.stroke();
  g.fillStyle = "#8b95a3";
  for (let k = 0; k <= 4; k++) { const b = ymax * k / 4; g.fillText(b.toFixed(2), 4, Y(b) + 4); }
  g.textAlign = "center";
  for (let k = 0; k <= 4; k++) { const n = x0 + (x1 - x0) * k / 4; g.fillText(n.toFixed(0), Math.min(X(n), w - 20), h - 5); }
  g.textAlign = "left";
  g.fillText("depth mm", L + 4, 12); g.fillText("r/min", w - 40, h - B - 4);
  if (view.now_rpm) {
    g.beginPath(); g.arc(X(view.now_rpm), Y(depth), 5, 0, 7); g.fillStyle = "#58a6ff"; g.fill();
  }
  $("#lobes-now").textContent = view.now_rpm ? `now ${fmt(view.now_rpm, 0)} r/min, ${fmt(depth, 2)} mm` : "";
}

function drawRobot() {
  const m = (S.status && S.status.machines || []).find((x) => S.latest[x.name + "/j1_deg"] !== undefined);
  if (!m) { $("#joints").textContent = "no robot arm on this line"; return; }
  const v = (q) => S.latest[m.name + "/" + q];
  $("#joints").innerHTML = [1, 2, 3, 4, 5, 6].map((j) => {
    const a = v("j" + j + "_deg");
    const pos = a === undefined ? 50 : Math.max(0, Math.min(100, (a + 180) / 3.6));
    return `<div class="joint">J${j} <span class="value">${fmt(a, 1)}°</span><div class="bar"><i style="left:${pos}%"></i></div></div>`;
  }).join("");
  $("#robot-tool").textContent = `X ${fmt(v("tool_x_mm"))}  Y ${fmt(v("tool_y_mm"))}  Z ${fmt(v("tool_z_mm"))} mm`;
  $("#robot-gripper").textContent = ["open", "closed", "moving"][v("gripper")] || fmt(v("gripper"), 0);
  $("#robot-cycles").textContent = fmt(v("cycle_count"), 0);
  const st = ["idle", "running", "alarm"][v("state")] || "-";
  const b = $("#robot-state"); b.textContent = m.state === "connected" ? st : m.state;
  b.className = "badge " + (m.state !== "connected" || st === "alarm" ? "bad" : "ok");
}

function drawVibration() {
  const name = Object.keys(S.vib).find((k) => S.vib[k]);
  const v = name && S.vib[name];
  if (v) {
    const ms = v.env_t.map((t) => t * 1000);
    const peak = (col) => (u) => { const d = u.data[col]; let b = 0; d.forEach((x, i) => { if (x !== null && x > d[b]) b = i; }); return b; };
    chart("signal", [{ label: "max", digits: 1 }, { label: "min", stroke: "#1f6feb", digits: 1 }],
          { time: false, xlabel: "at", xunit: "ms", idle: peak(1) }).set([ms, v.env_max, v.env_min]);
    chart("spectrum", [{ label: "peak amplitude", stroke: "#3fb950", digits: 1 }], { time: false, xlabel: "at", xunit: "Hz", idle: peak(1) })
      .set([v.spec_f, v.spec_a]);
  }
  const ch = analyzer("chatter");
  if (ch) {
    const k = ch.name + "/chatter_index", th = ch.name + "/chatter_threshold";
    const data = joined([k, th]), top = indexTop(data[1], lastValue(data[2], data[0].length - 1));
    chart("index", [{ label: "index" }, { label: "threshold", stroke: "#f85149", dash: [6, 4] }],
          { scales: { y: { range: (u, lo, hi) => { const t = indexTop(u.data[1], lastValue(u.data[2], lastIdx(u)));
                                                  return t === null ? [Math.min(0, lo ?? 0), Math.max(hi ?? 1, 1)] : [0, t]; } } } }).set(data);
    const hi = Math.max(...data[1].filter((x) => x !== null));
    $("#index-clip").textContent = top !== null && hi > top ? `(peak ${fmt(hi, 1)} above the chart)` : "";
    if (ch.detector) $("#index-title").textContent = ch.detector;
    const b = $("#chatter-state"); b.textContent = ch.cut_state || ch.state;
    b.className = "badge " + (ch.cut_state === "chatter" ? "bad" : ch.cut_state === "watching" ? "ok" : "warn");
    $("#chatter-f").textContent = ch.chatter_frequency_hz ? fmt(ch.chatter_frequency_hz, 0) + " Hz" : "-";
    $("#chatter-index").textContent = ch.index === null || ch.index === undefined ? "-" : `${fmt(ch.index, 2)} / ${fmt(ch.threshold, 2)}`;
    drawEye(S.views[ch.name]);
  }
  const sup = analyzer("suppression");
  document.querySelectorAll(".switch button[data-mode]").forEach((bt) => bt.classList.toggle("on", !!sup && sup.mode === bt.dataset.mode));
  if (sup && sup.pending) note("#suppress-note", `proposed (manual mode): ${fmt(sup.pending.rpm_before, 0)} → ${fmt(sup.pending.rpm_after, 0)} r/min: press "suppress now"`);
  else if (sup && sup.last_was_advice && sup.last_advice) note("#suppress-note", `${sup.last_advice.advice} (${sup.advisories} held with advice in all)`);
  else if (sup && sup.last_action) {
    // why it moved (an alarm, the lobes' prediction, a remembered cure) and who, when not itself
    const a = sup.last_action, why = [a.trigger, a.by && a.by !== sup.name ? `by ${a.by}` : ""].filter(Boolean).join(", ");
    const cures = sup.remember ? `; ${(sup.cures || []).length} remembered cure(s)` : "";
    note("#suppress-note", `last action: ${fmt(a.rpm_before, 0)} → ${fmt(a.rpm_after, 0)} r/min (${why}), ${sup.actions} in all${cures}`);
  }
}

function drawEye(view) {
  const [g, w, h] = canvas("eye");
  if (!view || !view.eye_phi1 || !view.eye_phi1.length) { g.fillText("no chaos eye yet (drawn while the tool cuts)", 10, 20); return; }
  const all = view.eye_phi1.concat(view.eye_phi2, view.base_phi1 || [], view.base_phi2 || []).map(Math.abs).sort((a, b) => a - b);
  const r = all[Math.floor(all.length * 0.98)] || 1, s = Math.min(w, h) / 2 / (r * 1.1), cx = w / 2, cy = h / 2;
  g.beginPath(); g.moveTo(0, cy); g.lineTo(w, cy); g.moveTo(cx, 0); g.lineTo(cx, h); g.stroke();
  const dots = (xs, ys, color) => { g.fillStyle = color; xs.forEach((x, i) => g.fillRect(cx + x * s - 1, cy - ys[i] * s - 1, 2, 2)); };
  dots(view.eye_phi1, view.eye_phi2, "#58a6ff");
  if (view.base_phi1) dots(view.base_phi1, view.base_phi2, "rgba(240,136,62,.8)");   // on top: it is the small one
  g.fillStyle = "#8b95a3"; g.fillText("orange: start of cut (baseline)", 6, h - 20); g.fillText("blue: now", 6, h - 6);
  if (view.eye_from === "revolution difference") g.fillText("drawn from the revolution difference (the alarm is the detector's)", 6, h - 34);
}

function drawThermal() {
  const temps = Object.keys(S.hist).filter((k) => /\/t_/.test(k)).sort();
  if (temps.length) chart("temps", temps.map((k) => ({ label: k.split("/")[1].slice(2), unit: "°C", digits: 2 }))).set(joined(temps));
  const th = analyzer("thermal");
  if (!th) { note("#thermal-info", "no thermal analyzer"); return; }
  const keys = [th.name + "/predicted_growth_um", th.name + "/compensation_um"];
  chart("growth", [{ label: "predicted growth", unit: "µm", digits: 1 }, { label: "compensation", stroke: "#3fb950", unit: "µm", digits: 1 }]).set(joined(keys));
  const rf = th.last_refit;
  note("#thermal-info", `model ${th.model}; growth ${fmt(th.predicted_growth_um, 1)} µm; offset written ${fmt(th.applied_offset_um, 1)} µm (target ${fmt(th.target_offset_um, 1)}), ${th.writes} writes` + (th.refused ? `; refused: ${th.refused}` : "")
    + (rf ? "; last refit: " + refitText(rf) : "; no refit yet"));
}
// error before and after on held-out rows, the effects the model now has, and whether it was kept
function refitText(rf) {
  const fx = (rf.effects || []).map((e) => e.effect + (e.sensor ? " (" + e.sensor + ")" : "")).join(", ");
  return `held-out error ${fmt(rf.before_rmse_um, 2)} → ${fmt(rf.after_rmse_um, 2)} µm, ` +
    (rf.better ? `adopted ${rf.model_after}` : `kept ${rf.model_before}`) + (fx ? `; effects: ${fx}` : "") + (rf.by ? ` (by ${rf.by})` : "");
}

function shownEvents() {
  const f = $("#filter").value.trim().toLowerCase();
  return S.events.filter((e) => !f || (e.kind + " " + e.source + " " + JSON.stringify(e.payload)).toLowerCase().includes(f));
}
const EVENT_ROWS = 150;
let eventsShown = { filter: null, last: -1 };
const eventRow = (e) => { const d = esc(detail(e.payload));
  return `<tr class="${/alarm|fault|refused|abnormal|unobserved/.test(e.kind) ? "abnormal" : ""}"><td>${e.id}</td><td>${hhmmss(e.t)}</td><td>${esc(e.source)}</td><td>${esc(e.kind)}</td><td title="${d}">${d}</td></tr>`; };
function drawRecords() {
  if (recordsDirty) {
    // new events go on top of the rows there; all are rebuilt only when the filter changes (or after a reconnect)
    recordsDirty = false;
    const f = $("#filter").value, tb = $("#events tbody");
    const ev = shownEvents();
    const fresh = eventsShown.filter === f ? ev.filter((e) => e.id > eventsShown.last) : null;
    if (fresh === null || fresh.length >= EVENT_ROWS) tb.innerHTML = ev.slice(-EVENT_ROWS).reverse().map(eventRow).join("");
    else if (fresh.length) {
      tb.insertAdjacentHTML("afterbegin", fresh.reverse().map(eventRow).join(""));
      while (tb.rows.length > EVENT_ROWS) tb.deleteRow(-1);
    }
    eventsShown = { filter: f, last: ev.length ? ev[ev.length - 1].id : -1 };
  }
  if (!partsDirty) return;      // rebuilt only when the parts or their filter change
  partsDirty = false;
  const only = $("#abnormal-only").checked;
  $("#parts tbody").innerHTML = S.parts.filter((p) => !only || p.abnormal).slice().reverse().map((p) =>
    `<tr class="${p.abnormal ? "abnormal" : ""}"><td>${p.id} <small>#${fmt(p.part_no, 0)}</small></td><td>${p.end_t ? hhmmss(p.end_t) : "-"}</td>
     <td>${fmt(p.max_chatter_index, 2)}</td><td>${fmt(p.compensation_um, 1)}</td><td>${esc(p.queued_reason || p.reason || "")}</td>
     <td>${p.inspected_t ? `Ra ${fmt(p.ra_um, 2)} Ø ${fmt(p.diameter_error_um, 1)} (${esc(p.inspector || "")})` : (p.queued_t ? "to inspect" : "")}</td></tr>`).join("");
}
function detail(p) {
  return Object.entries(p || {}).slice(0, 6).map(([k, v]) => k + "=" + (typeof v === "number" ? +v.toPrecision(4) : JSON.stringify(v))).join(" ");
}

let partsBusy = false;
async function refreshParts() {
  if (partsBusy) return;
  partsBusy = true;
  try {
    const r = await fetch("/api/parts?abnormal=" + ($("#abnormal-only").checked ? 1 : 0));
    const j = await r.json();
    if (r.ok && !j.error) { S.parts = j.result; dirty = partsDirty = true; } else confirmed("#records-confirm", "parts: " + j.error, true);
  } finally { partsBusy = false; }
}
async function refreshRecommend() {
  const r = await fetch("/api/recommend"), a = await r.json();
  if (a.error) { note("#recommend-note", "Taguchi recommendation: " + a.error); return; }
  const j = a.result, cur = j.current || {};
  // each factor's best level(s), with the physical setting where one was recorded
  const best = (v) => v ? esc(Object.entries(v.best_settings).map(([f, xs]) => f + " " + xs.map((x, i) => x ?? v.best[f][i]).join("/")).join(", ")) : "<small>not measured</small>";
  $("#recommend tbody").innerHTML = j.pairs.map((p) => {
    const now = p.tool === cur.tool && p.material === cur.material;
    const head = `<td>${esc(p.tool)} / ${esc(p.material)}${now ? " <small>(in use)</small>" : ""}</td>`;
    if (p.error) return `<tr>${head}<td colspan="4" class="bad">${esc(p.error)}</td></tr>`;
    const o = p.objectives || {};
    return `<tr class="${now ? "current" : ""}">${head}<td>${p.trials}</td><td>${best(o.precision)}</td><td>${best(o.surface)}</td><td>${best(o.efficiency)}</td></tr>`;
  }).join("");
  note("#recommend-note", j.pairs.length ? `in use: ${cur.tool} / ${cur.material}` : "no experiment records yet: add them with `lathectl experiment add`");
}

// -- actions ----------------------------------------------------------------------------------
async function act(path, body, confirmSel) {
  const r = await fetch("/api/" + path, { method: "POST", headers: { "Content-Type": "application/json", "X-CSRF-Token": META.csrf },
                                          body: JSON.stringify(body) });
  const j = await r.json().catch(() => ({ error: r.statusText }));
  if (!r.ok) confirmed(confirmSel, `refused (${r.status}): ${j.error}`, true);
  return [r.status, j];
}
document.querySelectorAll(".switch button[data-mode]").forEach((b) => b.addEventListener("click", async () => {
  const [st] = await act("suppress", { action: b.dataset.mode }, "#suppress-confirm");
  if (st === 200) confirmed("#suppress-confirm", `suppression set to ${b.dataset.mode} by ${META.user}`);
}));
$("#suppress-now").addEventListener("click", async () => {
  const [st, j] = await act("suppress", { action: "now" }, "#suppress-confirm");
  if (st === 200) confirmed("#suppress-confirm", `suppressed by ${META.user}: ${fmt(j.rpm_before, 0)} → ${fmt(j.rpm_after, 0)} r/min`);
});
$("#touchoff").addEventListener("click", async () => {
  const [st] = await act("thermal", { action: "touchoff" }, "#thermal-confirm");
  if (st === 200) confirmed("#thermal-confirm", `touch-off recorded by ${META.user}: growth counts from now`);
});
$("#refit").addEventListener("click", async () => {
  confirmed("#thermal-confirm", "refitting the thermal model…");
  const [st, j] = await act("thermal", { action: "refit" }, "#thermal-confirm");
  if (st === 200) confirmed("#thermal-confirm", "refit: " + refitText(j));
});
$("#inspect").addEventListener("submit", async (e) => {
  e.preventDefault();
  const f = new FormData(e.target), val = (k) => f.get(k) === "" ? null : Number(f.get(k));
  const [st] = await act("inspect", { part: f.get("part"), ra_um: val("ra_um"), diameter_error_um: val("diameter_error_um") }, "#records-confirm");
  if (st === 200) { confirmed("#records-confirm", `inspection of part ${f.get("part")} recorded by ${META.user}`); refreshParts(); }
});
function csv(rows, cols) {
  const cell = (v) => { const s = v === null || v === undefined ? "" : (typeof v === "object" ? JSON.stringify(v) : String(v)); return /[",\n]/.test(s) ? '"' + s.replace(/"/g, '""') + '"' : s; };
  return [cols.join(","), ...rows.map((r) => cols.map((c) => cell(r[c])).join(","))].join("\n");
}
function download(name, text) {
  const a = document.createElement("a");
  a.href = URL.createObjectURL(new Blob([text], { type: "text/csv" })); a.download = name; a.click();
}
$("#export-events").addEventListener("click", () => download("events.csv", csv(shownEvents(), ["id", "t", "source", "kind", "payload"])));
$("#export-parts").addEventListener("click", () => download("parts.csv", csv(S.parts, Object.keys(S.parts[0] || { id: 0 }))));
$("#filter").addEventListener("input", () => { dirty = recordsDirty = true; });
$("#abnormal-only").addEventListener("change", refreshParts);

// -- the loop ---------------------------------------------------------------------------------------
function draw() {
  if (S.connected && Date.now() - S.lastFrame > 4000) setLink(false, "no data from lathed-web for 4 s");
  $("#clock").textContent = new Date().toLocaleTimeString([], { hour12: false });
  if (!dirty) return;
  dirty = false;
  window.__draws = (window.__draws || 0) + 1;
  if (S.status) $("#daemon-name").textContent = `${S.status.daemon.name}: ${S.connected ? S.status.daemon.state : "not reachable, values below are the last seen"}`;
  for (const f of [drawMachines, drawLobes, drawRobot, drawVibration, drawThermal, drawRecords]) {
    try { f(); } catch (e) { console.error(f.name, e); }
  }
}
$("#who").textContent = `${META.user} (${META.role})`;
if (META.role !== "operator") document.querySelectorAll("button.act, .switch button").forEach((b) => { b.disabled = true; b.title = "read-only: a viewer cannot act"; });
connect();
refreshParts(); refreshRecommend();
setInterval(draw, 250);
setInterval(refreshParts, 10000);
setInterval(refreshRecommend, 60000);
