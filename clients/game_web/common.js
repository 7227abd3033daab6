// bodynet rehab game: helpers of both pages (the player's page and the therapist's view).
"use strict";

const $ = (id) => document.getElementById(id);

function plural(n, word, many) { return `${n} ${n === 1 ? word : (many || word + "s")}`; }

function fmt(x, digits = 1) {
  return x === null || x === undefined || x === "" ? "–" : Number(x).toFixed(digits);
}

// "practice 1", "2", "2 (attempt 2)"
function trialLabel(t) {
  return `${t.practice ? "practice " : ""}${t.number}${t.attempt > 1 ? ` (attempt ${t.attempt})` : ""}`;
}

function trialOutcome(t) {
  if (!t.complete) return `incomplete: ${t.reason}`;
  return t.success ? "success" : "targets missed";
}

// the arm dofs whose range the tables show, with their column titles
const ROM_COLUMNS = ["shoulder_flexion", "shoulder_abduction", "elbow_flexion", "wrist_flexion",
  "elbow_pronation"];

function row(cells, attrs = {}) {
  const tr = document.createElement("tr");
  for (const [k, v] of Object.entries(attrs)) tr.setAttribute(k, v);
  for (const c of cells) {
    const td = document.createElement("td");
    td.textContent = c;
    tr.appendChild(td);
  }
  return tr;
}

// Large print: a button, remembered by the browser; ?large=1 turns it on too.
function setupLargePrint() {
  const button = $("large");
  const on = new URLSearchParams(location.search).get("large") === "1" ||
    localStorage.getItem("bodynet-large") === "1";
  const set = (value) => {
    document.body.classList.toggle("large", value);
    button.setAttribute("aria-pressed", String(value));
    button.textContent = value ? "Normal print" : "Large print";
    localStorage.setItem("bodynet-large", value ? "1" : "0");
  };
  set(on);
  button.addEventListener("click", () => set(!document.body.classList.contains("large")));
}
