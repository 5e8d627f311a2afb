// radarseg viewer: segments a .npy RAD cube, an ADC frame (.npy) or a frame of a DCA1000 capture (.bin) with this
// service and draws what came back. Talks only to the documented API: GET /v1/models, GET /v1/examples[/{n}[?frame=K]],
// POST /v1/segment?outputs=objects,masks,views&encoding=zlib (with ?input=adc for an ADC frame, and
// ?input=adc&format=dca1000&frame=K for a capture, read with the model's radar profile), and for a sequence POST /v1/streams, then
// POST /v1/streams/{id}/frames?seq=K, DELETE /v1/streams/{id}. State the tests read: body[data-state]
// (idle | loading | done | error), #message, canvas[data-drawn], #objects rows, #compute, body[data-input] (what was
// sent: complex, log_power, adc or dca1000), #frame-control and #frame for a capture, and after a stream
// canvas#ra-view[data-frames, data-arrows, data-trails].
"use strict";

// Class colours of our pictures (pipelines/figures.py CLASS_COLOURS); 0 is the background.
const CLASS_COLOURS = ["#00000000", "#ff4040", "#40c0ff", "#ffd000", "#60ff60"];
const MASK_ALPHA = 0.45;
// matplotlib's viridis at 9 stops, interpolated into a 256-entry table.
const VIRIDIS_STOPS = [[68, 1, 84], [71, 44, 122], [59, 81, 139], [44, 113, 142], [33, 144, 141],
  [39, 173, 129], [92, 200, 99], [170, 220, 50], [253, 231, 37]];
const VIRIDIS = Array.from({ length: 256 }, (_, i) => {
  const t = (i / 255) * (VIRIDIS_STOPS.length - 1);
  const k = Math.min(Math.floor(t), VIRIDIS_STOPS.length - 2);
  const f = t - k;
  return VIRIDIS_STOPS[k].map((c, j) => Math.round(c + f * (VIRIDIS_STOPS[k + 1][j] - c)));
});
const STAGES = ["decode", "transform", "detect", "grow", "segment", "project"];
const MARGIN = { left: 56, right: 74, top: 12, bottom: 46 };

const $ = (id) => document.getElementById(id);
const page = { key: null, model: null, shapes: {}, cube: null, result: null, hover: -1, retry: null, trails: null };
const HEAD_BYTES = 512; // a .npy header is read from the file's first bytes; the file itself goes to the service
const ARROW_SECONDS = 1; // a velocity arrow ends where its object would be after this long

class ApiFailure extends Error {
  constructor(status, body, retryAfter) {
    super(`${status} ${body.error}: ${body.detail}`);
    this.status = status;
    this.body = body;
    this.retryAfter = retryAfter;
  }
}

// ------------------------------------------------------------------ the API
async function api(path, options = {}) {
  const headers = { ...(options.headers || {}) };
  if (page.key) headers["X-API-Key"] = page.key;
  const response = await fetch(path, { ...options, headers });
  if (response.ok) return response;
  const text = await response.text();
  let body;
  try {
    body = JSON.parse(text);
  } catch {
    body = { error: response.statusText || "error", detail: text.slice(0, 300) || "(empty answer)" };
  }
  throw new ApiFailure(response.status, body, response.headers.get("Retry-After"));
}

async function getJson(path) {
  return (await api(path)).json();
}

// ------------------------------------------------------------------ arrays
async function decodeArray(encoded) {
  const n = encoded.shape.reduce((a, b) => a * b, 1);
  const Typed = { uint8: Uint8Array, uint16: Uint16Array, int32: Int32Array }[encoded.dtype];
  if (!Typed) throw new Error(`the viewer cannot draw arrays of dtype ${encoded.dtype}`);
  if (encoded.encoding === "zlib") {
    const packed = Uint8Array.from(atob(encoded.data), (c) => c.charCodeAt(0));
    const stream = new Blob([packed]).stream().pipeThrough(new DecompressionStream("deflate"));
    return new Typed(await new Response(stream).arrayBuffer(), 0, n);
  }
  const out = new Typed(n);
  let at = 0;
  for (const [value, length] of encoded.runs) {
    out.fill(value, at, at + length);
    at += length;
  }
  return out;
}

// A .npy header's dtype and shape (null for bytes that are no .npy file).
function npyHeader(head) {
  if (head.length < 12 || head[0] !== 0x93 || String.fromCharCode(...head.slice(1, 6)) !== "NUMPY") return null;
  const text = String.fromCharCode(...head.slice(head[6] === 1 ? 10 : 12));
  const descr = /'descr':\s*'([^']+)'/.exec(text);
  const shape = /'shape':\s*\(([^)]*)\)/.exec(text);
  return { descr: descr ? descr[1] : "", shape: shape ? shape[1].split(",").filter((n) => n.trim()).map(Number) : [] };
}

