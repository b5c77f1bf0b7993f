// The operator screen: renders the service's pushed state and frames, sends commands.
// Every control is a POST with this session's CSRF token; the server decides what is allowed.
"use strict";

const $ = (id) => document.getElementById(id);
const CONFIRM_COMMANDS = new Set(["Stop", "Halt"]);
const BLOCKED_WHILE_RECALIBRATING = new Set(["StartSingleJob", "StartContinuous", "Resume"]);

// What the page measured, for the operator (frame-meta) and for the tests and benchmark.
window.screenStats = { frames: 0, lastSeq: -1, latenciesMs: [], serviceMs: [], states: 0, lastState: null, retries: 0 };

let csrf = null;
let canControl = false;
let state = null;
let events = null;
let openReport = null;

// Reconnecting: the server sends state at least once a second; a stream silent for longer than
// SILENT_MS, or one the browser gave up on (a 503 when every screen slot is taken, a reset),
// is opened again after a pause that doubles up to RETRY_MAX_MS (with jitter, so screens that
// lost the server together do not all come back at the same instant).
const SILENT_MS = 10000;
const RETRY_FIRST_MS = 1000;
const RETRY_MAX_MS = 30000;
let retryMs = RETRY_FIRST_MS;
let retryTimer = null;
let silenceTimer = null;

function showMessage(text, bad) {
  const box = $("message");
  box.textContent = text;
  box.classList.toggle("bad", !!bad);
  box.hidden = false;
  clearTimeout(showMessage.timer);
  showMessage.timer = setTimeout(() => { box.hidden = true; }, bad ? 8000 : 3000);
}

async function post(url, body, contentType) {
  const headers = { "X-CSRF-Token": csrf || "" };
  if (contentType) headers["Content-Type"] = contentType;
  const reply = await fetch(url, { method: "POST", headers, body, credentials: "same-origin" });
  let data = {};
  try { data = await reply.json(); } catch (e) { data = { error: `HTTP ${reply.status}` }; }
  if (!reply.ok) throw new Error(data.error || `HTTP ${reply.status}`);
  return data;
}

function localTime(iso) {
  return iso ? new Date(iso).toLocaleTimeString([], { hour12: false }) : "-";
}

function fixed(values, digits) {
  return values.map((v) => v.toFixed(digits)).join(", ");
}

// ---- state -------------------------------------------------------------------------
function render(s) {
  state = s;
  window.screenStats.states += 1;
  window.screenStats.lastState = s;
  $("banner").className = `state-${s.display.key}`;
  $("state-label").textContent = s.display.label;
  $("vision-state").textContent = s.vision_state;
  $("cell-state").textContent = s.cell_state;
  $("heartbeat").textContent = s.heartbeat;
  if (s.shift !== undefined) $("shift").textContent = s.shift || "-";
  renderButtons(s);
  for (const [name, value] of Object.entries(s.counters)) {
    const cell = $(`count-${name}`);
    if (cell) cell.textContent = value;
  }
  $("parts-per-min").textContent = s.parts_per_min === null ? "-" : s.parts_per_min.toFixed(1);
  renderAlarm(s.alarm);
  renderCalibration(s.calibration);
  renderPicks(s.last_picks);
}

function renderButtons(s) {
  for (const button of document.querySelectorAll("button[data-command]")) {
    const command = button.dataset.command;
    const blocked = s.recalibration_open && BLOCKED_WHILE_RECALIBRATING.has(command);
    button.disabled = !canControl || !s.allowed.includes(command) || blocked;
  }
  $("recal-open").disabled = !canControl || !(s.recalibration_allowed || s.recalibration_open);
}

function renderAlarm(alarm) {
  $("alarm").hidden = !alarm;
  if (!alarm) return;
  $("alarm-reason").textContent = alarm.reason;
  $("alarm-hint").textContent = alarm.hint;
  $("alarm-time").textContent = localTime(alarm.time);
}

function renderCalibration(cal) {
  $("cal-none").hidden = !!cal;
  $("cal-table").hidden = !cal;
  $("cal-pictures").hidden = !(cal && cal.pictures);
  $("cal-no-pictures").hidden = !cal || cal.pictures;
  if (!cal) return;
  $("cal-model").textContent = cal.model;
  $("cal-rms").textContent = cal.cv_rms_mm.toFixed(4);
  $("cal-max").textContent = cal.cv_max_mm.toFixed(4);
  $("cal-time").textContent = cal.time ? new Date(cal.time).toLocaleString([], { hour12: false }) : "-";
  $("cal-source").textContent = cal.source_image;
  if (cal.pictures) {
    const tag = encodeURIComponent(cal.time || "");
    for (const [img, link, name] of [["cal-plate", "cal-plate-link", "plate.jpg"], ["cal-dev", "cal-dev-link", "deviation.png"]]) {
      const url = `/api/calibration/${name}?made=${tag}`;
      if ($(img).getAttribute("src") !== url) { $(img).src = url; $(link).href = url; }
    }
  }
}

