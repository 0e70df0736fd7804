// The browser panel: presets, the volume slider, chamber pressures, scenes, vent and faults, live plots and the gland in
// 3D, over the daemon's WebSocket API (host/web.py). Plain modules, no build step.
import { Rpc } from "./rpc.js";
import { Plots } from "./plots.js";
import { Gland } from "./gland.js";

const $ = (id) => document.getElementById(id);

// What each latched fault means, in words (protocol/messages.toml, bits.fault)
const FAULT_WORDS = {
  OVERPRESSURE: "pressure above the board's limit",
  SENSOR: "pressure sensor out of range (cut, unplugged or shorted)",
  DEAD_HOST: "the board heard nothing from the daemon within its deadline and stopped the blowers",
  WATCHDOG_RESET: "the board restarted after its watchdog fired",
  LEAK: "cannot reach or hold its setpoint with the blower at its ceiling (a leak?)",
  IMPLAUSIBLE: "the reading does not follow its blower (a sensor tube off, a stuck sensor, a chamber open)",
  SUPPLY: "the board's supply voltage is too low",
};

// No status for this long (ms; it comes ten times a second) and what the page shows is marked stale: the daemon is
// stopped, frozen or gone, and nothing on the page is live any more.
const STALE_MS = 2000;
// A measured pressure this close to 0 (kPa: one count of the sensor's ADC, its noise) is shown as 0.00.
const NOISE_KPA = 0.05;

const state = {
  access: null, labels: ["base", "left lobe", "right lobe"], chambers: [], plots: null, gland: null,
  status: null, simulated: false, shown: {},
  // the latest outcome the daemon told (reached, faulted, ...), for the target it names: {key, outcome, text}
  outcome: null,
  lastStatusMs: 0, stale: false, inFlight: new Set(),
};

function show(id, text) {
  // write only what changed: status comes ten times a second, and an unchanged text costs a layout for nothing
  const element = $(id);
  if (state.shown[id] === text || !element) return; // (the chambers' cards are built once the daemon named them)
  state.shown[id] = text;
  element.textContent = text;
}

function ml(value) { return value == null ? "–" : `${value.toFixed(1)} ml`; }
function kpa(value) { return value == null ? "–" : `${(Math.abs(value) < NOISE_KPA ? 0 : value).toFixed(2)} kPa`; }

function faultWords(name) {
  const match = /^([A-Z_]+?)(?:_(\d))?$/.exec(name);
  const base = match ? match[1] : name;
  const chamber = match && match[2] != null ? `${state.labels[Number(match[2])] || `chamber ${match[2]}`}: ` : "";
  return `${name} (${chamber}${FAULT_WORDS[base] || "see the board's fault flags"})`;
}

function notice(text, kind = "warn") {
  const box = $("notice");
  box.textContent = panelWords(text);
  box.hidden = !text;
  box.dataset.kind = kind;
  clearTimeout(notice.timer);
  if (text) notice.timer = setTimeout(() => { box.hidden = true; }, 12000);
}

// A request the page sends for a button: what went wrong goes to the notice, in words. While the daemon is not
// answering nothing but a vent is sent (a target or a scene arriving whenever it wakes would surprise); a vent is
// sent, and the notice says that nobody answered it.
async function act(method, params, what) {
  if (state.stale && method !== "vent") {
    const error = new Error("not sent: the daemon is not answering");
    notice(`${what}: ${error.message}`);
    throw error;
  }
  if (state.stale) notice(`${what}: sent, but the daemon is not answering: not known to be done`);
  state.inFlight.add(what);
  try {
    return await state.rpc.call(method, params);
  } catch (error) {
    notice(`${what}: ${error.message}`);
    throw error;
  } finally {
    state.inFlight.delete(what);
  }
}

// --- targets ---------------------------------------------------------------------------------------------------

