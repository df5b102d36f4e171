// ERNI control page: a live map of the team over one WebSocket to the control node.
"use strict";

const SVGNS = "http://www.w3.org/2000/svg";
const $ = (id) => document.getElementById(id);
const ROBOT_RADIUS = 0.25;          // m, drawn size of a robot (at least MIN_PX)
const MIN_PX = 13;
const TRAIL = 120;                  // positions kept per robot
// Gestures, in CSS px and ms. A press that drifts no further than its slop is a tap (or, held, a
// long press); a robot is teleported only when held LONG_PRESS ms and then dragged DROP_MIN px.
const SLOP = { touch: 12, pen: 8, mouse: 5 };
const LONG_PRESS = 500;
const DROP_MIN = 24;
const HINT = "Tap or click a robot, then the map to send it there · hold a robot, then drag to teleport it · " +
  "pinch or wheel to zoom · drag to pan · shift-drag to select · hold or right-click a robot for its menu";

const ui = {
  ws: null, client: null, state: null, connected: false, everConnected: false,
  lastMessage: 0, retry: 500,
  selection: new Set(),
  view: { scale: 60, ox: 0, oy: 0, fitted: false },
  armed: null,                       // {action: "goto"|"teleport", robots: [...]}
  drag: null,                        // one-pointer gesture in progress
  pointers: new Map(),               // pointerId -> [x, y] of every pointer down on the map
  pinch: null,                       // two-finger zoom in progress
  real: new Map(),                   // robot -> true: teleport re-bases its odometry; false: a simulator moves it
  staleTeleports: new Set(),         // teleports of a robot since lost (it may come back as another machine)
  ask: null,                         // the question shown, {yes, ghost}
  menuAt: 0,                         // when the menu opened (a long press's release does not close it)
  trails: new Map(), showTrails: true,
  mic: null,
  renders: 0, drawn: {},             // states rendered; JSON of each part as last drawn
};

// True when `value` differs from what part `key` showed last: an unchanged part is not redrawn.
function changed(key, value) {
  const text = JSON.stringify(value);
  if (ui.drawn[key] === text) return false;
  ui.drawn[key] = text;
  return true;
}

// ---- geometry -------------------------------------------------------------------------
function toScreen(x, y) { return [ui.view.ox + x * ui.view.scale, ui.view.oy - y * ui.view.scale]; }
function toWorld(sx, sy) { return [(sx - ui.view.ox) / ui.view.scale, (ui.view.oy - sy) / ui.view.scale]; }
function svgPoint(ev) { const r = $("map").getBoundingClientRect(); return [ev.clientX - r.left, ev.clientY - r.top]; }
function el(tag, attrs, parent) {
  const e = document.createElementNS(SVGNS, tag);
  for (const k in attrs) e.setAttribute(k, attrs[k]);
  if (parent) parent.appendChild(e);
  return e;
}
function h(tag, attrs, text) {
  const e = document.createElement(tag);
  for (const k in (attrs || {})) e.setAttribute(k, attrs[k]);
  if (text !== undefined) e.textContent = text;
  return e;
}
function fmt(v, d) { return (v === null || v === undefined) ? "–" : Number(v).toFixed(d); }
function qualityColour(q) {
  const a = [224, 82, 58], b = [224, 180, 58], c = [62, 196, 109];
  const [p, r, t] = q < 0.5 ? [a, b, q / 0.5] : [b, c, (q - 0.5) / 0.5];
  return `rgb(${p.map((v, i) => Math.round(v + (r[i] - v) * t)).join(",")})`;
}

// ---- connection -------------------------------------------------------------------------
function connect() {
  setConn("connecting");
  const proto = location.protocol === "https:" ? "wss" : "ws";
  const ws = new WebSocket(`${proto}://${location.host}/ws${location.search}`);
  ws.binaryType = "arraybuffer";
  ui.ws = ws;
  ws.onopen = () => { ui.retry = 500; ui.lastMessage = Date.now(); setConn("ok"); };
  ws.onmessage = (ev) => { ui.lastMessage = Date.now(); onText(ev.data); };
  ws.onclose = () => {
    if (ui.ws !== ws) return;
    ui.ws = null;
    stopMic();
    setConn("lost");
    setTimeout(connect, ui.retry);
    ui.retry = Math.min(ui.retry * 2, 4000);
  };
}
function send(msg) {
  if (ui.ws && ui.ws.readyState === WebSocket.OPEN) { ui.ws.send(JSON.stringify(msg)); return true; }
  logLocal("error", "not connected to the control node: command not sent");
  return false;
}
setInterval(() => {
  if (!ui.ws || ui.ws.readyState !== WebSocket.OPEN) return;
  if (Date.now() - ui.lastMessage > 6000) { ui.ws.close(); return; }   // silent server: reconnect
  ui.ws.send('{"type":"ping"}');
}, 2000);
function setConn(s) {
  ui.connected = s === "ok";
  if (s === "ok") ui.everConnected = true;
  const c = $("conn");
  c.className = "conn " + s;
  $("conn-text").textContent = s === "ok" ? "control node connected" : s === "lost" ? "control node lost" : "connecting…";
  $("banner").classList.toggle("hidden", s === "ok" || !ui.everConnected);
  document.body.dataset.conn = s;
}

// A message the page cannot read is named in the log and dropped: the last state stays on screen.
function onText(text) {
  let m;
  try { m = JSON.parse(text); } catch (e) {
    logLocal("error", `unreadable message from the control node, ignored: ${String(e.message).slice(0, 120)}`);
    return;
  }
  if (m && typeof m === "object") onMessage(m);
}

function onMessage(m) {
  if (m.type === "hello") ui.client = m.client;
  else if (m.type === "state") { ui.state = checked(m); render(); }
  else if (m.type === "select") setSelection(m.robots);
  else if (m.type === "reply") onReply(m);
  else if (m.type === "error") { logLocal("error", m.message); showReply("", m.message, false); }
}

