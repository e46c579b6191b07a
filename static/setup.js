// mazebot setup view: the raw lidar revolution as a polar plot (D3), the wheels, hold-to-run jog buttons,
// the doctor's checks (mazebot/web/setup.py) and the calibration (mazebot/web/calibration.py). Jogging is
// made safe on the server: a jog is a request that goes stale after the motors' command time-to-live, so
// this page re-sends it while a button is held. A calibration runs on the robot; this page polls it, and
// the robot stops it when the polls stop (a lost connection, a closed page).
(function () {
  "use strict";
  const PIN_KEY = "mazebot.pin"; // the same PIN the start/stop button remembers (app.js)
  const JOG_RESEND_MS = 100;
  const POLL_MS = 200;
  const $ = (id) => document.getElementById(id);
  const view = $("setup");
  const pinInput = $("setup-pin");
  let poll = null;
  let jogTimer = null;
  let maxThrottle = 0.4;

  function loadPin() { try { return localStorage.getItem(PIN_KEY) || ""; } catch { return ""; } }
  function savePin(pin) { try { localStorage.setItem(PIN_KEY, pin); } catch { /* private mode */ } }

  function open() {
    view.hidden = false;
    pinInput.value = pinInput.value || loadPin();
    refresh();
    poll = setInterval(refresh, POLL_MS);
    pollCalibration();
  }
  function close() {
    stopJog();
    view.hidden = true;
    clearInterval(poll);
    poll = null;
  }

  async function refresh() {
    let data;
    try {
      const resp = await fetch("/api/setup", { cache: "no-store" });
      if (!resp.ok) return;
      data = await resp.json();
    } catch { return; }
    maxThrottle = data.jog_max_throttle;
    const e = data.encoders;
    const [vl, vr] = data.wheel_speeds_mps;
    $("setup-wheels").textContent =
      `encoders L ${e.left_ticks} R ${e.right_ticks} · wheels ${vl.toFixed(2)} / ${vr.toFixed(2)} m/s`;
    view.dataset.jog = data.jog_refused ? "refused" : "allowed";
    if (data.jog_refused && !jogTimer) $("jog-status").textContent = data.jog_refused;
    drawScan(data.scan);
  }

  function drawScan(scan) {
    const svg = d3.select("#polar");
    if (!scan) { $("setup-scan").textContent = "no revolution from the lidar yet"; return; }
    const far = Math.max(0.5, d3.max(scan.range_m) || 0.5);
    const r = d3.scaleLinear().domain([0, far]).range([0, 100]);
    const rings = d3.ticks(0, far, 4).filter((m) => m > 0);
    svg.selectAll("circle.ring").data(rings).join("circle").attr("class", "ring").attr("r", (m) => r(m));
    // robot frame, angles counter-clockwise from straight ahead: ahead is up on the screen
    const pts = scan.angle_rad.map((a, i) => [-Math.sin(a) * r(scan.range_m[i]), -Math.cos(a) * r(scan.range_m[i])]);
    svg.selectAll("circle.hit").data(pts).join("circle").attr("class", "hit").attr("r", 1.1)
      .attr("cx", (p) => p[0]).attr("cy", (p) => p[1]);
    $("setup-scan").textContent =
      `revolution ${scan.revolution}: ${scan.valid} of ${scan.samples} samples valid, farthest ${far.toFixed(2)} m`;
  }

  // One jog request at a time, each sent after the answer to the one before: with several connections
  // a browser may deliver two requests in either order, and a drive request overtaking the release's
  // zero would drive the wheels for another time-to-live after the button was let go.
  let jogChain = Promise.resolve(true);
  let jogBusy = false;
  function sendJog(left, right) {
    jogChain = jogChain.then(() => postJog(left, right));
    return jogChain;
  }

  async function postJog(left, right) {
    jogBusy = true;
    try { return await postJogNow(left, right); } finally { jogBusy = false; }
  }

  async function postJogNow(left, right) {
    const pin = pinInput.value;
    try {
      const resp = await fetch("/api/jog", {
        method: "POST", headers: { "Content-Type": "application/json", "X-Mazebot-Token": pin },
        body: JSON.stringify({ left, right }),
      });
      const body = await resp.json();
      if (resp.ok) { savePin(pin); return true; }
      $("jog-status").textContent = body.error || `refused (${resp.status})`;
    } catch { $("jog-status").textContent = "no connection to the robot"; }
    stopJog(false);
    return false;
  }

  function startJog(button) {
    stopJog(false);
    const [l, r] = button.dataset.jog.split(",").map(Number);
    const left = l * maxThrottle * 0.75, right = r * maxThrottle * 0.75;
    button.classList.add("held");
    $("jog-status").textContent = "driving: release to stop";
    sendJog(left, right);
    jogTimer = setInterval(() => { if (!jogBusy) sendJog(left, right); }, JOG_RESEND_MS);
  }
  function stopJog(sendZero = true) {
    const was = jogTimer !== null;
    clearInterval(jogTimer);
    jogTimer = null;
    document.querySelectorAll(".jog button.held").forEach((b) => b.classList.remove("held"));
    if (sendZero && was) {
      sendJog(0, 0);
      $("jog-status").textContent = "stopped";
    }
  }

  async function runDoctor() {
    const list = $("doctor");
    list.textContent = "";
    try {
      const resp = await fetch("/api/doctor", { cache: "no-store" });
      const body = await resp.json();
      for (const c of body.checks) {
        const li = document.createElement("li");
        li.dataset.status = c.status;
        const b = document.createElement("b");
        b.textContent = c.status;
        li.append(b, ` ${c.part}: ${c.detail}${c.action && c.status !== "ok" ? " → " + c.action : ""}`);
        list.append(li);
      }
    } catch { list.textContent = "no connection to the robot"; }
  }

  // --- calibration --------------------------------------------------------------------------------------
  const CALIB_POLL_MS = 500; // the robot stops a calibration whose page is silent for 3 s (on_daemon.py)
  let calibId = null;
  let calibTimer = null;

  async function calibPost(path, body) {
    const pin = pinInput.value;
    try {
      const resp = await fetch(path, {
        method: "POST", headers: { "Content-Type": "application/json", "X-Mazebot-Token": pin },
        body: JSON.stringify(body || {}),
      });
      const data = await resp.json();
      if (resp.ok) savePin(pin);
      else $("calib-status").textContent = data.error || `refused (${resp.status})`;
      return resp.ok ? data : null;
    } catch {
      $("calib-status").textContent = "no connection to the robot";
      return null;
    }
  }

  function renderCalibration(run) {
    const box = $("calib");
    box.dataset.status = run ? run.status : "idle";
    const running = !!run && run.status === "running";
    $("calib-start").hidden = running;
    $("calib-stop").hidden = !running;
    if (!run) return;
    const list = $("calib-steps");
    list.textContent = "";
    run.steps.forEach((step) => {
      const li = document.createElement("li");
      li.dataset.step = step.name;
      li.dataset.state = step.state;
      const b = document.createElement("b");
      b.textContent = step.state;
      li.append(b, ` ${step.title}`);
      const figures = Object.entries(step.measured)
        .filter(([, v]) => typeof v === "number")
        .map(([k, v]) => `${k} ${v}`).join(", ");
      const detail = [step.detail, figures].filter(Boolean).join(" · ");
      if (detail) {
        const small = document.createElement("small");
        small.textContent = detail;
        li.append(small);
      }
      list.append(li);
    });
    const done = run.steps.filter((s) => s.state === "done").length;
    const status = {
      running: `step ${Math.min(done + 1, run.steps.length)} of ${run.steps.length}: keep clear of the robot`,
      done: run.diff.length ? "finished: check the changes, then write them" : run.reason,
      failed: `failed in step ${run.failed_step || "?"}: nothing was written`,
      stopped: `stopped (${run.reason}): the motors are off, nothing was written`,
      written: run.reason,
    }[run.status];
    $("calib-status").textContent = status || run.status;
    const rows = $("calib-diff-rows");
    rows.textContent = "";
    for (const d of run.diff) {
      const tr = document.createElement("tr");
      for (const text of [d.key, JSON.stringify(d.old), "→", JSON.stringify(d.new)]) {
        const td = document.createElement("td");
        td.textContent = text;
        tr.append(td);
      }
      rows.append(tr);
    }
    const finished = run.status === "done" || run.status === "written";
    $("calib-diff").hidden = !finished || run.diff.length === 0;
    $("calib-write").hidden = run.status !== "done" || run.diff.length === 0;
    const png = $("calib-png");
    if (finished && png.hidden) { png.src = `/api/calibration.png?id=${encodeURIComponent(run.id || "")}`; }
    png.hidden = !finished;
  }

  async function pollCalibration() {
    try {
      const resp = await fetch(`/api/calibration?id=${encodeURIComponent(calibId || "")}`, { cache: "no-store" });
      if (!resp.ok) return;
      const body = await resp.json();
      if (!body.available) { $("calib-start").disabled = true; $("calib-status").textContent = body.why; return; }
      renderCalibration(body.run);
      if (!body.run || body.run.status !== "running") { clearInterval(calibTimer); calibTimer = null; }
    } catch { $("calib-status").textContent = "no connection to the robot"; }
  }

  function followCalibration() {
    clearInterval(calibTimer);
    calibTimer = setInterval(pollCalibration, CALIB_POLL_MS);
  }

  async function startCalibration() {
    $("calib-png").hidden = true;
    const run = await calibPost("/api/calibration");
    if (!run) return;
    calibId = run.id;
    renderCalibration(run);
    followCalibration();
  }

  async function writeCalibration() {
    const run = await calibPost("/api/calibration/write", { id: calibId });
    if (run) renderCalibration(run);
  }

  $("calib-start").addEventListener("click", startCalibration);
  $("calib-stop").addEventListener("click", async () => { await calibPost("/api/calibration/stop"); pollCalibration(); });
  $("calib-write").addEventListener("click", writeCalibration);

  $("setup-open").addEventListener("click", open);
  $("setup-close").addEventListener("click", close);
  $("doctor-run").addEventListener("click", runDoctor);
  document.querySelectorAll(".jog button").forEach((button) => {
    button.addEventListener("pointerdown", (ev) => { ev.preventDefault(); startJog(button); });
    for (const end of ["pointerup", "pointercancel", "pointerleave"]) button.addEventListener(end, () => stopJog());
    button.addEventListener("contextmenu", (ev) => ev.preventDefault());
  });
  window.addEventListener("blur", () => stopJog());
  document.addEventListener("visibilitychange", () => { if (document.hidden) stopJog(); });
})();
