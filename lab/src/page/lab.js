// Nori Lab's page: the robot drawn from the lab's state frames (points the lab computes from
// the one robot description), joint sliders within the calibrated ranges, a tool target
// dragged in 3D (the lab solves the arm's inverse kinematics), the stop button. Everything
// that moves the robot is checked again by the lab and the driver; this page only makes it
// hard to ask for what they would refuse.
"use strict";

const token = new URLSearchParams(location.hash.slice(1)).get("token") || "";
const canvas = document.getElementById("view");
const ctx = canvas.getContext("2d");
const $ = (id) => document.getElementById(id);

const lab = {
  connected: false, page: null, model: null, state: null, frames: 0,
  missed: 0, // state frames with a joint whose reply the driver missed (drawn hollow grey)
  replies: [], ended: [], recorded: [],
  target: null, // {arm, position, rotation}
  camera: { az: 0.9, el: 0.35, dist: 2.2, center: [0.15, 0, 0.85], fov: 0.8 },
};
window.lab = lab;

// ---- the link ----
let ws = null;
function send(msg) {
  if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(msg));
}
function connect() {
  ws = new WebSocket(`ws://${location.host}/ws?token=${encodeURIComponent(token)}`);
  ws.binaryType = "arraybuffer";
  ws.onopen = () => { lab.connected = true; };
  ws.onclose = () => {
    lab.connected = false;
    setControl(false);
    $("status").textContent = "disconnected: retrying…";
    setTimeout(connect, 1000);
  };
  ws.onmessage = (ev) => {
    if (ev.data instanceof ArrayBuffer) { showImage(new Uint8Array(ev.data)); return; }
    const m = JSON.parse(ev.data);
    if (m.type === "hello") { lab.page = m.page; buildCameras(m.cameras); }
    else if (m.type === "model") { lab.model = m; buildJoints(); }
    else if (m.type === "state") {
      lab.state = m; lab.frames++;
      if (m.joints.some((j) => !j.v)) lab.missed++;
      update(); redraw();
    }
    else if (m.type === "reply") {
      lab.replies.push(m);
      if (lab.replies.length > 50) lab.replies.shift();
      const r = $("reply");
      if (m.ok) { r.className = "muted"; r.textContent = m.text || (m.solved ? `reached within ${(m.solved.position_error_m * 1000).toFixed(2)} mm` : "taken"); }
      else { r.className = "bad"; r.textContent = `refused: ${m.error}`; if (lab.target && m.refused === "unreachable") lab.target.unreachable = true; }
    } else if (m.type === "recorded") {
      lab.recorded.push(m.outcome);
    } else if (m.type === "ended") {
      lab.ended.push(m.why);
      setControl(false);
      $("reply").className = "bad";
      $("reply").textContent = `teleoperation ended: ${m.why.replace("_", " ")}`;
    }
  };
}

// ---- the cameras: each image is the camera's own JPEG, shown as it came ----
lab.images = {};
function buildCameras(names) {
  $("cameras").innerHTML = names.map((n) => `<figure><img id="cam-${n}" alt="${n}"><figcaption id="cap-${n}">${n}</figcaption></figure>`).join("");
  for (const n of names) {
    const img = document.getElementById(`cam-${n}`);
    lab.images[n] = { received: 0, decoded: 0, broken: 0 };
    img.onload = () => { img.dataset.loaded = `${img.naturalWidth}x${img.naturalHeight}`; lab.images[n].decoded++; };
    img.onerror = () => { lab.images[n].broken++; };
  }
}
function showImage(bytes) {
  if (bytes[0] !== 1) return;
  const name = new TextDecoder().decode(bytes.subarray(2, 2 + bytes[1]));
  const img = document.getElementById(`cam-${name}`);
  if (!img) return;
  lab.images[name].received++;
  const old = img.src;
  img.src = URL.createObjectURL(new Blob([bytes.subarray(2 + bytes[1])], { type: "image/jpeg" }));
  if (old) URL.revokeObjectURL(old);
}

