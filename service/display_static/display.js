// drillnav surgeon's display. Live data arrive over one WebSocket (/ws); the trajectory is drawn here, at the
// browser's frame rate, from the newest axis and each view's 3x4 projection matrix. Nothing is fetched from
// outside the daemon. State a test or benchmark reads is in window.drillnav (read-only for them).
"use strict";

const STALE_MS = 500;          // no new axis for this long: the overlay greys out and an alert shows
const CAMERA_LOST_MS = 1500;   // no camera preview (sent at ~5 Hz) for this long
const COLOURS = { axis: "#F0E442", cone: "#E69F00", plan: "#56B4E9", entry: "#CC79A7", ok: "#009E73", alarm: "#D55E00", stale: "#9a9a9a" };
const CONE_REACH_MM = 400;     // the cone is drawn this far either side of the working point
const PANEL_PERIOD_MS = 200;   // the numbers' text is rewritten at most this often: text that changes every frame re-lays out the page every frame
const CAMERA_WIDTH_PX = 320;   // the preview is decoded straight to this width, off the main thread

const S = window.drillnav = {
  connected: false, serverOffsetMs: 0, plan: [], ctAvailable: false,
  axis: null, axisRecvPerf: 0, axisCt: null, axisCtRecvPerf: 0, status: null, markers: null, cameraStamp: 0, cameraRecvPerf: 0,
  views: {},                   // name -> {stamp_ns, P (3x4), rows, columns, image, canvas, overlay, drawn}
  newAxis: false, newAxisCt: false, lastDrawnStamp: 0,
  latenciesMs: [], hubToDrawnMs: [], repeats: 0, framesDrawn: 0, axesReceived: 0, alerts: [], mode: "fluoro", ct: null, ctDrawn: null,
  camerasShown: 0, panelAt: -Infinity, preview: null, tagsDrawn: null,
};

// ---- small linear algebra ------------------------------------------------------------------------------
const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const mul = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => Math.hypot(a[0], a[1], a[2]);
const unit = (a) => mul(a, 1 / norm(a));
const apply4 = (T, p) => [0, 1, 2].map((r) => T[r][0] * p[0] + T[r][1] * p[1] + T[r][2] * p[2] + T[r][3]);
const applyDir4 = (T, d) => [0, 1, 2].map((r) => T[r][0] * d[0] + T[r][1] * d[1] + T[r][2] * d[2]);
function inv3(m) {
  const [a, b, c] = m[0], [d, e, f] = m[1], [g, h, i] = m[2];
  const A = e * i - f * h, B = -(d * i - f * g), C = d * h - e * g;
  const det = a * A + b * B + c * C;
  return [[A / det, -(b * i - c * h) / det, (b * f - c * e) / det],
          [B / det, (a * i - c * g) / det, -(a * f - c * d) / det],
          [C / det, -(a * h - b * g) / det, (a * e - b * d) / det]];
}
function invRigid4(T) {  // inverse of a rigid 4x4 (rotation + translation)
  const R = [[T[0][0], T[1][0], T[2][0]], [T[0][1], T[1][1], T[2][1]], [T[0][2], T[1][2], T[2][2]]];
  const t = [T[0][3], T[1][3], T[2][3]];
  const it = R.map((row) => -(row[0] * t[0] + row[1] * t[1] + row[2] * t[2]));
  return [[...R[0], it[0]], [...R[1], it[1]], [...R[2], it[2]], [0, 0, 0, 1]];
}

// ---- projection (pixels: column, row; (0, 0) the centre of the first pixel, as registration/carm.py) -----
function projectH(P, X) { return [0, 1, 2].map((r) => P[r][0] * X[0] + P[r][1] * X[1] + P[r][2] * X[2] + P[r][3]); }
function project(P, X) { const h = projectH(P, X); return h[2] > 1e-9 ? [h[0] / h[2], h[1] / h[2]] : null; }
function sourceOf(P) { const Mi = inv3(P.map((r) => r.slice(0, 3))); return mul([0, 1, 2].map((r) => dot(Mi[r], [P[0][3], P[1][3], P[2][3]])), -1); }

