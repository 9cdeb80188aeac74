// mntes-stream quick-look page: draws what the server pushes over /ws (see monitor/server.py).
// Everything arrives already reduced on the server; this file only lays it out with plotly.
// window.mntesMonitor exposes the page's state (updates drawn, render latencies) for tests.
"use strict";

const STATE_COLORS = {
  transition: "#2ca02c", saturated: "#d62728", superconducting: "#1f77b4",
  flagged: "#ff7f0e", silent: "#9e9e9e",
};
const CONFIG = { displaylogo: false, responsive: true };
const M = (window.mntesMonitor = {
  updates: 0,          // updates drawn
  renders: [],         // {t_pub_ns, t_render_ms, latency_ms} per newly drawn power chunk
  last: null,          // the last update message
  layout: null,        // [{board, module, channels}] grid rows
  selection: [],
  chosen: false,       // the selection is the user's (else the server's default, which it may still change)
  errors: [],
  ws: null,
  fresh: { state: "waiting", text: "waiting for data" },  // what the badge says
  freshChanges: [],    // {state, t_ms}: when the badge changed state
  lastUpdateMs: null,  // performance.now() when the last update arrived
  focalMetric: "state",
  focalLayout: "bmc",
  clicks: 0,           // focal-plane cells clicked
});
let lastPubNs = 0;
let gridGeom = null;   // {rows, cols, ids, offsets}

const $ = (id) => document.getElementById(id);
const fmt = (v, d = 2) => (v === null || v === undefined || Number.isNaN(v) ? "–" : Number(v).toFixed(d));

function send(obj) {
  if (M.ws && M.ws.readyState === WebSocket.OPEN) M.ws.send(JSON.stringify(obj));
}

