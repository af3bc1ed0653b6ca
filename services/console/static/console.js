// The mfvs operator console: one WebSocket to the console that served this page. Frames come as binary messages
// (a 4-byte header length, a JSON header with the capture stamp, the JPEG), overlays and the status as JSON text;
// requests go back as JSON text. Nothing here talks to the robot: the console carries a request out, or refuses
// it and says why.
"use strict";

const $ = (id) => document.getElementById(id);
const CORNER_COLOURS = ["#2fb95c", "#4ea1ff", "#f0b429", "#c77dff"];
const GREEN = "#2fb95c", GOAL = "#ff4fd8";

// what the tests and the benchmark read (window.mfvsConsole)
const stats = { frames: 0, delaysMs: [], consoleMs: [], firstAt: null, lastAt: null, refusals: [], results: [],
                connects: 0, lastCapture: null, sent: [] };
const page = {
  ws: null, token: sessionStorage.getItem("mfvs-token") || "", tokenRequired: false, authenticated: false,
  backoffMs: 500, nextId: 0, region: null, bitmap: null, frameHeader: null, decoding: false, pendingFrame: null,
  overlays: [], status: null,
};
// the person's stick (the on-screen one, or a gamepad through the Gamepad API), sent as snapshots to the console,
// which maps them into jog requests (services/console/jog.py)
const jog = {
  enabled: false, why: "waiting for the console", number: null, seq: 0, mode: "translation", level: 1,
  pointers: new Map(), axes: [0, 0, 0], input: "none", active: false, pad: null, padButtons: [], sent: 0,
  lastStatus: null,
};
window.mfvsConsole = { stats, page, jog };

function wallNowMs() { return performance.timeOrigin + performance.now(); }

// ------------------------------------------------------------------------------------------- the connection
function connect() {
  const url = (location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws";
  let ws;
  try { ws = new WebSocket(url); } catch (err) { retry(); return; }
  ws.binaryType = "arraybuffer";
  page.ws = ws;
  ws.onopen = () => { page.backoffMs = 500; stats.connects += 1; setLink(true, "connected"); };
  ws.onmessage = (event) => {
    if (typeof event.data === "string") onText(JSON.parse(event.data));
    else onFrame(event.data);
  };
  ws.onclose = () => { page.authenticated = false; setLink(false, "reconnecting…"); retry(); };
  ws.onerror = () => {};  // onclose follows
}

function retry() {
  setTimeout(connect, page.backoffMs);
  page.backoffMs = Math.min(page.backoffMs * 2, 5000);  // the console or the stack restarts: try again, calmly
}

function setLink(up, text) {
  const link = $("link");
  link.textContent = text;
  link.className = up ? "up" : "down";
  if (!up) $("estop").textContent = "E-STOP (not connected)";
  else renderEStop();
}

function send(message) {
  if (!page.ws || page.ws.readyState !== WebSocket.OPEN) return false;
  page.ws.send(JSON.stringify(message));
  return true;
}

function onText(message) {
  switch (message.type) {
    case "hello":
      $("robot").textContent = message.robot_id;
      jog.number = message.page;
      if (message.jog) renderJogStatus(message.jog, null);
      page.tokenRequired = message.token_required;
      page.authenticated = message.authenticated;
      if (page.tokenRequired && !page.authenticated) {
        if (page.token) send({ type: "auth", token: page.token });
        else askToken();
      }
      break;
    case "auth":
      page.authenticated = true;
      sessionStorage.setItem("mfvs-token", page.token);
      break;
    case "status": page.status = message; renderStatus(message); break;
    case "overlay":
      page.overlays.push(message);
      if (page.overlays.length > 30) page.overlays.shift();
      draw();
      break;
    case "result":
      stats.results.push(message);
      say(message.message, message.ok ? "ok" : "error");
      break;
    case "refused":
      stats.refusals.push(message);
      if (message.jog) { $("jog-state").textContent = "stick refused: " + message.message; break; }
      say("Refused: " + message.message, "error");
      if (message.reason === "token") { page.token = ""; sessionStorage.removeItem("mfvs-token"); askToken(); }
      break;
  }
}

// ------------------------------------------------------------------------------------------- the camera
function onFrame(buffer) {
  if (page.decoding) { page.pendingFrame = buffer; return; }  // the newest waits; older ones are dropped
  page.decoding = true;
  const length = new DataView(buffer).getUint32(0);
  const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 4, length)));
  const jpeg = new Blob([new Uint8Array(buffer, 4 + length)], { type: "image/jpeg" });
  createImageBitmap(jpeg).then((bitmap) => {
    if (page.bitmap) page.bitmap.close();
    page.bitmap = bitmap;
    page.frameHeader = header;
    draw();
    const now = wallNowMs();
    stats.frames += 1;
    recentFrames.push(now);
    stats.firstAt = stats.firstAt ?? now;
    stats.lastAt = now;
    stats.lastCapture = header.capture_ns;
    keep(stats.consoleMs, now - header.received_ns / 1e6);
    if (header.wall_stamps) keep(stats.delaysMs, now - header.capture_ns / 1e6);
  }).catch(() => {}).finally(() => {
    page.decoding = false;
    // drawn (or not decodable): the console sends the next frame only now, so frames never queue on the way here
    send({ type: "drawn", seq: header.seq });
    if (page.pendingFrame) { const next = page.pendingFrame; page.pendingFrame = null; onFrame(next); }
  });
}

