// i4cal dashboard: plain JavaScript against /api/v1 (no build step).
"use strict";
const API = "/api/v1";
const $ = (sel) => document.querySelector(sel);
const COMBOS = ["L", "H-D", "S-q02/2", "S-(q04-q03)/2"];
const SEVEN = ["H", "q02", "q03", "q04", "S", "D", "L"];
const ACTIVE = ["queued", "acquiring", "extracting", "calibrating"];
let selected = null;
let source = null;
let frameTimer = null;
let METHODS = [];  // GET /api/v1/methods: [{name, label, colour, description, required_phases, ...}]

// The API's times are UTC (ISO 8601 with Z); one without a zone is UTC too (never the browser's local time).
// Shown in the browser's time zone, named: "23/11/2026, 16:20:41 CET".
function fmtTime(iso) {
  if (!iso) return "";
  const s = /(Z|[+-]\d\d:?\d\d)$/.test(iso) ? iso : iso + "Z";
  const d = new Date(s);
  return esc(isNaN(d) ? String(iso) : d.toLocaleString(undefined, { timeZoneName: "short" }));
}

const tokenInput = $("#token");
tokenInput.value = localStorage.getItem("i4cal-token") || "";
tokenInput.addEventListener("change", () => {
  localStorage.setItem("i4cal-token", tokenInput.value.trim());
  // a new token: what was refused without it is asked again, and the old refusal no longer shown
  say("");
  refreshRuns();
  refreshDevices();
  refreshCurrent();
  if (selected) select(selected);
});

function headers(json) {
  const h = {};
  const t = tokenInput.value.trim();
  if (t) h["Authorization"] = "Bearer " + t;
  if (json) h["Content-Type"] = "application/json";
  return h;
}

async function api(method, path, body) {
  const r = await fetch(API + path, { method, headers: headers(body !== undefined),
    body: body === undefined ? undefined : JSON.stringify(body) });
  let data = null;
  try { data = await r.json(); } catch (e) { /* not JSON */ }
  if (!r.ok) {
    let msg = data && data.detail ? data.detail : r.statusText;
    if (Array.isArray(msg)) msg = msg.map((d) => (d.loc || []).join(".") + ": " + d.msg).join("; ");
    throw new Error(r.status + " " + msg);
  }
  return data;
}

// A GET with the token (reads may be closed: open_reads false); the response as it is.
function authGet(path) {
  return fetch(path, { headers: headers(false), cache: "no-store" });
}

// why a response failed, in words (its JSON detail when there is one)
async function failure(r) {
  let detail = r.statusText;
  try { const d = await r.json(); if (d && d.detail) detail = typeof d.detail === "string" ? d.detail : JSON.stringify(d.detail); } catch (e) { /* not JSON */ }
  return r.status === 401 ? `${r.status} ${detail}: give the bearer token (top right)` : `${r.status} ${detail}`;
}

// A download (dataset zip, report) fetched with the token and saved from a blob URL (a plain link cannot send it).
async function download(path, filename) {
  say(`downloading ${filename}…`);
  let r;
  try { r = await authGet(path); } catch (e) { say(`${filename}: ${e.message}`, true); return; }
  if (!r.ok) { say(`${filename}: ${await failure(r)}`, true); return; }
  const url = URL.createObjectURL(await r.blob());
  const a = Object.assign(document.createElement("a"), { href: url, download: filename });
  document.body.appendChild(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 60_000);
  say(`downloaded ${filename}`);
}

// Server-Sent Events read over fetch (EventSource cannot send the token): past events, then live ones; reconnects
// after the last event seen while the run is active; a failure is said in the live panel.
class RunEvents {
  constructor(id, onEvent) {
    this.id = id; this.onEvent = onEvent; this.last = 0; this.ctrl = null; this.closed = false;
    this.loop();
  }
  close() { this.closed = true; if (this.ctrl) this.ctrl.abort(); }
  async loop() {
    while (!this.closed) {
      this.ctrl = new AbortController();
      let r;
      try {
        r = await fetch(`${API}/runs/${this.id}/events?after=${this.last}`, { headers: headers(false), signal: this.ctrl.signal });
      } catch (e) { if (this.closed) return; liveError(`live view: ${e.message}; retrying`); await sleep(2000); continue; }
      if (!r.ok) { liveError(`live view: ${await failure(r)}`); return; }
      liveError("");
      try { await this.read(r.body.getReader()); } catch (e) { if (this.closed) return; }
      if (this.closed || !ACTIVE.includes($("#live-panel").dataset.state)) return;
      await sleep(1000);
    }
  }
  async read(reader) {
    const dec = new TextDecoder();
    let buf = "";
    for (;;) {
      const { value, done } = await reader.read();
      if (done) return;
      buf += dec.decode(value, { stream: true });
      let cut;
      while ((cut = buf.indexOf("\n\n")) >= 0) {
        const block = buf.slice(0, cut);
        buf = buf.slice(cut + 2);
        const data = block.split("\n").filter((l) => l.startsWith("data: ")).map((l) => l.slice(6)).join("\n");
        if (!data) continue;
        const ev = JSON.parse(data);
        this.last = Math.max(this.last, ev.seq || 0);
        if (!this.closed) this.onEvent(this.id, ev);
      }
    }
  }
}
const sleep = (ms) => new Promise((res) => setTimeout(res, ms));
function liveError(text) { $("#live-error").textContent = text; }

