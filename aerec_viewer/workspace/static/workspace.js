// The image workspace: the selected GCP side by side in every image, one 2D canvas per image.
// What this tab chose (the GCP, each canvas's pan and zoom, the display) lives here only; the
// GCPs are the viewer's, read from /api/state whenever /api/version moves, and every edit
// names its GCP and its image.
"use strict";

const TILE = 256;             // tile side (workspace/tiles.py)
const POLL_MS = 700;          // version poll
const DRAG_PX = 4;            // a press that moves less than this is a click
const LOCATED_ZOOM = 4;       // screen px per image px when a canvas centres on the GCP
const MAX_ZOOM = 64;
const COLOURS = {observed: "#ffd400", predicted: "#00e5ff", residual: "#ff8c00", surveyed: "#ff5cf0",
                 control: "#e53935", check: "#1e88e5", off: "#9e9e9e"};

const tab = {
  data: null,                 // the last /api/state
  selected: null,             // the GCP id this tab works on
  display: {contrast: 1, brightness: 0, gamma: 2},
  views: new Map(),           // image -> View
  refined: new Map(),         // "gcp|image|version" -> refined prediction (or null)
  edits: Promise.resolve(),   // edits go one after the other, in the order made
};

// -- server ------------------------------------------------------------------------------------
async function api(path, body) {
  const opts = body === undefined ? {} : {method: "POST", body: JSON.stringify(body),
                                          headers: {"Content-Type": "application/json"}};
  const r = await fetch(path, opts);
  const ctype = r.headers.get("Content-Type") || "";
  const out = ctype.startsWith("application/json") ? await r.json() : null;
  if (!r.ok) throw new Error((out && out.error) || `${r.status} ${r.statusText}`);
  return out;
}

function say(text, level = "info") {
  const el = document.getElementById("status");
  el.textContent = text;
  el.className = level;
}

// An edit: queued behind the previous ones; its note (or its refusal) on the status line.
function edit(path, body) {
  tab.edits = tab.edits.then(async () => {
    try {
      const out = await api(path, body);
      say(out.note + (out.stale ? " (the page was refreshing: check it)" : ""));
      await refresh(true);
    } catch (err) {
      say(err.message, "error");
      await refresh(true);
    }
  });
  return tab.edits;
}

// Returns whether the viewer answered (the poll backs off while it does not).
async function refresh(force = false) {
  try {
    if (!force && tab.data) {
      const v = await api("/api/version");
      if (v.version === tab.data.version) return;
    }
    const data = await api("/api/state");
    if (tab.data && data.version < tab.data.version) return;     // an older answer arrived late
    const first = tab.data === null;
    tab.data = data;
    if (first) startup();
    else if (tab.selected !== null && !gcp(tab.selected)) {
      say(`${tab.selected} no longer exists (deleted or renamed in another tab or in the 3D viewer): choose a GCP`, "error");
      select(null);
    }
    render();
    return true;
  } catch (err) {
    say(`the viewer does not answer (${err.message}); retrying`, "error");
    return false;
  }
}

// One poll at a time, the next POLL_MS after the last answer; while the viewer does not answer,
// twice as long each time, up to 10 s (a stopped viewer is not asked 1.4 times a second forever).
async function poll(wait = POLL_MS) {
  const next = (await refresh(false)) ? POLL_MS : Math.min(2 * wait, 10000);
  setTimeout(() => poll(next), next);
}

function gcp(id) {
  return tab.data ? tab.data.gcps.find(g => g.id === id) || null : null;
}

function registered() {
  return tab.data.images.filter(im => im.registered).map(im => im.name);
}

// -- selection ---------------------------------------------------------------------------------
function startup() {
  document.getElementById("site").textContent = `· ${tab.data.site}`;
  const reg = registered();
  const todo = tab.data.gcps.find(g => reg.some(im => !(g.images[im] && g.images[im].observed)));
  select(todo ? todo.id : (tab.data.gcps[0] || {}).id || null);
  say(tab.data.gcps.length ? "choose a GCP (N / P, or a row of the list); a click in an image places it there"
                           : "no GCP yet: add them in the 3D viewer's GCP tab, or import a CSV");
}