// ---- what a state may hold ------------------------------------------------------------------
// The page draws only what it can: a robot whose report it cannot read (a position that is not a
// finite number within WORLD metres, fields missing) is listed as faulty and left off the map, and
// the other robots are shown as usual. A link whose ends or quality are unreadable is not drawn.
const WORLD = 1e6;                   // m: a position beyond this is no place on any map
const STATES = ["ok", "warn", "lost"];
function finite(v) { return typeof v === "number" && Number.isFinite(v); }
function checkedRobot(r, i) {
  if (!r || typeof r !== "object") r = {};
  const name = typeof r.name === "string" && r.name ? r.name : `unnamed robot ${i + 1}`;
  const out = { name, number: typeof r.number === "number" || typeof r.number === "string" ? r.number : "?",
    up: r.up === true, state: STATES.includes(r.state) ? r.state : "fault",
    reasons: Array.isArray(r.reasons) ? r.reasons.filter((x) => typeof x === "string") : [],
    pose: null, address: typeof r.address === "string" ? r.address : "", task: typeof r.task === "string" ? r.task : "" };
  const why = [];
  if (!STATES.includes(r.state) || !Array.isArray(r.reasons) || typeof r.name !== "string") why.push("incomplete report");
  const p = r.pose;
  if (p !== null && p !== undefined) {
    if (p && typeof p === "object" && ["x", "y", "theta"].every((k) => finite(p[k])) && Math.abs(p.x) <= WORLD &&
        Math.abs(p.y) <= WORLD) {
      out.pose = { x: p.x, y: p.y, theta: p.theta, v: finite(p.v) ? p.v : null, w: finite(p.w) ? p.w : null,
        battery: finite(p.battery) ? p.battery : null };
    } else why.push("position unreadable");
  }
  if (why.length) { out.state = "fault"; out.reasons = [...why, ...out.reasons]; }
  return out;
}
function checked(s) {
  const list = (v) => (Array.isArray(v) ? v : []);
  s.robots = list(s.robots).map(checkedRobot);
  s.links = list(s.links).filter((l) => l && typeof l.a === "string" && typeof l.b === "string" && finite(l.quality));
  s.tasks = list(s.tasks).filter((t) => t && typeof t.uid === "string");
  for (const t of s.tasks) { t.params = t.params || {}; t.values = t.values || {}; }
  s.log = list(s.log);
  return s;
}

// ---- rendering ----------------------------------------------------------------------------
function render() {
  const s = ui.state;
  if (!s || !s.robots) return;
  ui.renders++;
  $("agent").textContent = s.agent;
  $("mode").innerHTML = `tasks as <b>${s.verb}</b>`;
  for (const r of s.robots) {
    if (!r.pose) continue;
    const t = ui.trails.get(r.name) || [];
    const last = t[t.length - 1];
    if (!last || Math.hypot(last[0] - r.pose.x, last[1] - r.pose.y) > 0.02) t.push([r.pose.x, r.pose.y]);
    if (t.length > TRAIL) t.shift();
    ui.trails.set(r.name, t);
  }
  learnRobotKinds(s);
  const fitting = !ui.view.fitted && s.robots.some((r) => r.pose);
  if (fitting) fit();
  if (changed("metrics", s.metrics)) renderMetrics(s);
  if (changed("map", [s.robots, s.links, s.tasks, s.floorplan]) || fitting) renderMap();
  if (changed("robots", s.robots)) renderRobotTable(s);
  renderStrategies(s);
  if (changed("tasks", s.tasks)) renderTasks(s);
  if (changed("log", s.log)) renderLog(s);
  $("listening").textContent = s.speech && s.speech.available ? (s.listening ? "voice: listening" : "voice: standing by — say “attention”") : "voice: no recogniser";
  $("mic").disabled = !(s.speech && s.speech.available);
  $("mic").title = s.speech && s.speech.available ? "stream the microphone to the control node's recogniser" : (s.speech ? s.speech.error : "");
}

// A teleport's result says how it was done: `moved` true on a simulator (the robot was moved),
// false on a real robot (only its odometry was re-based). Remembered beyond the task list, and
// forgotten when the robot is lost: what answers to its name next may be another machine.
function learnRobotKinds(s) {
  for (const r of s.robots) {
    if (r.state !== "lost" || !ui.real.has(r.name)) continue;
    ui.real.delete(r.name);
    for (const t of s.tasks) if (t.robot === r.name && t.preposition === "teleport") ui.staleTeleports.add(t.uid);
  }
  for (const t of [...s.tasks].reverse()) {   // oldest first: the newest answer wins
    if (ui.staleTeleports.has(t.uid)) continue;
    if (t.preposition === "teleport" && t.state === "succeeded" && typeof t.values.moved === "boolean") {
      ui.real.set(t.robot, !t.values.moved);
    }
  }
}

function renderMetrics(s) {
  const m = s.metrics, box = $("metrics");
  box.innerHTML = "";
  const add = (label, value, bad, title) => {
    const d = h("span", { class: "metric" + (bad ? " bad" : ""), title: title || "" }, label);
    d.appendChild(h("b", {}, value));
    box.appendChild(d);
  };
  add("robots up", `${m.up}/${m.robots}`, m.up < m.robots);
  if (!m.network_known) { add("network", "no NetInfo yet", false, "robots share NetInfo when MobiNet watches the network"); return; }
  add("links", String(m.links));
  add("mean quality", m.mean_quality === null ? "–" : m.mean_quality.toFixed(2), m.mean_quality !== null && m.mean_quality < 0.5);
  add("components", String(m.components), m.components > 1, "connected parts of the network");
  add("cut nodes", m.articulation_points.length ? m.articulation_points.join(" ") : "none",
      m.articulation_points.length > 0, "articulation points: robots whose loss splits the network");
  add("mean degree", String(m.degree));
}

function renderGrid(w, hgt) {
  const g = $("grid");
  g.innerHTML = "";
  const [x0, y1] = toWorld(0, 0), [x1, y0] = toWorld(w, hgt);
  let step = 1;
  while (step * ui.view.scale < 35) step *= 2;
  while (step * ui.view.scale > 160 && step > 0.25) step /= 2;
  for (let x = Math.floor(x0 / step) * step; x <= x1; x += step) {
    const [sx] = toScreen(x, 0);
    const major = Math.abs(x / (step * 5) - Math.round(x / (step * 5))) < 1e-6;
    el("line", { x1: sx, y1: 0, x2: sx, y2: hgt, class: Math.abs(x) < 1e-9 ? "axis" : "grid-line" + (major ? " grid-major" : "") }, g);
    if (sx > 24) el("text", { x: sx + 3, y: hgt - 6, class: "grid-label" }, g).textContent = `${+x.toFixed(2)}`;
  }
  for (let y = Math.floor(y0 / step) * step; y <= y1; y += step) {
    const [, sy] = toScreen(0, y);
    const major = Math.abs(y / (step * 5) - Math.round(y / (step * 5))) < 1e-6;
    el("line", { x1: 0, y1: sy, x2: w, y2: sy, class: Math.abs(y) < 1e-9 ? "axis" : "grid-line" + (major ? " grid-major" : "") }, g);
    if (sy < hgt - 24 && sy > 110) el("text", { x: 4, y: sy - 3, class: "grid-label" }, g).textContent = `${+y.toFixed(2)}`;
  }
  const px = step * ui.view.scale;
  $("scale-bar").style.width = px + "px";
  $("scale-text").textContent = `${+step.toFixed(2)} m`;
}

