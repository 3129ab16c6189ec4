// The pbrsr dashboard: upload, job list and job view. The REST API gives the state; the
// key's event stream (/v1/events, Server-Sent Events read with fetch so the API key can go in
// a header) says when to read it again. Polling takes over only while the stream is down.
"use strict";

const $ = (id) => document.getElementById(id);
const POLL_MS = 1000; // only while the event stream is down
const RECONNECT_MS = 2000;
const TERMINAL = new Set(["finished", "failed", "canceled"]);

const state = {
  key: localStorage.getItem("pbrsr-api-key") || "",
  file: null,
  selected: null,
  detail: null,
  blobUrls: new Map(), // url -> object URL (files fetched with the API key)
  shownFiles: "",
  shownCrops: "",
  waitingViewer: false,
};

// ---------------------------------------------------------------------------- API helpers
function headers() {
  return state.key ? { "X-API-Key": state.key } : {};
}

async function api(path, init) {
  const resp = await fetch(path, { ...(init || {}), headers: { ...headers(), ...((init || {}).headers || {}) } });
  if (resp.status === 401) {
    $("auth").hidden = false;
    throw new Error("this server needs an API key: enter it at the top right");
  }
  if (!resp.ok && resp.status !== 202 && resp.status !== 204) {
    let detail = resp.statusText;
    try { detail = (await resp.json()).detail || detail; } catch (_) { /* not JSON */ }
    throw new Error(detail);
  }
  if (resp.status === 204) return null;
  return resp.json();
}

// A job's file fetched with the API key: the file itself, or (s3 storage) a presigned URL
// as JSON, so that the key never follows a redirect to the bucket.
async function keyedFile(path) {
  const resp = await fetch(`${path}?redirect=false`, { headers: headers() });
  if (!resp.ok) throw new Error(`cannot load ${path}`);
  if ((resp.headers.get("content-type") || "").startsWith("application/json")) {
    return { url: (await resp.json()).url, resp: null };
  }
  return { url: URL.createObjectURL(await resp.blob()), resp };
}

// A URL the page loads a job's file from without sending the API key: the API's own path
// when there is no key, else a blob: URL of the bytes or a presigned URL of the bucket.
async function fileUrl(path) {
  if (!state.key) return path;
  if (state.blobUrls.has(path)) return state.blobUrls.get(path);
  const { url, resp } = await keyedFile(path);
  if (resp) state.blobUrls.set(path, url); // a presigned URL expires: asked again next time
  return url;
}

function fmtDuration(s) {
  if (s === null || s === undefined || !isFinite(s)) return "";
  s = Math.round(s);
  if (s < 60) return `${s} s`;
  const m = Math.floor(s / 60), r = s % 60;
  if (m < 60) return `${m} min ${r.toString().padStart(2, "0")} s`;
  return `${Math.floor(m / 60)} h ${(m % 60).toString().padStart(2, "0")} min`;
}

function fmtTime(iso) {
  if (!iso) return "";
  const d = new Date(iso);
  return d.toLocaleString([], { month: "short", day: "numeric", hour: "2-digit", minute: "2-digit", second: "2-digit" });
}

function setBar(bar, fraction, status) {
  bar.classList.toggle("done", status === "finished");
  bar.classList.toggle("failed", status === "failed" || status === "canceled");
  const pct = status === "finished" ? 100 : Math.round(100 * Math.max(0, Math.min(1, fraction || 0)));
  bar.firstElementChild.style.width = pct + "%";
  bar.setAttribute("aria-valuenow", String(pct));
}

// -------------------------------------------------------------------------------- upload
function pickFile(file) {
  state.file = file || null;
  const zone = $("drop-zone");
  zone.classList.toggle("has-file", !!file);
  $("drop-text").textContent = file ? `${file.name} (${(file.size / 1024).toFixed(0)} KB)` : "Drop a .glb, .gltf or .zip here, or click to choose";
  $("submit").disabled = !file;
}

function checkedMaps() {
  const boxes = [...document.querySelectorAll("#opt-maps input[type=checkbox]")];
  const on = boxes.filter((b) => b.checked).map((b) => b.value);
  return on.length === boxes.length ? null : on;  // null: every map, extensions' too
}

