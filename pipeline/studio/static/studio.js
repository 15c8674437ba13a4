// The studio's page: one script for both modes (a scene's fit, a capture), talking to
// pipeline/studio/server.py's JSON routes; it polls the running fit or run twice a second.
"use strict";
const $ = id => document.getElementById(id);
let session = null;
// This start's token (server.py serves it with the page): sent with every request, and
// needed by every POST, which no other site's page can send with it.
const TOKEN = document.querySelector('meta[name="studio-token"]')?.content ?? "";

async function api(path, body) {
  const headers = { "X-Studio-Token": TOKEN };
  const init = body === undefined ? { headers } : { method: "POST", headers: { ...headers, "Content-Type": "application/json" }, body: JSON.stringify(body) };
  const response = await fetch(path, init);
  const data = response.status === 204 ? null : await response.json();
  if (!response.ok) throw new Error(data && data.error ? data.error : `${response.status} ${response.statusText}`);
  return data;
}
// One request of a poll at a time: under load a poll can outlast the interval, and two
// in flight would both append the lines after the same position.
function singleFlight(poll) {
  let busy = null;
  return () => busy ?? (busy = poll().finally(() => { busy = null; }));
}
function showError(message) { $("error").hidden = !message; $("error").textContent = message || ""; }
function cell(row, content) { const td = row.insertCell(); if (content instanceof Node) td.appendChild(content); else td.textContent = content ?? ""; return td; }
function fmt(v) { return Array.isArray(v) ? v.map(x => Number(x).toPrecision(4)).join(", ") : (v ?? ""); }

// ---- a scene's fit ----
let log = [], since = 0, previewVersion = -1, fitStatus = "idle";

