// The History page: picks filtered and paged, the alarm list (active, then history, with who
// reset each), failure images opened full size. Read-only: GETs of the screen's JSON routes.
"use strict";

const $ = (id) => document.getElementById(id);
const PAGE = 50;
let picksOffset = 0;
let alarmsOffset = 0;

// What the page did, for the tests.
window.historyStats = { picksLoads: 0, alarmsLoads: 0, lastPicks: null, lastAlarms: null, imagesShown: 0 };

function showMessage(text) {
  const box = $("message");
  box.textContent = text;
  box.classList.add("bad");
  box.hidden = false;
  clearTimeout(showMessage.timer);
  showMessage.timer = setTimeout(() => { box.hidden = true; }, 8000);
}

async function getJson(url) {
  const reply = await fetch(url, { credentials: "same-origin" });
  let data = {};
  try { data = await reply.json(); } catch (e) { data = { error: `HTTP ${reply.status}` }; }
  if (!reply.ok) throw new Error(data.error || `HTTP ${reply.status}`);
  return data;
}

function localTime(iso) {
  return iso ? new Date(iso).toLocaleString([], { hour12: false }) : "";
}

function fixed(values, digits) {
  return values.map((v) => (v === null ? "-" : v.toFixed(digits))).join(", ");
}

function cell(tr, text, className) {
  const td = document.createElement("td");
  td.textContent = text === null || text === undefined ? "" : text;
  if (className) td.className = className;
  tr.appendChild(td);
  return td;
}

function imageButton(tr, imageId, title) {
  const td = document.createElement("td");
  if (imageId) {
    const b = document.createElement("button");
    b.type = "button";
    b.className = "image-open";
    b.textContent = "view";
    b.dataset.image = imageId;
    b.addEventListener("click", () => openImage(imageId, title));
    td.appendChild(b);
  }
  tr.appendChild(td);
}

function openImage(imageId, title) {
  const img = $("image-full");
  img.onload = () => { window.historyStats.imagesShown += 1; };
  img.src = `/api/history/image/${imageId}/annotated.png`;
  $("image-frame-link").href = `/api/history/image/${imageId}/frame.png`;
  $("image-title").textContent = title;
  $("image-view").showModal();
}

// ---- picks ---------------------------------------------------------------------------
function toIso(local) {
  return local ? new Date(local).toISOString() : "";
}

function filterQuery() {
  const q = new URLSearchParams();
  const put = (key, value) => { if (value) q.set(key, value); };
  put("shift", $("f-shift").value.trim());
  put("since", toIso($("f-since").value));
  put("until", toIso($("f-until").value));
  put("job", $("f-job").value.trim());
  put("class", $("f-class").value);
  put("outcome", $("f-outcome").value);
  q.set("limit", PAGE);
  q.set("offset", picksOffset);
  return q.toString();
}

async function loadPicks() {
  let data;
  try { data = await getJson(`/api/history/picks?${filterQuery()}`); } catch (e) { showMessage(e.message); return; }
  window.historyStats.picksLoads += 1;
  window.historyStats.lastPicks = data;
  const rows = data.picks.map((p) => {
    const tr = document.createElement("tr");
    cell(tr, localTime(p.time_utc));
    cell(tr, p.id);
    cell(tr, p.class);
    cell(tr, fixed(p.table_mm, 1));
    cell(tr, fixed(p.robot_mm, 1));
    cell(tr, p.jaw_angle_deg === null ? "" : p.jaw_angle_deg.toFixed(1));
    cell(tr, p.calibration_id);
    cell(tr, p.outcome, `outcome-${p.outcome}`);
    imageButton(tr, p.image_id, `${p.id}: ${p.class} ${p.outcome}`);
    return tr;
  });
  $("history-body").replaceChildren(...rows);
  const last = Math.min(data.offset + data.picks.length, data.total);
  $("picks-status").textContent = data.total ? `${data.total} picks` : "no picks match";
  $("picks-page").textContent = data.total ? `${data.offset + 1}-${last} of ${data.total}` : "-";
  $("picks-prev").disabled = data.offset === 0;
  $("picks-next").disabled = last >= data.total;
}

// ---- alarms --------------------------------------------------------------------------
async function loadAlarms() {
  let data;
  try { data = await getJson(`/api/history/alarms?limit=20&offset=${alarmsOffset}`); } catch (e) { showMessage(e.message); return; }
  window.historyStats.alarmsLoads += 1;
  window.historyStats.lastAlarms = data;
  $("alarms-none").hidden = data.active.length > 0;
  $("alarms-active").hidden = data.active.length === 0;
  $("alarms-active-body").replaceChildren(...data.active.map((a) => {
    const tr = document.createElement("tr");
    tr.className = "active-alarm";
    cell(tr, localTime(a.raised_utc));
    cell(tr, a.severity, `sev-${a.severity}`);
    cell(tr, a.reason);
    cell(tr, a.hint);
    cell(tr, a.source);
    return tr;
  }));
  $("alarms-history-body").replaceChildren(...data.history.map((a) => {
    const tr = document.createElement("tr");
    cell(tr, localTime(a.raised_utc));
    cell(tr, a.cleared_utc ? localTime(a.cleared_utc) : "active");
    cell(tr, a.severity, `sev-${a.severity}`);
    cell(tr, a.hint ? `${a.reason} (${a.hint})` : a.reason);
    cell(tr, a.cleared_interface ? `${a.cleared_user || "anonymous"} via ${a.cleared_interface}` : "");
    imageButton(tr, a.image_id, `alarm ${a.alarm_id}: ${a.reason}`);
    return tr;
  }));
  $("alarms-page").textContent = data.history.length ? `${data.offset + 1}-${data.offset + data.history.length}` : "-";
  $("alarms-newer").disabled = data.offset === 0;
  $("alarms-older").disabled = data.history.length < data.limit;
}

async function loadShift() {
  try {
    const s = await getJson("/api/state");
    $("shift-now").textContent = s.shift || "-";
  } catch (e) { showMessage(e.message); }
}

function init() {
  const params = new URLSearchParams(location.search);
  for (const key of ["shift", "job", "class", "outcome"]) {
    if (params.get(key)) $(`f-${key}`).value = params.get(key);
  }
  $("filters").addEventListener("submit", (e) => { e.preventDefault(); picksOffset = 0; loadPicks(); });
  $("f-clear").addEventListener("click", () => { $("filters").reset(); picksOffset = 0; loadPicks(); });
  $("picks-prev").addEventListener("click", () => { picksOffset = Math.max(0, picksOffset - PAGE); loadPicks(); });
  $("picks-next").addEventListener("click", () => { picksOffset += PAGE; loadPicks(); });
  $("alarms-newer").addEventListener("click", () => { alarmsOffset = Math.max(0, alarmsOffset - 20); loadAlarms(); });
  $("alarms-older").addEventListener("click", () => { alarmsOffset += 20; loadAlarms(); });
  $("image-close").addEventListener("click", () => $("image-view").close());
  loadShift();
  loadPicks();
  loadAlarms();
}

init();
