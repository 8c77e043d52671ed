// mbcal studio: the page.  The server computes every projection; this script draws them over the
// photos (SVG), keeps the operator's edits (sent whole to the server after each one) and the undo
// history.  Image coordinates follow OpenCV: the centre of the top-left pixel is (0, 0).
"use strict";

const SVGNS = "http://www.w3.org/2000/svg";
const $ = (sel) => document.querySelector(sel);
const S = {
  state: null, clicks: [], estimate: [], values: {}, hidden: [], config: "default", views: {},
  armed: null, selected: null, history: [], future: [], nextId: 1, report: null, suggested: [],
  redraws: 0, timings: [], pending: {}, inflight: {},
};
window.studio = S;

function el(tag, attrs = {}, parent = null, ns = null) {
  const e = ns ? document.createElementNS(ns, tag) : document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "text") e.textContent = v; else e.setAttribute(k, v);
  }
  if (parent) parent.appendChild(e);
  return e;
}
const sv = (tag, attrs, parent) => el(tag, attrs, parent, SVGNS);

// The token: the server writes it into the page (no cookie, which every local port would see).
const TOKEN = (document.querySelector('meta[name="studio-token"]') || {}).content || "";
const withToken = (path) => `${path}${path.includes("?") ? "&" : "?"}token=${encodeURIComponent(TOKEN)}`;

async function api(method, path, body) {
  const opts = { method, credentials: "omit", headers: { "X-Studio-Token": TOKEN } };
  if (body !== undefined) {
    opts.headers["Content-Type"] = "application/json";
    opts.body = JSON.stringify(body);
  }
  const r = await fetch(path, opts);
  const data = await r.json().catch(() => ({ error: { message: `HTTP ${r.status}` } }));
  if (!r.ok) {
    showError(data.error || { message: `HTTP ${r.status}` }, true);
    throw new Error((data.error && data.error.message) || `HTTP ${r.status}`);
  }
  if (method !== "GET" && $("#error").dataset.transient === "1") showError(null);  // a later success clears it
  return data;
}

function status(text) { $("#status").textContent = (S.unsaved ? "NOT SAVED — " : "") + text; }

// The model's error stays until the model loads; a refused request's error until the next success.
function showError(err, transient = false) {
  const box = $("#error");
  if (!err) { box.hidden = true; box.dataset.transient = ""; return; }
  box.hidden = false;
  box.dataset.transient = transient ? "1" : "";
  $("#error-location").textContent = err.location ? `${err.message}` : err.message;
  let src = "";
  if (err.source !== null && err.source !== undefined) {
    src = err.source + "\n" + " ".repeat(Math.max(0, (err.column || 1) - 1)) + "^";
  }
  $("#error-source").textContent = src;
}

// ---- short names ----------------------------------------------------------------------------------
function shortPoint(name) {
  const p = (S.state.points || []).find((q) => q.name === name);
  return p ? p.short : name;
}
function shortCamera(name) {
  const c = (S.state.cameras || []).find((q) => q.name === name);
  return c ? c.short : name;
}
function param(name) { return (S.state.params || []).find((p) => p.name === name); }
function globRegex(glob) {
  const esc = glob.replace(/[.+^${}()|\\]/g, "\\$&").replace(/\*/g, ".*").replace(/\?/g, ".");
  return new RegExp("^" + esc + "$");
}
function unknownNames() {
  const out = [];
  for (const pat of S.estimate) {
    const re = globRegex(pat);
    for (const p of S.state.params || []) if (re.test(p.name) && !out.includes(p.name)) out.push(p.name);
  }
  return out;
}
function activeValues() {
  const names = unknownNames();
  const out = {};
  for (const [k, v] of Object.entries(S.values)) {
    if (names.includes(k.split("@")[0])) out[k] = v;  // name, or name@config for per-configuration ones
  }
  return out;
}