// What to send, from the first bytes and the name: a .bin that is no .npy is a DCA1000 capture (?input=adc&format=
// dca1000); in a .npy, integers (16-bit I/Q on a trailing axis of 2) are an ADC frame, floats log power in dB, and
// complex values the complex RAD cube when they have the model's cube shape, else an ADC frame (?input=adc). The
// service checks the rest and says what it expects.
function inputOf(head, name) {
  const header = npyHeader(head);
  if (!header) {
    return /\.bin$/i.test(name) ? { input: "adc", format: "dca1000", what: "a DCA1000 capture" }
      : { input: "complex", what: "a complex RAD cube" };
  }
  if (/^[<>|=]?[iu]\d/.test(header.descr)) return { input: "adc", what: "an ADC frame" };
  if (/^[<>|=]?f\d/.test(header.descr)) return { input: "log_power", what: "a log power cube" };
  const rad = page.shapes[page.model] || [];
  const isRad = header.shape.length === rad.length && header.shape.every((n, i) => n === rad[i]);
  return isRad ? { input: "complex", what: "a complex RAD cube" } : { input: "adc", what: "an ADC frame" };
}

// ------------------------------------------------------------------ messages and state
function setState(state, status) {
  document.body.dataset.state = state;
  if (status === undefined) delete document.body.dataset.status;
  else document.body.dataset.status = String(status);
}

function say(kind, text) {
  const box = $("message");
  box.dataset.kind = kind;
  box.textContent = text;
}

function showFailure(error) {
  const box = $("message");
  box.dataset.kind = "error";
  box.textContent = "";
  if (!(error instanceof ApiFailure)) {
    box.textContent = `The page could not finish: ${error.message}`;
    setState("error");
    return;
  }
  const code = document.createElement("span");
  code.className = "code";
  code.textContent = `${error.status} ${error.body.error}`;
  const extra = [];
  if (error.status === 429 && "used_macs" in error.body) {
    extra.push(`used ${fmtCount(error.body.used_macs)} of ${fmtCount(error.body.limit_macs)} MACs today`);
  }
  if (error.retryAfter) extra.push(`retry after ${error.retryAfter} s`);
  if (page.cube && page.cube.sent && error.status === 422) extra.push(`sent as ${page.cube.sent.what}`);
  if (error.status === 401) extra.push("enter an API key above");
  const detail = document.createElement("span");
  detail.className = "detail";
  detail.textContent = error.body.detail;
  box.append(code, detail, extra.length ? ` (${extra.join("; ")})` : "");
  setState("error", error.status);
  if (error.status === 401) {
    $("key-panel").hidden = false;
    $("api-key").focus();
  }
}

// Every user action goes through here: its failure is shown, and after a 401 it reruns once a key is given.
async function act(action) {
  page.retry = action;
  try {
    await action();
  } catch (error) {
    showFailure(error);
  }
}

// ------------------------------------------------------------------ models and examples
async function loadModels(wanted) {
  const answer = await getJson("/v1/models");
  const select = $("model");
  select.replaceChildren(...answer.models.map((m) => {
    const option = new Option(`${m.name} (${m.preset ?? "?"}${m.ready ? "" : ", not ready"})`, m.name);
    option.disabled = !m.ready;
    return option;
  }));
  const names = answer.models.map((m) => m.name);
  page.shapes = Object.fromEntries(answer.models.map((m) => [m.name, m.shape]));
  page.model = wanted && names.includes(wanted) ? wanted : answer.default;
  select.value = page.model;
}

async function loadExamples() {
  const answer = await getJson(`/v1/examples?model=${encodeURIComponent(page.model)}`);
  const select = $("example");
  select.replaceChildren(new Option("choose…", ""), ...answer.examples.map((e) => {
    const counts = {};
    for (const o of e.objects) counts[o.class_name] = (counts[o.class_name] || 0) + 1;
    const what = Object.entries(counts).map(([name, k]) => (k > 1 ? `${k} ${name}s` : `a ${name}`)).join(", ");
    return new Option(`${e.n}: ${what || "empty road"} (seed ${e.seed})`, String(e.n));
  }));
  page.examples = answer.examples;
}