function keep(list, value) { list.push(value); if (list.length > 5000) list.shift(); }

function overlayFor(capture) {
  let best = null;
  for (const overlay of page.overlays) {
    if (overlay.capture_ns === capture) return overlay;
    if (overlay.capture_ns <= capture) best = overlay;
  }
  return best || page.overlays[page.overlays.length - 1] || null;
}

function polygon(ctx, points, colour, width, dashed) {
  if (!points || points.length < 2) return;
  ctx.beginPath();
  ctx.setLineDash(dashed ? [8, 6] : []);
  ctx.strokeStyle = colour;
  ctx.lineWidth = width;
  points.forEach(([x, y], i) => (i ? ctx.lineTo(x, y) : ctx.moveTo(x, y)));
  ctx.closePath();
  ctx.stroke();
  ctx.setLineDash([]);
}

function draw() {
  const canvas = $("camera"), ctx = canvas.getContext("2d");
  const header = page.frameHeader;
  if (!page.bitmap || !header) return;
  if (canvas.width !== header.width || canvas.height !== header.height) {
    canvas.width = header.width; canvas.height = header.height;
  }
  ctx.drawImage(page.bitmap, 0, 0, header.width, header.height);  // a halved frame drawn at the whole size
  const paths = page.status ? page.status.paths : [];
  paths.forEach((path, i) => {
    ctx.beginPath();
    ctx.strokeStyle = CORNER_COLOURS[i % CORNER_COLOURS.length];
    ctx.lineWidth = 1.5;
    path.forEach(([x, y], j) => (j ? ctx.lineTo(x, y) : ctx.moveTo(x, y)));
    ctx.stroke();
  });
  if (page.region) polygon(ctx, boxCorners(page.region), "#ffd400", 2, true);
  const overlay = overlayFor(header.capture_ns);
  if (overlay) {
    const few = overlay.points.length <= 8;  // a tag's corners: numbered; a keypoint target's inliers: dots
    if (few) {
      polygon(ctx, overlay.goal, GOAL, 2, true);
    } else {
      ctx.strokeStyle = GOAL; ctx.lineWidth = 1;
      overlay.goal.forEach(([x, y]) => {
        ctx.beginPath(); ctx.moveTo(x - 3, y - 3); ctx.lineTo(x + 3, y + 3);
        ctx.moveTo(x - 3, y + 3); ctx.lineTo(x + 3, y - 3); ctx.stroke();
      });
    }
    polygon(ctx, overlay.outline, GREEN, 2.5, false);
    ctx.font = "16px 'DejaVu Sans', sans-serif";
    overlay.points.forEach(([x, y], i) => {
      ctx.fillStyle = few ? CORNER_COLOURS[i % CORNER_COLOURS.length] : GREEN;
      ctx.beginPath(); ctx.arc(x, y, few ? 4 : 2, 0, 2 * Math.PI); ctx.fill();
      if (few) ctx.fillText(String(i), x + 6, y - 6);
    });
    const inliers = overlay.inliers === null ? "" : `  ${overlay.inliers} inliers`;
    const lost = overlay.status === "target_lost" && overlay.detail ? `: ${overlay.detail}` : "";
    const text = `${overlay.status}${lost}  ‖e‖ ${overlay.error_norm.toExponential(2)}${inliers}`;
    ctx.fillStyle = "rgba(0,0,0,0.6)";
    ctx.fillRect(4, 4, Math.max(250, ctx.measureText(text).width + 14), 26);
    ctx.fillStyle = "#fff";
    ctx.fillText(text, 10, 23);
  }
  const fps = frameRate(wallNowMs());
  const delays = stats.delaysMs.slice(-30);
  const delay = delays.length ? ` · ${Math.round(median(delays))} ms behind capture` : "";
  const halved = header.scale > 1
    ? ` · sent at ${page.bitmap.width}×${page.bitmap.height}: this page draws slower than the camera` : "";
  $("camera-info").textContent = `${fps.toFixed(0)} frames/s${delay}${halved}`;
}