function renderFloorplan(fp) {
  const g = $("floor");
  g.innerHTML = "";
  if (!fp) return;
  const pts = (list) => list.map((p) => toScreen(p[0], p[1]).join(",")).join(" ");
  if (fp.bounds) {
    const [x0, y0, x1, y1] = fp.bounds;
    el("polygon", { points: pts([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]), class: "fp-bounds" }, g);
  }
  for (const wl of fp.wall) {
    const [ax, ay] = toScreen(wl.a[0], wl.a[1]), [bx, by] = toScreen(wl.b[0], wl.b[1]);
    el("line", { x1: ax, y1: ay, x2: bx, y2: by, class: "fp-wall" }, g);
  }
  for (const c of fp.circle) {
    const [cx, cy] = toScreen(c.center[0], c.center[1]);
    el("circle", { cx, cy, r: c.radius * ui.view.scale, class: "fp-solid" }, g);
  }
  for (const p of fp.polygon) el("polygon", { points: pts(p.points), class: "fp-solid" }, g);
}

function renderMap() {
  const svg = $("map"), w = svg.clientWidth, hgt = svg.clientHeight, s = ui.state;
  renderGrid(w, hgt);
  renderFloorplan(s.floorplan);
  const byName = new Map(s.robots.map((r) => [r.name, r]));
  // links
  const lg = $("links");
  lg.innerHTML = "";
  for (const l of s.links) {
    const a = byName.get(l.a), b = byName.get(l.b);
    if (!a || !b || !a.pose || !b.pose) continue;
    const [ax, ay] = toScreen(a.pose.x, a.pose.y), [bx, by] = toScreen(b.pose.x, b.pose.y);
    const line = el("line", { x1: ax, y1: ay, x2: bx, y2: by, class: "link-line" + (l.stale ? " stale" : ""),
      stroke: l.stale ? "#59626f" : qualityColour(l.quality), "stroke-width": l.stale ? 1.5 : 1.5 + 3 * l.quality,
      "data-a": l.a, "data-b": l.b, "data-quality": l.quality, "data-stale": l.stale }, lg);
    el("title", {}, line).textContent = `${l.a} – ${l.b}: delivery ratio ${l.quality.toFixed(2)}${l.stale ? " (stale)" : ""}`;
    if (!l.stale) el("text", { x: (ax + bx) / 2, y: (ay + by) / 2, class: "link-label", "data-ends": [ax, ay, bx, by].join(",") },
      lg).textContent = l.quality.toFixed(2);
  }
  // trails
  const tg = $("trails");
  tg.innerHTML = "";
  if (ui.showTrails) {
    for (const r of s.robots) {
      const t = ui.trails.get(r.name);
      if (!t || t.length < 2) continue;
      el("polyline", { points: t.map((p) => toScreen(p[0], p[1]).join(",")).join(" "), class: "trail",
        stroke: r.state === "ok" ? "#35b86b" : r.state === "warn" ? "#e65c9c" : "#7b828e" }, tg);
    }
  }
  // goals of running gotos
  const gg = $("goals");
  gg.innerHTML = "";
  for (const t of s.tasks) {
    if (!["goto", "widep"].includes(t.preposition) || ["succeeded", "failed", "cancelled"].includes(t.state)) continue;
    if (typeof t.params.x !== "number" || typeof t.params.y !== "number") continue;
    const r = byName.get(t.robot);
    const [gx, gy] = toScreen(t.params.x, t.params.y);
    if (r && r.pose) { const [rx, ry] = toScreen(r.pose.x, r.pose.y); el("line", { x1: rx, y1: ry, x2: gx, y2: gy, class: "goal-path" }, gg); }
    el("path", { d: `M${gx - 7},${gy - 7}L${gx + 7},${gy + 7}M${gx - 7},${gy + 7}L${gx + 7},${gy - 7}`, class: "goal", "data-robot": t.robot }, gg);
  }
  // robots
  const rg = $("robots");
  rg.innerHTML = "";
  const rad = Math.max(MIN_PX, ROBOT_RADIUS * ui.view.scale);
  for (const r of s.robots) {
    if (!r.pose) continue;
    let [sx, sy] = toScreen(r.pose.x, r.pose.y);
    const lifted = ui.drag && ui.drag.kind === "robot" && ui.drag.lifted && ui.drag.name === r.name;
    const g = el("g", { class: `robot ${r.state}${ui.selection.has(r.name) ? " selected" : ""}${lifted ? " lifted" : ""}`, "data-name": r.name,
      "data-state": r.state, "data-x": r.pose.x, "data-y": r.pose.y, transform: `translate(${sx},${sy})` }, rg);
    el("circle", { r: rad + 5, class: "ring" }, g);
    el("circle", { r: rad, class: "body" }, g);
    const th = r.pose.theta;
    el("line", { x1: Math.cos(th) * rad * 0.45, y1: -Math.sin(th) * rad * 0.45, x2: Math.cos(th) * (rad + 10),
      y2: -Math.sin(th) * (rad + 10), class: "heading" }, g);
    el("text", { class: "num" }, g).textContent = r.number;
    el("text", { x: rad + 6, y: -rad + 2, class: "tag" }, g).textContent = r.name;
    if (r.state === "lost") el("text", { x: rad + 6, y: -rad + 15, class: "lost-tag" }, g).textContent = "LINK LOST";
    else if (r.reasons.length) el("text", { x: rad + 6, y: -rad + 15, class: "lost-tag" }, g).textContent = r.reasons.join(", ");
    el("title", {}, g).textContent = `${r.name} (${r.state})\nx ${fmt(r.pose.x, 2)} m, y ${fmt(r.pose.y, 2)} m, heading ${fmt(r.pose.theta * 180 / Math.PI, 0)}°\n` +
      `v ${fmt(r.pose.v, 2)} m/s, battery ${fmt(r.pose.battery, 1)} V${r.task ? "\n" + r.task : ""}`;
  }
  placeLabels(svg, rad);
  if (ui.drag && ui.drag.kind === "robot" && ui.drag.lifted && ui.drag.moved) {
    el("circle", { cx: ui.drag.at[0], cy: ui.drag.at[1], r: rad, class: "ghost" }, rg);
  }
  if (ui.ask && ui.ask.ghost) {
    const [gx, gy] = toScreen(ui.ask.ghost[0], ui.ask.ghost[1]);
    el("circle", { cx: gx, cy: gy, r: rad, class: "ghost" }, rg);
  }
}