// A growth ratio's key as a chamber's index: the daemon's status says "1", a preset "chamber1" or "left lobe".
function chamberIndex(key) {
  if (/^\d+$/.test(key)) return Number(key);
  const named = state.chambers.indexOf(key);
  if (named >= 0) return named;
  const labelled = state.labels.indexOf(key);
  if (labelled >= 0) return labelled;
  const numbered = /^chamber(\d+)$/.exec(key);
  return numbered ? Number(numbered[1]) : key;
}

function growthRatio(ratio) {
  return Object.entries(ratio).map(([key, weight]) => [chamberIndex(key), weight])
    .sort(([a], [b]) => (a < b ? -1 : a > b ? 1 : 0));
}

// A target as one string, however it was written (a preset's, the status's): equal strings are the same target.
function targetKey(target) {
  if (!target || typeof target !== "object") return null;
  const number = (value) => (value == null ? null : Number(Number(value).toPrecision(6)));
  if (target.volume_ml != null) {
    return JSON.stringify({ volume_ml: number(target.volume_ml),
      growth: target.growth_ratio ? growthRatio(target.growth_ratio).map(([i, w]) => [i, number(w)]) : null });
  }
  for (const kind of ["pressures_kpa", "chamber_volumes_ml"]) {
    if (target[kind]) return JSON.stringify({ [kind]: target[kind].map(number) });
  }
  return JSON.stringify(target);
}

function describeTarget(target) {
  if (!target) return "none";
  if (typeof target === "string") return target; // a scene's step, described by the daemon
  if (target.volume_ml != null) {
    const ratio = target.growth_ratio ? ` (growth ${growthRatio(target.growth_ratio).map(([i, weight]) =>
      `${typeof i === "number" ? state.labels[i] || `chamber ${i}` : i} ${weight}`).join(", ")})` : "";
    return `${target.volume_ml.toFixed(1)} ml${ratio}`;
  }
  if (target.pressures_kpa) return `${target.pressures_kpa.map((p) => p.toFixed(2)).join(" / ")} kPa`;
  if (target.chamber_volumes_ml) return `chambers ${target.chamber_volumes_ml.map((v) => (v == null ? "-" : v.toFixed(1))).join(" / ")} ml`;
  return JSON.stringify(target);
}

function setTargetState(text, kind) {
  const element = $("target-state");
  if (state.shown["target-state"] === text && element.className === `state ${kind}`) return;
  state.shown["target-state"] = text;
  element.textContent = text;
  element.className = `state ${kind}`;
}

// The line under the target: this page's request while it is answered, and a refused one's why until the next
// request. The target line itself is always the target the daemon holds (a refused request leaves it as it was).
function showRequest(text, kind = "working") {
  $("request-state").hidden = !text;
  show("request-state", panelWords(text || ""));
  $("request-state").className = `request ${kind}`;
}

function refuse(what, why) {
  notice(`${what}: ${why}`);
  showRequest(`${what}: not applied: ${why}`, "failed");
}

async function setTarget(target, name) {
  const what = `set ${name || describeTarget(target)}`;
  const params = { ...target };
  const verify = $("verify-box").hidden ? "" : $("verify-mode").value;
  if (verify && target.volume_ml == null) {
    refuse(what, `verify (${verify}) checks a gland volume by the scanner: set "Verify a volume by the scanner" `
      + "to no for chamber pressures");
    return;
  }
  if (verify) params.verify = verify;
  showRequest(`${what}: solving…`);
  try {
    const answer = await act("set_target", params, what);
    showRequest(null);
    // the same target asked again is judged again: its earlier outcome no longer stands
    if (answer && state.outcome && state.outcome.key === targetKey(answer.target)) state.outcome = null;
    renderTarget();
    return answer;
  } catch (error) {
    showRequest(`${what}: not applied: ${error.message}`, "failed");
  }
}

// A number typed in a field, or a notice naming the field and undefined.
function fieldNumber(input, name) {
  const value = input.value.trim();
  const number = Number(value);
  if (input.validity.badInput || value === "" || !Number.isFinite(number)) {
    const why = input.validity.badInput ? "is not a number" : value === "" ? "is empty" : `${value} is not a finite number`;
    return { error: `${name} ${why}: give a number of kPa` };
  }
  return { number };
}