function median(values) { const s = [...values].sort((a, b) => a - b); return s[Math.floor(s.length / 2)]; }

const recentFrames = [];
function frameRate(now) {
  while (recentFrames.length && recentFrames[0] < now - 2000) recentFrames.shift();
  return recentFrames.length / 2;
}

// ------------------------------------------------------------------------------------------- the status
function renderStatus(status) {
  page.status = status;
  renderEStop();
  const features = status.features;
  if (status.taught || (features && features.goal)) {
    const goal = features && features.goal ? `servoing to ${features.goal}` : "";
    const kept = status.taught ? ` · last taught ${status.taught.goal} (${status.taught.digest}), kept in ${status.taught.path}` : "";
    const seen = features && features.front_end === "keypoints"
      ? ` · ${features.status}${features.inliers !== null ? `, ${features.inliers} inliers` : ""}${features.status === "target_lost" && features.detail ? `: ${features.detail}` : ""}`
      : "";
    $("teach-state").textContent = `${goal}${seen}${kept}`.replace(/^ · /, "");
  }
  const task = status.task, controller = status.controller;
  if (task) {
    const by = task.by ? `, by ${task.by}${task.reason ? ": " + task.reason : ""}` : "";
    const doing = task.state === "running" ? `, ${task.plan}${task.phase ? " in " + task.phase : ""}` : "";
    const hand = task.grasp ? `, the hand ${task.grasp}` : "";
    const ended = task.state !== "running" && task.outcome ? `, last ${task.outcome}` : "";
    $("task-state").textContent = `${task.state} (task ${task.task}${by}${doing}${hand}${ended})`;
  } else {
    $("task-state").textContent = "unknown (no controller answers)";
  }
  $("controller-state").textContent = controller
    ? `${controller.law}: ${controller.status}, iteration ${controller.iteration}, ‖e‖ ${controller.error_norm.toExponential(2)}`
    : "";
  plot($("error-plot"), status.error, { log: true, colour: "#4ea1ff", unit: "" });
  const speed = status.speed;
  plot($("speed-plot"), speed, { colour: "#2fb95c", limit: speed.limit, unit: " m/s", min: 0 });
  if (speed.now !== null && speed.limit) {
    const joint = speed.joint_ratio === null ? "" : `; fastest joint at ${Math.round(100 * speed.joint_ratio)} % of its limit`;
    $("speed-text").textContent = `${speed.now.toFixed(3)} m/s of ${speed.limit.toFixed(3)} m/s limit ` +
      `(${Math.round(100 * speed.now / speed.limit)} %)${joint}`;
  }
  if (status.jog) renderJogStatus(status.jog, status.safety);
  renderArm(status.arm);
  renderJoints(status.joints);
  renderFingers(status.fingers || []);
  renderHealth(status.health);
  renderEvents(status.events);
  const counts = Object.entries(status.console.errors).filter(([k]) => k.startsWith("refused."));
  $("console-counts").textContent = counts.length
    ? "console refused: " + counts.map(([k, v]) => `${k.slice(8)} ${v}`).join(", ") : "console refused nothing";
  if (!page.bitmap) $("camera-info").textContent = "no image yet";
}

