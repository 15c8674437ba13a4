// Line plots on a canvas, with no library: series of (x, y) points, a linear or a
// logarithmic y axis, ticks at the ends, a legend. data-points on the canvas counts
// the points drawn (what the browser tests read).
"use strict";
const COLOURS = ["#1565c0", "#e65100", "#2e7d32", "#6a1b9a", "#c62828", "#00838f"];

function plotLines(canvas, series, options = {}) {
  const ctx = canvas.getContext("2d");
  const w = canvas.width, h = canvas.height, left = 60, right = 10, top = 10, bottom = 24;
  ctx.clearRect(0, 0, w, h);
  const log = !!options.log;
  const points = series.flatMap(s => s.points.filter(p => Number.isFinite(p[1]) && (!log || p[1] > 0)));
  canvas.dataset.points = String(points.length);
  if (!points.length) return;
  const ys = points.map(p => log ? Math.log10(p[1]) : p[1]);
  const xs = points.map(p => p[0]);
  let [y0, y1] = [Math.min(...ys), Math.max(...ys)];
  if (y1 - y0 < 1e-12) { y0 -= 0.5; y1 += 0.5; }
  const [x0, x1] = [Math.min(...xs), Math.max(...xs) + 1e-9];
  const px = x => left + (x - x0) / (x1 - x0) * (w - left - right);
  const py = y => top + (1 - (y - y0) / (y1 - y0)) * (h - top - bottom);
  ctx.strokeStyle = "#999"; ctx.lineWidth = 1;
  ctx.strokeRect(left, top, w - left - right, h - top - bottom);
  ctx.fillStyle = "#333"; ctx.font = "11px sans-serif";
  const label = v => (log ? Math.pow(10, v) : v).toPrecision(3);
  ctx.fillText(label(y1), 2, top + 10); ctx.fillText(label(y0), 2, h - bottom);
  ctx.fillText(String(Math.round(x0)), left, h - 8);
  ctx.fillText(String(Math.round(x1)) + (options.xlabel ? " " + options.xlabel : ""), w - right - 60, h - 8);
  series.forEach((s, i) => {
    ctx.strokeStyle = s.colour || COLOURS[i % COLOURS.length]; ctx.lineWidth = 1.5; ctx.beginPath();
    let started = false;
    for (const [x, y] of s.points) {
      if (!Number.isFinite(y) || (log && y <= 0)) continue;
      const cx = px(x), cy = py(log ? Math.log10(y) : y);
      if (started) ctx.lineTo(cx, cy); else { ctx.moveTo(cx, cy); started = true; }
      if (s.dots) ctx.fillRect(cx - 2, cy - 2, 4, 4);
    }
    ctx.stroke();
    ctx.fillStyle = s.colour || COLOURS[i % COLOURS.length];
    ctx.fillText(s.name, left + 8 + 130 * i, top + 14);
  });
}

// One small plot per fitted parameter from log entries' "params" (a colour: one line per channel).
function plotTrajectories(container, log) {
  const keys = new Set();
  log.forEach(e => Object.keys(e.params || {}).forEach(k => keys.add(k)));
  for (const key of keys) {
    let canvas = container.querySelector(`canvas[data-key="${CSS.escape(key)}"]`);
    if (!canvas) {
      const box = document.createElement("div"); box.className = "traj";
      box.textContent = key; box.appendChild(document.createElement("br"));
      canvas = document.createElement("canvas"); canvas.width = 300; canvas.height = 140; canvas.dataset.key = key;
      box.appendChild(canvas); container.appendChild(box);
    }
    const channels = Math.max(...log.filter(e => e.params && e.params[key]).map(e => e.params[key].length));
    // x: the step over the whole fit (a coarse-to-fine fit counts its levels' steps on)
    const series = [];
    for (let c = 0; c < channels; c++) {
      series.push({ name: channels > 1 ? "rgb"[c] || String(c) : "value",
        colour: channels === 3 ? ["#c62828", "#2e7d32", "#1565c0"][c] : undefined,
        points: log.map((e, i) => [i + 1, e.params && e.params[key] ? e.params[key][c] : NaN]) });
    }
    plotLines(canvas, series, { xlabel: "step" });
  }
}

function lossSeries(log) {
  const steps = log.map((e, i) => [i + 1, e.loss]);
  const held = log.map((e, i) => [i + 1, e.validation_error]).filter(p => p[1] !== undefined && p[1] !== null);
  const series = [{ name: "training loss", points: steps }];
  if (held.length) series.push({ name: "held-out error", points: held, dots: true });
  return series;
}