// Labels that never cover each other or a robot: robot names (and their state line) first, each at
// the first free spot around its robot, then link qualities at the first free spot along their
// link. A link label with no free spot is left out (the link's tooltip keeps its quality).
function placeLabels(svg, rad) {
  const frame = svg.getBoundingClientRect(), pad = 1;
  const taken = [...svg.querySelectorAll("#robots g.robot circle.body")].map((c) => c.getBoundingClientRect());
  const free = (r) => r.left >= frame.left && r.right <= frame.right && r.top >= frame.top && r.bottom <= frame.bottom &&
    !taken.some((t) => r.left < t.right + pad && t.left < r.right + pad && r.top < t.bottom + pad && t.top < r.bottom + pad);
  const put = (text, spots) => {
    for (const [x, y] of spots) {
      text.setAttribute("x", x); text.setAttribute("y", y);
      const r = text.getBoundingClientRect();
      if (free(r)) { taken.push(r); return true; }
    }
    return false;
  };
  const around = (w) => {  // spots beside, above and below a robot, in rings, nearest first
    const right = rad + 6, left = -rad - 6 - w, spots = [];
    for (let d = 0; d <= 65; d += 13) {
      spots.push([right, -rad + 2 - d], [right, rad + 10 + d], [left, -rad + 2 - d], [left, rad + 10 + d],
                 [-w / 2, -rad - 7 - d], [-w / 2, rad + 17 + d]);
    }
    return spots;
  };
  for (const g of svg.querySelectorAll("#robots g.robot")) {
    const tag = g.querySelector("text.tag"), state = g.querySelector("text.lost-tag");
    if (!tag) continue;
    if (!put(tag, around(tag.getBBox().width))) {
      tag.setAttribute("x", rad + 6); tag.setAttribute("y", -rad + 2); taken.push(tag.getBoundingClientRect());
    }
    if (state) {
      const x = +tag.getAttribute("x"), y = +tag.getAttribute("y");
      if (!put(state, [[x, y + 13], [x, y - 13], ...around(state.getBBox().width)])) {
        state.setAttribute("x", x); state.setAttribute("y", y + 13);  // a robot's state is never hidden
        taken.push(state.getBoundingClientRect());
      }
    }
  }
  for (const text of svg.querySelectorAll("#links text.link-label")) {
    const [ax, ay, bx, by] = text.dataset.ends.split(",").map(Number), len = Math.hypot(bx - ax, by - ay) || 1;
    const nx = -(by - ay) / len * 9, ny = (bx - ax) / len * 9, spots = [];
    for (const t of [0.5, 0.4, 0.6, 0.3, 0.7, 0.2, 0.8]) {
      const px = ax + (bx - ax) * t, py = ay + (by - ay) * t;
      spots.push([px + nx, py + ny], [px - nx, py - ny]);
    }
    if (!put(text, spots)) text.remove();
  }
}

// Rows are kept and updated in place, so a click never lands on a row being replaced.
function keyed(box, items, key, create, update) {
  const old = new Map([...box.children].filter((c) => c.dataset.key !== undefined).map((c) => [c.dataset.key, c]));
  let prev = null;
  for (const item of items) {
    const k = key(item);
    let row = old.get(k);
    if (row) old.delete(k); else { row = create(item); row.dataset.key = k; }
    update(row, item);
    const next = prev ? prev.nextSibling : box.firstChild;
    if (row !== next) box.insertBefore(row, next);
    prev = row;
  }
  for (const row of old.values()) row.remove();
}

function renderRobotTable(s) {
  $("no-robots").classList.toggle("hidden", s.robots.length > 0);
  keyed(document.querySelector("#robot-table tbody"), s.robots, (r) => r.name, (r) => {
    const tr = h("tr", { "data-name": r.name });
    const cb = h("input", { type: "checkbox", class: "sel", "data-name": r.name, "aria-label": `select ${r.name}` });
    cb.addEventListener("change", () => { cb.checked ? ui.selection.add(r.name) : ui.selection.delete(r.name); selectionChanged(); });
    const hit = h("label", { class: "hit" }); hit.appendChild(cb);
    const td0 = h("td", { class: "pick" }); td0.appendChild(hit); tr.appendChild(td0);
    tr.appendChild(h("td", { class: "num" }));
    const name = h("td", { class: "name" });
    name.appendChild(h("span", { class: "state-dot" }));
    name.appendChild(h("span", { class: "label" }));
    tr.appendChild(name);
    for (const c of ["batt", "vel", "doing"]) tr.appendChild(h("td", { class: c }));
    tr.addEventListener("contextmenu", (ev) => { ev.preventDefault(); openMenu(r.name, ev.clientX, ev.clientY); });
    return tr;
  }, (tr, r) => {
    tr.className = (ui.selection.has(r.name) ? "selected " : "") + r.state;
    tr.dataset.state = r.state;
    tr.querySelector("input").checked = ui.selection.has(r.name);
    tr.querySelector(".num").textContent = r.number;
    tr.querySelector(".name").title = r.reasons.join(", ") || r.address;
    tr.querySelector(".state-dot").className = "state-dot " + r.state;
    tr.querySelector(".label").textContent = r.name + (r.state === "lost" ? " — link lost" : r.state === "fault" ? ` — ${r.reasons[0]}` : "");
    tr.querySelector(".batt").textContent = r.pose ? fmt(r.pose.battery, 1) : "–";
    tr.querySelector(".vel").textContent = r.pose ? fmt(r.pose.v, 2) : "–";
    const doing = tr.querySelector(".doing");
    doing.textContent = r.task || "idle";
    doing.title = r.task;
  });
  $("sel-count").textContent = ui.selection.size ? `${ui.selection.size} selected` : "select robots first";
}

function renderStrategies(s) {
  const box = $("strategies");
  const want = (s.strategies || []).join(",");
  if (box.dataset.have === want) return;
  box.dataset.have = want;
  box.innerHTML = "";
  for (const name of s.strategies || []) {
    const b = h("button", { "data-act": name, title: STRATEGY_HELP[name] || "deployment strategy" }, name.replace(/_/g, " "));
    b.addEventListener("click", () => doAction(name));
    box.appendChild(b);
  }
}

