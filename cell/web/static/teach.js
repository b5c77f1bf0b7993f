// The Teach page: frames of example parts from the cell's camera, a name and a height, the model
// learnt on the server (the same code as `run-cell part teach`), its outlines and jaws on each frame,
// then Confirm (AddPartType: the type added to a recipe file) or Cancel. Plain JS, no libraries.
"use strict";

const $ = (id) => document.getElementById(id);
let csrf = null;
let canControl = false;
let session = null;  // the server's teaching session (GET /api/teach), or null
let learnt = null;

// What the page did, for the tests.
window.teachStats = { loads: 0, captures: 0, learns: 0, confirmed: null, refusal: null, picturesShown: 0 };

function showMessage(text, bad) {
  const box = $("message");
  box.textContent = text;
  box.classList.toggle("bad", !!bad);
}

class Refused extends Error {
  constructor(data, status) {
    super(data.error || `HTTP ${status}`);
    this.data = data;
  }
}

async function call(url, body) {
  const options = body === undefined ? { credentials: "same-origin" } : {
    method: "POST",
    credentials: "same-origin",
    headers: { "X-CSRF-Token": csrf || "", "Content-Type": "application/json" },
    body: JSON.stringify(body),
  };
  const reply = await fetch(url, options);
  let data = {};
  try { data = await reply.json(); } catch (e) { data = { error: `HTTP ${reply.status}` }; }
  if (!reply.ok) throw new Refused(data, reply.status);
  return data;
}

function refusedWords(e) {
  const d = e.data || {};
  return [d.say || e.message, d.do || ""].filter(Boolean).join(" ");
}

function render() {
  const frames = session && session.session ? session.frames : 0;
  const whose = frames && session.owner ? ` (${session.owner}'s session: only they confirm it)` : "";
  $("teach-frames").textContent = frames ? `${frames} frame(s) held${whose}.` : "No frames yet.";
  $("teach-take").disabled = !canControl;
  $("teach-learn").disabled = !canControl || !frames;
  $("teach-cancel").disabled = !canControl || !frames;
  $("teach-ok").disabled = !canControl || !(learnt && learnt.ok);
  $("teach-login").hidden = canControl;
}

function renderLearnt(l) {
  learnt = l;
  $("teach-result").hidden = !l;
  if (!l) { render(); return; }
  $("teach-say").textContent = l.ok ? `Learnt "${l.name}": Confirm to add it to the recipe, or Cancel.` : `Refused: ${l.refusal}`;
  $("teach-say").classList.toggle("bad", !l.ok);
  $("teach-do").textContent = l.ok ? "" : (l.hint || "");
  $("teach-figures").hidden = !l.ok;
  if (l.ok) {
    const c = l.consistency;
    $("fig-examples").textContent = `${l.examples_count} from ${l.pictures.length} frame(s); area ${l.area_mm2} mm², ${l.holes} hole(s)`;
    $("fig-consistency").textContent = `worst misfit ${c.worst_misfit_mm2.toFixed(2)} mm² (limit ${l.tolerance_mm2.toFixed(2)}), worst overlap ${c.worst_score.toFixed(4)}, area sd ${c.area_sd_mm2.toFixed(2)} mm²`;
    $("fig-symmetry").textContent = l.symmetry_words;
    $("fig-mirror").textContent = l.mirror_distinct ? "another part (told apart)" : "the same part";
    $("fig-grip").textContent = `jaws close along ${l.grip.angle_deg}° (part frame), width ${l.grip.width_mm} mm, opening ${l.grip.opening_mm} mm`;
  }
  $("teach-lines").textContent = (l.lines || []).join("\n");
  const box = $("teach-pictures");
  box.replaceChildren();
  l.pictures.forEach((url, i) => {
    const img = document.createElement("img");
    img.alt = `frame ${i + 1} with each example's outline${l.ok ? " and the jaws" : ""}`;
    img.addEventListener("load", () => { window.teachStats.picturesShown += 1; });
    img.src = `${url}?t=${Date.now()}`;
    box.appendChild(img);
  });
  render();
}

