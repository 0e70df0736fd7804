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

const state = {
  access: null, labels: ["base", "left lobe", "right lobe"], plots: null, gland: null, presets: [],
  status: null, outcome: null, wanted: null, simulated: false, shown: {},
};

function show(id, text) {
  // write only what changed: status comes ten times a second, and an unchanged text costs a layout for nothing
  const element = $(id);
  if (state.shown[id] === text || !element) return; // (the chambers' cards are built once the daemon named them)
  state.shown[id] = text;
  element.textContent = text;
}

function ml(value) { return value == null ? "–" : `${value.toFixed(1)} ml`; }
function kpa(value) { return value == null ? "–" : `${(Math.abs(value) < 0.005 ? 0 : value).toFixed(2)} kPa`; }

function faultWords(name) {
  const match = /^([A-Z_]+?)(?:_(\d))?$/.exec(name);
  const base = match ? match[1] : name;
  const chamber = match && match[2] != null ? `${state.labels[Number(match[2])] || `chamber ${match[2]}`}: ` : "";
  return `${name} (${chamber}${FAULT_WORDS[base] || "see the board's fault flags"})`;
}

function notice(text, kind = "warn") {
  const box = $("notice");
  box.textContent = text;
  box.hidden = !text;
  box.dataset.kind = kind;
  clearTimeout(notice.timer);
  if (text) notice.timer = setTimeout(() => { box.hidden = true; }, 12000);
}

async function act(method, params, what) {
  try {
    return await state.rpc.call(method, params);
  } catch (error) {
    notice(`${what}: ${error.message}`);
    throw error;
  }
}

// --- targets ---------------------------------------------------------------------------------------------------