function say(text, isError) {
  const m = $("#message");
  m.textContent = text;
  m.className = isError ? "error" : "";
}

// a duration in seconds, in the unit that reads best: "3.2 s", "74 s", "2.5 min"
const fmtDuration = (s) => (s === null || s === undefined ? "–" : s < 10 ? `${s.toFixed(1)} s` : s < 120 ? `${s.toFixed(0)} s` : `${(s / 60).toFixed(1)} min`);
const mm = (v) => (v === null || v === undefined ? "–" : (v * 1e3).toFixed(3));
const pm = (v, s) => mm(v) + (s === null || s === undefined ? "" : " ± " + mm(s));
const esc = (s) => String(s ?? "").replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" }[c]));

// -- methods (the registry, GET /api/v1/methods) ----------------------------------------------
const methodLabel = (name) => (METHODS.find((m) => m.name === name) || {}).label || name;
const methodColour = (name) => (METHODS.find((m) => m.name === name) || {}).colour;

async function loadMethods() {
  try { METHODS = await api("GET", "/methods"); } catch (e) { say("methods: " + e.message, true); return; }
  const fs = $("#methods");
  fs.querySelectorAll("label").forEach((l) => l.remove());
  for (const m of METHODS) {
    const l = document.createElement("label");
    l.title = m.description + " (needs phases: " + m.required_phases.join(", ") + ")";
    l.innerHTML = `<input type="checkbox" value="${esc(m.name)}" checked> ${esc(m.label)}`;
    fs.appendChild(l);
  }
  fs.dataset.loaded = "true";
}
let methodsLoaded = loadMethods();
tokenInput.addEventListener("change", () => { if (!METHODS.length) methodsLoaded = loadMethods(); });

// -- runs list ---------------------------------------------------------------------------------
async function refreshRuns() {
  let runs;
  try { runs = await api("GET", "/runs?limit=50"); } catch (e) { say(e.message, true); return; }
  const tb = $("#runs tbody");
  tb.innerHTML = "";
  for (const r of runs) {
    const tr = document.createElement("tr");
    tr.dataset.id = r.id;
    tr.dataset.state = r.state;
    if (r.id === selected) tr.className = "selected";
    const [label, cls] = stateBadge(r);
    tr.innerHTML = `<td><code>${r.id.slice(0, 8)}</code></td><td><span class="state ${cls}">${esc(label)}</span></td>` +
      `<td>${esc(r.bench)}</td><td>${esc(r.plan || (r.dataset ? "dataset " + r.dataset.slice(0, 8) : ""))}</td>` +
      `<td>${r.progress.done}/${r.progress.total}</td><td>${fmtTime(r.created_at)}</td><td>${esc(r.note)}</td>` +
      `<td>${r.has_result ? `<a class="report" href="${API}/runs/${r.id}/report">report</a>` : ""}</td>`;
    tr.addEventListener("click", () => select(r.id));
    const rep = tr.querySelector("a.report");
    if (rep) rep.addEventListener("click", (ev) => { ev.preventDefault(); ev.stopPropagation(); download(rep.getAttribute("href"), `i4cal-report-${r.id.slice(0, 8)}.html`); });
    tb.appendChild(tr);
  }
  if (!selected && runs.length) select(runs[0].id);
}

// A run's state as shown: "done" only when a fit gave a result to load; a run whose every fit failed is
// "done · no fit converged" (red), the reason shown once in its results.
function stateBadge(run) {
  const v = run.verdict;
  if (run.state === "done" && v && !v.method) {
    const failed = Object.keys(v.failed || {});
    return [failed.length ? "done · no fit converged" : "done · nothing to load", "done-nofit"];
  }
  if (run.state === "done" && !run.has_result && run.methods && run.methods.length) return ["done · no result", "done-nofit"];
  return [run.state + (run.progress && run.progress.paused ? " (paused)" : ""), run.state];
}

// the devices' states; before the first run the service has not contacted them: said so, not "unknown"
const DEVICE_STATE = { unknown: "not contacted yet" };
async function refreshDevices() {
  try {
    const d = await api("GET", "/devices");
    $("#bench").textContent = d.bench ? `bench: ${d.bench}${d.simulated ? " (simulated)" : ""}` : "no bench";
    $("#devices").innerHTML = d.devices.map((x) =>
      `<span class="dev ${x.state}" title="${esc(x.last_error || x.uri)}${x.state === "unknown" ? " (the service connects at the first run)" : ""}">${esc(x.name)}: ${esc(DEVICE_STATE[x.state] || x.state)}</span>`).join("");
  } catch (e) { /* reads may be closed */ }
}

async function refreshCurrent() {
  try {
    const c = await api("GET", "/calibration/current");
    $("#current").innerHTML = `<p>bench <b>${esc(c.bench)}</b>: ${esc(c.method)} from run <code>${c.run_id.slice(0, 8)}</code>, applied ` +
      `${fmtTime(c.applied_at)} (i4cal ${esc(c.software_version)})</p><table><caption>the four combinations (mm, ± 1 std)</caption><tr>` +
      COMBOS.map((k) => `<th>${k}</th>`).join("") + "</tr><tr>" +
      COMBOS.map((k) => `<td>${pm(c.combinations[k], c.combinations_std && c.combinations_std[k])}</td>`).join("") +
      "</tr></table>";
    $("#current").className = "";
  } catch (e) { /* none yet */ }
}