function setPressures() {
  const pressures = [];
  for (const [i, label] of state.labels.entries()) {
    const { number, error } = fieldNumber($(`pressure-${i}`), label);
    if (error) {
      refuse("set pressures", error);
      $(`pressure-${i}`).focus();
      return;
    }
    pressures.push(number);
  }
  setTarget({ pressures_kpa: pressures }, null);
}

// --- what the daemon sends -------------------------------------------------------------------------------------------

// The words and numbers are rewritten at most this often (ms): people read no faster, and each rewrite lays the page
// out again; the plots take every status.
const WORDS_EVERY_MS = 250;

// What the target line says, from the latest status and the outcome the daemon told for its target.
function renderTarget() {
  const status = state.status;
  if (!status || state.stale) return;
  const key = targetKey(status.target);
  const faults = status.faults || [];
  const told = state.outcome && state.outcome.key === key ? state.outcome : null;
  const interrupted = status.target_after_interruption; // {state, after}: the board lost a reached target's setpoints
  if (status.control === "vented") {
    setTargetState("vented", "working");
  } else if (!status.target) {
    setTargetState(status.ready ? "no target" : "starting…", "idle");
  } else if (faults.length) {
    // the board set every chamber to 0 when the fault latched: the target is not held, whatever was reached
    setTargetState(`not held: fault latched (${faults.join(", ")}); find why, then press Clear fault`, "failed");
  } else if (status.target_pending) {
    setTargetState(`waiting: ${panelWords(status.target_pending)}`, "working");
  } else if (status.verify && !told) {
    setTargetState(`verifying, round ${status.verify.round}…`, "working"); // the line below says how far
  } else if (interrupted && interrupted.state === "held_again") {
    // reached before the board lost its setpoints (a fault, a restart, a lost link), and held again since: the
    // daemon's word (its reached rule), told once
    const reached = told && told.outcome === "reached" ? `${told.text}, ` : "";
    setTargetState(`${reached}held again after ${interruptedAfter(interrupted)}`, "reached");
  } else if (interrupted && interrupted.state === "settling") {
    setTargetState(`settling again after ${interruptedAfter(interrupted)}…`, "working");
  } else if (interrupted && interrupted.state === "not_held") {
    setTargetState(`not held since ${interruptedAfter(interrupted)}: its setpoints are being sent again…`, "working");
  } else if (told && told.outcome === "reached") {
    setTargetState(told.text, "reached");
  } else if (told && told.outcome !== "faulted") {
    setTargetState(told.outcome.replaceAll("_", " "), "failed");
  } else {
    setTargetState("reaching…", "working"); // (a target faulted is reached again once the fault is cleared)
  }
}

// What interrupted a reached target (the status's target_after_interruption.after), in words.
const INTERRUPTION_WORDS = { "fault": "the fault", "board restart": "the board restarted",
  "link loss": "the link was lost" };

function interruptedAfter(interrupted) {
  return INTERRUPTION_WORDS[interrupted.after] || interrupted.after;
}

// The daemon's words for the CLI, as the page says them (it has a button for it).
function panelWords(text) {
  return text.replace(/\(?`?phantom clear-fault`?\)?/g, "(the Clear fault button)");
}

// Which preset is the target held: only that one is highlighted (not one pressed and refused, nor one replaced
// by another client's target or a scene's step).
function highlightPreset(status) {
  const key = status.control === "vented" ? null : targetKey(status.target);
  document.querySelectorAll(".preset").forEach((button) => {
    const active = key !== null && button.dataset.key === key;
    if (button.classList.contains("active") !== active) button.classList.toggle("active", active);
  });
}