function renderTasks(s) {
  const box = $("tasks");
  $("no-tasks").classList.toggle("hidden", s.tasks.length > 0);
  keyed(box, s.tasks, (t) => t.uid, (t) => {
    const row = h("div", { "data-uid": t.uid, "data-robot": t.robot });
    row.appendChild(h("span", { class: "who" }, t.robot));
    const what = h("span", { class: "what" });
    what.appendChild(h("span", { class: "badge" }));
    what.appendChild(h("span", { class: "text" }));
    row.appendChild(what);
    const x = h("button", { class: "x", title: "cancel this task" }, "×");
    x.addEventListener("click", () => send({ type: "cancel_task", uid: t.uid }));
    row.appendChild(x);
    row.appendChild(h("span", { class: "msg" }));
    const bar = h("div", { class: "bar" });
    bar.appendChild(h("i"));
    row.appendChild(bar);
    return row;
  }, (row, t) => {
    const done = ["succeeded", "failed", "cancelled"].includes(t.state);
    row.className = `task ${t.state}${done ? " done" : ""}`;
    row.dataset.state = t.state;
    row.querySelector(".what").title = `${t.verb} ${t.text} (from ${t.source})`;
    const badge = row.querySelector(".badge");
    badge.className = "badge " + t.state;
    badge.textContent = t.state;
    row.querySelector(".text").textContent = t.text;
    row.querySelector(".x").style.visibility = done ? "hidden" : "visible";
    const vals = Object.entries(t.values).map(([k, v]) => `${k}=${typeof v === "number" ? +v.toFixed(2) : v}`).join(" ");
    const msg = row.querySelector(".msg");
    msg.textContent = [t.message, vals].filter(Boolean).join(" · ");
    msg.title = t.message;
    row.querySelector(".bar i").style.width = `${Math.round(100 * (t.state === "succeeded" ? 1 : t.progress))}%`;
  });
}

const localLog = [];
function logLocal(level, text) { localLog.push({ t: Date.now() / 1000, level, text, local: true }); if (ui.state) renderLog(ui.state); }
function renderLog(s) {
  const box = $("log");
  const atBottom = box.scrollHeight - box.scrollTop - box.clientHeight < 20;
  box.innerHTML = "";
  const lines = s.log.concat(localLog).sort((a, b) => a.t - b.t).slice(-200);
  for (const l of lines) {
    const d = h("div", { class: "logline " + l.level });
    d.appendChild(h("span", { class: "t" }, new Date(l.t * 1000).toLocaleTimeString([], { hour12: false })));
    d.appendChild(document.createTextNode(l.text));
    box.appendChild(d);
  }
  if (atBottom) box.scrollTop = box.scrollHeight;
}

// ---- view ------------------------------------------------------------------------------------
function fit() {
  const s = ui.state, svg = $("map");
  const pts = s.robots.filter((r) => r.pose).map((r) => [r.pose.x, r.pose.y]);
  if (s.floorplan && s.floorplan.bounds) pts.push(s.floorplan.bounds.slice(0, 2), s.floorplan.bounds.slice(2));
  if (!pts.length || !svg.clientWidth) return;
  const xs = pts.map((p) => p[0]), ys = pts.map((p) => p[1]);
  const [x0, x1, y0, y1] = [Math.min(...xs) - 2, Math.max(...xs) + 2, Math.min(...ys) - 2, Math.max(...ys) + 2];
  const scale = Math.min(svg.clientWidth / (x1 - x0), svg.clientHeight / (y1 - y0));
  ui.view.scale = Math.max(8, Math.min(300, scale));
  ui.view.ox = svg.clientWidth / 2 - ((x0 + x1) / 2) * ui.view.scale;
  ui.view.oy = svg.clientHeight / 2 + ((y0 + y1) / 2) * ui.view.scale;
  ui.view.fitted = true;
}
function zoomAt(sx, sy, factor) {
  const [wx, wy] = toWorld(sx, sy);
  ui.view.scale = Math.max(4, Math.min(600, ui.view.scale * factor));
  ui.view.ox = sx - wx * ui.view.scale;
  ui.view.oy = sy + wy * ui.view.scale;
  if (ui.state) renderMap();
}

// ---- selection and commands -------------------------------------------------------------------
function setSelection(names) {
  ui.selection = new Set(names);
  if (ui.state) { renderMap(); renderRobotTable(ui.state); }
}
function selectionChanged() {
  send({ type: "select", robots: [...ui.selection] });
  if (ui.state) { renderMap(); renderRobotTable(ui.state); }
}
function targets(robots) {
  const list = robots || [...ui.selection];
  if (!list.length) { logLocal("warn", "select one or more robots first (checkbox, click, or shift-drag a rectangle)"); return null; }
  return list;
}
function command(action, params, robots) {
  // Stop is never refused: with nothing selected it stops every robot
  const list = action === "stop" && !(robots || ui.selection.size) ? [] : targets(robots);
  if (!list) return;
  send({ type: "command", action, params, robots: list });
}
function num(id) { return parseFloat($(id).value); }
const STRATEGY_HELP = {
  spread: "spread out: keep distance d from neighbours (potential field)",
  widep: "WiDep: click the point of interest to cover",
  patrol: "patrol: drag the territory block on the map",
  relay: "relay: click the source robot, then the destination robot",
};
const ARMED_HINT = {
  goto: "Go to: tap or click the map to send {r} there",
  teleport: "Teleport: tap or click the map to put {r} there",
  widep: "WiDep: click the point of interest {r} should cover",
  patrol: "Patrol: drag the territory block for {r}",
  relay: "Relay: click the source robot, then the destination robot, for {r}",
};
function doAction(act, robots) {
  const speed = num("p-speed");
  if (act in ARMED_HINT) arm(act, robots);
  else if (act === "forward" || act === "backward") command(act, { distance: num("p-distance"), speed }, robots);
  else if (act === "turn-left") command("turn", { angle: Math.abs(num("p-angle")) }, robots);
  else if (act === "turn-right") command("turn", { angle: -Math.abs(num("p-angle")) }, robots);
  else if (act === "randomwalk") command("randomwalk", { speed }, robots);
  else command(act, {}, robots);
}
function arm(action, robots) {
  const list = targets(robots);
  if (!list) return;
  ui.armed = { action, robots: list, ends: [] };
  $("map").classList.add("arming");
  for (const b of document.querySelectorAll("button[data-act]")) b.classList.toggle("armed", b.dataset.act === action && !b.closest("#menu"));
  const hint = $("hint");
  hint.classList.add("armed");
  hint.textContent = ARMED_HINT[action].replace("{r}", list.join(", ")) + " · Esc to cancel";
}
function disarm() {
  ui.armed = null;
  $("map").classList.remove("arming");
  for (const b of document.querySelectorAll("button.armed")) b.classList.remove("armed");
  const hint = $("hint");
  hint.classList.remove("armed");
  hint.classList.remove("lifted");
  hint.textContent = HINT;
}
function robotAt(target) {
  const g = target.closest ? target.closest("g.robot") : null;
  return g ? g.dataset.name : null;
}
function robotByName(name) { return ui.state ? ui.state.robots.find((r) => r.name === name) : null; }