function buildParams(parameters) {
  const body = $("params").tBodies[0];
  for (const p of parameters) {
    const row = body.insertRow(); row.dataset.key = p.key;
    if (!p.fittable) { row.className = "disabled"; row.title = p.why_not; }
    const tick = document.createElement("input"); tick.type = "checkbox"; tick.disabled = !p.fittable; tick.className = "tick";
    cell(row, tick); cell(row, p.key); cell(row, p.type); cell(row, fmt(p.value));
    for (const side of [0, 1]) {
      const input = document.createElement("input"); input.type = "number"; input.step = "any";
      input.className = side ? "upper" : "lower"; input.disabled = !p.fittable;
      if (p.bounds) input.value = p.bounds[side];
      cell(row, input);
    }
  }
}
function buildViews(names) {
  const body = $("views").tBodies[0];
  for (const name of names) {
    const row = body.insertRow(); row.dataset.view = name;
    const tick = document.createElement("input"); tick.type = "checkbox"; tick.className = "heldout";
    cell(row, name); cell(row, tick);
    $("preview-view").add(new Option(name, name));
  }
}
function buildSettings(schema) {
  const form = $("settings");
  for (const s of schema) {
    const label = document.createElement("label"); label.title = `${s.doc} (${s.type})`;
    label.append(s.name);
    let input;
    if (s.kind === "bool") { input = document.createElement("input"); input.type = "checkbox"; input.checked = !!s.default; }
    else if (s.kind === "choice") { input = document.createElement("select"); s.choices.forEach(c => input.add(new Option(c, c))); input.value = s.default; }
    else {
      input = document.createElement("input"); input.type = "number"; input.step = s.kind === "int" ? "1" : "any";
      if (s.lo !== null) input.min = s.lo; if (s.hi !== null) input.max = s.hi;
      input.value = s.default ?? ""; input.placeholder = s.default === null ? "default" : "";
    }
    input.name = s.name; input.dataset.kind = s.kind; label.appendChild(input); form.appendChild(label);
  }
}
function formValues() {
  const settings = {};
  for (const input of $("settings").elements) {
    if (input.dataset.kind === "bool") settings[input.name] = input.checked;
    else if (input.dataset.kind === "choice") settings[input.name] = input.value;
    else if (input.value !== "") settings[input.name] = input.dataset.kind === "int" ? parseInt(input.value, 10) : parseFloat(input.value);
  }
  const params = [], bounds = {};
  for (const row of $("params").tBodies[0].rows) {
    if (!row.querySelector(".tick").checked) continue;
    params.push(row.dataset.key);
    const lo = row.querySelector(".lower").value, hi = row.querySelector(".upper").value;
    if (lo !== "" && hi !== "") bounds[row.dataset.key] = [parseFloat(lo), parseFloat(hi)];
  }
  const heldout = [...$("views").tBodies[0].rows].filter(r => r.querySelector(".heldout").checked).map(r => r.dataset.view);
  return { params, bounds, settings, heldout };
}
async function filterParams() {
  try {
    const { keys } = await api(`/api/fit/match?words=${encodeURIComponent($("filter").value)}`);
    const shown = new Set(keys);
    for (const row of $("params").tBodies[0].rows) row.hidden = !shown.has(row.dataset.key);
    showError("");
  } catch (e) { showError(e.message); }
}
const pollFit = singleFlight(async () => {
  try {
    const state = await api(`/api/fit/state?since=${since}`);
    log = log.concat(state.log); since = log.length; fitStatus = state.status;
    $("status").textContent = state.status + (state.levels.length > 1 ? ` (level ${state.level + 1} of ${state.levels.length})` : "");
    $("start").disabled = ["running", "paused", "stopping"].includes(state.status);
    $("pause").disabled = !["running", "paused"].includes(state.status);
    $("pause").textContent = state.status === "paused" ? "Resume" : "Pause";
    $("stop").disabled = !["running", "paused"].includes(state.status);
    plotLines($("loss-plot"), lossSeries(log), { log: true, xlabel: "step" });
    plotTrajectories($("trajectories"), log);
    if (state.preview_version !== previewVersion) {
      previewVersion = state.preview_version;
      $("preview-images").hidden = previewVersion === 0;
      for (const kind of ["render", "reference", "difference"]) $(`preview-${kind}`).src = `/api/fit/preview/${kind}?v=${previewVersion}`;
      $("preview-images").dataset.view = state.preview_of ?? "";
    }
    $("stopped").textContent = state.stopped ? `Stopped: ${state.stopped}` : "";
    if (state.error) showError(state.error);
    const downloads = $("downloads"); downloads.replaceChildren();
    for (const name of state.outputs) {
      const a = document.createElement("a"); a.href = `/api/fit/download/${encodeURIComponent(name)}`; a.textContent = name; a.download = name;
      const li = document.createElement("li"); li.appendChild(a); downloads.appendChild(li);
    }
  } catch (e) { showError(e.message); }
});
function setupFit(info) {
  $("fit").hidden = false;
  $("target").textContent = `${info.scene} (references ${info.references}, results into ${info.out})`;
  buildParams(info.parameters); buildViews(info.views); buildSettings(info.settings);
  $("filter").addEventListener("input", filterParams);
  $("start").addEventListener("click", async () => {
    try { showError(""); log = []; since = 0; $("trajectories").replaceChildren(); await api("/api/fit/start", formValues()); await pollFit(); }
    catch (e) { showError(e.message); }
  });
  $("pause").addEventListener("click", () => api(`/api/fit/${fitStatus === "paused" ? "resume" : "pause"}`, {}).catch(e => showError(e.message)));
  $("stop").addEventListener("click", () => api("/api/fit/stop", {}).catch(e => showError(e.message)));
  $("preview-view").addEventListener("change", e => api("/api/fit/view", { name: e.target.value }).catch(err => showError(err.message)));
  pollFit(); setInterval(pollFit, 500);
}

// ---- a capture ----
let runLine = 0, viewer = null, wasRunning = false, stagePreviewAt = 0, stagePreviewKey = "";