// Nothing from the daemon for STALE_MS, or the connection lost: nothing shown is live any more. The numbers and
// states go, the page is greyed, and the header says so.
function markStale(why) {
  show("link", why);
  $("link").className = "pill bad";
  if (state.stale) return;
  state.stale = true;
  document.body.dataset.stale = "true";
  show("control", "–");
  $("control").className = "pill";
  for (const id of ["n-target", "n-estimate", "n-true"]) show(id, "–");
  state.labels.forEach((_, i) => { show(`ch${i}-p`, "–"); show(`ch${i}-s`, "not known: the daemon is not answering"); });
  setTargetState("not known: the daemon is not answering", "failed");
  for (const what of state.inFlight) notice(`${what}: no answer yet: the daemon is not answering`);
}

function watchStatus() {
  if (!state.stale && state.lastStatusMs && performance.now() - state.lastStatusMs > STALE_MS) {
    markStale("daemon not answering");
  }
}

function onStatus(status) {
  state.status = status;
  state.lastStatusMs = performance.now();
  state.plots && state.plots.status(status);
  const now = performance.now();
  const faults = status.faults || [];
  let changed = faults.length !== (state.faultCount ?? -1) || status.control !== state.control;
  if (state.stale) {
    state.stale = false;
    delete document.body.dataset.stale;
    changed = true;
  }
  if (!changed && now - (state.wordsMs || 0) < WORDS_EVERY_MS) return; // a fault or a vent is shown at once
  state.wordsMs = now;
  state.faultCount = faults.length;
  state.control = status.control;
  // vented and the chambers emptied: the gland back at rest is drawn once (a vent has no "reached")
  if (status.control === "vented" && status.pressures_kpa && Math.max(...status.pressures_kpa) < 0.05
      && state.glandKpa > 0.1) {
    state.glandKpa = 0;
    refreshGland();
  }
  const link = status.link;
  show("link", `link ${link}`);
  $("link").className = `pill ${link === "online" ? "ok" : link === "connecting" ? "warn" : "bad"}`;
  // the header is always on screen: a latched fault is said there, wherever the page is scrolled
  show("control", faults.length ? `FAULT: ${faults.join(", ")}` : status.ready ? status.control : "starting");
  $("control").className = `pill ${faults.length ? "bad" : status.control === "vented" ? "warn" : "ok"}`;
  show("target-text", status.control === "vented" ? "none (vented)" : describeTarget(status.target));
  renderTarget();
  highlightPreset(status);
  show("n-target", ml(status.target_volume_ml));
  show("n-estimate", ml(status.estimated_volume_ml));
  if (status.plant_volume_ml != null) { $("n-true-box").hidden = false; show("n-true", ml(status.plant_volume_ml)); }
  status.chamber_labels.forEach((label, i) => {
    show(`ch${i}-p`, kpa(status.pressures_kpa ? status.pressures_kpa[i] : null));
    show(`ch${i}-s`, `setpoint ${kpa(status.setpoints_kpa ? status.setpoints_kpa[i] : null)}, drive ${
      status.drive_levels ? Math.round(status.drive_levels[i] * 100) + " %" : "–"}, ${
      status.chamber_states ? status.chamber_states[i] : "–"}`);
  });
  $("faults").hidden = faults.length === 0;
  document.body.dataset.fault = faults.length ? "true" : "false";
  show("fault-text", faults.map(faultWords).join("; "));
  const scene = status.scene;
  const step = scene && scene.steps.length ? scene.steps[scene.steps.length - 1] : null;
  const sceneName = scene ? scene.name.split("/").pop().replace(/\.toml$/, "").replaceAll("_", " ") : "";
  const stepText = step ? `: step ${step.index} (${describeTarget(step.target)})` : "";
  show("scene-state", !scene ? "no scene playing" : scene.stopped ? `${sceneName} stopped (${scene.stopped})${stepText}`
    : scene.finished ? `${sceneName} ended${stepText}`
    : `${sceneName} playing, ${scene.time_s.toFixed(0)} of ${scene.end_s.toFixed(0)} s${stepText}`);
  renderPairs("correction", status.correction && status.correction.in_force
    ? status.correction : { "in force": "none", why: (status.correction && status.correction.error) || "no measured volumes" });
  const scanRun = status.motion && status.motion.scan;
  const verifying = status.verify ? `verifying ${status.verify.text}` : "";
  $("verify-state").hidden = !verifying;
  show("verify-state", verifying);
  const scan = {}; // a verification's rounds are on their own line above
  if (scanRun) scan.scan = `${scanRun.text}, started ${scanRun.started_utc}`;
  for (const axis of (status.motion && status.motion.axes) || []) {
    scan[axis.name] = axis.position_deg != null ? `${axis.position_deg.toFixed(1)}° ${axis.state || ""}` : (axis.state || "not configured");
  }
  if (state.lastScanEvent) scan.latest = state.lastScanEvent;
  renderPairs("scan", scan);
  if (!$("status-raw").closest("details").open) return;
  show("status-raw", JSON.stringify(status, null, 1));
}

