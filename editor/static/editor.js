// Expression editor page (no build step). Talks to editor/server.py; state lives here:
// the edit is {base: null (the neutral) | geometry being touched up, pinned: Map index -> [x, y]},
// the server turns it into the propagated geometry and its synthesized image.
"use strict";

const TOKEN = document.body.dataset.token;
const CLIENT = Array.from(crypto.getRandomValues(new Uint8Array(8)), (b) => b.toString(16).padStart(2, "0")).join("");
const PICK_RADIUS = 9;        // px on screen: how near a press must be to take a point
const CLICK_SLOP = 2;         // px on screen a press may wander and still be a click (unpin)
const INBETWEEN_MS = 70;      // display time of each in-between frame (Sec. 14.2)
const STILL_MS = 150;         // a drag whose pointer rests this long gets the full image (not the preview)

const imageCanvas = document.getElementById("image");
const overlay = document.getElementById("overlay");
const imageCtx = imageCanvas.getContext("2d");
const overlayCtx = overlay.getContext("2d");
const $ = (id) => document.getElementById(id);

let layout = null;            // /api/describe
let edit = { base: null, pinned: new Map() };
let geometry = null;          // the geometry of the image shown, [[x, y] * N]
const undoStack = [];         // edits before, for undo
const redoStack = [];         // edits undone, for redo
let seq = 0;                  // sequence number of our image requests (the server drops older ones)
let latestShown = -1;         // sequence number of the image on screen
const MAX_IN_FLIGHT = 2;      // render requests under way at once (the server has two renderer processes)
let inFlight = 0;             // render requests under way
let pending = null;           // the newest edit not yet sent: {body, time}
let drag = null;              // {index, moved, before: edit, from: geometry, still: timer}
let playback = 0;             // generation of the in-between animation (a new drag stops it)
let playing = null;           // the in-between animation under way (a promise)
let keyframes = [];           // [{time_s, points}]
let idleWaiters = [];
const actions = new Set();    // asynchronous button actions under way (load frame, save, export)

// Measurements read by the tests and scripts/bench_editor.py.
const stats = {
  updates: [], latencies: [], widths: [], types: [], synthMs: [], synthCpuMs: [], propagateCpuMs: [],
  waitMs: [],    // request sent -> answer received, less the server's work on it (queue, transfer)
  decodeMs: [],  // answer received -> image decoded
  answers: [],   // when each image answer to a render request arrived (shown or overtaken)
  played: 0, errors: 0,
};
let shown = null;             // the image on the canvas: {type, width, height} as sent
window.editor = {
  stats,
  geometry: () => geometry,
  pinned: () => Array.from(edit.pinned.keys()),
  keyframes: () => keyframes,
  layout: () => layout,
  shown: () => shown,
  idle,
};

// Resolves when nothing is being dragged, rendered or played.
async function idle() {
  for (;;) {
    if (inFlight || pending || drag) await new Promise((resolve) => idleWaiters.push(resolve));
    else if (playing) await playing;
    else if (actions.size) await Promise.allSettled(Array.from(actions));
    else return;
  }
}

// Runs an asynchronous action of a button so that idle() waits for it.
function track(action) {
  return () => {
    const promise = action().catch((e) => status(`${e}`)).finally(() => actions.delete(promise));
    actions.add(promise);
  };
}

function status(text) { $("status").textContent = text || ""; }

function api(path, body) {
  const init = { headers: { "X-Editor-Token": TOKEN } };
  if (body !== undefined) {
    init.method = "POST";
    init.headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(body);
  }
  return fetch(path, init);
}

async function failure(response) {
  let message = response.statusText;
  try { message = (await response.json()).error; } catch (e) { /* not JSON */ }
  stats.errors += 1;
  status(`${response.status}: ${message}`);
}

// An image answer: uint32 LE header length, JSON header, images (meta.types) back to back.
async function unpack(response) {
  const buffer = await response.arrayBuffer();
  const length = new DataView(buffer).getUint32(0, true);
  const meta = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 4, length)));
  let offset = 4 + length;
  const images = meta.sizes.map((size, k) => {
    const blob = new Blob([new Uint8Array(buffer, offset, size)], { type: meta.types[k] });
    offset += size;
    return blob;
  });
  return { meta, images };
}

async function decode(blobs) {
  return Promise.all(blobs.map(async (b) => Object.assign(await createImageBitmap(b), { mime: b.type })));
}

// Images while dragging come smaller than the canvas with --preview-scale below 1, and are
// drawn scaled to it.
function show(bitmap) {
  imageCtx.drawImage(bitmap, 0, 0, imageCanvas.width, imageCanvas.height);
  shown = { type: bitmap.mime, width: bitmap.width, height: bitmap.height };
}

function wakeIdle() {
  if (inFlight || pending || drag) return;
  const waiters = idleWaiters;
  idleWaiters = [];
  waiters.forEach((resolve) => resolve());
}