// ---- loading -------------------------------------------------------------------------------------
async function loadState() {
  const st = await api("GET", "/api/state");
  S.state = st;
  const ses = st.session;
  S.clicks = ses.clicks; S.estimate = ses.estimate; S.values = ses.values; S.hidden = ses.hidden;
  S.nextId = st.next_id;
  $("#model-name").textContent = st.model;
  showError(st.error);
  $("#notes").textContent = (st.notes || []).join(" · ");
  const sel = $("#config");
  sel.innerHTML = "";
  for (const c of st.configurations) el("option", { value: c, text: c }, sel);
  if (!st.configurations.includes(S.config)) S.config = st.configurations[0];
  sel.value = S.config;
  $("#estimate").value = S.estimate.join(", ");
  buildPointList(); buildObjects(); buildSliders(); buildParamTree(); buildViews(); renderClicks();
  refreshAll();
}

function buildPointList() {
  const ul = $("#pointlist");
  ul.innerHTML = "";
  const q = $("#search").value.trim().toLowerCase();
  for (const p of S.state.points || []) {
    if (q && !p.name.toLowerCase().includes(q)) continue;
    const li = el("li", { "data-point": p.name, title: p.name }, ul);
    const done = S.clicks.filter((c) => c.point === p.name && c.config === S.config).length;
    li.textContent = p.short;
    if (done) el("span", { class: "done", text: ` ✓${done}` }, li);
    if (p.name === S.armed) li.classList.add("armed");
    if (S.suggested.some((s) => s.point === p.name)) li.classList.add("suggested");
    li.addEventListener("click", () => arm(p.name));
  }
}

function buildObjects() {
  const box = $("#objects");
  box.innerHTML = "";
  for (const name of S.state.objects || []) {
    const lab = el("label", {}, box);
    const cb = el("input", { type: "checkbox", "data-object": name }, lab);
    cb.checked = !S.hidden.includes(name);
    lab.appendChild(document.createTextNode(" " + name));
    cb.addEventListener("change", () => {
      S.hidden = S.hidden.filter((h) => h !== name);
      if (!cb.checked) S.hidden.push(name);
      applyHidden();
      saveSession();
    });
  }
}

function applyHidden() {
  for (const v of Object.values(S.views)) {
    for (const path of v.wire.querySelectorAll("path")) {
      path.style.display = S.hidden.includes(path.dataset.object) ? "none" : "";
    }
  }
}

// The parameter tree: parameters grouped by their first name part, each with its search range;
// a check box adds or removes one unknown (a glob that matched it is expanded into its names).
function buildParamTree() {
  const box = $("#params");
  box.innerHTML = "";
  const chosen = unknownNames();
  const groups = {};
  for (const p of S.state.params || []) (groups[p.name.split(".")[0]] ||= []).push(p);
  for (const [group, params] of Object.entries(groups)) {
    const det = el("details", {}, box);
    el("summary", { text: `${group} (${params.length})` }, det);
    if (params.some((p) => chosen.includes(p.name))) det.open = true;
    for (const p of params) {
      const lab = el("label", {}, det);
      const cb = el("input", { type: "checkbox", "data-estimate": p.name }, lab);
      cb.checked = chosen.includes(p.name);
      lab.appendChild(document.createTextNode(" " + p.name + " "));
      const range = p.lower === null ? "no search range" :
        `[${fmt(displayValue(p, p.lower))}, ${fmt(displayValue(p, p.upper))}] ${p.unit}`;
      el("span", { class: "range", text: (p.per_configuration ? "per configuration, " : "") + range }, lab);
      cb.addEventListener("change", () => toggleUnknown(p.name, cb.checked));
    }
  }
}
const fmt = (x) => Number(x).toPrecision(3);

function toggleUnknown(name, on) {
  if (on) { if (!unknownNames().includes(name)) S.estimate.push(name); }
  else {
    const out = [];
    for (const pat of S.estimate) {
      const re = globRegex(pat);
      if (pat === name) continue;
      if (re.test(name)) {  // a glob: keep what else it matched
        for (const p of S.state.params) if (re.test(p.name) && p.name !== name && !out.includes(p.name)) out.push(p.name);
      } else out.push(pat);
    }
    S.estimate = out;
  }
  $("#estimate").value = S.estimate.join(", ");
  setEstimate();
}

function displayValue(p, si) { return p.unit === "deg" ? (si * 180) / Math.PI : si; }
function fromDisplay(p, d) { return p.unit === "deg" ? (d * Math.PI) / 180 : d; }

