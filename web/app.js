// Surfel's page: upload a cloud, preview and orbit it, render, simplify, resample it and combine
// it with a second cloud (boolean) through the HTTP/JSON API (docs/http.md), with every job's
// progress from its event stream.
"use strict";

const $ = (id) => document.getElementById(id);
let threeReady = null;  // resolves once the preview is set up (or known to be unavailable)
const state = { cloud: null, cloudB: null, camera: null, controls: null, three: null, scene: null,
                points: null, renderer: null, lastRenderSpec: null };

// ---- errors: every failure is shown in words ------------------------------------------------
function showError(message) {
  const box = $("error");
  box.textContent = message;
  box.hidden = false;
}
function clearError() { $("error").hidden = true; $("error").textContent = ""; }
window.addEventListener("unhandledrejection", (e) => showError(String(e.reason && e.reason.message || e.reason)));
window.addEventListener("error", (e) => showError(e.message));

// The server's google.rpc.Status body {code, message, details} -> an Error with its message.
async function failure(response) {
  let message = `${response.status} ${response.statusText}`;
  try {
    const body = await response.json();
    if (body && body.message) message = body.message;
  } catch (_) { /* not JSON: keep the status line */ }
  return new Error(message);
}

// ---- auth: a server started with --auth-tokens wants "Authorization: Bearer <token>" on every
// API call (docs/security.md). The token lives in sessionStorage (this tab only).
function token() { return sessionStorage.getItem("surfel-token") || ""; }
function authHeaders(extra) {
  const h = { ...(extra || {}) };
  if (token()) h.Authorization = `Bearer ${token()}`;
  return h;
}
// A result URL usable in <img src> / <a href>: the path itself without a token; with one, the
// bytes fetched with the header into an object URL (a link cannot send headers).
async function resultHref(jobId) {
  const path = `/v1/jobs/${jobId}/result`;
  if (!token()) return path;
  const response = await fetch(path, { headers: authHeaders() });
  if (!response.ok) throw await failure(response);
  return URL.createObjectURL(await response.blob());
}
// The event-stream URL: EventSource sends no headers, so with a token the server signs a
// short-lived URL for it (POST /v1/jobs/{id}:eventsUrl).
async function eventsUrl(jobId) {
  if (!token()) return `/v1/jobs/${jobId}/events`;
  return (await api("POST", `/v1/jobs/${jobId}:eventsUrl`)).url;
}
{
  const input = document.getElementById("token");
  if (input) {
    input.value = token();
    input.addEventListener("change", () => {
      sessionStorage.setItem("surfel-token", input.value.trim());
      refreshJobs();
    });
  }
}

async function api(method, path, body) {
  let response;
  try {
    response = await fetch(path, { method, headers: authHeaders(body ? { "Content-Type": "application/json" } : {}),
                                   body: body ? JSON.stringify(body) : undefined });
  } catch (e) {
    throw new Error(`cannot reach the server (${method} ${path}): ${e.message}`);
  }
  if (!response.ok) throw await failure(response);
  return response.json();
}

// ---- upload with progress ------------------------------------------------------------------
function upload(file, bar, status) {
  clearError();
  bar.hidden = false;
  bar.value = 0;
  status.textContent = `uploading ${file.name}…`;
  return new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    xhr.open("POST", `/v1/clouds?filename=${encodeURIComponent(file.name)}`);
    if (token()) xhr.setRequestHeader("Authorization", `Bearer ${token()}`);
    xhr.upload.onprogress = (e) => { if (e.lengthComputable) bar.value = e.loaded / e.total; };
    xhr.onerror = () => reject(new Error(`upload of ${file.name} failed: the connection broke`));
    xhr.onload = () => {
      let body = null;
      try { body = JSON.parse(xhr.responseText); } catch (_) { /* handled below */ }
      if (xhr.status === 200 && body) resolve(body);
      else reject(new Error(body && body.message ? body.message : `upload failed: HTTP ${xhr.status}`));
    };
    xhr.send(file);
  });
}

