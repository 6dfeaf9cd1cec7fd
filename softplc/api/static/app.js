/* softplc operator page: the net live (Cytoscape.js + dagre), the process image with writes
   and forcing, program handling, scan timing (uPlot) and events. Everything comes from the
   same origin's HTTP API. Who acts: a session from the login form (an HttpOnly cookie the
   page never reads; every request sends it, same-origin, with the browser's Origin header
   the API checks), or an API key (sessionStorage, only ever in the Authorization header,
   never in a URL; it is taken before the cookie). */
"use strict";

const API = "/api/v1";
const page = { cy: null, netHash: undefined, netWanted: undefined, netLoading: false,
               netBuilds: 0, frames: 0, lastFrame: null, counts: {}, symbols: [], rows: {},
               plot: null, series: [[], [], [], []], events: 0 };
window.softplc = page;  // for people poking around (and the browser tests)

const $ = (sel) => document.querySelector(sel);
const text = (el, value) => { if (el.textContent !== String(value)) el.textContent = value; };

function token() { return sessionStorage.getItem("softplc-token") || ""; }

function headers(extra) {
  const h = Object.assign({}, extra || {});
  if (token()) h.Authorization = "Bearer " + token();
  return h;
}

async function api(method, path, body, contentType) {
  const init = { method, headers: headers(contentType ? { "Content-Type": contentType } : {}) };
  if (body !== undefined) init.body = body;
  const response = await fetch(API + path, init);
  let data = {};
  try { data = await response.json(); } catch (e) { data = {}; }
  if (response.status === 401) askToken(data.error);
  return { ok: response.ok, status: response.status, data };
}

/* -- program handling -------------------------------------------------------------------- */

function say(message, ok, problems) {
  $("#offer-login").classList.add("hidden");
  const el = $("#message");
  el.textContent = message;
  el.className = "message " + (ok ? "ok" : "refused");
  const list = $("#problems");
  list.replaceChildren(...(problems || []).map((p) => {
    const li = document.createElement("li");
    li.textContent = p;
    return li;
  }));
}

for (const button of document.querySelectorAll("button[data-command]")) {
  button.addEventListener("click", async () => {
    const command = button.dataset.command;
    const answer = await api("POST", "/" + command);
    if (answer.ok) say(`${command}: ${answer.data.message}`, true);
    else if (!denied(command, answer)) {
      say(`${command} refused: ${answer.data.error || answer.status}`, false,
          answer.data.problems);
    }
  });
}

$("#download").addEventListener("click", async () => {
  const file = $("#program-file").files[0];
  if (!file) { say("choose a program file first", false); return; }
  const body = await file.text();
  const query = `?name=${encodeURIComponent(file.name.replace(/[^A-Za-z0-9._-]/g, "_"))}` +
                ($("#online").checked ? "&online=true" : "");
  const answer = await api("POST", "/program" + query, body, "application/yaml");
  if (answer.ok) say(`download: ${answer.data.message}`, true);
  else if (!denied("download", answer)) {
    say(answer.data.error || `download refused (${answer.status})`, false,
        answer.data.problems);
  }
});

$("#release-all").addEventListener("click", async () => {
  const answer = await api("DELETE", "/forces");
  if (!denied("unforce", answer)) {
    say(answer.ok ? answer.data.message : `unforce refused: ${answer.data.error}`, answer.ok);
  }
});

/* -- the net ----------------------------------------------------------------------------- */

// cytoscape-dagre registers itself with the global cytoscape when it loads.

