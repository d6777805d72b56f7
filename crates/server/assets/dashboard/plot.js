// Small SVG plotting kit: linear scales with round ticks, a chart frame with axes, a
// confidence colour scale (viridis, readable in grey and by colour-blind people) and
// thinning of long series so a 30,000-image map or a long trip stays a few thousand nodes.

export const SVG_NS = "http://www.w3.org/2000/svg";

/** Creates an SVG element with attributes and children. */
export function s(tag, attrs, ...children) {
  const el = document.createElementNS(SVG_NS, tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === null || v === undefined || v === false) continue;
    if (k === "class") el.setAttribute("class", v);
    else if (k.startsWith("on")) el.addEventListener(k.slice(2), v);
    else el.setAttribute(k, String(v));
  }
  for (const c of children.flat(Infinity)) {
    if (c === null || c === undefined || c === false) continue;
    el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return el;
}

/** A linear map from [d0, d1] to [r0, r1], with `invert`. */
export function scale(d0, d1, r0, r1) {
  const span = d1 - d0 || 1;
  const f = (v) => r0 + ((v - d0) / span) * (r1 - r0);
  f.invert = (p) => d0 + ((p - r0) / (r1 - r0 || 1)) * span;
  f.domain = [d0, d1];
  f.range = [r0, r1];
  return f;
}

/** About `n` round tick values (1, 2 or 5 times a power of ten) within [a, b]. */
export function ticks(a, b, n) {
  if (!(b > a)) return [a];
  const raw = (b - a) / Math.max(1, n);
  const mag = Math.pow(10, Math.floor(Math.log10(raw)));
  const step = [1, 2, 2.5, 5, 10].map((m) => m * mag).find((st) => st >= raw) || raw;
  const out = [];
  for (let v = Math.ceil(a / step) * step; v <= b + step * 1e-9; v += step) {
    out.push(Number(v.toPrecision(12)));
  }
  return out;
}

function tickLabel(v) {
  if (Math.abs(v) >= 10000) return (v / 1000).toLocaleString("en-US") + "k";
  return Number(v.toPrecision(6)).toLocaleString("en-US");
}

/**
 * A chart frame: an <svg> of the given pixel size with x/y axes, labels and a clipped plot
 * group. `yDown`: y grows downwards (matrix rows). Returns {svg, plot, sx, sy, w, h, m}.
 */
export function chart({ width, height, x, y, xLabel, yLabel, yDown, title, margin }) {
  const m = Object.assign({ top: 12, right: 16, bottom: 40, left: 56 }, margin || {});
  const w = Math.max(40, width - m.left - m.right);
  const hh = Math.max(40, height - m.top - m.bottom);
  const sx = scale(x[0], x[1], 0, w);
  const sy = yDown ? scale(y[0], y[1], 0, hh) : scale(y[0], y[1], hh, 0);
  const clipId = "clip" + Math.random().toString(36).slice(2, 9);
  const svg = s("svg", {
    class: "chart",
    width,
    height,
    viewBox: `0 0 ${width} ${height}`,
    role: "img",
    "aria-label": title || "",
  });
  if (title) svg.append(s("title", {}, title));
  svg.append(s("defs", {}, s("clipPath", { id: clipId }, s("rect", { x: 0, y: 0, width: w, height: hh }))));
  const frame = s("g", { transform: `translate(${m.left},${m.top})` });
  svg.append(frame);
  const grid = s("g", { class: "grid" });
  const axes = s("g", { class: "axes" });
  for (const t of ticks(x[0], x[1], Math.max(2, Math.floor(w / 90)))) {
    const px = sx(t);
    grid.append(s("line", { x1: px, x2: px, y1: 0, y2: hh }));
    axes.append(s("text", { x: px, y: hh + 16, "text-anchor": "middle" }, tickLabel(t)));
  }
  for (const t of ticks(Math.min(y[0], y[1]), Math.max(y[0], y[1]), Math.max(3, Math.floor(hh / 40)))) {
    const py = sy(t);
    grid.append(s("line", { x1: 0, x2: w, y1: py, y2: py }));
    axes.append(s("text", { x: -8, y: py + 4, "text-anchor": "end" }, tickLabel(t)));
  }
  axes.append(s("rect", { class: "frame", x: 0, y: 0, width: w, height: hh }));
  if (xLabel) axes.append(s("text", { class: "label", x: w / 2, y: hh + 34, "text-anchor": "middle" }, xLabel));
  if (yLabel) {
    axes.append(
      s("text", { class: "label", transform: `translate(${-m.left + 14},${hh / 2}) rotate(-90)`, "text-anchor": "middle" }, yLabel),
    );
  }
  const plot = s("g", { "clip-path": `url(#${clipId})` });
  frame.append(grid, plot, axes);
  return { svg, plot, frame, sx, sy, w, h: hh, m };
}