function renderEStop() {
  const button = $("estop"), state = $("estop-state"), release = $("release");
  const engaged = page.status ? page.status.estop.engaged : null;
  button.classList.toggle("engaged", engaged === true);
  if (page.ws && page.ws.readyState === WebSocket.OPEN) {
    button.textContent = engaged === true ? "E-STOP ENGAGED" : "E-STOP";
  }
  state.textContent = engaged === true ? "engaged: the arm is held" : engaged === false ? "released"
    : "unknown: safety is not reporting";
  release.hidden = engaged !== true;
}

function plot(canvas, series, options) {
  const ctx = canvas.getContext("2d"), w = canvas.width, h = canvas.height, pad = 34;
  ctx.clearRect(0, 0, w, h);
  ctx.font = "12px 'DejaVu Sans', sans-serif";
  ctx.fillStyle = "#9aa0a6";
  if (!series || !series.t.length) { ctx.fillText("no data yet", pad, h / 2); return; }
  const tr = (v) => (options.log ? Math.log10(Math.max(v, 1e-9)) : v);
  let values = series.v.map(tr);
  if (options.limit) values = values.concat([tr(options.limit)]);
  let lo = Math.min(...values), hi = Math.max(...values);
  // a flat series is drawn flat: at least a decade (log) or a tenth of its size (linear) between the edges
  const least = options.log ? 1 : Math.max(1e-3, 0.1 * Math.max(Math.abs(hi), Math.abs(lo)));
  if (hi - lo < least) { const mid = (hi + lo) / 2; lo = Math.min(lo, mid - least / 2); hi = Math.max(hi, mid + least / 2); }
  if (options.min !== undefined) lo = options.min;
  const t0 = Math.min(-10, series.t[0]);
  const x = (t) => pad + (w - pad - 6) * (t - t0) / (0 - t0);
  const y = (v) => h - 18 - (h - 26) * (tr(v) - lo) / (hi - lo);
  ctx.strokeStyle = "#343a42";
  ctx.beginPath(); ctx.moveTo(pad, 4); ctx.lineTo(pad, h - 18); ctx.lineTo(w - 4, h - 18); ctx.stroke();
  const label = (v) => (options.log ? `1e${Math.round(v)}` : v.toFixed(2));
  ctx.fillText(label(hi), 2, 14);
  ctx.fillText(label(lo), 2, h - 20);
  ctx.fillText(`${t0.toFixed(0)} s`, pad, h - 4);
  ctx.fillText("now", w - 30, h - 4);
  if (options.limit) {
    ctx.strokeStyle = "#e5484d"; ctx.setLineDash([6, 4]);
    ctx.beginPath(); ctx.moveTo(pad, y(options.limit)); ctx.lineTo(w - 4, y(options.limit)); ctx.stroke();
    ctx.setLineDash([]);
    ctx.fillStyle = "#e5484d"; ctx.fillText("limit", w - 40, y(options.limit) - 4);
  }
  ctx.strokeStyle = options.colour; ctx.lineWidth = 2;
  ctx.beginPath();
  series.t.forEach((t, i) => (i ? ctx.lineTo(x(t), y(series.v[i])) : ctx.moveTo(x(t), y(series.v[i]))));
  ctx.stroke();
  ctx.lineWidth = 1;
}

