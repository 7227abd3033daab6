// bodynet rehab game, the therapist's view: past sessions as saved in the results
// folder (read by the server from its JSON files: /api/sessions).
"use strict";

setupLargePrint();
$("refresh").addEventListener("click", load);

function pct(a, b) { return b ? ` (${Math.round((100 * a) / b)} %)` : ""; }

async function load() {
  $("status").textContent = "loading…";
  let data;
  try {
    const response = await fetch("/api/sessions", { cache: "no-store" });
    data = await response.json();
  } catch (err) {
    $("status").textContent = `cannot read the sessions: ${err}`;
    return;
  }
  const days = $("days");
  days.replaceChildren();
  for (const d of data.days) {
    days.appendChild(row([d.date, d.patient || "–", d.arm, d.sessions, d.trials,
      `${d.reached} / ${d.targets}${pct(d.reached, d.targets)}`, fmt(d.mean_time_to_target_s),
      ...ROM_COLUMNS.map((c) => fmt(d.rom_deg[c]))]));
  }
  const box = $("sessions");
  box.replaceChildren();
  for (const s of data.sessions) {
    const section = document.createElement("section");
    section.className = "session";
    section.dataset.file = s.file;
    const h = document.createElement("h3");
    h.textContent = `${s.started_utc.replace("T", " ").replace("Z", " UTC")} – ` +
      `${s.patient || "no patient id"}, ${s.arm} arm, ${plural(s.trials.length, "trial")}, ` +
      `score ${s.score}${s.finished ? ", finished" : ""}` +
      (s.file === data.current ? " (this session)" : "");
    section.appendChild(h);
    const table = document.createElement("table");
    table.innerHTML = "<thead><tr><th>trial</th><th>outcome</th><th>targets reached</th>" +
      "<th>not measured</th><th>score</th><th>duration (s)</th><th>mean time-to-target (s)</th>" +
      "<th>shoulder flexion range (°)</th><th>shoulder abduction range (°)</th>" +
      "<th>elbow flexion range (°)</th><th>wrist flexion range (°)</th>" +
      "<th>forearm roll range (°)</th></tr></thead>";
    const body = document.createElement("tbody");
    for (const t of s.trials) {
      body.appendChild(row([trialLabel(t), trialOutcome({ ...t, success: t.reached === t.targets }),
        `${t.reached} / ${t.targets}`, t.not_measured, t.score, fmt(t.duration_s),
        fmt(t.mean_time_to_target_s), ...ROM_COLUMNS.map((c) => fmt(t.rom_deg[c]))],
      { class: t.complete ? "complete" : "incomplete" }));
    }
    table.appendChild(body);
    section.appendChild(table);
    const file = document.createElement("p");
    file.className = "file";
    file.textContent = s.file;
    section.appendChild(file);
    box.appendChild(section);
  }
  $("status").textContent = `${plural(data.sessions.length, "session")} saved` +
    (data.unreadable.length ? `; not readable: ${data.unreadable.join("; ")}` : "");
}

load();