// The image of an infinite 3-D line, clipped to the detector: the homogeneous line through the images of two of
// its points, cut by the image rectangle. Returns [[c0, r0], [c1, r1]] ordered along the drill's direction.
function clipLineToImage(P, point, dir, cols, rows) {
  const a = projectH(P, point), b = projectH(P, add(point, mul(dir, 100)));
  const l = cross(a, b);
  const x0 = -0.5, y0 = -0.5, x1 = cols - 0.5, y1 = rows - 0.5, hits = [];
  if (Math.abs(l[1]) > 1e-12) for (const x of [x0, x1]) { const y = -(l[0] * x + l[2]) / l[1]; if (y >= y0 - 1e-6 && y <= y1 + 1e-6) hits.push([x, y]); }
  if (Math.abs(l[0]) > 1e-12) for (const y of [y0, y1]) { const x = -(l[1] * y + l[2]) / l[0]; if (x >= x0 - 1e-6 && x <= x1 + 1e-6) hits.push([x, y]); }
  if (hits.length < 2) return null;
  let best = null, bd = -1;  // the two hits farthest apart (a corner gives duplicates)
  for (let i = 0; i < hits.length; i++) for (let j = i + 1; j < hits.length; j++) {
    const d = Math.hypot(hits[i][0] - hits[j][0], hits[i][1] - hits[j][1]); if (d > bd) { bd = d; best = [hits[i], hits[j]]; }
  }
  const pa = project(P, point), pb = project(P, add(point, mul(dir, 100)));
  if (pa && pb && (best[1][0] - best[0][0]) * (pb[0] - pa[0]) + (best[1][1] - best[0][1]) * (pb[1] - pa[1]) < 0) best.reverse();
  return best;
}

// An image intensifier bends the image: the registration's estimate of a view's distortion k = [pincushion, S], the
// shift at the field's corner (px), moves an ideal pixel as registration/carm.py's intensifier_shift_px does.
const CURVE_POINTS = 65;
function distort(v, uv, k) {
  if (!k || !uv) return uv;
  const cx = (v.columns - 1) / 2, cy = (v.rows - 1) / 2, R = Math.hypot(cx, cy);
  const dx = uv[0] - cx, dy = uv[1] - cy, r2 = (dx * dx + dy * dy) / (R * R * R);
  return [uv[0] + (k[0] * dx - k[1] * dy) * r2, uv[1] + (k[0] * dy + k[1] * dx) * r2];
}
function projectV(v, X, k) { return distort(v, project(v.P, X), k); }
function bent(v, a, b, k, n = 17) {  // the image of the 3-D segment a-b: n points, bent by the view's distortion
  return Array.from({ length: n }, (_, i) => projectV(v, add(a, mul(sub(b, a), i / (n - 1))), k)).filter((q) => q);
}

// The axis's image bent by an intensifier (registration/overlay.py axis_curve_px): the ideal line a little past the
// border either side, CURVE_POINTS points, distorted, then cut at the border.
function axisCurve(v, point, dir, k) {
  const a = project(v.P, point), b = project(v.P, add(point, mul(dir, 100)));
  if (!a || !b) return null;
  const L = Math.hypot(b[0] - a[0], b[1] - a[1]), u = [(b[0] - a[0]) / L, (b[1] - a[1]) / L];
  const cx = (v.columns - 1) / 2, cy = (v.rows - 1) / 2, t0 = (cx - a[0]) * u[0] + (cy - a[1]) * u[1];
  const mid = [a[0] + t0 * u[0], a[1] + t0 * u[1]], reach = 1.2 * Math.hypot(cx, cy);
  const pts = Array.from({ length: CURVE_POINTS }, (_, i) => { const t = -reach + (2 * reach * i) / (CURVE_POINTS - 1); return distort(v, [mid[0] + t * u[0], mid[1] + t * u[1]], k); });
  const lo = -0.5, hx = v.columns - 0.5, hy = v.rows - 0.5;
  const inside = (q) => q[0] >= lo && q[0] <= hx && q[1] >= lo && q[1] <= hy;
  const i = pts.findIndex(inside);
  if (i < 0) return null;
  let j = pts.length - 1; while (!inside(pts[j])) j--;
  const cut = (p, q) => {  // p outside, q inside: where p-q crosses the border
    let t = 0;
    for (const [c, h] of [[0, hx], [1, hy]]) {
      if (p[c] < lo) t = Math.max(t, (lo - p[c]) / (q[c] - p[c]));
      if (p[c] > h) t = Math.max(t, (h - p[c]) / (q[c] - p[c]));
    }
    t = Math.min(1, t);
    return [p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])];
  };
  const curve = pts.slice(i, j + 1);
  if (i > 0) curve.unshift(cut(pts[i - 1], pts[i]));
  if (j < pts.length - 1) curve.push(cut(pts[j + 1], pts[j]));
  return curve;
}

