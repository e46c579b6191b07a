// mazebot setup view: the raw lidar revolution as a polar plot (D3), the wheels, hold-to-run jog buttons
// and the doctor's checks (mazebot/web/setup.py). Jogging is made safe on the server: a jog is a request
// that goes stale after the motors' command time-to-live, so this page re-sends it while a button is held.
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

  async function sendJog(left, right) {
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
    jogTimer = setInterval(() => sendJog(left, right), JOG_RESEND_MS);
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