function options() {
  const steps = $("opt-iterations").value.trim();  // empty: the preset's
  const maxSize = $("opt-max-size").value.trim();  // empty: every map at the scale
  const maps = checkedMaps();
  return {
    scale: Number($("opt-scale").value),
    ...(maxSize !== "" ? { max_size: Number(maxSize) } : {}),
    ...(maps ? { maps, other_maps: $("opt-other-maps").value } : {}),
    method: $("opt-method").value,
    preset: $("opt-preset").value,
    ...(steps !== "" && $("opt-method").value === "pbrsr" ? { iterations: Number(steps) } : {}),
    image_format: $("opt-format").value,
    lr_kernel: $("opt-lr-kernel").value,
    seed: Math.max(0, Number($("opt-seed").value) || 0),
  };
}

function upload(event) {
  event.preventDefault();
  if (!state.file) return;
  const maps = checkedMaps();
  if (maps && maps.length === 0) {
    $("upload-status").textContent = "Check at least one map to upscale.";
    return;
  }
  const form = new FormData();
  form.append("file", state.file, state.file.name);
  form.append("options", JSON.stringify(options()));
  const xhr = new XMLHttpRequest();
  const bar = $("upload-bar");
  bar.hidden = false;
  setBar(bar, 0, "running");
  $("submit").disabled = true;
  $("upload-status").textContent = "Uploading…";
  xhr.upload.onprogress = (e) => { if (e.lengthComputable) setBar(bar, e.loaded / e.total, "running"); };
  xhr.onload = () => {
    bar.hidden = true;
    $("submit").disabled = !state.file;
    let body = {};
    try { body = JSON.parse(xhr.responseText); } catch (_) { /* empty */ }
    if (xhr.status === 202) {
      $("upload-status").textContent = "Queued.";
      select(body.id);
      refreshList();
    } else {
      if (xhr.status === 401) $("auth").hidden = false;
      $("upload-status").textContent = `Refused: ${body.detail || xhr.statusText}`;
    }
  };
  xhr.onerror = () => {
    bar.hidden = true;
    $("submit").disabled = !state.file;
    $("upload-status").textContent = "Upload failed: the server is unreachable.";
  };
  xhr.open("POST", "/v1/jobs");
  for (const [k, v] of Object.entries(headers())) xhr.setRequestHeader(k, v);
  xhr.send(form);
}

// ------------------------------------------------------------------------------ job list
async function refreshList() {
  const filter = $("filter").value;
  let page;
  try {
    page = await api(`/v1/jobs?limit=50${filter ? "&status=" + filter : ""}`);
  } catch (err) {
    $("job-list-empty").textContent = err.message;
    $("job-list-empty").hidden = false;
    return;
  }
  const list = $("job-list");
  list.replaceChildren(...page.items.map(jobRow));
  $("job-list-empty").hidden = page.items.length > 0;
  $("job-list-empty").textContent = "No jobs yet.";
}

function jobRow(job) {
  const li = document.createElement("li");
  li.className = "job-row" + (job.id === state.selected ? " selected" : "");
  li.dataset.id = job.id;
  li.dataset.status = job.status;
  const title = document.createElement("span");
  title.className = "title";
  title.textContent = job.name;
  const badge = document.createElement("span");
  badge.className = `badge ${job.status}`;
  badge.textContent = job.status;
  const sub = document.createElement("span");
  sub.className = "sub";
  const bits = [fmtTime(job.created_at)];
  if (job.status === "running") bits.push(job.stage || "starting", job.eta_s != null ? `ETA ${fmtDuration(job.eta_s)}` : "");
  if (job.status === "failed" && job.error) bits.push(job.error.slice(0, 80));
  if (job.batch) {
    bits.push(`batch ${job.batch.slice(0, 8)}`);
    sub.title = `batch ${job.batch}`;
  }
  sub.textContent = bits.filter(Boolean).join(" · ");
  const bar = document.createElement("div");
  bar.className = "bar thin";
  bar.appendChild(document.createElement("div"));
  setBar(bar, job.fraction, job.status);
  li.append(title, badge, bar, sub);
  li.addEventListener("click", () => select(job.id));
  return li;
}