// ---- WebSocket -------------------------------------------------------------------------------------------
function connect() {
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`);
  ws.onopen = () => { S.connected = true; };
  ws.onclose = () => { S.connected = false; setTimeout(connect, 1000); };
  ws.onmessage = (ev) => {
    const m = JSON.parse(ev.data), now = performance.now();
    switch (m.type) {
      case "hello":
        S.serverOffsetMs = Date.now() - m.server_ns / 1e6; S.plan = m.plan; S.ctAvailable = m.ct;
        document.getElementById("b-ct").disabled = !m.ct;
        if (m.ct && !S.ct) loadCt();
        break;
      case "axis":
        if (S.axis && m.data.source_frame_stamp_ns <= S.axis.source_frame_stamp_ns) { S.repeats++; break; }  // never again as new
        S.axis = m.data; S.axisRecvPerf = now; S.axisHubNs = m.recv_ns; S.newAxis = true; S.axesReceived++; break;
      case "axis_ct": S.axisCt = m.data; S.axisCtRecvPerf = now; S.newAxisCt = true; break;
      case "status": S.status = m.data; S.serverOffsetMs = Date.now() - m.server_ns / 1e6; break;
      case "markers": S.markers = m.data; break;
      case "camera": showCamera(m, now); break;
      case "view": addView(m); break;
      case "event": addEvent(m.data); break;
    }
  };
}

function serverNowMs() { return Date.now() - S.serverOffsetMs; }
function ageS(stampNs) { return Math.max(0, (serverNowMs() - stampNs / 1e6) / 1000); }
function fmtAge(s) { return s < 60 ? `${s.toFixed(s < 10 ? 1 : 0)} s` : `${Math.floor(s / 60)} min ${Math.round(s % 60)} s`; }

// The preview is decoded by createImageBitmap (off the main thread, straight to the preview's size) and drawn on a
// small canvas: an <img> given a data URL decodes the full frame on the main thread at paint, in the frame that
// draws the axis. A preview arriving while the previous one decodes is skipped (a thumbnail, a few per second).
let cameraDecoding = false;
function showCamera(m, now) {
  S.cameraStamp = m.stamp_ns; S.cameraRecvPerf = now;
  if (cameraDecoding) return;
  cameraDecoding = true;
  const bin = atob(m.data_base64), bytes = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
  const blob = new Blob([bytes], { type: m.format === "png" ? "image/png" : "image/jpeg" });
  const stamp = m.stamp_ns, tags = m.tags;
  createImageBitmap(blob, { resizeWidth: CAMERA_WIDTH_PX, resizeQuality: "medium" }).then((bmp) => {
    if (S.preview) S.preview.bmp.close();
    S.preview = { bmp, stamp, tags };
    drawPreview();
    S.camerasShown++;
  }).catch(() => {}).finally(() => { cameraDecoding = false; });  // an undecodable preview: the next one tries again
}

// The preview with the tags the node found in that very frame (the hub sends them together; null when the node
// tracks nothing): outlined and numbered. Tags of another frame are never drawn on it.
function drawPreview() {
  const c = document.getElementById("camera-canvas"), { bmp, stamp, tags: t } = S.preview;
  if (c.width !== bmp.width || c.height !== bmp.height) { c.width = bmp.width; c.height = bmp.height; }
  const ctx = c.getContext("2d");
  ctx.drawImage(bmp, 0, 0);
  if (!t || t.stamp_ns !== stamp) { S.tagsDrawn = null; return; }
  const k = c.width / t.image_size[0];
  ctx.font = "bold 18px sans-serif"; ctx.textAlign = "center"; ctx.textBaseline = "middle"; ctx.lineJoin = "round";
  for (const tag of t.markers) {
    const q = tag.corners_px.map(([x, y]) => [(x + 0.5) * k - 0.5, (y + 0.5) * k - 0.5]);
    ctx.lineWidth = 2; ctx.strokeStyle = COLOURS.ok; polyline(ctx, q); ctx.closePath(); ctx.stroke();
    // The id beside the tag, white on a black edge: legible over the tag's own pattern and the background alike.
    const cx = q.reduce((s, p) => s + p[0], 0) / 4, top = Math.min(...q.map((p) => p[1]));
    const y = top > 14 ? top - 10 : Math.max(...q.map((p) => p[1])) + 10;
    ctx.lineWidth = 4; ctx.strokeStyle = "#000"; ctx.strokeText(String(tag.id), cx, y);
    ctx.fillStyle = "#fff"; ctx.fillText(String(tag.id), cx, y);
  }
  S.tagsDrawn = { stamp_ns: stamp, ids: t.markers.map((tag) => tag.id), scale: k };
}

function addEvent(e) {
  const li = document.createElement("li");
  li.className = e.level;
  li.textContent = `${new Date(e.stamp_ns / 1e6).toLocaleTimeString()} ${e.message}`;
  const ol = document.getElementById("events");
  ol.prepend(li);
  while (ol.children.length > 30) ol.lastChild.remove();
}

function addView(m) {
  let v = S.views[m.name];
  if (!v) {
    const fig = document.createElement("figure"); fig.className = "view"; fig.dataset.view = m.name;
    const stack = document.createElement("div"); stack.className = "stack";
    const image = document.createElement("canvas"), overlay = document.createElement("canvas");
    overlay.className = "overlay"; stack.append(image, overlay);
    const cap = document.createElement("figcaption"); cap.innerHTML = `<span class="name"></span><span class="age"></span>`;
    fig.append(stack, cap); document.getElementById("views").append(fig);
    v = S.views[m.name] = { fig, image, overlay, cap, drawn: null };
  }
  document.getElementById("no-views").hidden = true;
  const pj = m.projection;
  // Until its image has loaded (and sized the canvases), a view shows nothing: no axis on a stale geometry.
  Object.assign(v, { name: m.name, ready: false, drawn: null, stamp_ns: m.stamp_ns, P: pj.projection_matrix, rows: pj.rows, columns: pj.columns, source: sourceOf(pj.projection_matrix) });
  v.cap.querySelector(".name").textContent = m.name;
  const img = new Image();
  img.onload = () => {
    for (const c of [v.image, v.overlay]) { c.width = pj.columns; c.height = pj.rows; }
    v.image.getContext("2d").drawImage(img, 0, 0);
    v.ready = true; v.forceDraw = true;
  };
  img.src = `data:image/png;base64,${m.png_base64}`;
  for (const name of Object.keys(S.views)) if (!m.views.includes(name)) { S.views[name].fig.remove(); delete S.views[name]; }
}

// ---- plan in C: through carm_from_ct of the newest CT registration ----------------------------------------
function planInCarm() {
  if (!S.axisCt || !S.axisCt.carm_from_ct || !S.plan.length) return [];
  const T = S.axisCt.carm_from_ct;
  return S.plan.map((t) => ({ name: t.name, entry: apply4(T, t.entry_mm), target: apply4(T, t.target_mm), radius: t.radius_mm }));
}

// ---- drawing on a fluoroscopy view ---------------------------------------------------------------------
function polyline(ctx, pts) { ctx.beginPath(); pts.forEach((p, i) => (i ? ctx.lineTo(p[0] + 0.5, p[1] + 0.5) : ctx.moveTo(p[0] + 0.5, p[1] + 0.5))); }

function drawView(v, axis, stale) {
  const ctx = v.overlay.getContext("2d"), W = v.columns, H = v.rows;
  ctx.clearRect(0, 0, W, H);
  const lw = Math.max(3, W / 220);  // ~4-5 px on a 976 px view shown ~500 px wide: visible across the room
  // The view's intensifier distortion as the axis's registration estimated it (none for a flat panel).
  const k = (axis && axis.detector_distortion_px && axis.detector_distortion_px[v.name]) || null;
  // Planned trajectories and corridors.
  for (const t of planInCarm()) {
    const d = unit(sub(t.target, t.entry));
    const mid = mul(add(t.entry, t.target), 0.5);
    const side = unit(cross(d, unit(sub(mid, v.source))));
    ctx.strokeStyle = COLOURS.plan; ctx.lineWidth = lw * 0.6; ctx.setLineDash([]);
    for (const s of [-1, 1]) {
      const edge = bent(v, add(t.entry, mul(side, s * t.radius)), add(t.target, mul(side, s * t.radius)), k);
      if (edge.length > 1) { polyline(ctx, edge); ctx.stroke(); }
    }
    const centre = bent(v, t.entry, t.target, k), a = projectV(v, t.entry, k);
    if (centre.length > 1) { ctx.setLineDash([lw * 3, lw * 2]); ctx.lineWidth = lw; polyline(ctx, centre); ctx.stroke(); ctx.setLineDash([]); }
    if (a) { ctx.beginPath(); ctx.arc(a[0] + 0.5, a[1] + 0.5, lw * 2.5, 0, 2 * Math.PI); ctx.stroke(); }
  }
  if (!axis) { v.drawn = null; return; }
  const p = axis.point_mm, dir = unit(axis.direction);
  const col = stale ? COLOURS.stale : COLOURS.axis;
  // Error cone: the predicted position error at the working point, widening with the angle error either side.
  const pe = axis.predicted_error || { position_mm: 0, angle_deg: 0 };
  const tanA = Math.tan((pe.angle_deg * Math.PI) / 180), upper = [], lower = [];
  for (let s = -CONE_REACH_MM; s <= CONE_REACH_MM; s += 20) {
    const c = add(p, mul(dir, s));
    const side = unit(cross(dir, unit(sub(c, v.source))));
    const r = pe.position_mm + Math.abs(s) * tanA;
    const a = projectV(v, add(c, mul(side, r)), k), b = projectV(v, add(c, mul(side, -r)), k);
    if (a && b) { upper.push(a); lower.push(b); }
  }
  if (upper.length > 1) {
    ctx.fillStyle = stale ? "rgba(154,154,154,0.25)" : "rgba(230,159,0,0.28)";
    polyline(ctx, upper.concat(lower.reverse())); ctx.closePath(); ctx.fill();
    ctx.strokeStyle = stale ? COLOURS.stale : COLOURS.cone; ctx.lineWidth = lw * 0.5;
    polyline(ctx, upper); ctx.stroke(); polyline(ctx, lower.reverse()); ctx.stroke();
  }
  // The axis across the whole image, outlined in black so it reads on bone and on air alike.
  const curve = k ? axisCurve(v, p, dir, k) : clipLineToImage(v.P, p, dir, W, H);
  const seg = curve && curve.length > 1 ? [curve[0], curve[curve.length - 1]] : null;
  if (seg) {
    ctx.setLineDash(stale ? [lw * 4, lw * 3] : []);
    ctx.strokeStyle = "#000"; ctx.lineWidth = lw * 2; polyline(ctx, curve); ctx.stroke();
    ctx.strokeStyle = col; ctx.lineWidth = lw; polyline(ctx, curve); ctx.stroke();
    ctx.setLineDash([]);
    // Arrowhead at the far end: the way the drill advances (along the curve's last piece).
    const a = curve[curve.length - 2], b = curve[curve.length - 1], L = Math.hypot(b[0] - a[0], b[1] - a[1]) || 1;
    const ux = (b[0] - a[0]) / L, uy = (b[1] - a[1]) / L, h = lw * 6;
    const tip = [b[0] - ux * 4 * lw, b[1] - uy * 4 * lw];
    ctx.fillStyle = col; ctx.beginPath(); ctx.moveTo(tip[0] + 0.5, tip[1] + 0.5);
    ctx.lineTo(tip[0] - ux * h - uy * h * 0.5 + 0.5, tip[1] - uy * h + ux * h * 0.5 + 0.5);
    ctx.lineTo(tip[0] - ux * h + uy * h * 0.5 + 0.5, tip[1] - uy * h - ux * h * 0.5 + 0.5); ctx.closePath(); ctx.fill();
  }
  // Entry: where the axis passes the planned entry (nearest point), else the working point.
  const plans = planInCarm();
  let entry = p;
  if (plans.length) {
    const t = plans.reduce((best, t) => (norm(cross(sub(t.entry, p), dir)) < norm(cross(sub(best.entry, p), dir)) ? t : best));
    entry = add(p, mul(dir, dot(sub(t.entry, p), dir)));
  }
  const e = projectV(v, entry, k);
  if (e) {
    ctx.lineWidth = lw; ctx.strokeStyle = "#000"; ctx.fillStyle = stale ? COLOURS.stale : COLOURS.entry;
    ctx.beginPath(); ctx.arc(e[0] + 0.5, e[1] + 0.5, lw * 2, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
  }
  v.drawn = { source_frame_stamp_ns: axis.source_frame_stamp_ns, segment: seg, curve, distortion_px: k, entry_px: e, stale };
}

// ---- video-CT: the volume once, resliced here ------------------------------------------------------------
async function loadCt() {
  const meta = await (await fetch("/display/ct.json")).json();
  const buf = await (await fetch("/display/ct.bin")).arrayBuffer();
  const A = meta.patient_from_voxel;
  const R = inv3(A.map((r) => r.slice(0, 3)));
  const t = [0, 1, 2].map((r) => -dot(R[r], [A[0][3], A[1][3], A[2][3]]));
  S.ct = { shape: meta.shape, data: new Uint8Array(buf), voxelFromPatient: [[...R[0], t[0]], [...R[1], t[1]], [...R[2], t[2]]] };
}

const CT_FOV_MM = 160;

function ctPlanes(axisCt, centre) {
  const d = unit(axisCt.direction), z = [0, 0, 1];
  let down = sub(mul(z, -1), mul(d, dot(mul(z, -1), d)));
  if (norm(down) < 1e-3) down = sub([0, 1, 0], mul(d, d[1]));
  return {
    axial: { c: centre, r: [1, 0, 0], d: [0, 1, 0], labels: ["R", "L", "A", "P"] },
    coronal: { c: centre, r: [1, 0, 0], d: [0, 0, -1], labels: ["R", "L", "H", "F"] },
    sagittal: { c: centre, r: [0, 1, 0], d: [0, 0, -1], labels: ["A", "P", "H", "F"] },
    oblique: { c: centre, r: d, d: unit(down), labels: ["", "", "", ""] },
  };
}

function reslice(canvas, plane) {
  const N = canvas.width, px = CT_FOV_MM / N, ct = S.ct, [nk, nj, ni] = ct.shape, V = ct.voxelFromPatient;
  const ctx = canvas.getContext("2d"), img = ctx.createImageData(N, N), out = img.data, src = ct.data;
  const half = N / 2 - 0.5;
  const o = apply4(V, add(plane.c, add(mul(plane.r, -half * px), mul(plane.d, -half * px))));
  const du = applyDir4(V, mul(plane.r, px)), dv = applyDir4(V, mul(plane.d, px));
  for (let row = 0; row < N; row++) {
    let x = o[0] + dv[0] * row, y = o[1] + dv[1] * row, z = o[2] + dv[2] * row;
    for (let c = 0, q = row * N * 4; c < N; c++, q += 4, x += du[0], y += du[1], z += du[2]) {
      const i = Math.round(x), j = Math.round(y), k = Math.round(z);
      const g = i >= 0 && j >= 0 && k >= 0 && i < ni && j < nj && k < nk ? src[(k * nj + j) * ni + i] : 0;
      out[q] = out[q + 1] = out[q + 2] = g; out[q + 3] = 255;
    }
  }
  ctx.putImageData(img, 0, 0);
}

function drawCt(stale) {
  const a = S.axisCt;
  const verdict = document.getElementById("verdict");
  if (!a || !S.ct) { verdict.className = "verdict unknown"; verdict.textContent = S.ct ? "waiting for the CT registration…" : "loading CT…"; return; }
  const dir = unit(a.direction), p = a.point_mm, conf = a.conformance;
  const plan = conf ? S.plan.find((t) => t.name === conf.trajectory) : null;
  // Planes through the axis at the middle of the planned stretch: the 160 mm field holds entry to target.
  const centre = plan ? add(p, mul(dir, dot(sub(mul(add(plan.entry_mm, plan.target_mm), 0.5), p), dir))) : p;
  const planes = ctPlanes(a, centre);
  const col = stale ? COLOURS.stale : COLOURS.axis;
  const pe = a.predicted_error || { position_mm: 0, angle_deg: 0 }, tanA = Math.tan((pe.angle_deg * Math.PI) / 180);
  for (const [name, pl] of Object.entries(planes)) {
    const canvas = document.getElementById(`ct-${name}`), N = canvas.width, px = CT_FOV_MM / N, half = N / 2 - 0.5;
    reslice(canvas, pl);
    const ctx = canvas.getContext("2d"), lw = Math.max(2, N / 160);
    const toPx = (X) => { const q = sub(X, pl.c); return [dot(q, pl.r) / px + half, dot(q, pl.d) / px + half]; };
    const n = unit(cross(pl.r, pl.d));
    for (const t of S.plan) {
      const td = unit(sub(t.target_mm, t.entry_mm));
      let across = name === "oblique" ? pl.d : cross(td, n);
      ctx.strokeStyle = COLOURS.plan; ctx.lineWidth = lw * 0.6;
      if (norm(across) > 1e-6) {
        across = unit(sub(across, mul(td, dot(across, td))));
        for (const s of [-1, 1]) { polyline(ctx, [toPx(add(t.entry_mm, mul(across, s * t.radius_mm))), toPx(add(t.target_mm, mul(across, s * t.radius_mm)))]); ctx.stroke(); }
      }
      ctx.setLineDash([lw * 3, lw * 2]); ctx.lineWidth = lw; polyline(ctx, [toPx(t.entry_mm), toPx(t.target_mm)]); ctx.stroke(); ctx.setLineDash([]);
    }
    const side = cross(dir, n);
    if (norm(side) > 1e-6) {
      const sd = unit(side), up = [], lo = [];
      for (let s = -200; s <= 200; s += 10) {
        const c = add(centre, mul(dir, s)), r = pe.position_mm + Math.abs(s) * tanA;
        up.push(toPx(add(c, mul(sd, r)))); lo.push(toPx(add(c, mul(sd, -r))));
      }
      ctx.fillStyle = stale ? "rgba(154,154,154,0.25)" : "rgba(230,159,0,0.30)";
      polyline(ctx, up.concat(lo.reverse())); ctx.closePath(); ctx.fill();
    }
    const a0 = toPx(add(centre, mul(dir, -400))), a1 = toPx(add(centre, mul(dir, 400)));
    ctx.setLineDash(stale ? [lw * 4, lw * 3] : []);
    ctx.strokeStyle = "#000"; ctx.lineWidth = lw * 2; polyline(ctx, [a0, a1]); ctx.stroke();
    ctx.strokeStyle = col; ctx.lineWidth = lw; polyline(ctx, [a0, a1]); ctx.stroke(); ctx.setLineDash([]);
    if (conf && conf.min_clearance_point_mm) {
      const m = toPx(conf.min_clearance_point_mm);
      ctx.strokeStyle = conf.breach ? COLOURS.alarm : COLOURS.ok; ctx.lineWidth = lw;
      ctx.beginPath(); ctx.arc(m[0] + 0.5, m[1] + 0.5, lw * 4, 0, 2 * Math.PI); ctx.stroke();
    }
    ctx.fillStyle = "#ddd"; ctx.font = `bold ${Math.round(N / 16)}px sans-serif`;
    const [l, r, t, b] = pl.labels;
    ctx.textAlign = "left"; ctx.fillText(l, 4, N / 2); ctx.textAlign = "right"; ctx.fillText(r, N - 4, N / 2);
    ctx.textAlign = "center"; ctx.fillText(t, N / 2, N / 14); ctx.fillText(b, N / 2, N - 6);
  }
  if (!conf) { verdict.className = "verdict unknown"; verdict.textContent = "no planned trajectory within 45° of the axis"; }
  else {
    const where = conf.min_clearance_along_mm != null ? ` at ${conf.min_clearance_along_mm.toFixed(0)} mm into bone` : "";
    const clr = conf.min_clearance_mm == null ? "axis misses the bone" : `min clearance ${conf.min_clearance_mm.toFixed(1)} mm${where}`;
    verdict.className = `verdict ${conf.breach ? "breach" : "clear"}`;
    verdict.textContent = `${conf.breach ? "BREACH" : "CLEAR"} (${conf.trajectory}): ${clr}`;
  }
  S.ctDrawn = { stamp_ns: a.stamp_ns, breach: conf ? conf.breach : null, stale };
}

// ---- the always-on numbers and the alerts ------------------------------------------------------------------
function alerts(now) {
  const out = [], st = S.status || {}, a = S.axis;
  if (!S.connected) out.push(["critical", "NO CONNECTION TO THE DAEMON"]);
  if (S.cameraRecvPerf && now - S.cameraRecvPerf > CAMERA_LOST_MS) out.push(["critical", "CAMERA LOST"]);
  else if (!S.cameraRecvPerf && S.connected && st.state) out.push(["critical", "NO CAMERA"]);
  if (a && now - S.axisRecvPerf > STALE_MS) out.push(["critical", `AXIS STALE: no update for ${((now - S.axisRecvPerf) / 1000).toFixed(1)} s`]);
  if (typeof st.state === "string" && st.state.startsWith("registration failed")) out.push(["critical", "REGISTRATION FAILED"]);
  if (a && a.markers_rejected && a.markers_rejected.length) out.push(["critical", `MARKER ${a.markers_rejected.join(", ")} MOVED? Re-shoot`]);
  if (st.ct_last_error) out.push(["warning", "CT NOT CONVERGED"]);
  const c = S.axisCt && S.axisCt.conformance;
  if (c && c.breach && now - S.axisCtRecvPerf <= STALE_MS) out.push(["critical", `BREACH: ${c.trajectory}`]);
  return out;
}

function updatePanel(now, force) {
  updateAlerts(now);  // every frame: an alert must never wait
  if (!force && now - S.panelAt < PANEL_PERIOD_MS) return;
  S.panelAt = now;
  const a = S.axis, st = S.status || {};
  const set = (id, text, bad) => { const e = document.getElementById(id); if (e.textContent !== text) e.textContent = text; e.parentElement.classList.toggle("bad", !!bad); };
  if (a) set("v-error", `${a.predicted_error.position_mm.toFixed(1)} mm, ${a.predicted_error.angle_deg.toFixed(1)}°`, a.predicted_error.position_mm > 2 || a.predicted_error.angle_deg > 2);
  else set("v-error", "–", true);
  if (S.markers) set("v-reg", `#${S.markers.registration_id}, ${fmtAge(ageS(S.markers.stamp_ns))} ago`, false);
  else set("v-reg", st.state || "–", true);
  if (a) {
    const seen = [...(a.markers_used || []), ...(a.markers_rejected || [])].sort((x, y) => x - y);
    const reg = S.markers ? S.markers.markers.filter((m) => m.converged).map((m) => m.id).sort((x, y) => x - y) : [];
    set("v-markers", `${seen.join(" ")} / ${reg.join(" ")}`, (a.markers_rejected || []).length > 0);
  }
  set("v-axis", a ? (now - S.axisRecvPerf > STALE_MS ? "STALE" : `live, ${Math.max(0, serverNowMs() - a.source_frame_stamp_ns / 1e6).toFixed(0)} ms`) : "none", !a || now - S.axisRecvPerf > STALE_MS);
  for (const v of Object.values(S.views)) {
    const t = `${fmtAge(ageS(v.stamp_ns))} ago`;
    const age = v.cap.querySelector(".age"); if (age.textContent !== t) age.textContent = t;
  }
  if (S.cameraStamp) { const cap = document.getElementById("camera-cap"), t = `camera, ${fmtAge(ageS(S.cameraStamp))} ago`; if (cap.textContent !== t) cap.textContent = t; }
}