function buildSliders() {
  const box = $("#sliders");
  box.innerHTML = "";
  for (const name of unknownNames()) {
    const p = param(name);
    if (!p || p.per_configuration) continue;
    let lo = p.lower, hi = p.upper;
    if (lo === null || hi === null) {
      const w = p.unit === "deg" ? 0.2 : Math.max(0.1, Math.abs(p.nominal) * 0.5);
      lo = p.nominal - w; hi = p.nominal + w;
    }
    const cur = name in S.values ? S.values[name] : p.nominal;
    lo = Math.min(lo, cur); hi = Math.max(hi, cur);  // an estimate may leave the search range
    const div = el("div", { class: "slider" }, box);
    const lab = el("div", {}, div);
    const input = el("input", {
      type: "range", "data-param": name,
      min: displayValue(p, lo), max: displayValue(p, hi), step: (displayValue(p, hi) - displayValue(p, lo)) / 2000,
      value: displayValue(p, cur),
    }, div);
    const show = () => { lab.textContent = `${name} = ${Number(input.value).toPrecision(5)} ${p.unit}`; };
    show();
    input.addEventListener("input", () => {
      S.values[name] = fromDisplay(p, Number(input.value));
      show();
      const t0 = performance.now();
      refreshAll(t0, false);
    });
    input.addEventListener("change", () => { saveSession(); refreshAll(undefined, true); });
  }
}

// ---- the camera views -----------------------------------------------------------------------------
function buildViews() {
  const box = $("#views");
  box.innerHTML = "";
  S.views = {};
  const photos = (S.state.photos || []).filter((p) => p.config === S.config);
  for (const ph of photos) {
    const div = el("div", { class: "view", "data-photo": ph.id }, box);
    el("h3", { text: `${shortCamera(ph.camera)} · ${ph.config}` }, div);
    const svg = sv("svg", { viewBox: `-0.5 -0.5 ${ph.width} ${ph.height}`, "data-photo": ph.id }, div);
    const img = sv("image", { href: withToken(`/api/photo/${ph.id}`), x: -0.5, y: -0.5, width: ph.width, height: ph.height,
      preserveAspectRatio: "none" }, svg);
    const solid = sv("image", { class: "solid", x: -0.5, y: -0.5, width: ph.width, height: ph.height,
      preserveAspectRatio: "none" }, svg);
    const overlay = sv("g", { class: "overlay" }, svg);
    const wire = sv("g", { class: "wire", transform: "scale(0.1)" }, overlay);
    const markers = sv("g", { class: "markers" }, overlay);
    const resid = sv("g", { class: "resids" }, svg);
    const clicks = sv("g", { class: "clicks" }, svg);
    const v = { photo: ph, svg, img, solid, overlay, wire, markers, resid, clicks, proj: null, box: [-0.5, -0.5, ph.width, ph.height] };
    S.views[ph.id] = v;
    svg.addEventListener("pointerdown", (e) => onPointerDown(v, e));
    svg.addEventListener("pointermove", (e) => onPointerMove(v, e));
    svg.addEventListener("pointerup", (e) => onPointerUp(v, e));
    svg.addEventListener("pointerleave", () => { $("#loupe").hidden = true; });
    svg.addEventListener("wheel", (e) => onWheel(v, e), { passive: false });
  }
  applyOpacity();
  document.body.classList.toggle("armed-mode", !!S.armed);
}

function applyOpacity() {
  const o = $("#opacity").value;
  const so = $("#solid-opacity").value;
  for (const v of Object.values(S.views)) {
    v.overlay.setAttribute("opacity", o);
    v.solid.setAttribute("opacity", so);
    v.solid.style.display = Number(so) > 0 ? "" : "none";
  }
  $("#views").classList.toggle("hide-points", !$("#show-points").checked);
}

function toImage(v, e) {
  const pt = v.svg.createSVGPoint();
  pt.x = e.clientX; pt.y = e.clientY;
  const p = pt.matrixTransform(v.svg.getScreenCTM().inverse());
  return [p.x, p.y];
}
// Client (CSS pixel) coordinates of an image position: for tests and the benchmark.
S.toClient = (photoId, u, v) => {
  const view = S.views[photoId];
  const pt = view.svg.createSVGPoint();
  pt.x = u; pt.y = v;
  const p = pt.matrixTransform(view.svg.getScreenCTM());
  return [p.x, p.y];
};