function select(id) {
  tab.selected = id;
  for (const v of tab.views.values()) v.located = false;       // each canvas centres on it again
  render();
}

function step(k) {
  const ids = tab.data.gcps.map(g => g.id);
  if (!ids.length) return;
  const i = ids.indexOf(tab.selected);
  select(ids[((i < 0 ? (k > 0 ? -1 : 0) : i) + k + ids.length) % ids.length]);
  const g = gcp(tab.selected);
  say(`${g.id} selected (${roleWords(g)}): a click in an image places it there`);
}

function roleWords(g) {
  return `${g.role} point${g.enabled ? "" : ", disabled: left out of the upgrade"}`;
}

// -- the list ----------------------------------------------------------------------------------
function fmt(v, d = 2) { return v === null || v === undefined ? "–" : v.toFixed(d); }

function worst(g) {
  let best = null;
  for (const [im, o] of Object.entries(g.images)) {
    if (o.residual_px !== null && (best === null || o.residual_px > best[1])) best = [im, o.residual_px];
  }
  return best;
}

function renderList() {
  const body = document.querySelector("#gcps tbody");
  const reg = registered();
  body.replaceChildren(...tab.data.gcps.map(g => {
    const tr = document.createElement("tr");
    tr.dataset.gcp = g.id;
    if (g.id === tab.selected) tr.classList.add("selected");
    if (!g.enabled) tr.classList.add("off");
    const placed = reg.filter(im => g.images[im] && g.images[im].observed).length;
    const e = g.error_m;
    const w = worst(g);
    const cells = [g.id + (g.sigma_h_m !== null ? ` (h ±${fmt(g.sigma_h_m, 1)} m)` : ""),
                   g.role + (g.enabled ? "" : ", off"), `${placed} / ${reg.length}`,
                   e ? `${fmt(e.E)} / ${fmt(e.N)} / ${fmt(e.U)}${e.left_out ? "*" : ""}` : "–",
                   w ? fmt(w[1]) : "–"];
    for (const c of cells) { const td = document.createElement("td"); td.textContent = c; tr.append(td); }
    if (w && w[1] > 1) tr.lastChild.classList.add("bad");
    tr.addEventListener("click", () => { select(g.id); say(`${g.id} selected (${roleWords(g)})`); });
    return tr;
  }));
  const up = tab.data.upgrade;
  const starred = tab.data.gcps.some(g => g.error_m && g.error_m.left_out);
  document.getElementById("upgrade-note").textContent =
    (!up ? "Errors in metres appear after an upgrade (Upgrade in the 3D viewer's Results tab)."
         : up.stale ? "The GCPs changed since the last upgrade: its errors are out of date; press Upgrade again." : "")
    + (starred ? " * a control point's error as the other control points predict it (left out of the fit)." : "");
}

function renderDetails() {
  const el = document.getElementById("details");
  const g = gcp(tab.selected);
  if (!g) { el.replaceChildren(); return; }
  const h = document.createElement("h2");
  h.textContent = `${g.id}: ${roleWords(g)}`;
  const p = document.createElement("p");
  p.className = "note";
  p.textContent = `lon ${g.lon.toFixed(7)}, lat ${g.lat.toFixed(7)}, h ${g.h.toFixed(2)} m`
    + (g.sigma_h_m !== null ? `; its height is known only to ±${g.sigma_h_m.toFixed(1)} m` : "")
    + (g.picked_on_cloud.length ? "; picked on the cloud (that pick replaces its image observations)" : "");
  const t = document.createElement("table");
  t.innerHTML = "<thead><tr><th>image</th><th title=\"col, row\">observed</th><th title=\"col, row\">predicted</th>" +
    "<th title=\"observed minus predicted\">residual px</th>" +
    "<th title=\"after an upgrade: from the observation to where its surveyed position projects (its error in the upgrade, in pixels)\">to survey px</th></tr></thead>";
  const tb = document.createElement("tbody");
  for (const im of tab.data.images) {
    const o = g.images[im.name];
    const tr = document.createElement("tr");
    const cells = [im.name, o && o.observed ? `${fmt(o.observed[0])}, ${fmt(o.observed[1])}` : "–",
                   o && o.predicted ? `${fmt(o.predicted[0])}, ${fmt(o.predicted[1])}` : "–",
                   o && o.residual_px !== null ? fmt(o.residual_px) : "–", fmt(surveyGap(o))];
    for (const c of cells) { const td = document.createElement("td"); td.textContent = c; tr.append(td); }
    if (o && o.residual_px > 1) tr.children[3].classList.add("bad");
    tb.append(tr);
  }
  t.append(tb);
  el.replaceChildren(h, p, t);
}