function describeTarget(target) {
  if (!target) return "none";
  if (typeof target === "string") return target; // a scene's step, described by the daemon
  if (target.volume_ml != null) {
    const ratio = target.growth_ratio ? ` (growth ${Object.entries(target.growth_ratio).map(([k, v]) => `${k} ${v}`).join(", ")})` : "";
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

async function setTarget(target, name) {
  state.outcome = null;
  state.wanted = name || null;
  document.querySelectorAll(".preset").forEach((button) => button.classList.toggle("active", button.dataset.name === name));
  setTargetState("solving…", "working");
  const params = { ...target };
  const verify = $("verify-box").hidden ? "" : $("verify-mode").value;
  if (verify) params.verify = verify; // a target without a volume is refused, and the refusal says why
  try {
    const answer = await act("set_target", params, `set ${name || describeTarget(target)}`);
    if (!state.outcome) setTargetState("reaching…", "working");
    return answer;
  } catch (error) {
    setTargetState(error.code === "unreachable" ? "unreachable" : "refused", "failed");
  }
}

// --- what the daemon sends -------------------------------------------------------------------------------------------

// The words and numbers are rewritten at most this often (ms): people read no faster, and each rewrite lays the page
// out again; the plots take every status.
const WORDS_EVERY_MS = 250;

function onStatus(status) {
  state.status = status;
  state.plots && state.plots.status(status);
  const now = performance.now();
  const changed = (status.faults || []).length !== (state.faultCount ?? -1) || status.control !== state.control;
  if (!changed && now - (state.wordsMs || 0) < WORDS_EVERY_MS) return; // a fault or a vent is shown at once
  state.wordsMs = now;
  state.faultCount = (status.faults || []).length;
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
  show("control", status.ready ? status.control : "starting");
  $("control").className = `pill ${status.control === "vented" ? "warn" : "ok"}`;
  show("target-text", status.control === "vented" ? "none (vented)" : describeTarget(status.target));
  // a new target (this page's, another client's or a scene's step) is being reached until its outcome comes
  const targetKey = JSON.stringify(status.target);
  if (targetKey !== state.targetKey) {
    state.targetKey = targetKey;
    if (status.target && status.control !== "vented" && state.outcomeFor !== targetKey) {
      state.outcome = null;
      setTargetState("reaching…", "working");
    }
  }
  if (status.control === "vented" && state.outcome !== "vented") {
    state.outcome = "vented";
    setTargetState("vented", "working");
    document.querySelectorAll(".preset.active").forEach((button) => button.classList.remove("active"));
  } else if (status.target_pending && !state.outcome) {
    setTargetState(`waiting: ${status.target_pending}`, "working");
  } else if (status.verify && !state.outcome) {
    setTargetState(`verifying, round ${status.verify.round}…`, "working"); // the line below says how far
  }
  show("n-target", ml(status.target_volume_ml));
  show("n-estimate", ml(status.estimated_volume_ml));
  if (status.plant_volume_ml != null) { $("n-true-box").hidden = false; show("n-true", ml(status.plant_volume_ml)); }
  status.chamber_labels.forEach((label, i) => {
    show(`ch${i}-p`, kpa(status.pressures_kpa ? status.pressures_kpa[i] : null));
    show(`ch${i}-s`, `setpoint ${kpa(status.setpoints_kpa ? status.setpoints_kpa[i] : null)}, drive ${
      status.drive_levels ? Math.round(status.drive_levels[i] * 100) + " %" : "–"}, ${
      status.chamber_states ? status.chamber_states[i] : "–"}`);
  });
  const faults = status.faults || [];
  $("faults").hidden = faults.length === 0;
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
  if (state.status && (state.status.control === "vented" || JSON.stringify(event.target) !== state.targetKey)) return;
  state.outcome = event.outcome;
  state.outcomeFor = JSON.stringify(event.target);
  if (event.outcome === "reached") {
    setTargetState(describeReached(event), "reached");
    refreshGland();
  } else if (event.outcome !== "replaced") {
    setTargetState(event.outcome.replaceAll("_", " "), "failed");
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
    show("gland-note", `largest displacement ${largest.toFixed(1)} mm, at ${surface.pressures_kpa ? surface.pressures_kpa.map((p) => (Math.abs(p) < 0.005 ? 0 : p).toFixed(2)).join(" / ") + " kPa" : "rest"}; drag to turn it`);
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
      state.outcome = null;
      await act("run_scene", { path: scene.path }, `play ${scene.name}`);
      notice(`playing ${scene.name}`, "ok");
    });
    scenes.append(button);
  }
  const stop = document.createElement("button");
  stop.id = "scene-stop";
  stop.className = "control";
  stop.textContent = "■ Stop (vents)";
  stop.addEventListener("click", () => act("vent", {}, "stop the scene"));
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
  state.labels = status.chamber_labels;
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
  $("vent").addEventListener("click", () => act("vent", {}, "vent"));
  $("clear-fault").addEventListener("click", async () => {
    const answer = await act("clear_fault", {}, "clear the fault");
    notice(`cleared ${answer.cleared.join(", ") || "nothing"}${answer.setpoints_restored ? "; the target is held again" : ""}`, "ok");
  });
  const slider = $("volume-slider");
  slider.addEventListener("input", () => { $("volume-value").textContent = `${Number(slider.value).toFixed(1)} ml`; });
  slider.addEventListener("keydown", (event) => { if (event.key === "Enter") $("volume-set").click(); });
  $("volume-set").addEventListener("click", () => setTarget({ volume_ml: Number(slider.value) }, null));
  $("pressures-set").addEventListener("click", () => setTarget({
    pressures_kpa: state.labels.map((_, i) => Number($(`pressure-${i}`).value)) }, null));
  $("gland-refresh").addEventListener("click", refreshGland);
  document.addEventListener("keydown", (event) => {
    // V vents from anywhere but a text field: the one key that must always work
    if ((event.key === "v" || event.key === "V") && !/INPUT|TEXTAREA/.test(event.target.tagName) && !event.ctrlKey && !event.metaKey) {
      $("vent").click();
    }
  });
}

async function main() {
  wire();
  applyAccess(null); // nothing to press until the daemon says what this token may do
  const access = await (await fetch("/access", { cache: "no-store" })).json();
  if (!access.access) {
    $("token-dialog").showModal();
    show("link", "no token");
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
    onClose: () => { show("link", "daemon unreachable"); $("link").className = "pill bad"; applyAccess(null); },
  });
  state.rpc.connect();
}

main();