// -- one run -----------------------------------------------------------------------------------
async function select(id) {
  selected = id;
  document.querySelectorAll("#runs tbody tr").forEach((tr) => tr.classList.toggle("selected", tr.dataset.id === id));
  $("#live-panel").hidden = false;
  $("#run-id").textContent = id.slice(0, 8);
  $("#log").innerHTML = "";
  $("#download").href = `${API}/runs/${id}/dataset`;
  $("#results-panel").hidden = true;
  if (source) source.close();
  source = null;
  resetFrame();
  liveError("");
  let run;
  try { run = await api("GET", "/runs/" + id); } catch (e) { if (id === selected) liveError(`run ${id.slice(0, 8)}: ${e.message}`); return; }
  if (id !== selected) return;  // another run was selected while this one's answer came: it is not shown over it
  showRun(run);
  $("#detail").textContent = "";
  source = new RunEvents(id, onEvent);
  if (run.has_result) showResult(id);
}

function showRun(run) {
  const st = $("#run-state");
  const [label, cls] = stateBadge(run);
  st.textContent = label;
  st.className = "state " + cls;
  $("#live-panel").dataset.state = run.state;
  // the controls act on an active run only: pause while it runs, resume while paused, abort until it ends
  const active = ACTIVE.includes(run.state);
  $("#pause").disabled = !active || run.progress.paused;
  $("#resume").disabled = !(active && run.progress.paused) && run.state !== "interrupted";
  $("#abort").disabled = !active && run.state !== "interrupted";
  $("#timings").textContent = runTimes(run);
  setProgress(run.progress.done, run.progress.total);
  $("#phase").textContent = run.progress.phase || "";
  $("#pose").textContent = run.progress.pose ? run.progress.pose.map((v) => (v * 1e3).toFixed(1)).join(", ") + " mm" : "";
  $("#run-error").textContent = run.error || "";
  if (run.progress.total || run.progress.done) loadFrame(run.id);
}

// the run's own times: each stage as measured, beside the plan's predicted motion time
function runTimes(run) {
  const t = run.timings || {};
  const parts = [["acquisition", t.acquisition_s], ["extraction", t.extraction_s], ["calibration", t.calibration_s], ["total", t.total_s]]
    .filter(([, v]) => v !== undefined && v !== null).map(([k, v]) => `${k} ${fmtDuration(v)}`);
  const pred = run.prediction && run.prediction.motion_time_s;
  if (pred !== null && pred !== undefined) parts.push(`predicted motion ${fmtDuration(pred)} (motion only: no camera frames or settling)`);
  return parts.join(" · ");
}

function setProgress(done, total) {
  $("#progress").max = Math.max(total, 1);
  $("#progress").value = done;
  $("#progress-text").textContent = `${done}/${total}`;
}

// the frame is fetched with the token and shown from a blob URL; hidden until one arrives (no broken image)
let frameURL = null;
function resetFrame() {
  const img = $("#frame");
  img.hidden = true;
  img.removeAttribute("src");
  if (frameURL) URL.revokeObjectURL(frameURL);
  frameURL = null;
  $("#frame-caption").textContent = "no frame yet";
  $("#frame-caption").className = "muted";
}

function loadFrame(id) {
  if (frameTimer) return;
  frameTimer = setTimeout(async () => {
    frameTimer = null;
    const extracting = $("#live-panel").dataset.state === "extracting";
    let r;
    try { r = await authGet(`${API}/runs/${id}/frames/latest?max_width=800`); } catch (e) { return; }
    if (id !== selected) return;
    const cap = $("#frame-caption");
    if (r.status === 404) { if (!frameURL) { cap.textContent = "no frame yet"; cap.className = "muted"; } return; }
    if (!r.ok) { cap.textContent = `frame: ${await failure(r)}`; cap.className = "error"; return; }
    const url = URL.createObjectURL(await r.blob());
    const img = $("#frame");
    img.onload = () => { if (frameURL && frameURL !== url) URL.revokeObjectURL(frameURL); frameURL = url; img.hidden = false; };
    img.src = url;
    cap.textContent = extracting ? "last frame extracted, with what was found in it" : "last frame";
    cap.className = "";
  }, 250);
}

// a log line at the event's own time (the service's clock, shown in the browser's time zone)
function log(text, t) {
  const li = document.createElement("li");
  const at = t ? new Date(/(Z|[+-]\d\d:?\d\d)$/.test(t) ? t : t + "Z") : new Date();
  li.textContent = (isNaN(at) ? String(t) : at.toLocaleTimeString()) + " " + text;
  if (t) li.dataset.t = t;
  const ol = $("#log");
  ol.appendChild(li);
  while (ol.children.length > 200) ol.removeChild(ol.firstChild);
  ol.scrollTop = ol.scrollHeight;
}