// The bins a new type may share: the recipe's bolt and nut (or the config's) and its taught types with one.
async function loadBins() {
  const recipe = $("teach-recipe").value.trim();
  const select = $("teach-bin-of");
  if (!recipe) return;
  let r;
  try {
    r = await call(`/api/teach/bins?recipe_id=${encodeURIComponent(recipe)}`);
  } catch (e) {
    $("teach-said").textContent = `No bins listed: ${refusedWords(e)}`;
    return;
  }
  const kept = select.value;  // the list is replaced whole, once the answer is in: a choice is never lost
  select.replaceChildren(...r.bins.map((b) => {
    const option = document.createElement("option");
    option.value = b.class;
    option.textContent = `${b.class} (${b.bin_robot_mm.map((v) => v.toFixed(1)).join(", ")})`;
    return option;
  }));
  if (kept && r.bins.some((b) => b.class === kept)) select.value = kept;
}

// What Confirm sends about the bin: none, another class's, or coordinates.
function binChoice() {
  const kind = document.querySelector('input[name="teach-bin-kind"]:checked').value;
  if (kind === "of") return $("teach-bin-of").value ? { bin_of: $("teach-bin-of").value } : null;
  if (kind === "at") {
    const xyz = ["x", "y", "z"].map((a) => $(`teach-bin-${a}`).value.trim());
    if (xyz.some((v) => v === "" || !Number.isFinite(Number(v)))) return null;
    return { bin_robot_mm: xyz.map(Number) };
  }
  return {};
}

async function load() {
  const s = await call("/api/session");
  canControl = s.can_control;
  csrf = s.csrf;
  session = await call("/api/teach");
  if (!$("teach-recipe").value) $("teach-recipe").value = session.active_recipe || "taught-parts";
  await loadBins();
  renderLearnt(session.learnt);
  window.teachStats.loads += 1;
  render();
}

async function capture() {
  $("teach-take").disabled = true;
  showMessage("Capturing…");
  try {
    session = await call("/api/teach/capture", {});
    window.teachStats.captures += 1;
    showMessage(`Frame ${session.frames} captured.`);
    renderLearnt(null);
    if ($("teach-type").value && $("teach-height").value) await learn();
  } catch (e) {
    showMessage(`Refused: ${refusedWords(e)}`, true);
  }
  render();
}

async function learn(event) {
  if (event) event.preventDefault();
  if (!session || !session.session) return;
  const body = { name: $("teach-type").value.trim(), height_mm: Number($("teach-height").value) };
  $("teach-learn").disabled = true;
  showMessage("Teaching…");
  try {
    renderLearnt(await call(`/api/teach/${session.session}/learn`, body));
    showMessage("Learnt: look at the outlines and the jaws, then Confirm or Cancel.");
    window.teachStats.refusal = null;
  } catch (e) {
    const d = e.data || {};
    if (d.pictures) renderLearnt(d); else renderLearnt(null);
    window.teachStats.refusal = d.say || e.message;
    showMessage(`Refused: ${refusedWords(e)}`, true);
  }
  window.teachStats.learns += 1;
  render();
}

async function confirmType() {
  const bin = binChoice();
  if (bin === null) {
    showMessage("Refused: give the bin's X, Y and Z in robot mm, or choose the class whose bin it shares.", true);
    return;
  }
  $("teach-ok").disabled = true;
  try {
    const r = await call(`/api/teach/${session.session}/confirm`, { recipe_id: $("teach-recipe").value.trim(), ...bin });
    window.teachStats.confirmed = r;
    showMessage(`Added "${r.name}" to recipe ${r.recipe_id}.`);
    $("teach-said").textContent = (r.said || []).join(" ");
    $("teach-said").classList.toggle("bad", (r.said || []).some((line) => line.includes("no bin")));
    session = { session: null };
    renderLearnt(null);
    await loadBins();
  } catch (e) {
    showMessage(`Refused: ${refusedWords(e)}`, true);
  }
  render();
}

async function cancel() {
  try {
    await call(`/api/teach/${session.session}/cancel`, {});
    showMessage("Cancelled: the frames are discarded.");
    session = { session: null };
    renderLearnt(null);
  } catch (e) {
    showMessage(`Refused: ${refusedWords(e)}`, true);
  }
  render();
}

document.addEventListener("DOMContentLoaded", () => {
  $("teach-take").addEventListener("click", capture);
  $("teach-form").addEventListener("submit", learn);
  $("teach-ok").addEventListener("click", confirmType);
  $("teach-cancel").addEventListener("click", cancel);
  $("teach-recipe").addEventListener("change", loadBins);
  $("teach-bin-of").addEventListener("change", () => { $("teach-bin-shared").checked = true; });
  for (const a of ["x", "y", "z"]) $(`teach-bin-${a}`).addEventListener("input", () => { $("teach-bin-at").checked = true; });
  load().catch((e) => showMessage(`Cannot load: ${refusedWords(e)}`, true));
});
