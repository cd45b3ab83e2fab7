/* Run page: live state, progress, prompts and samples over server-sent events; operator controls. */
"use strict";

(() => {
  const root = document.getElementById("run");
  if (!root) return;
  const runId = root.dataset.runId;
  const timeScale = parseFloat(root.dataset.timeScale) || 1;
  const isOperator = root.dataset.operator === "true";
  const ACTIVE = ["queued", "running", "paused"];
  const FINAL = ["completed", "failed", "aborted"];
  let status = root.dataset.status;
  let source = null;
  let stopFallback = null;
  let stopSamples = null;
  let ended = false;

  // ------------------------------------------------------------------ state, progress, buttons
  function setButtons() {
    const pause = document.getElementById("pause");
    const resume = document.getElementById("resume");
    const abort = document.getElementById("abort");
    if (pause) pause.disabled = status !== "running";
    if (resume) resume.disabled = status !== "paused";
    if (abort) abort.disabled = !ACTIVE.includes(status);
  }

  function setState(state) {
    status = state;
    root.dataset.status = state;
    const el = document.getElementById("state");
    if (el) {
      el.textContent = state;
      el.className = `state-${state}`;
    }
    if (state !== "running") setPauseRequested(false);
    setButtons();
  }

  function setPauseRequested(on) {
    const el = document.getElementById("pause-requested");
    if (el) el.hidden = !on;
  }

  // the stream replays the run's history from its start: never show an older progress than the page has
  const shown = document.getElementById("progress");
  let maxPercent = shown ? parseFloat(shown.textContent) || 0 : 0;

  function setProgress(p) {
    if (!p) return;
    if (typeof p.percent === "number") {
      if (p.percent < maxPercent) return;
      maxPercent = p.percent;
      const pct = Math.max(0, Math.min(100, p.percent));
      cc.setText("progress", `${pct.toFixed(1)} %`);
      const bar = document.getElementById("progress-bar");
      if (bar) {
        bar.value = pct;
        bar.textContent = `${pct.toFixed(1)} %`;
      }
    }
    // one notion of time left: wall-clock seconds (left_wall_s); left_s is table time, which a
    // simulated station runs time_scale times faster (an event from before left_wall_s: divide)
    const wall = typeof p.left_wall_s === "number" ? p.left_wall_s
      : typeof p.left_s === "number" ? p.left_s / timeScale : null;
    if (wall !== null) {
      const el = cc.setText("time-left", cc.duration(wall));
      if (el) el.title = typeof p.left_s === "number" && timeScale !== 1
        ? `wall-clock time (${cc.duration(p.left_s)} of table time at time scale ${timeScale})` : "wall-clock time";
    }
    if (typeof p.samples === "number") cc.setText("samples", String(p.samples));
  }

  function describeStep(d) {
    if (d.warning) return `warning: ${d.warning}`;
    if (d.retry) return `retry ${d.retry}: ${d.reason || ""}`;
    const s = d.step;
    if (!s || typeof s !== "object") return "";
    const fmt = (v) => (typeof v === "number" ? v.toFixed(1) : v);
    switch (s.kind) {
      case "move": return `move to ψ ${fmt(s.psi)}°, θ ${fmt(s.theta)}°, φ ${fmt(s.phi)}°`;
      case "acquire": return `acquire ${s.step || ""} (${s.samples} samples)`;
      case "settle": return `settle ${s.seconds} s`;
      case "compute": return `computing the ${s.label || ""}` + (typeof s.percent === "number" ? `: ${s.stage || ""} ${s.percent.toFixed(0)} %` : "");
      case "prompt": return "waiting for the operator";
      case "checkpoint": return "checkpoint";
      case "identify": return "identifying the units";
      case "where": return "reading where the table stands";
      default: return s.kind || "";
    }
  }

  // --------------------------------------------------------------------------------- units
  // A run started without serial numbers learns them from the compasses as it starts: the page,
  // rendered before that, asks the run for them at its state changes until it knows them.
  const serialsEl = document.getElementById("serials");
  let askingUnits = false;

  function showUnits(serials) {
    const entries = Object.entries(serials || {}).filter(([, v]) => v);
    if (!serialsEl || !entries.length) return;
    serialsEl.replaceChildren();
    for (const [slot, serial] of entries.sort((a, b) => Number(a[0]) - Number(b[0]))) {
      serialsEl.append(`slot ${slot}: `, cc.el("a", { href: `/ui/devices/${encodeURIComponent(serial)}` }, serial), " ");
    }
  }

  async function refreshUnits() {
    if (!serialsEl || serialsEl.querySelector("a") || askingUnits) return;
    askingUnits = true;
    try {
      const run = await cc.api("GET", `/runs/${runId}`);
      showUnits(run.serials);
    } catch (e) {
      console.warn("units:", e && e.message ? e.message : e);
    } finally {
      askingUnits = false;
    }
  }

  // ------------------------------------------------------------------------------- prompts
  const prompts = document.getElementById("prompts");

  function findPrompt(id) {
    if (!prompts) return null;
    for (const div of prompts.querySelectorAll(".prompt")) if (div.dataset.prompt === id) return div;
    return null;
  }

  function showPrompt(id, text) {
    if (!prompts || findPrompt(id)) return;
    const div = cc.el("div", { className: "prompt", "data-prompt": id });
    div.append(cc.el("span", { className: "prompt-text" }, text));
    if (isOperator) for (const b of cc.answerButtons(id)) div.append(b, " ");
    prompts.append(div);
  }

  function dropPrompt(id) {
    const div = findPrompt(id);
    if (div) div.remove();
  }

  function syncPrompts(list) {
    if (!prompts) return;
    const ids = new Set((list || []).map((p) => p.id));
    for (const div of prompts.querySelectorAll(".prompt")) if (!ids.has(div.dataset.prompt)) div.remove();
    for (const p of list || []) showPrompt(p.id, p.text);
  }

  if (prompts) {
    prompts.addEventListener("click", async (ev) => {
      const button = ev.target instanceof Element ? ev.target.closest("button.answer") : null;
      if (!button) return;
      const id = button.dataset.prompt;
      button.disabled = true;
      try {
        await cc.api("POST", `/runs/${runId}/prompts/${encodeURIComponent(id)}`, { answer: button.dataset.answer || "done" });
        dropPrompt(id);
      } catch (e) {
        cc.setText("control-error", e.message);
        button.disabled = false;
      }
    });
  }

  // ------------------------------------------------------------------------------ controls
  async function request(state) {
    cc.setText("control-error", "");
    try {
      const r = await cc.api("PUT", `/runs/${runId}/state`, { state });
      if (state === "paused" && r && r.pause_requested) setPauseRequested(true);
      if (state === "running") setPauseRequested(false);
    } catch (e) {
      cc.setText("control-error", e.message);
    }
  }
  for (const [id, state] of [["pause", "paused"], ["resume", "running"], ["abort", "aborted"]]) {
    const b = document.getElementById(id);
    if (b) b.addEventListener("click", () => request(state));
  }

  // ---------------------------------------------------------------------------- the end
  function end(state) {
    if (ended) return;
    ended = true;
    if (source) source.close();
    if (stopFallback) stopFallback();
    if (stopSamples) stopSamples();
    setState(state);
    if (state === "completed") setProgress({ percent: 100, left_s: 0, left_wall_s: 0 });
    // the results (tables, curves, verdicts) are rendered by the server: show them
    setTimeout(() => window.location.reload(), 400);
  }

  // ------------------------------------------------------------------ server-sent events
  function onEvent(kind, handler) {
    source.addEventListener(kind, (ev) => {
      let data = {};
      try { data = JSON.parse(ev.data); } catch (e) { return; }
      handler(data);
    });
  }

  function startEvents() {
    if (typeof EventSource === "undefined") { startFallback(); return; }
    source = new EventSource(`/runs/${runId}/events`, { withCredentials: true });
    onEvent("state", (d) => {
      if (!d.state) return;
      if (FINAL.includes(d.state)) { end(d.state); return; }
      setState(d.state);
      refreshUnits();
    });
    onEvent("progress", setProgress);
    onEvent("step", (d) => {
      const s = d.step;
      const t = describeStep(d);
      // a checkpoint only marks where a pause may hold: the step field keeps the step done before it
      // (as the server renders it: web.py step_view)
      if (t && !(s && s.kind === "checkpoint")) cc.setText("step", t);
      if (s && s.kind === "acquire" && s.step) setLiveStep(String(s.step));
    });
    onEvent("samples", (d) => { if (typeof d.count === "number") cc.setText("samples", String(d.count)); });
    onEvent("prompt", (d) => { if (d.answered) dropPrompt(d.id); else showPrompt(d.id, d.text || ""); });
    source.onerror = () => {
      // CONNECTING: the browser reconnects by itself (resuming after the last event id);
      // CLOSED: it gave up, so follow the run by polling instead
      if (source && source.readyState === EventSource.CLOSED && !ended) startFallback();
    };
  }

  function startFallback() {
    if (stopFallback) return;
    stopFallback = cc.poll(async () => {
      const run = await cc.api("GET", `/runs/${runId}`);
      if (FINAL.includes(run.status)) { end(run.status); return false; }
      setState(run.status);
      setPauseRequested(Boolean(run.pause_requested));
      setProgress(run.progress);
      showUnits(run.serials);
      syncPrompts(run.prompts);
      return true;
    }, 2000);
  }

  // ------------------------------------------------------------------------ live plot
  const plot = document.getElementById("live-plot");
  const SVG = "http://www.w3.org/2000/svg";
  const MOVING = { rotate_z: 0, level: 0, sweep_y: 1, sweep_x: 2 };
  const ANGLE_NAMES = ["ψ_t (table azimuth)", "θ_t (middle axis)", "φ_t (inner axis)"];
  const COLORS = ["#d62728", "#2ca02c", "#1f77b4"];
  let rows = [];   // [step, psi, theta, phi, mx, my, mz] of the newest step fetched only
  let lastId = 0;
  // the step the run acquires now (its step events); its samples arrive only after its first pose,
  // so until then the plot waits for them rather than go on showing the step before
  let liveStep = root.dataset.liveStep || null;

  function setLiveStep(label) {
    if (label === liveStep) return;
    liveStep = label;
    cc.setText("live-caption", `(slot 0, step ${label})`);
    draw();
  }

  function svg(tag, attrs, text) {
    const e = document.createElementNS(SVG, tag);
    for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, String(v));
    if (text !== undefined) e.textContent = text;
    return e;
  }

  function movingAxis(step) {
    if (step in MOVING) return MOVING[step];
    let best = 0, span = -1;
    for (let j = 0; j < 3; j++) {
      const v = rows.map((r) => r[1 + j]);
      const s = Math.max(...v) - Math.min(...v);
      if (s > span) { span = s; best = j; }
    }
    return best;
  }

  function niceTicks(lo, hi, n) {
    const step0 = (hi - lo) / Math.max(1, n);
    const mag = Math.pow(10, Math.floor(Math.log10(step0)));
    const step = [1, 2, 5, 10].map((f) => f * mag).find((s) => s >= step0) || step0;
    const out = [];
    for (let v = Math.ceil(lo / step) * step; v <= hi + 1e-9; v += step) out.push(Math.abs(v) < 1e-9 ? 0 : v);
    return out;
  }

  function draw() {
    if (!plot) return;
    plot.replaceChildren();
    const W = 720, H = 300, L = 70, R = 110, T = 28, B = 42;
    if (!rows.length || (liveStep && rows[rows.length - 1][0] !== liveStep)) {
      const what = liveStep ? `waiting for the samples of step ${liveStep}…` : "waiting for samples…";
      plot.append(svg("text", { x: W / 2, y: H / 2, "text-anchor": "middle" }, what));
      return;
    }
    const step = rows[rows.length - 1][0];
    const axis = movingAxis(step);
    // average each pose (all samples at one angle): the curve shape, not the noise
    const poses = new Map();
    for (const r of rows) {
      const key = r[1 + axis].toFixed(2);
      const p = poses.get(key) || { x: r[1 + axis], n: 0, m: [0, 0, 0] };
      p.n += 1;
      for (let j = 0; j < 3; j++) p.m[j] += r[4 + j];
      poses.set(key, p);
    }
    const pts = [...poses.values()].map((p) => ({ x: p.x, m: p.m.map((v) => v / p.n) })).sort((a, b) => a.x - b.x);
    let x0 = Math.min(...pts.map((p) => p.x)), x1 = Math.max(...pts.map((p) => p.x));
    if (x1 - x0 < 1) { x0 -= 5; x1 += 5; }
    const ys = pts.flatMap((p) => p.m);
    let y0 = Math.min(...ys), y1 = Math.max(...ys);
    const pad = (y1 - y0) * 0.08 || 10;
    y0 -= pad; y1 += pad;
    const sx = (x) => L + ((x - x0) / (x1 - x0)) * (W - L - R);
    const sy = (y) => H - B - ((y - y0) / (y1 - y0)) * (H - T - B);
    plot.append(svg("rect", { x: L, y: T, width: W - L - R, height: H - T - B, fill: "none", stroke: "#999" }));
    for (const t of niceTicks(x0, x1, 8)) {
      plot.append(svg("line", { x1: sx(t), x2: sx(t), y1: T, y2: H - B, stroke: "#eee" }));
      plot.append(svg("text", { x: sx(t), y: H - B + 14, "text-anchor": "middle" }, String(Math.round(t * 10) / 10)));
    }
    for (const t of niceTicks(y0, y1, 6)) {
      plot.append(svg("line", { x1: L, x2: W - R, y1: sy(t), y2: sy(t), stroke: "#eee" }));
      plot.append(svg("text", { x: L - 6, y: sy(t) + 4, "text-anchor": "end" }, String(Math.round(t))));
    }
    plot.append(svg("text", { x: (L + W - R) / 2, y: H - 6, "text-anchor": "middle" }, `${ANGLE_NAMES[axis]} (deg)`));
    plot.append(svg("text", { x: 14, y: (T + H - B) / 2, "text-anchor": "middle", transform: `rotate(-90 14 ${(T + H - B) / 2})` }, "raw reading (LSB)"));
    plot.append(svg("text", { x: L, y: T - 10 }, `step ${step}: ${pts.length} poses, ${rows.length} samples`));
    ["mx", "my", "mz"].forEach((name, j) => {
      const d = pts.map((p) => `${sx(p.x).toFixed(1)},${sy(p.m[j]).toFixed(1)}`).join(" ");
      plot.append(svg("polyline", { points: d, fill: "none", stroke: COLORS[j], "stroke-width": 1.5 }));
      for (const p of pts) plot.append(svg("circle", { cx: sx(p.x).toFixed(1), cy: sy(p.m[j]).toFixed(1), r: 2.5, fill: COLORS[j] }));
      plot.append(svg("line", { x1: W - R + 12, x2: W - R + 32, y1: T + 12 + 18 * j, y2: T + 12 + 18 * j, stroke: COLORS[j], "stroke-width": 2 }));
      plot.append(svg("text", { x: W - R + 38, y: T + 16 + 18 * j }, name));
    });
  }

  function startSamples() {
    if (!plot) return;
    draw();
    stopSamples = cc.poll(async () => {
      for (let i = 0; i < 20; i++) {  // catch up in pieces when a long run's page is opened late
        const d = await cc.api("GET", `/ui/runs/${runId}/samples.json?slot=0&after=${lastId}`);
        for (const r of d.rows) {
          if (rows.length && rows[rows.length - 1][0] !== r[0]) rows = [];  // a new step: a new plot
          rows.push(r);
        }
        lastId = d.last;
        if (!d.more) break;
      }
      draw();
      return !ended;
    }, 2000, 0);
  }

  setButtons();
  if (root.dataset.active === "true") {
    const left = parseFloat((document.getElementById("time-left") || {}).dataset?.leftWallS);
    if (isFinite(left)) setProgress({ left_wall_s: left });
    startEvents();
    startSamples();
  }
})();
