// bodynet rehab game, the player's page: draws what the game server sends over /ws
// and sends the requests (start, stop, new session) back. No library, no network
// beyond the page's own server. Points come in metres from the live shoulder:
// +X forward, +Y left, +Z up.
"use strict";

const VIEWS = [
  // side view: forward to the right, up is up
  { canvas: $("side-view"), h: (p) => p[0], v: (p) => p[2], range: () => [-0.35, 0.9] },
  // front view as in a mirror: the player's left on the left
  { canvas: $("front-view"), h: (p) => -p[1], v: (p) => p[2],
    range: () => (last && last.side === "right" ? [-0.45, 0.9] : [-0.9, 0.45]) },
];
const V_RANGE = [-0.9, 0.6];
let last = null;       // the latest state message
let socket = null;
let retryMs = 500;
let message = null;    // {cause, state, at}: what clears the message line

function showMessage(text, cause) {
  $("message").textContent = text;
  message = text ? { cause, state: last ? last.state : null, at: Date.now() } : null;
}

function send(obj) {
  if (socket && socket.readyState === WebSocket.OPEN) {
    socket.send(JSON.stringify(obj));
  } else {
    showMessage("not connected to the game", "connection");
  }
}
$("start").addEventListener("click", () => { showMessage(""); send({ t: "start" }); });
$("stop").addEventListener("click", () => send({ t: "stop" }));
$("new-session").addEventListener("click", () => {
  showMessage("");
  send({ t: "new_session", patient: $("patient").value, arm: $("arm").value });
});
setupLargePrint();

function connect() {
  const proto = location.protocol === "https:" ? "wss" : "ws";
  socket = new WebSocket(`${proto}://${location.host}/ws`);
  socket.onopen = () => {
    retryMs = 500;
    $("conn").textContent = "connected";
    $("conn").className = "ok";
    if (message && message.cause === "connection") showMessage("");
  };
  socket.onmessage = (ev) => {
    const msg = JSON.parse(ev.data);
    if (msg.t === "state") onState(msg);
    else if (msg.t === "results") onResults(msg);
    else if (msg.t === "error") showMessage(msg.message, msg.cause);
  };
  socket.onclose = () => {
    $("conn").textContent = "disconnected – reconnecting…";
    $("conn").className = "bad";
    setTimeout(connect, retryMs);
    retryMs = Math.min(retryMs * 2, 5000);
  };
}

const CUES = {
  ready: "Press Start when you are ready.",
  paused: "Trial stopped. Press Start to go on.",
  rest: "Well done! Next trial…",
  finished: "Session complete. Thank you!",
};
const FLASH = { reached: "Reached!", missed: "Missed", "not measured": "Not measured" };

function signalText(msg) {
  if (!msg.router.connected) return "waiting for the Zenoh router…";
  if (!msg.arm) return "no arm signal";
  if (msg.arm.stale) return `arm signal lost (${msg.arm.age_s.toFixed(1)} s)`;
  return "arm live";
}

function onState(msg) {
  last = msg;
  const live = msg.router.connected && msg.arm && !msg.arm.stale;
  $("side").textContent = `(${msg.patient ? msg.patient + ", " : ""}${msg.side} arm)`;
  $("state").textContent = msg.state;
  $("done").textContent = `${msg.done} / ${msg.of}`;
  $("arm-state").textContent = signalText(msg);
  $("arm-state").className = live ? "ok" : "bad";
  const unmeasured = msg.arm ? msg.arm.unmeasured : [];
  $("unmeasured").textContent = unmeasured.length
    ? `not measured now: ${unmeasured.join(", ").replaceAll("_", " ")}` : "";
  const cue = $("cue"), countdown = $("countdown");
  cue.className = "";
  countdown.className = "";
  countdown.dataset.left = "";
  if (msg.target) {
    const t = msg.target;
    if (t.paused) {
      cue.textContent = "Arm signal lost – waiting for it to come back";
      cue.className = "lost";
      countdown.textContent = "paused";
    } else if (t.waiting_for.length) {
      cue.textContent = `Waiting for a measurement of ${t.waiting_for.join(", ").replaceAll("_", " ")}`;
      cue.className = "waiting";
    } else {
      cue.textContent = t.cue;
    }
    if (!t.paused) {
      countdown.textContent = t.arrived ? `${Math.ceil(t.left_s)} s` : "";
      countdown.dataset.left = t.arrived ? String(t.left_s) : "";
      if (t.arrived && t.left_s <= 5) countdown.className = "low";
    }
    $("trial").textContent = trialLabel(msg.trial);
    $("target").textContent = `${t.i} / ${t.n}: ${t.cue}`;
    $("score").textContent = msg.trial.score;
  } else {
    cue.textContent = msg.router.connected ? CUES[msg.state] || "" : "Waiting for the Zenoh router…";
    if (msg.router.connected && !live && (msg.state === "ready" || msg.state === "paused")) {
      cue.textContent = msg.arm ? "Arm signal lost – waiting for it to come back" : "Waiting for the arm's signal…";
      cue.className = "lost";
    }
    countdown.textContent = "";
    $("trial").textContent = "–";
    $("target").textContent = "–";
    $("score").textContent = msg.score;
  }
  const flash = $("flash");
  if (msg.flash) {
    flash.textContent = `${FLASH[msg.flash.outcome] || msg.flash.outcome}` +
      (msg.flash.outcome === "not measured" ? ` (${msg.flash.waited_for.join(", ").replaceAll("_", " ")})` : "");
    flash.dataset.outcome = msg.flash.outcome;
    flash.dataset.i = String(msg.flash.i);
    flash.classList.remove("hidden");
  } else {
    flash.classList.add("hidden");
    flash.dataset.outcome = "";
    flash.dataset.i = "";
  }
  // a message clears when its cause does: the signal is back, or the state moved on
  if (message && ((message.cause === "signal" && live) ||
      (message.cause !== "signal" && message.cause !== "connection" &&
       (msg.state !== message.state || Date.now() - message.at > 10000)))) {
    showMessage("");
  }
  $("start").disabled = !(msg.state === "ready" || msg.state === "paused");
  $("stop").disabled = msg.state !== "running";
}