const NET_STYLE = [
  { selector: "node", style: { "font-size": 11, "text-wrap": "wrap", color: "#1d2733" } },
  { selector: "node.place", style: {
      shape: "ellipse", width: 38, height: 38, "background-color": "#fff",
      "border-width": 2, "border-color": "#334155", label: "data(label)",
      "text-valign": "center", "text-halign": "center", "font-size": 15,
      "font-weight": "bold" } },
  { selector: "node.place.marked", style: { "background-color": "#dbeafe",
      "border-color": "#2563eb", color: "#1e40af" } },
  { selector: "node.place[caption]", style: { "text-valign": "center" } },
  { selector: "node.trans", style: {
      shape: "rectangle", width: 10, height: 34, "background-color": "#334155",
      label: "data(label)", "text-valign": "center", "text-halign": "right",
      "text-margin-x": 4, "font-size": 10, "transition-property": "background-color",
      "transition-duration": "0.25s" } },
  { selector: "node.trans.fired", style: { "background-color": "#f59f00", width: 14 } },
  { selector: "node.trans.busy", style: { "background-color": "#7048e8", width: 14 } },
  { selector: "node.caption", style: { label: "data(label)", "background-opacity": 0,
      "border-width": 0, width: 1, height: 1, "font-size": 10, color: "#6b7785" } },
  { selector: "node.instance", style: {
      "background-color": "#f1f5f9", "border-color": "#94a3b8", "border-width": 1,
      "border-style": "dashed", label: "data(label)", "text-valign": "top",
      "text-halign": "center", "font-size": 12, color: "#475569", padding: 14,
      shape: "round-rectangle" } },
  { selector: "edge", style: { width: 1.5, "line-color": "#94a3b8", "curve-style": "bezier",
      "target-arrow-shape": "triangle", "target-arrow-color": "#94a3b8", "arrow-scale": 0.9,
      label: "data(weight)", "font-size": 10, "text-background-color": "#fff",
      "text-background-opacity": 1 } },
  { selector: "edge.inhibitor", style: { "target-arrow-shape": "circle",
      "line-color": "#d0342c", "target-arrow-color": "#d0342c" } },
  { selector: "edge.test", style: { "line-style": "dashed", "target-arrow-shape": "none" } },
];

function nodeId(name) { return "n:" + name; }

function shortName(name, instance) {
  return instance ? name.slice(instance.length + 1) : name;
}

function buildNet(net) {
  if (page.cy) { page.cy.destroy(); page.cy = null; }
  if (net.error || !net.nodes) {
    $("#net-summary").textContent = net.error || (net.too_large ?
      `${net.places} places, ${net.transitions} transitions: too large to draw` : "no net");
    return;
  }
  const elements = [];
  for (const inst of net.subnets || []) {
    elements.push({ data: { id: "i:" + inst, label: inst }, classes: "instance" });
  }
  for (const p of net.nodes.places) {
    elements.push({ data: { id: nodeId(p.name), name: p.name, kind: "place",
                            label: "", parent: p.instance ? "i:" + p.instance : undefined,
                            info: p }, classes: "place" });
    elements.push({ data: { id: "c:" + p.name, label: shortName(p.name, p.instance),
                            parent: p.instance ? "i:" + p.instance : undefined },
                    classes: "caption" });
  }
  for (const t of net.nodes.transitions) {
    elements.push({ data: { id: nodeId(t.name), name: t.name, kind: "trans",
                            label: shortName(t.name, t.instance),
                            parent: t.instance ? "i:" + t.instance : undefined, info: t },
                    classes: "trans" });
  }
  net.arcs.forEach(([from, to, weight, kind], i) => {
    elements.push({ data: { id: "a" + i, source: nodeId(from), target: nodeId(to),
                            weight: weight > 1 ? String(weight) : "" }, classes: kind });
  });
  page.netBuilds += 1;  // once per program: the browser tests count them
  page.cy = cytoscape({ container: $("#net"), elements, style: NET_STYLE, wheelSensitivity: 0.3,
                        minZoom: 0.2, maxZoom: 3 });
  page.cy.layout({ name: "dagre", rankDir: "LR", nodeSep: 30, rankSep: 55, edgeSep: 10 }).run();
  placeCaptions();
  page.cy.fit(undefined, 20);
  page.cy.on("mouseover", "node.place, node.trans", (ev) => showTip(ev.target, ev));
  page.cy.on("mouseout", "node", () => $("#tip").classList.add("hidden"));
  $("#net-summary").textContent = `${net.nodes.places.length} places, ` +
    `${net.nodes.transitions.length} transitions, ${net.arcs.length} arcs` +
    (net.subnets.length ? `, subnets ${net.subnets.join(", ")}` : "");
}

