/* qradar view: the live stream (or a recording) of `qradar view --web`, drawn with uPlot.
 *
 * The view's events arrive as Server-Sent Events on /events (hello, targets, tracks,
 * profile, health, replay, reset, stats; qradar/web/events.py, docs/stream.md). Events only
 * update the state; drawing happens once per animation frame and only for what changed, so
 * a burst of events costs one frame. window.qradarView.stats() gives the page's own timings
 * (render time per frame, interval between frames while data flow), which
 * tests/test_web.py and benchmarks/bench_web.py read. */
"use strict";
(function () {
  const COLORS = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#e377c2", "#8c564b", "#17becf", "#bcbd22"];
  const TRAIL = 12;         // past frames of targets shown faint
  const STALE_MS = 2000;    // live: a sensor's targets and tracks go after this long without news
  const FLOWING_MS = 250;   // data flow when the last event is this recent
  const RING = 4096;        // timing samples kept
  const MIN_SPAN_M = 10;    // the x-y plot shows at least this much
  const DB_SPAN = 100;      // a profile's y axis spans at most this many dB
  const token = new URLSearchParams(location.search).get("token");
  const query = token ? "?token=" + encodeURIComponent(token) : "";
  const pr = window.devicePixelRatio || 1;

  const sensors = new Map();  // id -> state of one sensor
  let hello = null, replay = null, es = null, connected = false, xy = null, xyKeys = "", box = null;
  const dirty = { xy: false, profiles: new Set(), health: false, header: false };

  // -- timings ---------------------------------------------------------------------------
  const ring = () => ({ v: new Float64Array(RING), n: 0 });
  const push = (r, x) => { r.v[r.n % RING] = x; r.n++; };
  function summary(r) {
    const a = Array.from(r.v.subarray(0, Math.min(r.n, RING))).sort((p, q) => p - q);
    if (!a.length) return { n: 0, p50: null, p95: null, p99: null, max: null, mean: null };
    const at = p => a[Math.min(a.length - 1, Math.floor(p / 100 * a.length))];
    return { n: r.n, p50: at(50), p95: at(95), p99: at(99), max: a[a.length - 1],
             mean: a.reduce((s, x) => s + x, 0) / a.length };
  }
  // frame: the page's work for one frame (the events handled since the last one, and the drawing);
  // interval: between animation frames while data flow; longFrames: the browser's own count of
  // frames over 50 ms (Long Animation Frames API), while data flow
  const perf = { frame: ring(), render: ring(), interval: ring(), handle: ring(), pending: 0, longFrames: 0,
                 events: {}, connects: 0, firstEventMs: null,
                 firstTargetsMs: null, lastData: -1e9, renders: 0, refused: false, dropped: 0, sent: 0, errors: [],
                 targetsDrawn: 0, truthDrawn: 0, tracksDrawn: 0, ellipsesDrawn: 0, profilesDrawn: 0, healthRows: 0 };

  // -- state -----------------------------------------------------------------------------
  function sensor(id) {
    let s = sensors.get(id);
    if (!s) {
      s = { id, color: COLORS[sensors.size % COLORS.length], targets: [], trail: [], truth: null, tracks: [],
            targetsAt: -1e9, tracksAt: -1e9, profile: null, health: new Map(), arrivals: [], seq: null,
            frames: 0, plot: null, el: null, xs: null, yRange: null };
      sensors.set(id, s);
      dirty.xy = dirty.health = dirty.header = true;
    }
    return s;
  }
  const live = () => !hello || hello.mode !== "recording";
  const fresh = (s, at) => !live() || performance.now() - at < STALE_MS;
  const pose = id => (hello && hello.poses && hello.poses[id]) || [0, 0, 0];

  const on = {
    hello(d) { hello = d; replay = d.recording; setupReplay(); dirty.header = dirty.xy = true; },
    targets(d) {
      const s = sensor(d.s), now = performance.now();
      if (s.targets.length) { s.trail.push(s.targets); if (s.trail.length > TRAIL) s.trail.shift(); }
      s.targets = d.targets; s.targetsAt = now; s.seq = d.seq; s.frames++;
      if (d.truth) s.truth = d.truth;
      s.arrivals.push([now, d.t / 1e6]);
      while (s.arrivals.length && now - s.arrivals[0][0] > 3000) s.arrivals.shift();
      dirty.xy = true; dirty.profiles.add(d.s);
    },
    tracks(d) { const s = sensor(d.s); s.tracks = d.tracks; s.tracksAt = performance.now(); dirty.xy = true; },
    profile(d) { sensor(d.s).profile = d; dirty.profiles.add(d.s); },
    health(d) { sensor(d.s).health.set(d.node, d); dirty.health = true; },
    replay(d) { replay = d; dirty.header = true; },
    reset(d) {
      replay = d;
      for (const s of sensors.values()) { s.targets = []; s.trail = []; s.tracks = []; s.profile = null; s.arrivals = []; }
      dirty.xy = dirty.header = true;
      for (const id of sensors.keys()) dirty.profiles.add(id);
    },
    stats(d) { perf.dropped = d.dropped; perf.sent = d.sent; dirty.header = true; },
  };

  // -- connection ------------------------------------------------------------------------
  function setStatus(cls, text) {
    const el = document.getElementById("status");
    el.className = "status " + cls; el.textContent = text;
  }
  function connect() {
    es = new EventSource("events" + query);
    es.onopen = () => { connected = true; perf.connects++; setStatus("on", "connected"); };
    es.onerror = () => {
      connected = false;
      if (es.readyState === EventSource.CLOSED) { setStatus("off", "disconnected"); closed(); }
      else setStatus("off", "reconnecting…");
    };
    for (const kind of Object.keys(on)) {
      es.addEventListener(kind, ev => {
        const t0 = performance.now();
        try { on[kind](JSON.parse(ev.data)); } catch (e) { if (perf.errors.length < 20) perf.errors.push(kind + ": " + e); }
        perf.events[kind] = (perf.events[kind] || 0) + 1;
        if (kind !== "stats") { perf.lastData = t0; if (perf.firstEventMs === null) perf.firstEventMs = t0; }
        const dt = performance.now() - t0;
        push(perf.handle, dt); perf.pending += dt;
      });
    }
  }
  function closed() {  // the server refused the stream (a token?) or is gone: find out, then try again
    fetch("./" + query, { method: "HEAD", cache: "no-store" }).then(r => {
      if (r.status === 401) { perf.refused = true; setStatus("refused", "token refused: open the URL the view printed"); }
      else setTimeout(connect, 1000);
    }, () => setTimeout(connect, 1000));
  }

  // -- the x-y plane -----------------------------------------------------------------------
  const pointsPath = uPlot.paths.points();
  function buildXY() {
    const el = document.getElementById("xy");
    if (xy) xy.destroy();
    const series = [{}];
    for (const s of sensors.values()) {
      series.push({ label: s.id + " past", stroke: s.color + "50", fill: s.color + "30", paths: pointsPath,
                    points: { show: false, size: 5, width: 0 }, width: 0 });
      series.push({ label: s.id + " targets", stroke: "#000", fill: s.color, paths: pointsPath,
                    points: { show: false, size: 10, width: 1 }, width: 1 });
    }
    xy = new uPlot({
      mode: 2, width: el.clientWidth, height: Math.max(el.clientHeight, 100),
      cursor: { show: false, drag: { x: false, y: false } }, legend: { show: false },
      scales: { x: { time: false, auto: false }, y: { auto: false } },
      axes: [{ label: "x (m): a sensor at yaw 0 looks along +x", grid: { stroke: "#e6e8eb" } },
             { label: "y (m)", grid: { stroke: "#e6e8eb" } }],
      series, hooks: { draw: [drawOverlay] },
    }, xyData(), el);
    xyKeys = [...sensors.keys()].join(",");
  }
  function xyData() {
    const data = [null];
    for (const s of sensors.values()) {
      const ok = fresh(s, s.targetsAt);
      const past = ok ? s.trail.flat() : [];
      const now = ok ? s.targets : [];
      data.push([past.map(t => t.x), past.map(t => t.y)], [now.map(t => t.x), now.map(t => t.y)]);
    }
    return data;
  }
  function extent() {
    // what must be seen: the sensors, the truth, the tracks and the targets, except, when there
    // is a truth or are tracks, targets more than twice as far from their sensor (ghosts)
    let x0 = Infinity, x1 = -Infinity, y0 = Infinity, y1 = -Infinity, reach = 0;
    const add = (x, y) => { x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, y); y1 = Math.max(y1, y); };
    for (const s of sensors.values()) {
      const p = pose(s.id), far = (x, y) => Math.hypot(x - p[0], y - p[1]);
      add(p[0], p[1]);
      for (const q of s.truth || []) { add(q[0], q[1]); reach = Math.max(reach, far(q[0], q[1])); }
      if (fresh(s, s.tracksAt)) for (const t of s.tracks) { add(t.x, t.y); reach = Math.max(reach, far(t.x, t.y)); }
    }
    const limit = reach > 0 ? Math.max(2 * reach, MIN_SPAN_M) : Infinity;
    for (const s of sensors.values()) {
      const p = pose(s.id);
      if (fresh(s, s.targetsAt)) for (const t of s.targets) if (Math.hypot(t.x - p[0], t.y - p[1]) <= limit) add(t.x, t.y);
    }
    if (x0 === Infinity) { x0 = y0 = -1; x1 = y1 = 1; }
    return [x0, x1, y0, y1];
  }
  function fitBox() {  // the box grows at once, shrinks only when content fills less than 40 % of it
    const [x0, x1, y0, y1] = extent();
    const inside = box && x0 >= box[0] && x1 <= box[1] && y0 >= box[2] && y1 <= box[3];
    const small = box && Math.max(x1 - x0, y1 - y0) < 0.4 * Math.max(box[1] - box[0], box[3] - box[2]);
    if (!inside || small) {
      const span = Math.max(x1 - x0, y1 - y0, MIN_SPAN_M) * 1.15, cx = (x0 + x1) / 2, cy = (y0 + y1) / 2;
      box = [cx - span / 2, cx + span / 2, cy - span / 2, cy + span / 2];
    }
    const w = xy.bbox.width, h = xy.bbox.height;  // equal metres per pixel on both axes
    let sx = box[1] - box[0], sy = box[3] - box[2];
    if (sx / sy > w / h) sy = sx * h / w; else sx = sy * w / h;
    const cx = (box[0] + box[1]) / 2, cy = (box[2] + box[3]) / 2;
    return [cx - sx / 2, cx + sx / 2, cy - sy / 2, cy + sy / 2];
  }
  function drawOverlay(u) {
    const ctx = u.ctx, X = v => u.valToPos(v, "x", true), Y = v => u.valToPos(v, "y", true);
    const m = Math.abs(X(1) - X(0));  // pixels per metre
    ctx.save();
    ctx.beginPath(); ctx.rect(u.bbox.left, u.bbox.top, u.bbox.width, u.bbox.height); ctx.clip();
    ctx.font = `${11 * pr}px system-ui, sans-serif`;
    let ellipses = 0, tracks = 0, truth = 0;
    const places = new Map();  // sensors standing at the same place get their labels stacked
    for (const s of sensors.values()) {
      const [px, py, yaw] = pose(s.id), a = -yaw * Math.PI / 180, sx = X(px), sy = Y(py), r = 9 * pr;
      ctx.fillStyle = s.color; ctx.beginPath();  // the sensor: a wedge along its boresight
      ctx.moveTo(sx + r * Math.cos(a), sy + r * Math.sin(a));
      ctx.lineTo(sx + r * Math.cos(a + 2.5), sy + r * Math.sin(a + 2.5));
      ctx.lineTo(sx + r * Math.cos(a - 2.5), sy + r * Math.sin(a - 2.5));
      ctx.fill();
      const place = `${px},${py}`, below = places.get(place) || 0;
      places.set(place, below + 1);
      ctx.fillText(s.id, sx + 6 * pr, sy + (16 + 12 * below) * pr);
      ctx.strokeStyle = "#222"; ctx.lineWidth = 2 * pr;  // the truth: a cross
      for (const q of s.truth || []) {
        const qx = X(q[0]), qy = Y(q[1]), c = 7 * pr;
        ctx.beginPath(); ctx.moveTo(qx - c, qy - c); ctx.lineTo(qx + c, qy + c); ctx.moveTo(qx - c, qy + c);
        ctx.lineTo(qx + c, qy - c); ctx.stroke(); truth++;
      }
      ctx.strokeStyle = s.color; ctx.lineWidth = 1.5 * pr;
      if (fresh(s, s.targetsAt)) {
        for (const t of s.targets) {
          if (!t.ell) continue;
          ctx.beginPath();
          ctx.ellipse(X(t.x), Y(t.y), Math.max(t.ell[0] * m, 1), Math.max(t.ell[1] * m, 1), -t.ell[2], 0, 2 * Math.PI);
          ctx.stroke(); ellipses++;
        }
      }
      if (!fresh(s, s.tracksAt)) continue;
      for (const t of s.tracks) {
        const tx = X(t.x), ty = Y(t.y), rad = Math.max(t.sigma * m, 4 * pr);
        ctx.strokeStyle = t.static ? "#1e7b3c" : "#e07000"; ctx.lineWidth = 2 * pr;
        ctx.beginPath(); ctx.arc(tx, ty, rad, 0, 2 * Math.PI); ctx.stroke();
        if (!t.static) {  // where it will be in 1 s
          ctx.beginPath(); ctx.moveTo(tx, ty); ctx.lineTo(X(t.x + t.vx), Y(t.y + t.vy)); ctx.stroke();
        }
        ctx.fillStyle = "#111";
        const speed = Math.hypot(t.vx, t.vy);
        const radial = t.vr === undefined ? "" : ` (radial ${t.vr >= 0 ? "+" : ""}${t.vr.toFixed(2)})`;  // the Doppler's
        ctx.fillText(`#${t.id}` + (t.static ? "" : ` ${speed.toFixed(1)} m/s${radial}`), tx + rad + 6 * pr, ty - rad - 4 * pr);
        tracks++;
      }
    }
    ctx.restore();
    perf.ellipsesDrawn = ellipses; perf.tracksDrawn = tracks; perf.truthDrawn = truth;
  }
  function renderXY() {
    if (!sensors.size) return;  // nothing to plot yet (uPlot's x-y mode needs a series)
    const keys = [...sensors.keys()].join(",");
    if (!xy || keys !== xyKeys) { buildXY(); renderLegend(); }
    const data = xyData(), b = fitBox();
    xy.batch(() => {
      xy.setScale("x", { min: b[0], max: b[1] });
      xy.setScale("y", { min: b[2], max: b[3] });
      xy.setData(data, false);
    });
    let n = 0;
    for (let i = 1; i < data.length; i += 2) n += data[i + 1][0].length;
    perf.targetsDrawn = n;
  }

  // -- range profiles --------------------------------------------------------------------------
  function buildProfile(s) {
    const box = document.getElementById("profile-plots");
    s.el = document.createElement("div"); s.el.className = "profile";
    const name = document.createElement("span"); name.className = "name"; name.textContent = s.id;
    name.style.color = s.color; s.el.appendChild(name);
    box.appendChild(s.el);
    s.plot = new uPlot({
      width: 300, height: 100, legend: { show: false },
      scales: { x: { time: false, auto: false }, y: { auto: false } },
      axes: [{ label: "range (m)", grid: { stroke: "#eceef1" } }, { label: "dB FS", size: 48, grid: { stroke: "#eceef1" } }],
      series: [{ label: "range (m)" }, { label: "receiver 1", stroke: s.color, width: 1.2 * pr },
               { label: "receiver 2", stroke: "#555", width: 1 * pr, dash: [4 * pr, 3 * pr] }],
      hooks: { draw: [u => markTargets(u, s)] },
    }, [[], [], []], s.el);
    sizeProfiles();
  }
  function sizeProfiles() {
    const box = document.getElementById("profile-plots"), shown = [...sensors.values()].filter(s => s.plot);
    const h = Math.max(Math.floor(box.clientHeight / Math.max(shown.length, 1)), 90);
    for (const s of shown) s.plot.setSize({ width: box.clientWidth, height: h });
  }
  function markTargets(u, s) {  // a triangle at the top of the plot at each target's range
    if (!fresh(s, s.targetsAt)) return;
    const ctx = u.ctx, top = u.bbox.top;
    ctx.save(); ctx.fillStyle = s.color;
    for (const t of s.targets) {
      const x = u.valToPos(t.r, "x", true);
      ctx.beginPath(); ctx.moveTo(x - 5 * pr, top); ctx.lineTo(x + 5 * pr, top); ctx.lineTo(x, top + 8 * pr); ctx.fill();
    }
    ctx.restore();
  }
  function renderProfile(s) {
    const p = s.profile;
    if (!s.plot) { if (!p) return; buildProfile(s); }
    if (!p) { s.plot.setData([[], [], []], false); return; }
    const n = p.rx1.length;
    if (!s.xs || s.xs.length !== n || s.xs[1] !== p.r0 + p.dr) s.xs = Float64Array.from({ length: n }, (_, i) => p.r0 + i * p.dr);
    let lo = Infinity, hi = -Infinity;
    for (let i = 0; i < n; i++) { const a = p.rx1[i], b = p.rx2[i]; if (a > hi) hi = a; if (b > hi) hi = b; if (a < lo) lo = a; if (b < lo) lo = b; }
    const top = Math.ceil(hi / 10) * 10 + 5, bottom = Math.max(Math.floor(lo / 10) * 10, top - DB_SPAN);
    const r = s.yRange;  // kept while the data fit it and fill it, so the axis does not jump each frame
    if (!r || top > r[1] || top < r[1] - 20 || bottom < r[0] - 10 || bottom > r[0] + 20) s.yRange = [bottom, top];
    const full = p.r0 + "/" + p.dr + "/" + n;  // x is set when the bins change, so a zoom (drag) stays
    s.plot.batch(() => {
      if (s.xFull !== full) { s.xFull = full; s.plot.setScale("x", { min: p.r0, max: p.r0 + (n - 1) * p.dr }); }
      s.plot.setScale("y", { min: s.yRange[0], max: s.yRange[1] });
      s.plot.setData([s.xs, p.rx1, p.rx2], false);
    });
    perf.profilesDrawn++;
  }

  // -- health ----------------------------------------------------------------------------------
  function rateHz(s) {  // frames per second over the last 3 s, by the sensor's own timestamps
    const a = s.arrivals, n = a.length;
    if (!live() && replay && !replay.playing) return null;
    const span = n > 1 ? (a[n - 1][1] - a[0][1]) / 1000 : 0;
    return span > 0 && performance.now() - a[n - 1][0] < STALE_MS ? (n - 1) / span : null;
  }
  const esc = v => String(v).replace(/[&<>"']/g, c => `&#${c.charCodeAt(0)};`);
  const ms = v => (v === null || v === undefined ? "–" : Number(v).toFixed(1));
  function calibration(s) {
    for (const h of s.health.values()) {
      if (!h.extra || !("calibration" in h.extra)) continue;
      const c = h.extra.calibration;
      if (c === null || c === false) return ["uncalibrated", true];
      return ["calibrated" + (c && c.file ? " (" + String(c.file).split("/").pop() + ")" : ""), false];
    }
    return ["–", false];
  }
  function renderHealth() {
    const rows = [];
    for (const s of sensors.values()) {
      const r = rateHz(s), rate = r === null ? "–" : r.toFixed(1) + " Hz";
      const [cal, uncal] = calibration(s);
      const nodes = [...s.health.values()].sort((a, b) => a.node.localeCompare(b.node));
      const head = `<td class="sensor" style="color:${s.color}">${esc(s.id)}</td><td class="num">${rate}</td>` +
                   `<td class="num">${fresh(s, s.targetsAt) ? s.targets.length : "–"}</td>`;
      if (!nodes.length) rows.push(`<tr>${head}<td colspan="6">no health yet</td><td>${esc(cal)}</td></tr>`);
      nodes.forEach((h, i) => {
        const errors = (h.decode_errors || 0) + (h.invalid_frames || 0) + (h.processing_errors || 0);
        const lat = h.latency_ms || {};
        rows.push(`<tr>${i ? "<td></td><td></td><td></td>" : head}<td>${esc(h.node)}</td>` +
                  `<td class="num">${h.frames_in} / ${h.frames_out}</td>` +
                  `<td class="num${h.drops ? " bad" : ""}">${h.drops}</td>` +
                  `<td class="num${h.frames_missing ? " bad" : ""}">${h.frames_missing || 0}</td>` +
                  `<td class="num${errors ? " bad" : ""}">${errors}</td>` +
                  `<td class="num">${ms(lat.p50)} / ${ms(lat.p99)} ms</td>` +
                  `<td class="${i === 0 && uncal ? "bad" : ""}">${i ? "" : esc(cal)}</td></tr>`);
      });
    }
    document.querySelector("#health-table tbody").innerHTML = rows.join("");
    perf.healthRows = rows.length;
  }

  // -- header and replay ------------------------------------------------------------------------
  function setupReplay() {
    const el = document.getElementById("replay");
    el.hidden = !replay;
    if (!replay) return;
    const seek = document.getElementById("seek");
    seek.max = String(replay.duration_s);
  }
  function renderLegend() {
    const parts = [...sensors.values()].map(s => `<span style="color:${s.color}">■ ${esc(s.id)}</span>`);
    document.getElementById("xy-legend").innerHTML = parts.join(" ");
  }
  function renderHeader() {
    document.getElementById("source").textContent = !hello ? "" :
      hello.mode === "recording" ? `recording ${replay ? replay.name : ""}` : `live, ${hello.prefix}/*`;
    if (replay) {
      document.getElementById("play").textContent = replay.playing ? "pause" : "play";
      const seek = document.getElementById("seek");
      if (document.activeElement !== seek) seek.value = String(replay.position_s);
      document.getElementById("position").textContent = `${replay.position_s.toFixed(1)} / ${replay.duration_s.toFixed(1)} s`;
    }
    let rate = 0;
    for (const s of sensors.values()) rate += rateHz(s) || 0;
    document.getElementById("counters").textContent =
      `${sensors.size} sensor${sensors.size === 1 ? "" : "s"} · ${rate.toFixed(0)} frames/s · dropped for this page ${perf.dropped}`;
  }
  function control(action, position_s) {
    return fetch("control" + query, { method: "POST", headers: { "Content-Type": "application/json" },
                                      body: JSON.stringify({ action, position_s }) })
      .then(r => r.ok ? r.json() : r.text().then(t => { throw new Error(t); }))
      .then(state => { replay = state; dirty.header = true; return state; });
  }
  document.getElementById("play").addEventListener("click", () => control(replay && replay.playing ? "pause" : "play"));
  document.getElementById("seek").addEventListener("change", ev => control("seek", Number(ev.target.value)));

  // -- the frame loop ------------------------------------------------------------------------
  let last = 0, nextHealth = 0;
  function frame(now) {
    requestAnimationFrame(frame);
    const flowing = now - perf.lastData < FLOWING_MS;
    if (last && flowing) push(perf.interval, now - last);
    last = now;
    const healthDue = dirty.health && now >= nextHealth;
    if (!(dirty.xy || dirty.profiles.size || healthDue || dirty.header)) return;
    const t0 = performance.now();
    if (dirty.xy) { dirty.xy = false; renderXY(); }
    for (const id of dirty.profiles) renderProfile(sensors.get(id));
    dirty.profiles.clear();
    if (healthDue) { dirty.health = false; nextHealth = now + 500; renderHealth(); dirty.header = true; }
    if (dirty.header) { dirty.header = false; renderHeader(); }
    const t1 = performance.now();
    if (flowing) { push(perf.render, t1 - t0); push(perf.frame, perf.pending + t1 - t0); }
    perf.pending = 0;
    perf.renders++;
    if (perf.firstTargetsMs === null && perf.targetsDrawn > 0) perf.firstTargetsMs = t1;
  }
  setInterval(() => { if (live()) { dirty.xy = true; dirty.health = true; } }, 1000);  // stale data go
  const resized = new ResizeObserver(() => {  // the plots follow their boxes (the window, the health table's rows)
    const el = document.getElementById("xy");
    if (xy) xy.setSize({ width: el.clientWidth, height: Math.max(el.clientHeight, 100) });
    sizeProfiles(); dirty.xy = true;
  });
  resized.observe(document.getElementById("xy"));
  resized.observe(document.getElementById("profile-plots"));

  window.qradarView = {
    stats() {
      const per = {};
      for (const s of sensors.values()) per[s.id] = { frames: s.frames, seq: s.seq, targets: s.targets.length, tracks: s.tracks.length,
                                                      truth: (s.truth || []).length, profile: !!s.profile, nodes: s.health.size };
      return { connected, connects: perf.connects, refused: perf.refused, mode: hello && hello.mode, events: { ...perf.events },
               firstEventMs: perf.firstEventMs, firstTargetsMs: perf.firstTargetsMs, renders: perf.renders,
               frame: summary(perf.frame), render: summary(perf.render), interval: summary(perf.interval),
               handle: summary(perf.handle), longFrames: perf.longFrames,
               targetsDrawn: perf.targetsDrawn, truthDrawn: perf.truthDrawn, tracksDrawn: perf.tracksDrawn,
               ellipsesDrawn: perf.ellipsesDrawn, profilesDrawn: perf.profilesDrawn, healthRows: perf.healthRows,
               dropped: perf.dropped, sent: perf.sent, sensors: per, replay, errors: perf.errors.slice() };
    },
    resetTimings() { perf.frame = ring(); perf.render = ring(); perf.interval = ring(); perf.handle = ring(); perf.longFrames = 0; },
    control,
  };
  try {  // frames over 50 ms, as the browser measures them (layout and paint included)
    new PerformanceObserver(list => {
      for (const e of list.getEntries()) if (e.startTime - perf.lastData < FLOWING_MS) perf.longFrames++;
    }).observe({ type: "long-animation-frame", buffered: false });
  } catch (e) { /* a browser without the API: the count stays 0 */ }
  connect();
  requestAnimationFrame(frame);
})();