// ---- control and the dead-man ----
function setControl(on) {
  $("control").checked = on;
  if (!on) { if (lab.target) send({ type: "release" }); lab.target = null; }
}
$("control").onchange = (e) => setControl(e.target.checked);
setInterval(() => { if ($("control").checked) send({ type: "alive" }); }, 100);
document.addEventListener("visibilitychange", () => { if (document.hidden) setControl(false); });
$("stop").onclick = () => { setControl(false); send({ type: "stop" }); };
$("resume").onclick = () => send({ type: "resume" });
$("record-start").onclick = () => send({ type: "record_start", task: $("task").value });
$("record-stop").onclick = () => send({ type: "record_stop" });
$("record-discard").onclick = () => send({ type: "record_discard" });

// The page offers nothing the robot would refuse: while it is in its safe state (stopped, or
// no supervisor) the controls do not send; `lab.setTool` does, for scripts that check the lab's
// own refusal.
function blocked() {
  if (!lab.state || !lab.state.safe) return false;
  $("reply").className = "bad";
  $("reply").textContent = lab.state.stopped ? "stopped: resume first" : "the robot is in its safe state";
  return true;
}

function armOf(bus) { return lab.state && lab.state.arms.find((a) => a.bus === bus); }
function selectedArm() { return $("arm").value; }

// Moves the target of `arm` to `position` (`rotation` [w,x,y,z], else the tool's own): the
// page's API for scripts and tests, used by the drag too.
lab.setTool = (arm, position, rotation) => {
  const a = armOf(arm);
  if (!a) return false;
  rotation = rotation || (lab.target && lab.target.arm === arm ? lab.target.rotation : a.rotation);
  lab.target = { arm, position: position.slice(), rotation: rotation.slice(), unreachable: false };
  $("control").checked = true;
  send({ type: "tool", arm, position: lab.target.position, rotation: lab.target.rotation });
  redraw();
  return true;
};
lab.stop = () => $("stop").click();
lab.resume = () => $("resume").click();

// ---- joints table and sliders ----
function buildJoints() {
  const body = document.querySelector("#joints tbody");
  body.innerHTML = "";
  $("arm").innerHTML = lab.model.arms.map((a) => `<option>${a.bus}</option>`).join("");
  lab.model.joints.forEach((j, i) => {
    const tr = document.createElement("tr");
    const slider = j.role === "wheel" ? "<span class=muted>speed</span>"
      : `<input type=range min=${j.range[0]} max=${j.range[1]} step=0.001 data-joint="${j.name}">`;
    tr.innerHTML = `<td>${j.name}</td><td>${slider}</td><td id=p${i}></td><td id=t${i}></td><td id=c${i}></td><td id=s${i}></td>`;
    body.appendChild(tr);
  });
  body.querySelectorAll("input[type=range]").forEach((s) => {
    s.oninput = () => {
      if (blocked()) return;
      $("control").checked = true;
      lab.target = null;
      send({ type: "joints", goals: { [s.dataset.joint]: parseFloat(s.value) } });
    };
  });
}

const FLAG_OUTPUT_LOST = 1, FLAG_BUS_DISABLED = 2, FLAG_BUS_LOST = 4, FLAG_DRIVER_TRIP = 8;
function jointState(j) {
  if (!j.v) return "not read";
  if (j.f & FLAG_BUS_LOST) return "bus lost";
  if (j.f & (FLAG_BUS_DISABLED | FLAG_DRIVER_TRIP)) return "bus off (tripped)";
  if (j.f & FLAG_OUTPUT_LOST) return "output lost";
  return j.on ? "on" : "torque off";
}

