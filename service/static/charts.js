// Small SVG line charts for the dashboard (no library): lineChart(el, series, opts).
// series: [{name, points: [[x, y], ...]}]; opts: {log: bool, xlabel: string}.
"use strict";

const CHART_COLOURS = ["#3a6df0", "#e0613a", "#1f9d55", "#9b4dd6", "#c07a00", "#1aa3b8", "#d03b8a"];
const SVG_NS = "http://www.w3.org/2000/svg";

function svgEl(tag, attrs, text) {
  const el = document.createElementNS(SVG_NS, tag);
  for (const [k, v] of Object.entries(attrs || {})) el.setAttribute(k, v);
  if (text !== undefined) el.textContent = text;
  return el;
}

function niceTicks(lo, hi, count) {
  if (!(hi > lo)) { const d = Math.abs(lo) || 1; lo -= d * 0.5; hi += d * 0.5; }
  const raw = (hi - lo) / Math.max(count, 1);
  const mag = Math.pow(10, Math.floor(Math.log10(raw)));
  const step = [1, 2, 5, 10].map((m) => m * mag).find((s) => s >= raw) || raw;
  const ticks = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) ticks.push(+v.toPrecision(12));
  return { lo: Math.min(lo, ticks[0]), hi: Math.max(hi, ticks[ticks.length - 1]), ticks };
}

function fmtTick(v) {
  const a = Math.abs(v);
  if (a !== 0 && (a < 1e-2 || a >= 1e4)) return v.toExponential(0);
  return +v.toPrecision(3) + "";
}

function lineChart(el, series, opts) {
  opts = opts || {};
  const W = el.clientWidth || 400, H = el.clientHeight || 200;
  const m = { l: 46, r: 10, t: 24, b: 34 };
  const svg = svgEl("svg", { viewBox: `0 0 ${W} ${H}`, role: "img" });
  const usable = series
    .map((s) => ({ name: s.name, points: s.points.filter((p) => isFinite(p[0]) && isFinite(p[1]) && (!opts.log || p[1] > 0)) }))
    .filter((s) => s.points.length > 0);
  el.replaceChildren(svg);
  if (!usable.length) {
    svg.appendChild(svgEl("text", { x: W / 2, y: H / 2, "text-anchor": "middle", class: "empty" }, opts.empty || "no data yet"));
    return;
  }
  const ty = (y) => (opts.log ? Math.log10(y) : y);
  let x0 = Infinity, x1 = -Infinity, y0 = Infinity, y1 = -Infinity;
  for (const s of usable) for (const [x, y] of s.points) {
    x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, ty(y)); y1 = Math.max(y1, ty(y));
  }
  if (x1 === x0) x1 = x0 + 1;
  const xt = niceTicks(x0, x1, 5), yt = niceTicks(y0, y1, 4);
  const px = (x) => m.l + ((x - xt.lo) / (xt.hi - xt.lo)) * (W - m.l - m.r);
  const py = (y) => H - m.b - ((ty(y) - yt.lo) / (yt.hi - yt.lo)) * (H - m.t - m.b);
  const pyRaw = (v) => H - m.b - ((v - yt.lo) / (yt.hi - yt.lo)) * (H - m.t - m.b);
  for (const v of yt.ticks) {
    svg.appendChild(svgEl("line", { x1: m.l, x2: W - m.r, y1: pyRaw(v), y2: pyRaw(v), class: "gridline" }));
    const label = opts.log ? fmtTick(Math.pow(10, v)) : fmtTick(v);
    svg.appendChild(svgEl("text", { x: m.l - 5, y: pyRaw(v) + 3, "text-anchor": "end", class: "tick" }, label));
  }
  for (const v of xt.ticks) {
    svg.appendChild(svgEl("text", { x: px(v), y: H - m.b + 13, "text-anchor": "middle", class: "tick" }, fmtTick(v)));
  }
  svg.appendChild(svgEl("line", { x1: m.l, x2: W - m.r, y1: H - m.b, y2: H - m.b, class: "axis" }));
  svg.appendChild(svgEl("line", { x1: m.l, x2: m.l, y1: m.t, y2: H - m.b, class: "axis" }));
  if (opts.xlabel) svg.appendChild(svgEl("text", { x: W - m.r, y: H - 4, "text-anchor": "end", class: "tick" }, opts.xlabel));
  let lx = m.l + 6;
  usable.forEach((s, i) => {
    const colour = CHART_COLOURS[i % CHART_COLOURS.length];
    const d = s.points.map((p, j) => `${j ? "L" : "M"}${px(p[0]).toFixed(1)},${py(p[1]).toFixed(1)}`).join("");
    svg.appendChild(svgEl("path", { d, fill: "none", stroke: colour, "stroke-width": 1.6, "stroke-linejoin": "round", "data-series": s.name }));
    if (s.points.length === 1) {
      const [x, y] = s.points[0];
      svg.appendChild(svgEl("circle", { cx: px(x), cy: py(y), r: 2.5, fill: colour }));
    }
    svg.appendChild(svgEl("rect", { x: lx, y: 8, width: 10, height: 3, fill: colour }));
    const t = svgEl("text", { x: lx + 13, y: 13, class: "legend" }, s.name);
    svg.appendChild(t);
    lx += 20 + 6 * s.name.length;
  });
}

window.lineChart = lineChart;