// What a reached target's outcome knows of its volume: scanned (measured), within the correction's band from the
// stored measurements (verify auto, no scan), or the model's estimate.
export function describeReached(event) {
  if (event.verified) {
    return `reached and measured: scanned ${event.scanned_volume_ml.toFixed(2)} ml after ${event.rounds.length} `
      + `round${event.rounds.length === 1 ? "" : "s"}`;
  }
  const volume = event.estimated_volume_ml;
  const text = event.scanned_volume_ml != null ? `reached, scanned ${event.scanned_volume_ml.toFixed(2)} ml`
    : `reached${volume != null ? ` (${volume.toFixed(1)} ml)` : ""}`;
  if (event.band_pct == null) return text;
  return `${text}, within ±${event.band_pct.toFixed(2)} % (95 %) from ${event.measurements} stored measurement`
    + `${event.measurements === 1 ? "" : "s"}`;
}

function renderPairs(id, object) {
  const text = JSON.stringify(object);
  if (state.shown[id] === text) return;
  state.shown[id] = text;
  const box = $(id);
  box.replaceChildren();
  for (const [key, value] of Object.entries(object || {})) {
    if (value == null || (typeof value === "object" && !Array.isArray(value) && Object.keys(value).length > 6)) continue;
    const k = document.createElement("span");
    k.className = "k";
    k.textContent = key.replaceAll("_", " ");
    const v = document.createElement("span");
    v.textContent = typeof value === "number" ? (Number.isInteger(value) ? value : value.toFixed(3))
      : typeof value === "object" ? JSON.stringify(value) : String(value);
    box.append(k, v);
  }
}

function onEvent(event) {
  const item = document.createElement("li");
  item.className = event.level;
  item.textContent = `${event.time_s.toFixed(1)} s  ${event.text}`;
  const list = $("events");
  list.prepend(item);
  while (list.children.length > 60) list.lastChild.remove();
  if (/scan|verif/.test(event.kind) || event.rounds) state.lastScanEvent = event.text;
  if (!event.outcome || event.outcome === "replaced") return;
  state.outcome = { key: targetKey(event.target), outcome: event.outcome,
    text: event.outcome === "reached" ? describeReached(event) : event.outcome };
  renderTarget();
  if (event.outcome === "reached" && state.status && state.outcome.key === targetKey(state.status.target)) {
    refreshGland();
  }
}

function onTelemetry(frame) {
  state.plots && state.plots.telemetry(frame);
}

// --- the gland ----------------------------------------------------------------------------------------------------

async function refreshGland() {
  if (!state.gland) return;
  try {
    const surface = await state.rpc.call("surface");
    state.glandKpa = Math.max(...(surface.pressures_kpa || [0]));
    const largest = state.gland.show(surface);
    show("gland-max", `${state.gland.scaleMm.toFixed(1)} mm`);
    show("gland-note", `largest displacement ${largest.toFixed(1)} mm, at ${surface.pressures_kpa ? surface.pressures_kpa.map((p) => (Math.abs(p) < NOISE_KPA ? 0 : p).toFixed(2)).join(" / ") + " kPa" : "rest"}; drag to turn it`);
    $("gland").dataset.drawn = String((Number($("gland").dataset.drawn) || 0) + 1);
  } catch (error) {
    show("gland-note", `the surface could not be drawn: ${error.message}`);
  }
}