async function onFile(file) {
  if (!file) return;
  try {
    const [cloud, bytes] = await Promise.all([upload(file, $("upload-progress"), $("upload-status")),
                                              file.arrayBuffer()]);
    state.cloud = cloud;
    $("upload-status").textContent = cloud.deduplicated ? "stored before (same bytes)" : "stored";
    showCloud(cloud);
    await threeReady;
    preview(parseCloud(bytes, file.name), cloud);
    for (const id of ["render", "simplify", "resample"]) $(id).disabled = false;
    $("boolean").disabled = !state.cloudB;
  } catch (e) {
    $("upload-status").textContent = "upload failed";
    showError(e.message);
  }
}

// The boolean's second solid: uploaded the same way, not previewed (the result is).
async function onFileB(file) {
  if (!file) return;
  const bar = document.createElement("progress");
  try {
    state.cloudB = await upload(file, bar, $("upload-b-status"));
    $("upload-b-status").textContent =
      `B: ${file.name}, ${Number(state.cloudB.points).toLocaleString()} points`;
    $("boolean").disabled = !state.cloud;
  } catch (e) {
    state.cloudB = null;
    $("upload-b-status").textContent = "upload of B failed";
    $("boolean").disabled = true;
    showError(e.message);
  }
}

function fmt(v) { return v ? `(${[v.x || 0, v.y || 0, v.z || 0].map((c) => c.toPrecision(4)).join(", ")})` : "?"; }
function showCloud(c) {
  $("cloud").hidden = false;
  $("cloud-id").textContent = c.id;
  $("cloud-points").textContent = Number(c.points).toLocaleString();
  $("cloud-bounds").textContent = `${fmt(c.boundsMin)} – ${fmt(c.boundsMax)}`;
  $("cloud-attributes").textContent = (c.attributes || []).join(", ") || "none";
  $("cloud-format").textContent = `${c.format}, ${Number(c.sizeBytes).toLocaleString()} bytes`;
}

// ---- a small reader of PLY (ascii, binary) and XYZ positions, for the preview ---------------
function parseCloud(buffer, name) {
  const bytes = new Uint8Array(buffer);
  const head = new TextDecoder().decode(bytes.subarray(0, Math.min(bytes.length, 4096)));
  if (head.startsWith("ply")) return parsePly(buffer, bytes);
  if (/\.(xyz|txt|pts)$/i.test(name) || /^[\s\d.eE+-]+$/.test(head.split("\n")[0])) return parseXyz(buffer);
  throw new Error(`${name}: not a PLY or XYZ file`);
}

function parseXyz(buffer) {
  const lines = new TextDecoder().decode(buffer).split("\n");
  const out = [];
  for (const line of lines) {
    const f = line.trim().split(/\s+/);
    if (f.length >= 3 && !line.trim().startsWith("#")) out.push(+f[0], +f[1], +f[2]);
  }
  return { positions: new Float32Array(out), colors: null };
}

// A boolean's result: the `source` vertex property (0 = A, 1 = B, 2 = the intersection curve).
const SOURCE_COLORS = [[0.78, 0.82, 0.85], [0.95, 0.62, 0.25], [0.95, 0.2, 0.2]];

const PLY_TYPES = { char: [1, "getInt8"], int8: [1, "getInt8"], uchar: [1, "getUint8"], uint8: [1, "getUint8"],
  short: [2, "getInt16"], int16: [2, "getInt16"], ushort: [2, "getUint16"], uint16: [2, "getUint16"],
  int: [4, "getInt32"], int32: [4, "getInt32"], uint: [4, "getUint32"], uint32: [4, "getUint32"],
  float: [4, "getFloat32"], float32: [4, "getFloat32"], double: [8, "getFloat64"], float64: [8, "getFloat64"] };