function onResults(msg) {
  $("file").textContent = msg.file ? `saved to ${msg.file}` :
    "not saved yet: the results are saved when a trial ends";
  const body = $("trials");
  body.replaceChildren();
  for (const t of msg.trials) {
    const times = t.targets.filter((x) => x.time_to_target_s !== null).map((x) => x.time_to_target_s);
    const mean = times.length ? times.reduce((a, b) => a + b, 0) / times.length : null;
    const rom = (d) => (t.rom_deg[d] ? t.rom_deg[d].range : null);
    body.appendChild(row([trialLabel(t), trialOutcome(t),
      `${t.targets.filter((x) => x.reached).length} / ${t.targets.length}`,
      t.targets.filter((x) => x.outcome === "not measured").length, t.score, fmt(mean),
      ...ROM_COLUMNS.map((d) => fmt(rom(d)))],
    { class: t.complete ? "complete" : "incomplete", "data-complete": String(t.complete),
      "data-success": String(t.success) }));
  }
  $("summary").textContent = msg.trials.length
    ? `${plural(msg.complete_trials, "complete trial")} (practice not counted), ` +
      `${msg.successful_trials} successful, ${msg.targets_reached} of ${plural(msg.targets, "target")} ` +
      `reached, score ${msg.score}, mean time-to-target ${fmt(msg.mean_time_to_target_s)} s` +
      (msg.finished ? " – session finished" : "")
    : "no trial yet";
}

function drawView({ canvas, h, v, range }) {
  const dpr = window.devicePixelRatio || 1;
  const cw = Math.round(canvas.clientWidth * dpr), ch = Math.round(canvas.clientHeight * dpr);
  if (canvas.width !== cw || canvas.height !== ch) { canvas.width = cw; canvas.height = ch; }
  const ctx = canvas.getContext("2d");
  const w = canvas.width, ht = canvas.height;
  const [h0, h1] = range();
  const scale = Math.min(w / (h1 - h0), ht / (V_RANGE[1] - V_RANGE[0]));
  const ox = (w - scale * (h1 - h0)) / 2 - h0 * scale;  // the shoulder, centred in the extent
  const oy = (ht - scale * (V_RANGE[1] - V_RANGE[0])) / 2 + V_RANGE[1] * scale;
  const X = (p) => ox + h(p) * scale;
  const Y = (p) => oy - v(p) * scale;
  ctx.clearRect(0, 0, w, ht);
  const px = scale / 100;  // about a centimetre
  // the body for reference: trunk below the shoulder, head above it
  ctx.strokeStyle = "#ccd";
  ctx.lineWidth = 5 * px;
  ctx.lineCap = "round";
  const side = last && last.side === "right" ? -1 : 1;
  const mid = [0, -side * 0.22, 0];
  ctx.beginPath();
  ctx.moveTo(X([0, 0, 0]), Y([0, 0, 0]));
  ctx.lineTo(X(mid), Y(mid));
  ctx.lineTo(X([0, mid[1], -0.5]), Y([0, mid[1], -0.5]));
  ctx.stroke();
  ctx.beginPath();
  ctx.arc(X([0, mid[1], 0.2]), Y([0, mid[1], 0.2]), 0.1 * scale, 0, 2 * Math.PI);
  ctx.stroke();
  if (!last) return;
  if (last.ball) {
    const b = last.ball, t = last.target;
    const waiting = t && t.arrived && !t.paused;
    ctx.fillStyle = waiting ? "rgba(255,150,40,0.25)" : "rgba(150,150,150,0.2)";
    ctx.beginPath();
    ctx.arc(X(b), Y(b), last.radius_m * scale, 0, 2 * Math.PI);
    ctx.fill();
    if (waiting) {  // the countdown as a ring that empties
      ctx.strokeStyle = t.left_s <= 5 ? "#c0392b" : "#ff8c1a";
      ctx.lineWidth = 1.5 * px;
      ctx.beginPath();
      ctx.arc(X(b), Y(b), last.radius_m * scale, -Math.PI / 2,
        -Math.PI / 2 + 2 * Math.PI * Math.max(0, t.left_s / t.timeout_s));
      ctx.stroke();
    }
    ctx.fillStyle = waiting ? "#ff8c1a" : "#999";
    ctx.beginPath();
    ctx.arc(X(b), Y(b), 0.04 * scale, 0, 2 * Math.PI);
    ctx.fill();
  }
  const arm = last.arm;
  if (arm) {
    const colours = ["#2a6fdb", "#2fa36b", "#c04ad1"];  // upper arm, forearm, hand
    ctx.setLineDash(arm.stale ? [3 * px, 3 * px] : []);
    for (let i = 0; i < 3; i++) {
      ctx.strokeStyle = arm.stale ? "#aaa" : colours[i];
      ctx.lineWidth = (4 - i) * px;
      ctx.beginPath();
      ctx.moveTo(X(arm.pts[i]), Y(arm.pts[i]));
      ctx.lineTo(X(arm.pts[i + 1]), Y(arm.pts[i + 1]));
      ctx.stroke();
    }
    ctx.setLineDash([]);
  }
}

function draw() {
  for (const view of VIEWS) drawView(view);
  requestAnimationFrame(draw);
}

connect();
requestAnimationFrame(draw);