function updateAlerts(now) {
  const list = alerts(now);
  const key = JSON.stringify(list);
  if (key !== S.alertsKey) {
    S.alerts = list; S.alertsKey = key;
    const box = document.getElementById("alerts"); box.replaceChildren();
    for (const [level, text] of list) { const d = document.createElement("div"); d.className = `alert ${level}`; d.textContent = text; box.append(d); }
  }
}

// ---- the frame loop --------------------------------------------------------------------------------------
let lastStale = null;
function frame(t) {
  const now = performance.now();
  const stale = !S.axis || now - S.axisRecvPerf > STALE_MS;
  const fresh = S.newAxis; S.newAxis = false;
  if (S.mode === "fluoro") {
    for (const v of Object.values(S.views)) {
      if (!v.ready) continue;
      if (fresh || v.forceDraw || stale !== lastStale) { drawView(v, S.axis, stale); v.fig.classList.toggle("stale", stale); v.forceDraw = false; }
    }
  }
  if (fresh) {
    // rAF time and capture stamp on one clock (one machine): glass-to-glass to the frame that shows this axis.
    const shownMs = performance.timeOrigin + t;
    S.latenciesMs.push(shownMs - S.axis.source_frame_stamp_ns / 1e6);
    S.hubToDrawnMs.push(shownMs - S.axisHubNs / 1e6);  // the display's own share: hub, socket, browser
    if (S.latenciesMs.length > 100000) { S.latenciesMs.splice(0, 50000); S.hubToDrawnMs.splice(0, 50000); }
    S.framesDrawn++;
  }
  const ctStale = !S.axisCt || now - S.axisCtRecvPerf > STALE_MS;
  if (S.mode === "ct" && S.ct && (S.newAxisCt || ctStale !== S.lastCtStale || !S.ctDrawn)) { drawCt(ctStale); S.newAxisCt = false; S.lastCtStale = ctStale; }
  updatePanel(now, stale !== lastStale);  // going stale (or live) is shown in the same frame as the greyed overlay
  lastStale = stale;
  requestAnimationFrame(frame);
}

function setMode(mode) {
  S.mode = mode; S.ctDrawn = null;
  for (const m of ["fluoro", "ct"]) { document.getElementById(m).hidden = m !== mode; document.getElementById(`b-${m}`).classList.toggle("on", m === mode); }
  for (const v of Object.values(S.views)) v.forceDraw = true;
}

document.querySelectorAll("#modes button").forEach((b) => b.addEventListener("click", () => setMode(b.dataset.mode)));
setMode(new URLSearchParams(location.search).get("mode") === "ct" ? "ct" : "fluoro");
connect();
requestAnimationFrame(frame);