function update() {
  const s = lab.state;
  const st = s.stopped ? "STOPPED (resume to drive)" : s.safe ? "SAFE STATE (no supervisor?)" : "driving";
  const t = s.extra.teleop;
  const who = t.owner == null ? "nobody in control" : t.owner === lab.page ? "you are in control" : `page ${t.owner} in control`;
  $("status").textContent = `${lab.connected ? "connected" : "offline"} · ${st} · ${who}`;
  canvas.className = s.stopped ? "stopped" : s.safe ? "safe" : "";
  s.joints.forEach((j, i) => {
    const cell = (k) => document.getElementById(k + i);
    if (!cell("p")) return;
    cell("p").textContent = j.p.toFixed(3);
    cell("t").textContent = j.t.toFixed(0);
    cell("c").textContent = j.c.toFixed(2);
    cell("s").textContent = jointState(j);
    cell("s").className = j.v && j.on && !j.f ? "" : "bad";
    const slider = document.querySelector(`input[data-joint="${lab.model.joints[i].name}"]`);
    if (slider && document.activeElement !== slider) slider.value = j.p;
  });
  for (const c of s.extra.cameras) {
    const cap = document.getElementById(`cap-${c.name}`);
    if (!cap) continue;
    const stale = c.age_ms == null || c.age_ms > 500;
    cap.textContent = `${c.name} ${c.width}×${c.height} · ${c.age_ms == null ? "no image yet" : `${c.age_ms.toFixed(0)} ms old`}`;
    cap.className = stale ? "bad" : "muted";
  }
  const l = s.extra.lift, bs = s.extra.base;
  $("body").textContent = [
    l ? `lift ${l.state}${l.height_m != null ? ` at ${l.height_m.toFixed(3)} m` : ""}` : "no lift",
    bs ? `base x ${bs.x_m.toFixed(2)} m, y ${bs.y_m.toFixed(2)} m, heading ${bs.heading_rad.toFixed(2)} rad, ${bs.linear_m_s.toFixed(2)} m/s${bs.flags.length ? ` (${bs.flags.join(", ")})` : ""}` : "no base",
  ].join(" · ");
  const rec = s.extra.recording;
  lab.recording = rec;
  $("recording").textContent = !rec ? "this lab records nothing (start it with --dataset DIR)"
    : `${rec.episodes} episode(s) in ${rec.dataset} · ${rec.state}${rec.seconds != null ? ` ${rec.seconds.toFixed(1)} s` : ""}`
      + (rec.last ? ` · last: ${rec.last.saved ? `episode ${rec.last.episode} saved, ${rec.last.frames} frames` : rec.last.discarded ? "discarded" : rec.last.failed}` : "");
  $("events").innerHTML = s.extra.events.slice().reverse()
    .map((e) => `${e.kind} joint ${e.joint} bus ${e.bus} level ${e.level} value ${e.value.toFixed(1)}`).join("<br>");
}

// ---- the 3D view: a perspective camera orbiting a point, drawn on a 2D canvas ----
const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const mul = (a, k) => [a[0] * k, a[1] * k, a[2] * k];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const unit = (a) => mul(a, 1 / Math.hypot(a[0], a[1], a[2]));

function basis() {
  const c = lab.camera;
  const eye = add(c.center, mul([Math.cos(c.el) * Math.cos(c.az), Math.cos(c.el) * Math.sin(c.az), Math.sin(c.el)], c.dist));
  const f = unit(sub(c.center, eye));
  const r = unit(cross(f, [0, 0, 1]));
  const u = cross(r, f);
  const focal = canvas.height / (2 * Math.tan(c.fov / 2));
  return { eye, f, r, u, focal };
}
// A point of the base's frame on the canvas, in canvas pixels (and its depth, m).
function project(p, b = basis()) {
  const d = sub(p, b.eye);
  const z = dot(d, b.f);
  return [canvas.width / 2 + b.focal * dot(d, b.r) / z, canvas.height / 2 - b.focal * dot(d, b.u) / z, z];
}
// ... and in the page's CSS pixels, for scripted pointer events.
lab.project = (p) => {
  const [x, y] = project(p);
  const rect = canvas.getBoundingClientRect();
  return [rect.left + x * rect.width / canvas.width, rect.top + y * rect.height / canvas.height];
};
lab.view = () => {
  const rect = canvas.getBoundingClientRect();
  return Object.assign({ width: canvas.width, height: canvas.height, left: rect.left, top: rect.top, cssWidth: rect.width, cssHeight: rect.height }, lab.camera);
};

// Temperature → colour: blue when cool, through yellow, red at the firmware cutoff.
function heat(t, cutoff) {
  const x = Math.max(0, Math.min(1, (t - 30) / (cutoff - 30)));
  const r = Math.round(255 * Math.min(1, 2 * x)), g = Math.round(255 * Math.min(1, 2 * (1 - x))), b = Math.round(255 * Math.max(0, 1 - 3 * x));
  return `rgb(${r},${g},${b})`;
}
lab.heat = heat;

function line(b, p, q, color, width, dash) {
  const [x0, y0, z0] = project(p, b), [x1, y1, z1] = project(q, b);
  if (z0 <= 0.05 || z1 <= 0.05) return;
  ctx.strokeStyle = color; ctx.lineWidth = width; ctx.setLineDash(dash || []);
  ctx.beginPath(); ctx.moveTo(x0, y0); ctx.lineTo(x1, y1); ctx.stroke();
  ctx.setLineDash([]);
}