// the arm the robot declares: which it is and which angles its joints are shown in (the physical degrees the arm
// reports, GetAngularPosition's, when this host describes that arm; model angles otherwise, without ranges)
function renderArm(arm) {
  const box = $("arm");
  if (!arm) { box.textContent = "no robot state yet"; box.className = "small"; return; }
  if (arm.described) {
    box.textContent = `${arm.name} (${arm.title}): degrees as the arm reports them (GetAngularPosition)`;
    box.className = "small";
  } else {
    box.textContent = `${arm.name}: not described on this host (${arm.problem}); model angles in degrees, ` +
      "no ranges";
    box.className = "small warning";
  }
}

function renderJoints(joints) {
  const box = $("joints");
  if (box.children.length !== joints.length) {
    box.replaceChildren(...joints.map(() => {
      const row = document.createElement("div");
      row.className = "joint";
      row.innerHTML = '<span class="label"></span><div class="track"><div class="mark"></div></div><span class="value"></span>';
      return row;
    }));
  }
  joints.forEach((joint, i) => {
    const row = box.children[i], track = row.querySelector(".track"), mark = row.querySelector(".mark");
    row.querySelector(".label").textContent = joint.label;
    row.querySelector(".value").textContent = `${joint.deg.toFixed(1)}°`;
    if (joint.lower_deg === null) {
      track.className = "track continuous";
      mark.style.left = `${(((joint.deg % 360) + 360) % 360) / 3.6}%`;  // where it points in a turn, 0-360°
      track.title = "continuous joint (or no range known)";
    } else {
      const span = joint.upper_deg - joint.lower_deg;
      const at = Math.min(1, Math.max(0, (joint.deg - joint.lower_deg) / span));
      track.className = joint.margin_deg < 10 ? "track near" : "track";
      mark.style.left = `${100 * at}%`;
      track.title = `${joint.lower_deg.toFixed(0)}° … ${joint.upper_deg.toFixed(0)}°`;
    }
  });
}

// the hand's fingers (none where the robot reports none): where each is, the target it holds, its current
function renderFingers(fingers) {
  const box = $("fingers");
  box.textContent = fingers.map((f) => `${f.label} ${f.deg.toFixed(1)}° → ${f.target_deg.toFixed(1)}°` +
    (f.units === null ? "" : ` (${f.units} units)`) + ` ${f.current_a.toFixed(2)} A`).join(" · ");
}

function renderHealth(services) {
  $("health").replaceChildren(...services.map((s) => {
    const li = document.createElement("li");
    const name = document.createElement("span"); name.className = "name"; name.textContent = s.name;
    const badge = document.createElement("span"); badge.className = `badge ${s.condition}`; badge.textContent = s.condition;
    const detail = document.createElement("span"); detail.className = "detail";
    detail.textContent = s.degraded.length ? s.degraded.join("; ") : s.detail;
    detail.title = s.detail;
    li.append(name, badge, detail);
    return li;
  }));
}

function renderEvents(events) {
  $("events").replaceChildren(...events.slice(0, 12).map((e) => {
    const li = document.createElement("li");
    li.className = e.level;
    const at = document.createElement("span"); at.className = "at";
    at.textContent = new Date(e.at_s * 1000).toLocaleTimeString([], { hour12: false });
    li.append(at, document.createTextNode(`${e.source}: ${e.text}`));
    return li;
  }));
}

// ------------------------------------------------------------------------------------------- requests
let toastTimer = null;
function say(text, kind) {
  const toast = $("toast");
  toast.textContent = text;
  toast.className = kind;
  toast.hidden = false;
  clearTimeout(toastTimer);
  toastTimer = setTimeout(() => { toast.hidden = true; }, kind === "error" ? 15000 : 6000);
}