function parsePly(buffer, bytes) {
  const end = new TextDecoder().decode(bytes.subarray(0, Math.min(bytes.length, 65536))).indexOf("end_header");
  if (end < 0) throw new Error("PLY: no end_header");
  let bodyStart = end + "end_header".length;
  while (bytes[bodyStart] === 13 || bytes[bodyStart] === 10) { bodyStart++; if (bytes[bodyStart - 1] === 10) break; }
  const header = new TextDecoder().decode(bytes.subarray(0, end)).split(/\r?\n/);
  let format = "ascii", count = 0, inVertex = false, beforeVertex = true;
  const props = [];
  for (const line of header) {
    const f = line.trim().split(/\s+/);
    if (f[0] === "format") format = f[1];
    if (f[0] === "element") {
      if (inVertex) beforeVertex = false;
      inVertex = f[1] === "vertex";
      if (inVertex) { count = +f[2]; if (!beforeVertex) throw new Error("PLY: vertex is not the first element"); }
      else if (beforeVertex && +f[2] > 0) throw new Error("PLY: the preview reads files whose first element is vertex");
    }
    if (f[0] === "property" && inVertex) {
      if (f[1] === "list") throw new Error("PLY: list property in vertex");
      props.push({ type: f[1], name: f[2] });
    }
  }
  const idx = (n) => props.findIndex((p) => p.name === n);
  const [ix, iy, iz, ir, ig, ib, isrc] = ["x", "y", "z", "red", "green", "blue", "source"].map(idx);
  if (ix < 0 || iy < 0 || iz < 0) throw new Error("PLY: no x, y, z");
  const positions = new Float32Array(count * 3);
  const rgb = ir >= 0 && ig >= 0 && ib >= 0;
  const colors = rgb || isrc >= 0 ? new Float32Array(count * 3) : null;
  const values = new Array(props.length);
  if (format === "ascii") {
    const text = new TextDecoder().decode(bytes.subarray(bodyStart));
    const tokens = text.split(/\s+/).filter((t) => t.length);
    for (let i = 0, t = 0; i < count; i++) {
      for (let p = 0; p < props.length; p++) values[p] = +tokens[t++];
      store(i, values);
    }
  } else {
    const little = format === "binary_little_endian";
    const view = new DataView(buffer);
    let o = bodyStart;
    for (let i = 0; i < count; i++) {
      for (let p = 0; p < props.length; p++) {
        const [size, getter] = PLY_TYPES[props[p].type] || [];
        if (!size) throw new Error(`PLY: unknown type ${props[p].type}`);
        values[p] = size === 1 ? view[getter](o) : view[getter](o, little);
        o += size;
      }
      store(i, values);
    }
  }
  function store(i, v) {
    positions[3 * i] = v[ix]; positions[3 * i + 1] = v[iy]; positions[3 * i + 2] = v[iz];
    if (rgb) { colors[3 * i] = v[ir] / 255; colors[3 * i + 1] = v[ig] / 255; colors[3 * i + 2] = v[ib] / 255; }
    else if (colors) colors.set(SOURCE_COLORS[v[isrc]] || SOURCE_COLORS[0], 3 * i);
  }
  return { positions, colors };
}

// ---- the 3D preview (Debian's libjs-three, served at /three/) -------------------------------
async function initThree() {
  try {
    const THREE = await import("/three/build/three.module.js");
    const { OrbitControls } = await import("/three/examples/jsm/controls/OrbitControls.js");
    state.three = THREE;
    const host = $("preview");
    state.scene = new THREE.Scene();
    state.scene.background = new THREE.Color(0x1b1f24);
    state.camera = new THREE.PerspectiveCamera(40, host.clientWidth / host.clientHeight, 0.001, 1000);
    state.camera.position.set(0, 0, 3);
    state.controls = new OrbitControls(state.camera, host);
    try {
      state.renderer = new THREE.WebGLRenderer({ antialias: true });
      state.renderer.setSize(host.clientWidth, host.clientHeight);
      host.appendChild(state.renderer.domElement);
    } catch (e) {
      $("preview-status").textContent = `no 3D preview (WebGL unavailable: ${e.message}); ` +
        "drag still orbits the render camera";
      state.renderer = null;
    }
    state.controls.addEventListener("change", draw);
    new ResizeObserver(() => {
      state.camera.aspect = host.clientWidth / host.clientHeight;
      state.camera.updateProjectionMatrix();
      if (state.renderer) state.renderer.setSize(host.clientWidth, host.clientHeight);
      draw();
    }).observe(host);
  } catch (e) {
    $("preview-status").textContent = `no 3D preview: three.js did not load (${e.message}); install libjs-three`;
  }
}

function draw() { if (state.renderer) state.renderer.render(state.scene, state.camera); }