// ------------------------------------------------------------------------------ job view
function select(id) {
  if (state.selected !== id) {
    state.selected = id;
    state.detail = null;
    state.shownFiles = "";
    state.shownCrops = "";
    // nothing of the previous job stays on view until this one's detail arrives
    delete $("job-view").dataset.status;
    $("job-name").textContent = "";
    $("preview-pairs").replaceChildren();
    $("thumbs").replaceChildren();
    $("crops").replaceChildren();
    $("crops-box").hidden = true;
    $("model-box").hidden = true;
    if (window.pbrsrViewer) window.pbrsrViewer.clear($("model-view"));
  }
  for (const row of document.querySelectorAll(".job-row")) row.classList.toggle("selected", row.dataset.id === id);
  $("job-view").hidden = false;
  $("placeholder").hidden = true;
  refreshJob();
}

async function refreshJob() {
  const id = state.selected;
  if (!id) return;
  let job;
  try {
    job = await api(`/v1/jobs/${id}`);
  } catch (err) {
    $("job-error").hidden = false;
    $("job-error").textContent = err.message;
    return;
  }
  if (id !== state.selected) return;
  state.detail = job;
  renderJob(job);
}

// The LR model the job inverts: the one it was told, or for "auto" the estimate once the
// job's summary has it (the protocol's where no map was large or varied enough to tell);
// nothing for the protocol's when told.
function inputLine(o, lrModel) {
  if (o.lr_kernel !== "auto") return o.lr_kernel && o.lr_kernel !== "gaussian" ? `input by ${o.lr_kernel}` : "";
  if (!lrModel) return "input kernel to estimate";
  return `input by ${lrModel.kernel} (${lrModel.estimated ? "estimated" : "no map to estimate from"})`;
}

function renderJob(job) {
  $("job-view").dataset.status = job.status;
  $("job-name").textContent = job.name;
  const o = job.options || {};
  $("job-meta").textContent = [
    `x${o.scale}`, o.max_size ? `at most ${o.max_size} px` : "",
    o.maps ? `maps: ${o.maps.join(", ")}${o.other_maps === "bicubic" ? " (the rest bicubic)" : ""}` : "",
    inputLine(o, job.summary && job.summary.lr_model), o.method, o.method === "pbrsr" ? o.preset : "",
    `created ${fmtTime(job.created_at)}`,
    job.attempt > 1 ? `attempt ${job.attempt}` : "",
  ].filter(Boolean).join(" · ");
  const badge = $("job-status");
  badge.className = `badge ${job.status}`;
  badge.textContent = job.cancel_requested && !TERMINAL.has(job.status) ? "canceling" : job.status;
  const stage = job.status === "running" ? `${job.stage || "starting"}${job.total ? ` ${job.step}/${job.total}` : ""}` : "";
  $("job-stage").textContent = stage;
  $("job-eta").textContent = job.status === "running" && job.eta_s != null ? `about ${fmtDuration(job.eta_s)} left` : "";
  setBar($("job-bar"), job.fraction, job.status);

  const err = $("job-error");
  err.hidden = !job.error;
  err.textContent = job.error || "";
  $("cancel").hidden = TERMINAL.has(job.status) || job.cancel_requested;
  const dl = $("download");
  dl.hidden = !job.links.result;
  if (job.links.result) {
    dl.href = job.links.result;
    dl.setAttribute("download", "");
  }
  renderCharts(job);
  renderFiles(job);
  renderModel(job);
  renderCrops(job);
  renderMapTable(job);
  renderTimings(job);
}

function renderCharts(job) {
  const lossNames = new Set(), psnrNames = new Set();
  for (const p of job.history) {
    Object.keys(p.losses).forEach((k) => lossNames.add(k));
    // the optimizer's metrics are the consistency PSNR of each map group ("0:albedo", ...)
    Object.keys(p.metrics).forEach((k) => psnrNames.add(k));
  }
  const series = (names, field) => [...names].map((name) => ({
    name, points: job.history.filter((p) => name in p[field]).map((p) => [p.t, p[field][name]]),
  }));
  lineChart($("loss-chart"), series(lossNames, "losses"), { log: true, xlabel: "seconds", empty: job.status === "finished" ? "no losses reported (this method does not optimise)" : "waiting for the optimizer…" });
  lineChart($("psnr-chart"), series(psnrNames, "metrics"), { xlabel: "seconds", empty: job.status === "finished" ? "no PSNR reported" : "waiting for the optimizer…" });
}

