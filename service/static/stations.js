/* Stations page: start runs (operators), and keep each station's state fresh. */
"use strict";

(() => {
  const table = document.getElementById("stations");
  if (!table) return;

  const rowOf = (name) => {
    for (const tr of table.querySelectorAll("tr[data-station]")) if (tr.dataset.station === name) return tr;
    return null;
  };

  for (const form of document.querySelectorAll("form.start-run")) {
    const error = form.querySelector(".error");
    form.addEventListener("submit", async (ev) => {
      ev.preventDefault();
      const button = form.querySelector("button.start");
      const station = form.dataset.station;
      const procedure = form.elements.procedure ? form.elements.procedure.value : "calibrate";
      const parameters = {};
      const samples = form.elements.samples ? form.elements.samples.value.trim() : "";
      if (samples) parameters.samples = parseInt(samples, 10);
      // per slot, optional: a slot left empty is named by its compass's own serial number
      const serials = {};
      for (const input of form.querySelectorAll("input.serial")) {
        const v = input.value.trim();
        if (v) serials[input.dataset.slot] = v;
      }
      const body = { station, procedure, parameters };
      if (Object.keys(serials).length) body.serials = serials;
      if (error) error.textContent = "";
      if (button) button.disabled = true;
      try {
        const run = await cc.api("POST", "/runs", body);
        window.location.href = `/ui/runs/${run.id}`;
      } catch (e) {
        if (error) error.textContent = e.message;
        if (button) button.disabled = false;
      }
    });
    const reset = form.querySelector("button.reset");
    if (reset) {
      reset.addEventListener("click", async () => {
        reset.disabled = true;
        if (error) error.textContent = "";
        try {
          const st = await cc.api("POST", `/stations/${encodeURIComponent(form.dataset.station)}/reset`);
          update(st);
        } catch (e) {
          if (error) error.textContent = e.message;
        } finally {
          reset.disabled = false;
        }
      });
    }
  }

  function update(st) {
    const tr = rowOf(st.name);
    if (!tr) return;
    const state = tr.querySelector("td.state");
    if (state) {
      state.textContent = st.state;
      state.className = `state state-${st.state}`;
    }
    const run = tr.querySelector("td.run");
    if (run) {
      run.replaceChildren();
      if (st.run_id) run.append(cc.el("a", { className: "run-link", href: `/ui/runs/${st.run_id}` }, `run ${st.run_id}`), " ");
      if (st.batch_id) run.append(cc.el("a", { className: "batch-link", href: `/ui/batches/${st.batch_id}` }, `batch ${st.batch_id}`), " ");
      run.append(cc.el("span", { className: "fault" }, st.fault || ""));
    }
    const start = tr.querySelector("button.start");
    if (start) start.disabled = st.state !== "idle" || Boolean(st.batch_id);
    const reset = tr.querySelector("button.reset");
    if (reset) reset.hidden = st.state !== "fault";
  }

  cc.poll(async () => {
    if (document.hidden) return true;
    const stations = await cc.api("GET", "/stations");
    for (const st of stations) update(st);
    return true;
  }, 2000);
})();