async function segmentExample(n) {
  setState("loading");
  say("info", `Fetching example ${n}…`);
  const example = (page.examples || []).find((e) => e.n === n);
  const url = example ? example.url : `/v1/examples/${n}?model=${encodeURIComponent(page.model)}`;
  const bytes = await (await api(url)).arrayBuffer();
  $("example").value = String(n);
  await segment(new Blob([bytes]), `example ${n}`);
}

async function segmentUrl(url, frame) {
  setState("loading");
  say("info", "Fetching the cube…");
  const response = await fetch(url);
  if (!response.ok) throw new Error(`could not fetch the cube at ${url}: HTTP ${response.status}`);
  await segment(await response.blob(), "the cube from the address", frame, url);
}

// ------------------------------------------------------------------ streams
// Plays example n's sequence as a stream: each frame segmented and tracked by the service, drawn as it comes with
// each track's trail and velocity arrow; the stream is closed at the end.
async function playStream(n) {
  setState("loading");
  const example = (page.examples || []).find((e) => e.n === n);
  if (!example) throw new Error(`no example ${n} for model ${page.model}`);
  $("example").value = String(n);
  const stream = await (await api("/v1/streams", {
    method: "POST", body: JSON.stringify({ model: page.model }), headers: { "Content-Type": "application/json" },
  })).json();
  page.trails = new Map();
  page.cube = null;
  showFrameControl();
  try {
    for (let k = 0; k < example.frames; k++) {
      say("info", `Stream of example ${n}: frame ${k + 1} of ${example.frames}…`);
      const bytes = await (await api(`${example.url}&frame=${k}`)).arrayBuffer();
      const query = new URLSearchParams({ seq: String(k), outputs: "objects,masks,views", encoding: "zlib" });
      const response = await api(`/v1/streams/${stream.id}/frames?${query}`, {
        method: "POST", body: bytes, headers: { "Content-Type": "application/x-npy" },
      });
      const answer = await response.json();
      const [ra, rd, raMask, rdMask] = await Promise.all([answer.views.ra.array, answer.views.rd.array,
        answer.ra_mask, answer.rd_mask].map(decodeArray));
      for (const o of answer.objects) {
        if (!page.trails.has(o.track_id)) page.trails.set(o.track_id, []);
        page.trails.get(o.track_id).push({ x: o.x, y: o.y });
      }
      page.result = { answer, ra, rd, raMask, rdMask };
      page.hover = -1;
      render();
      $("ra-view").dataset.frames = String(k + 1);
    }
  } finally {
    await api(`/v1/streams/${stream.id}`, { method: "DELETE" }).catch(() => {});
  }
  const tracks = page.result.answer.stream.tracks;
  say("ok", `example ${n} as a stream: ${example.frames} frames, ${tracks.length} track${tracks.length === 1 ? "" : "s"}`
    + ` confirmed at the end (${tracks.map((t) => `#${t.track_id} ${t.class_name} ${t.speed.toFixed(1)} m/s`
      + (t.status === "lost" ? ", coasted: not seen in the last frame" : "")).join("; ")})`);
  setState("done", 200);
}

// ------------------------------------------------------------------ segmentation
// Segments ``source`` (a Blob: a picked or dropped file is sent as it is, never read whole by the page; the service's
// body limit answers 413 for a larger one). ``name`` tells a capture (.bin), whose frame ``frame`` is segmented.
async function segment(source, label, frame = 0, name = label) {
  const sameSource = page.cube && page.cube.source === source;
  const sent = inputOf(new Uint8Array(await source.slice(0, HEAD_BYTES).arrayBuffer()), name);
  page.cube = { source, label, name, frame, sent, frames: sameSource ? page.cube.frames : null };
  page.trails = null;
  showFrameControl();
  setState("loading");
  document.body.dataset.input = sent.format || sent.input;
  const what = sent.format ? `${label}, frame ${frame}` : label;
  say("info", `Segmenting ${what} (${(source.size / 2 ** 20).toFixed(1)} MiB, ${sent.what}) with ${page.model}…`);
  const query = new URLSearchParams({ model: page.model, input: sent.input, outputs: "objects,masks,views",
    encoding: "zlib" });
  if (sent.format) {
    query.set("format", sent.format);
    query.set("frame", String(frame));
  }
  const response = await api(`/v1/segment?${query}`, {
    method: "POST", body: source,
    headers: { "Content-Type": sent.format ? "application/octet-stream" : "application/x-npy" },
  });
  const frames = response.headers.get("X-Capture-Frames");
  page.cube.frames = frames === null ? null : Number(frames);
  showFrameControl();
  const answer = await response.json();
  const [ra, rd, raMask, rdMask] = await Promise.all([answer.views.ra.array, answer.views.rd.array,
    answer.ra_mask, answer.rd_mask].map(decodeArray));
  page.result = { answer, ra, rd, raMask, rdMask };
  page.hover = -1;
  render();
  const c = answer.compute;
  say("ok", `${what}${frames === null ? "" : ` (${frames} frames, from 0)`}: ${answer.objects.length} `
    + `object${answer.objects.length === 1 ? "" : "s"}, `
    + `${fmtCount(c.macs.total)}MACs, ${fmtMs(c.seconds.total)} (model ${answer.model}, preset ${answer.preset})`);
  setState("done", response.status);
}

// The frame index control: shown for a capture once the service has said how many frames it holds.
function showFrameControl() {
  const frames = page.cube && page.cube.sent && page.cube.sent.format ? page.cube.frames : null;
  $("frame-control").hidden = frames === null;
  if (frames === null) return;
  $("frame").max = String(frames - 1);
  $("frame").value = String(page.cube.frame);
  $("frame-count").textContent = `of ${frames} (0 to ${frames - 1})`;
}

// ------------------------------------------------------------------ drawing
function niceStep(span, ticks) {
  const raw = span / ticks;
  const power = 10 ** Math.floor(Math.log10(raw));
  return [1, 2, 5, 10].map((m) => m * power).find((s) => s >= raw);
}

// Fractional bin index of a physical value on a monotonic axis of bin centres.
function binOf(values, v) {
  const n = values.length;
  if (v <= values[0]) return (v - values[0]) / (values[1] - values[0]);
  for (let i = 0; i < n - 1; i++) {
    if (v <= values[i + 1]) return i + (v - values[i]) / (values[i + 1] - values[i]);
  }
  return n - 1 + (v - values[n - 1]) / (values[n - 1] - values[n - 2]);
}

function hexRgb(hex) {
  return [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16));
}

function setupCanvas(canvas) {
  const ratio = window.devicePixelRatio || 1;
  const { width, height } = canvas.getBoundingClientRect();
  canvas.width = Math.round(width * ratio);
  canvas.height = Math.round(height * ratio);
  const ctx = canvas.getContext("2d");
  ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
  return { ctx, width, height };
}

// The view (rows = range bins, range upwards) with the mask blended in, one pixel per bin.
function viewImage(levels, mask, rows, cols) {
  const image = new ImageData(cols, rows);
  const colours = CLASS_COLOURS.map((c, i) => (i === 0 ? null : hexRgb(c)));
  for (let r = 0; r < rows; r++) {
    for (let c = 0; c < cols; c++) {
      const src = r * cols + c;
      const dst = ((rows - 1 - r) * cols + c) * 4;
      let rgb = VIRIDIS[levels[src]];
      const k = mask[src];
      if (k > 0 && colours[k]) rgb = rgb.map((v, j) => v * (1 - MASK_ALPHA) + colours[k][j] * MASK_ALPHA);
      image.data.set([rgb[0], rgb[1], rgb[2], 255], dst);
    }
  }
  const offscreen = document.createElement("canvas");
  offscreen.width = cols;
  offscreen.height = rows;
  offscreen.getContext("2d").putImageData(image, 0, 0);
  return offscreen;
}

function drawView(canvas, spec) {
  const { ctx, width, height } = setupCanvas(canvas);
  const plot = { x: MARGIN.left, y: MARGIN.top, w: width - MARGIN.left - MARGIN.right,
    h: height - MARGIN.top - MARGIN.bottom };
  const sx = plot.w / spec.cols;
  const sy = plot.h / spec.rows;
  const px = (col) => plot.x + col * sx; // col, row in bin units (cell edges at integers)
  const py = (row) => plot.y + plot.h - row * sy;
  ctx.fillStyle = "#181c22";
  ctx.fillRect(0, 0, width, height);
  ctx.imageSmoothingEnabled = false;
  ctx.drawImage(viewImage(spec.levels, spec.mask, spec.rows, spec.cols), plot.x, plot.y, plot.w, plot.h);

  // Mask outlines: every edge between two cells of different classes, in the colour of the object side.
  let maskCells = 0;
  const paths = CLASS_COLOURS.map(() => new Path2D());
  const at = (r, c) => spec.mask[r * spec.cols + c];
  for (let r = 0; r < spec.rows; r++) {
    for (let c = 0; c < spec.cols; c++) {
      const k = at(r, c);
      if (k > 0) maskCells++;
      const right = c + 1 < spec.cols ? at(r, c + 1) : 0;
      const up = r + 1 < spec.rows ? at(r + 1, c) : 0;
      if (k !== right) {
        const path = paths[k || right];
        path.moveTo(px(c + 1), py(r));
        path.lineTo(px(c + 1), py(r + 1));
      }
      if (k !== up) {
        const path = paths[k || up];
        path.moveTo(px(c), py(r + 1));
        path.lineTo(px(c + 1), py(r + 1));
      }
      if (c === 0 && k > 0) { paths[k].moveTo(px(0), py(r)); paths[k].lineTo(px(0), py(r + 1)); }
      if (r === 0 && k > 0) { paths[k].moveTo(px(c), py(0)); paths[k].lineTo(px(c + 1), py(0)); }
    }
  }
  ctx.lineWidth = 1.4;
  paths.forEach((path, k) => {
    if (k === 0) return;
    ctx.strokeStyle = CLASS_COLOURS[k].slice(0, 7);
    ctx.stroke(path);
  });

  // Axes: ticks at round physical values, placed through the service's bin centres.
  ctx.strokeStyle = "#5a6470";
  ctx.lineWidth = 1;
  ctx.strokeRect(plot.x + 0.5, plot.y + 0.5, plot.w - 1, plot.h - 1);
  ctx.fillStyle = "#c3cad3";
  ctx.font = "12px system-ui, sans-serif";
  const tick = (x0, y0, x1, y1) => { ctx.beginPath(); ctx.moveTo(x0, y0); ctx.lineTo(x1, y1); ctx.stroke(); };
  ctx.textAlign = "center";
  ctx.textBaseline = "top";
  for (const value of spec.xTicks) {
    const x = px(binOf(spec.xAxis, value) + 0.5);
    if (x < plot.x - 0.5 || x > plot.x + plot.w + 0.5) continue;
    tick(x, plot.y + plot.h, x, plot.y + plot.h + 5);
    ctx.fillText(String(value), x, plot.y + plot.h + 7);
  }
  ctx.fillText(spec.xLabel, plot.x + plot.w / 2, plot.y + plot.h + 26);
  ctx.textAlign = "right";
  ctx.textBaseline = "middle";
  const ranges = spec.yAxis;
  const rangeStep = niceStep(ranges[ranges.length - 1] - ranges[0], 6);
  for (let value = 0; value <= ranges[ranges.length - 1]; value += rangeStep) {
    const y = py(binOf(ranges, value) + 0.5);
    tick(plot.x - 5, y, plot.x, y);
    ctx.fillText(String(value), plot.x - 8, y);
  }
  ctx.save();
  ctx.translate(16, plot.y + plot.h / 2);
  ctx.rotate(-Math.PI / 2);
  ctx.textAlign = "center";
  ctx.fillText("range (m)", 0, 0);
  ctx.restore();

  // Colour bar of this view's dB range.
  const bar = { x: plot.x + plot.w + 14, y: plot.y, w: 12, h: plot.h };
  const gradient = ctx.createLinearGradient(0, bar.y + bar.h, 0, bar.y);
  VIRIDIS_STOPS.forEach((rgb, i) => gradient.addColorStop(i / (VIRIDIS_STOPS.length - 1), `rgb(${rgb.join(",")})`));
  ctx.fillStyle = gradient;
  ctx.fillRect(bar.x, bar.y, bar.w, bar.h);
  ctx.fillStyle = "#c3cad3";
  ctx.textAlign = "left";
  const dbStep = niceStep(spec.high - spec.low, 5);
  for (let db = Math.ceil(spec.low / dbStep) * dbStep; db <= spec.high; db += dbStep) {
    const y = bar.y + bar.h - ((db - spec.low) / (spec.high - spec.low)) * bar.h;
    tick(bar.x + bar.w, y, bar.x + bar.w + 4, y);
    ctx.fillText(db.toFixed(0), bar.x + bar.w + 6, y);
  }
  ctx.textAlign = "center";
  ctx.textBaseline = "top";
  ctx.fillText("dB", bar.x + bar.w / 2 + 8, bar.y + bar.h + 7);

  // Objects: a numbered marker on each (row order of the table); the hovered one ringed in its class colour.
  spec.markers.forEach((m, i) => {
    const x = px(m.col + 0.5);
    const y = py(m.row + 0.5);
    const hovered = i === page.hover;
    ctx.lineWidth = hovered ? 3 : 1.5;
    ctx.strokeStyle = hovered ? m.colour : "rgba(255,255,255,0.85)";
    ctx.beginPath();
    ctx.arc(x, y, hovered ? 15 : 9, 0, 2 * Math.PI);
    ctx.stroke();
    ctx.font = `${hovered ? "bold " : ""}12px system-ui, sans-serif`;
    ctx.textAlign = "left";
    ctx.textBaseline = "bottom";
    ctx.fillStyle = "#ffffff";
    ctx.fillText(hovered ? `${i + 1} ${m.label}` : String(i + 1), x + (hovered ? 16 : 9), y - (hovered ? 8 : 5));
  });

  // Tracks (streams): each track's past positions as a dashed trail, each object's velocity vector as an arrow.
  ctx.setLineDash([4, 3]);
  ctx.lineWidth = 1.2;
  ctx.strokeStyle = "rgba(255,255,255,0.7)";
  for (const trail of spec.trails || []) {
    ctx.beginPath();
    trail.forEach((p, i) => (i ? ctx.lineTo : ctx.moveTo).call(ctx, px(p.col + 0.5), py(p.row + 0.5)));
    ctx.stroke();
  }
  ctx.setLineDash([]);
  for (const a of spec.arrows || []) {
    const [x0, y0, x1, y1] = [px(a.from.col + 0.5), py(a.from.row + 0.5), px(a.to.col + 0.5), py(a.to.row + 0.5)];
    const angle = Math.atan2(y1 - y0, x1 - x0);
    ctx.strokeStyle = a.colour;
    ctx.fillStyle = a.colour;
    ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.moveTo(x0, y0);
    ctx.lineTo(x1, y1);
    ctx.stroke();
    ctx.beginPath();
    ctx.moveTo(x1, y1);
    ctx.lineTo(x1 - 8 * Math.cos(angle - 0.4), y1 - 8 * Math.sin(angle - 0.4));
    ctx.lineTo(x1 - 8 * Math.cos(angle + 0.4), y1 - 8 * Math.sin(angle + 0.4));
    ctx.fill();
    ctx.font = "bold 11px system-ui, sans-serif";
    ctx.textAlign = "left";
    ctx.textBaseline = "top";
    ctx.fillText(a.label, x1 + 4, y1 + 2);
  }
  canvas.dataset.arrows = String((spec.arrows || []).length);
  canvas.dataset.trails = String((spec.trails || []).length);

  canvas.markerPositions = spec.markers.map((m) => ({ x: px(m.col + 0.5), y: py(m.row + 0.5) }));
  canvas.dataset.drawn = "true";
  canvas.dataset.maskCells = String(maskCells);
  canvas.dataset.markers = String(spec.markers.length);
  canvas.dataset.hovered = String(page.hover);
}

function renderViews() {
  const { answer, ra, rd, raMask, rdMask } = page.result;
  const axes = answer.views.axes;
  const [nRange, nAngle, nDoppler] = answer.shape;
  const vMax = Math.max(...axes.velocity_mps.map(Math.abs));
  const vStep = niceStep(2 * vMax, 6);
  const velocityTicks = [];
  for (let v = -Math.floor(vMax / vStep) * vStep; v <= vMax; v += vStep) velocityTicks.push(Number(v.toFixed(2)));
  const objects = answer.objects.map((o) => ({ ...o, colour: CLASS_COLOURS[o.class_id].slice(0, 7),
    label: `${o.class_name} ${o.score.toFixed(2)}` }));
  // a Cartesian point (m) on the RA view, in bins
  const raBins = (x, y) => ({ col: binOf(axes.angle_deg, (Math.atan2(x, y) * 180) / Math.PI),
    row: binOf(axes.range_m, Math.hypot(x, y)) });
  const tracked = page.trails !== null;
  drawView($("ra-view"), {
    levels: ra, mask: raMask, rows: nRange, cols: nAngle, low: answer.views.ra.low_db, high: answer.views.ra.high_db,
    xAxis: axes.angle_deg, xTicks: [-60, -30, 0, 30, 60], xLabel: "azimuth (°, right > 0)", yAxis: axes.range_m,
    markers: objects.map((o) => ({ ...o, col: binOf(axes.angle_deg, o.angle_deg), row: binOf(axes.range_m, o.range_m) })),
    arrows: tracked ? objects.map((o) => ({ from: raBins(o.x, o.y), colour: o.colour, label: `#${o.track_id}`,
      to: raBins(o.x + ARROW_SECONDS * o.vx, o.y + ARROW_SECONDS * o.vy) })) : [],
    trails: tracked ? [...page.trails.values()].filter((t) => t.length > 1).map((t) => t.map((p) => raBins(p.x, p.y)))
      : [],
  });
  drawView($("rd-view"), {
    levels: rd, mask: rdMask, rows: nRange, cols: nDoppler, low: answer.views.rd.low_db, high: answer.views.rd.high_db,
    xAxis: axes.velocity_mps, xTicks: velocityTicks, xLabel: "radial velocity (m/s, receding > 0)",
    yAxis: axes.range_m,
    markers: objects.map((o) => ({ ...o, col: binOf(axes.velocity_mps, o.velocity_mps),
      row: binOf(axes.range_m, o.range_m) })),
  });
  $("legend").replaceChildren(...answer.class_names.slice(1).map((name, i) => {
    const item = document.createElement("div");
    const swatch = document.createElement("span");
    swatch.className = "swatch";
    swatch.style.background = CLASS_COLOURS[i + 1].slice(0, 7);
    item.append(swatch, name);
    return item;
  }));
}