function refreshAll(t0, solid = true) {
  if (S.state.error) return;
  requestOverlay(t0);
  if (solid) for (const id of Object.keys(S.views)) requestSolid(id);
}

// The translucent solid: the model rendered on the server (pyrender), fetched when the values
// settle (not at every slider step: rendering takes longer than a wireframe).
function requestSolid(id) {
  if (Number($("#solid-opacity").value) <= 0) return;
  const body = JSON.stringify({ photo: id, values: activeValues() });  // one camera per rendering
  fetch("/api/solid", { method: "POST", credentials: "omit", headers: { "Content-Type": "application/json", "X-Studio-Token": TOKEN }, body })
    .then((r) => (r.ok ? r.blob() : null))
    .then((blob) => {
      const v = S.views[id];
      if (!blob || !v) return;
      if (v.solidUrl) URL.revokeObjectURL(v.solidUrl);
      v.solidUrl = URL.createObjectURL(blob);
      v.solid.setAttribute("href", v.solidUrl);
      v.solid.dataset.loaded = "1";
      S.solids = (S.solids || 0) + 1;
    })
    .catch(() => {});
}

// One request (all photos of the configuration) in flight at a time; a slider move during it asks
// again with the newest values when it is back.
function requestOverlay(t0) {
  const ids = Object.keys(S.views);
  if (!ids.length) return;
  if (S.inflight.overlay) { S.pending.overlay = t0 || performance.now(); return; }
  S.inflight.overlay = true;
  const start = t0 || performance.now();
  api("POST", "/api/overlay", { photos: ids, values: activeValues(), occlusion: $("#occlusion").checked })
    .then((r) => {
      for (const [id, proj] of Object.entries(r.views)) drawOverlay(S.views[id], proj);
      requestAnimationFrame(() => {
        S.redraws += 1;
        S.timings.push(performance.now() - start);
      });
    })
    .catch(() => {})
    .finally(() => {
      S.inflight.overlay = false;
      if (S.pending.overlay) { const t = S.pending.overlay; delete S.pending.overlay; requestOverlay(t); }
    });
}

// Polylines of m points, coordinates in tenths of a pixel (the wire group is scaled by 0.1).
function pathData(groups) {
  const parts = [];
  for (const [m, xy] of groups) {
    for (let i = 0; i < xy.length; i += 2 * m) {
      let d = "M" + xy[i] + "," + xy[i + 1];
      for (let k = 1; k < m; k++) d += " " + xy[i + 2 * k] + "," + xy[i + 2 * k + 1];
      parts.push(d);
    }
  }
  return parts.join("");
}

function drawOverlay(v, proj) {
  if (!v) return;
  v.proj = proj;
  const existing = {};
  for (const p of v.wire.querySelectorAll("path")) existing[p.dataset.object] = p;
  for (const [obj, groups] of Object.entries(proj.paths)) {
    let p = existing[obj];
    if (!p) { p = sv("path", { "data-object": obj }, v.wire); }
    p.setAttribute("d", pathData(groups));
    p.style.display = S.hidden.includes(obj) ? "none" : "";
    delete existing[obj];
  }
  for (const p of Object.values(existing)) p.remove();
  drawMarkers(v);
  drawClicks(v);
}

function markerRadius(v) { return Math.max(2, v.box[2] / 160); }

function drawMarkers(v) {
  v.markers.innerHTML = "";
  if (!v.proj) return;
  const r = markerRadius(v);
  for (const p of v.proj.points) {
    if (p.u === null) continue;
    const c = sv("circle", { class: "marker", cx: p.u, cy: p.v, r, "data-point": p.name }, v.markers);
    sv("title", {}, c).textContent = p.name;
    if (p.name === S.armed) c.classList.add("armed");
    if (p.hidden) c.classList.add("hidden");
    if (S.suggested.some((s) => s.point === p.name && (!s.camera || s.camera === v.proj.camera))) c.classList.add("suggested");
    c.addEventListener("pointerdown", (e) => { e.stopPropagation(); arm(p.name); });
  }
}

