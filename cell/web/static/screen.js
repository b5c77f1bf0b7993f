// The operator screen: renders the service's pushed state and frames, sends commands.
// Every control is a POST with this session's CSRF token; the server decides what is allowed.
"use strict";

const $ = (id) => document.getElementById(id);
const CONFIRM_COMMANDS = new Set(["Stop", "Halt"]);
const BLOCKED_WHILE_RECALIBRATING = new Set(["StartSingleJob", "StartContinuous", "Resume"]);

// What the page measured, for the operator (frame-meta) and for the tests and benchmark.
window.screenStats = {
  frames: 0, lastSeq: -1, latenciesMs: [], serviceMs: [], states: 0, lastState: null, retries: 0,
  liveFrames: 0, lastLive: false, lastCaptured: null,
};

let csrf = null;
let canControl = false;
let state = null;
let events = null;
let openReport = null;
let recipesLoaded = false;
let shownRecipe = null;
const RECIPES_REFRESH_MS = 30000;

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

// The status line: a reserved line under the banner (never over the content); a message stays
// a while, then the line empties but keeps its place.
function showMessage(text, bad) {
  const box = $("message");
  box.textContent = text;
  box.title = text;
  box.classList.toggle("bad", !!bad);
  clearTimeout(showMessage.timer);
  showMessage.timer = setTimeout(() => { box.textContent = ""; box.title = ""; box.classList.remove("bad"); },
    bad ? 15000 : 5000);
}

// A refused request: the server's message, and its operator words when it gave them (say, do, details).
class Refused extends Error {
  constructor(data, status) {
    super(data.error || `HTTP ${status}`);
    this.data = data;
  }
}

async function post(url, body, contentType) {
  const headers = { "X-CSRF-Token": csrf || "" };
  if (contentType) headers["Content-Type"] = contentType;
  const reply = await fetch(url, { method: "POST", headers, body, credentials: "same-origin" });
  let data = {};
  try { data = await reply.json(); } catch (e) { data = { error: `HTTP ${reply.status}` }; }
  if (!reply.ok) throw new Refused(data, reply.status);
  return data;
}

// One date format everywhere: ISO 8601 in the screen's local time with its zone (2026-12-01T14:03:05+01:00).
function isoLocal(iso) {
  if (!iso) return "-";
  const d = new Date(iso);
  if (Number.isNaN(d.getTime())) return iso;
  const two = (n) => String(n).padStart(2, "0");
  const offset = -d.getTimezoneOffset();
  const zone = `${offset >= 0 ? "+" : "-"}${two(Math.floor(Math.abs(offset) / 60))}:${two(Math.abs(offset) % 60)}`;
  return `${d.getFullYear()}-${two(d.getMonth() + 1)}-${two(d.getDate())}T${two(d.getHours())}:${two(d.getMinutes())}:${two(d.getSeconds())}${zone}`;
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
  $("state-next").textContent = s.display.next || "";
  $("vision-state").textContent = s.vision_state;
  $("cell-state").textContent = s.cell_state;
  $("heartbeat").textContent = s.heartbeat;
  if (s.shift !== undefined) $("shift").textContent = s.shift || "-";
  renderButtons(s);
  renderClasses(s.part_classes || []);
  for (const [name, value] of Object.entries(s.counters)) {
    const cell = $(`count-${name}`);
    if (cell) cell.textContent = value;
  }
  $("parts-per-min").textContent = s.parts_per_min === null ? "-" : s.parts_per_min.toFixed(1);
  renderAlarm(s.alarm);
  renderWarnings(s.warnings || []);
  renderRecipe(s);
  renderCheckToggle(s);
  renderCalibration(s.calibration);
  renderPicks(s.last_picks);
}