// ---- Stop: nothing of the page stands between the operator and it --------------------------------
// Stop is drawn above every question, menu and overlay (style.css) and acts on the press itself, not on
// the click that may follow it: a click needs the release on the same element, and a touch screen makes
// none while another finger rests on the map. It sends the stop first, then closes whatever is open
// (the question, unanswered; the menu; an armed Go to… or Teleport to…; a robot held for a teleport),
// so that nothing that was open acts after it.
function stopNow() {
  command("stop", {});
  if (ui.ask) answer(false);
  closeMenu();
  if (ui.armed) disarm();
  if (ui.drag) { dropGesture(); if (ui.state) renderMap(); }
}

// ---- pointer gestures on the map -------------------------------------------------------------
// One pointer: tap, pan, shift-drag a rectangle, or hold a robot and drag it (teleport). Two
// fingers: pinch zoom about the point between them (and pan with it). Mouse, pen and touch alike.
function onPointerDown(ev) {
  if (ev.button !== 0) return;
  closeMenu();
  const at = svgPoint(ev), name = robotAt(ev.target);
  $("map").setPointerCapture(ev.pointerId);
  ui.pointers.set(ev.pointerId, at);
  if (ui.pointers.size === 2) { startPinch(); return; }
  if (ui.pointers.size > 2 || ui.pinch || ui.ask) return;
  if (ui.armed && ui.armed.action === "relay") {
    if (name) pickRelayEnd(name);
    return;
  }
  const base = { id: ev.pointerId, start: at, at, moved: false, slop: SLOP[ev.pointerType] || SLOP.mouse };
  if (ui.armed && ui.armed.action === "patrol") ui.drag = { ...base, kind: "rect", patrol: true };
  else if (name) ui.drag = { ...base, kind: "robot", name, lifted: false, timer: setTimeout(lift, LONG_PRESS) };
  else if (ev.shiftKey) ui.drag = { ...base, kind: "rect" };
  else ui.drag = { ...base, kind: "pan", ox: ui.view.ox, oy: ui.view.oy };
}
// Held still long enough on a robot: it is lifted, and a drag now teleports it.
function lift() {
  const d = ui.drag;
  if (!d || d.kind !== "robot" || d.moved) return;
  d.lifted = true;
  const hint = $("hint");
  hint.classList.add("lifted");
  hint.textContent = `Teleport ${d.name}: drag it where it is · release here for its menu`;
  if (navigator.vibrate) navigator.vibrate(20);
  if (ui.state) renderMap();
}
function endLift() {
  const hint = $("hint");
  if (!hint.classList.contains("lifted")) return;
  hint.classList.remove("lifted");
  if (!ui.armed) hint.textContent = HINT;
}
function dropGesture() {
  const d = ui.drag;
  ui.drag = null;
  if (d && d.timer) clearTimeout(d.timer);
  $("rubber").classList.add("hidden");
  $("map").classList.remove("panning");
  endLift();
  return d;
}
function twoFingers() {
  const [a, b] = [...ui.pointers.values()];
  return { d: Math.max(1, Math.hypot(a[0] - b[0], a[1] - b[1])), mid: [(a[0] + b[0]) / 2, (a[1] + b[1]) / 2] };
}
function startPinch() {
  dropGesture();
  const f = twoFingers();
  ui.pinch = { d0: f.d, scale0: ui.view.scale, anchor: toWorld(f.mid[0], f.mid[1]) };
  if (ui.state) renderMap();
}
function movePinch() {
  const p = ui.pinch, f = twoFingers();
  ui.view.scale = Math.max(4, Math.min(600, p.scale0 * f.d / p.d0));
  ui.view.ox = f.mid[0] - p.anchor[0] * ui.view.scale;   // the world point first between the fingers stays there
  ui.view.oy = f.mid[1] + p.anchor[1] * ui.view.scale;
  if (ui.state) renderMap();
}
function onPointerMove(ev) {
  const at = svgPoint(ev), [wx, wy] = toWorld(at[0], at[1]);
  $("cursor").textContent = `x ${wx.toFixed(2)} m   y ${wy.toFixed(2)} m`;
  if (ui.pointers.has(ev.pointerId)) ui.pointers.set(ev.pointerId, at);
  if (ui.pinch) { if (ui.pointers.size >= 2) movePinch(); return; }
  const d = ui.drag;
  if (!d || d.id !== ev.pointerId) return;
  d.at = at;
  if (!d.moved && Math.hypot(at[0] - d.start[0], at[1] - d.start[1]) > d.slop) {
    d.moved = true;
    if (d.kind === "robot" && !d.lifted) {   // moved before the long press: the map pans, the robot stays
      clearTimeout(d.timer);
      Object.assign(d, { kind: "pan", ox: ui.view.ox, oy: ui.view.oy });
    }
  }
  if (!d.moved) return;
  if (d.kind === "pan") {
    ui.view.ox = d.ox + at[0] - d.start[0]; ui.view.oy = d.oy + at[1] - d.start[1];
    $("map").classList.add("panning");
    renderMap();
  } else if (d.kind === "rect") {
    const r = $("rubber");
    r.classList.remove("hidden");
    r.setAttribute("x", Math.min(d.start[0], at[0])); r.setAttribute("y", Math.min(d.start[1], at[1]));
    r.setAttribute("width", Math.abs(at[0] - d.start[0])); r.setAttribute("height", Math.abs(at[1] - d.start[1]));
  } else if (d.kind === "robot") renderMap();
}
function onPointerCancel(ev) {
  ui.pointers.delete(ev.pointerId);
  if (ui.pointers.size < 2) ui.pinch = null;
  if (ui.drag && ui.drag.id === ev.pointerId) { dropGesture(); if (ui.state) renderMap(); }
}
function onPointerUp(ev) {
  ui.pointers.delete(ev.pointerId);
  if (ui.pinch) { if (ui.pointers.size < 2) ui.pinch = null; return; }   // the other finger does nothing more
  if (!ui.drag || ui.drag.id !== ev.pointerId) return;
  const d = dropGesture();
  const at = svgPoint(ev), [wx, wy] = toWorld(at[0], at[1]);
  if (d.kind === "pan" && d.moved) {  // the release point, even when the last moves were coalesced
    ui.view.ox = d.ox + at[0] - d.start[0]; ui.view.oy = d.oy + at[1] - d.start[1];
    renderMap();
  }
  if (d.kind === "robot") {
    if (d.lifted && Math.hypot(at[0] - d.start[0], at[1] - d.start[1]) >= DROP_MIN) {
      const r = robotByName(d.name);
      const heading = r && r.pose ? r.pose.theta * 180 / Math.PI : 0;
      teleport([d.name], { x: round(wx), y: round(wy), heading: round(heading) });
    } else if (d.lifted) {
      openMenu(d.name, ev.clientX, ev.clientY);
    } else {
      if (ev.ctrlKey || ev.metaKey || ev.shiftKey) ui.selection.has(d.name) ? ui.selection.delete(d.name) : ui.selection.add(d.name);
      else ui.selection = new Set([d.name]);
      selectionChanged();
      if (ui.selection.size) arm("goto");
    }
    renderMap();
  } else if (d.kind === "rect" && d.patrol) {
    if (!d.moved) return;
    const a = ui.armed, [ax, ay] = toWorld(d.start[0], d.start[1]);
    disarm();
    command("patrol", { xmin: round(Math.min(ax, wx)), ymin: round(Math.min(ay, wy)), xmax: round(Math.max(ax, wx)),
      ymax: round(Math.max(ay, wy)) }, a.robots);
  } else if (d.kind === "rect") {
    const [x0, x1] = [Math.min(d.start[0], at[0]), Math.max(d.start[0], at[0])];
    const [y0, y1] = [Math.min(d.start[1], at[1]), Math.max(d.start[1], at[1])];
    if (!(ev.ctrlKey || ev.metaKey)) ui.selection.clear();
    for (const r of ui.state ? ui.state.robots : []) {
      if (!r.pose) continue;
      const [sx, sy] = toScreen(r.pose.x, r.pose.y);
      if (sx >= x0 && sx <= x1 && sy >= y0 && sy <= y1) ui.selection.add(r.name);
    }
    selectionChanged();
  } else if (d.kind === "pan" && !d.moved && ui.armed) {
    const a = ui.armed;
    disarm();
    if (a.action === "goto") command("goto", { x: round(wx), y: round(wy), speed: num("p-speed") }, a.robots);
    else if (a.action === "widep") command("widep", { x: round(wx), y: round(wy) }, a.robots);
    else teleport(a.robots, { x: round(wx), y: round(wy) });
  }
}