function preview(parsed, cloud) {
  if (!state.three) return;
  const THREE = state.three;
  if (state.points) { state.scene.remove(state.points); state.points.geometry.dispose(); }
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(parsed.positions, 3));
  if (parsed.colors) geometry.setAttribute("color", new THREE.BufferAttribute(parsed.colors, 3));
  const min = cloud.boundsMin || {}, max = cloud.boundsMax || {};
  const lo = new THREE.Vector3(min.x || 0, min.y || 0, min.z || 0), hi = new THREE.Vector3(max.x || 0, max.y || 0, max.z || 0);
  const center = lo.clone().add(hi).multiplyScalar(0.5);
  const radius = Math.max(hi.clone().sub(lo).length() / 2, 1e-6);
  const material = new THREE.PointsMaterial({ size: radius / 150, vertexColors: !!parsed.colors,
                                              color: parsed.colors ? 0xffffff : 0xc8d0d8 });
  state.points = new THREE.Points(geometry, material);
  state.scene.add(state.points);
  const keepCamera = state.framedCloud === cloud.id;
  if (!keepCamera) {
    const distance = radius / Math.sin((40 * Math.PI) / 360) * 1.1;
    state.camera.near = distance / 100;
    state.camera.far = distance * 100;
    state.camera.position.set(center.x, center.y, center.z + distance);
    state.camera.up.set(0, 1, 0);
    state.controls.target.copy(center);
    state.camera.updateProjectionMatrix();
    state.controls.update();
    state.framedCloud = cloud.id;
  }
  $("preview-status").textContent = `${(parsed.positions.length / 3).toLocaleString()} points` +
    (state.renderer ? " — drag to orbit" : "");
  draw();
}

// ---- jobs: submit, follow the event stream, fetch the result --------------------------------
const vec = (v) => ({ x: v.x, y: v.y, z: v.z });

function renderSpec(format) {
  const spec = { cloudId: state.cloud.id, width: +$("width").value, height: +$("height").value,
                 samplesPerPixel: +$("spp").value, format, quality: $("quality").value };
  if (state.camera) {
    const eye = state.camera.position, target = state.controls.target;
    spec.camera = { eye: vec(eye), target: vec(target), up: vec(state.camera.up), fovyDeg: 40 };
    const forward = target.clone().sub(eye).normalize();
    const up = state.camera.up.clone().normalize();
    const right = forward.clone().cross(up).normalize();
    const from = $("light").value;
    const dir = from === "camera" ? forward.clone().add(up.clone().multiplyScalar(-0.3)).add(right.clone().multiplyScalar(0.3))
              : from === "above" ? up.clone().multiplyScalar(-1).add(forward.clone().multiplyScalar(0.3))
              : right.clone().add(forward.clone().multiplyScalar(0.3));
    spec.lights = [{ kind: "DIRECTIONAL", vector: vec(dir.normalize()), intensity: +$("intensity").value || 1 }];
  } else {
    spec.lights = [{ kind: "DIRECTIONAL", vector: { x: 0.3, y: -0.3, z: -1 }, intensity: +$("intensity").value || 1 }];
  }
  return spec;
}

// Follows /v1/jobs/{id}/events until the final event; resolves with the result, rejects with
// the job's failure in words.
function follow(jobId, bar, status) {
  bar.hidden = false;
  bar.value = 0;
  return eventsUrl(jobId).then((url) => new Promise((resolve, reject) => {
    const events = new EventSource(url);
    events.onmessage = (m) => {
      const e = JSON.parse(m.data);
      if (e.state) status.textContent = e.state.state.toLowerCase();
      if (e.queued) status.textContent = `queued (${e.queued.position} ahead)`;
      if (e.running) { bar.value = e.running.fraction || 0; status.textContent = `${e.running.stage || "running"} ${Math.round(100 * (e.running.fraction || 0))} %`; }
      if (e.finished) { events.close(); bar.value = 1; status.textContent = "done"; resolve(e.finished); }
      if (e.failed) { events.close(); status.textContent = "failed"; reject(new Error(e.failed.message || "the job failed")); }
      refreshJobs();
    };
    events.onerror = () => {
      if (events.readyState !== EventSource.CLOSED) {
        status.textContent = "reconnecting…";  // EventSource resumes with Last-Event-ID
        return;
      }
      // Refused: EventSource cannot read the answer, so ask for the job to get the server's words.
      api("GET", `/v1/jobs/${jobId}`).then(
        (job) => reject(new Error(`the event stream of job ${jobId} was refused; the job is ` +
                                  `${job.state.toLowerCase()}${job.statusMessage ? ": " + job.statusMessage : ""}`)),
        (e) => reject(e));
    };
  }));
}