// --- building the page --------------------------------------------------------------------------------------------------

function buildControls(answer) {
  const box = $("presets");
  box.replaceChildren();
  for (const preset of answer.presets) {
    const button = document.createElement("button");
    button.className = "preset control";
    button.dataset.name = preset.name;
    button.dataset.key = targetKey(preset.target);
    const name = document.createElement("b");
    name.textContent = preset.name;
    const meaning = document.createElement("span");
    meaning.textContent = preset.meaning;
    button.append(name, meaning);
    button.addEventListener("click", () => setTarget(preset.target, preset.name));
    box.append(button);
  }
  const [low, high] = answer.volume_range_ml;
  const slider = $("volume-slider");
  slider.min = (Math.ceil(low * 2) / 2).toFixed(1);
  slider.max = (Math.floor(high * 2) / 2).toFixed(1);
  show("volume-range", `reachable: ${low.toFixed(1)} ml (at rest) to ${high.toFixed(1)} ml (every chamber at ${answer.pressure_max_kpa} kPa)`);
  $("volume-value").textContent = `${Number(slider.value).toFixed(1)} ml`;
  const inputs = $("pressure-inputs");
  inputs.replaceChildren();
  answer.chamber_labels.forEach((label, i) => {
    const name = document.createElement("label");
    name.htmlFor = `pressure-${i}`;
    name.textContent = `${label} (kPa)`;
    const input = document.createElement("input");
    Object.assign(input, { id: `pressure-${i}`, type: "number", min: 0, max: answer.pressure_max_kpa, step: 0.1, value: 0 });
    input.className = "control";
    inputs.append(name, input);
  });
  const scenes = $("scenes");
  scenes.replaceChildren();
  for (const scene of answer.scenes) {
    const button = document.createElement("button");
    button.className = "scene-play control";
    button.textContent = `▶ ${scene.name.replaceAll("_", " ")}`;
    button.title = scene.description;
    button.addEventListener("click", async () => {
      await act("run_scene", { path: scene.path }, `play ${scene.name}`);
      notice(`playing ${scene.name}`, "ok");
    });
    scenes.append(button);
  }
  const stop = document.createElement("button");
  stop.id = "scene-stop";
  stop.className = "control";
  stop.textContent = "■ Stop (vents)";
  stop.addEventListener("click", () => { showRequest(null); act("vent", {}, "stop the scene"); });
  scenes.append(stop);
}

function buildChambers(labels) {
  const box = $("chambers");
  box.replaceChildren();
  labels.forEach((label, i) => {
    const card = document.createElement("div");
    card.className = "chamber";
    card.innerHTML = `<span class="label"></span><br><b id="ch${i}-p">–</b><p class="hint" id="ch${i}-s"></p>`;
    card.querySelector(".label").textContent = label;
    box.append(card);
  });
}

function applyAccess(access) {
  state.access = access;
  show("access", access === "control" ? "control" : access === "read" ? "read-only" : "–");
  $("access").className = `pill ${access === "control" ? "ok" : "warn"}`;
  document.querySelectorAll("button.control, input.control, select.control, #volume-slider, #volume-set, #pressures-set, #vent, #clear-fault")
    .forEach((element) => { element.disabled = access !== "control"; });
}