// ------------------------------------------------------------------ tables
function fmtCount(n) {
  const units = [[1e12, "T"], [1e9, "G"], [1e6, "M"], [1e3, "k"]];
  const [scale, unit] = units.find(([s]) => Math.abs(n) >= s) || [1, ""];
  return `${scale === 1 ? String(n) : (n / scale).toPrecision(3)} ${unit}`;
}

function fmtMs(seconds) {
  return seconds >= 1 ? `${seconds.toFixed(2)} s` : `${(seconds * 1e3).toFixed(1)} ms`;
}

function cell(text, title) {
  const td = document.createElement("td");
  td.textContent = text;
  if (title) td.title = title;
  return td;
}

function renderObjects() {
  const { answer } = page.result;
  const body = $("objects").tBodies[0];
  $("objects-count").textContent = `(${answer.objects.length})`;
  if (!answer.objects.length) {
    const row = document.createElement("tr");
    row.className = "empty";
    row.append(cell("no object above the model's score threshold"));
    row.firstChild.colSpan = 8;
    body.replaceChildren(row);
    return;
  }
  body.replaceChildren(...answer.objects.map((o, i) => {
    const row = document.createElement("tr");
    row.dataset.index = String(i);
    row.dataset.class = o.class_name;
    const name = cell(o.class_name);
    const swatch = document.createElement("span");
    swatch.className = "swatch";
    swatch.style.background = CLASS_COLOURS[o.class_id].slice(0, 7);
    name.prepend(swatch);
    row.append(cell(String(i + 1)), name, cell(o.score.toFixed(2)), cell(o.range_m.toFixed(1)),
      cell(o.angle_deg.toFixed(1)), cell(o.velocity_mps.toFixed(2)), cell(String(o.n_voxels)),
      o.track_id === undefined ? cell("–") : cell(`#${o.track_id}  ${o.vx.toFixed(1)} ${o.vy.toFixed(1)}`));
    if (o.track_id !== undefined) row.dataset.track = String(o.track_id);
    row.addEventListener("mouseenter", () => highlight(i));
    row.addEventListener("mouseleave", () => highlight(-1));
    return row;
  }));
}