function placeCaptions() {
  // A place's name sits under it (its centre shows the tokens).
  page.cy.nodes("node.place").forEach((n) => {
    const caption = page.cy.getElementById("c:" + n.data("name"));
    const pos = n.position();
    caption.position({ x: pos.x, y: pos.y + 30 });
    caption.ungrabify();
  });
}

function showTip(node, ev) {
  const info = node.data("info") || {};
  const frame = page.lastFrame || { marking: {}, net_live: {} };
  const live = frame.net_live || {};
  let lines = [node.data("name")];
  if (node.hasClass("place")) {
    lines.push(`tokens: ${frame.marking[info.name] || 0}` +
               (info.capacity >= 0 ? ` (capacity ${info.capacity})` : ""));
    const tokens = (live.tokens || {})[info.name];
    if (tokens) lines.push(...tokens.map((t) => "  " + JSON.stringify(t)));
    if (info.outputs.length) lines.push("outputs: " + info.outputs.map((o) => o.join("=")).join(", "));
  } else {
    if (info.guard) lines.push("when: " + info.guard);
    if (info.delay_ms) lines.push(`delay: ${info.delay_ms} ms`);
    if (info.duration_ms) lines.push(`duration: ${info.duration_ms} ms`);
    if (info.actions.length) lines.push("do: " + info.actions.join("; "));
    lines.push(`priority ${info.priority}, fired ${(live.fired_counts || {})[info.name] || 0}x`);
  }
  const tip = $("#tip");
  tip.textContent = lines.join("\n");
  const box = $("#net").getBoundingClientRect();
  const card = $("#net").parentElement.getBoundingClientRect();
  tip.style.left = (ev.renderedPosition.x + box.left - card.left + 14) + "px";
  tip.style.top = (ev.renderedPosition.y + box.top - card.top + 14) + "px";
  tip.classList.remove("hidden");
}

function updateNet(frame) {
  const cy = page.cy;
  if (!cy) return;
  const live = frame.net_live || {};
  const counts = live.fired_counts || {};
  const busy = live.busy || {};
  const waiting = live.delay_left_ms || {};
  cy.batch(() => {
    cy.nodes("node.place").forEach((n) => {
      const tokens = frame.marking[n.data("name")] || 0;
      const label = tokens === 0 ? "" : tokens <= 3 ? "●".repeat(tokens) : String(tokens);
      if (n.data("label") !== label) n.data("label", label);
      n.toggleClass("marked", tokens > 0);
    });
    cy.nodes("node.trans").forEach((n) => {
      const name = n.data("name");
      const fired = (counts[name] || 0) > (page.counts[name] || 0);
      n.toggleClass("fired", fired);
      n.toggleClass("busy", name in busy);
      const info = n.data("info");
      let label = shortName(name, info.instance);
      if (name in busy) label += `\n${Math.round(busy[name].remaining_ms)} ms left`;
      else if (name in waiting && waiting[name] > 0) label += `\n(${Math.round(waiting[name])} ms)`;
      if (n.data("label") !== label) n.data("label", label);
    });
  });
  page.counts = counts;
}

/* One load of the net at a time, whatever the frames' rate: a frame only says which program
   it wants (its hash); the loader fetches /net until what is drawn is that program. A failed
   or lagging answer (a busy board: 503; a board that does not show the new program yet) keeps
   what is drawn and retries; only "no program" with no program wanted clears the net. */
const NET_RETRY_MS = 300;

function wantNet(hash) {
  page.netWanted = hash ?? null;
  if (!page.netLoading && page.netWanted !== page.netHash) loadNet();
}

function showNoNet(message) {
  if (page.cy) { page.cy.destroy(); page.cy = null; }
  page.symbols = [];
  buildImage();
  $("#net-summary").textContent = message;
}