function overrides() { return $("overrides").value.split("\n").map(s => s.trim()).filter(Boolean); }
async function refreshStages() {
  try {
    const query = new URLSearchParams({ preset: $("preset").value }); overrides().forEach(s => query.append("set", s));
    const data = await api(`/api/capture/stages?${query}`);
    const body = $("stages").tBodies[0]; body.replaceChildren();
    for (const s of data.stages) {
      const row = body.insertRow(); row.dataset.stage = s.stage;
      cell(row, s.stage); cell(row, s.state).className = "state"; cell(row, s.reason); cell(row, s.finished);
      cell(row, s.seconds === null ? "-" : s.seconds.toFixed(1)); cell(row, s.entries); cell(row, `${(s.bytes / 1e6).toFixed(1)} MB`);
    }
    $("lock").textContent = data.locked_by ? `In use by ${data.locked_by}` : "";
    body.dataset.loaded = "1"; showError("");
  } catch (e) { showError(e.message); }
}
const pollRun = singleFlight(async () => {
  try {
    const state = await api(`/api/capture/run?since=${runLine}`);
    runLine = state.next;
    if (state.log.length) { const pre = $("run-log"); pre.textContent += state.log.join("\n") + "\n"; pre.scrollTop = pre.scrollHeight; }
    $("run").disabled = state.running; $("run-stop").disabled = !state.running;
    $("run-status").textContent = state.running ? "running" : state.exit_code === null ? "" : `finished with exit code ${state.exit_code}`;
    $("status").textContent = state.running ? "running" : "idle";
    $("fit-stage-title").textContent = state.fit_stage ? `Fit: ${state.fit_stage}` : "Fit (when a fit stage runs)";
    if (state.fit_stage) {
      plotLines($("stage-loss-plot"), lossSeries(state.fit_log), { log: true, xlabel: "step" });
      plotTrajectories($("stage-trajectories"), state.fit_log);
      refreshStagePreview(state);
    }
    // a stage finished during the run (its table row, and the photos, cameras or mesh it
    // made), or the run ended (the report too)
    if ((state.running && state.log.some(line => / done in [\d.]+ s$/.test(line))) || (wasRunning && !state.running)) refreshAll();
    wasRunning = state.running;
  } catch (e) { showError(e.message); }
});
// The running fit's latest values rendered in one photo's view: every 10 s at most
// (each is a render beside the run), and when another view is picked.
function refreshStagePreview(state) {
  const view = $("stage-view").value;
  if (!view || !state.fit_log.length) return;
  const key = `${view}/${state.fit_stage}/${state.fit_log[state.fit_log.length - 1].iteration}`;
  if (key === stagePreviewKey || (Date.now() - stagePreviewAt < 10000 && stagePreviewKey.startsWith(view + "/"))) return;
  stagePreviewKey = key; stagePreviewAt = Date.now();
  const query = `view=${encodeURIComponent(view)}&v=${encodeURIComponent(key)}`;
  $("stage-render").onload = () => { $("stage-images").hidden = false; for (const kind of ["photo", "difference"]) $(`stage-${kind}`).src = `/api/capture/fit-preview/${kind === "photo" ? "reference" : kind}?${query}`; };
  $("stage-render").src = `/api/capture/fit-preview/render?${query}`;
}
async function loadPhotos() {
  const { photos } = await api("/api/capture/photos");
  const select = $("stage-view"), chosen = select.value; select.replaceChildren();
  photos.forEach(name => select.add(new Option(name, name)));
  if (photos.includes(chosen)) select.value = chosen;
  const box = $("photos"); box.replaceChildren();
  for (const name of photos) {
    const figure = document.createElement("figure"); const img = document.createElement("img");
    img.loading = "lazy"; img.src = `/api/capture/photo/${encodeURIComponent(name)}`; img.alt = name;
    const caption = document.createElement("figcaption"); caption.textContent = name;
    figure.append(img, caption); box.appendChild(figure);
  }
}
async function load3d() {
  const V = window.THREE_VIEWER; const THREE = V.THREE; const canvas = $("view3d");
  if (!viewer) {
    const renderer = new THREE.WebGLRenderer({ canvas, antialias: true });
    const scene = new THREE.Scene(); scene.background = new THREE.Color(0xeeeeee);
    scene.environment = new THREE.PMREMGenerator(renderer).fromScene(new V.RoomEnvironment()).texture;
    const camera = new THREE.PerspectiveCamera(40, canvas.width / canvas.height, 0.001, 1000);
    const controls = new V.OrbitControls(camera, canvas);
    // drawn when something changed, not every frame: an idle page costs nothing
    const draw = () => { renderer.render(scene, camera); canvas.dataset.rendered = "1"; };
    controls.addEventListener("change", draw);
    viewer = { renderer, scene, camera, controls, group: null, draw };
  }
  if (viewer.group) viewer.scene.remove(viewer.group);
  const group = new THREE.Group(); viewer.group = group; viewer.scene.add(group);
  const { cameras } = await api("/api/capture/cameras");
  const lines = [];
  for (const c of cameras) {
    for (const corner of c.corners) lines.push(c.centre, corner);
    for (let i = 0; i < 4; i++) lines.push(c.corners[i], c.corners[(i + 1) % 4]);
  }
  if (lines.length) {
    const geometry = new THREE.BufferGeometry().setFromPoints(lines.map(p => new THREE.Vector3(...p)));
    group.add(new THREE.LineSegments(geometry, new THREE.LineBasicMaterial({ color: 0x1565c0 })));
  }
  const response = await fetch("/api/capture/mesh.glb");
  let note = `${cameras.length} cameras`;
  if (response.status === 200) {
    const gltf = await new V.GLTFLoader().parseAsync(await response.arrayBuffer(), "");
    group.add(gltf.scene); note += ", the current mesh";
  } else note += ", no mesh yet";
  canvas.dataset.cameras = String(cameras.length);
  $("view3d-note").textContent = note;
  const box = new THREE.Box3().setFromObject(group);
  if (!box.isEmpty()) {
    const centre = box.getCenter(new THREE.Vector3()); const size = box.getSize(new THREE.Vector3()).length() || 1;
    viewer.camera.position.copy(centre).add(new THREE.Vector3(0.6, -0.9, 0.6).multiplyScalar(size));
    viewer.camera.up.set(0, 0, 1); viewer.controls.target.copy(centre); viewer.controls.update();
  }
  viewer.draw();
}
async function loadReport() {
  const response = await fetch("/output/report.html");
  $("report").src = response.ok ? "/output/report.html" : "about:blank";
  $("report-link").hidden = !response.ok;
}
async function refreshAll() {
  await refreshStages();
  for (const load of [loadPhotos, load3d, loadReport]) { try { await load(); } catch (e) { showError(e.message); } }
}
function setupCapture(info) {
  $("capture").hidden = false; $("target").textContent = info.capture;
  info.presets.forEach(p => $("preset").add(new Option(p, p))); $("preset").value = info.preset;
  $("overrides").value = info.set.join("\n");
  $("refresh").addEventListener("click", refreshAll);
  $("preset").addEventListener("change", refreshStages);
  $("run").addEventListener("click", async () => {
    try { showError(""); await api("/api/capture/run", { preset: $("preset").value, set: overrides() }); $("run-log").textContent = ""; runLine = 0; await pollRun(); }
    catch (e) { showError(e.message); }
  });
  $("run-stop").addEventListener("click", () => api("/api/capture/stop", {}).catch(e => showError(e.message)));
  refreshAll(); pollRun(); setInterval(pollRun, 500);
}

(async () => {
  try {
    session = await api("/api/session");
    if (session.mode === "fit") setupFit(session);
    else if (session.mode === "capture") setupCapture(session);
    else { $("status").textContent = "error"; showError(session.error); }
  } catch (e) { showError(e.message); }
})();