function onEvent(id, ev) {
  if (id !== selected) return;
  const d = ev.data;
  const L = (text) => log(text, ev.t);
  if (ev.type === "state") {
    L("state: " + d.state + (d.error ? " — " + d.error : ""));
    api("GET", "/runs/" + id).then((run) => { if (id === selected) showRun(run); });
    if (d.state === "done") showResult(id);
    refreshRuns();
  } else if (ev.type === "progress") {
    setProgress(d.done, d.total);
    $("#phase").textContent = (d.stage === "acquisition" ? d.phase || d.state : d.stage) || "";
    if (d.pose) $("#pose").textContent = d.pose.map((v) => (v * 1e3).toFixed(1)).join(", ") + " mm";
    if (d.stage === "acquisition") {
      if (d.message) L(d.message);
      loadFrame(id);
    }
  } else if (ev.type === "extraction") {
    L("extraction: " + Object.entries(d.phases || {}).map(([p, c]) => `${p} board ${c.board}/${c.frames} rods ${c.rods_total || !c.rods_not_read ? `${c.rods}/${c.rods_total}` : "not read"}`).join("; "));
    loadFrame(id);
  } else if (ev.type === "frames") {
    // per-frame extraction results, batched (at most a few events per second)
    const f = d.items[d.items.length - 1];
    const board = f.board ? `board ${f.corners} corners, ${Number(f.rms_px).toFixed(2)} px` : "no board";
    const rods = f.rods === null ? "" : ` · rods ${f.rods}/${f.rods_total}`;
    const miss = Object.keys(f.missing || {}).length;
    $("#detail").textContent = `frame ${f.frame} (${f.phase}, ${f.stage}): ${board}${rods}` + (miss ? ` · ${miss} missing` : "");
    for (const g of d.items) {
      if (g.stage === "rods" && Object.keys(g.missing || {}).length) {
        L(`frame ${g.frame}: ` + Object.entries(g.missing).map(([k, v]) => `${k}: ${v}`).join("; "));
      }
    }
    loadFrame(id);
  } else if (ev.type === "iterations") {
    const it = d.items[d.items.length - 1];
    $("#detail").textContent = `fit ${it.method} · ${it.stage} · iteration ${it.iteration} · cost ${Number(it.cost).toExponential(3)}`;
  } else if (ev.type === "fit") {
    L(`fit ${d.method}: ${d.state}` + (d.iterations ? ` (${d.iterations} evaluations)` : "") + (d.error ? ` — ${d.error}` : ""));
  } else {
    L(ev.type);
  }
}

async function showResult(id) {
  let res;
  try { res = await api("GET", `/runs/${id}/result`); } catch (e) { return; }
  if (id !== selected) return;
  showVerdict(id);
  const methods = Object.keys(res.methods);
  const nom = res.nominal_combinations || {};
  let h = "<tr><th></th><th>a priori</th>" + methods.map((m) => `<th>${esc(methodLabel(m))}</th>`).join("") + "</tr>";
  for (const k of COMBOS) {
    h += `<tr><th>${k}</th><td>${mm(nom[k])}</td>` + methods.map((m) => {
      const e = res.methods[m];
      return e.parameters ? `<td>${pm(e.parameters[k], e.std && e.std[k])}</td>` : '<td class="error">fit failed</td>';
    }).join("") + "</tr>";
  }
  // a failed fit's reason, once (not in every cell)
  $("#fit-errors").replaceChildren(...methods.filter((m) => !res.methods[m].parameters).map((m) =>
    Object.assign(document.createElement("li"), { textContent: `${methodLabel(m)}: fit failed: ${res.methods[m].error || res.methods[m].message || "no parameters"}` })));
  h += "<tr><th>residual RMS</th><td></td>" + methods.map((m) => {
    const e = res.methods[m];
    return `<td>${e.residual_rms != null ? e.residual_rms.toExponential(3) + " " + esc(e.residual_unit || "") : "–"}</td>`;
  }).join("") + "</tr>";
  $("#table1").innerHTML = h;
  const sevenMethods = methods.filter((m) => res.methods[m].seven);
  let h2 = "<tr><th></th><th>a priori</th>" + sevenMethods.map((m) => `<th>${esc(methodLabel(m))}</th>`).join("") + "</tr>";
  for (const k of SEVEN) {
    h2 += `<tr><th>${k}</th><td>${mm(res.nominal[k])}</td>` + sevenMethods.map((m) =>
      `<td>${pm(res.methods[m].seven[k], res.methods[m].seven_std && res.methods[m].seven_std[k])}</td>`).join("") + "</tr>";
  }
  $("#table2").innerHTML = sevenMethods.length ? h2 : "<tr><td class=muted>no method of this run identified the seven parameters (legs does)</td></tr>";
  const cols = ["a priori", ...methods];
  const val = res.validation || {};
  const f = (x, key) => (x && x[key] != null ? Number(x[key]).toFixed(3) : "–");
  let h3 = "<tr><th></th>" + cols.map((c) => `<th>${esc(methodLabel(c))}</th>`).join("") + "</tr>";
  for (const [label, part, key] of [["gaps (fit poses) RMS", "gaps_poses", "rms_mm"],
    ["gaps (validation) RMS", "gaps_validation", "rms_mm"], ["gaps (validation) max", "gaps_validation", "max_abs_mm"],
    ["straightness RMS", "straightness", "rms_mm"]]) {
    h3 += `<tr><th>${label}</th>` + cols.map((c) => `<td>${f((val[c] || {})[part], key)}</td>`).join("") + "</tr>";
  }
  $("#table3").innerHTML = h3;
  $("#plot").innerHTML = residualPlot(cols.map((c) => [c, ((val[c] || {}).gaps_validation || {}).gaps_mm || []]));
  const sel = $("#apply-method");
  sel.innerHTML = methods.filter((m) => res.methods[m].converged)
    .map((m) => `<option value="${esc(m)}">${esc(methodLabel(m))}</option>`).join("");
  $("#apply").disabled = !sel.options.length;  // nothing converged: nothing to apply
  $("#results-panel").hidden = false;
  $("#results-panel").dataset.run = id;
  showPredicted(id, res);
}

