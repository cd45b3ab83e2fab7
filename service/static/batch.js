/* Batch page: refresh the units' rows and prompts while the batch runs; answer prompts (operators). */
"use strict";

(() => {
  const root = document.getElementById("batch");
  if (!root) return;
  const batchId = root.dataset.batchId;
  const isOperator = root.dataset.operator === "true";
  const prompts = document.getElementById("prompts");
  const DONE = ["completed", "failed", "aborted"];

  function rowOf(serial) {
    for (const tr of document.querySelectorAll("#units tr[data-serial]")) if (tr.dataset.serial === serial) return tr;
    return null;
  }

  function update(b) {
    const st = document.getElementById("batch-status");
    if (st) { st.textContent = b.status; st.className = `status-${b.status}`; }
    let done = 0;
    for (const u of b.units) {
      if (DONE.includes(u.status)) done += 1;
      const tr = rowOf(u.serial);
      if (!tr) continue;
      const run = tr.querySelector("td.run");
      if (run) {
        run.replaceChildren();
        if (u.run_id) run.append(cc.el("a", { href: `/ui/runs/${u.run_id}` }, `run ${u.run_id}`));
      }
      const statusText = u.status + (u.reason ? `: ${u.reason}` : "");
      const status = tr.querySelector("td.status");
      if (status) {
        status.textContent = statusText;
        status.className = `status status-${u.status}`;
      }
      const verdict = tr.querySelector("td.verdict");
      if (verdict) {
        const over = DONE.includes(u.status) || !["queued", "running"].includes(b.status);
        const said = over ? (b.summary || {})[u.serial] || "" : "";
        // the summary's line of a unit whose run ended without a verdict repeats its status cell: said once
        const v = u.verdict || (said === statusText ? "" : said);
        verdict.textContent = v;
        verdict.className = `verdict verdict-${(u.verdict || "").toLowerCase()}`;
      }
      const ident = tr.querySelector("td.identified");
      if (ident) {  // what the mounted unit reported, and how it compared with the serial typed
        const how = u.identification && u.identification !== "identified" ? ` (${u.identification})` : "";
        ident.textContent = u.identified_serial ? u.identified_serial + how : (u.identification || "");
      }
      const tableS = tr.querySelector("td.table-s");
      if (tableS) tableS.textContent = u.table_seconds ? `${Math.round(u.table_seconds)} s` : "";
      const target = tr.querySelector("td.target");
      if (target) target.textContent = u.target || "";
      const cert = tr.querySelector("td.cert");
      if (cert) {
        cert.replaceChildren();
        if (u.calibration_id) cert.append(cc.el("a", { className: "certificate", href: `/ui/calibrations/${u.calibration_id}/certificate` }, "certificate"));
      }
    }
    cc.setText("batch-progress", `${done} of ${b.units.length} units done`);
    cc.setText("batch-tally", Object.entries(b.tally || {}).filter(([k, n]) => n && k !== "pending").map(([k, n]) => `${n} ${k}`).join(", "));
    const bar = document.getElementById("batch-bar");
    if (bar) bar.value = done;
    if (prompts) {
      const want = b.units.flatMap((u) => (u.prompts || []).map((p) => ({ run: u.run_id, ...p })));
      const key = (run, id) => `${run}/${id}`;
      const keep = new Set(want.map((p) => key(p.run, p.id)));
      for (const div of prompts.querySelectorAll(".prompt")) if (!keep.has(key(div.dataset.run, div.dataset.prompt))) div.remove();
      for (const p of want) {
        const exists = [...prompts.querySelectorAll(".prompt")].some((d) => d.dataset.run === String(p.run) && d.dataset.prompt === p.id);
        if (exists) continue;
        const div = cc.el("div", { className: "prompt", "data-run": p.run, "data-prompt": p.id });
        div.append(cc.el("span", { className: "prompt-text" }, p.text));
        if (isOperator) for (const b of cc.answerButtons(p.id, { "data-run": p.run })) div.append(" ", b);
        div.append(" ", cc.el("a", { href: `/ui/runs/${p.run}` }, `run ${p.run}`));
        prompts.append(div);
      }
    }
  }

  if (prompts) {
    prompts.addEventListener("click", async (ev) => {
      const button = ev.target instanceof Element ? ev.target.closest("button.answer") : null;
      if (!button) return;
      button.disabled = true;
      try {
        await cc.api("POST", `/runs/${button.dataset.run}/prompts/${encodeURIComponent(button.dataset.prompt)}`, { answer: button.dataset.answer || "done" });
        const div = button.closest(".prompt");
        if (div) div.remove();
      } catch (e) {
        button.disabled = false;
        button.title = e.message;
      }
    });
  }

  const abort = document.getElementById("abort-batch");
  if (abort) {
    abort.addEventListener("click", async () => {
      if (!window.confirm("Abort the batch: the unit on the table is aborted and no further unit is started?")) return;
      abort.disabled = true;
      try {
        update(await cc.api("PUT", `/batches/${batchId}/state`, { state: "aborted" }));
      } catch (e) {
        abort.disabled = false;
        abort.title = e.message;
      }
    });
  }

  if (root.dataset.active === "true") {
    cc.poll(async () => {
      const b = await cc.api("GET", `/batches/${batchId}`);
      update(b);
      if (abort && b.status !== "running") abort.remove();
      if (!["queued", "running", "aborting"].includes(b.status)) {
        setTimeout(() => window.location.reload(), 400);
        return false;
      }
      return true;
    }, 2000);
  }
})();