async function renderFiles(job) {
  const previews = Object.entries(job.links.previews || {});
  const thumbs = Object.entries(job.links.thumbs || {});
  const key = JSON.stringify([previews, thumbs]);
  if (key === state.shownFiles) return;
  state.shownFiles = key;
  const pairs = previews.filter(([n]) => n !== "preview.png").sort(([a], [b]) => {
    const [la, ea] = a.replace(".png", "").split("_"), [lb, eb] = b.replace(".png", "").split("_");
    return ea === eb ? (la === "before" ? -1 : 1) : ea < eb ? -1 : 1;
  });
  const shown = pairs.length ? pairs : previews;
  $("previews").hidden = shown.length === 0;
  $("preview-pairs").replaceChildren(...await Promise.all(shown.map(([name, url]) => figure(name.replace(".png", "").replace("_", " — "), url))));
  $("maps").hidden = thumbs.length === 0;
  $("thumbs").replaceChildren(...await Promise.all(thumbs.map(([name, url]) => figure(name.replace(".png", ""), url))));
}

async function figure(caption, url) {
  const fig = document.createElement("figure");
  const img = document.createElement("img");
  img.alt = caption;
  img.loading = "lazy";
  try { img.src = await fileUrl(url); } catch (_) { /* leave it empty */ }
  const cap = document.createElement("figcaption");
  cap.textContent = caption;
  fig.append(img, cap);
  return fig;
}

// The upscaled asset in the 3D viewer (viewer3d.js, a module that may still be loading, or
// missing when its npm package is not installed).
function renderModel(job) {
  const url = job.links.model;
  $("model-box").hidden = !url;
  if (!url) return;
  const status = $("model-status");
  if (document.documentElement.dataset.viewer === "unavailable") {
    status.textContent = "The 3D viewer is not installed on this server (its npm package 'three': run scripts/setup).";
    return;
  }
  if (!window.pbrsrViewer) {
    status.textContent = "Loading the 3D viewer…";
    if (!state.waitingViewer) {
      state.waitingViewer = true;
      document.addEventListener("pbrsr-viewer-ready", () => {
        state.waitingViewer = false;
        if (state.detail) renderModel(state.detail);
      }, { once: true });
    }
    return;
  }
  const view = $("model-view");
  const note = () => {
    const notes = { loading: "Loading the model…", error: `Cannot show the model: ${view.dataset.error}` };
    status.textContent = notes[view.dataset.state] || "";
  };
  window.pbrsrViewer.show(view, url, fileUrl).then(
    () => { if (state.selected === job.id) note(); },
    (err) => { status.textContent = `Cannot show the model: ${err.message || err}`; },
  );
  note();
}

// Per map: the same region of the input map and of the result, one over the other, with a
// wipe between them (left of the split the input, each texel a square; right the result).
async function renderCrops(job) {
  const url = job.links.crops;
  if (!url || url === state.shownCrops) return;
  state.shownCrops = url;
  let list;
  try {
    list = await api(url);
  } catch (_) {
    state.shownCrops = ""; // read again on the next refresh
    return;
  }
  if (state.selected !== job.id) return;
  const figures = await Promise.all(list.items.map(wipeFigure));
  if (state.selected !== job.id) return;
  $("crops").replaceChildren(...figures);
  $("crops-box").hidden = figures.length === 0;
}