function act(action, extra = {}) {
  const message = { type: "action", action, id: ++page.nextId, operator: $("operator").value.trim(),
                    reason: $("reason").value.trim(), confirm: Boolean(extra.confirm), token: page.token };
  if (action === "teach") {
    message.region_px = page.region ? boxCorners(page.region) : [];
    message.name = $("goal-name").value.trim();
  }
  const at = wallNowMs();  // before the send: the console may have acted on it before send returns
  if (!send(message)) {
    say(action === "estop_engage"
      ? "NOT CONNECTED: the e-stop was NOT sent. Use the arm's own emergency stop."
      : "Not connected to the console: nothing was sent.", "error");
    return;
  }
  stats.sent.push({ action, at });
  localStorage.setItem("mfvs-operator", message.operator);
  say(`Sent: ${action.replace("_", " ")}…`, "info");
}

function askToken() {
  const dialog = $("token-dialog");
  if (!dialog.open) dialog.showModal();
}

// ------------------------------------------------------------------------------------------- the teach's region
// a box dragged on the camera's image, in the image's own pixels (the canvas may be drawn smaller)
function imagePoint(event) {
  const canvas = $("camera"), rect = canvas.getBoundingClientRect();
  return [(event.clientX - rect.left) * canvas.width / rect.width, (event.clientY - rect.top) * canvas.height / rect.height];
}
function boxCorners([x0, y0, x1, y1]) {
  const [a, b, c, d] = [Math.min(x0, x1), Math.min(y0, y1), Math.max(x0, x1), Math.max(y0, y1)];
  return [[a, b], [c, b], [c, d], [a, d]];
}
function watchRegion() {
  const canvas = $("camera");
  let start = null;
  canvas.addEventListener("pointerdown", (event) => { start = imagePoint(event); canvas.setPointerCapture(event.pointerId); });
  canvas.addEventListener("pointermove", (event) => {
    if (start) page.region = [...start, ...imagePoint(event)];
  });
  canvas.addEventListener("pointerup", (event) => {
    if (!start) return;
    const end = imagePoint(event);
    page.region = Math.abs(end[0] - start[0]) > 8 && Math.abs(end[1] - start[1]) > 8 ? [...start, ...end] : null;
    start = null;
    $("teach-state").textContent = page.region ? "the box will be taught" : "no box: the whole view will be taught";
  });
}

// ------------------------------------------------------------------------------------------- the stick
const MODES = ["translation", "wrist", "fingers"];
const LEVELS = [1, 2, 3];
// our map of a standard-mapping gamepad (the W3C Gamepad spec's "standard" layout), mirroring `mfvs jog`'s evdev map:
// the left stick's Y and X and the right stick's Y are the three axes (up and left positive: the browser's Y axes
// point down), the left bumper is the dead-man, A (the bottom face button) cycles the modes, the right bumper and
// X (the left face button) step the speed level up and down, Start resumes a paused task
const PAD = { deadman: 4, mode: 0, faster: 5, slower: 2, resume: 9 };
const JOG_PERIOD_MS = 20;  // 50 snapshots a second while the stick is held or a pad is connected (ours)

function clamp(v) { return Math.max(-1, Math.min(1, v)); }

function watchStick() {
  for (const [id, kind] of [["jog-pad", "xy"], ["jog-z", "z"]]) {
    const area = $(id);
    const place = (event) => {
      const r = area.getBoundingClientRect();
      const dx = (event.clientX - (r.left + r.width / 2)) / (r.width / 2);
      const dy = (event.clientY - (r.top + r.height / 2)) / (r.height / 2);
      jog.pointers.set(event.pointerId, kind === "xy" ? { kind, x: clamp(dx), y: clamp(dy) } : { kind, y: clamp(dy) });
    };
    area.addEventListener("pointerdown", (event) => {
      if (!jog.enabled) return;
      event.preventDefault();
      area.setPointerCapture(event.pointerId);
      place(event);
      jogTick();  // at once: the dead-man held
    });
    area.addEventListener("pointermove", (event) => { if (jog.pointers.has(event.pointerId)) place(event); });
    const letGo = (event) => {  // the pointer up (or lost): the dead-man released
      if (!jog.pointers.delete(event.pointerId)) return;
      jogTick();
    };
    for (const kind of ["pointerup", "pointercancel", "lostpointercapture"]) area.addEventListener(kind, letGo);
  }
}