// One counter row per part class, in the registry's order, before "Parts / min" (made once per class).
function renderClasses(classes) {
  const end = $("count-classes-end");
  for (const c of classes) {
    if ($(`count-${c.key}`)) continue;
    const row = document.createElement("div");
    const dt = document.createElement("dt");
    const dd = document.createElement("dd");
    dt.textContent = c.label;
    dd.id = `count-${c.key}`;
    dd.textContent = "0";
    row.append(dt, dd);
    end.parentNode.insertBefore(row, end);
  }
}

function renderButtons(s) {
  for (const button of document.querySelectorAll("button[data-command]")) {
    const command = button.dataset.command;
    const blocked = s.recalibration_open && BLOCKED_WHILE_RECALIBRATING.has(command);
    button.disabled = !canControl || !s.allowed.includes(command) || blocked;
  }
  $("recal-open").disabled = !canControl || !(s.recalibration_allowed || s.recalibration_open);
  $("alarm-recal").disabled = $("recal-open").disabled;
  const recipeOk = canControl && s.recipe_allowed;
  $("recipe-select").disabled = !recipeOk;
  $("recipe-use").disabled = !recipeOk || $("recipe-select").value === (s.recipe || "");
}

function renderAlarm(alarm) {
  $("alarm").hidden = !alarm;
  document.querySelector("aside").classList.toggle("alarmed", !!alarm);  // the alarm card right under the buttons
  if (!alarm) return;
  $("alarm-recal").hidden = !alarm.do.includes("Recalibrate");  // the alarm's advice, one press away

  $("alarm-reason").textContent = alarm.say;
  $("alarm-hint").textContent = alarm.do;
  $("alarm-details").hidden = !alarm.details;
  $("alarm-technical").textContent = alarm.details;
  $("alarm-time").textContent = isoLocal(alarm.time);
}

function renderWarnings(warnings) {
  $("warnings").hidden = warnings.length === 0;
  const items = warnings.map((w) => {
    const li = document.createElement("li");
    li.textContent = `${w.say} ${w.do}`.trim();
    li.title = w.details || "";
    return li;
  });
  $("warnings-list").replaceChildren(...items);
}

// ---- recipes -----------------------------------------------------------------------
function renderRecipe(s) {
  $("recipe-active").textContent = s.recipe || "none";
  const select = $("recipe-select");
  if (recipesLoaded && shownRecipe !== null && shownRecipe !== (s.recipe || "")) loadRecipes().catch(() => {});
  shownRecipe = s.recipe || "";
  if (!recipesLoaded || (document.activeElement !== select && !select.dataset.dirty)) {
    if ([...select.options].some((o) => o.value === (s.recipe || ""))) select.value = s.recipe || "";
  }
}

async function loadRecipes() {
  const reply = await fetch("/api/recipes", { credentials: "same-origin" });
  if (!reply.ok) return;
  const data = await reply.json();
  const none = new Option("none (the cell's own settings)", "");
  const options = [none, ...data.recipes.map((r) => {
    const o = new Option(r.description ? `${r.id}: ${r.description}` : r.id, r.id);
    if (r.error) { o.disabled = true; o.title = r.error; o.textContent = `${r.id} (invalid)`; }
    return o;
  })];
  const select = $("recipe-select");
  const chosen = select.dataset.dirty ? select.value : data.active || "";
  select.replaceChildren(...options);
  select.value = options.some((o) => o.value === chosen && !o.disabled) ? chosen : data.active || "";
  if (select.value === (data.active || "")) delete select.dataset.dirty;
  recipesLoaded = true;
  if (state) renderButtons(state);
}

async function useRecipe() {
  const id = $("recipe-select").value;
  try {
    await post("/api/recipe", JSON.stringify({ recipe_id: id }), "application/json");
    delete $("recipe-select").dataset.dirty;
    showMessage(id ? `Recipe ${id} is in use from the next start.` : "No recipe: the cell's own settings from the next start.");
  } catch (e) {
    showMessage(`Recipe not changed: ${e.message}`, true);
  }
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
  $("cal-time").textContent = isoLocal(cal.time);
  $("cal-source").textContent = cal.source_image;
  if (cal.pictures) {
    const tag = encodeURIComponent(cal.time || "");
    for (const [img, name] of [["cal-plate", "plate.jpg"], ["cal-dev", "deviation.png"]]) {
      const url = `/api/calibration/${name}?made=${tag}`;
      if ($(img).getAttribute("src") !== url) $(img).src = url;
    }
  }
}