// which method's result to load and why, and the next command (the service's calib.identify.verdict, as the CLI says it)
async function showVerdict(id) {
  const box = $("#verdict");
  if (box.dataset.run !== id) { box.hidden = true; box.replaceChildren(); }  // never another run's verdict meanwhile
  let run;
  try { run = await api("GET", "/runs/" + id); } catch (e) { return; }
  if (id !== selected) return;
  box.dataset.run = id;
  const v = run.verdict;
  if (!v) { box.hidden = true; return; }
  box.hidden = false;
  box.className = v.method ? "verdict ok" : "verdict none";
  box.replaceChildren(...v.lines.map((l, i) => {
    const p = document.createElement("p");
    if (i === 0) p.textContent = l; else p.append("next: ", Object.assign(document.createElement("code"), { textContent: l.replace(/^next: /, "") }));
    return p;
  }));
  if (v.method) $("#apply-method").value = v.method;
}

function residualPlot(series) {
  const W = 640, H = 240, pad = 52, bottom = 30;
  const all = series.flatMap(([, g]) => g).filter((v) => v != null);
  if (!all.length) return "<p class=muted>no validation gaps</p>";
  const n = Math.max(...series.map(([, g]) => g.length));
  const ymax = Math.max(...all.map(Math.abs), 1e-6);
  const colors = ["#888", "#1f77b4", "#d62728", "#2ca02c", "#9467bd"];
  const x = (i) => pad + (i + 0.5) * (W - 2 * pad) / Math.max(n, 1);
  const mid = (H - bottom) / 2;
  const y = (v) => mid - v / ymax * (mid - 14);
  let s = `<svg width="${W}" height="${H}" viewBox="0 0 ${W} ${H}" role="img" aria-label="residual plot">` +
    `<line x1="${pad}" x2="${W - pad}" y1="${mid}" y2="${mid}" stroke="#999"/>` +
    `<line x1="${pad}" x2="${pad}" y1="4" y2="${H - bottom}" stroke="#999"/>` +
    `<text x="${pad - 4}" y="18" font-size="11" text-anchor="end">+${ymax.toFixed(2)}</text>` +
    `<text x="${pad - 4}" y="${mid + 4}" font-size="11" text-anchor="end">0</text>` +
    `<text x="${pad - 4}" y="${H - bottom}" font-size="11" text-anchor="end">-${ymax.toFixed(2)}</text>` +
    `<text class="axis-label" transform="translate(12 ${mid}) rotate(-90)" font-size="11" text-anchor="middle">gap, vision − model (mm)</text>` +
    `<text class="axis-label" x="${W / 2}" y="${H - 6}" font-size="11" text-anchor="middle">validation pose pair (index)</text>`;
  series.forEach(([name, g], k) => {
    const c = methodColour(name) || colors[k % colors.length];
    g.forEach((v, i) => { if (v != null) s += `<circle cx="${x(i) + (k - 1) * 3}" cy="${y(v)}" r="3" fill="${c}"><title>${name} #${i}: ${v.toFixed(3)} mm</title></circle>`; });
    s += `<text x="${W - pad - 110}" y="${14 + 13 * k}" font-size="11" fill="${c}">● ${name}</text>`;
  });
  return s + "</svg>";
}

// -- actions -----------------------------------------------------------------------------------
$("#start-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  await methodsLoaded;
  const methods = [...document.querySelectorAll("#methods input:checked")].map((i) => i.value);
  try {
    const run = await api("POST", "/runs", { plan: $("#plan").value, methods, note: $("#note").value });
    say(`run ${run.id.slice(0, 8)} started`);
    selected = run.id;
    await refreshRuns();
    select(run.id);
  } catch (e) { say(e.message, true); }
});

$("#download").addEventListener("click", (ev) => {
  ev.preventDefault();
  if (selected) download(`${API}/runs/${selected}/dataset`, `i4cal-${selected.slice(0, 8)}-dataset.zip`);
});

for (const action of ["pause", "resume", "abort"]) {
  $("#" + action).addEventListener("click", async () => {
    const id = selected;
    if (!id) return;
    try {
      const run = await api("POST", `/runs/${id}/${action}`);
      if (id === selected) showRun(run);
      say(`${action} accepted (run ${id.slice(0, 8)})`);
    } catch (e) { say(e.message, true); }
  });
}

$("#apply").addEventListener("click", async () => {
  const run = $("#results-panel").dataset.run;
  try {
    const c = await api("POST", `/runs/${run}/apply`, { method: $("#apply-method").value });
    say(`applied ${c.method} of run ${c.run_id.slice(0, 8)}`);
    refreshCurrent();
  } catch (e) { say(e.message, true); }
});

// -- experiment design (POST /api/v1/plans/design): the prediction before a run, predicted vs obtained after ----
let designed = null;  // the last design: {plan, predicted_std_m, ...}

// the sources of a prediction's error (predicted_parts_std_m), named by the phase or calibration they come from
const PART_LABELS = {
  board_poses_and_encoders: "fit poses: board poses, encoders",
  joint_centres: "lock phases: joint centres",
  joint_depth_systematic: "lock phases: shading (systematic)",
  leg_directions: "fit poses: leg directions",
  intrinsics: "camera intrinsics",
  limb_edge_bias: "limb-edge bias",
  a_priori: "a priori tolerance",
};