// pixels from the observation to where the surveyed position projects (null: either missing)
function surveyGap(o) {
  return o && o.observed && o.surveyed ? Math.hypot(o.observed[0] - o.surveyed[0], o.observed[1] - o.surveyed[1]) : null;
}

function renderHelp() {
  const id = tab.selected || "the selected GCP";
  document.getElementById("help").textContent =
    `Drag: pan · wheel: zoom at the cursor · click: place ${id} in that image · ←↑↓→: nudge it 0.1 px ` +
    "(shift: 1 px) in the image under the cursor · Delete: remove it there · Enter: accept the prediction · " +
    "N / P: next / previous GCP · C: centre · Ctrl+Z / Ctrl+Y: undo / redo";
}

// -- the canvases --------------------------------------------------------------------------------
const tiles = new Map();      // "image|level|tx|ty" -> {url, img (loaded), loading}

function tileUrl(image, level, tx, ty) {
  const d = tab.display;
  return `/api/tile?image=${encodeURIComponent(image)}&level=${level}&tx=${tx}&ty=${ty}` +
         `&contrast=${d.contrast.toFixed(3)}&brightness=${d.brightness.toFixed(3)}&gamma=${d.gamma.toFixed(2)}`;
}

// The tile's image for the current display, or the last one loaded (another contrast) meanwhile.
function tile(image, level, tx, ty, onload, fetchIt) {
  const key = `${image}|${level}|${tx}|${ty}`;
  const url = tileUrl(image, level, tx, ty);
  let t = tiles.get(key);
  if (!t) { t = {url: null, img: null, loading: null}; tiles.set(key, t); }
  if (fetchIt && t.url !== url && t.loading !== url) {
    t.loading = url;
    const img = new Image();
    img.onload = () => { if (t.loading === url) { t.img = img; t.url = url; t.loading = null; } onload(); };
    img.onerror = () => { if (t.loading === url) t.loading = null; };
    img.src = url;
  }
  return t.img;
}

class View {
  constructor(info) {
    this.info = info;                     // {name, width, height, levels}
    this.s = 1; this.cx = info.width / 2; this.cy = info.height / 2;
    this.located = false;                 // centred on the selected GCP yet
    this.moved = false;                   // panned or zoomed by the operator since
    this.el = document.createElement("div");
    this.el.className = "view";
    this.head = document.createElement("div");
    this.head.className = "head";
    this.title = document.createElement("span");
    this.title.className = "title";
    this.text = document.createElement("span");
    this.text.className = "what";
    this.actions = document.createElement("span");
    this.actions.className = "actions";
    this.head.append(this.title, this.text, this.actions);
    this.canvas = document.createElement("canvas");
    this.canvas.tabIndex = 0;
    this.canvas.dataset.image = info.name;
    this.canvas.setAttribute("aria-label", `image ${info.name}`);
    this.el.append(this.head, this.canvas);
    this.pending = false;
    this.wire();
    new ResizeObserver(() => this.draw()).observe(this.canvas);
  }

  // screen (CSS px in the canvas) <-> image pixel (full resolution, pixel centres at integers)
  toImage(x, y) {
    return [this.cx + (x - this.canvas.clientWidth / 2) / this.s, this.cy + (y - this.canvas.clientHeight / 2) / this.s];
  }
  toScreen(c, r) {
    return [(c - this.cx) * this.s + this.canvas.clientWidth / 2, (r - this.cy) * this.s + this.canvas.clientHeight / 2];
  }
  fitScale() {
    return Math.min(this.canvas.clientWidth / this.info.width, this.canvas.clientHeight / this.info.height) || 1;
  }