function highlight(index) {
  if (page.hover === index) return;
  page.hover = index;
  for (const row of $("objects").tBodies[0].rows) row.classList.toggle("hovered", row.dataset.index === String(index));
  renderViews();
}

function figure(value, label, id, title) {
  const box = document.createElement("div");
  box.className = "figure";
  const b = document.createElement("b");
  b.textContent = value;
  if (id) b.id = id;
  if (title) b.title = title;
  const small = document.createElement("small");
  small.textContent = label;
  box.append(b, small);
  return box;
}

function renderCompute() {
  const { answer } = page.result;
  const c = answer.compute;
  const u = answer.usage;
  const panel = $("compute");
  const heading = document.createElement("h2");
  heading.textContent = "Compute";
  const figures = document.createElement("div");
  figures.className = "figures";
  figures.append(
    figure(`${fmtCount(c.macs.total)}MACs`, "total", "macs-total", `${c.macs.total} MACs`),
    figure(`${fmtCount(c.macs.detect)}MACs`, "detect", "macs-detect", `${c.macs.detect} MACs`),
    figure(`${fmtCount(c.macs.segment)}MACs`, "segment (sparse, on the ROI)", "macs-segment", `${c.macs.segment} MACs`),
    figure(`${fmtCount(c.macs.grow)}MACs`, "grow (region growing)", "macs-grow", `${c.macs.grow} MACs`),
    figure(c.roi_voxels.toLocaleString("en"), "ROI voxels", "roi-voxels"),
    figure(c.visited_points.toLocaleString("en"), "visited points", "visited-points"),
    figure(fmtCount(c.params.total).trim(), "parameters", "params",
      `detector ${c.params.detector}, segmenter ${c.params.segmenter}`),
    figure(String(c.detections), "centres (seeds)", "detections",
      "centres the detector found; an object is a centre whose region the segmenter labelled"),
    figure(fmtMs(c.seconds.total), "latency", "seconds-total"),
  );
  const latency = document.createElement("h2");
  latency.textContent = "Latency per stage";
  const bars = document.createElement("div");
  bars.className = "bars";
  const longest = Math.max(...STAGES.map((s) => c.seconds[s]), 1e-9);
  for (const stage of STAGES) {
    const name = document.createElement("span");
    name.className = "name";
    name.textContent = stage;
    const bar = document.createElement("div");
    bar.className = "bar";
    bar.dataset.stage = stage;
    bar.style.width = `${(100 * c.seconds[stage]) / longest}%`;
    const value = document.createElement("span");
    value.className = "value";
    value.textContent = fmtMs(c.seconds[stage]);
    bars.append(name, bar, value);
  }
  const usage = document.createElement("p");
  usage.className = "usage";
  usage.id = "usage";
  const quota = u.quota_macs == null ? "no daily quota"
    : `${fmtCount(u.remaining_macs)}MACs left of ${fmtCount(u.quota_macs)}MACs`;
  usage.append("Tenant ", bold(u.tenant), ` on ${u.day}: `, bold(`${u.requests} request${u.requests === 1 ? "" : "s"}`), ", ",
    bold(`${fmtCount(u.macs)}MACs`), ", ", bold(fmtMs(u.compute_seconds)), ` of compute; ${quota}.`);
  panel.replaceChildren(heading, figures, latency, bars, usage);
}