function modelPixel(v, point) {
  if (!v.proj) return null;
  const p = v.proj.points.find((q) => q.name === point);
  return p && p.u !== null ? [p.u, p.v] : null;
}

function drawClicks(v) {
  v.clicks.innerHTML = "";
  v.resid.innerHTML = "";
  const r = markerRadius(v) * 1.3;
  for (const c of S.clicks) {
    if (c.config !== v.photo.config || c.camera !== v.proj?.camera) continue;
    const m = modelPixel(v, c.point);
    if (m) sv("line", { class: "link", x1: m[0], y1: m[1], x2: c.u, y2: c.v }, v.clicks);
    const g = sv("g", { "data-click": c.id }, v.clicks);
    const cls = "click" + (c.id === S.selected ? " selected" : "");
    sv("circle", { class: cls, cx: c.u, cy: c.v, r, "data-click": c.id }, g);
    sv("line", { class: cls, x1: c.u - r, y1: c.v, x2: c.u + r, y2: c.v }, g);
    sv("line", { class: cls, x1: c.u, y1: c.v - r, x2: c.u, y2: c.v + r }, g);
    sv("title", {}, g).textContent = `${c.id}: ${c.point}`;
    const res = S.report && S.report.residuals[c.id];
    if (res) {
      const [pu, pv] = res.predicted;
      const scale = 10;
      sv("line", { class: "resid", x1: pu, y1: pv, x2: pu + scale * (res.measured[0] - pu), y2: pv + scale * (res.measured[1] - pv) }, v.resid);
    }
  }
}

// ---- picking, dragging, zoom, loupe ---------------------------------------------------------------
function arm(name) {
  S.armed = S.armed === name ? null : name;
  $("#armed").textContent = S.armed ? `now click ${S.armed} in a photo (Esc cancels)` : "pick a point, then click it in a photo";
  document.body.classList.toggle("armed-mode", !!S.armed);
  buildPointList();
  for (const v of Object.values(S.views)) drawMarkers(v);
}

function onPointerDown(v, e) {
  if (e.button !== 0) return;
  const [u, w] = toImage(v, e);
  const target = e.target.closest ? e.target.closest("[data-click]") : null;
  if (S.armed) {
    addClick(v, S.armed, u, w);
    e.preventDefault();
    return;
  }
  if (target) {
    const id = target.getAttribute("data-click");
    S.selected = id;
    S.drag = { view: v, id, moved: false };
    v.svg.setPointerCapture(e.pointerId);
    renderClicks();
    e.preventDefault();
  }
}

function onPointerMove(v, e) {
  const [u, w] = toImage(v, e);
  showLoupe(v, e, u, w);
  if (S.drag && S.drag.view === v) {
    const c = S.clicks.find((q) => q.id === S.drag.id);
    if (!c) return;
    if (!S.drag.moved) { pushHistory(); S.drag.moved = true; }
    c.u = round3(u); c.v = round3(w);
    drawClicks(v);
  }
}

function onPointerUp(v, e) {
  if (S.drag && S.drag.view === v) {
    const moved = S.drag.moved;
    S.drag = null;
    try { v.svg.releasePointerCapture(e.pointerId); } catch (err) { /* not captured */ }
    if (moved) { renderClicks(); saveSession(); }
  }
}

function onWheel(v, e) {
  e.preventDefault();
  const [u, w] = toImage(v, e);
  const f = e.deltaY < 0 ? 0.8 : 1.25;
  const [x0, y0, W, H] = v.box;
  let nw = Math.min(v.photo.width, W * f), nh = Math.min(v.photo.height, H * f);
  nw = Math.max(nw, 8); nh = Math.max(nh, 8 * v.photo.height / v.photo.width);
  const nx = u - ((u - x0) * nw) / W, ny = w - ((w - y0) * nh) / H;
  v.box = [nx, ny, nw, nh];
  v.svg.setAttribute("viewBox", v.box.join(" "));
  drawMarkers(v); drawClicks(v);
}