function renderPicks(picks) {
  const rows = picks.map((p) => {
    const tr = document.createElement("tr");
    const cells = [localTime(p.time), p.part, p.class, fixed(p.table_mm, 1), fixed(p.robot_mm, 1),
      p.angle_deg === null ? "" : p.angle_deg.toFixed(1), p.outcome];
    for (const value of cells) {
      const td = document.createElement("td");
      td.textContent = value;
      tr.appendChild(td);
    }
    tr.lastChild.className = `outcome-${p.outcome}`;
    return tr;
  });
  $("picks-body").replaceChildren(...rows);
}

// ---- frames ------------------------------------------------------------------------
async function showFrame(f) {
  const img = $("frame");
  img.src = `data:image/jpeg;base64,${f.jpeg_b64}`;
  try { await img.decode(); } catch (e) { return; }  // a newer frame replaced it mid-decode
  const latency = Date.now() - f.capture_wall_ms;
  const stats = window.screenStats;
  stats.frames += 1;
  stats.lastSeq = f.seq;
  stats.latenciesMs.push(latency);
  stats.serviceMs.push(f.encoded_wall_ms - f.capture_wall_ms);
  if (stats.latenciesMs.length > 1000) { stats.latenciesMs.shift(); stats.serviceMs.shift(); }
  $("frame-seq").textContent = f.seq;
  $("frame-latency").textContent = Math.round(latency);
}

// ---- connection --------------------------------------------------------------------
function connect() {
  clearTimeout(retryTimer);
  if (events) events.close();
  events = new EventSource("/api/events");
  events.addEventListener("state", (e) => {
    heard();
    retryMs = RETRY_FIRST_MS;
    $("link").textContent = "live";
    $("link").className = "";
    render(JSON.parse(e.data));
  });
  events.addEventListener("frame", (e) => { heard(); showFrame(JSON.parse(e.data)); });
  events.onerror = () => {
    linkDown();
    if (events && events.readyState === EventSource.CLOSED) retryLater();  // the browser gave up: we do not
  };
  heard();
}

function linkDown() {
  $("link").textContent = "connection lost, retrying";
  $("link").className = "down";
}

function heard() {
  clearTimeout(silenceTimer);
  silenceTimer = setTimeout(() => { linkDown(); retryLater(); }, SILENT_MS);
}

function retryLater() {
  clearTimeout(silenceTimer);
  clearTimeout(retryTimer);
  if (events) { events.close(); events = null; }
  const wait = retryMs * (0.75 + Math.random() / 2);
  retryMs = Math.min(2 * retryMs, RETRY_MAX_MS);
  window.screenStats.retries += 1;
  retryTimer = setTimeout(reconnect, wait);
}

async function reconnect() {
  try {
    await loadSession();  // the login may have ended meanwhile: then the login dialog, not a stream
  } catch (e) {
    linkDown();
    retryLater();  // the server is not answering yet
  }
}

async function loadSession() {
  const reply = await fetch("/api/session", { credentials: "same-origin" });
  if (!reply.ok) throw new Error(`HTTP ${reply.status}`);
  const s = await reply.json();
  csrf = s.csrf;
  canControl = s.can_control;
  $("control-note").hidden = canControl;
  $("logout").hidden = !s.logged_in;
  if (state) renderButtons(state);
  if (!s.can_view) {
    $("state-label").textContent = "Log in to watch the cell";
    $("login").showModal();
    return;
  }
  connect();
}

async function login(event) {
  event.preventDefault();
  const reply = await fetch("/api/login", {
    method: "POST", credentials: "same-origin", headers: { "Content-Type": "application/json" },
    body: JSON.stringify({ user: $("login-user").value, password: $("login-password").value }),
  });
  if (!reply.ok) {
    const data = await reply.json().catch(() => ({}));
    $("login-error").textContent = data.error || `HTTP ${reply.status}`;
    $("login-error").hidden = false;
    return;
  }
  $("login-password").value = "";
  $("login-error").hidden = true;
  $("login").close();
  await loadSession();
}