async function wipeFigure(crop) {
  const fig = document.createElement("figure");
  fig.className = "wipe";
  fig.dataset.map = crop.map;
  const box = document.createElement("div");
  box.className = "wipe-box";
  const [x, y, w, h] = crop.hr_region;
  box.style.aspectRatio = `${w} / ${h}`;
  const hr = document.createElement("img"), lr = document.createElement("img");
  hr.className = "wipe-hr";
  lr.className = "wipe-lr";
  hr.alt = `${crop.label}: result`;
  lr.alt = `${crop.label}: input`;
  try { [hr.src, lr.src] = await Promise.all([fileUrl(crop.hr), fileUrl(crop.lr)]); } catch (_) { /* left empty */ }
  const line = document.createElement("div");
  line.className = "wipe-line";
  box.append(hr, lr, line);
  const range = document.createElement("input");
  range.type = "range";
  range.min = "0";
  range.max = "100";
  range.step = "any";
  range.className = "wipe-range";
  range.setAttribute("aria-label", `${crop.label}: split between the input and the result`);
  const split = (pct) => {
    pct = Math.max(0, Math.min(100, pct));
    range.value = String(pct);
    box.style.setProperty("--split", `${pct}%`);
  };
  range.addEventListener("input", () => split(Number(range.value)));
  const follow = (e) => {
    const rect = box.getBoundingClientRect();
    split((100 * (e.clientX - rect.left)) / rect.width);
  };
  box.addEventListener("pointerdown", (e) => { box.setPointerCapture(e.pointerId); follow(e); });
  box.addEventListener("pointermove", (e) => { if (box.hasPointerCapture(e.pointerId)) follow(e); });
  split(50);
  const ends = document.createElement("div");
  ends.className = "wipe-ends";
  const [left, right] = [document.createElement("span"), document.createElement("span")];
  left.textContent = `input ${crop.lr_region[2]}×${crop.lr_region[3]}`;
  right.textContent = `result ${w}×${h}`;
  ends.append(left, right);
  const cap = document.createElement("figcaption");
  cap.textContent = `${crop.label} · x${crop.scale} · texels ${x},${y} of ${crop.hr_size[0]}×${crop.hr_size[1]}`;
  cap.title = crop.map;
  fig.append(cap, box, range, ends);
  return fig;
}

// One row per map of a finished job (pbrsr_core.map_table, in the job's summary).
function renderMapTable(job) {
  const rows = (job.summary && job.summary.map_rows) || [];
  $("map-table-box").hidden = rows.length === 0;
  const size = ([w, h]) => (w === h ? `${w}²` : `${w}×${h}`);
  $("map-table").tBodies[0].replaceChildren(...rows.map((r) => {
    const tr = document.createElement("tr");
    tr.dataset.index = String(r.index);
    const cells = [
      r.name, r.label || "",
      r.scale > 1 ? `${size(r.lr_size)} x${r.scale} = ${size(r.size)}` : `${size(r.lr_size)} kept`,
      r.made_from,
      Object.values(r.consistency_db || {}).map((db) => db.toFixed(1)).join(" "),
    ];
    tr.append(...cells.map((text) => {
      const td = document.createElement("td");
      td.textContent = text;
      return td;
    }));
    // which role each consistency PSNR is of (a data map has one per channel it holds)
    tr.cells[4].title = Object.entries(r.consistency_db || {}).map(([k, db]) => `${k} ${db.toFixed(2)} dB`).join(", ");
    return tr;
  }));
}

function renderTimings(job) {
  const rows = Object.entries(job.timings || {});
  $("timings-box").hidden = rows.length === 0;
  $("timings").replaceChildren(...rows.map(([k, v]) => {
    const tr = document.createElement("tr");
    const a = document.createElement("td"), b = document.createElement("td");
    a.textContent = k;
    b.textContent = `${v.toFixed(1)} s`;
    tr.append(a, b);
    return tr;
  }));
}

async function cancelSelected() {
  if (!state.selected) return;
  $("cancel").disabled = true;
  try {
    await api(`/v1/jobs/${state.selected}`, { method: "DELETE" });
  } catch (err) {
    $("job-error").hidden = false;
    $("job-error").textContent = err.message;
  } finally {
    $("cancel").disabled = false;
  }
  refreshJob();
  refreshList();
}

async function download(event) {
  if (!state.key) return; // a plain link works without a key
  event.preventDefault();
  let file;
  try { file = await keyedFile($("download").getAttribute("href")); } catch (_) { return; }
  const a = document.createElement("a");
  a.href = file.url;
  if (file.resp) { // the bytes: name them as the server does
    const name = (file.resp.headers.get("content-disposition") || "").match(/filename="?([^";]+)"?/);
    a.download = name ? name[1] : "result.zip";
  } // a presigned URL names the download itself
  a.click();
}

// --------------------------------------------------------------------------------- start
function poll() {
  refreshList();
  if (state.selected && (!state.detail || !TERMINAL.has(state.detail.status))) refreshJob();
}