// Drawn when something changed (a state frame, the view, the target), at most once an
// animation frame: an idle page costs the operator's machine nothing.
let drawPending = false;
function redraw() {
  if (!drawPending) { drawPending = true; requestAnimationFrame(draw); }
}
lab.redraw = redraw;

function draw() {
  drawPending = false;
  const b = basis();
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  for (let k = -10; k <= 10; k++) {
    line(b, [k / 10, -1, 0], [k / 10, 1, 0], "#e6e6e6", 1);
    line(b, [-1, k / 10, 0], [1, k / 10, 0], "#e6e6e6", 1);
  }
  const s = lab.state, m = lab.model;
  if (!s || !m) return;
  // The base's footprint and the lift's column up to the shoulders.
  const h = 0.225, sq = [[h, h], [-h, h], [-h, -h], [h, -h]];
  for (let k = 0; k < 4; k++) line(b, [...sq[k], 0.05], [...sq[(k + 1) % 4], 0.05], "#555", 2);
  const shoulders = s.arms.map((a) => a.points[0]);
  if (shoulders.length) {
    const top = mul(shoulders.reduce((acc, p) => add(acc, p), [0, 0, 0]), 1 / shoulders.length);
    line(b, [0, 0, 0.05], [0, 0, top[2]], "#777", 10);
    if (shoulders.length > 1) line(b, shoulders[0], shoulders[1], "#777", 8);
  }
  if ($("workspace").checked) {
    ctx.fillStyle = "rgba(40,160,80,0.35)";
    for (const a of m.arms) for (const p of a.workspace) {
      const [x, y, z] = project(p, b);
      if (z > 0.05) ctx.fillRect(x - 1, y - 1, 2, 2);
    }
  }
  for (const a of s.arms) {
    const names = m.arms.find((x) => x.bus === a.bus).joints;
    const idx = names.map((n) => m.joints.findIndex((j) => j.name === n));
    for (let k = 0; k + 1 < a.points.length; k++) line(b, a.points[k], a.points[k + 1], "#2b3a55", 7, a.valid ? null : [6, 6]);
    // Each joint at its origin, coloured by its motor's temperature; a motor without torque
    // hollow grey, one whose bus is off or tripped crossed out.
    for (let k = 0; k < idx.length; k++) {
      const j = s.joints[idx[k]], info = m.joints[idx[k]];
      const [x, y, z] = project(a.points[k + 1], b);
      if (z <= 0.05) continue;
      // Its size: the motor's current (9 px at rest, up to 15 px at 3 A).
      ctx.beginPath(); ctx.arc(x, y, 9 + 2 * Math.min(3, Math.abs(j.c)), 0, 2 * Math.PI);
      ctx.fillStyle = j.v && j.on ? heat(j.t, info.cutoff_c) : "#bbb";
      ctx.fill(); ctx.lineWidth = 2; ctx.strokeStyle = "#111"; ctx.stroke();
      if (j.f & (FLAG_BUS_DISABLED | FLAG_DRIVER_TRIP | FLAG_OUTPUT_LOST | FLAG_BUS_LOST)) {
        ctx.strokeStyle = "#c0141c"; ctx.lineWidth = 3;
        ctx.beginPath(); ctx.moveTo(x - 11, y - 11); ctx.lineTo(x + 11, y + 11); ctx.moveTo(x + 11, y - 11); ctx.lineTo(x - 11, y + 11); ctx.stroke();
      }
    }
    // The gripper at the tool: its jaw opening drawn from the gripper joint.
    const gi = m.joints.findIndex((j) => j.role === "gripper" && j.bus === a.bus);
    const [x, y, z] = project(a.points[a.points.length - 1], b);
    if (z > 0.05) {
      const g = gi >= 0 ? s.joints[gi] : null;
      ctx.beginPath(); ctx.arc(x, y, 5 + 6 * Math.max(0, g ? g.p : 0.5), 0, 2 * Math.PI);
      ctx.lineWidth = 4; ctx.strokeStyle = g && g.v && g.on ? heat(g.t, m.joints[gi].cutoff_c) : "#bbb"; ctx.stroke();
    }
  }
  if (lab.target) {
    const [x, y, z] = project(lab.target.position, b);
    if (z > 0.05) {
      ctx.beginPath(); ctx.arc(x, y, 12, 0, 2 * Math.PI);
      ctx.lineWidth = 3; ctx.strokeStyle = lab.target.unreachable ? "#c0141c" : "#d0208f"; ctx.stroke();
    }
  }
  ctx.font = "bold 22px system-ui";
  if (s.stopped) { ctx.fillStyle = "#c0141c"; ctx.fillText("STOPPED", 14, 30); }
  else if (s.safe) { ctx.fillStyle = "#e0a000"; ctx.fillText("SAFE STATE", 14, 30); }
}