async function fetchNetOnce(wanted) {
  let answer;
  try { answer = await api("GET", "/net"); } catch (e) { answer = { ok: false, data: {} }; }
  const hash = answer.ok ? answer.data.program_hash ?? wanted : undefined;
  if (answer.ok && hash !== page.netHash) {
    page.netHash = hash;  // set first: a net that cannot be drawn is not fetched again
    page.symbols = answer.data.symbols || [];
    buildImage();
    buildNet(answer.data);
  } else if (!answer.ok && answer.status === 404 && wanted === null) {
    showNoNet(answer.data.error || "no program loaded");
    page.netHash = null;
  } else if (!answer.ok && !page.cy) {
    $("#net-summary").textContent = (answer.data.error || "net unavailable") + ", retrying";
  }
  return answer.status;
}

async function loadNet() {
  page.netLoading = true;
  try {
    while (page.netWanted !== page.netHash) {
      const wanted = page.netWanted;
      if (await fetchNetOnce(wanted) === 401) break;  // the token dialog; its stream asks again
      if (page.netWanted !== page.netHash && page.netWanted === wanted) {
        await new Promise((resolve) => setTimeout(resolve, NET_RETRY_MS));
      }
    }
  } finally {
    page.netLoading = false;
  }
}

/* -- process image ----------------------------------------------------------------------- */

function cell(tr, className, content) {
  const td = document.createElement("td");
  if (className) td.className = className;
  if (content instanceof Node) td.appendChild(content); else if (content !== undefined) td.textContent = content;
  tr.appendChild(td);
  return td;
}

/* What a symbol takes and how it is shown come from the server (softplc/core/present.py,
   docs/programs.md "How values are shown and given"): `range` (a scaled symbol's engineering
   span, an integer type's range), `unit` and `decimals` (the scale's resolution). The server
   checks the value and says why it refuses one. */
const DECIMAL = new Set(["real", "lreal"]);

function takes(sym) {
  if (sym.type === "bool") return "0/1";
  const unit = sym.unit ? " " + sym.unit : "";
  if (Array.isArray(sym.range)) return `${sym.range[0]}..${sym.range[1]}${unit}`;
  return "a number, e.g. 12.5" + unit;
}

function valueInput(sym, label, onValue) {
  const wrap = document.createElement("span");
  const input = document.createElement("input");
  input.placeholder = takes(sym);
  input.title = `${label} ${sym.name}: ${takes(sym)}`;
  if (Array.isArray(sym.range)) { input.dataset.min = sym.range[0]; input.dataset.max = sym.range[1]; }
  input.className = label;
  const button = document.createElement("button");
  button.className = "small " + label;
  button.textContent = label;
  button.addEventListener("click", () => onValue(input.value.trim()));
  wrap.append(input, button);
  return wrap;
}

/* A value as a person reads it: a scaled one at its scale's resolution with its unit. */
function symbolText(sym, v) {
  if (v === undefined || v === null) return "";
  if (sym.type === "bool") return v ? "1" : "0";
  if (typeof v !== "number") return String(v);  // "NaN", "Infinity" (never raw bits)
  const unit = sym.unit ? " " + sym.unit : "";
  if (Number.isInteger(sym.decimals)) {
    const fixed = v.toFixed(sym.decimals);
    return (Number(fixed) === 0 ? fixed.replace(/^-/, "") : fixed) + unit;
  }
  if (sym.scaled) return String(Number(v.toPrecision(7))) + unit;  // a scaled real
  return String(v) + unit;
}

function parseValue(sym, raw) {
  if (sym.type === "bool") {
    if (["1", "true", "on"].includes(raw.toLowerCase())) return true;
    if (["0", "false", "off"].includes(raw.toLowerCase())) return false;
    return null;
  }
  if (raw === "") return null;
  const n = Number(raw);
  if (DECIMAL.has(sym.type)) return Number.isFinite(n) ? n : null;
  return Number.isInteger(n) || (sym.scaled && Number.isFinite(n)) ? n : null;
}