// Refreshes asked for by events: the selected job on each of its events, the list on a job's
// state changes and at most every LIST_PROGRESS_MS for progress; one read of each in flight.
const LIST_PROGRESS_MS = 2000;
const pending = { list: false, job: false, timer: null, listAt: 0 };
function onEvent(event) {
  if (event.type !== "progress" || Date.now() - pending.listAt > LIST_PROGRESS_MS) pending.list = true;
  if (event.job === state.selected) pending.job = true;
  if (pending.timer) return;
  pending.timer = setTimeout(() => {
    pending.timer = null;
    if (pending.list) { pending.list = false; pending.listAt = Date.now(); refreshList(); }
    if (pending.job) { pending.job = false; refreshJob(); }
  }, 100);
}

// One SSE message block -> {id, event, data}.
function parseEvent(block) {
  const msg = {};
  for (const line of block.split("\n")) {
    if (!line || line.startsWith(":")) continue;
    const at = line.indexOf(":");
    const field = at < 0 ? line : line.slice(0, at);
    const value = at < 0 ? "" : line.slice(at + 1).replace(/^ /, "");
    msg[field] = field === "data" && msg.data !== undefined ? `${msg.data}\n${value}` : value;
  }
  return msg;
}

const stream = { lastId: "", timer: null, live: false, abort: null };
async function followEvents() {
  stream.abort = new AbortController();
  const init = {
    signal: stream.abort.signal,
    headers: { ...headers(), ...(stream.lastId ? { "Last-Event-ID": stream.lastId } : {}) },
  };
  try {
    const resp = await fetch("/v1/events", init);
    if (!resp.ok || !resp.body) throw new Error(`event stream: ${resp.status}`);
    stream.live = true;
    document.body.dataset.events = "live";
    if (stream.timer) { clearInterval(stream.timer); stream.timer = null; }
    poll(); // what happened while the stream was down
    const reader = resp.body.pipeThrough(new TextDecoderStream()).getReader();
    let buf = "";
    for (;;) {
      const { value, done } = await reader.read();
      if (done) break;
      buf += value;
      const blocks = buf.split("\n\n");
      buf = blocks.pop();
      for (const block of blocks) {
        const msg = parseEvent(block);
        if (msg.id) stream.lastId = msg.id;
        if (msg.event && msg.data) onEvent(JSON.parse(msg.data));
      }
    }
  } catch (_) { /* down: poll until it is back */ }
  stream.live = false;
  document.body.dataset.events = "polling";
  if (!stream.timer) stream.timer = setInterval(poll, POLL_MS);
  setTimeout(followEvents, RECONNECT_MS);
}

function init() {
  $("api-key").value = state.key;
  if (state.key) $("auth").hidden = false;
  $("save-key").addEventListener("click", () => {
    state.key = $("api-key").value.trim();
    localStorage.setItem("pbrsr-api-key", state.key);
    state.blobUrls.clear();
    stream.lastId = "";
    if (stream.abort) stream.abort.abort(); // reconnects with the new key
    poll();
  });
  $("file-input").addEventListener("change", (e) => pickFile(e.target.files[0]));
  const zone = $("drop-zone");
  for (const ev of ["dragenter", "dragover"]) zone.addEventListener(ev, (e) => { e.preventDefault(); zone.classList.add("over"); });
  for (const ev of ["dragleave", "drop"]) zone.addEventListener(ev, (e) => { e.preventDefault(); zone.classList.remove("over"); });
  zone.addEventListener("drop", (e) => pickFile(e.dataTransfer.files[0]));
  zone.addEventListener("keydown", (e) => { if (e.key === "Enter" || e.key === " ") $("file-input").click(); });
  $("upload-form").addEventListener("submit", upload);
  $("filter").addEventListener("change", refreshList);
  $("cancel").addEventListener("click", cancelSelected);
  $("download").addEventListener("click", download);
  $("opt-method").addEventListener("change", () => {
    const pbrsr = $("opt-method").value === "pbrsr";
    $("opt-preset").disabled = !pbrsr;
    $("opt-iterations").disabled = !pbrsr;
  });
  poll();
  followEvents();
}

document.addEventListener("DOMContentLoaded", init);
