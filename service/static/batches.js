/* Batches page: start a batch (operators) through the JSON API, then follow it on its own page. */
"use strict";

(() => {
  const form = document.getElementById("start-batch");
  if (!form) return;
  const error = form.querySelector(".error");
  form.addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const button = form.querySelector("button.start");
    // one serial number per line; blank lines and surrounding spaces are nobody's serial number
    const serials = form.elements.serials.value.split(/\r?\n/).map((s) => s.trim()).filter((s) => s);
    const parameters = {};
    const samples = form.elements.samples.value.trim();
    if (samples) parameters.samples = parseInt(samples, 10);
    if (error) error.textContent = "";
    if (!serials.length) {
      if (error) error.textContent = "give at least one serial number";
      return;
    }
    if (button) button.disabled = true;
    try {
      const batch = await cc.api("POST", "/batches", { station: form.elements.station.value, serials, parameters });
      window.location.href = `/ui/batches/${batch.id}`;
    } catch (e) {
      if (error) error.textContent = e.message;
      if (button) button.disabled = false;
    }
  });
})();
