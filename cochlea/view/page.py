"""The replay page: one self-contained HTML file (inline script and style, nothing fetched),
drawing a replay (:func:`cochlea.view.replay.build_replay`) on a 2-D canvas in a perspective
projection the user orbits (drag: rotate, wheel: zoom).

The page's query ``?t=SECONDS`` sets the replay time (the last kept row at or before it; the
page stays paused there), so equal loads draw equal images; ``zoom``, ``yaw`` and ``pitch``
(rad) set the view. Once drawn, the element ``#status`` reads
``drawn N frames, t = T s`` (``N``: the replay's frames), which a headless browser's DOM dump
shows.
"""

from __future__ import annotations

import html
import json

TEMPLATE = r"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<title>cochlea-view: __TITLE__</title>
<style>
body{margin:0;font:13px sans-serif;background:#fff;color:#222;overflow:hidden}
#bar{position:absolute;left:0;right:0;bottom:0;padding:6px 8px;background:#f2f2f2;
display:flex;gap:8px;align-items:center}
#slider{flex:1}
#info{position:absolute;left:8px;top:6px;white-space:pre;pointer-events:none}
#legend{position:absolute;right:8px;top:6px;white-space:pre;text-align:right;pointer-events:none}
#stop{color:#c00}
canvas{display:block}
</style></head><body>
<canvas id="view"></canvas>
<div id="info">__TITLE__</div>
<div id="legend"><span style="color:#1f5fbf">&#9473; links</span>
<span style="color:#e08000">&#9473; actual tool path</span>
<span style="color:#2a9d3a">&#9477; desired tool path</span>
<span style="color:#c00">&#9675; keep-out</span></div>
<div id="bar"><button id="play">play</button>
<input id="slider" type="range" min="0" max="0" step="1" value="0">
<span id="time">t = 0 s</span> <span id="stop"></span>
<span id="status">loading</span></div>
<script id="replay" type="application/json">__DATA__</script>
<script>
"use strict";
const R = JSON.parse(document.getElementById("replay").textContent);
const canvas = document.getElementById("view"), ctx = canvas.getContext("2d");
const slider = document.getElementById("slider"), button = document.getElementById("play");
const T = R.times, N = T.length;
let index = 0, playing = false, yaw = -0.6, pitch = 0.5, zoom = 1, wall0 = 0, run0 = 0;
// the scene's centre and size, from every point drawn
const pts = [];
for (const u of R.units) {
  for (const f of u.frames) if (f) for (const p of f) pts.push(p);
  for (const path of [u.actual, u.desired || []]) for (const tool of path)
    for (const p of tool) if (p && p[0] !== null) pts.push(p);
}
for (const k of R.keep_out) pts.push(k.centre);
const lo = [0, 1, 2].map(i => Math.min(...pts.map(p => p[i])));
const hi = [0, 1, 2].map(i => Math.max(...pts.map(p => p[i])));
const centre = lo.map((v, i) => (v + hi[i]) / 2);
const size = Math.max(1e-3, ...hi.map((v, i) => v - lo[i]));
function resize() { canvas.width = window.innerWidth; canvas.height = window.innerHeight - 34; }
function project(p) {          // world (m) -> canvas (px), z up, orbit yaw/pitch
  const x = p[0] - centre[0], y = p[1] - centre[1], z = p[2] - centre[2];
  const cy = Math.cos(yaw), sy = Math.sin(yaw), cp = Math.cos(pitch), sp = Math.sin(pitch);
  const xr = cy * x - sy * y, yr = sy * x + cy * y;
  const depth = cp * yr + sp * z, up = -sp * yr + cp * z;
  const scale = zoom * 0.8 * Math.min(canvas.width, canvas.height) / size;
  const persp = 1 / (1 + 0.25 * depth / size);
  return [canvas.width / 2 + xr * scale * persp, canvas.height / 2 - up * scale * persp];
}
function polyline(points, colour, width, dash) {
  ctx.strokeStyle = colour; ctx.lineWidth = width; ctx.setLineDash(dash || []);
  ctx.beginPath(); let pen = false;
  for (const p of points) {
    if (!p || p[0] === null) { pen = false; continue; }
    const [a, b] = project(p);
    if (pen) ctx.lineTo(a, b); else ctx.moveTo(a, b);
    pen = true;
  }
  ctx.stroke(); ctx.setLineDash([]);
}
function circle(c, r, plane) {  // plane: the two axes the circle spans
  const out = [];
  for (let k = 0; k <= 64; k++) {
    const a = 2 * Math.PI * k / 64, p = c.slice();
    p[plane[0]] += r * Math.cos(a); p[plane[1]] += r * Math.sin(a); out.push(p);
  }
  return out;
}
function grid() {              // the world's x-y plane at z = 0 and its axes
  const step = Math.pow(10, Math.floor(Math.log10(size))) / 2, n = Math.ceil(size / step);
  const gx = Math.round(centre[0] / step) * step, gy = Math.round(centre[1] / step) * step;
  for (let k = -n; k <= n; k++) {
    polyline([[gx + k * step, gy - n * step, 0], [gx + k * step, gy + n * step, 0]], "#e6e6e6", 1);
    polyline([[gx - n * step, gy + k * step, 0], [gx + n * step, gy + k * step, 0]], "#e6e6e6", 1);
  }
  const L = size / 5;
  polyline([[0, 0, 0], [L, 0, 0]], "#d33", 2); polyline([[0, 0, 0], [0, L, 0]], "#3a3", 2);
  polyline([[0, 0, 0], [0, 0, L]], "#33d", 2);
}
function draw() {
  ctx.fillStyle = "#fff"; ctx.fillRect(0, 0, canvas.width, canvas.height);
  grid();
  for (const k of R.keep_out) {
    const c = k.centre.slice();
    if (k.moving) c[1] = k.moving[index];
    polyline(circle(c, k.radius, [0, 1]), "#c00", 1.5);
    if (k.kind === "sphere") {
      polyline(circle(c, k.radius, [0, 2]), "#c00", 1);
      polyline(circle(c, k.radius, [1, 2]), "#c00", 1);
    }
  }
  for (const u of R.units) {
    for (const tool of u.actual) polyline(tool.slice(0, index + 1), "#e08000", 2.5);
    if (u.desired) for (const tool of u.desired) polyline(tool, "#2a9d3a", 1.5, [5, 4]);
  }
  for (const u of R.units) {
    const f = u.frames[index];
    if (!f) continue;
    for (const [a, b] of u.edges) polyline([f[a], f[b]], "#1f5fbf", 5);
    ctx.fillStyle = "#123";
    for (const p of f) { const [x, y] = project(p); ctx.fillRect(x - 3, y - 3, 6, 6); }
    for (const tool of u.actual) {
      const p = tool[index];
      if (p && p[0] !== null) {
        const [x, y] = project(p);
        ctx.fillStyle = "#e08000"; ctx.beginPath(); ctx.arc(x, y, 5, 0, 2 * Math.PI); ctx.fill();
      }
    }
  }
  if (R.stop && R.stop.time_s !== null && T[index] >= R.stop.time_s) {
    for (const u of R.units) for (const tool of u.actual) {
      const s = stopIndex(), p = tool[s];
      if (!p || p[0] === null) continue;
      const [x, y] = project(p);
      ctx.strokeStyle = "#c00"; ctx.lineWidth = 3; ctx.beginPath();
      ctx.moveTo(x - 9, y - 9); ctx.lineTo(x + 9, y + 9);
      ctx.moveTo(x + 9, y - 9); ctx.lineTo(x - 9, y + 9); ctx.stroke();
    }
  }
  slider.value = index;
  document.getElementById("time").textContent = "t = " + T[index].toFixed(3) + " s";
  document.getElementById("status").textContent = "drawn " + N + " frames, t = " +
    T[index].toFixed(3) + " s";
}
function stopIndex() {
  let s = 0;
  while (s + 1 < N && T[s + 1] <= R.stop.time_s) s++;
  return s;
}
function at(t) {                // the last kept row at or before t (s)
  let k = 0;
  while (k + 1 < N && T[k + 1] <= t + 1e-9) k++;
  return k;
}
function tick(now) {
  if (!playing) return;
  const t = run0 + (now - wall0) / 1000;
  index = at(t);
  if (index >= N - 1) { playing = false; button.textContent = "play"; }
  draw();
  if (playing) requestAnimationFrame(tick);
}
button.onclick = () => {
  playing = !playing; button.textContent = playing ? "pause" : "play";
  if (playing) {
    if (index >= N - 1) index = 0;
    run0 = T[index]; wall0 = performance.now(); requestAnimationFrame(tick);
  }
};
slider.oninput = () => {
  index = +slider.value; playing = false; button.textContent = "play"; draw();
};
let drag = null;
canvas.onmousedown = e => { drag = [e.clientX, e.clientY]; };
window.onmouseup = () => { drag = null; };
window.onmousemove = e => {
  if (!drag) return;
  yaw -= (e.clientX - drag[0]) * 0.01;
  pitch = Math.max(-1.5, Math.min(1.5, pitch + (e.clientY - drag[1]) * 0.01));
  drag = [e.clientX, e.clientY]; draw();
};
canvas.onwheel = e => { e.preventDefault(); zoom *= Math.exp(-e.deltaY * 0.001); draw(); };
window.onresize = () => { resize(); draw(); };
slider.max = N - 1;
if (R.stop) document.getElementById("stop").textContent = "supervisor: " + R.stop.kind +
  " by rule " + R.stop.rule + (R.stop.time_s === null ? "" : " at t = " + R.stop.time_s + " s");
const query = new URLSearchParams(window.location.search);
const number = key => (query.get(key) !== null && isFinite(parseFloat(query.get(key))))
  ? parseFloat(query.get(key)) : null;
if (number("t") !== null) index = at(number("t"));
if (number("zoom") !== null && number("zoom") > 0) zoom = number("zoom");
if (number("yaw") !== null) yaw = number("yaw");
if (number("pitch") !== null) pitch = Math.max(-1.5, Math.min(1.5, number("pitch")));
resize(); draw();
</script></body></html>
"""


def render_page(replay: dict) -> str:
    """The page of ``replay``: the template with the replay's JSON inline (``<`` escaped, so no
    value can close the script element)."""
    data = json.dumps(replay, separators=(",", ":"), allow_nan=False).replace("<", "\\u003c")
    title = html.escape(f"{replay.get('robot')} robot, scenario {replay.get('scenario')}, "
                        f"{replay.get('space')} space, controller {replay.get('controller')}")
    return TEMPLATE.replace("__TITLE__", title).replace("__DATA__", data)


__all__ = ["render_page", "TEMPLATE"]