function bold(text) {
  const b = document.createElement("b");
  b.textContent = text;
  return b;
}

function render() {
  renderViews();
  renderObjects();
  renderCompute();
}

// ------------------------------------------------------------------ wiring
function wire() {
  $("model").addEventListener("change", (event) => act(async () => {
    page.model = event.target.value;
    await loadExamples();
    if (page.cube) await segment(page.cube.source, page.cube.label, page.cube.frame, page.cube.name);
  }));
  $("play").addEventListener("click", () => act(() => playStream(Number($("example").value) || 1)));
  $("example").addEventListener("change", (event) => {
    if (event.target.value) act(() => segmentExample(Number(event.target.value)));
  });
  $("file").addEventListener("change", (event) => {
    const file = event.target.files[0];
    if (file) act(() => segment(file, file.name));
    event.target.value = "";
  });
  $("frame").addEventListener("change", (event) => {
    const frame = Number(event.target.value);
    if (page.cube && Number.isInteger(frame) && frame >= 0) {
      act(() => segment(page.cube.source, page.cube.label, frame, page.cube.name));
    }
  });
  document.addEventListener("dragover", (event) => {
    event.preventDefault();
    document.body.classList.add("dragging");
  });
  document.addEventListener("dragleave", () => document.body.classList.remove("dragging"));
  document.addEventListener("drop", (event) => {
    event.preventDefault();
    document.body.classList.remove("dragging");
    const file = event.dataTransfer.files[0];
    if (file) act(() => segment(file, file.name));
  });
  const useKey = () => {
    page.key = $("api-key").value.trim() || null;
    $("key-panel").hidden = true;
    if (page.retry) act(page.retry);
  };
  $("key-use").addEventListener("click", useKey);
  $("api-key").addEventListener("keydown", (event) => { if (event.key === "Enter") useKey(); });
  window.addEventListener("resize", () => { if (page.result) renderViews(); });
  for (const canvas of [$("ra-view"), $("rd-view")]) { // pointing at a marker highlights its object too
    canvas.addEventListener("mousemove", (event) => {
      if (!canvas.markerPositions) return;
      const box = canvas.getBoundingClientRect();
      let nearest = -1;
      let distance = 14;
      canvas.markerPositions.forEach((p, i) => {
        const d = Math.hypot(p.x - (event.clientX - box.left), p.y - (event.clientY - box.top));
        if (d < distance) [nearest, distance] = [i, d];
      });
      highlight(nearest);
    });
    canvas.addEventListener("mouseleave", () => highlight(-1));
  }
}

function start() {
  wire();
  const params = new URLSearchParams(window.location.search);
  act(async () => {
    setState("loading");
    await loadModels(params.get("model"));
    await loadExamples();
    if (params.get("cube")) await segmentUrl(params.get("cube"), Number(params.get("frame")) || 0);
    else if (params.get("stream")) await playStream(Number(params.get("stream")));
    else if (params.get("example")) await segmentExample(Number(params.get("example")));
    else {
      say("info", "Choose an example, or open a cube or an ADC frame (.npy) or a DCA1000 capture (.bin).");
      setState("idle");
    }
  });
}

start();