// ---- pointer, keyboard, gamepad ----
let drag = null;
canvas.addEventListener("pointerdown", (e) => {
  canvas.setPointerCapture(e.pointerId);
  const rect = canvas.getBoundingClientRect();
  const px = (e.clientX - rect.left) * canvas.width / rect.width, py = (e.clientY - rect.top) * canvas.height / rect.height;
  const arm = armOf(selectedArm());
  const grab = lab.target ? lab.target.position : arm ? arm.points[arm.points.length - 1] : null;
  if (grab) {
    const [x, y, z] = project(grab);
    if (Math.hypot(px - x, py - y) < 16) { drag = { kind: "target", start: grab.slice(), px, py, z }; return; }
  }
  drag = { kind: "orbit", px, py, az: lab.camera.az, el: lab.camera.el };
});
canvas.addEventListener("pointermove", (e) => {
  if (!drag) return;
  const rect = canvas.getBoundingClientRect();
  const px = (e.clientX - rect.left) * canvas.width / rect.width, py = (e.clientY - rect.top) * canvas.height / rect.height;
  if (drag.kind === "orbit") {
    lab.camera.az = drag.az - (px - drag.px) * 0.01;
    lab.camera.el = Math.max(-0.2, Math.min(1.4, drag.el + (py - drag.py) * 0.01));
    redraw();
    return;
  }
  // The target moves in the plane facing the camera through where it was grabbed.
  const b = basis(), k = drag.z / b.focal;
  const p = add(drag.start, add(mul(b.r, (px - drag.px) * k), mul(b.u, -(py - drag.py) * k)));
  if (!blocked()) lab.setTool(selectedArm(), p);
});
canvas.addEventListener("pointerup", () => { drag = null; });
canvas.addEventListener("wheel", (e) => { e.preventDefault(); lab.camera.dist = Math.max(0.6, Math.min(6, lab.camera.dist * Math.exp(e.deltaY * 0.001))); redraw(); });
$("workspace").onchange = redraw;
document.addEventListener("keydown", (e) => {
  const step = { ArrowUp: [0.005, 0, 0], ArrowDown: [-0.005, 0, 0], ArrowLeft: [0, 0.005, 0], ArrowRight: [0, -0.005, 0], PageUp: [0, 0, 0.005], PageDown: [0, 0, -0.005] }[e.key];
  const arm = armOf(selectedArm());
  if (!step || !arm || e.target.tagName === "INPUT") return;
  e.preventDefault();
  if (blocked()) return;
  lab.setTool(selectedArm(), add(lab.target ? lab.target.position : arm.points[arm.points.length - 1], step));
});
// A gamepad's A button is a dead-man: the target follows the sticks only while it is held.
let lastPad = performance.now();
function gamepad() {
  const now = performance.now(), dt = Math.min(0.05, (now - lastPad) / 1000);
  lastPad = now;
  const pad = navigator.getGamepads ? Array.from(navigator.getGamepads()).find((g) => g && g.connected) : null;
  if (pad) {
    const held = pad.buttons[0] && pad.buttons[0].pressed;
    const arm = armOf(selectedArm());
    if (held && arm && !blocked()) {
      const dz = (v) => (Math.abs(v) < 0.15 ? 0 : v);
      const v = [-dz(pad.axes[1]) * 0.15, -dz(pad.axes[0]) * 0.15, -dz(pad.axes[3] || 0) * 0.15];
      if (v.some((x) => x !== 0)) lab.setTool(selectedArm(), add(lab.target ? lab.target.position : arm.points[arm.points.length - 1], mul(v, dt)));
    } else if (lab.padHeld) setControl(false);
    lab.padHeld = held;
  }
  requestAnimationFrame(gamepad);
}

connect();
redraw();
requestAnimationFrame(gamepad);