function designRows(pred, obtained, parts) {
  let h = "<tr><th>method</th>" + COMBOS.map((k) => `<th>${k}</th>`).join("") + "</tr>";
  for (const m of Object.keys(pred)) {
    h += `<tr><th>${esc(methodLabel(m))}</th>` + COMBOS.map((k) => {
      const p = pred[m][k];
      const o = obtained && obtained[m] && obtained[m].std ? obtained[m].std[k] : undefined;
      if (obtained === undefined) return `<td>${mm(p)}</td>`;
      const ratio = o && p ? ` (${(o / p).toFixed(2)}×)` : "";
      return `<td>${mm(p)} / ${mm(o)}${ratio}</td>`;
    }).join("") + "</tr>";
    for (const [part, std] of Object.entries((parts && parts[m]) || {})) {
      if (!COMBOS.some((k) => std[k] > 1e-9)) continue;  // parts that contribute at least a nanometre
      h += `<tr class="part"><td>of which ${esc(PART_LABELS[part] || part)}</td>` +
        COMBOS.map((k) => `<td>${mm(std[k])}</td>`).join("") + "</tr>";
    }
  }
  return h;
}

// the design form's fields as a request body (POST /plans/design and /plans/tradeoff); fit poses only for a design
function designBody(withCount) {
  const body = {};
  const t = parseFloat($("#design-target").value);
  if (t > 0) body.target_std_m = t * 1e-3;
  const minutes = parseFloat($("#design-minutes").value);
  if (minutes > 0) body.max_minutes = minutes;
  const n = parseInt($("#design-nfit").value, 10);
  if (withCount && n > 0) body.n_fit = n;
  const lockFrames = parseInt($("#design-lock").value, 10);
  if (lockFrames > 0) body.lock_frames = lockFrames;
  if ($("#design-criterion").value) body.criterion = $("#design-criterion").value;
  if ($("#design-legs").checked) body.methods = ["combined", "legs"];
  return body;
}

$("#design-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  const body = designBody(true);
  $("#design-summary").textContent = "designing…";
  $("#design-notes").replaceChildren();
  $("#design-start").disabled = true;
  try {
    designed = await api("POST", "/plans/design", body);
  } catch (e) { $("#design-summary").textContent = ""; say("design: " + e.message, true); return; }
  const d = designed;
  $("#design-summary").textContent = `${d.n_fit} fit poses · ` +
    Object.entries(d.counts).map(([k, v]) => `${k} ${v}`).join(", ") +
    ` · motion ${fmtDuration(d.motion_time_s)}` +
    (d.target_met === null ? "" : d.target_met ? " · target met" : " · target NOT met") +
    (d.time_met === null ? "" : d.time_met ? " · time met" : " · time NOT met") +
    ` · designed for ${d.plan.design.request.methods.join(" and ")}`;
  // what the design found: why a target is missed, how far more poses go, what the prediction leans on
  $("#design-notes").replaceChildren(...d.notes.map((n) => Object.assign(document.createElement("li"), { textContent: n })));
  $("#design-table").innerHTML = designRows(d.predicted_std_m, undefined, d.predicted_parts_std_m);
  $("#design-start").disabled = false;
});

// accuracy against bench time (POST /api/v1/plans/tradeoff): a designed plan per count; "use" sets the fit poses
$("#tradeoff").addEventListener("click", async () => {
  const counts = $("#tradeoff-counts").value.split(",").map((c) => parseInt(c, 10)).filter((c) => c > 0);
  if (!counts.length) { say("compare: give fit-pose counts, e.g. 8,12,20,30", true); return; }
  $("#tradeoff-summary").textContent = `designing ${counts.length} plans…`;
  let d;
  try {
    d = await api("POST", "/plans/tradeoff", { ...designBody(false), counts });
  } catch (e) { $("#tradeoff-summary").textContent = ""; say("compare: " + e.message, true); return; }
  const withTarget = d.rows.some((r) => r.worst_ratio_to_target !== null);
  let h = "<tr><th>fit poses</th><th>motion (min)</th>" + COMBOS.map((k) => `<th>combined ${k}</th>`).join("") +
    (withTarget ? "<th>worst / target</th>" : "") + "<th></th></tr>";
  for (const r of d.rows) {
    const std = r.predicted_std_m.combined || {};
    const best = r.n_fit === d.recommended_n_fit;
    h += `<tr${best ? ' class="recommended"' : ""}><td>${r.n_fit}${best ? " (recommended)" : ""}</td>` +
      `<td>${(r.motion_s / 60).toFixed(2)}${r.time_met === false ? " (over)" : ""}</td>` +
      COMBOS.map((k) => `<td>${mm(std[k])}</td>`).join("") +
      (withTarget ? `<td>${r.worst_ratio_to_target.toFixed(2)}×</td>` : "") +
      `<td><button type="button" class="use-count" data-n="${r.n_fit}">use</button></td></tr>`;
  }
  $("#tradeoff-table").innerHTML = h;
  $("#tradeoff-summary").textContent = d.recommended_n_fit !== null
    ? `recommended: ${d.recommended_n_fit} fit poses (${d.recommendation})`
    : (withTarget || d.rows.some((r) => r.time_met !== null) ? `no count listed qualifies (${d.recommendation})`
      : "predicted std (mm) of the combined method per count; give a target or minutes to get a recommendation");
  const tr = d.count_trend;  // past the largest count: where more poses level off, when the target is reached
  if (tr && tr.floor_std_m.combined) {
    $("#tradeoff-summary").textContent += ` · with more fit poses (trend from ${tr.n_fit[0]} to ${tr.n_fit[1]}): ` +
      "combined levels off near " + COMBOS.map((k) => `${k} ${mm(tr.floor_std_m.combined[k])}`).join(", ") + " mm" +
      (withTarget ? (tr.n_fit_needed ? `, the target in about ${tr.n_fit_needed}` : ", the target in none") : "");
  }
  document.querySelectorAll("#tradeoff-table .use-count").forEach((b) => b.addEventListener("click", () => {
    $("#design-nfit").value = b.dataset.n;
    say(`fit poses set to ${b.dataset.n}: Design to see its plan`);
  }));
});