function renderPicks(picks) {
  const rows = picks.map((p) => {
    const tr = document.createElement("tr");
    const cells = [isoLocal(p.time), p.part, p.class, fixed(p.table_mm, 1), fixed(p.robot_mm, 1),
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
  if (!f.live) {  // a live frame waits for its interval and its screen: no latency to measure
    stats.latenciesMs.push(latency);
    stats.serviceMs.push(f.encoded_wall_ms - f.capture_wall_ms);
    if (stats.latenciesMs.length > 1000) { stats.latenciesMs.shift(); stats.serviceMs.shift(); }
  }
  stats.lastLive = !!f.live;
  stats.lastCaptured = f.captured_utc || null;
  if (f.live) stats.liveFrames += 1;
  $("frame-kind").hidden = false;
  $("frame-kind").textContent = f.live ? "● live camera" : "job frame";
  $("frame-kind").className = f.live ? "badge live" : "badge";
  $("frame-time").textContent = isoLocal(f.captured_utc);
  $("frame-seq").textContent = f.seq;
  $("frame-latency").textContent = Math.round(latency);
  $("frame-shown").hidden = !!f.live;  // a live frame waits for its screen: its latency says nothing
  if (f.check) renderCheck(f.check);
}

// ---- the camera check (run-cell camera --live on the screen) ----------------------------
function renderCheck(c) {
  $("check-wait").hidden = true;
  $("check-readings").hidden = false;
  $("check-focus").textContent = `${c.focus.toFixed(1)}, best ${c.focus_best.toFixed(1)} (${c.focus_pct.toFixed(0)} %)`;
  $("check-focus-meter").value = c.focus_pct;
  const e = c.exposure;
  $("check-exposure").textContent = `mean ${e.mean.toFixed(0)} of 255, black ${e.black_pct.toFixed(1)} %, white ${e.white_pct.toFixed(1)} %`;
  const top = Math.max(...e.histogram, 1e-9);
  $("check-histogram").replaceChildren(...e.histogram.map((share) => {
    const bar = document.createElement("i");
    bar.style.height = `${Math.max(1, Math.round(100 * share / top))}%`;
    return bar;
  }));
  const p = c.plate;
  $("check-plate").textContent = p
    ? `${p.found} of ${p.expected} circles, ${p.coverage_pct.toFixed(0)} % of the view${p.in_view ? "" : " (not wholly in view)"}, ` +
      `camera ${p.tilt_deg.toFixed(1)} deg from square${p.nearer ? ` (${p.nearer} nearer)` : ""}, turned ${p.turned_deg.toFixed(1)} deg`
    : `not found (${c.plate_note})`;
  const advice = c.advice.length ? c.advice : ["nothing"];
  $("check-advice").replaceChildren(...advice.map((a) => { const li = document.createElement("li"); li.textContent = a; return li; }));
}

function renderCheckToggle(s) {
  const on = !!s.camera_check;
  $("check-toggle").setAttribute("aria-pressed", String(on));
  $("check-toggle").classList.toggle("on", on);
  $("check-toggle").disabled = !canControl;
  if ($("check").hidden === on) {  // switched (here, on another screen, or timed out)
    $("check").hidden = !on;
    $("picks").hidden = on;
    $("check-wait").hidden = false;
    $("check-readings").hidden = true;
  }
}

async function toggleCheck() {
  const on = !(state && state.camera_check);
  try {
    await post("/api/camera-check", JSON.stringify({ on }), "application/json");
  } catch (e) {
    showMessage(`Camera check: ${e.message}`, true);
  }
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
  if (s.can_view && !recipesLoaded) loadRecipes().catch(() => {});
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
    showMessage(`${button.textContent}: accepted`);
  } catch (e) {
    showMessage(`${button.textContent} refused: ${e.message}`, true);
  }
}

// ---- recalibration -----------------------------------------------------------------
// What the recalibration dialog says: a line, what to do, and the technical text behind "details".
function recalSay(say, todo, details) {
  $("recal-status").textContent = say;
  $("recal-do").textContent = todo || "";
  $("recal-details").hidden = !details;
  $("recal-details").open = false;
  $("recal-technical").textContent = details || "";
}

function recalRefused(e) {
  const d = e.data || {};
  recalSay(`Refused: ${d.say || e.message}`, d.do, d.say ? d.details : "");
}

function recalBusy(text) {
  recalSay(text);
  $("recal-capture").disabled = true;
  $("recal-accept").disabled = true;
  $("recal-reject").disabled = true;
}

function showReport(r) {
  openReport = r;
  recalSay(r.passes ? "The fit passes the quality gate: Accept to use it, or Reject." : "The fit fails the quality gate: Reject it and try again.");
  $("rep-source").textContent = r.source;
  $("rep-model").textContent = r.why;
  $("rep-points").textContent = `${r.points} circles` + (r.missing.length ? `, missing ${r.missing.join(", ")}` : "");
  $("rep-fit-rms").textContent = r.fit_rms_mm.toFixed(4);
  $("rep-fit-max").textContent = r.fit_max_mm.toFixed(4);
  $("rep-cv-rms").textContent = r.cv_rms_mm.toFixed(4);
  $("rep-cv-max").textContent = r.cv_max_mm.toFixed(4);
  const gate = r.gate_words;
  $("rep-gate").textContent = r.passes ? "passes" : gate ? `${gate.say} ${gate.do}`.trim() : r.gate_failure;
  $("rep-gate").className = r.passes ? "" : "error";
  $("rep-gate-details").hidden = r.passes || !gate;
  $("rep-gate-technical").textContent = r.passes ? "" : r.gate_failure;
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
    recalRefused(e);
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
    recalSay(answer === "accept" ? "Accepted: the cell now uses the new calibration." : "Rejected: the calibration in use is unchanged.");
    showMessage($("recal-status").textContent);
    if (answer === "reject") $("recal").close();  // nothing left to look at
  } catch (e) {
    recalRefused(e);
    $("recal-reject").disabled = false;
  }
  $("recal-capture").disabled = false;
}

// ---- pictures full size --------------------------------------------------------------
function openPicture(img) {
  if (!img.getAttribute("src")) return;
  $("picture-img").src = img.src;
  $("picture-img").alt = img.alt;
  $("picture").showModal();
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
  const openRecal = () => {
    recalSay("");
    $("recal-capture").disabled = false;
    $("recal").showModal();
  };
  $("recal-open").addEventListener("click", openRecal);
  $("alarm-recal").addEventListener("click", openRecal);
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
  for (const img of document.querySelectorAll("img.zoom")) img.addEventListener("click", () => openPicture(img));
  $("picture").addEventListener("click", () => $("picture").close());
  $("recipe-select").addEventListener("change", () => {
    $("recipe-select").dataset.dirty = "1";
    if (state) renderButtons(state);
  });
  setInterval(() => {  // recipes added or removed from elsewhere (OPC UA)
    if (recipesLoaded && document.activeElement !== $("recipe-select") && !$("recipe-select").dataset.dirty) {
      loadRecipes().catch(() => {});
    }
  }, RECIPES_REFRESH_MS);
  $("recipe-use").addEventListener("click", useRecipe);
  $("check-toggle").addEventListener("click", toggleCheck);
  loadSession().catch(() => { linkDown(); retryLater(); });
});