// ---- rendering while dragging: at most MAX_IN_FLIGHT requests, only the newest edit waits ----
// While dragging (preview) the server sends a JPEG (at the pack's size unless --preview-scale
// says less); otherwise the pipeline's image, lossless.
function requestRender(time, preview = false) {
  const body = {
    client: CLIENT, seq: ++seq, base: edit.base, preview,
    pinned: Array.from(edit.pinned, ([i, p]) => [i, p[0], p[1]]),
  };
  pending = { body, time };
  pump();
}

async function pump() {
  if (inFlight >= MAX_IN_FLIGHT || !pending) return;
  const job = pending;
  pending = null;
  inFlight += 1;
  try {
    const sent = performance.now();
    const response = await api("api/render", job.body);
    if (response.ok) {
      const { meta, images } = await unpack(response);
      stats.answers.push(performance.now());
      if (meta.seq > latestShown) {           // an answer overtaken by a newer one is not shown
        const received = performance.now();
        const [bitmap] = await decode(images);
        const decoded = performance.now();
        if (meta.seq > latestShown) {
          latestShown = meta.seq;
          show(bitmap);
          geometry = meta.points;
          drawOverlay();
          const now = performance.now();
          stats.updates.push(now);
          stats.latencies.push(now - job.time);
          stats.widths.push(bitmap.width);
          stats.types.push(bitmap.mime);
          stats.waitMs.push(received - sent - meta.work_ms);
          stats.decodeMs.push(decoded - received);
          stats.synthMs.push(meta.synth_ms);
          stats.synthCpuMs.push(meta.synth_cpu_ms);
          stats.propagateCpuMs.push(meta.propagate_cpu_ms);
        }
      }
      status("");
    } else if (response.status !== 409) {
      await failure(response);
    }
  } catch (e) {
    stats.errors += 1;
    status(`request failed: ${e}`);
  } finally {
    inFlight -= 1;
    if (pending) pump(); else wakeIdle();
  }
}

// ---- when the mouse stops: the five in-betweens from the previous to the current geometry -----
async function playInbetweens(from) {
  const generation = ++playback;
  const to = geometry;
  const response = await api("api/inbetweens", { client: CLIENT, seq: ++seq, from, to });
  if (!response.ok) { if (response.status !== 409) await failure(response); return; }
  const { meta, images } = await unpack(response);
  const bitmaps = await decode(images);
  for (const bitmap of bitmaps) {
    if (generation !== playback || latestShown > meta.seq) return;
    show(bitmap);
    stats.played += 1;
    await new Promise((resolve) => setTimeout(resolve, INBETWEEN_MS));
  }
  latestShown = Math.max(latestShown, meta.seq);
}

// ---- overlay: points (pinned in red) and subregion outlines ----------------------------------
function drawOverlay() {
  const ctx = overlayCtx;
  ctx.clearRect(0, 0, overlay.width, overlay.height);
  if (!geometry) return;
  if ($("show-subregions").checked) {
    ctx.lineWidth = 1;
    layout.subregions.forEach((s, k) => {
      ctx.strokeStyle = `hsl(${(k * 47) % 360} 90% 60%)`;
      ctx.beginPath();
      s.polygon.forEach((i, j) => (j ? ctx.lineTo : ctx.moveTo).call(ctx, geometry[i][0] + 0.5, geometry[i][1] + 0.5));
      ctx.closePath();
      ctx.stroke();
    });
  }
  geometry.forEach(([x, y], i) => {
    const pinned = edit.pinned.has(i);
    ctx.beginPath();
    ctx.arc(x + 0.5, y + 0.5, pinned ? 3.5 : 2.5, 0, 2 * Math.PI);
    ctx.fillStyle = pinned ? "#ff3030" : "rgba(0, 230, 255, 0.85)";
    ctx.fill();
  });
}

// Image coordinates of a pointer event (pixel centres at integers, as OpenCV).
function toImage(event) {
  const box = overlay.getBoundingClientRect();
  const sx = overlay.width / box.width, sy = overlay.height / box.height;
  return [(event.clientX - box.left) * sx - 0.5, (event.clientY - box.top) * sy - 0.5];
}

function nearest([x, y]) {
  const box = overlay.getBoundingClientRect();
  const radius = PICK_RADIUS * overlay.width / box.width;
  let best = -1, bestDist = radius * radius;
  geometry.forEach(([px, py], i) => {
    const d = (px - x) ** 2 + (py - y) ** 2;
    if (d <= bestDist) { best = i; bestDist = d; }
  });
  return best;
}

const snapshot = () => ({ base: edit.base, pinned: new Map(edit.pinned) });

function commit(before) {
  undoStack.push(before);
  redoStack.length = 0;
  updateButtons();
}

overlay.addEventListener("pointerdown", (event) => {
  if (!geometry || event.button !== 0) return;
  const index = nearest(toImage(event));
  if (index < 0) return;
  overlay.setPointerCapture(event.pointerId);
  playback += 1;
  drag = { index, moved: false, before: snapshot(), from: geometry, down: [event.clientX, event.clientY] };
});