$("#design-start").addEventListener("click", async () => {
  if (!designed) return;
  const methods = [...document.querySelectorAll("#methods input:checked")].map((i) => i.value);
  try {
    const run = await api("POST", "/runs", { plan: designed.plan, methods, note: "designed plan" });
    say(`started designed run ${run.id.slice(0, 8)}`);
    await refreshRuns();
    select(run.id);
  } catch (e) { say(e.message, true); }
});

// predicted before the run (stored with the run by the service: GET /runs/{id}'s prediction) vs obtained
async function showPredicted(id, res) {
  let run = null;
  try { run = await api("GET", "/runs/" + id); } catch (e) { run = null; }
  if (id !== selected) return;
  const pred = run && run.prediction && Object.keys(run.prediction.predicted_std_m || {}).length
    ? run.prediction.predicted_std_m : null;
  $("#design-compare").hidden = !pred;
  if (!pred) return;
  $("#design-compare-table").innerHTML = designRows(pred, res.methods) +
    `<tr><td colspan="${COMBOS.length + 1}" class="muted">predicted / obtained (reported std; obtained ÷ predicted)</td></tr>`;
}

// what the chosen plan will buy before it runs (POST /api/v1/plans/predict); the latest request wins
let predicting = 0;
async function predictChosenPlan() {
  const ticket = ++predicting;
  const plan = $("#plan").value;
  $("#plan-prediction").textContent = `predicting ${plan}…`;
  let d;
  try {
    d = await api("POST", "/plans/predict", { plan });
  } catch (e) {
    if (ticket === predicting) { $("#plan-prediction").textContent = ""; $("#plan-prediction-table").innerHTML = ""; }
    return;
  }
  if (ticket !== predicting) return;
  const why = Object.entries(d.prediction_errors).map(([m, w]) => `${methodLabel(m)}: ${w}`);
  $("#plan-prediction").textContent = `${d.plan}: predicted std (mm) · motion ${fmtDuration(d.motion_time_s)} (motion only)` +
    (d.unseen.length ? ` · ${d.unseen.length} steps not fully in view` : "") +
    (why.length ? " · not predicted: " + why.join("; ") : "");
  $("#plan-prediction-table").innerHTML = Object.keys(d.predicted_std_m).length ? designRows(d.predicted_std_m) : "";
}
$("#plan").addEventListener("change", predictChosenPlan);
$("#token").addEventListener("change", predictChosenPlan);

// -- checks (GET /api/v1/checks): each check's verdict, and each combination's change over time against the threshold
const VERDICT_COLOUR = { holds: "#1a7f2e", drifted: "#c00", inconclusive: "#888" };
const checkTime = (c) => c.finished_at || c.created_at;
const utcMs = (iso) => Date.parse(/(Z|[+-]\d\d:?\d\d)$/.test(iso) ? iso : iso + "Z");

async function refreshChecks() {
  let list;
  try { list = await api("GET", "/checks?limit=200"); } catch (e) {
    $("#checks-message").textContent = "checks: " + e.message + (e.message.startsWith("401") ? ": give the bearer token (top right)" : "");
    $("#checks-message").className = "error";
    return;
  }
  $("#checks-message").className = "muted";
  $("#checks-message").textContent = list.length ? "" : "no check yet (POST /api/v1/checks or i4cal check)";
  $("#checks tbody").innerHTML = list.map((c) => {
    const drifted = Object.entries((c.result && c.result.drifted) || {})
      .map(([k, d]) => `${esc(k)} ${pm(d.change_m, d.std_m)}`).join("; ");
    const why = c.error || (c.result && c.result.reasons && c.result.reasons.join("; ")) || "";
    return `<tr data-id="${esc(c.id)}"><td><code>${esc(c.id.slice(0, 8))}</code></td><td>${fmtTime(checkTime(c))}</td>` +
      `<td>${esc(c.state)}</td><td class="verdict-${esc(c.verdict || "none")}">${esc(c.verdict || "–")}</td>` +
      `<td>${drifted || `<span class="muted">${esc(why)}</span>`}</td></tr>`;
  }).join("");
  // one point per finished check that estimated the combination, oldest first
  const done = list.filter((c) => c.result && c.result.changes).sort((a, b) => utcMs(checkTime(a)) - utcMs(checkTime(b)));
  $("#drift-plots").innerHTML = COMBOS.map((k) => {
    const pts = done.filter((c) => c.result.changes[k] && Number.isFinite(c.result.changes[k].change_m) &&
      Number.isFinite(c.result.changes[k].std_m) && Number.isFinite(c.result.threshold))
      .map((c) => ({ id: c.id, t: utcMs(checkTime(c)), iso: checkTime(c), verdict: c.verdict, threshold: c.result.threshold,
        drifted: k in (c.result.drifted || {}), ...c.result.changes[k] }));
    return `<figure data-combination="${esc(k)}"><figcaption>${esc(k)}</figcaption>${driftPlot(k, pts)}</figure>`;
  }).join("");
}