function buildImage() {
  const body = $("#image tbody");
  body.replaceChildren();
  page.rows = {};
  for (const sym of page.symbols) {
    const tr = document.createElement("tr");
    tr.dataset.symbol = sym.name;
    cell(tr, "name", sym.name);
    cell(tr, "", sym.address);
    cell(tr, "dir-" + sym.direction, sym.direction);
    const value = cell(tr, "value", "");
    const desc = cell(tr, "desc", sym.description || "");
    desc.title = sym.description || "";
    cell(tr, "", sym.hmi_writable ? valueInput(sym, "write", async (raw) => {
      const v = parseValue(sym, raw);
      if (v === null) { say(`write ${sym.name}: not a ${sym.type} value`, false); return; }
      const answer = await api("PUT", "/symbols/" + encodeURIComponent(sym.name),
                               JSON.stringify({ value: v }), "application/json");
      if (denied(`write ${sym.name}`, answer)) return;
      say(answer.ok ? `write ${sym.name} = ${v} queued` : answer.data.error, answer.ok);
    }) : "");
    const force = valueInput(sym, "force", async (raw) => {
      const v = parseValue(sym, raw);
      if (v === null) { say(`force ${sym.name}: not a ${sym.type} value`, false); return; }
      const answer = await api("PUT", "/forces/" + encodeURIComponent(sym.name),
                               JSON.stringify({ value: v }), "application/json");
      if (denied(`force ${sym.name}`, answer)) return;
      say(answer.ok ? answer.data.message : answer.data.error, answer.ok);
    });
    const release = document.createElement("button");
    release.className = "small release";
    release.textContent = "release";
    release.addEventListener("click", async () => {
      const answer = await api("DELETE", "/forces/" + encodeURIComponent(sym.name));
      if (denied(`release ${sym.name}`, answer)) return;
      say(answer.ok ? answer.data.message : answer.data.error, answer.ok);
    });
    force.appendChild(release);
    cell(tr, "", force);
    body.appendChild(tr);
    page.rows[sym.name] = { tr, value, sym, release };
  }
}

function updateImage(frame) {
  for (const [name, row] of Object.entries(page.rows)) {
    // Values arrive typed (softplc/core/present.py): a negative int, a real as a decimal
    // number, "NaN"/"Infinity" as text; shown as they are, never as raw bits.
    const v = frame.values[name];
    text(row.value, symbolText(row.sym, v));
    if (row.sym.type === "bool") row.value.className = "value " + (v ? "on" : "off");
    const forced = name in (frame.forced || {});
    row.tr.classList.toggle("forced", forced);
    row.release.classList.toggle("hidden", !forced);
  }
}

/* -- timing and events ------------------------------------------------------------------- */

function makePlot() {
  const el = $("#plot");
  const opts = {
    width: Math.max(el.clientWidth, 300), height: 200,
    scales: { x: { time: true }, y: { range: (u, min, max) => [0, Math.max(max * 1.1, 10)] } },
    axes: [{}, { label: "µs", size: 50 }],
    series: [{}, { label: "exec last", stroke: "#2563eb", width: 1 },
             { label: "exec p99", stroke: "#7048e8", width: 1 },
             { label: "lateness p99", stroke: "#e8590c", width: 1.5 }],
  };
  page.plot = new uPlot(opts, page.series, el);
}

function updatePlot(frame) {
  const t = frame.timing || {};
  const s = page.series;
  s[0].push(frame.wall_ms / 1000);
  s[1].push(t.last_exec_us ?? t.exec_median_us ?? null);
  s[2].push(t.exec_p99_us ?? null);
  s[3].push(t.lateness_p99_us ?? null);
  if (s[0].length > 600) s.forEach((a) => a.shift());  // ~30 s at the page's rate
  if (page.frames % 3 === 0) page.plot.setData(page.series);
  text($("#overruns"), t.overruns ?? 0);
}

function updateEvents(frame) {
  const body = $("#events tbody");
  for (const e of frame.events || []) {
    const tr = document.createElement("tr");
    const when = new Date(frame.wall_ms).toLocaleTimeString();
    cell(tr, "", when);
    cell(tr, "", e.scan);
    cell(tr, "", e.name);
    body.prepend(tr);
    page.events += 1;
  }
  while (body.children.length > 200) body.lastChild.remove();
}

/* -- header ------------------------------------------------------------------------------ */