  // centre on the selected GCP's observation, else its prediction, else show the whole image
  locate(at) {
    if (at) { this.cx = at[0]; this.cy = at[1]; this.s = Math.max(this.s, LOCATED_ZOOM); }
    else { this.cx = (this.info.width - 1) / 2; this.cy = (this.info.height - 1) / 2; this.s = this.fitScale(); }
    this.located = true;
    this.moved = false;
  }

  zoomAt(x, y, factor) {
    const [c, r] = this.toImage(x, y);
    this.s = Math.min(MAX_ZOOM, Math.max(this.fitScale() / 4, this.s * factor));
    this.cx = c - (x - this.canvas.clientWidth / 2) / this.s;
    this.cy = r - (y - this.canvas.clientHeight / 2) / this.s;
    this.moved = true;
    this.draw();
  }

  // the pointer in the canvas's drawing area (CSS px, fractional: a sub-pixel aim stays so)
  at(ev) {
    const rect = this.canvas.getBoundingClientRect();
    return [ev.clientX - rect.left - this.canvas.clientLeft, ev.clientY - rect.top - this.canvas.clientTop];
  }

  wire() {
    const cv = this.canvas;
    let press = null;
    cv.addEventListener("pointerenter", () => cv.focus({preventScroll: true}));
    cv.addEventListener("pointerdown", ev => {
      if (ev.button !== 0) return;
      cv.focus({preventScroll: true});
      cv.setPointerCapture(ev.pointerId);
      const [x, y] = this.at(ev);
      press = {x, y, cx: this.cx, cy: this.cy, drag: false};
    });
    cv.addEventListener("pointermove", ev => {
      if (!press) return;
      const [x, y] = this.at(ev);
      const dx = x - press.x, dy = y - press.y;
      if (!press.drag && Math.hypot(dx, dy) < DRAG_PX) return;
      press.drag = true;
      cv.classList.add("panning");
      this.cx = press.cx - dx / this.s; this.cy = press.cy - dy / this.s;
      this.moved = true;
      this.draw();
    });
    cv.addEventListener("pointerup", ev => {
      if (!press) return;
      const was = press;
      press = null;
      cv.classList.remove("panning");
      if (!was.drag) this.place(...this.at(ev));
    });
    cv.addEventListener("pointercancel", () => { press = null; cv.classList.remove("panning"); });
    cv.addEventListener("wheel", ev => {
      ev.preventDefault();
      const dy = ev.deltaMode === 1 ? ev.deltaY * 33 : ev.deltaY;
      this.zoomAt(...this.at(ev), Math.exp(-dy * 0.0015));
    }, {passive: false});
    cv.addEventListener("keydown", ev => this.key(ev));
  }

  // a click: THIS tab's GCP, in THIS canvas's image, at the sub-pixel under the cursor
  place(x, y) {
    const id = tab.selected;
    if (!id) { say("choose a GCP first (N, or a row of the list)", "error"); return; }
    const [c, r] = this.toImage(x, y);
    const {width: w, height: h, name} = this.info;
    if (c < -0.5 || r < -0.5 || c > w - 0.5 || r > h - 0.5) { say(`the click is outside ${name}: nothing placed`, "error"); return; }
    edit("/api/observe", {gcp: id, image: name, col: c, row: r, version_seen: tab.data.version});
  }

  key(ev) {
    const id = tab.selected;
    const arrows = {ArrowLeft: [-1, 0], ArrowRight: [1, 0], ArrowUp: [0, -1], ArrowDown: [0, 1]};
    if (arrows[ev.key] && id && !ev.ctrlKey && !ev.metaKey && !ev.altKey) {
      ev.preventDefault();
      ev.stopPropagation();
      const k = ev.shiftKey ? 1 : 0.1;
      edit("/api/nudge", {gcp: id, image: this.info.name, dcol: arrows[ev.key][0] * k, drow: arrows[ev.key][1] * k});
    } else if ((ev.key === "Delete" || ev.key === "Backspace") && id) {
      ev.preventDefault();
      ev.stopPropagation();
      edit("/api/remove", {gcp: id, image: this.info.name});
    } else if (ev.key === "Enter" && id) {
      ev.preventDefault();
      ev.stopPropagation();
      this.accept();
    }
  }

  entry() {
    const g = gcp(tab.selected);
    return g ? g.images[this.info.name] || null : null;
  }