// ---- teleport: asked first unless every robot is known to be simulated --------------------------
function teleport(robots, params) {
  const fp = ui.state && ui.state.floorplan;
  if (fp && fp.bounds) {
    const [x0, y0, x1, y1] = fp.bounds;
    if (params.x < x0 || params.x > x1 || params.y < y0 || params.y > y1) {
      logLocal("error", `teleport of ${robots.join(", ")} refused: (${params.x}, ${params.y}) m is outside the floor plan ` +
        `(x ${x0}…${x1}, y ${y0}…${y1}); drop it inside`);
      return;
    }
  }
  const real = robots.filter((r) => ui.real.get(r) === true), unknown = robots.filter((r) => !ui.real.has(r));
  if (!real.length && !unknown.length) { command("teleport", params, robots); return; }
  const where = `(${params.x}, ${params.y}) m`;
  const text = real.length
    ? `${real.join(", ")} ${real.length > 1 ? "are real robots" : "is a real robot"}: a teleport does not move it, it re-bases ` +
      `its odometry so that its pose reads ${where}. Do this only when it really stands there.`
    : `Teleport ${unknown.join(", ")} to ${where}? A simulator moves the robot there; a real robot stays where it is and ` +
      `its odometry is re-based to read that pose. This page has not yet seen how ${unknown.join(", ")} teleports.`;
  ask(real.length ? "Re-base odometry?" : "Teleport?", text, [params.x, params.y], () => command("teleport", params, robots));
}
function ask(title, text, ghost, yes) {
  ui.ask = { yes, ghost, at: performance.now() };
  $("confirm-title").textContent = title;
  $("confirm-text").textContent = text;
  $("confirm").classList.remove("hidden");
  $("confirm-cancel").focus();
  if (ui.state) renderMap();
}
function answer(ok) {
  const a = ui.ask;
  if (a && ok && fresh(a.at)) return;   // a stray press as it opens does not say yes
  ui.ask = null;
  $("confirm").classList.add("hidden");
  if (ui.state) renderMap();
  if (a && ok) a.yes();
}
function pickRelayEnd(name) {
  const a = ui.armed;
  a.ends.push(name);
  if (a.ends.length < 2) { $("hint").textContent = `Relay: source ${name}; now click the destination robot · Esc to cancel`; return; }
  disarm();
  command("relay", { source: a.ends[0], destination: a.ends[1] }, a.robots);
}
function round(v) { return Math.round(v * 100) / 100; }

// ---- context menu -------------------------------------------------------------------------------
function openMenu(name, x, y) {
  const m = $("menu");
  m.innerHTML = "";
  m.appendChild(h("div", { class: "title" }, name));
  const items = [["Go to…", "goto"], ["Random walk", "randomwalk"], ["Forward", "forward"], ["Back", "backward"],
    ["Turn left", "turn-left"], ["Turn right", "turn-right"], ["Stop", "stop"], ["Cancel tasks", "cancel"], ["Teleport to…", "teleport"]];
  for (const s of (ui.state && ui.state.strategies) || []) items.push([s.replace(/_/g, " "), s]);
  for (const [label, act] of items) {
    const b = h("button", { "data-act": act }, label);
    b.addEventListener("click", () => { closeMenu(); doAction(act, [name]); });
    if (act === "teleport") b.title = "then tap or click the map; a real robot's odometry is re-based, after a question";
    m.appendChild(b);
  }
  const only = h("button", {}, "Select only this robot");
  only.addEventListener("click", () => { closeMenu(); setSelection([name]); selectionChanged(); });
  m.appendChild(only);
  // shown, then placed: the whole menu on screen, above a phone's Stop bar (which stays on top of it)
  const stop = $("cmd-stop"), bottom = getComputedStyle(stop).position === "fixed" ? stop.getBoundingClientRect().top : innerHeight;
  m.style.maxHeight = Math.max(120, bottom - 8) + "px";
  m.classList.remove("hidden");
  m.style.left = Math.max(0, Math.min(x, innerWidth - m.offsetWidth - 4)) + "px";
  m.style.top = Math.max(4, Math.min(y, bottom - m.offsetHeight - 4)) + "px";
  const s = stop.getBoundingClientRect(), r = m.getBoundingClientRect();   // never over Stop: beside it
  if (r.left < s.right && s.left < r.right && r.top < s.bottom && s.top < r.bottom) {
    m.style.left = (s.left - r.width - 4 >= 0 ? s.left - r.width - 4 : Math.min(s.right + 4, innerWidth - r.width)) + "px";
  }
  ui.menuAt = performance.now();
}
// True for a moment after something opened: a press that opened it does not also choose in it.
function fresh(since) { return performance.now() - since < 300; }
function closeMenu() { $("menu").classList.add("hidden"); }