function showLoupe(v, e, u, w) {
  const loupe = $("#loupe");
  if (!loupe.firstChild) {
    const svg = sv("svg", { viewBox: "0 0 20 20" }, loupe);
    sv("image", { preserveAspectRatio: "none" }, svg);
    sv("path", { class: "cross", d: "M10,0 V20 M0,10 H20" }, svg);
    sv("text", { x: 0.5, y: 19.3, "font-size": 1.2, fill: "#fff" }, svg);
  }
  const svg = loupe.firstChild;
  const half = 12; // a 24 px window shown 160 px wide: about 6.7 times magnified
  svg.setAttribute("viewBox", `${u - half} ${w - half} ${2 * half} ${2 * half}`);
  const img = svg.querySelector("image");
  img.setAttribute("href", withToken(`/api/photo/${v.photo.id}`));
  img.setAttribute("x", -0.5); img.setAttribute("y", -0.5);
  img.setAttribute("width", v.photo.width); img.setAttribute("height", v.photo.height);
  svg.querySelector("path").setAttribute("d", `M${u},${w - half} V${w + half} M${u - half},${w} H${u + half}`);
  svg.querySelector("path").setAttribute("stroke-width", half / 60);
  const t = svg.querySelector("text");
  t.setAttribute("x", u - half + 0.3); t.setAttribute("y", w + half - 0.4); t.setAttribute("font-size", half / 8);
  t.textContent = `${u.toFixed(2)}, ${w.toFixed(2)}`;
  loupe.hidden = false;
  loupe.style.left = `${e.clientX + 24}px`;
  loupe.style.top = `${e.clientY + 24}px`;
}

const round3 = (x) => Math.round(x * 1000) / 1000;

function addClick(v, point, u, w) {
  pushHistory();
  const camera = v.proj ? v.proj.camera : v.photo.camera;
  const sigma = Number($("#sigma").value) || 1;
  const old = S.clicks.find((c) => c.point === point && c.camera === camera && c.config === v.photo.config);
  if (old) { old.u = round3(u); old.v = round3(w); S.selected = old.id; }
  else {
    const id = `c${S.nextId++}`;
    S.clicks.push({ id, camera, config: v.photo.config, point, u: round3(u), v: round3(w), sigma });
    S.selected = id;
  }
  S.armed = null;
  arm(null);
  renderClicks();
  saveSession();
}

// ---- the measurement table, history, saving --------------------------------------------------------
function renderClicks() {
  const body = $("#clicks tbody");
  body.innerHTML = "";
  for (const c of S.clicks) {
    const tr = el("tr", { "data-click": c.id }, body);
    if (c.id === S.selected) tr.classList.add("selected");
    el("td", { text: c.id }, tr);
    el("td", { text: shortCamera(c.camera) }, tr);
    el("td", { text: c.config }, tr);
    el("td", { text: shortPoint(c.point), title: c.point }, tr);
    el("td", { text: c.u.toFixed(2) }, tr);
    el("td", { text: c.v.toFixed(2) }, tr);
    const td = el("td", {}, tr);
    const inp = el("input", { type: "number", min: "0.01", step: "0.1", value: c.sigma, "data-sigma": c.id }, td);
    if (c.sigma_v !== undefined) {
      // From a measurement file's sigma_u, sigma_v: both kept; an edit sets one σ of both.
      el("span", { class: "sigma-v", text: ` / ${c.sigma_v}`, title: "σ of u / σ of v; an edit sets both", "data-sigma-v": c.id }, td);
    }
    inp.addEventListener("change", () => {
      const s = Number(inp.value);
      if (!(s > 0)) { inp.value = c.sigma; return; }
      pushHistory(); c.sigma = s;
      if (c.sigma_v !== undefined) { delete c.sigma_v; renderClicks(); }
      saveSession();
    });
    const res = S.report && S.report.residuals[c.id];
    el("td", { text: res ? Math.hypot(res.measured[0] - res.predicted[0], res.measured[1] - res.predicted[1]).toFixed(2) + " px" : "" }, tr);
    const del = el("button", { text: "✕", title: "delete (Del)", "data-delete": c.id }, el("td", {}, tr));
    del.addEventListener("click", () => deleteClick(c.id));
    tr.addEventListener("click", (e) => { if (e.target.tagName !== "INPUT" && e.target.tagName !== "BUTTON") { S.selected = c.id; renderClicks(); } });
  }
  for (const v of Object.values(S.views)) if (v.proj) drawClicks(v);
  buildPointList();
  $("#undo").disabled = S.history.length === 0;
  $("#redo").disabled = S.future.length === 0;
}