  // the prediction shown: refined by matching when the server gave one, else the geometric one
  prediction() {
    const o = this.entry();
    if (!o || !o.predicted) return null;
    if (!o.observed) {
      const ref = tab.refined.get(`${tab.selected}|${this.info.name}|${tab.data.version}`);
      if (ref) return {at: [ref.col, ref.row], how: `${ref.how} (${ref.uncertainty})`};
    }
    return {at: o.predicted, how: o.how, surveyed: o.source === "surveyed"};
  }

  accept() {
    const o = this.entry(), p = this.prediction();
    if (!p || (o && o.observed)) { say(`no prediction to accept in ${this.info.name}`, "error"); return; }
    if (p.surveyed) {
      // where the upgrade puts the survey, not what the image shows: recorded, it would agree
      // with the upgrade by construction and hide an error in the GCP's coordinates
      say(`${tab.selected} in ${this.info.name}: the prediction comes from its surveyed position; ` +
          "click the point itself in the image", "error");
      return;
    }
    edit("/api/observe", {gcp: tab.selected, image: this.info.name, col: p.at[0], row: p.at[1],
                          version_seen: tab.data.version});
  }

  update() {
    const g = gcp(tab.selected), o = this.entry(), p = this.prediction();
    this.title.textContent = this.info.name + (this.info.registered ? "" : " (not registered)");
    this.el.classList.toggle("unseen", !o);
    const btn = (label, title, fn) => {
      const b = document.createElement("button");
      b.type = "button"; b.textContent = label; b.title = title;
      b.addEventListener("click", fn);
      return b;
    };
    const acts = [btn("Centre", "C", () => { this.locate(this.anchor()); this.draw(); })];
    if (!g) this.text.textContent = "choose a GCP";
    else if (o && o.observed) {
      const gap = surveyGap(o);
      this.text.textContent = `${g.id} at col ${fmt(o.observed[0])}, row ${fmt(o.observed[1])}` +
        (o.residual_px !== null ? ` · residual ${fmt(o.residual_px)} px` : "") +
        (gap !== null ? ` · ${fmt(gap)} px from its surveyed position` : "");
      this.text.title = gap !== null ? "the surveyed position: where its ground coordinates project through the upgrade" : "";
      this.text.classList.toggle("bad", o.residual_px > 1);
      acts.push(btn("Remove", "Delete", () => edit("/api/remove", {gcp: g.id, image: this.info.name})));
    } else if (p) {
      this.text.textContent = `${g.id} predicted at col ${fmt(p.at[0])}, row ${fmt(p.at[1])}` +
        (p.surveyed ? " from its surveyed position · click the point itself" : " · Enter accepts");
      this.text.title = p.how;
      this.text.classList.remove("bad");
      if (!p.surveyed) acts.push(btn("Accept", "Enter", () => this.accept()));
    } else {
      this.text.textContent = `${g.id}: not placed, not predicted here · find it, click it`;
      this.text.classList.remove("bad");
    }
    this.actions.replaceChildren(...acts);
    if (!this.located && this.canvas.clientWidth) this.locate(this.anchor());
    this.draw();
  }

  anchor() {
    const o = this.entry(), p = this.prediction();
    return o && o.observed ? o.observed : p ? p.at : null;
  }

  draw() {
    if (this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => { this.pending = false; this.paint(); });
  }

  paint() {
    const cv = this.canvas, dpr = window.devicePixelRatio || 1;
    const W = cv.clientWidth, H = cv.clientHeight;
    if (!W || !H) return;
    if (cv.width !== Math.round(W * dpr) || cv.height !== Math.round(H * dpr)) {
      cv.width = Math.round(W * dpr); cv.height = Math.round(H * dpr);
    }
    if (!this.located && tab.data) this.locate(this.anchor());
    const ctx = cv.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.fillStyle = "#202124";
    ctx.fillRect(0, 0, W, H);
    this.paintTiles(ctx, W, H);
    if (this.s >= 12) this.paintGrid(ctx, W, H);
    this.paintMarks(ctx);
  }