/** Path data through points [x, y] in pixels; `null` entries break the line. */
export function pathData(points) {
  let d = "";
  let pen = false;
  for (const p of points) {
    if (!p) {
      pen = false;
      continue;
    }
    d += (pen ? "L" : "M") + p[0].toFixed(1) + "," + p[1].toFixed(1);
    pen = true;
  }
  return d;
}

/** Every k-th element (and the last) so that at most `max` remain; order kept. */
export function thin(xs, max) {
  if (xs.length <= max) return xs;
  const k = Math.ceil(xs.length / max);
  const out = [];
  for (let i = 0; i < xs.length; i += k) out.push(xs[i]);
  if (out[out.length - 1] !== xs[xs.length - 1]) out.push(xs[xs.length - 1]);
  return out;
}

const VIRIDIS = [
  [68, 1, 84], [71, 44, 122], [59, 81, 139], [44, 113, 142], [33, 144, 141],
  [39, 173, 129], [92, 200, 99], [170, 220, 50], [253, 231, 37],
];

/** Viridis at t in [0, 1] as an rgb() string. */
export function viridis(t) {
  const u = Math.min(1, Math.max(0, Number.isFinite(t) ? t : 0)) * (VIRIDIS.length - 1);
  const i = Math.min(VIRIDIS.length - 2, Math.floor(u));
  const f = u - i;
  const c = VIRIDIS[i].map((a, k) => Math.round(a + f * (VIRIDIS[i + 1][k] - a)));
  return `rgb(${c[0]},${c[1]},${c[2]})`;
}

/**
 * A colour scale for confidences: the 5th to 95th percentile of the values span the colours,
 * so one extreme value does not wash the rest out. Returns f(value) -> colour, with f.lo, f.hi.
 */
export function confidenceColors(values) {
  const v = values.filter(Number.isFinite).sort((a, b) => a - b);
  let lo = v.length ? v[Math.floor(0.05 * (v.length - 1))] : 0;
  let hi = v.length ? v[Math.ceil(0.95 * (v.length - 1))] : 1;
  if (!(hi > lo)) {
    lo -= 0.5;
    hi += 0.5;
  }
  const f = (x) => viridis((x - lo) / (hi - lo));
  f.lo = lo;
  f.hi = hi;
  return f;
}

/**
 * Colours for calibrated probabilities (`p_correct`): one fixed scale from 0 to 1, so a colour
 * means the same on every page, route and map.
 */
export function probabilityColors() {
  const f = (p) => viridis(Math.max(0, Math.min(1, p)));
  f.lo = 0;
  f.hi = 1;
  f.fixed = true;
  return f;
}

/** A horizontal colour legend for `colors` (from confidenceColors or probabilityColors), `width` px wide. */
export function legend(colors, label, width) {
  const id = "grad" + Math.random().toString(36).slice(2, 9);
  const bar = Math.max(80, width - 150);
  return s(
    "svg",
    { class: "legend", width, height: 34, viewBox: `0 0 ${width} 34`, role: "img", "aria-label": label },
    s(
      "defs",
      {},
      s(
        "linearGradient",
        { id },
        VIRIDIS.map((_, i) => s("stop", { offset: i / (VIRIDIS.length - 1), "stop-color": viridis(i / (VIRIDIS.length - 1)) })),
      ),
    ),
    s("text", { x: 0, y: 20 }, label),
    s("text", { x: 140, y: 31, "text-anchor": "middle", class: "small" }, (colors.fixed ? "" : "≤ ") + tickLabel(Number(colors.lo.toPrecision(3)))),
    s("rect", { x: 140, y: 6, width: bar - 30, height: 12, fill: `url(#${id})` }),
    s("text", { x: 110 + bar, y: 31, "text-anchor": "middle", class: "small" }, (colors.fixed ? "" : "≥ ") + tickLabel(Number(colors.hi.toPrecision(3)))),
  );
}

/**
 * The y range of a confidence chart: the data's own range with a margin, so differences in
 * the second decimal (typical of ratios near 1) are visible. Returns [lo, hi].
 */
export function confidenceRange(values) {
  const v = values.filter(Number.isFinite);
  if (!v.length) return [0, 1];
  let lo = Math.min(...v);
  let hi = Math.max(...v);
  const pad = (hi - lo) * 0.08 || Math.abs(hi) * 0.05 || 0.5;
  return [lo - pad, hi + pad];
}

/** Width available inside `el` for a chart (at least 300 px, at most 1400 px). */
export function widthOf(el) {
  return Math.max(300, Math.min(1400, Math.floor(el.getBoundingClientRect().width || 800)));
}