overlay.addEventListener("pointermove", (event) => {
  if (!drag) return;
  if (!drag.moved && Math.hypot(event.clientX - drag.down[0], event.clientY - drag.down[1]) < CLICK_SLOP) return;
  drag.moved = true;
  const xy = toImage(event);
  edit.pinned.set(drag.index, xy);
  geometry = geometry.map((p, i) => (i === drag.index ? xy : p));
  drawOverlay();
  requestRender(event.timeStamp, true);
  clearTimeout(drag.still);
  drag.still = setTimeout(() => { if (drag) requestRender(performance.now()); }, STILL_MS);
});

function endDrag(event) {
  if (!drag) return;
  const { index, moved, before, from, still } = drag;
  clearTimeout(still);
  drag = null;
  if (moved) {
    commit(before);
    const play = settled().then(() => playInbetweens(from)).catch((e) => status(`in-betweens failed: ${e}`)).finally(() => { if (playing === play) playing = null; });
    playing = play;
  } else if (edit.pinned.has(index)) {           // a click on a pinned point unpins it
    commit(before);
    edit.pinned.delete(index);
    requestRender(event.timeStamp);
  }
  wakeIdle();
}
overlay.addEventListener("pointerup", endDrag);
overlay.addEventListener("pointercancel", endDrag);

// Resolves when the newest edit has been rendered.
function settled() {
  return inFlight || pending ? new Promise((resolve) => idleWaiters.push(resolve)) : Promise.resolve();
}

function restore(target) {
  edit = target;
  playback += 1;
  requestRender(performance.now());
  updateButtons();
}

$("undo").addEventListener("click", () => { if (undoStack.length) { redoStack.push(snapshot()); restore(undoStack.pop()); } });
$("redo").addEventListener("click", () => { if (redoStack.length) { undoStack.push(snapshot()); restore(redoStack.pop()); } });
$("reset").addEventListener("click", () => {
  const before = snapshot();
  commit(before);
  restore({ base: null, pinned: new Map() });
});
document.addEventListener("keydown", (event) => {
  if (!(event.ctrlKey || event.metaKey) || event.key.toLowerCase() !== "z") return;
  event.preventDefault();
  $(event.shiftKey ? "redo" : "undo").click();
});
$("show-subregions").addEventListener("change", drawOverlay);

function updateButtons() {
  $("undo").disabled = undoStack.length === 0;
  $("redo").disabled = redoStack.length === 0;
  $("export").disabled = keyframes.length === 0;
}

// ---- keyframes --------------------------------------------------------------------------------
function listKeyframes() {
  const list = $("keys");
  list.replaceChildren(...keyframes.map((key, k) => {
    const item = document.createElement("li");
    item.textContent = `${key.time_s.toFixed(2)} s (${key.pinned} pinned)`;
    const remove = document.createElement("button");
    remove.textContent = "remove";
    remove.addEventListener("click", () => { keyframes.splice(k, 1); listKeyframes(); });
    item.appendChild(remove);
    return item;
  }));
  updateButtons();
}

$("save-key").addEventListener("click", track(async () => {
  await settled();
  const time = Number($("key-time").value);
  if (!Number.isFinite(time) || time < 0) { status("keyframe time must be a number >= 0"); return; }
  keyframes = keyframes.filter((k) => Math.abs(k.time_s - time) > 1e-9);
  keyframes.push({ time_s: time, points: geometry.map((p) => [p[0], p[1]]), pinned: edit.pinned.size });
  keyframes.sort((a, b) => a.time_s - b.time_s);
  $("key-time").value = (time + 1).toString();
  listKeyframes();
}));

$("export").addEventListener("click", track(async () => {
  const body = { fps: Number($("fps").value), keyframes: keyframes.map(({ time_s, points }) => ({ time_s, points })) };
  const response = await api("api/export", body);
  if (!response.ok) { await failure(response); return; }
  const link = document.createElement("a");
  link.href = URL.createObjectURL(await response.blob());
  link.download = "keyframes.npz";
  link.click();
  setTimeout(() => URL.revokeObjectURL(link.href), 10000);
}));

$("load-frame").addEventListener("click", track(async () => {
  const response = await api(`api/frame?index=${encodeURIComponent($("frame-index").value)}`);
  if (!response.ok) { await failure(response); return; }
  const frame = await response.json();
  commit(snapshot());
  restore({ base: frame.points, pinned: new Map() });
}));

// ---- start -------------------------------------------------------------------------------------
(async () => {
  const response = await api("api/describe");
  if (!response.ok) { await failure(response); return; }
  layout = await response.json();
  const [width, height] = layout.size;
  for (const canvas of [imageCanvas, overlay]) { canvas.width = width; canvas.height = height; }
  geometry = layout.neutral;
  $("performance").hidden = layout.performance_frames === 0;
  $("frame-index").max = String(Math.max(layout.performance_frames - 1, 0));
  updateButtons();
  drawOverlay();
  requestRender(performance.now());
})();