function stickAxes() {
  const axes = [0, 0, 0];
  for (const p of jog.pointers.values()) {
    if (p.kind === "xy") {
      const length = Math.hypot(p.x, p.y), scale = length > 1 ? 1 / length : 1;  // inside the pad's circle
      axes[0] = -p.y * scale; axes[1] = -p.x * scale;  // up: +X, left: +Y
    } else {
      axes[2] = -p.y;  // up: +Z
    }
  }
  return axes;
}

function readGamepad() {
  const pads = navigator.getGamepads ? Array.from(navigator.getGamepads() || []) : [];
  return pads.find((p) => p && p.connected && p.mapping === "standard") || null;
}

function pressed(pad, index) {
  const b = pad.buttons[index];
  return Boolean(b && (b.pressed || b.value > 0.5));
}

function padButtons(pad) {
  // a press (not a hold) steps the mode or the level, or resumes
  const was = jog.padButtons;
  const now = pad.buttons.map((_, i) => pressed(pad, i));
  const edge = (i) => now[i] && !was[i];
  if (edge(PAD.mode)) setMode(MODES[(MODES.indexOf(jog.mode) + 1) % MODES.length]);
  if (edge(PAD.faster)) setLevel(jog.level + 1);
  if (edge(PAD.slower)) setLevel(jog.level - 1);
  if (edge(PAD.resume)) act("task_resume");
  jog.padButtons = now;
}

function jogTick() {
  const pad = readGamepad();
  if (pad) padButtons(pad); else jog.padButtons = [];
  let snapshot = null;
  const base = { type: "jog", mode: jog.mode, speed_level: jog.level };
  if (jog.pointers.size) {
    snapshot = { ...base, input: "stick", axes: stickAxes(), deadman: true };
  } else if (pad) {
    const a = pad.axes;
    snapshot = { ...base, input: "gamepad", axes: [-(a[1] || 0), -(a[0] || 0), -(a[3] || 0)].map(clamp),
                 deadman: pressed(pad, PAD.deadman),
                 gamepad: { connected: pad.connected, timestamp: pad.timestamp, id: pad.id.slice(0, 128),
                            mapping: pad.mapping } };
  }
  jog.pad = pad;
  if (snapshot && jog.enabled && !document.hidden) {
    jog.input = snapshot.input;
    jog.axes = snapshot.axes;
    jog.deadman = snapshot.deadman;
    jog.active = true;
    sendJog(snapshot);
  } else if (jog.active) {  // nothing held and no pad (or the tab hidden): one released snapshot, then silence
    jog.active = false;
    jog.deadman = false;
    jog.axes = [0, 0, 0];
    sendJog({ ...base, input: jog.input === "gamepad" ? "gamepad" : "stick", axes: [0, 0, 0], deadman: false,
              ...(jog.input === "gamepad" ? { gamepad: { connected: Boolean(pad), timestamp: pad ? pad.timestamp : null,
                                                          id: pad ? pad.id.slice(0, 128) : "", mapping: "standard" } } : {}) });
    jog.input = "none";
  }
  renderStick();
}

function sendJog(snapshot) {
  snapshot.seq = ++jog.seq;
  if (send(snapshot)) jog.sent += 1;
}

function setMode(mode) { jog.mode = mode; renderStick(); }
function setLevel(level) { jog.level = Math.max(LEVELS[0], Math.min(LEVELS[LEVELS.length - 1], level)); renderStick(); }