  // coarse levels first (always loaded: a few tiles), then the level of this zoom over them
  paintTiles(ctx, W, H) {
    const {name, width, height, levels} = this.info;
    const want = Math.max(0, Math.min(levels - 1, Math.floor(Math.log2(1 / this.s))));
    ctx.imageSmoothingEnabled = this.s < 1;
    const [c0, r0] = this.toImage(0, 0), [c1, r1] = this.toImage(W, H);
    for (let L = levels - 1; L >= want; L--) {
      const side = TILE << L;
      const tx0 = Math.max(0, Math.floor((c0 + 0.5) / side)), tx1 = Math.min(Math.ceil(width / side) - 1, Math.floor((c1 + 0.5) / side));
      const ty0 = Math.max(0, Math.floor((r0 + 0.5) / side)), ty1 = Math.min(Math.ceil(height / side) - 1, Math.floor((r1 + 0.5) / side));
      for (let ty = ty0; ty <= ty1; ty++) {
        for (let tx = tx0; tx <= tx1; tx++) {
          const img = tile(name, L, tx, ty, () => this.draw(), L === want || L === levels - 1);
          if (!img) continue;
          const col0 = tx * side, row0 = ty * side;
          const w = Math.min(side, width - col0), h = Math.min(side, height - row0);
          const [x, y] = this.toScreen(col0 - 0.5, row0 - 0.5);
          ctx.drawImage(img, x, y, w * this.s, h * this.s);
        }
      }
    }
  }

  paintGrid(ctx, W, H) {
    const [c0, r0] = this.toImage(0, 0), [c1, r1] = this.toImage(W, H);
    ctx.strokeStyle = "rgba(255,255,255,0.12)";
    ctx.lineWidth = 1;
    ctx.beginPath();
    for (let c = Math.floor(c0) + 0.5; c <= c1; c++) { const [x] = this.toScreen(c, 0); ctx.moveTo(x, 0); ctx.lineTo(x, H); }
    for (let r = Math.floor(r0) + 0.5; r <= r1; r++) { const [, y] = this.toScreen(0, r); ctx.moveTo(0, y); ctx.lineTo(W, y); }
    ctx.stroke();
  }

  paintMarks(ctx) {
    if (!tab.data) return;
    for (const g of tab.data.gcps) {                        // the other GCPs placed here
      const o = g.images[this.info.name];
      if (g.id === tab.selected || !o || !o.observed) continue;
      const [x, y] = this.toScreen(...o.observed);
      mark(ctx, "others", x, y, !g.enabled ? COLOURS.off : COLOURS[g.role] || COLOURS.control, g.id);
    }
    const g = gcp(tab.selected), o = this.entry(), p = this.prediction();
    if (!g) return;
    // where its surveyed position projects (around the prediction drawn below when that is
    // where it comes from); from an observation, a dashed line to it: the GCP's error in the
    // upgrade, true scale
    if (o && o.surveyed) {
      const [x, y] = this.toScreen(...o.surveyed);
      if (o.observed) {
        const [xo, yo] = this.toScreen(...o.observed);
        ctx.save(); ctx.setLineDash([4, 3]); ctx.strokeStyle = COLOURS.surveyed; ctx.lineWidth = 1.5;
        ctx.beginPath(); ctx.moveTo(xo, yo); ctx.lineTo(x, y); ctx.stroke(); ctx.restore();
      }
      mark(ctx, "surveyed", x, y, COLOURS.surveyed, "");
    }
    if (p) {
      const [x, y] = this.toScreen(...p.at);
      if (o && o.observed) {
        const [xo, yo] = this.toScreen(...o.observed);
        ctx.strokeStyle = COLOURS.residual; ctx.lineWidth = 2;
        ctx.beginPath(); ctx.moveTo(xo, yo); ctx.lineTo(x, y); ctx.stroke();
      }
      mark(ctx, "predicted", x, y, COLOURS.predicted, o && o.observed ? "" : `${g.id}?`);
    }
    if (o && o.observed) {
      const [x, y] = this.toScreen(...o.observed);
      mark(ctx, "observed", x, y, COLOURS.observed, g.id);
    }
  }
}