async function submitAndFollow(spec, bar, status) {
  const job = await api("POST", "/v1/jobs", spec);
  refreshJobs();
  await follow(job.id, bar, status);
  return job;
}

$("render-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  clearError();
  $("render").disabled = true;
  try {
    state.lastRenderSpec = renderSpec("PNG");
    const job = await submitAndFollow({ render: state.lastRenderSpec }, $("render-progress"), $("render-status"));
    const img = $("render-img");
    await new Promise((resolve, reject) => {
      img.onload = resolve;
      img.onerror = () => reject(new Error(`the image of job ${job.id} did not load`));
      resultHref(job.id).then((href) => { img.src = href; }, reject);
    });
    $("png-download").href = img.src;
    $("png-download").download = `render-${job.id.slice(0, 12)}.png`;
    $("result").hidden = false;
  } catch (e) {
    showError(e.message);
  } finally {
    $("render").disabled = false;
  }
});

$("exr-download").addEventListener("click", async (ev) => {
  ev.preventDefault();
  if (!state.lastRenderSpec) return;
  clearError();
  try {
    const spec = { ...state.lastRenderSpec, format: "EXR" };
    const bar = document.createElement("progress");
    const job = await submitAndFollow({ render: spec }, bar, $("exr-status"));
    const a = document.createElement("a");
    a.href = await resultHref(job.id);
    a.download = `render-${job.id.slice(0, 12)}.exr`;
    document.body.appendChild(a);
    a.click();
    a.remove();
  } catch (e) {
    showError(e.message);
  }
});

// A job whose result is a cloud (simplify, resample, boolean): submit, follow, fetch the PLY,
// show it in place of the preview with its point count, offer it for download.
async function cloudJob(kind, spec) {
  clearError();
  $(kind).disabled = true;
  const status = $(`${kind}-status`);
  status.textContent = "submitting…";
  $(`${kind}-download`).hidden = true;
  try {
    const job = await api("POST", "/v1/jobs", { [kind]: spec });
    refreshJobs();
    const result = await follow(job.id, $(`${kind}-progress`), status);
    const url = `/v1/jobs/${job.id}/result`;
    const response = await fetch(url, { headers: authHeaders() });
    if (!response.ok) throw await failure(response);
    const parsed = parseCloud(await response.arrayBuffer(), `${kind}.ply`);
    preview(parsed, state.cloud);
    const n = parsed.positions.length / 3;
    status.textContent = `done: ${n.toLocaleString()} points` + reportSummary(kind, result);
    const a = $(`${kind}-download`);
    a.href = await resultHref(job.id);
    a.download = `${kind}-${job.id.slice(0, 12)}.ply`;
    a.hidden = false;
  } catch (e) {
    status.textContent = "failed";
    showError(e.message);
  } finally {
    $(kind).disabled = kind === "boolean" ? !(state.cloud && state.cloudB) : !state.cloud;
  }
}

// A few numbers of the job's report (the JSON `surfel <job> --json` prints).
function reportSummary(kind, result) {
  let r = null;
  try { r = result && result.reportJson ? JSON.parse(result.reportJson) : null; } catch (_) { return ""; }
  if (!r) return "";
  if (kind === "boolean")
    return ` (${r.kept_a} from A, ${r.kept_b} from B, ${r.curve_samples} on the intersection curve)`;
  if (kind === "resample" && r.spacing_mean)
    return ` (spacing ${r.spacing_mean.toPrecision(3)}, cv ${(r.spacing_cv || 0).toFixed(2)})`;
  return "";
}

// Particle simulation places its own points: a member representative is off for it.
$("method").addEventListener("change", () => {
  $("representative").disabled = $("method").value === "PARTICLE";
});

$("simplify-form").addEventListener("submit", (ev) => {
  ev.preventDefault();
  const spec = { cloudId: state.cloud.id, method: $("method").value, target: String(+$("target").value) };
  if (!$("representative").disabled) spec.representative = $("representative").value;
  cloudJob("simplify", spec);
});

