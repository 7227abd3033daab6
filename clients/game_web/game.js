// bodynet rehab game: draws what the game server sends over /ws and sends the
// player's requests (start, abort) back. No library, no network beyond the page's
// own server. Points come in metres from the live shoulder: +X forward, +Y left, +Z up.
"use strict";

const $ = (id) => document.getElementById(id);
const VIEWS = [
  // side view: forward to the right, up is up
  { canvas: $("side-view"), h: (p) => p[0], v: (p) => p[2] },
  // front view as in a mirror: the player's left on the left
  { canvas: $("front-view"), h: (p) => -p[1], v: (p) => p[2] },
];
let last = null;       // the latest state message
let socket = null;
let retryMs = 500;

function send(kind) {
  if (socket && socket.readyState === WebSocket.OPEN) {
    socket.send(JSON.stringify({ t: kind }));
  } else {
    $("message").textContent = "not connected to the game";
  }
}
$("start").addEventListener("click", () => { $("message").textContent = ""; send("start"); });
$("abort").addEventListener("click", () => send("abort"));

function connect() {
  const proto = location.protocol === "https:" ? "wss" : "ws";
  socket = new WebSocket(`${proto}://${location.host}/ws`);
  socket.onopen = () => {
    retryMs = 500;
    $("conn").textContent = "connected";
    $("conn").className = "ok";
  };
  socket.onmessage = (ev) => {
    const msg = JSON.parse(ev.data);
    if (msg.t === "state") onState(msg);
    else if (msg.t === "results") onResults(msg);
    else if (msg.t === "error") $("message").textContent = msg.message;
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

function onState(msg) {
  last = msg;
  $("side").textContent = `(${msg.side} arm)`;
  $("state").textContent = msg.state;
  $("done").textContent = `${msg.done} / ${msg.of}`;
  const arm = msg.arm;
  if (!arm) {
    $("arm-state").textContent = "no arm signal";
    $("arm-state").className = "bad";
  } else if (arm.stale) {
    $("arm-state").textContent = `arm signal lost (${arm.age_s.toFixed(1)} s)`;
    $("arm-state").className = "bad";
  } else {
    $("arm-state").textContent = "arm live";
    $("arm-state").className = "ok";
  }
  if (msg.target) {
    $("cue").textContent = msg.target.arrived ? msg.target.cue : "Follow the ball…";
    $("trial").textContent = `${msg.trial.number}${msg.trial.practice ? " (practice)" : ""}`;
    $("target").textContent = `${msg.target.i} / ${msg.target.n} ${msg.target.name}`;
    $("elapsed").textContent = `${msg.target.elapsed_s.toFixed(1)} s`;
    $("score").textContent = msg.trial.score;
  } else {
    $("cue").textContent = CUES[msg.state] || "";
    $("target").textContent = "–";
    $("elapsed").textContent = "–";
    $("score").textContent = msg.score;
  }
  $("start").disabled = !(msg.state === "ready" || msg.state === "paused");
  $("abort").disabled = msg.state !== "running";
}

function fmt(x) { return x === null || x === undefined || x === "" ? "–" : Number(x).toFixed(1); }

function onResults(msg) {
  $("file").textContent = msg.file;
  const body = $("trials");
  body.replaceChildren();
  for (const t of msg.trials) {
    const times = t.targets.filter((x) => x.time_to_target_s !== null).map((x) => x.time_to_target_s);
    const mean = times.length ? times.reduce((a, b) => a + b, 0) / times.length : null;
    const outcome = !t.complete ? `incomplete: ${t.reason}` : (t.success ? "success" : "missed targets");
    const rom = (d) => (t.rom_deg[d] ? t.rom_deg[d].range : null);
    const tr = document.createElement("tr");
    tr.className = t.complete ? "complete" : "incomplete";
    tr.dataset.complete = String(t.complete);
    tr.dataset.success = String(t.success);
    const cells = [`${t.number}${t.practice ? " (practice)" : ""}`, outcome,
      `${t.targets.filter((x) => x.reached).length} / ${t.targets.length}`, t.score, fmt(mean),
      fmt(rom("shoulder_flexion")), fmt(rom("elbow_flexion")), fmt(rom("wrist_flexion")),
      fmt(rom("elbow_pronation"))];
    for (const c of cells) {
      const td = document.createElement("td");
      td.textContent = c;
      tr.appendChild(td);
    }
    body.appendChild(tr);
  }
  const mean = msg.mean_time_to_target_s;
  $("summary").textContent = msg.trials.length
    ? `${msg.complete_trials} complete trials (practice not counted), ${msg.successful_trials} ` +
      `successful, score ${msg.score}, mean time-to-target ${fmt(mean)} s` +
      (msg.finished ? " – session finished" : "")
    : "no trial yet";
}

function draw() {
  for (const view of VIEWS) drawView(view);
  requestAnimationFrame(draw);
}

function drawView({ canvas, h, v }) {
  const ctx = canvas.getContext("2d");
  const w = canvas.width, ht = canvas.height;
  const scale = (Math.min(w, ht) / 2 - 12) / 0.95;
  const X = (p) => w / 2 + h(p) * scale;
  const Y = (p) => ht / 2 - v(p) * scale;
  ctx.clearRect(0, 0, w, ht);
  // the body for reference: trunk below the shoulder, head above it
  ctx.strokeStyle = "#ccd";
  ctx.lineWidth = 14;
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
    const b = last.ball;
    const waiting = last.target && last.target.arrived;
    ctx.fillStyle = waiting ? "rgba(255,150,40,0.25)" : "rgba(150,150,150,0.2)";
    ctx.beginPath();
    ctx.arc(X(b), Y(b), last.radius_m * scale, 0, 2 * Math.PI);
    ctx.fill();
    ctx.fillStyle = waiting ? "#ff8c1a" : "#999";
    ctx.beginPath();
    ctx.arc(X(b), Y(b), 0.04 * scale, 0, 2 * Math.PI);
    ctx.fill();
  }
  const arm = last.arm;
  if (arm) {
    const colours = ["#2a6fdb", "#2fa36b", "#c04ad1"];  // upper arm, forearm, hand
    ctx.setLineDash(arm.stale ? [8, 8] : []);
    for (let i = 0; i < 3; i++) {
      ctx.strokeStyle = arm.stale ? "#aaa" : colours[i];
      ctx.lineWidth = 10 - 2 * i;
      ctx.beginPath();
      ctx.moveTo(X(arm.pts[i]), Y(arm.pts[i]));
      ctx.lineTo(X(arm.pts[i + 1]), Y(arm.pts[i + 1]));
      ctx.stroke();
    }
    ctx.setLineDash([]);
  }
}

connect();
requestAnimationFrame(draw);
