// mazebot page: the live map over a websocket (docs/protocol.md), start/stop with a PIN.
// The map is an offscreen canvas, one pixel per grid cell, patched by every delta and
// drawn under a d3.zoom transform (pan, pinch-zoom) together with the robot, its
// uncertainty ellipse, the trajectory, the planned path and the goal.
"use strict";
(() => {
  const $ = (id) => document.getElementById(id);
  const PIN_KEY = "mazebot.pin";
  const PROTOCOL = 1;
  const KIND_FULL = 1, KIND_DELTA = 2, SECTION_GRID = 1, SECTION_CELLS = 2;
  // cell code -> RGBA packed as uint32 in the canvas' byte order (little-endian: ABGR)
  const rgba = (r, g, b, a) => ((a << 24) | (b << 16) | (g << 8) | r) >>> 0;
  const CELL_COLORS = new Uint32Array([rgba(0, 0, 0, 0), rgba(248, 248, 244, 255), rgba(24, 27, 33, 255)]);
  const ROBOT_RADIUS_M = 0.07;

  // ---- what we know ----------------------------------------------------------------------
  const view = {
    seq: null, // sequence number of the last packet applied
    epoch: null, // map epoch of the grid we hold
    awaitingFull: true, // after a gap: ignore deltas until a full map arrives
    status: {},
    grid: null, // {rows, cols, res, ox, oy, canvas, ctx, img, px}
    elapsedS: null, elapsedAt: 0,
  };
  const stats = { packets: 0, fulls: 0, deltas: 0, bytes: 0, gaps: 0, resyncs: 0, cells: 0, latencyMs: [] };

  // ---- binary packets --------------------------------------------------------------------
  async function inflate(bytes) {
    const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("deflate"));
    return new Uint8Array(await new Response(stream).arrayBuffer());
  }

  async function onPacket(buf) {
    const head = new DataView(buf);
    if (buf.byteLength < 8 || head.getUint8(0) !== 77 || head.getUint8(1) !== 90) throw new Error("not a mazebot packet");
    if (head.getUint8(2) !== PROTOCOL) throw new Error("protocol version " + head.getUint8(2));
    const kind = head.getUint8(3), seq = head.getUint32(4, true);
    stats.packets++; stats.bytes += buf.byteLength;
    if (kind === KIND_DELTA) {
      if (view.awaitingFull) return; // a full map is on its way
      if (seq !== view.seq + 1) { stats.gaps++; requestResync(); return; }
    }
    const body = await inflate(new Uint8Array(buf, 8));
    const dv = new DataView(body.buffer, body.byteOffset, body.byteLength);
    const jsonLen = dv.getUint32(0, true);
    const status = JSON.parse(new TextDecoder().decode(body.subarray(4, 4 + jsonLen)));
    let off = 4 + jsonLen;
    const section = off < body.byteLength ? dv.getUint8(off) : 0;
    if (kind === KIND_FULL) {
      stats.fulls++;
      view.status = {};
      if (section === SECTION_GRID) {
        const epoch = dv.getUint32(off + 4, true), rows = dv.getUint32(off + 8, true), cols = dv.getUint32(off + 12, true);
        const res = dv.getFloat64(off + 16, true), ox = dv.getFloat64(off + 24, true), oy = dv.getFloat64(off + 32, true);
        off += 40;
        setGrid(epoch, rows, cols, res, ox, oy, body.subarray(off, off + rows * cols));
      } else {
        setGrid(null);
      }
      view.awaitingFull = false;
    } else {
      stats.deltas++;
      if (section === SECTION_CELLS) {
        const epoch = dv.getUint32(off + 4, true), count = dv.getUint32(off + 8, true);
        if (epoch !== view.epoch || !view.grid) { stats.gaps++; requestResync(); return; }
        off += 12;
        const gaps = new DataView(body.buffer, body.byteOffset + off, 4 * count);
        patchGrid(gaps, body.subarray(off + 4 * count, off + 5 * count), count);
      }
    }
    view.seq = seq;
    mergeStatus(status);
    if (status.t_ms) {
      stats.latencyMs.push(Date.now() - status.t_ms);
      if (stats.latencyMs.length > 2000) stats.latencyMs.shift();
    }
    render();
    document.dispatchEvent(new CustomEvent("mazebot:status", { detail: view.status })); // progress.js
  }

  function mergeStatus(status) {
    for (const [key, value] of Object.entries(status)) {
      if (key === "trail+") {
        const trail = (view.status.trail = (view.status.trail || []).concat(value));
        if (trail.length > 20000) trail.splice(0, trail.length - 20000);
      } else {
        view.status[key] = value;
      }
    }
    if ("elapsed_s" in status) { view.elapsedS = status.elapsed_s; view.elapsedAt = performance.now(); }
  }

  // ---- the map image: one pixel per cell, north up -----------------------------------------
  function setGrid(epoch, rows, cols, res, ox, oy, codes) {
    if (epoch === null) { view.grid = null; view.epoch = null; return; }
    let g = view.grid;
    if (!g || g.rows !== rows || g.cols !== cols) {
      const canvas = document.createElement("canvas");
      canvas.width = cols; canvas.height = rows;
      const ctx = canvas.getContext("2d");
      const img = ctx.createImageData(cols, rows);
      g = { rows, cols, canvas, ctx, img, px: new Uint32Array(img.data.buffer) };
    }
    Object.assign(g, { res, ox, oy, known: null });
    for (let r = 0; r < rows; r++) { // wire row 0 is south; image row 0 is north
      const src = r * cols, dst = (rows - 1 - r) * cols;
      for (let c = 0; c < cols; c++) {
        const code = codes[src + c];
        g.px[dst + c] = CELL_COLORS[code];
        if (code) growKnown(g, r, c);
      }
    }
    g.ctx.putImageData(g.img, 0, 0);
    view.grid = g; view.epoch = epoch;
    if (autoFit) fitSoon();
  }

  // the known part of the map (cells, wire rows), for fitting the view to what matters
  function growKnown(g, r, c) {
    const k = g.known;
    if (!k) { g.known = { r0: r, r1: r, c0: c, c1: c }; return true; }
    let grew = false;
    if (r < k.r0) { k.r0 = r; grew = true; } else if (r > k.r1) { k.r1 = r; grew = true; }
    if (c < k.c0) { k.c0 = c; grew = true; } else if (c > k.c1) { k.c1 = c; grew = true; }
    return grew;
  }

  function patchGrid(gaps, codes, count) {
    const g = view.grid;
    let idx = 0, x0 = g.cols, y0 = g.rows, x1 = -1, y1 = -1;
    for (let i = 0; i < count; i++) {
      idx += gaps.getUint32(4 * i, true);
      const r = Math.floor(idx / g.cols), c = idx - r * g.cols, y = g.rows - 1 - r;
      g.px[y * g.cols + c] = CELL_COLORS[codes[i]];
      if (c < x0) x0 = c; if (c > x1) x1 = c; if (y < y0) y0 = y; if (y > y1) y1 = y;
      if (codes[i] && growKnown(g, r, c) && autoFit) fitSoon();
    }
    stats.cells += count;
    if (x1 >= 0) g.ctx.putImageData(g.img, 0, 0, x0, y0, x1 - x0 + 1, y1 - y0 + 1);
  }

  // ---- the websocket ---------------------------------------------------------------------
  // the folder the page was served from: "/" on the robot, "/robot/<name>/" on `mazebot watch`
  const BASE = location.pathname.replace(/[^/]*$/, "");
  let ws = null, retryMs = 500, lastMessageAt = 0, heartbeatS = 10, chain = Promise.resolve(), lastResyncAt = 0;
  let viewToken = false; // the server wants the PIN even to watch

  function connect() {
    setConn("connecting");
    const pin = viewToken ? loadPin() : null;
    const url = (location.protocol === "https:" ? "wss://" : "ws://") + location.host + BASE + "ws" +
      (pin ? "?token=" + encodeURIComponent(pin) : "");
    const sock = new WebSocket(url);
    sock.binaryType = "arraybuffer";
    ws = sock;
    view.awaitingFull = true;
    sock.onopen = () => { retryMs = 500; lastMessageAt = performance.now(); setConn("open"); };
    sock.onmessage = (ev) => {
      lastMessageAt = performance.now();
      const data = ev.data; // text and packets in arrival order (packets inflate asynchronously)
      const handle = typeof data === "string" ? () => onText(JSON.parse(data)) : () => onPacket(data);
      chain = chain.then(handle).catch((err) => { console.error(err); requestResync(); });
    };
    sock.onclose = (ev) => {
      if (ws !== sock) return;
      ws = null;
      if (ev.code === 4401 || ev.code === 4403) { // watching needs the PIN
        viewToken = true;
        if (ev.code === 4403) forgetPin();
        askPin("This robot needs its PIN to watch.").then(() => reconnectSoon(0));
        setConn("closed", "PIN needed");
        return;
      }
      setConn("closed");
      reconnectSoon(retryMs);
      retryMs = Math.min(retryMs * 2, 5000);
    };
  }
  function reconnectSoon(ms) { setTimeout(() => { if (!ws) connect(); }, ms); }

  // a socket that went silent (phone asleep, Wi-Fi gone) is replaced without waiting for TCP
  setInterval(() => {
    if (ws && ws.readyState === WebSocket.OPEN && performance.now() - lastMessageAt > 2.5 * heartbeatS * 1000) {
      const old = ws;
      ws = null;
      old.onclose = null; old.onmessage = null;
      old.close();
      setConn("closed");
      connect();
    }
  }, 1000);

  function send(obj) {
    if (!ws || ws.readyState !== WebSocket.OPEN) return false;
    ws.send(JSON.stringify(obj));
    return true;
  }

  function requestResync() {
    view.awaitingFull = true;
    const now = performance.now();
    if (now - lastResyncAt < 1000) return; // one request in flight is enough
    lastResyncAt = now;
    stats.resyncs++;
    send({ type: "resync" });
  }

  function onText(msg) {
    if (msg.type === "hello") {
      heartbeatS = msg.heartbeat_s || heartbeatS;
      setReplay(msg.replay || null);
    } else if (msg.type === "heartbeat") {
      if (view.seq !== null && msg.seq !== view.seq && !view.awaitingFull) { stats.gaps++; requestResync(); }
    } else if (msg.type === "reply") {
      onReply(msg);
    } else if (msg.type === "error") {
      console.warn("server:", msg.message);
    }
  }

  // a recording played back (mazebot replay --serve): no robot to start or stop
  let replay = null;
  function setReplay(info) {
    replay = info;
    document.body.dataset.replay = info ? "1" : "";
    $("replay").hidden = !info;
    if (info) $("replay").textContent = `Replay of ${info.file}` + (info.speed ? ` at ${info.speed}×` : ", fast");
    setConn(document.body.dataset.conn);
  }

  function setConn(state, detail) {
    document.body.dataset.conn = state;
    const text = { open: replay ? "replay" : "live", connecting: "connecting…", closed: "offline, retrying" }[state];
    $("conn-text").textContent = detail ? `${text} (${detail})` : text;
    updateButton();
  }

  // ---- start / stop ----------------------------------------------------------------------
  let pendingCommand = null;
  function loadPin() { try { return localStorage.getItem(PIN_KEY); } catch { return null; } }
  function savePin(pin) { try { localStorage.setItem(PIN_KEY, pin); } catch { /* private mode */ } }
  function forgetPin() { try { localStorage.removeItem(PIN_KEY); } catch { /* private mode */ } }

  function askPin(hint) {
    const dialog = $("pin-dialog");
    $("pin-hint").textContent = hint || "Printed in the robot's log on first start.";
    $("pin").value = "";
    return new Promise((resolve) => {
      dialog.addEventListener("close", () => {
        const pin = dialog.returnValue === "ok" ? $("pin").value.trim() : "";
        if (pin) savePin(pin);
        resolve(pin || null);
      }, { once: true });
      dialog.returnValue = "";
      dialog.showModal();
    });
  }

  async function command(cmd) {
    let pin = loadPin();
    if (!pin) pin = await askPin();
    if (!pin) return;
    pendingCommand = cmd;
    updateButton();
    setTimeout(() => { pendingCommand = null; updateButton(); }, 1500);
    if (send({ type: cmd, token: pin })) return;
    try { // no websocket right now: the HTTP API does the same
      const resp = await fetch(BASE + "api/" + cmd, { method: "POST", headers: { "X-Mazebot-Token": pin } });
      const body = await resp.json().catch(() => ({}));
      onReply({ command: cmd, ok: resp.ok, status: resp.status, message: body.error || "" });
    } catch (err) {
      onReply({ command: cmd, ok: false, status: 0, message: "robot unreachable" });
    }
  }

  function onReply(msg) {
    pendingCommand = null;
    if (!msg.ok && (msg.status === 401 || msg.status === 403)) {
      forgetPin();
      askPin("Wrong PIN, try again.").then((pin) => { if (pin) command(msg.command); });
    } else if (!msg.ok) {
      showBanner(msg.message || `${msg.command} refused (${msg.status})`);
    }
    updateButton();
  }

  $("go").addEventListener("click", () => command(isMoving() ? "stop" : "start"));
  // exploring and returning drive the wheels; in a fault the button offers stop, which always works
  const MOVING = new Set(["exploring", "returning", "fault"]);
  const isMoving = () => MOVING.has(view.status.state);

  function updateButton() {
    const go = $("go");
    const known = view.status.state !== undefined;
    const moving = isMoving();
    go.textContent = pendingCommand ? (pendingCommand === "stop" ? "Stopping…" : "Starting…") : moving ? "Stop" : "Start";
    go.classList.toggle("stop", moving || pendingCommand === "stop");
    go.disabled = !known || (!moving && view.status.state === "fault");
    if (view.status.state === "fault") go.disabled = false; // stop stays possible
    if (replay) { go.disabled = true; go.textContent = "Replay"; go.classList.remove("stop"); }
  }

  // ---- the status bar ----------------------------------------------------------------------
  let bannerText = null, bannerUntil = 0;
  function showBanner(text) { bannerText = text; bannerUntil = performance.now() + 5000; renderStatus(); }

  function renderStatus() {
    const s = view.status;
    document.body.dataset.state = s.state || "unknown";
    setText($("state"), s.state || "–"); // live regions: rewritten only when they change
    setText($("coverage"), s.coverage == null ? "–" : Math.round(100 * s.coverage) + "%");
    $("speed").textContent = s.speed_mps == null ? "–" : Math.round(100 * Math.abs(s.speed_mps)) + " cm/s";
    const fault = s.fault ? `${s.fault.source}: ${s.fault.message}` : null;
    const message = fault || (performance.now() < bannerUntil ? bannerText : null);
    $("fault").hidden = !message;
    $("fault").textContent = message || "";
    $("planner").hidden = !s.planner;
    $("planner").textContent = s.planner || "";
    $("empty").hidden = !!view.grid;
    renderElapsed();
    updateButton();
  }

  function setText(el, text) { if (el.textContent !== text) el.textContent = text; }

  function renderElapsed() {
    let t = view.elapsedS;
    const counting = view.status.state === "exploring" || view.status.state === "returning";
    if (t != null && counting) t += (performance.now() - view.elapsedAt) / 1000;
    $("elapsed").textContent = t == null ? "–" : `${Math.floor(t / 60)}:${String(Math.floor(t % 60)).padStart(2, "0")}`;
  }
  setInterval(() => { renderElapsed(); if (bannerText && performance.now() > bannerUntil) { bannerText = null; renderStatus(); } }, 250);

  // ---- drawing -----------------------------------------------------------------------------
  const canvas = $("map"), ctx = canvas.getContext("2d");
  let zoomT = d3.zoomIdentity, base = { s: 100, tx: 0, ty: 0 }, autoFit = true, fitted = false, drawQueued = false;
  let cssW = 1, cssH = 1;
  const line = d3.line().context(ctx);
  const zoom = d3.zoom().scaleExtent([0.25, 40]).on("zoom", (ev) => {
    zoomT = ev.transform;
    if (ev.sourceEvent) autoFit = false; // the user moved the view: stop following
    requestDraw();
  });
  d3.select(canvas).call(zoom).on("dblclick.zoom", null);

  function resize() {
    const r = canvas.getBoundingClientRect(), dpr = window.devicePixelRatio || 1;
    cssW = Math.max(1, r.width); cssH = Math.max(1, r.height);
    canvas.width = Math.round(cssW * dpr); canvas.height = Math.round(cssH * dpr);
    if (autoFit) fit(); else requestDraw();
  }
  new ResizeObserver(resize).observe($("map-box"));

  // base transform: world metres (y up) -> CSS pixels, fitting the known map (or the robot) in view
  let fitTimer = null;
  function fitSoon() { // while following the map as it grows: at most once a second
    if (!fitTimer) fitTimer = setTimeout(() => { fitTimer = null; if (autoFit) fit(); }, fitted ? 1000 : 0);
  }
  function fit() {
    let x0, y0, x1, y1;
    const g = view.grid, k = g && g.known, p = view.status.pose || [0, 0];
    if (k) {
      x0 = g.ox + k.c0 * g.res; x1 = g.ox + (k.c1 + 1) * g.res;
      y0 = g.oy + k.r0 * g.res; y1 = g.oy + (k.r1 + 1) * g.res;
      fitted = true;
    } else { x0 = x1 = p[0]; y0 = y1 = p[1]; }
    const margin = 0.15, minSpan = 1.0; // metres
    const cx = (x0 + x1) / 2, cy = (y0 + y1) / 2;
    const w = Math.max(x1 - x0 + 2 * margin, minSpan), h = Math.max(y1 - y0 + 2 * margin, minSpan);
    x0 = cx - w / 2; x1 = cx + w / 2; y0 = cy - h / 2; y1 = cy + h / 2;
    const s = Math.min(cssW / (x1 - x0), cssH / (y1 - y0));
    base = { s, tx: cssW / 2 - s * (x0 + x1) / 2, ty: cssH / 2 + s * (y0 + y1) / 2 };
    autoFit = true;
    d3.select(canvas).call(zoom.transform, d3.zoomIdentity);
    requestDraw();
  }
  $("fit").addEventListener("click", fit);

  function requestDraw() {
    if (drawQueued) return;
    drawQueued = true;
    requestAnimationFrame(draw);
  }

  function render() { renderStatus(); requestDraw(); }

  function draw() {
    drawQueued = false;
    const dpr = window.devicePixelRatio || 1, s = view.status, g = view.grid;
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.translate(zoomT.x, zoomT.y);
    ctx.scale(zoomT.k, zoomT.k);
    ctx.translate(base.tx, base.ty);
    ctx.scale(base.s, -base.s); // world metres, y up
    const px = 1 / (base.s * zoomT.k); // one CSS pixel in metres
    if (g) {
      ctx.save();
      ctx.imageSmoothingEnabled = false;
      ctx.translate(g.ox, g.oy + g.rows * g.res);
      ctx.scale(g.res, -g.res);
      ctx.drawImage(g.canvas, 0, 0);
      ctx.restore();
    }
    ctx.lineJoin = "round"; ctx.lineCap = "round";
    const pairs = (flat) => { const out = []; for (let i = 0; i + 1 < (flat || []).length; i += 2) out.push([flat[i], flat[i + 1]]); return out; };
    const trail = pairs(s.trail);
    if (trail.length > 1) {
      ctx.beginPath(); line(trail);
      ctx.strokeStyle = "rgba(40, 110, 220, .85)"; ctx.lineWidth = 2 * px; ctx.stroke();
    }
    const path = pairs(s.path);
    if (s.pose && path.length) {
      ctx.beginPath(); line([[s.pose[0], s.pose[1]], ...path]);
      ctx.setLineDash([6 * px, 5 * px]);
      ctx.strokeStyle = "#f08c00"; ctx.lineWidth = 2.5 * px; ctx.stroke();
      ctx.setLineDash([]);
    }
    if (s.goal) {
      const [gx, gy] = s.goal, r = 7 * px;
      ctx.beginPath(); ctx.moveTo(gx - r, gy - r); ctx.lineTo(gx + r, gy + r); ctx.moveTo(gx - r, gy + r); ctx.lineTo(gx + r, gy - r);
      ctx.strokeStyle = "#e8590c"; ctx.lineWidth = 3 * px; ctx.stroke();
      ctx.beginPath(); ctx.arc(gx, gy, r * 1.4, 0, 2 * Math.PI); ctx.lineWidth = 1.5 * px; ctx.stroke();
    }
    if (s.pose) {
      const [x, y, th] = s.pose;
      if (s.ellipse) {
        const [a, b, ang, thStd] = s.ellipse;
        ctx.beginPath(); ctx.ellipse(x, y, Math.max(a, px), Math.max(b, px), ang, 0, 2 * Math.PI);
        ctx.fillStyle = "rgba(214, 51, 132, .18)"; ctx.fill();
        ctx.strokeStyle = "rgba(214, 51, 132, .9)"; ctx.lineWidth = 1.5 * px; ctx.stroke();
        if (thStd > 0.005) { // heading uncertainty: a 2-sigma wedge
          const len = ROBOT_RADIUS_M * 2.2;
          ctx.beginPath(); ctx.moveTo(x, y); ctx.arc(x, y, len, th - 2 * thStd, th + 2 * thStd); ctx.closePath();
          ctx.fillStyle = "rgba(214, 51, 132, .25)"; ctx.fill();
        }
      }
      ctx.beginPath(); ctx.arc(x, y, ROBOT_RADIUS_M, 0, 2 * Math.PI);
      ctx.fillStyle = "rgba(31, 157, 85, .9)"; ctx.fill();
      ctx.strokeStyle = "#fff"; ctx.lineWidth = 2 * px; ctx.stroke();
      ctx.beginPath(); ctx.moveTo(x, y); ctx.lineTo(x + Math.cos(th) * ROBOT_RADIUS_M * 1.6, y + Math.sin(th) * ROBOT_RADIUS_M * 1.6);
      ctx.strokeStyle = "#fff"; ctx.lineWidth = 3 * px; ctx.stroke();
    }
  }

  // ---- for tests and the curious: window.mazebot ----------------------------------------
  function knownCells() {
    const g = view.grid;
    if (!g) return { free: 0, occupied: 0 };
    let free = 0, occupied = 0;
    for (const v of g.px) { if (v === CELL_COLORS[1]) free++; else if (v === CELL_COLORS[2]) occupied++; }
    return { free, occupied };
  }
  function drawnPixels() { // pixels of the visible canvas the map image covers
    const d = ctx.getImageData(0, 0, canvas.width, canvas.height).data;
    let n = 0;
    for (let i = 3; i < d.length; i += 4) if (d[i] !== 0) n++;
    return n;
  }
  window.mazebot = { view, stats, knownCells, drawnPixels, fit, command };

  // Without DecompressionStream (Safari before 16.4) no packet can be read, and every failure
  // would ask for a resync: say so once, and show the state from /api/status instead (start and
  // stop then go over HTTP, as when the socket is down).
  function pollStatus() {
    const pin = loadPin();
    fetch("/api/status", { cache: "no-store", headers: pin ? { "X-Mazebot-Token": pin } : {} })
      .then((resp) => (resp.ok ? resp.json() : Promise.reject(new Error("HTTP " + resp.status))))
      .then((body) => {
        setConn("open");
        $("conn-text").textContent = "status only";
        const { state, coverage, distance_m, elapsed_s, planner, fault } = body;
        mergeStatus({ state, coverage, distance_m, elapsed_s, planner, fault });
        renderStatus();
        document.dispatchEvent(new CustomEvent("mazebot:status", { detail: view.status }));
      })
      .catch(() => setConn("closed", "no live map"))
      .finally(() => setTimeout(pollStatus, 1000));
  }

  renderStatus();
  if (typeof DecompressionStream === "function") {
    connect();
  } else {
    $("unsupported").hidden = false;
    $("empty").textContent = "no live map in this browser: ⤓ map saves a picture of it";
    pollStatus();
  }
})();