// mls keeps the input's points (it takes neither a count nor a spacing): the fields are off for it.
$("resample-method").addEventListener("change", () => {
  const mls = $("resample-method").value === "MLS";
  $("resample-target").disabled = mls;
  $("resample-spacing").disabled = mls;
});

$("resample-form").addEventListener("submit", (ev) => {
  ev.preventDefault();
  const spec = { cloudId: state.cloud.id, method: $("resample-method").value, adaptive: $("resample-adaptive").checked };
  const target = +$("resample-target").value, spacing = +$("resample-spacing").value;
  if (target > 0 && !$("resample-target").disabled) spec.target = String(target);  // uint64: a string in proto3 JSON
  if (spacing > 0 && !$("resample-spacing").disabled) spec.spacing = spacing;
  cloudJob("resample", spec);  // the server says which combination is wrong, in words
});

// Rotation about a coordinate axis by deg degrees, row-major (Similarity.rotation).
function axisRotation(axis, deg) {
  const t = (deg * Math.PI) / 180, c = Math.cos(t), s = Math.sin(t);
  if (axis === "x") return [1, 0, 0, 0, c, -s, 0, s, c];
  if (axis === "y") return [c, 0, s, 0, 1, 0, -s, 0, c];
  return [c, -s, 0, s, c, 0, 0, 0, 1];
}

$("boolean-form").addEventListener("submit", (ev) => {
  ev.preventDefault();
  if (!state.cloudB) { showError("boolean: choose the second solid (B) first"); return; }
  const transformB = { translation: { x: +$("b-tx").value || 0, y: +$("b-ty").value || 0, z: +$("b-tz").value || 0 },
                       scale: $("b-scale").value === "" ? 1 : +$("b-scale").value };
  const deg = +$("b-deg").value || 0;
  if (deg !== 0) transformB.rotation = axisRotation($("b-axis").value, deg);
  cloudJob("boolean", { cloudIdA: state.cloud.id, cloudIdB: state.cloudB.id, op: $("boolean-op").value, transformB });
});

// ---- the job list ---------------------------------------------------------------------------
let refreshing = false;
async function refreshJobs() {
  if (refreshing) return;
  refreshing = true;
  try {
    const { jobs = [] } = await api("GET", "/v1/jobs?limit=20");
    const body = $("jobs").querySelector("tbody");
    body.replaceChildren(...jobs.map((j) => {
      const tr = document.createElement("tr");
      tr.dataset.jobId = j.id;
      const cells = [j.id.slice(0, 12), j.type, j.state.toLowerCase() + (j.statusMessage ? `: ${j.statusMessage}` : ""),
                     j.state === "RUNNING" ? `${Math.round(100 * (j.fraction || 0))} % ${j.stage || ""}` : ""];
      for (const c of cells) { const td = document.createElement("td"); td.textContent = c; tr.appendChild(td); }
      const td = document.createElement("td");
      if (j.state === "QUEUED" || j.state === "RUNNING") {
        const b = document.createElement("button");
        b.textContent = "cancel";
        b.className = "cancel";
        b.onclick = async () => {
          try { await api("POST", `/v1/jobs/${j.id}:cancel`); } catch (e) { showError(e.message); }
          refreshJobs();
        };
        td.appendChild(b);
      }
      tr.appendChild(td);
      return tr;
    }));
  } catch (e) {
    showError(`job list: ${e.message}`);
  } finally {
    refreshing = false;
  }
}

// ---- wiring ---------------------------------------------------------------------------------
$("file").addEventListener("change", (e) => onFile(e.target.files[0]));
$("file-b").addEventListener("change", (e) => onFileB(e.target.files[0]));
const drop = $("drop");
drop.addEventListener("dragover", (e) => { e.preventDefault(); drop.classList.add("over"); });
drop.addEventListener("dragleave", () => drop.classList.remove("over"));
drop.addEventListener("drop", (e) => { e.preventDefault(); drop.classList.remove("over"); onFile(e.dataTransfer.files[0]); });
threeReady = initThree();
refreshJobs();
setInterval(refreshJobs, 2000);
