/* softplc operator page: the recent past (GET /api/v1/history, docs/web.md). A timing diagram
   of chosen symbols and places over the last scans (uPlot, one lane per signal, stepped like a
   logic analyzer, scans not sampled shaded), a slider that scrubs back through them showing the
   image, the marking and what fired at that scan, a watch list of pinned symbols, and "why":
   asked of the PLC at the newest scan; at a past scan the history has no why (the trace CLI has:
   softplc why T --trace). Uses app.js's api() and window.softplc (symbols, the net). */
"use strict";

(() => {
  const POLL_MS = 500;
  const MAX_NAMES = 64;  // per request (history.py)
  const LANE = 1.4;  // a lane's height in y units; a signal spans 0..1 of it
  const COLOURS = ["#2563eb", "#e8590c", "#1f9d55", "#7048e8", "#d0342c", "#0b7285"];
  const saved = JSON.parse(localStorage.getItem("softplc-timeline") || "{}");
  const tl = { signals: saved.signals || [], pinned: saved.pinned || [], data: null,
               index: -1, paused: false, plot: null, plotKey: "", polls: 0, error: "" };
  window.softplc.timeline = tl;  // for the browser tests

  const $ = (sel) => document.querySelector(sel);
  const page = window.softplc;

  function save() {
    localStorage.setItem("softplc-timeline",
                         JSON.stringify({ signals: tl.signals, pinned: tl.pinned }));
  }

  function places() { return page.cy ? page.cy.nodes(".place").map((n) => n.data("name")) : []; }
  function transitions() { return page.cy ? page.cy.nodes(".trans").map((n) => n.data("name")) : []; }
  function symbolNames() { return page.symbols.map((s) => s.name); }
  function isPlace(name) { return places().includes(name); }

  /* -- fetching: the whole window once, then what is new (since) --------------------------- */

  function wanted() {
    const first = (chosen, all) => {
      const names = chosen.filter((n) => all.includes(n));
      for (const n of all) if (names.length < MAX_NAMES && !names.includes(n)) names.push(n);
      return names.slice(0, MAX_NAMES);
    };
    const syms = symbolNames();
    return { symbols: first([...tl.signals, ...tl.pinned].filter((n) => syms.includes(n)), syms),
             places: first(tl.signals.filter(isPlace), places()) };
  }

  function emptyData(answer, names) {
    return { hash: answer.program_hash, names, capacity: answer.capacity.scans, scans: [],
             t: [], state: [], forced: [], values: Object.fromEntries(names.symbols.map((n) => [n, []])),
             types: answer.types, board: { scans: [], t: [], fired: [], forced: [],
             marking: Object.fromEntries(names.places.map((p) => [p, []])) } };
  }

  function merge(answer, names) {
    const key = JSON.stringify(names);
    let d = tl.data;
    if (!d || d.hash !== answer.program_hash || d.key !== key) {
      d = tl.data = emptyData(answer, names);
      d.key = key;
    }
    const last = d.scans.length ? d.scans[d.scans.length - 1] : -1;
    answer.scans.forEach((scan, i) => {
      if (scan <= last) return;
      d.scans.push(scan); d.t.push(answer.t_ms[i] / 1000); d.state.push(answer.state[i]);
      d.forced.push(answer.forced_count[i]);
      for (const n of names.symbols) d.values[n].push(answer.values[n][i]);
    });
    const b = answer.board;
    const lastBoard = d.board.scans.length ? d.board.scans[d.board.scans.length - 1] : -1;
    b.scans.forEach((scan, i) => {
      if (scan <= lastBoard) return;
      d.board.scans.push(scan); d.board.t.push(b.t_ms[i] / 1000);
      d.board.fired.push(b.fired[i]); d.board.forced.push(b.forced[i]);
      for (const p of names.places) d.board.marking[p].push(b.marking[p][i]);
    });
    const extra = d.scans.length - d.capacity;
    if (extra > 0) {
      for (const a of [d.scans, d.t, d.state, d.forced, ...Object.values(d.values)]) a.splice(0, extra);
      // keep the last board sample at or before the oldest scan: the marking it starts with
      let drop = 0;
      while (drop + 1 < d.board.scans.length && d.board.scans[drop + 1] <= d.scans[0]) drop += 1;
      for (const a of [d.board.scans, d.board.t, d.board.fired, d.board.forced,
                       ...Object.values(d.board.marking)]) a.splice(0, drop);
    }
  }

  async function poll() {
    if (tl.paused || tl.busy || !page.symbols.length) return;
    tl.busy = true;
    try { await pollOnce(); } finally { tl.busy = false; }
  }

  async function pollOnce() {
    const names = wanted();
    const key = JSON.stringify(names);
    const fresh = tl.data && tl.data.key === key && tl.data.hash === page.netHash;
    const since = fresh && tl.data.scans.length ? tl.data.scans[tl.data.scans.length - 1] : -1;
    const query = `?since=${since}&symbols=${encodeURIComponent(names.symbols.join(","))}` +
                  `&places=${encodeURIComponent(names.places.join(","))}`;
    let answer;
    try { answer = await api("GET", "/history" + query); } catch (e) { return; }
    if (!answer.ok) {
      tl.error = answer.data.error || `history: HTTP ${answer.status}`;
      $("#tl-summary").textContent = tl.error;
      return;
    }
    if (tl.paused) return;  // scrubbing started meanwhile: keep the window it scrubs
    tl.polls += 1;
    tl.error = "";
    merge(answer.data, names);
    tl.index = tl.data.scans.length - 1;
    draw();
  }

  /* -- the timing diagram ------------------------------------------------------------------ */

  function signalSeries(name) {
    // A place: the marking of the last board sample at or before each scan (sample and hold).
    const d = tl.data;
    if (name in d.values) return d.values[name].map((v) => (typeof v === "boolean" ? +v : v));
    const marks = d.board.marking[name] || [];
    let j = -1;
    return d.scans.map((scan) => {
      while (j + 1 < d.board.scans.length && d.board.scans[j + 1] <= scan) j += 1;
      return j < 0 ? null : marks[j];
    });
  }

  function lanes() {
    const d = tl.data;
    const shown = tl.signals.filter((n) => n in d.values || n in d.board.marking);
    return shown.map((name, i) => {
      const raw = signalSeries(name);
      const nums = raw.filter((v) => typeof v === "number");
      const lo = Math.min(0, ...nums), hi = Math.max(1, ...nums);
      const base = (shown.length - 1 - i) * LANE;
      return { name, raw, base, y: raw.map((v) => (typeof v === "number" ? base + (v - lo) / (hi - lo) : null)) };
    });
  }

  function gapTimes() {
    const d = tl.data, out = [];
    for (let i = 1; i < d.scans.length; i += 1) {
      if (d.scans[i] - d.scans[i - 1] > 1) out.push([d.t[i - 1], d.t[i], d.scans[i - 1] + 1, d.scans[i] - 1]);
    }
    return out;
  }

  function overlay(u) {
    const ctx = u.ctx, top = u.bbox.top, height = u.bbox.height;
    ctx.save();
    ctx.fillStyle = "rgba(208, 52, 44, 0.15)";
    for (const [a, b] of gapTimes()) {
      const x0 = u.valToPos(a, "x", true), x1 = u.valToPos(b, "x", true);
      ctx.fillRect(x0, top, Math.max(x1 - x0, 2), height);
    }
    if (tl.index >= 0 && tl.data.t[tl.index] !== undefined) {
      ctx.strokeStyle = "#7048e8";
      ctx.lineWidth = 2;
      const x = u.valToPos(tl.data.t[tl.index], "x", true);
      ctx.beginPath(); ctx.moveTo(x, top); ctx.lineTo(x, top + height); ctx.stroke();
    }
    ctx.restore();
  }

  function draw() {
    const d = tl.data;
    if (!d) return;
    const ls = lanes();
    const key = ls.map((l) => l.name).join(",");
    if (!tl.plot || tl.plotKey !== key) {
      if (tl.plot) { tl.plot.destroy(); tl.plot = null; }
      tl.plotKey = key;
      if (ls.length) tl.plot = makePlot(ls);
    }
    if (tl.plot) {
      tl.plot.series.forEach((s, i) => { if (i) s._raw = ls[i - 1].raw; });
      tl.plot.setData([d.t, ...ls.map((l) => l.y)]);
    }
    const slider = $("#tl-slider");
    slider.max = Math.max(d.scans.length - 1, 0);
    slider.value = tl.index;
    const gaps = gapTimes();
    const missed = gaps.reduce((n, g) => n + g[3] - g[2] + 1, 0);
    $("#tl-summary").textContent = d.scans.length ? `scans ${d.scans[0]}..${d.scans[d.scans.length - 1]}, ` +
      `${d.scans.length} sampled` + (missed ? `, ${missed} not sampled (shaded)` : "") : "no scans yet";
    showAt();
  }

  function makePlot(ls) {
    const el = $("#tl-chart");
    const stepped = uPlot.paths.stepped({ align: 1 });
    const series = [{}, ...ls.map((l, i) => ({
      label: l.name, stroke: COLOURS[i % COLOURS.length], width: 1.5, paths: stepped,
      points: { show: false }, spanGaps: false,
      value: (u, v, si, di) => (di == null || !u.series[si]._raw ? "" : shownValue(u.series[si]._raw[di], l.name)),
    }))];
    const lanesAt = ls.map((l) => l.base + 0.5);
    return new uPlot({
      width: Math.max(el.clientWidth, 300), height: 90 + 44 * ls.length,
      scales: { x: { time: true }, y: { range: [-0.2, ls.length * LANE - 0.2] } },
      axes: [{}, { size: 90, splits: () => lanesAt, values: () => ls.map((l) => l.name),
                   grid: { show: false } }],
      series, hooks: { draw: [overlay] },
    }, [tl.data.t, ...ls.map((l) => l.y)], el);
  }

  /* -- one scan of the window: image, marking, fired, watch list, why --------------------- */

  function boardAt(scan) {
    const b = tl.data.board;
    let j = -1;
    while (j + 1 < b.scans.length && b.scans[j + 1] <= scan) j += 1;
    return j;
  }

  function rows(table, entries, action) {
    $(table).replaceChildren(...entries.map(([k, v]) => {
      const tr = document.createElement("tr");
      for (const x of [k, v]) { const td = document.createElement("td"); td.textContent = x; tr.appendChild(td); }
      if (action) {
        const button = document.createElement("button");
        button.className = "small";
        button.textContent = action;
        const td = document.createElement("td");
        td.appendChild(button);
        tr.appendChild(td);
      }
      tr.dataset.name = k;
      return tr;
    }));
  }

  /* As the process image shows it (app.js's symbolText: unit, the scale's resolution). */
  function shownValue(v, name) {
    const sym = page.symbols.find((s) => s.name === name);
    if (sym) return symbolText(sym, v);
    return typeof v === "boolean" ? (v ? "1" : "0") : String(v);
  }

  function showAt() {
    const d = tl.data, i = tl.index;
    const at = $("#tl-at");
    if (!d || i < 0 || i >= d.scans.length) { at.textContent = "—"; return; }
    const scan = d.scans[i];
    const past = i < d.scans.length - 1;
    at.classList.toggle("past", past);
    const when = new Date(d.t[i] * 1000).toISOString().slice(11, 23);
    const gapBefore = i > 0 && scan - d.scans[i - 1] > 1 ? `, scans ${d.scans[i - 1] + 1}..${scan - 1} not sampled` : "";
    at.textContent = `scan ${scan} at ${when} UTC, ${d.state[i]}, ${d.forced[i]} forced` +
      (past ? ` (${d.scans.length - 1 - i} samples back; Live to follow again)` : " (newest)") + gapBefore;
    at.dataset.scan = scan;
    const syms = Object.keys(d.values);
    rows("#tl-image tbody", syms.map((n) => [n, shownValue(d.values[n][i], n)]));
    rows("#tl-watch tbody", tl.pinned.filter((n) => n in d.values).map((n) => [n, shownValue(d.values[n][i], n)]),
         "unpin");
    const j = boardAt(scan);
    const b = d.board;
    const marking = $("#tl-marking");
    if (j < 0) {
      marking.replaceChildren();
      $("#tl-fired").textContent = "no board sample at or before this scan";
    } else {
      marking.replaceChildren(...Object.keys(b.marking).filter((p) => b.marking[p][j]).map((p) => {
        const li = document.createElement("li");
        li.textContent = `${p}: ${b.marking[p][j]}`;
        li.dataset.place = p;
        return li;
      }));
      const fired = b.fired[j];
      const from = j > 0 ? b.scans[j - 1] + 1 : "?";
      $("#tl-fired").textContent = `marking of the board sample at scan ${b.scans[j]}; fired in scans ` +
        `${from}..${b.scans[j]}: ` + (fired === null ? "unknown" : Object.entries(fired)
          .map(([t, n]) => (n > 1 ? `${t} x${n}` : t)).join(", ") || "nothing") +
        `; forced: ${Object.entries(b.forced[j] || {}).map(([s, v]) => `${s}=${v}`).join(", ") || "none"}`;
    }
  }

  async function why() {
    const t = $("#tl-transition").value;
    const out = $("#tl-why-out");
    if (!t || !tl.data) return;
    const i = tl.index;
    if (i < tl.data.scans.length - 1) {
      const scan = tl.data.scans[i];
      const j = boardAt(scan);
      const fired = j >= 0 && tl.data.board.fired[j] ? (tl.data.board.fired[j][t] || 0) : null;
      out.textContent = `scan ${scan} is in the past: the history keeps marking, values and what ` +
        `fired, not the round (${t} fired ${fired === null ? "?" : fired}x in that board interval). ` +
        `Why at a past scan comes from a trace: softplc run --trace FILE, then\n` +
        `softplc why ${t} --trace FILE --program PROGRAM.yaml --at-scan ${scan}`;
      return;
    }
    const answer = await api("GET", "/why/" + encodeURIComponent(t));
    if (!answer.ok) { out.textContent = answer.data.error || `why: HTTP ${answer.status}`; return; }
    const a = answer.data;
    out.textContent = `${a.transition}: ${a.verdict} (the next round, after scan ${a.scan})\n` +
      a.reasons.map((r) => "  - " + r.text).join("\n");
  }

  /* -- controls ---------------------------------------------------------------------------- */

  function chips() {
    $("#tl-signals").replaceChildren(...tl.signals.map((name) => {
      const chip = document.createElement("span");
      chip.className = "tl-chip";
      chip.dataset.name = name;
      chip.textContent = name + (tl.pinned.includes(name) ? " (pinned)" : "");
      const x = document.createElement("button");
      x.textContent = "×";
      x.title = "remove";
      x.addEventListener("click", () => { tl.signals = tl.signals.filter((n) => n !== name); changed(); });
      chip.appendChild(x);
      return chip;
    }));
    const list = $("#tl-names");
    const names = [...symbolNames(), ...places()];
    if (list.children.length !== names.length) {
      list.replaceChildren(...names.map((n) => { const o = document.createElement("option"); o.value = n; return o; }));
    }
    const select = $("#tl-transition");
    const ts = transitions();
    if (select.options.length !== ts.length) {
      select.replaceChildren(...ts.map((t) => { const o = document.createElement("option"); o.value = t; o.textContent = t; return o; }));
    }
  }

  function changed() { save(); chips(); live(); }

  function add(pin) {
    const name = $("#tl-name").value.trim();
    if (!name) return;
    if (!symbolNames().includes(name) && !isPlace(name)) {
      $("#tl-summary").textContent = `no symbol or place ${name}`;
      return;
    }
    if (pin && symbolNames().includes(name) && !tl.pinned.includes(name)) tl.pinned.push(name);
    if (!pin && !tl.signals.includes(name)) tl.signals.push(name);
    $("#tl-name").value = "";
    changed();
  }

  function live() {
    tl.paused = false;
    tl.data = null;  // the whole window again: what was skipped while scrubbing
    poll();
  }

  $("#tl-plot").addEventListener("click", () => add(false));
  $("#tl-pin").addEventListener("click", () => add(true));
  $("#tl-name").addEventListener("keydown", (e) => { if (e.key === "Enter") add(false); });
  $("#tl-live").addEventListener("click", live);
  $("#tl-why").addEventListener("click", why);
  $("#tl-slider").addEventListener("input", () => {
    if (!tl.data) return;
    tl.index = Number($("#tl-slider").value);
    tl.paused = tl.index < tl.data.scans.length - 1;
    if (tl.plot) tl.plot.redraw(false, false);
    showAt();
  });
  $("#tl-watch").addEventListener("click", (e) => {
    const tr = e.target.tagName === "BUTTON" && e.target.closest("tr");
    if (tr) { tl.pinned = tl.pinned.filter((n) => n !== tr.dataset.name); changed(); }
  });

  setInterval(() => { chips(); poll(); }, POLL_MS);
})();