// The markers: shapes differ, not only colours. `kind`: observed (a crosshair open at its
// centre, so the pixel stays visible), predicted (a diamond), surveyed (a triangle, the survey
// mark's sign), others (a small ring).
function mark(ctx, kind, x, y, colour, label) {
  ctx.save();
  ctx.lineWidth = 2;
  ctx.strokeStyle = "rgba(0,0,0,0.7)";
  for (const [lw, col] of [[4, "rgba(0,0,0,0.55)"], [2, colour]]) {
    ctx.lineWidth = lw; ctx.strokeStyle = col;
    ctx.beginPath();
    if (kind === "observed") {
      ctx.arc(x, y, 9, 0, 2 * Math.PI);
      for (const [dx, dy] of [[1, 0], [-1, 0], [0, 1], [0, -1]]) { ctx.moveTo(x + 3 * dx, y + 3 * dy); ctx.lineTo(x + 14 * dx, y + 14 * dy); }
    } else if (kind === "predicted") {
      ctx.moveTo(x, y - 8); ctx.lineTo(x + 8, y); ctx.lineTo(x, y + 8); ctx.lineTo(x - 8, y); ctx.closePath();
    } else if (kind === "surveyed") {
      ctx.moveTo(x, y - 13); ctx.lineTo(x + 11, y + 7); ctx.lineTo(x - 11, y + 7); ctx.closePath();
    } else if (kind === "residual") {
      ctx.moveTo(x - 8, y + 6); ctx.lineTo(x + 8, y - 6);
    } else {
      ctx.arc(x, y, 6, 0, 2 * Math.PI);
    }
    ctx.stroke();
  }
  if (label) {
    ctx.font = "12px system-ui, sans-serif";
    ctx.lineWidth = 3; ctx.strokeStyle = "rgba(0,0,0,0.8)"; ctx.fillStyle = colour;
    ctx.strokeText(label, x + 12, y - 10); ctx.fillText(label, x + 12, y - 10);
  }
  ctx.restore();
}

// one canvas per image of the site, in the site's order whatever the GCP (each image keeps its
// place on the screen: a click right after N lands in the image it was aimed at)
function renderViews() {
  const box = document.getElementById("views");
  const g = gcp(tab.selected);
  const order = tab.data.images;
  for (const im of order) if (!tab.views.has(im.name)) tab.views.set(im.name, new View(im));
  const els = order.map(im => tab.views.get(im.name).el);
  if (els.some((el, i) => box.children[i] !== el) || box.children.length !== els.length) box.replaceChildren(...els);
  box.dataset.count = String(Math.min(els.length, 9));
  for (const im of order) { const v = tab.views.get(im.name); v.info = im; v.update(); }
  if (g) askRefined(g);
}

// the refined predictions of the selected GCP in the images it is not placed in (one at a time)
let asking = false;
async function askRefined(g) {
  if (asking) return;
  asking = true;
  try {
    for (const [im, o] of Object.entries(g.images)) {
      const key = `${g.id}|${im}|${tab.data.version}`;
      if (o.observed || !o.predicted || o.source === "surveyed" || tab.refined.has(key) || g.id !== tab.selected) continue;
      try {
        tab.refined.set(key, await api(`/api/predict?gcp=${encodeURIComponent(g.id)}&image=${encodeURIComponent(im)}`));
      } catch (err) {
        tab.refined.set(key, null);
      }
      const v = tab.views.get(im);
      if (v && g.id === tab.selected) { if (!v.moved) v.located = false; v.update(); }
    }
  } finally {
    asking = false;
  }
}

function render() {
  if (!tab.data) return;
  renderList();
  renderDetails();
  renderHelp();
  renderViews();
  const u = tab.data.undo, r = tab.data.redo;
  const undo = document.getElementById("undo"), redo = document.getElementById("redo");
  undo.disabled = !u; undo.textContent = u ? `Undo: ${u}` : "Undo";
  redo.disabled = !r; redo.textContent = r ? `Redo: ${r}` : "Redo";
}