function deleteClick(id) {
  if (!S.clicks.some((c) => c.id === id)) return;
  pushHistory();
  S.clicks = S.clicks.filter((c) => c.id !== id);
  if (S.selected === id) S.selected = null;
  renderClicks();
  saveSession();
}

function snapshot() { return JSON.stringify(S.clicks); }
function pushHistory() { S.history.push(snapshot()); if (S.history.length > 500) S.history.shift(); S.future = []; }
function undo() {
  if (!S.history.length) return;
  S.future.push(snapshot());
  S.clicks = JSON.parse(S.history.pop());
  renderClicks(); saveSession();
}
function redo() {
  if (!S.future.length) return;
  S.history.push(snapshot());
  S.clicks = JSON.parse(S.future.pop());
  renderClicks(); saveSession();
}

let saving = Promise.resolve();
function saveSession() {
  const body = { clicks: S.clicks, estimate: S.estimate, values: S.values, hidden: S.hidden };
  saving = saving.then(() => api("POST", "/api/session", body)
    .then((r) => {
      S.nextId = Math.max(S.nextId, r.next_id); S.saved = (S.saved || 0) + 1; S.unsaved = false;
      document.body.dataset.unsaved = ""; status(`saved ${r.saved} click(s)`);
    })
    .catch((e) => {
      // Lasting until a save succeeds: a later success elsewhere must not hide that edits are not on disk.
      S.unsaved = true; document.body.dataset.unsaved = "1";
      status(`${e.message} (the next edit tries again)`);
    }));
  return saving;
}

// ---- observe, solve, save --------------------------------------------------------------------------
async function doObserve() {
  await saving;
  status("analysing observability…");
  const r = await api("POST", "/api/observe", {});
  S.suggested = r.suggestions.filter((s) => s.point);
  const box = $("#suggestions");
  box.innerHTML = "";
  el("div", { class: r.observable ? "ok" : "bad", text: r.verdict, id: "verdict" }, box);
  for (const c of r.combinations) el("div", { class: "bad", text: "unobservable: " + c }, box);
  if (S.suggested.length) {
    el("div", { text: "click these next:" }, box);
    const ul = el("ul", {}, box);
    for (const s of S.suggested.slice(0, 8)) el("li", { text: `${shortPoint(s.point)} in ${shortCamera(s.camera || "")}`, "data-suggest": s.point }, ul);
  }
  $("#report").textContent = r.summary;
  buildPointList();
  for (const v of Object.values(S.views)) drawMarkers(v);
  status("observability analysed");
}

async function doSolve() {
  await saving;
  const restarts = Math.max(1, Math.min(256, Number($("#restarts").value) || 16));
  $("#solve").disabled = true;
  $("#stale").hidden = true;
  try {
    await api("POST", "/api/solve", { restarts, seed: 0 });
    let st;
    for (;;) {
      await new Promise((res) => setTimeout(res, 250));
      st = await api("GET", "/api/solve");
      status("solving: " + (st.messages[st.messages.length - 1] || "starting"));
      if (st.done) break;
    }
    if (st.error) { showError(st.error, true); status("solve failed"); return; }
    if (st.stale) {
      // Edited while it ran: the result is of other clicks; the page keeps the edits and their values.
      $("#stale").textContent = st.stale;
      $("#stale").hidden = false;
      status("solve finished after an edit: its result is not used");
      document.body.dataset.solved = "stale";
      return;
    }
    S.report = st.report;
    for (const p of S.report.params) S.values[p.name] = p.value;
    showReport(S.report);
    buildSliders();
    refreshAll();
    renderClicks();
    status(`solved: ${S.report.status}${S.report.ok ? "" : " (not trustworthy: see the report)"}`);
    document.body.dataset.solved = "1";
  } finally {
    $("#solve").disabled = false;
  }
}