// one combination's estimated change (mm) per check against time: ± 1 std error bars, the test's band
// (± threshold × std, per check since each check has its own std) shaded behind; a point outside its band drifted
function driftPlot(name, pts) {
  if (!pts.length) return "<p class=muted>no finished check estimated it</p>";
  const W = 290, H = 200, left = 56, right = 14, top = 10, bottom = 40;
  const ymax = Math.max(...pts.map((p) => Math.max(Math.abs(p.change_m) + p.std_m, p.threshold * p.std_m)), 1e-9) * 1.1e3;
  const t0 = Math.min(...pts.map((p) => p.t)), t1 = Math.max(...pts.map((p) => p.t));
  const inner = W - left - right, half = Math.min(12, inner / (2 * pts.length));
  const x = (t) => (t1 > t0 ? left + half + (t - t0) / (t1 - t0) * (inner - 2 * half) : left + inner / 2);
  const mid = top + (H - top - bottom) / 2;
  const y = (vmm) => mid - vmm / ymax * (mid - top);
  const f = (v) => v.toFixed(2);
  const short = (iso) => { const d = new Date(utcMs(iso)); return isNaN(d) ? "" : d.toLocaleString(undefined, { month: "short", day: "numeric", hour: "2-digit", minute: "2-digit" }); };
  let s = `<svg class="drift-plot" data-combination="${esc(name)}" width="${W}" height="${H}" viewBox="0 0 ${W} ${H}" role="img" aria-label="drift of ${esc(name)}">`;
  // the band: ± threshold × std around 0 at each check (joined between checks)
  const upper = pts.map((p) => `${f(x(p.t))},${f(y(p.threshold * p.std_m * 1e3))}`);
  const lower = pts.map((p) => `${f(x(p.t))},${f(y(-p.threshold * p.std_m * 1e3))}`).reverse();
  if (pts.length > 1) s += `<polygon class="band-joined" points="${upper.join(" ")} ${lower.join(" ")}" fill="#2ca02c" fill-opacity="0.08"/>`;
  for (const p of pts) {
    const b = p.threshold * p.std_m * 1e3;
    s += `<rect class="band" data-check="${esc(p.id)}" x="${f(x(p.t) - half)}" y="${f(y(b))}" width="${f(2 * half)}" height="${f(y(-b) - y(b))}" fill="#2ca02c" fill-opacity="0.18"><title>threshold: |z| ≤ ${p.threshold.toFixed(2)}, ± ${b.toFixed(3)} mm</title></rect>`;
  }
  s += `<line x1="${left}" x2="${W - right}" y1="${f(mid)}" y2="${f(mid)}" stroke="#999"/>` +
    `<line x1="${left}" x2="${left}" y1="${top}" y2="${H - bottom}" stroke="#999"/>` +
    `<text x="${left - 4}" y="${top + 8}" font-size="10" text-anchor="end">+${ymax.toFixed(3)}</text>` +
    `<text x="${left - 4}" y="${f(mid + 4)}" font-size="10" text-anchor="end">0</text>` +
    `<text x="${left - 4}" y="${H - bottom}" font-size="10" text-anchor="end">-${ymax.toFixed(3)}</text>` +
    `<text class="axis-label" transform="translate(12 ${f(mid)}) rotate(-90)" font-size="11" text-anchor="middle">change (mm)</text>` +
    `<text class="axis-label" x="${left + inner / 2}" y="${H - 4}" font-size="11" text-anchor="middle">time of the check (local)</text>` +
    `<text x="${left}" y="${H - bottom + 13}" font-size="9">${esc(short(pts[0].iso))}</text>`;
  if (t1 > t0) s += `<text x="${W - right}" y="${H - bottom + 13}" font-size="9" text-anchor="end">${esc(short(pts[pts.length - 1].iso))}</text>`;
  for (const p of pts) {
    const c = VERDICT_COLOUR[p.drifted ? "drifted" : p.verdict === "inconclusive" ? "inconclusive" : "holds"];
    const v = p.change_m * 1e3, e = p.std_m * 1e3;
    s += `<line class="errbar" data-check="${esc(p.id)}" x1="${f(x(p.t))}" x2="${f(x(p.t))}" y1="${f(y(v + e))}" y2="${f(y(v - e))}" stroke="${c}"/>` +
      `<circle class="point" data-check="${esc(p.id)}" data-drifted="${p.drifted}" cx="${f(x(p.t))}" cy="${f(y(v))}" r="3.5" fill="${c}">` +
      `<title>${esc(name)} at ${fmtTime(p.iso)}: ${v.toFixed(3)} ± ${e.toFixed(3)} mm, z ${Number(p.z).toFixed(2)} (threshold ${p.threshold.toFixed(2)})</title></circle>`;
  }
  return s + "</svg>";
}
$("#token").addEventListener("change", refreshChecks);

refreshRuns();
refreshDevices();
refreshCurrent();
predictChosenPlan();
refreshChecks();
setInterval(refreshChecks, 5000);
setInterval(refreshRuns, 3000);
setInterval(refreshDevices, 5000);