// -- the page's controls -------------------------------------------------------------------------
function wireControls() {
  const d = tab.display;
  const sliders = {
    contrast: [v => { d.contrast = Math.pow(2, v); return `${d.contrast.toFixed(2)}×`; }],
    brightness: [v => { d.brightness = v; return v.toFixed(2); }],
    gamma: [v => { d.gamma = v; return v.toFixed(1); }],
  };
  let timer = null;
  for (const [name, [set]] of Object.entries(sliders)) {
    const input = document.getElementById(name), out = document.getElementById(`${name}-out`);
    input.addEventListener("input", () => {
      out.textContent = set(parseFloat(input.value));
      clearTimeout(timer);
      timer = setTimeout(() => { for (const v of tab.views.values()) v.draw(); }, 120);
    });
  }
  document.getElementById("reset-display").addEventListener("click", () => {
    for (const [name, v] of [["contrast", 0], ["brightness", 0], ["gamma", 2]]) {
      const input = document.getElementById(name);
      input.value = v; input.dispatchEvent(new Event("input"));
    }
  });
  document.getElementById("centre").addEventListener("click", centreAll);
  document.getElementById("undo").addEventListener("click", () => edit("/api/undo", {}));
  document.getElementById("redo").addEventListener("click", () => edit("/api/redo", {}));
  document.getElementById("import").addEventListener("change", async ev => {
    const f = ev.target.files[0];
    ev.target.value = "";
    if (!f) return;
    tab.edits = tab.edits.then(async () => {
      try {
        const r = await fetch(`/api/import?name=${encodeURIComponent(f.name)}`, {method: "POST", body: await f.arrayBuffer(),
                              headers: {"Content-Type": "text/csv", "X-Aerec-Workspace": "1"}});
        const out = await r.json();
        if (!r.ok) throw new Error(out.error);
        say(out.note);
      } catch (err) {
        say(err.message, "error");
      }
      await refresh(true);
    });
  });
  document.addEventListener("keydown", ev => {
    if (ev.target instanceof HTMLInputElement) return;
    const k = ev.key.toLowerCase();
    if ((ev.ctrlKey || ev.metaKey) && k === "z" && !ev.shiftKey) { ev.preventDefault(); edit("/api/undo", {}); }
    else if ((ev.ctrlKey || ev.metaKey) && (k === "y" || (k === "z" && ev.shiftKey))) { ev.preventDefault(); edit("/api/redo", {}); }
    else if (ev.ctrlKey || ev.metaKey || ev.altKey) return;
    else if (k === "n") step(+1);
    else if (k === "p") step(-1);
    else if (k === "c") centreAll();
  });
}

function centreAll() {
  for (const v of tab.views.values()) { v.locate(v.anchor()); v.draw(); }
}

function drawLegend() {
  for (const cv of document.querySelectorAll("canvas.icon")) {
    const ctx = cv.getContext("2d"), kind = cv.dataset.icon;
    const colour = {observed: COLOURS.observed, predicted: COLOURS.predicted, residual: COLOURS.residual,
                    surveyed: COLOURS.surveyed}[kind];
    ctx.fillStyle = "#202124"; ctx.fillRect(0, 0, cv.width, cv.height);
    if (kind === "others") {
      mark(ctx, "others", 7, 11, COLOURS.control, "");
      mark(ctx, "others", 15, 11, COLOURS.check, "");
    } else {
      ctx.save(); ctx.translate(11, 11); ctx.scale(0.7, 0.7); mark(ctx, kind, 0, 0, colour, ""); ctx.restore();
    }
  }
}

// for tests and scripts: where a canvas's pixel is, and what this tab chose
function pageOrigin(image) {
  const cv = tab.views.get(image).canvas, rect = cv.getBoundingClientRect();
  return [rect.left + cv.clientLeft, rect.top + cv.clientTop];
}
window.workspace = {
  tab,
  selected: () => tab.selected,
  // image pixel <-> page position (CSS px, what a mouse event's clientX / clientY give)
  imageAt: (image, X, Y) => { const [x0, y0] = pageOrigin(image); return tab.views.get(image).toImage(X - x0, Y - y0); },
  pageOf: (image, c, r) => { const [x0, y0] = pageOrigin(image), [x, y] = tab.views.get(image).toScreen(c, r); return [x0 + x, y0 + y]; },
  view: image => { const v = tab.views.get(image); return {s: v.s, cx: v.cx, cy: v.cy}; },
  idle: () => tab.edits,
};

wireControls();
drawLegend();
refresh(true).then(() => setTimeout(poll, POLL_MS));