function showReport(rep) {
  const t = $("#estimates");
  t.innerHTML = "";
  const head = el("tr", {}, t);
  for (const h of ["unknown", "value", "σ", "unit"]) el("th", { text: h }, head);
  for (const p of rep.params) {
    const tr = el("tr", { "data-param": p.name }, t);
    el("td", { text: p.name }, tr);
    el("td", { text: Number(p.display).toPrecision(6) }, tr);
    el("td", { text: p.display_std === null ? "∞" : Number(p.display_std).toPrecision(3) }, tr);
    el("td", { text: p.unit }, tr);
  }
  $("#report").textContent = rep.summary;
}

async function doSave() {
  await saving;
  const r = await api("POST", "/api/save", { format: $("#format").value });
  const removed = r.removed.length ? `; removed ${r.removed.join(", ")} (an earlier save's, not redrawn)` : "";
  status("wrote " + r.written.join(", ") + " in " + r.out + removed);
  $("#notes").textContent = r.notes.join(" · ");  // overlays that could not be drawn say why
  document.body.dataset.saved = r.written.join(",");
}

async function doReload() {
  await saving;  // the server keeps the clicks it has: let the last edit arrive first
  const r = await api("POST", "/api/reload", {});
  S.report = null; S.suggested = [];
  await loadState();
  const what = (r.error && r.error.what) || "the model";
  status(r.ok ? "model reloaded" : `${what} has an error (see above); the server keeps running`);
}

// ---- wiring ----------------------------------------------------------------------------------------
function setEstimate() {
  S.estimate = $("#estimate").value.split(/[\s,]+/).filter((x) => x);
  buildSliders();
  buildParamTree();
  refreshAll();
  saveSession();
}

document.addEventListener("keydown", (e) => {
  const typing = ["INPUT", "SELECT", "TEXTAREA"].includes(document.activeElement.tagName) &&
    document.activeElement.type !== "range" && document.activeElement.type !== "checkbox";
  if (e.key === "Escape") { S.armed = null; arm(null); S.selected = null; renderClicks(); return; }
  if (typing) return;
  if ((e.ctrlKey || e.metaKey) && e.key.toLowerCase() === "z" && !e.shiftKey) { e.preventDefault(); undo(); }
  else if ((e.ctrlKey || e.metaKey) && (e.key.toLowerCase() === "y" || (e.key.toLowerCase() === "z" && e.shiftKey))) { e.preventDefault(); redo(); }
  else if ((e.key === "Delete" || e.key === "Backspace") && S.selected) { e.preventDefault(); deleteClick(S.selected); }
  else if (e.key === "/") { e.preventDefault(); $("#search").focus(); }
  else if (e.key === "o") { doObserve().catch(() => {}); }
});

window.addEventListener("DOMContentLoaded", () => {
  // The token came in the address; the page has it (TOKEN), so it is dropped from the address
  // bar and the history.
  if (new URLSearchParams(location.search).has("token")) history.replaceState(null, "", location.pathname);
  $("#search").addEventListener("input", buildPointList);
  $("#search").addEventListener("keydown", (e) => {
    if (e.key === "Enter") {
      const first = $("#pointlist li");
      if (first) { S.armed = null; arm(first.dataset.point); $("#search").blur(); }
    }
  });
  $("#config").addEventListener("change", () => { S.config = $("#config").value; buildViews(); buildPointList(); refreshAll(); });
  $("#opacity").addEventListener("input", applyOpacity);
  $("#solid-opacity").addEventListener("input", applyOpacity);
  $("#solid-opacity").addEventListener("change", () => refreshAll(undefined, true));
  $("#show-points").addEventListener("change", applyOpacity);
  $("#occlusion").addEventListener("change", () => refreshAll(undefined, false));
  $("#estimate").addEventListener("change", setEstimate);
  $("#observe").addEventListener("click", () => doObserve().catch(() => {}));
  $("#solve").addEventListener("click", () => doSolve().catch(() => {}));
  $("#save").addEventListener("click", () => doSave().catch(() => {}));
  $("#reload").addEventListener("click", () => doReload().catch(() => {}));
  $("#undo").addEventListener("click", undo);
  $("#redo").addEventListener("click", redo);
  loadState().then(() => { document.body.dataset.ready = "1"; }).catch((err) => status(String(err)));
});
