"""The preview page served at ``GET /``: one inline HTML document, no external assets."""

from __future__ import annotations

PAGE_HTML = """<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>upcast - local preview</title>
<style>
  :root { color-scheme: dark; }
  body { margin: 0; background: #111; color: #ddd; font: 14px/1.4 system-ui, sans-serif; }
  header { padding: 8px 14px; background: #1b1b1b; border-bottom: 1px solid #333; }
  header b { color: #fff; }
  .note { color: #aaa; font-size: 12px; }
  #stage { position: relative; display: inline-block; margin: 12px; outline: none;
           border: 2px solid #333; cursor: grab; user-select: none; }
  #stage:focus { border-color: #4a8; }
  #stage.dragging { cursor: grabbing; }
  #view { display: block; max-width: calc(100vw - 32px); height: auto; background: #000;
          min-width: 320px; min-height: 180px; }
  #overlay { position: absolute; top: 6px; left: 6px; padding: 6px 8px; border-radius: 4px;
             background: rgba(0, 0, 0, 0.6); font: 12px/1.35 ui-monospace, monospace;
             white-space: pre; pointer-events: none; }
  #controls { margin: 0 14px 12px; }
  #error { color: #f77; margin-left: 10px; }
  kbd { border: 1px solid #555; border-radius: 3px; padding: 0 4px; background: #222; }
</style>
</head>
<body>
<header>
  <b>upcast</b> &mdash; local preview (MJPEG over HTTP).
  <span class="note">This page is only a local preview of the upscaled output; the
  low-latency WebTransport player comes with the streaming server.</span>
</header>
<div id="stage" tabindex="0" title="click to focus, then steer">
  <img id="view" src="/stream.mjpg" alt="upscaled game stream" draggable="false">
  <div id="overlay">waiting for stats...</div>
</div>
<div id="controls">
  <label>upscaler <select id="upscaler"></select></label>
  <span class="note">&nbsp; Click the picture, then <kbd>W</kbd><kbd>A</kbd><kbd>S</kbd><kbd>D</kbd>
  or arrows to move, <kbd>Space</kbd>/<kbd>C</kbd> up/down, drag the mouse to look.</span>
  <span id="error"></span>
</div>
<script>
"use strict";
const $ = (id) => document.getElementById(id);
const view = $("view"), stage = $("stage"), overlay = $("overlay");
const select = $("upscaler"), errorBox = $("error");

function showError(text) {
  errorBox.textContent = text || "";
}

view.addEventListener("error", () => {
  setTimeout(() => { view.src = "/stream.mjpg?t=" + Date.now(); }, 1000);
});

function fmt(v) { return v === null || v === undefined ? "-" : Number(v).toFixed(1); }

let selectFilled = false;
async function pollStats() {
  try {
    const r = await fetch("/stats", { cache: "no-store" });
    const s = await r.json();
    if (!selectFilled && Array.isArray(s.upscalers)) {
      for (const name of s.upscalers) {
        const o = document.createElement("option");
        o.value = o.textContent = name;
        select.appendChild(o);
      }
      selectFilled = true;
    }
    if (s.upscaler && document.activeElement !== select) select.value = s.upscaler;
    const lines = [
      "fps " + fmt(s.fps) + "  (preview " + fmt(s.preview_fps) + ")",
      "frame " + (s.frame_id ?? "-") + "   upscaler " + (s.upscaler ?? "?"),
    ];
    for (const [k, v] of Object.entries(s.stages_ms || {})) {
      lines.push(k.padEnd(15) + fmt(v).padStart(7) + " ms");
    }
    lines.push("viewers " + s.viewers);
    if (s.session) lines.push("worker restarts " + s.session.worker_restarts);
    if (s.worker && s.worker.ok === false) lines.push("worker: " + s.worker.error);
    overlay.textContent = lines.join("\\n");
  } catch (e) {
    overlay.textContent = "stats unavailable (server stopped?)";
  }
}
setInterval(pollStats, 500);
pollStats();

select.addEventListener("change", async () => {
  showError("");
  try {
    const r = await fetch("/control", {
      method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ upscaler: select.value }),
    });
    const body = await r.json();
    if (!r.ok) showError(body.error || ("HTTP " + r.status));
  } catch (e) {
    showError(String(e));
  }
});

// ---- input: accumulated, then sent at most every 33 ms, one request in flight.
const SPEED_M_S = 3.0, LOOK_DEG_PER_PX = 0.2, SEND_MS = 33;
const MAX_LOOK = 90, MAX_MOVE = 5;
const keys = new Set();
const MOVE_KEYS = {
  KeyW: "f", ArrowUp: "f", KeyS: "b", ArrowDown: "b", KeyA: "l", ArrowLeft: "l",
  KeyD: "r", ArrowRight: "r", Space: "u", KeyC: "d",
};
let dyaw = 0, dpitch = 0, inFlight = false, lastTick = performance.now();
let dragging = false, lastX = 0, lastY = 0;

stage.addEventListener("keydown", (e) => {
  if (MOVE_KEYS[e.code]) { keys.add(MOVE_KEYS[e.code]); e.preventDefault(); }
});
stage.addEventListener("keyup", (e) => {
  if (MOVE_KEYS[e.code]) { keys.delete(MOVE_KEYS[e.code]); e.preventDefault(); }
});
stage.addEventListener("blur", () => keys.clear());
stage.addEventListener("pointerdown", (e) => {
  stage.focus();
  dragging = true; lastX = e.clientX; lastY = e.clientY;
  stage.classList.add("dragging");
  stage.setPointerCapture(e.pointerId);
  e.preventDefault();
});
stage.addEventListener("pointermove", (e) => {
  if (!dragging) return;
  dyaw -= (e.clientX - lastX) * LOOK_DEG_PER_PX;   // drag right: turn right
  dpitch -= (e.clientY - lastY) * LOOK_DEG_PER_PX; // drag up: look up
  lastX = e.clientX; lastY = e.clientY;
});
function endDrag() { dragging = false; stage.classList.remove("dragging"); }
stage.addEventListener("pointerup", endDrag);
stage.addEventListener("pointercancel", endDrag);

const clamp = (v, m) => Math.max(-m, Math.min(m, v));
function axis(pos, neg) { return (keys.has(pos) ? 1 : 0) - (keys.has(neg) ? 1 : 0); }

setInterval(async () => {
  const now = performance.now();
  const dt = Math.min(0.1, (now - lastTick) / 1000);
  lastTick = now;
  const step = SPEED_M_S * dt;
  const msg = {
    dyaw_deg: clamp(dyaw, MAX_LOOK), dpitch_deg: clamp(dpitch, MAX_LOOK),
    forward: clamp(axis("f", "b") * step, MAX_MOVE), right: clamp(axis("r", "l") * step, MAX_MOVE),
    up: clamp(axis("u", "d") * step, MAX_MOVE),
  };
  if (inFlight || Object.values(msg).every((v) => v === 0)) return;
  dyaw -= msg.dyaw_deg; dpitch -= msg.dpitch_deg;
  inFlight = true;
  try {
    const r = await fetch("/input", {
      method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify(msg),
    });
    if (!r.ok) showError("input refused: " + (await r.json()).error);
  } catch (e) {
    showError("input failed: " + e);
  } finally {
    inFlight = false;
  }
}, SEND_MS);
</script>
</body>
</html>
"""