// ---- speech: typed, microphone, replies -----------------------------------------------------
function onReply(m) {
  if (m.channel === "voice" && ui.state) ui.state.listening = m.text === "Listening" ? true : m.text === "Standing by" ? false : ui.state.listening;
  const mine = m.client === ui.client || m.channel === "voice";
  if (mine) showReply(m.heard, m.text, m.accepted);
  if (mine && $("speak-browser").checked && window.speechSynthesis) {
    try { speechSynthesis.speak(new SpeechSynthesisUtterance(m.text)); } catch (e) { /* no voices */ }
  }
}
function showReply(heard, said, ok) {
  const r = $("last-reply");
  r.className = "reply " + (ok ? "ok" : "no");
  r.innerHTML = "";
  if (heard) r.appendChild(h("span", { class: "heard" }, `“${heard}” → `));
  r.appendChild(h("span", { class: "said" }, said));
}
async function startMic() {
  if (!navigator.mediaDevices) { logLocal("error", "no microphone access on this page (needs https or localhost)"); return; }
  try {
    const stream = await navigator.mediaDevices.getUserMedia({ audio: { channelCount: 1, echoCancellation: true, noiseSuppression: true } });
    const ctx = new AudioContext({ sampleRate: 16000 });
    const src = ctx.createMediaStreamSource(stream);
    const proc = ctx.createScriptProcessor(4096, 1, 1);
    proc.onaudioprocess = (e) => {
      if (!ui.ws || ui.ws.readyState !== WebSocket.OPEN) return;
      ui.ws.send(toPcm16(e.inputBuffer.getChannelData(0), ctx.sampleRate));
    };
    src.connect(proc); proc.connect(ctx.destination);
    ui.mic = { stream, ctx, proc };
    send({ type: "mic", on: true, rate: 16000 });
    $("mic").classList.add("on");
  } catch (err) { logLocal("error", `microphone: ${err.message || err}`); }
}
function toPcm16(f32, rate) {
  const step = rate / 16000, n = Math.floor(f32.length / step), out = new Int16Array(n);
  for (let i = 0; i < n; i++) { const v = Math.max(-1, Math.min(1, f32[Math.floor(i * step)])); out[i] = v < 0 ? v * 32768 : v * 32767; }
  return out.buffer;
}
function stopMic() {
  if (!ui.mic) return;
  ui.mic.proc.disconnect(); ui.mic.stream.getTracks().forEach((t) => t.stop()); ui.mic.ctx.close();
  ui.mic = null;
  $("mic").classList.remove("on");
  if (ui.ws && ui.ws.readyState === WebSocket.OPEN) send({ type: "mic", on: false, rate: 16000 });
}

// ---- wiring ------------------------------------------------------------------------------------
function wire() {
  const svg = $("map");
  svg.addEventListener("pointerdown", onPointerDown);
  svg.addEventListener("pointermove", onPointerMove);
  svg.addEventListener("pointerup", onPointerUp);
  svg.addEventListener("pointercancel", onPointerCancel);
  // A finger's gesture on the map is done by its pointer events: no click follows it, which would
  // land on whatever the gesture opened under the finger (the menu, the teleport question).
  // (touchstart: a touchend goes to the element first touched, which a redraw may have replaced).
  svg.addEventListener("touchstart", (ev) => { if (ev.cancelable) ev.preventDefault(); }, { passive: false });
  svg.addEventListener("wheel", (ev) => { ev.preventDefault(); const [sx, sy] = svgPoint(ev); zoomAt(sx, sy, ev.deltaY < 0 ? 1.15 : 1 / 1.15); }, { passive: false });
  svg.addEventListener("contextmenu", (ev) => {
    ev.preventDefault();
    if (ui.pointers.size) return;   // a finger held down: the long press gesture handles it
    const name = robotAt(ev.target);
    if (name) openMenu(name, ev.clientX, ev.clientY); else closeMenu();
  });
  document.addEventListener("keydown", (ev) => {
    if (ev.key === "Escape") { if (ui.ask) answer(false); disarm(); closeMenu(); }
  });
  document.addEventListener("click", (ev) => {
    if (!$("menu").contains(ev.target) && !fresh(ui.menuAt)) closeMenu();
  });
  $("confirm-ok").onclick = () => answer(true);
  $("confirm-cancel").onclick = () => answer(false);
  $("confirm").addEventListener("click", (ev) => { if (ev.target === $("confirm")) answer(false); });
  $("hint").textContent = HINT;
  $("zoom-in").onclick = () => zoomAt(svg.clientWidth / 2, svg.clientHeight / 2, 1.3);
  $("zoom-out").onclick = () => zoomAt(svg.clientWidth / 2, svg.clientHeight / 2, 1 / 1.3);
  $("zoom-fit").onclick = () => { fit(); if (ui.state) renderMap(); };
  $("trails-toggle").onclick = (ev) => { ui.showTrails = !ui.showTrails; ev.target.classList.toggle("on", ui.showTrails); if (ui.state) renderMap(); };
  $("sel-all").onclick = () => { setSelection(ui.state ? ui.state.robots.map((r) => r.name) : []); selectionChanged(); };
  $("sel-none").onclick = () => { setSelection([]); selectionChanged(); };
  for (const b of document.querySelectorAll(".panel .buttons button[data-act]:not(#cmd-stop)")) b.addEventListener("click", () => doAction(b.dataset.act));
  const stop = $("cmd-stop");
  stop.addEventListener("pointerdown", () => stopNow());
  stop.addEventListener("click", (ev) => { if (ev.detail === 0) stopNow(); });   // Enter or Space on the focused button
  stop.addEventListener("contextmenu", (ev) => ev.preventDefault());
  $("say-form").addEventListener("submit", (ev) => {
    ev.preventDefault();
    const text = $("say-text").value.trim();
    if (!text) return;
    if (send({ type: "say", text, selection: [...ui.selection] })) $("say-text").value = "";
  });
  $("mic").onclick = () => (ui.mic ? stopMic() : startMic());
  window.addEventListener("resize", () => { if (ui.state) renderMap(); });
}

window.erni = { ui, toScreen, toWorld };   // for scripted tests and the console
wire();
connect();