function connect() {
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`);
  M.ws = ws;
  ws.onopen = () => { setConn("connected", "ok"); if (M.chosen) send({ type: "select", channels: M.selection }); };
  ws.onclose = () => { setConn("disconnected", "bad"); setTimeout(connect, 1000); };
  ws.onmessage = (ev) => {
    const msg = JSON.parse(ev.data);
    if (msg.type === "update") {
      M.lastUpdateMs = performance.now();
      draw(msg).catch((e) => { M.errors.push(String(e)); console.error(e); });
    }
    else if (msg.type === "error") { M.errors.push(msg.message); setConn(msg.message, "warn"); }
  };
}

function setConn(text, cls) { const c = $("conn"); c.textContent = text; c.className = "pill " + cls; }

// ---------------------------------------------------------------- channel picking

function idOf(b, m, c) { return `b${b}m${m}c${String(c).padStart(3, "0")}`; }

function fillPicker() {
  const boards = [...new Set(M.layout.map((r) => r.board))];
  const bSel = $("pick-board");
  const keep = bSel.value;
  bSel.innerHTML = boards.map((b) => `<option>${b}</option>`).join("");
  if (keep !== "" && boards.includes(Number(keep))) bSel.value = keep;
  fillModules();
}
function fillModules() {
  const b = Number($("pick-board").value);
  const mods = M.layout.filter((r) => r.board === b).map((r) => r.module);
  const mSel = $("pick-module");
  const keep = mSel.value;
  mSel.innerHTML = mods.map((m) => `<option>${m}</option>`).join("");
  if (keep !== "" && mods.includes(Number(keep))) mSel.value = keep;
  fillChannels();
}
function fillChannels() {
  const b = Number($("pick-board").value), m = Number($("pick-module").value);
  const row = M.layout.find((r) => r.board === b && r.module === m);
  $("pick-channel").innerHTML = (row ? row.channels : []).map((c) => `<option value="${c}">${c}</option>`).join("");
}
function select(ids) {
  M.chosen = true;
  M.selection = [...new Set(ids)];
  renderSelected();
  send({ type: "select", channels: M.selection });
}
function renderSelected() {
  $("selected").innerHTML = M.selection.map((id) => `<span>${id}<b data-id="${id}">×</b></span>`).join("");
}
$("pick-board").onchange = fillModules;
$("pick-module").onchange = fillChannels;
$("add").onclick = () => {
  const b = $("pick-board").value, m = $("pick-module").value;
  const chans = [...$("pick-channel").selectedOptions].map((o) => idOf(b, m, o.value));
  select(M.selection.concat(chans));
};
$("clear").onclick = () => select([]);
$("selected").onclick = (ev) => { const id = ev.target.dataset.id; if (id) select(M.selection.filter((s) => s !== id)); };
$("f-hwp").onchange = () => { $("f-hwp-auto").checked = false; send({ type: "f_hwp", value: $("f-hwp").value }); };
$("f-hwp-auto").onchange = () => send({ type: "f_hwp", value: $("f-hwp-auto").checked ? "auto" : ($("f-hwp").value || "config") });
$("window").onchange = () => send({ type: "window", seconds: Number($("window").value) });
$("focal-metric").onchange = () => { M.focalMetric = $("focal-metric").value; send({ type: "focal", metric: M.focalMetric }); };
$("focal-layout").onchange = () => { M.focalLayout = $("focal-layout").value; if (M.last) grid(M.last); };

// ---------------------------------------------------------------- freshness badge
// The server says how old the newest power is against 3 chunk intervals; the page adds its own check:
// a page that stops getting updates (server gone, stuck, network) must not keep showing the last green.

const ageText = (s) => (s < 60 ? `${s.toFixed(1)} s` : s < 7200 ? `${(s / 60).toFixed(1)} min` : `${(s / 3600).toFixed(1)} h`);
const utc = (ns) => new Date(ns / 1e6).toISOString().replace("T", " ").slice(0, 19) + " UTC";

function setFresh(state, text) {
  if (state !== M.fresh.state) {  // when the badge changed, on this machine's clock (for tests and the curious)
    M.freshChanges.push({ state, t_ms: performance.timeOrigin + performance.now() });
    if (M.freshChanges.length > 100) M.freshChanges.shift();
  }
  M.fresh = { state, text };
  const b = $("fresh");
  if (b.textContent !== text) b.textContent = text;
  const cls = "pill " + ({ live: "ok", replay: "replay", shedding: "warn", lagging: "warn", stale: "bad", waiting: "bad", silent: "bad" }[state] || "bad");
  if (b.className !== cls) b.className = cls;
}

function refreshBadge() {
  const msg = M.last;
  if (!msg || M.lastUpdateMs === null) return;
  const since = (performance.now() - M.lastUpdateMs) / 1000;
  const period = msg.update_s || 0.5;
  if (since > Math.max(3 * period, 2)) {
    setFresh("silent", `NO UPDATE from the monitor for ${ageText(since)}`);
    return;
  }
  const fr = msg.freshness;
  if (fr.state === "waiting") setFresh("waiting", "waiting for data");
  else if (fr.state === "stale") setFresh("stale", `STALE: no data for ${ageText(fr.age_s + since)} (> ${fr.stale_chunks} chunk intervals, ${fmt(fr.threshold_s, 2)} s)`);
  else if (fr.state === "replay") setFresh("replay", `REPLAY · recorded ${utc(fr.newest_t_ns)}`);
  else if (fr.state === "shedding") setFresh("shedding", `SHEDDING · ${fr.shedding.shed.toLocaleString("en")} chunks shed, ${fr.shedding.set_aside.toLocaleString("en")} set aside (${fr.shedding.services.join(", ")})`);
  else if (fr.state === "lagging") setFresh("lagging", `LAGGING · data ${ageText(fr.lag_s)} old on arrival (${fr.behind ? "behind: " + fr.behind : "replay, or a process behind"})`);
  else setFresh("live", `LIVE · ${fmt(fr.age_s, 1)} s`);
}
setInterval(refreshBadge, 200);

// An empty chart says why instead of drawing an axis around 1 January 2000.
function emptyLayout(layout, text) {
  return Object.assign({}, layout, {
    xaxis: { visible: false }, yaxis: { visible: false }, yaxis2: { visible: false }, shapes: [],
    annotations: [{ text, xref: "paper", yref: "paper", x: 0.5, y: 0.5, showarrow: false, font: { size: 15, color: "#777" } }],
  });
}
const hasPoints = (traces) => traces.some((t) => t.x.length > 0);

// ---------------------------------------------------------------- drawing

function timeStreams(msg) {
  const traces = msg.streams.map((s) => ({
    type: "scatter", mode: "lines", name: `${s.id} (${s.state})`, x: s.t_ms, y: s.p_pw,
    line: { width: 1 }, connectgaps: false,
  }));
  const replay = msg.freshness.state === "replay" || msg.freshness.replay;
  const slow = msg.streams.filter((s) => s.resolution !== "full rate").map((s) => s.id);
  const layout = {
    uirevision: "ts", margin: { l: 60, r: 10, t: 10, b: 40 }, legend: { orientation: "h", y: 1.12 },
    xaxis: { type: "date", title: { text: `${replay ? "recording time" : "time"} (UTC), last ${ageText(msg.window_s)}${slow.length ? `; ${slow.join(", ")}: ${msg.streams.find((s) => s.resolution !== "full rate").resolution}` : ""}` } },
    yaxis: { title: { text: "P_opt [pW]" }, exponentformat: "none" },
  };
  if (!hasPoints(traces)) {
    const why = msg.selection.length ? "no data yet for the selected channels" : (M.layout && M.layout.length ? "no channel selected: pick one or click the focal plane" : "waiting for power");
    return Plotly.react("timestreams", [], emptyLayout(layout, why), CONFIG);
  }
  return Plotly.react("timestreams", traces, layout, CONFIG);
}

function spectrum(msg) {
  const sp = msg.spectrum;
  const traces = sp.channels.map((c) => ({
    type: "scatter", mode: "lines", name: c.id, x: c.f_hz, y: c.log10_asd.map((v) => (v === null ? null : 10 ** v)),
    line: { width: 1 },
  }));
  const labels = ["1f", "2f", "4f"];
  const shapes = sp.harmonics_hz.map((f) => ({
    type: "line", xref: "x", yref: "paper", x0: f, x1: f, y0: 0, y1: 1, line: { color: "#c62828", width: 1, dash: "dot" },
  }));
  const annotations = sp.harmonics_hz.map((f, i) => ({
    x: Math.log10(f), xref: "x", y: 1, yref: "paper", text: labels[i], showarrow: false, yanchor: "bottom", font: { color: "#c62828" },
  }));
  const layout = {
    uirevision: "sp", margin: { l: 60, r: 10, t: 20, b: 40 }, showlegend: false, shapes, annotations,
    xaxis: { type: "log", title: { text: "frequency [Hz]" } }, yaxis: { type: "log", title: { text: "ASD [aW/√Hz]" } },
  };
  $("f-hwp-info").textContent = sp.f_hwp_hz === null ? `(${sp.f_hwp_source})` : `(${fmt(sp.f_hwp_hz, 3)} Hz, ${sp.f_hwp_source})`;
  if (!$("f-hwp").value && sp.f_hwp_hz !== null && sp.f_hwp_source === "configured") $("f-hwp").value = sp.f_hwp_hz;
  if (!hasPoints(traces)) return Plotly.react("spectrum", [], emptyLayout(layout, "no spectrum yet"), CONFIG);
  return Plotly.react("spectrum", traces, layout, CONFIG);
}

function buildGridGeometry() {
  const cols = Math.max(1, ...M.layout.map((r) => r.channels.length));
  const ids = [], offsets = [];
  let off = 0;
  for (const r of M.layout) {
    offsets.push(off);
    off += r.channels.length;
    const row = r.channels.map((c) => idOf(r.board, r.module, c));
    while (row.length < cols) row.push(null);
    ids.push(row);
  }
  gridGeom = { rows: M.layout.length, cols, ids, offsets, labels: M.layout.map((r) => `b${r.board}m${r.module}`) };
}

const FOCAL_UNITS = { power_pw: "pW", flag_pct: "% flagged", noise_aw_rthz: "aW/√Hz", linear_nl_per_pw: "pW⁻¹ (linear; bound if unresolved)" };
let gridClickBound = false;

function focalValue(msg, k) {
  // The server sends the figure this page colours by (msg.focal.metric), per channel in layout order.
  const f = msg.focal;
  return f && f.values && f.metric === M.focalMetric ? f.values[k] : null;
}

function grid(msg) {
  const names = msg.state_names, codes = msg.codes, g = gridGeom;
  const metric = M.focalMetric === "state" || !msg.focal || msg.focal.metric !== M.focalMetric ? "state" : M.focalMetric;
  const hasSky = M.layout.some((r) => r.positions && r.positions.some((p) => p));
  const skyOpt = $("focal-layout").querySelector('option[value="sky"]');
  skyOpt.disabled = !hasSky;
  const sky = hasSky && M.focalLayout === "sky";
  const stateOf = (k) => names[codes.charCodeAt(k) - 48];
  const label = (k, id) => {
    const v = focalValue(msg, k);
    return metric === "state" ? `${id}: ${stateOf(k)}` : `${id}: ${stateOf(k)} · ${v === null ? "–" : v} ${FOCAL_UNITS[metric]}`;
  };
  const n = names.length, colorscale = [];
  names.forEach((name, k) => { colorscale.push([k / n, STATE_COLORS[name]], [(k + 1) / n, STATE_COLORS[name]]); });
  let trace, layout;
  if (sky) {
    const x = [], y = [], c = [], text = [], ids = [];
    M.layout.forEach((r, i) => r.channels.forEach((ch, j) => {
      const p = r.positions && r.positions[j];
      if (!p) return;
      const k = g.offsets[i] + j, id = g.ids[i][j];
      x.push(p[0]); y.push(p[1]); ids.push(id); text.push(label(k, id));
      c.push(metric === "state" ? codes.charCodeAt(k) - 48 : focalValue(msg, k));
    }));
    const marker = metric === "state"
      ? { color: c, colorscale, cmin: -0.5, cmax: n - 0.5, size: 9 }
      : { color: c, colorscale: "Viridis", size: 9, showscale: true, colorbar: { title: { text: FOCAL_UNITS[metric] } } };
    trace = { type: "scatter", mode: "markers", x, y, text, customdata: ids, hoverinfo: "text", marker };
    layout = {
      uirevision: "sky", margin: { l: 60, r: 10, t: 10, b: 45 },
      xaxis: { title: { text: "x [deg]" } }, yaxis: { title: { text: "y [deg]" }, scaleanchor: "x" },
    };
  } else {
    const z = [], text = [];
    M.layout.forEach((r, i) => {
      const zr = new Array(g.cols).fill(null), tr = new Array(g.cols).fill("");
      for (let j = 0; j < r.channels.length; j++) {
        const k = g.offsets[i] + j;
        zr[j] = metric === "state" ? codes.charCodeAt(k) - 48 : focalValue(msg, k);
        tr[j] = label(k, g.ids[i][j]);
      }
      z.push(zr); text.push(tr);
    });
    trace = {
      type: "heatmap", z, text, customdata: g.ids, hoverinfo: "text", showscale: metric !== "state",
      y: g.labels, xgap: g.cols > 64 ? 0 : 1, ygap: g.rows > 16 ? 0 : 1,  // gaps would hide a dense grid
    };
    if (metric === "state") Object.assign(trace, { zmin: -0.5, zmax: n - 0.5, colorscale });
    else Object.assign(trace, { colorscale: "Viridis", colorbar: { title: { text: FOCAL_UNITS[metric] } } });
    layout = {
      uirevision: "grid", margin: { l: 60, r: 10, t: 10, b: 45 },
      xaxis: { title: { text: "channel slot" }, showgrid: false }, yaxis: { autorange: "reversed", showgrid: false, type: "category" },
    };
  }
  $("legend").innerHTML = names.map((name) => `<span><i style="background:${STATE_COLORS[name]}"></i>${name} <b>${msg.state_counts[name]}</b></span>`).join("");
  if (!M.layout.length) return Plotly.react("grid", [], emptyLayout(layout, "no channels yet"), CONFIG);
  return Plotly.react("grid", [trace], layout, CONFIG).then((gd) => {
    if (!gridClickBound) {
      gridClickBound = true;
      gd.on("plotly_click", (ev) => {
        const id = ev.points && ev.points[0] && ev.points[0].customdata;
        if (id) { M.clicks += 1; select(M.selection.filter((s) => s !== id).concat([id])); }
      });
    }
  });
}

// The live leakage (monitor/leakage_live.py): per measured detector the linear conversion's effective
// nonlinearity against MNTES with its 1-sigma, or its 3-sigma upper limit, or why there is no number;
// the 0.014 pW^-1 requirement as a line. MNTES's own residual needs the truth: said, never drawn.
let leakDrawn = null;  // the measurement drawn: it changes every leakage_every_s (10 s), not every update

function leakage(msg) {
  const L = msg.leakage || {};
  const key = `${L.t_ns}|${L.why || ""}|${L.shadow || ""}`;
  if (key === leakDrawn) return Promise.resolve();
  leakDrawn = key;
  const rows = L.detectors || [];
  const ok = rows.filter((r) => r.resolved);
  const bound = rows.filter((r) => !r.resolved && r.bound_per_pw !== null && r.bound_per_pw !== undefined);
  const none = rows.filter((r) => r.nl_per_pw === undefined);
  const ids = rows.map((r) => r.id);
  const traces = [
    { type: "scatter", mode: "markers", name: "linear conversion (vs MNTES)", x: ok.map((r) => r.id),
      y: ok.map((r) => Math.abs(r.nl_per_pw)), error_y: { type: "data", array: ok.map((r) => r.sigma_per_pw), visible: true },
      marker: { color: "#d62728", size: 9 } },
    { type: "scatter", mode: "markers", name: "unresolved: 3σ upper limit", x: bound.map((r) => r.id),
      y: bound.map((r) => r.bound_per_pw), marker: { color: "#ff7f0e", symbol: "triangle-down", size: 10 } },
  ];
  const req = L.requirement_per_pw || 0.014;
  const shapes = [{ type: "line", xref: "paper", x0: 0, x1: 1, yref: "y", y0: req, y1: req, line: { color: "#2ca02c", dash: "dash" } }];
  const annotations = [{ xref: "paper", x: 1, y: Math.log10(req), yref: "y", text: `requirement ${req} pW⁻¹`, showarrow: false,
    xanchor: "right", yanchor: "bottom", font: { color: "#2ca02c" } }];
  none.forEach((r) => annotations.push({ x: r.id, xref: "x", y: Math.log10(req), yref: "y", text: r.status.replaceAll("_", " "),
    textangle: -90, showarrow: false, yanchor: "bottom", font: { size: 10, color: "#777" } }));
  const layout = {
    uirevision: "leak", margin: { l: 60, r: 10, t: 20, b: 70 }, legend: { orientation: "h", y: 1.15 }, shapes, annotations,
    xaxis: { type: "category", categoryarray: ids, tickangle: -45 },
    yaxis: { type: "log", title: { text: "|f''/f'| [pW⁻¹]" } },
  };
  const med = L.median || {};
  const medText = med.value_per_pw !== null && med.value_per_pw !== undefined ? `median ${fmt(med.value_per_pw, 3)} ± ${med.sigma_per_pw} pW⁻¹`
    : med.bound_per_pw !== null && med.bound_per_pw !== undefined ? `median < ${med.bound_per_pw} pW⁻¹ (3σ)` : "no detector measured";
  const fitted = Math.max(0, ...rows.map((r) => r.window_s || 0));
  $("leakage-info").textContent = L.t_ns ? `Linear conversion: ${medText}, ${rows.length} detectors, ` +
    `window ${fmt(fitted, 1)} s fitted of ${L.window_s} s ` +
    `(refit every ${L.every_s} s), f_HWP ${L.f_hwp_hz === null ? "–" : fmt(L.f_hwp_hz, 4) + " Hz"} (${L.f_hwp_source}). ` +
    `MNTES residual: ${L.mntes}.${L.shadow ? " Shadow: " + L.shadow + "." : ""}` : `Leakage: ${L.why || "off"}. MNTES residual: ${L.mntes || ""}`;
  if (!rows.length) return Plotly.react("leakage", [], emptyLayout(layout, L.why || "no leakage measured yet"), CONFIG);
  return Plotly.react("leakage", traces, layout, CONFIG);
}

function housekeeping(msg) {
  const tb = msg.hk.t_bath || { t_ms: [], value: [] }, bf = msg.hk.b_field || { t_ms: [], value: [] };
  const traces = [
    { type: "scatter", mode: "lines", name: "T_bath [mK]", x: tb.t_ms, y: tb.value.map((v) => (v === null ? null : v * 1e3)), line: { width: 1 } },
    { type: "scatter", mode: "lines", name: "B [µT]", x: bf.t_ms, y: bf.value.map((v) => (v === null ? null : v * 1e6)), yaxis: "y2", line: { width: 1 } },
  ];
  const layout = {
    uirevision: "hk", margin: { l: 60, r: 10, t: 10, b: 40 }, legend: { orientation: "h", y: 1.12 },
    grid: { rows: 2, columns: 1, subplots: [["xy"], ["xy2"]], roworder: "top to bottom" },
    xaxis: { type: "date" }, yaxis: { title: { text: "T_bath [mK]" }, exponentformat: "none" }, yaxis2: { title: { text: "B [µT]" } },
  };
  if (!hasPoints(traces)) return Plotly.react("hk", [], emptyLayout(layout, "no housekeeping received"), CONFIG);
  return Plotly.react("hk", traces, layout, CONFIG);
}

function health(msg) {
  const h = msg.health, mon = h.monitor, pl = h.page_latency_ms;
  const cell = (v, bad) => `<td class="${bad ? "bad-cell" : ""}">${v}</td>`;
  let rows = "<tr><th>source</th><th>in [chunks/s]</th><th>out [chunks/s]</th><th>out [Msamples/s]</th><th>latency p50 / p99 / max [ms]</th><th>lost chunks</th><th>shed / set aside / late</th><th>pending</th><th>stale hk samples</th><th>bad msgs</th><th>status age [s]</th></tr>";
  let ledgers = "";
  for (const s of h.services) {
    const shed = `${s.chunks_shed} / ${s.chunks_set_aside} / ${s.chunks_late}${s.shedding ? " SHEDDING" : ""}`;
    rows += `<tr><td>${esc(s.service)}</td>${cell(fmt(s.in_chunks_per_s, 1))}${cell(fmt(s.out_chunks_per_s, 1))}${cell(fmt(s.out_msamples_per_s, 3))}` +
      `${cell(`${fmt(s.latency_p50_ms, 1)} / ${fmt(s.latency_p99_ms, 1)} / ${fmt(s.latency_max_ms, 1)}`)}` +
      `${cell(s.chunks_lost, s.chunks_lost > 0)}<td class="${s.shedding ? "warn-cell" : s.chunks_shed > 0 ? "bad-cell" : ""}">${shed}</td>${cell(s.chunks_pending)}${cell(s.hk_stale_samples, s.hk_stale_samples > 0)}` +
      `${cell(s.bad_messages, s.bad_messages > 0)}${cell(fmt(s.age_s, 1), s.stale)}</tr>`;
    if (s.ledger) ledgers += ledgerTable(s.service, s.ledger);
  }
  const bad = Object.values(mon.bad_messages).reduce((a, b) => a + b, 0);
  rows += `<tr><td>monitor (received${msg.freshness.replay ? "; replay: latency on the recording's clock" : ""})</td>${cell(fmt(mon.chunks_per_s, 1))}${cell("")}${cell(fmt(mon.msamples_per_s, 3))}` +
    `${cell(`${fmt(mon.latency_p50_ms, 1)} / – / ${fmt(mon.latency_max_ms, 1)}`)}${cell(mon.lost_chunks, mon.lost_chunks > 0)}` +
    `${cell(`late ${mon.late_power_chunks}`)}${cell(`dropped ${mon.dropped}`, mon.dropped > 0)}${cell("")}${cell(bad, bad > 0)}${cell("")}</tr>`;
  rows += `<tr><td>page (publication → drawn)</td>${cell("")}${cell("")}${cell("")}${cell(`${fmt(pl.p50, 0)} / – / ${fmt(pl.max, 0)}`)}${cell("")}${cell("")}${cell("")}${cell("")}${cell("")}${cell("")}</tr>`;
  let hk = "";
  for (const [name, s] of Object.entries(h.hk)) {
    const v = s.value === null ? "–" : name === "t_bath" ? `${fmt(s.value * 1e3, 4)} mK` : `${fmt(s.value * 1e6, 3)} µT`;
    hk += `<span class="${s.stale ? "bad-cell" : ""}">${name}: ${v} (received ${fmt(s.age_s, 1)} s ago${s.stale ? ", STALE" : ""})</span> &nbsp; `;
  }
  $("health").innerHTML = `<table>${rows}</table><p>${hk} &nbsp; channels: ${mon.channels} in ${mon.modules} modules</p>${ledgers}`;
}

// Names come from the network: never markup.
const esc = (v) => String(v).replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" }[c]));
const LEDGER_COLUMNS = [["converted", "converted"], ["late", "late"], ["shed", "shed"], ["rejected", "rejected"],
  ["duplicate", "duplicate"], ["never_received", "never received"], ["lost", "lost"], ["pending", "pending"]];

// One converter's ledger: its summary line and a row per stream (lossy streams first).
function ledgerTable(service, led) {
  const head = LEDGER_COLUMNS.map(([, name]) => `<th>${name}</th>`).join("");
  const row = (name, r) => `<tr><td>${esc(name)}</td>` + LEDGER_COLUMNS.map(([k]) =>
    `<td class="${(k === "lost" || k === "shed" || k === "rejected") && r[k] > 0 ? "bad-cell" : ""}">${r[k].toLocaleString("en")}</td>`).join("") + "</tr>";
  let body = row("all streams", led.totals);
  for (const r of led.streams) body += row(r.stream, r);
  const more = led.streams_total - led.streams.length;
  return `<h3 class="ledger">ledger of ${esc(service)}: ${esc(led.line)}</h3>` +
    `<table class="ledger"><tr><th>stream</th>${head}</tr>${body}</table>` +
    `${more > 0 ? `<p>+${more} more streams</p>` : ""}` +
    [led.conflict_line, led.began_line].filter((x) => x).map((x) => `<p class="bad-cell">${esc(x)}</p>`).join("") +
    `<p class="note">${esc(led.lost_means)}</p>`;
}

async function draw(msg) {
  if (msg.layout) { M.layout = msg.layout; fillPicker(); buildGridGeometry(); }
  if (!M.layout) return;
  if (JSON.stringify(msg.selection) !== JSON.stringify(M.selection) && msg.unknown.length === 0) {
    M.selection = msg.selection;
    renderSelected();
  }
  M.last = msg;
  refreshBadge();
  health(msg);
  await Promise.all([timeStreams(msg), spectrum(msg), grid(msg), leakage(msg), housekeeping(msg)]);
  // The next frame is when the browser has painted what was just drawn.
  await new Promise((resolve) => requestAnimationFrame(() => setTimeout(resolve, 0)));
  const tRenderMs = performance.timeOrigin + performance.now();
  M.updates += 1;
  $("updated").textContent = `updated ${new Date(tRenderMs).toISOString().slice(11, 19)} UTC`;
  if (msg.freshness.replay) {
    $("latency").textContent = `replay: latency ${fmt(msg.health.monitor.latency_p50_ms, 0)} ms on the recording's clock (samples → publication)`;
  } else if (msg.newest_t_pub_ns > lastPubNs) {
    lastPubNs = msg.newest_t_pub_ns;
    const latency = tRenderMs - msg.newest_t_pub_ns / 1e6;
    M.renders.push({ t_pub_ns: msg.newest_t_pub_ns, t_render_ms: tRenderMs, latency_ms: latency });
    if (M.renders.length > 1000) M.renders.shift();
    $("latency").textContent = `publication → drawn ${fmt(latency, 0)} ms`;
    send({ type: "rendered", newest_t_pub_ns: msg.newest_t_pub_ns, t_render_ns: Math.round(tRenderMs * 1e6) });
  }
}

connect();