function renderStick() {
  const held = { xy: false, z: false };
  for (const p of jog.pointers.values()) held[p.kind] = true;
  $("jog-pad").classList.toggle("held", held.xy);
  $("jog-z").classList.toggle("held", held.z);
  for (const id of ["jog-pad", "jog-z"]) $(id).classList.toggle("off", !jog.enabled);
  const axes = jog.pointers.size ? stickAxes() : [0, 0, 0];
  $("jog-knob").style.left = `${50 - 50 * axes[1]}%`;
  $("jog-knob").style.top = `${50 - 50 * axes[0]}%`;
  $("jog-z-knob").style.top = `${50 - 50 * axes[2]}%`;
  for (const mode of MODES) $(`jog-${mode}`).classList.toggle("on", jog.mode === mode);
  $("jog-level").textContent = String(jog.level);
  const input = jog.input === "stick" ? "the on-screen stick"
    : jog.input === "gamepad" ? `gamepad ${jog.pad ? jog.pad.id : ""}` : jog.pad ? `gamepad ${jog.pad.id} (idle)` : "none";
  $("jog-state").textContent = `input: ${input} · ${jog.mode} · speed level ${jog.level} of ${LEVELS.length} · ` +
    `dead-man ${jog.active && jog.deadman ? "HELD" : "released"}`;
}

function renderJogStatus(status, safety) {
  jog.enabled = status.enabled;
  jog.why = status.why;
  jog.lastStatus = status;
  const why = $("jog-why");
  why.hidden = status.enabled;
  why.textContent = status.enabled ? "" : `The stick is off: ${status.why}`;
  for (const id of ["jog-translation", "jog-wrist", "jog-fingers", "jog-slower", "jog-faster"]) $(id).disabled = !status.enabled;
  if (!status.enabled) jog.pointers.clear();
  const holder = status.page === null || !status.fresh ? "" : status.page === jog.number ? " · this page drives"
    : " · another page drives";
  const control = safety ? (safety.in_control || "nobody (the arm is at rest or stopping)") : "unknown (safety silent)";
  $("jog-control").textContent = `in control: ${control}${holder}`;
  renderStick();
}

window.addEventListener("DOMContentLoaded", () => {
  $("operator").value = localStorage.getItem("mfvs-operator") || "";
  watchRegion();
  $("teach").addEventListener("click", () => $("confirm-teach").showModal());
  $("teach-cancel").addEventListener("click", () => { $("confirm-teach").close(); say("Teach cancelled: nothing moved.", "info"); });
  $("teach-confirm").addEventListener("click", () => { $("confirm-teach").close(); act("teach", { confirm: true }); });
  $("region-clear").addEventListener("click", () => { page.region = null; $("teach-state").textContent = "no box: the whole view will be taught"; });
  $("estop").addEventListener("click", () => act("estop_engage"));
  watchStick();
  for (const mode of MODES) $(`jog-${mode}`).addEventListener("click", () => setMode(mode));
  $("jog-slower").addEventListener("click", () => setLevel(jog.level - 1));
  $("jog-faster").addEventListener("click", () => setLevel(jog.level + 1));
  $("resume").addEventListener("click", () => act("task_resume"));
  // a hidden tab lets go at once (its timers slow to once a second: the console would release it anyway)
  document.addEventListener("visibilitychange", () => { if (document.hidden) { jog.pointers.clear(); jogTick(); } });
  setInterval(jogTick, JOG_PERIOD_MS);
  $("start").addEventListener("click", () => act("task_start"));
  $("stop").addEventListener("click", () => act("task_stop"));
  $("grasp").addEventListener("click", () => act("grasp"));
  $("open-hand").addEventListener("click", () => $("confirm-open-hand").showModal());
  $("open-hand-cancel").addEventListener("click", () => { $("confirm-open-hand").close(); say("The hand stays closed.", "info"); });
  $("open-hand-confirm").addEventListener("click", () => { $("confirm-open-hand").close(); act("open_hand", { confirm: true }); });
  $("release").hidden = true;
  $("release").addEventListener("click", () => $("confirm-release").showModal());
  $("release-cancel").addEventListener("click", () => { $("confirm-release").close(); say("Release cancelled: the e-stop stays engaged.", "info"); });
  $("release-confirm").addEventListener("click", () => { $("confirm-release").close(); act("estop_release", { confirm: true }); });
  $("token-ok").addEventListener("click", () => {
    page.token = $("token").value;
    $("token-dialog").close();
    send({ type: "auth", token: page.token });
  });
  connect();
});