async function onOpen() {
  const identity = await state.rpc.call("identify");
  await state.rpc.call("subscribe", { topics: ["status", "events", "telemetry"] });
  const [presets, status] = await Promise.all([state.rpc.call("presets"), state.rpc.call("status")]);
  if (status.pid !== state.pid) state.outcome = null; // another daemon (restarted): what the last one told is gone
  state.pid = status.pid;
  state.labels = status.chamber_labels;
  state.chambers = status.chambers || [];
  state.simulated = status.plant_volume_ml != null || status.simulated_board != null;
  if (!state.plots) {
    state.plots = new Plots(state.labels, state.simulated);
    buildChambers(state.labels);
  }
  buildControls(presets);
  $("verify-box").hidden = !identity.methods.includes("scan");
  applyAccess(identity.access);
  onStatus(status);
  for (const event of status.events) onEvent(event); // oldest first: each goes on top
  if (!state.gland) {
    try {
      state.gland = new Gland($("gland"));
    } catch (error) {
      show("gland-note", `no 3D view in this browser: ${error.message}`);
    }
  }
  if (state.gland) {
    state.gland.setRest(await state.rpc.call("surface", { pressures_kpa: state.labels.map(() => 0) }));
    await refreshGland();
  }
  document.body.dataset.ready = "true";
}

function wire() {
  $("vent").addEventListener("click", () => { showRequest(null); act("vent", {}, "vent").catch(() => {}); });
  $("clear-fault").addEventListener("click", async () => {
    const answer = await act("clear_fault", {}, "clear the fault");
    notice(`cleared ${answer.cleared.join(", ") || "nothing"}${answer.setpoints_restored
      ? "; the target's setpoints are restored" : ""}`, "ok");
  });
  const slider = $("volume-slider");
  slider.addEventListener("input", () => { $("volume-value").textContent = `${Number(slider.value).toFixed(1)} ml`; });
  slider.addEventListener("keydown", (event) => { if (event.key === "Enter") $("volume-set").click(); });
  $("volume-set").addEventListener("click", () => setTarget({ volume_ml: Number(slider.value) }, null));
  $("pressures-set").addEventListener("click", setPressures);
  $("gland-refresh").addEventListener("click", refreshGland);
  document.addEventListener("keydown", (event) => {
    // V vents from anywhere but a field that types text (the slider, a number field: V vents): the one key that
    // must always work
    if ((event.key === "v" || event.key === "V") && !typesText(event.target) && !event.ctrlKey && !event.metaKey
        && !event.altKey) {
      event.preventDefault();
      $("vent").click();
    }
  });
  setInterval(watchStatus, 250);
}

// Whether a key pressed in this element types a character into it (a text field, the token's): V is then a letter.
function typesText(element) {
  if (element.isContentEditable || element.tagName === "TEXTAREA") return true;
  return element.tagName === "INPUT" && !["range", "number", "checkbox", "radio", "button", "submit", "reset",
    "color", "file"].includes(element.type);
}

function askToken(why, link) {
  $("token-why").textContent = why;
  if (!$("token-dialog").open) $("token-dialog").showModal();
  show("link", link);
  $("link").className = "pill bad";
}

// The connection closed: the daemon stopped or restarted, or it no longer takes this page's token (restarted
// with new ones: the WebSocket is refused, 401, which a page cannot read; /access says it).
async function onClose() {
  markStale("daemon not answering (connection lost)");
  try {
    const access = await (await fetch("/access", { cache: "no-store" })).json();
    if (!access.access && access.token_needed) {
      state.rpc.stop();
      askToken("The daemon refused this panel's token: it was restarted with new tokens, or they were replaced. "
        + "Give the new one.", "token refused");
    }
  } catch {
    // the daemon is not there: the connection is tried again
  }
}

async function main() {
  wire();
  applyAccess(null); // nothing to press until the daemon says what this token may do
  const access = await (await fetch("/access", { cache: "no-store" })).json();
  if (!access.access) {
    askToken("This panel needs its token.", "no token");
    return;
  }
  state.rpc = new Rpc({
    onNotify: (topic, data) => {
      if (topic === "telemetry") onTelemetry(data);
      else if (topic === "status") onStatus(data);
      else if (topic === "events") onEvent(data);
    },
    onOpen: () => onOpen().catch((error) => {
      // a daemon still starting answers "starting": ask again on a new connection
      notice(`the daemon did not answer: ${error.message}; trying again`);
      setTimeout(() => state.rpc.socket.close(), 2000);
    }),
    onClose,
  });
  state.rpc.connect();
}

main();
