/* compasscal pages: small helpers shared by the page scripts (no dependencies, no network but this server). */
"use strict";

const cc = {
  /** Call the JSON API with the browser session's cookie; resolves to the decoded body, rejects with an
   *  Error whose message is the API's detail (status in err.status). */
  async api(method, url, body) {
    const opt = { method, credentials: "same-origin", headers: { Accept: "application/json" } };
    if (body !== undefined) {
      opt.headers["Content-Type"] = "application/json";
      opt.body = JSON.stringify(body);
    }
    const r = await fetch(url, opt);
    const text = await r.text();
    let data = null;
    try { data = text ? JSON.parse(text) : null; } catch (e) { data = text; }
    if (!r.ok) {
      const err = new Error(cc.detail(data) || `${r.status} ${r.statusText}`);
      err.status = r.status;
      throw err;
    }
    return data;
  },

  /** The API's error detail as one line: a string, or [{field, problem}] from a 422. */
  detail(data) {
    if (!data || typeof data !== "object") return typeof data === "string" ? data : "";
    const d = data.detail;
    if (Array.isArray(d)) return d.map((e) => (e && e.field ? `${e.field}: ${e.problem}` : JSON.stringify(e))).join("; ");
    return d ? String(d) : "";
  },

  /** Seconds as "1 h 02 min", "3 min 07 s" or "12 s". */
  duration(s) {
    if (s === null || s === undefined || !isFinite(s)) return "-";
    s = Math.max(0, Math.round(s));
    const h = Math.floor(s / 3600), m = Math.floor((s % 3600) / 60), sec = s % 60;
    if (h) return `${h} h ${String(m).padStart(2, "0")} min`;
    if (m) return `${m} min ${String(sec).padStart(2, "0")} s`;
    return `${sec} s`;
  },

  /** Set an element's text if it exists (pages differ by role: an element may be absent). */
  setText(id, text) {
    const el = document.getElementById(id);
    if (el) el.textContent = text;
    return el;
  },

  /** A new element with attributes and text. */
  el(tag, attrs, text) {
    const e = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) {
      if (v === null || v === undefined || v === false) continue;
      if (k === "className") e.className = v; else e.setAttribute(k, v === true ? "" : v);
    }
    if (text !== undefined && text !== null) e.textContent = text;
    return e;
  },

  /** The answer buttons of operator prompt `id`: a serial prompt (serial-SLOT: a unit reporting another
   *  serial than the one typed) takes typed, identified or skip (data-answer); any other prompt, Done. */
  answerButtons(id, attrs) {
    const answers = id.startsWith("serial-") ? ["typed", "identified", "skip"] : [null];
    return answers.map((a) => cc.el("button", { type: "button", className: "answer", "data-prompt": id, "data-answer": a,
                                                ...(attrs || {}) }, a || "Done"));
  },

  /** Repeat fn every ms milliseconds (the first time after `first` ms, default ms), never overlapping,
   *  until it returns false; a failure is logged as a warning (a poll may fail while the service
   *  restarts) and retried. Returns a function that stops it. */
  poll(fn, ms, first) {
    let stopped = false;
    const tick = async () => {
      if (stopped) return;
      let again = true;
      try { again = (await fn()) !== false; } catch (e) { console.warn("poll:", e && e.message ? e.message : e); }
      if (again && !stopped) setTimeout(tick, ms);
    };
    setTimeout(tick, first === undefined ? ms : first);
    return () => { stopped = true; };
  },
};

document.addEventListener("click", (ev) => {
  const t = ev.target;
  if (t instanceof Element && t.closest("[data-print]")) window.print();
});