// ---- commands ----------------------------------------------------------------------
function confirmCommand(text) {
  return new Promise((resolve) => {
    const dialog = $("confirm");
    $("confirm-text").textContent = text;
    dialog.returnValue = "";
    dialog.addEventListener("close", () => resolve(dialog.returnValue === "yes"), { once: true });
    dialog.showModal();
  });
}

async function sendCommand(button) {
  const command = button.dataset.command;
  if (CONFIRM_COMMANDS.has(command) && !(await confirmCommand(button.dataset.confirm))) return;
  try {
    await post(`/api/command/${command}`);
    showMessage(`${button.textContent}: sent`);
  } catch (e) {
    showMessage(`${button.textContent} refused: ${e.message}`, true);
  }
}

// ---- recalibration -----------------------------------------------------------------
function recalBusy(text) {
  $("recal-status").textContent = text;
  $("recal-capture").disabled = true;
  $("recal-accept").disabled = true;
  $("recal-reject").disabled = true;
}

function showReport(r) {
  openReport = r;
  $("recal-status").textContent = r.passes ? "The fit passes the quality gate." : "The fit fails the quality gate.";
  $("rep-source").textContent = r.source;
  $("rep-model").textContent = r.why;
  $("rep-points").textContent = `${r.points} circles` + (r.missing.length ? `, missing ${r.missing.join(", ")}` : "");
  $("rep-fit-rms").textContent = r.fit_rms_mm.toFixed(4);
  $("rep-fit-max").textContent = r.fit_max_mm.toFixed(4);
  $("rep-cv-rms").textContent = r.cv_rms_mm.toFixed(4);
  $("rep-cv-max").textContent = r.cv_max_mm.toFixed(4);
  $("rep-gate").textContent = r.passes ? "passes" : r.gate_failure;
  $("rep-gate").className = r.passes ? "" : "error";
  $("rep-plate").src = `/api/recalibration/${r.id}/plate.jpg`;
  $("rep-dev").src = `/api/recalibration/${r.id}/deviation.png`;
  $("recal-report").hidden = false;
  $("recal-accept").disabled = !r.passes;
  $("recal-reject").disabled = false;
  $("recal-capture").disabled = false;
}

async function recalibrate(url, body) {
  recalBusy("Finding the plate and fitting…");
  $("recal-report").hidden = true;
  openReport = null;
  try {
    showReport(await post(url, body, body ? "application/octet-stream" : undefined));
  } catch (e) {
    $("recal-status").textContent = `Refused: ${e.message}`;
    $("recal-capture").disabled = false;
  }
}

async function answerReport(answer) {
  if (!openReport) return;
  const id = openReport.id;
  recalBusy(answer === "accept" ? "Installing…" : "Rejecting…");
  try {
    await post(`/api/recalibration/${id}/${answer}`);
    openReport = null;
    $("recal-report").hidden = true;
    $("recal-status").textContent = answer === "accept" ? "Accepted: the cell now uses the new calibration." : "Rejected: the calibration in use is unchanged.";
    showMessage($("recal-status").textContent);
  } catch (e) {
    $("recal-status").textContent = `Refused: ${e.message}`;
    $("recal-reject").disabled = false;
  }
  $("recal-capture").disabled = false;
}

async function closeRecal() {
  if (openReport) await answerReport("reject");  // never leave a report holding the cell
  $("recal").close();
}

// ---- wiring ------------------------------------------------------------------------
document.addEventListener("DOMContentLoaded", () => {
  for (const button of document.querySelectorAll("button[data-command]")) {
    button.addEventListener("click", () => sendCommand(button));
  }
  $("login-form").addEventListener("submit", login);
  $("login-open").addEventListener("click", () => $("login").showModal());
  $("logout").addEventListener("click", async () => {
    try { await post("/api/logout"); } catch (e) { /* already logged out */ }
    window.location.reload();
  });
  $("recal-open").addEventListener("click", () => {
    $("recal-status").textContent = "";
    $("recal-capture").disabled = false;
    $("recal").showModal();
  });
  $("recal-capture").addEventListener("click", () => recalibrate("/api/recalibration/capture"));
  $("recal-file").addEventListener("change", (e) => {
    const file = e.target.files[0];
    e.target.value = "";
    if (file) recalibrate("/api/recalibration/upload", file);
  });
  $("recal-accept").addEventListener("click", () => answerReport("accept"));
  $("recal-reject").addEventListener("click", () => answerReport("reject"));
  $("recal-close").addEventListener("click", closeRecal);
  $("recal").addEventListener("cancel", (e) => { e.preventDefault(); closeRecal(); });
  loadSession().catch(() => { linkDown(); retryLater(); });
});
