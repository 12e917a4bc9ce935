// hapsim live view: one WebSocket, frames of JSON at the display's rate (hapsim/view/server.py).
// Traces by uPlot (vendored, MIT); the scene, the histogram and the (k, b) grid on plain canvases.
"use strict";
(function () {
  const S = { layout: null, t: [], x: [], f: [], et: [], e: [], marks: [], pos: null, portF: null,
              hist: null, grid: null, felt: {}, measured: {}, measurements: [], links: {}, masses: {},
              frames: 0, count: 0, replies: [], journal: [], report: null, box: null,
              periodUs: 1000, span: 4.0,
              // the axis's units (the hello's layout.units: a rotary joint's, or SI)
              units: { position: "m", force: "N", stiffness: "N/m", friction: "N s/m" } };
  window.hapsimView = S;
  const $ = (id) => document.getElementById(id);
  const ws = new WebSocket(`ws://${location.host}/ws`);
  S.send = (obj) => ws.send(JSON.stringify(obj));
  S.request = (address, args) => S.send({ op: "request", address, args });
  ws.onopen = () => { $("status").textContent = "connected"; };
  ws.onclose = () => {
    $("status").textContent = S.report ? "run ended (report below)" : "disconnected";
    $("stop").disabled = true;
  };
  ws.onmessage = (ev) => {
    const m = JSON.parse(ev.data);
    if (m.type === "hello") hello(m);
    else if (m.type === "frame") frame(m);
    else if (m.type === "reply") reply(m);
  };
  $("stop").onclick = () => { S.send({ op: "stop" }); $("stop").disabled = true;
                              $("status").textContent = "stopping…"; };

  // ------------------------------------------------------------------ traces (uPlot)
  let plotXF = null, plotE = null;
  function marksHook(u) {
    const ctx = u.ctx, top = u.bbox.top, h = u.bbox.height;
    ctx.save();
    for (const mk of S.marks) {
      const px = u.valToPos(mk.t, "x", true);
      if (px < u.bbox.left || px > u.bbox.left + u.bbox.width) continue;
      ctx.strokeStyle = mk.kind === "late" ? "rgba(230,81,0,0.6)" :
                        mk.kind === "est" ? "rgba(106,27,154,0.6)" : "rgba(198,40,40,0.9)";
      ctx.lineWidth = mk.kind === "event" ? 2 : 1;
      ctx.beginPath(); ctx.moveTo(px, top); ctx.lineTo(px, top + h); ctx.stroke();
    }
    ctx.restore();
  }
  function makePlots(axis) {
    const w = Math.max(300, $("traces").clientWidth - 10);
    const ax = S.layout.dim > 1 ? ` ${"xyz"[axis] || axis}` : "";
    plotXF = new uPlot({ width: w, height: 190, title: "",
      scales: { x: { time: false }, f: {} },
      axes: [{ label: "t [s]" }, { label: `position${ax} [${S.units.position}]`, size: 70 },
             { scale: "f", side: 1, label: `force${ax} [${S.units.force}]`, grid: { show: false }, size: 60 }],
      series: [{ label: "t [s]" }, { label: `position${ax} [${S.units.position}]`, stroke: "#1565c0" },
               { label: `force${ax} [${S.units.force}]`, stroke: "#c62828", scale: "f" }],
      hooks: { draw: [marksHook] } }, [[], [], []], $("traces"));
    plotE = new uPlot({ width: w, height: 120,
      scales: { x: { time: false } },
      axes: [{ label: "t [s]" }, { label: "energy [J]", size: 70 }],
      series: [{ label: "t [s]" }, { label: "stored energy [J]", stroke: "#2e7d32" }] },
      [[], []], $("traces"));
  }

  // ------------------------------------------------------------------ messages
  function hello(m) {
    S.layout = m.layout; S.periodUs = m.period_us; S.histBins = m.hist_bins;
    S.units = m.layout.units || S.units;
    $("what").textContent = m.what;
    $("scene-note").textContent = `(${m.layout.dim}-D, ${m.layout.masses.length} masses, ` +
      `${m.layout.links.length} links, ${m.layout.rate_hz} Hz)`;
    if (!plotXF) makePlots(m.axis || 0);
    buildControls(m.controls);
  }
  function frame(m) {
    S.frames += 1; S.count = m.count;
    if (m.t && m.t.length) {
      for (let i = 0; i < m.t.length; i++) { S.t.push(m.t[i]); S.x.push(m.x[i]); S.f.push(m.f[i]); }
      const tEnd = S.t[S.t.length - 1];
      let cut = 0; while (cut < S.t.length && S.t[cut] < tEnd - S.span) cut++;
      if (cut) { S.t.splice(0, cut); S.x.splice(0, cut); S.f.splice(0, cut); }
      if (m.energy !== undefined && m.energy !== null) {
        S.et.push(tEnd); S.e.push(m.energy);
        let c2 = 0; while (c2 < S.et.length && S.et[c2] < tEnd - S.span) c2++;
        if (c2) { S.et.splice(0, c2); S.e.splice(0, c2); }
      }
      for (const t of m.late_t || []) S.marks.push({ t, kind: "late" });
      for (const t of m.est_t || []) S.marks.push({ t, kind: "est" });
      S.marks = S.marks.filter((k) => k.t >= tEnd - S.span);
      if (S.marks.length > 300) S.marks.splice(0, S.marks.length - 300);
      plotXF.setData([S.t, S.x, S.f]);
      plotE.setData([S.et, S.e]);
    }
    if (m.late_n !== undefined) {
      S.late = (S.late || 0) + m.late_n; S.est = (S.est || 0) + m.est_n;
    }
    for (const e of m.events || []) {
      const t = e.t !== undefined ? e.t : (e.sample !== undefined ? e.sample / S.layout.rate_hz : null);
      if (t !== null) S.marks.push({ t, kind: "event" });
      logLine(`loop: ${e.event}${e.reason ? " — " + e.reason : ""}`, e.sample);
    }
    $("marks").textContent = `— late ticks ${S.late || 0}, estimated samples ${S.est || 0} ` +
      "(orange: late, purple: estimated, red: safety/loop events)";
    if (m.pos) { S.pos = m.pos; }
    if (m.port_f) S.portF = m.port_f;
    if (m.hist) { S.hist = m.hist; S.histOver = m.hist_over; drawHist(); }
    if (m.felt) S.felt = m.felt;
    if (m.measured) S.measured = m.measured;
    for (const q of m.measurements || []) {   // the run's record so far, measured as it grows
      S.measurements.push(q);
      S.measured = q.k !== undefined && q.k !== null ? q :
        { ...S.measured, why_not: q.error || q.reason || "not measured" };
    }
    if (m.links) S.links = m.links;
    if (m.masses) S.masses = m.masses;
    if (m.grid) S.grid = m.grid;
    for (const j of m.journal || []) {
      S.journal.push(j);
      logLine(`${j.event} ${j.address} ${JSON.stringify(j.args)}` +
              (j.reason ? ` — ${j.reason}` : ""), j.sample);
    }
    if (m.report) showReport(m.report);
    $("status").textContent = `sample ${m.count} (${(m.count / S.layout.rate_hz).toFixed(2)} s)` +
      (m.accepted !== undefined ? `, changes ${m.accepted} accepted, ${m.refused} refused` : "");
    drawScene();
    // the grid only when what it shows changed (the page's drawing is CPU beside the loop)
    const key = JSON.stringify([!!S.grid, S.felt, S.measured, S.measurements.length]);
    if (key !== S.gridKey) { S.gridKey = key; drawGrid(); feltText(); }
  }
  function reply(m) {
    S.replies.push(m);
    const r = $("reply");
    if (m.op === "stop") { r.className = "ok"; r.textContent = "stop requested: the run ends at its next sample"; return; }
    if (m.ok) {
      r.className = "ok";
      r.textContent = `accepted ${m.address} ${JSON.stringify(m.args)}: ramp ${fmt(m.ramp_s)} s, ` +
        `felt k ${fmt(m.k)} ${S.units.stiffness}, b ${fmt(m.b)} ${S.units.friction}`;
    } else {
      r.className = "refused";
      r.textContent = `refused ${m.address} ${JSON.stringify(m.args)}: ${m.reason}`;
      resetControls();
    }
  }
  function showReport(rep) {
    S.report = rep;
    const el = $("report");
    el.style.display = "block";
    const keep = {};
    for (const k of ["stop_reason", "exit_code", "samples", "verdict", "measured", "predicted",
                     "loop", "felt", "accepted", "refused", "error"]) {
      if (rep[k] !== undefined) keep[k] = rep[k];
    }
    el.textContent = "The run's report\n" + JSON.stringify(keep, null, 1);
    $("status").textContent = "run ended (report below)";
    $("stop").disabled = true;
  }
  function logLine(s, sample) {
    const el = $("journal");
    el.textContent += (sample !== undefined ? `[${sample}] ` : "") + s + "\n";
    el.scrollTop = el.scrollHeight;
  }
  const fmt = (v) => (v === null || v === undefined || Number.isNaN(v)) ? "–" :
    (Math.abs(v) >= 1e4 || (Math.abs(v) < 1e-3 && v !== 0) ? v.toExponential(3) : (+v).toPrecision(4));

  // ------------------------------------------------------------------ controls
  function slider(label, value, max, onset) {
    const row = document.createElement("div"); row.className = "row";
    const l = document.createElement("label"); l.textContent = label; l.title = label;
    const r = document.createElement("input"); r.type = "range"; r.min = 0; r.max = max;
    r.step = max / 1000; r.value = value;
    const n = document.createElement("input"); n.type = "number"; n.value = value; n.step = "any";
    r.oninput = () => { n.value = r.value; };
    r.onchange = () => onset(parseFloat(r.value));
    n.onchange = () => { r.value = n.value; onset(parseFloat(n.value)); };
    row.append(l, r, n);
    row.dataset.initial = value;
    row.reset = (v) => { r.value = v; n.value = v; };
    return row;
  }
  const rows = {};
  function buildControls(enabled) {
    const box = $("controls"); box.innerHTML = "";
    if (!enabled) { box.textContent = "this run takes no live changes"; return; }
    const L = S.layout;
    const items = [...L.links.map((k) => ({ ...k, plane: false })),
                   ...L.planes.map((p) => ({ ...p, plane: true, kind: "plane contact" }))];
    for (const lk of items) {
      const K = lk.K || 0, B = lk.B || 0;
      const kmax = Math.max(3 * K, 1), bmax = Math.max(3 * Math.abs(B), 1);
      const cur = () => S.links[lk.name] || [K, B];
      const rK = slider(`${lk.name} (${lk.kind}) K [${S.units.stiffness}]`, K, kmax,
        (v) => S.request("/hapsim/link/kb", [lk.name, v, cur()[1]]));
      rK.id = `ctl-${lk.name}-K`;
      const rB = slider(`${lk.name} B [${S.units.friction}]`, B, bmax,
        (v) => S.request("/hapsim/link/kb", [lk.name, cur()[0], v]));
      rB.id = `ctl-${lk.name}-B`;
      rows[lk.name] = [rK, rB];
      box.append(rK, rB);
    }
    for (const m of L.masses.filter((q) => q.kind === "mass")) {
      const r = slider(`${m.name} mass [kg]`, m.mass, Math.max(3 * m.mass, 1e-3),
        (v) => S.request("/hapsim/mass", [m.name, v]));
      r.id = `ctl-${m.name}-m`;
      rows["mass:" + m.name] = [r];
      box.append(r);
    }
  }
  function resetControls() {      // a refused change leaves everything as it was: so do the sliders
    for (const [name, rs] of Object.entries(rows)) {
      if (name.startsWith("mass:")) { const v = S.masses[name.slice(5)]; if (v !== undefined) rs[0].reset(v); }
      else if (S.links[name]) { rs[0].reset(S.links[name][0]); rs[1].reset(S.links[name][1]); }
    }
  }

  // ------------------------------------------------------------------ scene (canvas)
  function project(p, dim) {
    if (dim === 1) return [p[0], 0];
    if (dim === 2) return [p[0], p[1]];
    const c = Math.cos(Math.PI / 6), s = Math.sin(Math.PI / 6);   // an oblique view of 3-D
    return [p[0] - 0.6 * c * p[1], p[2] + 0.6 * s * p[1]];
  }
  function drawScene() {
    const cv = $("scene"), ctx = cv.getContext("2d"), L = S.layout;
    if (!L || !S.pos) return;
    const W = cv.width, H = cv.height, dim = L.dim;
    ctx.clearRect(0, 0, W, H);
    const n = S.pos.length;
    const P = S.pos.map((p, i) => {
      const q = project(p, dim);
      return dim === 1 ? [q[0], n > 1 ? (i / (n - 1) - 0.5) : 0] : q;
    });
    let x0 = Infinity, x1 = -Infinity, y0 = Infinity, y1 = -Infinity;
    for (const [a, b] of P) { x0 = Math.min(x0, a); x1 = Math.max(x1, a); y0 = Math.min(y0, b); y1 = Math.max(y1, b); }
    if (dim === 1) {        // 1-D: the threshold of a contact widens the axis enough to see it
      for (const lk of L.links) if (lk.threshold) { x1 = Math.max(x1, x1 + 0 * lk.threshold); }
    }
    // a box that grows at once and shrinks slowly, so a still scene stays still
    const pad = (v0, v1) => { const d = Math.max(v1 - v0, 1e-4); return [v0 - 0.15 * d, v1 + 0.15 * d]; };
    [x0, x1] = pad(x0, x1); [y0, y1] = pad(y0, y1);
    if (!S.box) S.box = [x0, x1, y0, y1];
    const bx = S.box, a = 0.02;
    bx[0] = Math.min(x0, bx[0] + a * (x0 - bx[0])); bx[1] = Math.max(x1, bx[1] + a * (x1 - bx[1]));
    bx[2] = Math.min(y0, bx[2] + a * (y0 - bx[2])); bx[3] = Math.max(y1, bx[3] + a * (y1 - bx[3]));
    let sx = (W - 40) / (bx[1] - bx[0]), sy = (H - 40) / (bx[3] - bx[2]);
    if (dim > 1) { sx = sy = Math.min(sx, sy); }
    const X = (v) => 20 + (v - bx[0]) * sx, Y = (v) => H - 20 - (v - bx[2]) * sy;
    if (dim === 1) {
      ctx.strokeStyle = "#eee"; ctx.beginPath(); ctx.moveTo(0, H - 12); ctx.lineTo(W, H - 12); ctx.stroke();
      ctx.fillStyle = "#777"; ctx.fillText(`x [${S.units.position}]: ${fmt(bx[0])} … ${fmt(bx[1])}`, 4, H - 2);
    }
    for (const pl of L.planes || []) {       // a plane contact as its trace in the view
      const nrm = pl.normal, lit = pl.masses.some((i) => dot(S.pos[i], nrm) < pl.offset);
      ctx.strokeStyle = lit ? "#d81b60" : "#bbb"; ctx.lineWidth = lit ? 3 : 1;
      // its trace through the foot of the masses' centre on it (not the origin's: a
      // pantograph's workspace is centimetres away from it)
      const mid = S.pos[0].map((_, k) => S.pos.reduce((a, p) => a + p[k], 0) / S.pos.length);
      const h = dot(mid, nrm) - pl.offset, c = mid.map((v, k) => v - h * nrm[k]);
      const t = dim === 2 ? [-nrm[1], nrm[0]] : [1, 0, 0];
      const span = 2 * Math.max(bx[1] - bx[0], bx[3] - bx[2]);   // across the whole view
      const pA = project(c.map((v, k) => v - span * (t[k] || 0)), dim);
      const pB = project(c.map((v, k) => v + span * (t[k] || 0)), dim);
      ctx.beginPath(); ctx.moveTo(X(pA[0]), Y(pA[1])); ctx.lineTo(X(pB[0]), Y(pB[1])); ctx.stroke();
    }
    for (const lk of L.links) {
      const pi = S.pos[lk.i], pj = S.pos[lk.j];
      let lit = false;
      if (lk.kind === "contact") {
        const gap = dim === 1 ? pj[0] - pi[0] : Math.hypot(...pj.map((v, k) => v - pi[k]));
        lit = gap < (lk.threshold || 0);
      }
      ctx.strokeStyle = lk.kind === "contact" ? (lit ? "#d81b60" : "#e0b0c0") : "#90a4ae";
      ctx.lineWidth = lit ? 4 : 1.5;
      ctx.setLineDash(lk.kind === "contact" && !lit ? [4, 3] : []);
      ctx.beginPath(); ctx.moveTo(X(P[lk.i][0]), Y(P[lk.i][1])); ctx.lineTo(X(P[lk.j][0]), Y(P[lk.j][1]));
      ctx.stroke();
    }
    ctx.setLineDash([]);
    L.masses.forEach((m, i) => {
      const px = X(P[i][0]), py = Y(P[i][1]);
      if (m.kind === "ground") { ctx.fillStyle = "#555"; ctx.fillRect(px - 4, py - 4, 8, 8); }
      else if (m.kind === "port") {
        ctx.fillStyle = "#e65100"; ctx.beginPath();
        ctx.moveTo(px, py - 8); ctx.lineTo(px + 8, py); ctx.lineTo(px, py + 8); ctx.lineTo(px - 8, py);
        ctx.fill();
        if (S.portF) {         // the hand's force on the handle (minus the port force)
          const f = S.portF.map((v) => -v), fp = project(dim === 1 ? [f[0]] : f, dim);
          const mag = Math.hypot(fp[0], fp[1]) || 1, len = Math.min(60, 10 + 15 * Math.log1p(mag));
          const ux = fp[0] / mag, uy = -fp[1] / mag;
          ctx.strokeStyle = "#c62828"; ctx.lineWidth = 2; ctx.beginPath();
          ctx.moveTo(px, py); ctx.lineTo(px + len * ux, py + len * uy); ctx.stroke();
          ctx.fillStyle = "#c62828"; ctx.fillText(`${fmt(Math.hypot(...S.portF))} ${S.units.force}`, px + len * ux + 4, py + len * uy);
        }
      } else if (n <= 40 || i % Math.ceil(n / 200) === 0) {
        ctx.fillStyle = "#1565c0"; ctx.beginPath(); ctx.arc(px, py, n > 40 ? 2 : 4, 0, 2 * Math.PI); ctx.fill();
      }
      if (n <= 12) { ctx.fillStyle = "#333"; ctx.fillText(m.name, px + 6, py - 6); }
    });
  }
  const dot = (a, b) => a.reduce((s, v, k) => s + v * (b[k] || 0), 0);

  // ------------------------------------------------------------------ histogram
  function drawHist() {
    const cv = $("hist"), ctx = cv.getContext("2d"), W = cv.width, H = cv.height;
    ctx.clearRect(0, 0, W, H);
    const h = S.hist, nb = h.length, top = Math.max(...h, 1), tot = h.reduce((a, b) => a + b, 0);
    const bw = (W - 40) / nb;
    ctx.fillStyle = "#1565c0";
    h.forEach((v, i) => { const bh = (H - 30) * Math.sqrt(v / top); ctx.fillRect(30 + i * bw, H - 18 - bh, bw - 1, bh); });
    const xT = 30 + (W - 40) / 2;            // the bins span [0, 2 T]: the period is the middle
    ctx.strokeStyle = "#c62828"; ctx.lineWidth = 2; ctx.beginPath(); ctx.moveTo(xT, 4); ctx.lineTo(xT, H - 18); ctx.stroke();
    ctx.fillStyle = "#333";
    ctx.fillText("0", 30, H - 4); ctx.fillText(`T = ${fmt(S.periodUs)} µs`, xT - 30, H - 4);
    ctx.fillText(`2T`, W - 20, H - 4);
    $("histnote").textContent = `${tot} samples; ${S.histOver || 0} beyond 2T (height: square root of the count)`;
  }

  // ------------------------------------------------------------------ (k, b) grid
  function drawGrid() {
    const cv = $("grid"), ctx = cv.getContext("2d"), W = cv.width, H = cv.height;
    const g = S.grid;
    ctx.clearRect(0, 0, W, H);
    if (!g) { ctx.fillText(S.layout && S.layout.dim > 1 ?
      "the grid is the 1-D loop's (hapsim map); this scene's margin is its spectral radius" :
      "computing the grid…", 10, 20); return; }
    if (g.error) { ctx.fillText(`no grid: ${g.error}`, 10, 20); return; }
    const bb = g.b_bias || 0, pts = [];
    const add = (K, B) => { if (K !== null && B !== null) pts.push([K, B + bb]); };
    g.K.forEach((row, i) => row.forEach((K, j) => add(K, g.B[i][j])));
    (g.identity_K || []).forEach((row, i) => row.forEach((K, j) => add(K, g.identity_B[i][j])));
    const f = S.felt, tg = target(g);
    if (f.port_K !== undefined) add(f.port_K, f.port_B);
    if (tg) add(tg.k, tg.b - bb);
    let k0 = 0, k1 = Math.max(...pts.map((p) => p[0])) * 1.1;
    let b0 = Math.min(0, ...pts.map((p) => p[1])), b1 = Math.max(...pts.map((p) => p[1])) * 1.1;
    const X = (K) => 50 + (K - k0) / (k1 - k0) * (W - 60), Y = (B) => H - 30 - (B - b0) / (b1 - b0) * (H - 40);
    const line = (xs, ys, style, width, dash) => {
      ctx.strokeStyle = style; ctx.lineWidth = width; ctx.setLineDash(dash || []); ctx.beginPath();
      let on = false;
      for (let i = 0; i < xs.length; i++) {
        if (xs[i] === null || ys[i] === null) { on = false; continue; }
        const px = X(xs[i]), py = Y(ys[i] + bb);
        if (!on) { ctx.moveTo(px, py); on = true; } else ctx.lineTo(px, py);
      }
      ctx.stroke(); ctx.setLineDash([]);
    };
    const cols = (M, j) => M.map((r) => r[j]);
    if (g.identity_K) {
      g.identity_K.forEach((r, i) => line(r, g.identity_B[i], "#bbb", 1, [3, 3]));
      g.identity_K[0].forEach((_, j) => line(cols(g.identity_K, j), cols(g.identity_B, j), "#bbb", 1, [3, 3]));
    }
    g.K.forEach((r, i) => line(r, g.B[i], "#1565c0", 1.2));
    g.K[0].forEach((_, j) => line(cols(g.K, j), cols(g.B, j), "#2e7d32", 1.2));
    if (g.boundary_K) line(g.boundary_K, g.boundary_B, "#000", 2.5);
    ctx.fillStyle = "#333";
    ctx.fillText(`K [${S.units.stiffness}] →`, W - 70, H - 8); ctx.save(); ctx.translate(12, H / 2 + 40);
    ctx.rotate(-Math.PI / 2); ctx.fillText(`B + b0 [${S.units.friction}] →`, 0, 0); ctx.restore();
    ctx.fillText(`${fmt(k1)}`, W - 40, H - 18); ctx.fillText(`${fmt(b1)}`, 20, 14);
    const dotAt = (K, B, color, label, ek, eb) => {
      if (K === null || B === null || K === undefined || B === undefined || Number.isNaN(K)) return;
      const px = X(K), py = Y(B);
      if (ek || eb) {
        ctx.strokeStyle = color; ctx.lineWidth = 1; ctx.beginPath();
        if (ek) { ctx.moveTo(X(K - ek), py); ctx.lineTo(X(K + ek), py); }
        if (eb) { ctx.moveTo(px, Y(B - eb)); ctx.lineTo(px, Y(B + eb)); }
        ctx.stroke();
      }
      ctx.fillStyle = color; ctx.beginPath(); ctx.arc(px, py, 5, 0, 2 * Math.PI); ctx.fill();
      ctx.fillText(label, px + 7, py - 7);
    };
    if (f.port_K !== undefined) dotAt(f.port_K, f.port_B + bb, "#e65100", "simulated (K, B)");
    if (tg) {                  // the target: a ring on the identity grid
      ctx.strokeStyle = "#2e7d32"; ctx.lineWidth = 2; ctx.beginPath();
      ctx.arc(X(tg.k), Y(tg.b), 8, 0, 2 * Math.PI); ctx.stroke();
      ctx.fillStyle = "#2e7d32"; ctx.fillText(tg.label, X(tg.k) + 10, Y(tg.b) + 14);
    }
    dotAt(f.k, f.b, "#6a1b9a", "predicted felt (k, b)");
    // the measurements so far, oldest faint: the stated uncertainty shrinking as the record grows
    const ms = S.measurements.filter((q) => q.k !== undefined && q.k !== null);
    ms.slice(0, -1).forEach((q) => {
      ctx.globalAlpha = 0.35;
      dotAt(q.k, q.b, "#c62828", "", q.k_unc, q.b_unc);
      ctx.globalAlpha = 1;
    });
    const mm = S.measured;
    if (mm.k !== null && mm.k !== undefined) dotAt(mm.k, mm.b, "#c62828",
      mm.final ? "measured (k, b): the report's" : `measured (k, b), ${mm.rows || "?"} samples`,
      mm.k_unc, mm.b_unc);
  }
  // the felt target: the scene's target links (their sum), else the scene's own (K, B + b0),
  // which a perfect simulator would render (the identity grid)
  function target(g) {
    const T = (S.layout && S.layout.targets) || [];
    if (T.length) return { k: T.reduce((a, t) => a + t.k, 0), b: T.reduce((a, t) => a + t.b, 0),
                           label: "target (k, b)" };
    const f = S.felt;
    if (f.port_K === undefined || f.port_K === null) return null;
    return { k: f.port_K, b: f.port_B + (g.b_bias || 0), label: "target: the scene's (K, B + b0)" };
  }
  function feltText() {
    const f = S.felt, m = S.measured;
    if (!f || f.k === undefined) return;
    const margin = f.stiffness_limit ? 1 - (f.port_K || 0) / f.stiffness_limit : null;
    $("felt").textContent = `predicted felt k ${fmt(f.k)} ${S.units.stiffness}, b ${fmt(f.b)} ${S.units.friction} ` +
      `(f0 ${fmt(f.f0_hz)} Hz, ζ ${fmt(f.damping_ratio)}); spectral radius ${fmt(f.spectral_radius)} ` +
      `(${f.stable ? "stable" : "UNSTABLE"})` +
      (margin !== null ? `; stiffness margin to the boundary ${fmt(100 * margin)} % (K max ${fmt(f.stiffness_limit)} ${S.units.stiffness})` : "") +
      `. Measured: ` + (m.k !== null && m.k !== undefined ?
        `k ${fmt(m.k)} ± ${fmt(m.k_unc)} ${S.units.stiffness}, b ${fmt(m.b)} ± ${fmt(m.b_unc)} ${S.units.friction}` +
        (m.rows ? ` on ${m.rows} samples` : "") + (m.final ? " (the report's)" :
          S.measurements.length ? ` (${S.measurements.length} measurements as the record grew)` : "") +
        (m.verdict ? `, ${m.verdict}` : "") : (m.why_not || "–")) +
      ". Blue: iso-k, green: iso-b, dashed: identity (a perfect simulator), bold: stability boundary; " +
      "green ring: the target; red: the measured pair with its stated uncertainty, earlier ones faint.";
  }
})();