function updateHeader(frame) {
  const state = $("#state");
  text(state, frame.state || "?");
  state.className = "state state-" + (frame.state || "unknown");
  text($("#program"), frame.program || "—");
  text($("#hash"), frame.program_hash ? frame.program_hash.slice(0, 12) : "—");
  $("#hash").title = frame.program_hash || "";
  text($("#start-mode"), (frame.start_mode || "—") + (frame.boot_policy ? `, boot policy ${frame.boot_policy}` : ""));
  $("#start-mode").title = frame.start_reason || "";
  text($("#scan-count"), frame.scan_count);
  text($("#period"), frame.period_us ? (frame.period_us >= 1000 ? `${frame.period_us / 1000} ms`
                                                                 : `${frame.period_us} µs`) : "—");
  const forced = Object.keys(frame.forced || {}).length;
  text($("#forced-count"), `${forced} forced`);
  $("#forced-count").classList.toggle("hidden", forced === 0);
  const waiting = frame.waiting_for_devices || [];  // start-up: no firing round, outputs safe
  text($("#waiting-io"), `waiting for I/O: ${waiting.join(", ")}`);
  $("#waiting-io").classList.toggle("hidden", waiting.length === 0);
  const fault = $("#fault");
  fault.classList.toggle("hidden", !frame.fault_reason);
  text(fault, frame.fault_reason ? "FAULT: " + frame.fault_reason : "");
  showPause(frame.paused);
  showWaiting(frame.waiting || []);
}

function showWaiting(waits) {  // why nothing moves (core/waiting.py): the longest waits
  const list = $("#waiting");
  list.replaceChildren(...waits.map((w) => {
    const li = document.createElement("li");
    li.textContent = `${w.transition || "the net"} waits ${Number(w.for_s).toFixed(1)} s `
                     + `(net time): ${(w.blockers || []).join("; ")}`;
    return li;
  }));
  list.classList.toggle("hidden", waits.length === 0);
}

function showPause(paused) {  // at a breakpoint (docs/debug.md): a banner under the fault's
  let banner = $("#paused");
  if (!banner) {
    banner = document.createElement("div");
    banner.id = "paused";
    banner.className = "fault hidden";
    $("#fault").after(banner);
  }
  banner.classList.toggle("hidden", !paused);
  text(banner, paused ? `PAUSED after scan ${paused.k} (scan count ${paused.scan_count}, outputs `
                        + `${paused.outputs}): ${paused.reason}; softplc step | continue` : "");
}

function onFrame(frame) {
  page.frames += 1;
  wantNet(frame.program_hash);
  updateHeader(frame);
  updateNet(frame);
  updateImage(frame);
  updatePlot(frame);
  updateEvents(frame);
  page.lastFrame = frame;
}

/* -- the live stream (fetch, so that the token goes in a header) ------------------------- */

let streamAbort = null;

async function startStream() {
  if (streamAbort) streamAbort.abort();
  streamAbort = new AbortController();
  const link = $("#link");
  try {
    const response = await fetch(API + "/live", { headers: headers(), signal: streamAbort.signal });
    if (response.status === 401) {
      link.textContent = "log in needed";
      askToken("This PLC shows nothing without credentials: log in, or give a key.");
      return;
    }
    if (!response.ok) throw new Error("HTTP " + response.status);
    link.textContent = "live";
    link.classList.remove("down");
    const reader = response.body.getReader();
    const decoder = new TextDecoder();
    let buffer = "";
    for (;;) {
      const { value, done } = await reader.read();
      if (done) break;
      buffer += decoder.decode(value, { stream: true });
      let cut;
      while ((cut = buffer.indexOf("\n\n")) >= 0) {
        const block = buffer.slice(0, cut);
        buffer = buffer.slice(cut + 2);
        const data = block.split("\n").filter((l) => l.startsWith("data: "))
          .map((l) => l.slice(6)).join("\n");
        if (data) onFrame(JSON.parse(data));
      }
    }
    throw new Error("stream ended");
  } catch (err) {
    if (err.name === "AbortError") return;
    link.textContent = "reconnecting…";
    link.classList.add("down");
    setTimeout(startStream, 1000);
  }
}

makePlot();
startStream();  // account.js, loaded after this file, asks who is logged in
