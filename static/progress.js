// mazebot page, progress: coverage and distance driven over the run as a small D3 chart, and the
// map to keep (a PNG picture; ROS map_server PGM + YAML in one zip). Fed by the status app.js
// merges from every packet ("mazebot:status" events): coverage (0..1), distance_m and elapsed_s
// all come from the robot (docs/protocol.md), the page only keeps a bounded history of them.
"use strict";
(() => {
  const $ = (id) => document.getElementById(id);
  const PIN_KEY = "mazebot.pin"; // where app.js keeps the PIN
  const MAX_POINTS = 300; // samples kept, whatever the run's length: thinned by half when full
  const FIRST_SPACING_S = 0.5; // run time between kept samples at first; doubles at each thinning
  const MARGIN = { left: 30, right: 36, top: 6, bottom: 16 }; // CSS pixels around the plot

  // ---- the history: [elapsed_s, coverage or null, distance_m or null], oldest first -------
  const series = { points: [], spacingS: FIRST_SPACING_S, thinnings: 0, run: 0 };

  function add(status) {
    const t = status.elapsed_s;
    if (t == null) return false;
    let pts = series.points;
    if (pts.length && t < pts[pts.length - 1][0] - 0.5) { // its clock went back: a new exploration
      pts = series.points = [];
      series.spacingS = FIRST_SPACING_S;
      series.run++;
    }
    const p = [t, status.coverage ?? null, status.distance_m ?? null], n = pts.length;
    if (n && pts[n - 1].every((v, i) => v === p[i])) return false;
    // the newest sample moves with the robot until it is a spacing away from the one before it
    if (n >= 2 && t - pts[n - 2][0] < series.spacingS) pts[n - 1] = p; else pts.push(p);
    if (pts.length > MAX_POINTS) { // keep every other sample (and the newest): same span, half the points
      series.points = pts.filter((_, i) => i % 2 === 0 || i === pts.length - 1);
      series.spacingS *= 2;
      series.thinnings++;
    }
    return true;
  }

  // ---- the chart -----------------------------------------------------------------------
  const svg = d3.select("#chart");
  const xAxis = svg.append("g").attr("class", "axis x");
  const covAxis = svg.append("g").attr("class", "axis cov");
  const distAxis = svg.append("g").attr("class", "axis dist");
  const covLine = svg.append("path").attr("class", "line cov");
  const distLine = svg.append("path").attr("class", "line dist");
  const clock = (s) => `${Math.floor(s / 60)}:${String(Math.floor(s % 60)).padStart(2, "0")}`;
  let drawQueued = false;

  function requestDraw() {
    if (!drawQueued) { drawQueued = true; requestAnimationFrame(draw); }
  }

  function draw() {
    drawQueued = false;
    const node = svg.node(), w = Math.max(node.clientWidth, 120), h = Math.max(node.clientHeight, 40);
    const pts = series.points, last = pts[pts.length - 1];
    const x = d3.scaleLinear([0, Math.max(60, last ? last[0] : 0)], [MARGIN.left, w - MARGIN.right]);
    const yCov = d3.scaleLinear([0, 1], [h - MARGIN.bottom, MARGIN.top]);
    const yDist = d3.scaleLinear([0, Math.max(1, d3.max(pts, (p) => p[2]) || 0)], [h - MARGIN.bottom, MARGIN.top]).nice(3);
    xAxis.attr("transform", `translate(0,${h - MARGIN.bottom})`)
      .call(d3.axisBottom(x).ticks(Math.max(2, Math.floor(w / 90))).tickFormat(clock).tickSizeOuter(0));
    covAxis.attr("transform", `translate(${MARGIN.left},0)`)
      .call(d3.axisLeft(yCov).tickValues([0, 0.5, 1]).tickFormat(d3.format(".0%")).tickSizeOuter(0));
    distAxis.attr("transform", `translate(${w - MARGIN.right},0)`)
      .call(d3.axisRight(yDist).ticks(3).tickFormat((v) => `${v} m`).tickSizeOuter(0));
    covLine.attr("d", d3.line().defined((p) => p[1] != null).x((p) => x(p[0])).y((p) => yCov(p[1]))(pts));
    distLine.attr("d", d3.line().defined((p) => p[2] != null).x((p) => x(p[0])).y((p) => yDist(p[2]))(pts));
    describe(last);
  }

  function setText(el, text) { if (el.textContent !== text) el.textContent = text; }

  function describe(last) {
    const cov = last && last[1] != null ? `${Math.round(100 * last[1])} %` : "–";
    const dist = last && last[2] != null ? `${last[2].toFixed(1)} m` : "–";
    setText($("legend-coverage"), `coverage ${cov}`);
    setText($("legend-distance"), `distance ${dist}`);
    const label = last ? `coverage ${cov} and ${dist} driven after ${clock(last[0])} of the run`
      : "coverage and distance over time: no run yet";
    if ($("chart").getAttribute("aria-label") !== label) $("chart").setAttribute("aria-label", label);
  }

  document.addEventListener("mazebot:status", (ev) => { if (add(ev.detail)) requestDraw(); });
  new ResizeObserver(requestDraw).observe($("chart"));

  // ---- download the map: fetched, so an error is said in words, and saved under the robot's name
  function filenameOf(disposition) {
    const m = /filename="([^"]+)"/.exec(disposition || "");
    return m ? m[1] : null;
  }

  async function save(path, fallbackName) {
    const msg = $("save-msg");
    msg.textContent = "reading the map…";
    let pin = null;
    try { pin = localStorage.getItem(PIN_KEY); } catch { /* private mode */ }
    try {
      const resp = await fetch(path, { cache: "no-store", headers: pin ? { "X-Mazebot-Token": pin } : {} });
      if (!resp.ok) {
        const body = await resp.json().catch(() => ({}));
        msg.textContent = body.error || `the robot answered ${resp.status}`;
        return;
      }
      const name = filenameOf(resp.headers.get("Content-Disposition")) || fallbackName;
      const url = URL.createObjectURL(await resp.blob());
      const a = Object.assign(document.createElement("a"), { href: url, download: name });
      document.body.append(a);
      a.click();
      a.remove();
      setTimeout(() => URL.revokeObjectURL(url), 60_000);
      msg.textContent = `saved ${name}`;
      saved.push(name);
    } catch (err) {
      msg.textContent = "robot unreachable";
    }
  }
  const saved = [];
  $("save-png").addEventListener("click", () => save("/map.png?download", "mazebot-map.png"));
  $("save-ros").addEventListener("click", () => save("/map.zip", "mazebot-map.zip"));

  // for tests and the curious, next to app.js' window.mazebot
  const api = { series, saved, points: () => series.points.map((p) => p.slice()), draw };
  if (window.mazebot) window.mazebot.progress = api; else window.mazebotProgress = api;
  requestDraw();
})();
