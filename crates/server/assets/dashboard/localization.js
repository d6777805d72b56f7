// `/localizations/{id}`: the figure both papers explain their results with: queries (rows,
// downwards) against references (columns), every route hypothesis drawn over it and each
// query's prediction as a dot coloured by its p_correct (or its confidence for methods without a
// calibration); below it the same along the
// route, the parameters and the timings. Clicking a query (in the figure or the chart) shows
// what it was matched to.

import { getImageUrl, getJson, seg } from "./api.js";
import { thumbnail } from "./thumbs.js";
import { chart, confidenceColors, confidenceRange, legend, pathData, probabilityColors, s, thin, widthOf } from "./plot.js";
import { crumbs, facts, fill, fmtConf, fmtInt, fmtNum, fmtSeconds, fmtTime, h, section, shortId, stat } from "./ui.js";

/** Colours of hypotheses by rank (1 first); they cycle after the last. */
const RANK_COLORS = ["#e4572e", "#17becf", "#f28e2b", "#b07aa1", "#59a14f", "#edc948"];
/** Most prediction dots drawn (evenly thinned beyond). */
const MAX_DOTS = 3000;
/** Most points per hypothesis path (evenly thinned beyond). */
const MAX_PATH_POINTS = 6000;

export async function render(main, id) {
  crumbs([["Overview", "/"], ["Localization", null]]);
  const loc = await getJson(`/v1/localizations/${seg(id)}`);
  let map = null;
  try {
    map = await getJson(`/v1/maps/${seg(loc.map_id)}`);
  } catch (_) {
    // The map is gone (deleting a map deletes its localizations, so only in a race): keep its id.
  }
  const mapName = map ? map.name : shortId(loc.map_id);
  document.title = `seasonloc — localization ${shortId(loc.id)} on ${mapName}`;
  crumbs([["Overview", "/"], [mapName, `/maps/${loc.map_id}`], [`Localization ${shortId(loc.id)}`, null]]);

  // The similarity picture stored with the result (localizations made before it existed,
  // and methods without a similarity matrix, have none: the figure then shows the paths only).
  const pictureUrl = loc.picture ? await getImageUrl(`/v1/localizations/${seg(loc.id)}/picture`) : null;
  const byQuery = new Map(loc.predictions.map((p) => [p.query, p]));
  // Predictions with a calibrated p_correct (the flow method) are coloured and charted by it on
  // one fixed 0-1 scale; the others (the co-occurrence methods) by their own confidence.
  const calibrated = loc.predictions.length > 0 && loc.predictions.every((p) => typeof p.p_correct === "number");
  const score = calibrated ? (p) => p.p_correct : (p) => p.confidence;
  const scoreName = calibrated ? "p_correct" : "confidence";
  const colors = calibrated ? probabilityColors() : confidenceColors(loc.predictions.map(score));
  colors.score = score;
  colors.scoreName = scoreName;
  const figure = h("div", { class: "figure", id: "matrix-figure" });
  const confidence = h("div", { class: "figure", id: "confidence-chart" });
  const selected = h("div", { class: "selected", id: "selected-query", "aria-live": "polite" }, h("p", { class: "muted" }, "Click a query row in the figure or the chart to see its match."));
  const p = loc.params;
  const t = loc.timings;
  const total = t.load_references + t.features + t.similarity + t.solve;

  fill(
    main,
    h("h1", {}, `Localization ${shortId(loc.id)}`),
    h("p", { class: "subtitle" }, "on map ", h("a", { href: `/maps/${loc.map_id}`, id: "map-link" }, mapName), ` · ${fmtTime(loc.created_at_ms)}`),
    h(
      "div",
      { class: "stats" },
      stat("queries", fmtInt(loc.query_count)),
      stat("references", fmtInt(loc.reference_count)),
      stat("predicted", fmtInt(loc.predictions.length)),
      stat(loc.hypotheses.length === 1 ? "hypothesis" : "hypotheses", fmtInt(loc.hypotheses.length)),
      stat("total time", fmtSeconds(total)),
    ),
    section(
      pictureUrl ? "Similarity matrix with the route hypotheses" : "Queries × references with the route hypotheses",
      h(
        "p",
        { class: "muted" },
        "Each row is a query image, each column a reference image" +
          (pictureUrl ? `, bright where they look alike (normalised similarity ${fmtNum(loc.picture.lo)} or less is black, ${fmtNum(loc.picture.hi)} or more white${blockText(loc)})` : "") +
          ". Lines are the route hypotheses (rank 1 thickest), dots the predictions coloured by " + scoreName + ".",
      ),
      figure,
      h("div", { class: "legend-row", id: "figure-legend" }),
      selected,
    ),
    section(calibrated ? "p_correct along the route" : "Confidence along the route", confidence),
    h(
      "div",
      { class: "columns" },
      section(
        "Parameters",
        facts([
          ...(p.method ? [["Method", p.method]] : []),
          ["Fan-out K", p.fan_out],
          ["Hidden cost W", `${fmtNum(p.hidden_cost, 4)} (${p.hidden_cost_mode})`],
          ["Flows F", `${p.flows}${p.flows > 1 ? (p.exact ? " (exact)" : " (greedy)") : ""}`],
          ["Horizontal edges", p.horizontal ? "on" : "off"],
          ["Column normalisation", p.normalize ? "on" : "off"],
          ["Stop at hidden fraction", p.stop_hidden_fraction === null ? "—" : fmtNum(p.stop_hidden_fraction)],
          ["Total cost", fmtNum(loc.total_cost, 6)],
        ]),
      ),
      section("Timings", timings(t, total)),
    ),
  );

  sizeBars(main);

  let current = null;
  function select(q) {
    current = q;
    showSelection(selected, loc, byQuery, q);
    drawMarkers(q);
  }
  let markers = () => {};
  function drawMarkers(q) {
    markers(q);
  }

  function draw() {
    const w = widthOf(figure);
    const m1 = drawMatrix(figure, loc, colors, w, select, pictureUrl);
    const m2 = drawConfidence(confidence, loc, byQuery, colors, w, select);
    markers = (q) => {
      m1(q);
      m2(q);
    };
    fill(document.getElementById("figure-legend"), legend(colors, scoreName, Math.min(w, 460)));
    if (current !== null) drawMarkers(current);
  }
  draw();
  let resized = null;
  window.addEventListener("resize", () => {
    clearTimeout(resized);
    resized = setTimeout(draw, 150);
  });
  return null;
}

function timings(t, total) {
  const rows = [
    ["Reading references", t.load_references],
    ["Query features", t.features],
    ["Similarity", t.similarity],
    ["Solver and confidences", t.solve],
  ];
  return h(
    "div",
    { class: "timings" },
    rows.map(([label, v]) =>
      h(
        "div",
        { class: "timing" },
        h("span", { class: "timing-label" }, label),
        h("span", { class: "timing-bar" }, h("span", { class: "timing-fill", "data-share": total > 0 ? v / total : 0 })),
        h("span", { class: "timing-value" }, fmtSeconds(v)),
      ),
    ),
    h("div", { class: "timing total" }, h("span", { class: "timing-label" }, "Total"), h("span"), h("span", { class: "timing-value" }, fmtSeconds(total))),
  );
}

/** Sizes the timing bars (CSSOM, allowed by the page's style policy). */
function sizeBars(root) {
  for (const el of root.querySelectorAll(".timing-fill")) {
    el.style.width = `${(100 * Number(el.dataset.share)).toFixed(1)}%`;
  }
}

/** Draws the queries × references figure into `el`; returns a function that marks a query. */
function drawMatrix(el, loc, colors, width, select, pictureUrl) {
  const Q = Math.max(1, loc.query_count);
  const D = Math.max(1, loc.reference_count);
  const height = Math.round(Math.min(560, Math.max(260, ((width - 72) * Q) / D + 52)));
  const c = chart({
    width,
    height,
    x: [0, D],
    y: [0, Q],
    yDown: true,
    xLabel: "reference image",
    yLabel: "query image",
    title: `${fmtInt(Q)} queries × ${fmtInt(D)} references with ${loc.hypotheses.length} route hypotheses`,
  });
  c.svg.classList.add("matrix");
  if (pictureUrl) {
    c.plot.append(s("image", { class: "matrix-picture", href: pictureUrl, x: 0, y: 0, width: c.w, height: c.h, preserveAspectRatio: "none" }));
  }
  const cx = (j) => c.sx(j + 0.5);
  const cy = (i) => c.sy(i + 0.5);
  const paths = s("g", { class: "hypotheses" });
  // Lowest rank last, so the best hypothesis is on top.
  for (const hyp of [...loc.hypotheses].sort((a, b) => b.rank - a.rank)) {
    const pts = [];
    for (const row of hyp.rows) {
      if (!row.matches.length) {
        pts.push(null);
        continue;
      }
      for (const m of row.matches) pts.push([cx(m.ref), cy(row.query)]);
    }
    const d = pathData(thin(pts, MAX_PATH_POINTS));
    const color = RANK_COLORS[(hyp.rank - 1) % RANK_COLORS.length];
    const width = hyp.rank === 1 ? 3 : 2;
    paths.append(
      s("path", { class: "hypothesis-casing", d, "stroke-width": width + 2 }),
      s("path", { class: "hypothesis-path", d, stroke: color, "stroke-width": width, "data-rank": hyp.rank }, s("title", {}, `hypothesis ${hyp.rank}, cost ${fmtNum(hyp.cost, 6)}`)),
    );
  }
  const cell = Math.min(c.w / D, c.h / Q);
  const r = Math.max(2, Math.min(5, cell * 0.45));
  const dots = s("g", { class: "predictions" });
  for (const p of thin(loc.predictions, MAX_DOTS)) {
    dots.append(s("circle", { class: "prediction-dot", cx: cx(p.ref), cy: cy(p.query), r, fill: colors(colors.score(p)), "data-query": p.query }));
  }
  const marks = s("g", { class: "marks" });
  c.plot.append(paths, dots, marks);
  c.svg.addEventListener("click", (ev) => {
    const box = c.svg.getBoundingClientRect();
    const y = ev.clientY - box.top - c.m.top;
    if (y < 0 || y > c.h) return;
    select(Math.max(0, Math.min(Q - 1, Math.floor(c.sy.invert(y)))));
  });
  fill(el, c.svg);
  return (q) => {
    marks.replaceChildren(s("rect", { class: "query-row", x: 0, y: c.sy(q), width: c.w, height: Math.max(1.5, c.sy(q + 1) - c.sy(q)) }));
  };
}

/** Draws the confidence-along-the-route chart; returns a function that marks a query. */
function drawConfidence(el, loc, byQuery, colors, width, select) {
  const Q = Math.max(1, loc.query_count);
  const c = chart({
    width,
    height: 220,
    x: [0, Q],
    y: colors.fixed ? [0, 1] : confidenceRange(loc.predictions.map(colors.score)),
    xLabel: "query image",
    yLabel: colors.scoreName,
    title: `${colors.scoreName === "p_correct" ? "p_correct" : "Confidence"} of each query's prediction along the route`,
  });
  const g = s("g", { class: "confidence" });
  const colW = c.w / Q;
  const pts = [];
  for (let q = 0; q < Q; q++) {
    const p = byQuery.get(q);
    pts.push(p ? [c.sx(q + 0.5), c.sy(colors.score(p))] : null);
    if (!p) {
      g.append(s("rect", { class: "unmatched", x: c.sx(q), y: c.h - 4, width: Math.max(1, colW - 0.5), height: 4 }, s("title", {}, `query ${q}: no prediction`)));
    }
  }
  g.append(s("path", { class: "confidence-line", d: pathData(thin(pts, MAX_PATH_POINTS)) }));
  const r = Math.max(1.5, Math.min(3.5, colW * 0.4));
  for (const p of thin(loc.predictions, MAX_DOTS)) {
    const tip = typeof p.p_correct === "number" ? `query ${p.query}: p_correct ${fmtNum(p.p_correct, 2)} (confidence ${fmtConf(p.confidence)})` : `query ${p.query}: confidence ${fmtConf(p.confidence)}`;
    g.append(s("circle", { class: "confidence-dot", cx: c.sx(p.query + 0.5), cy: c.sy(colors.score(p)), r, fill: colors(colors.score(p)) }, s("title", {}, tip)));
  }
  const marks = s("g", { class: "marks" });
  c.plot.append(g, marks);
  c.svg.classList.add("clickable");
  c.svg.addEventListener("click", (ev) => {
    const box = c.svg.getBoundingClientRect();
    const x = ev.clientX - box.left - c.m.left;
    if (x < 0 || x > c.w) return;
    select(Math.max(0, Math.min(Q - 1, Math.floor(c.sx.invert(x)))));
  });
  fill(el, c.svg);
  return (q) => {
    marks.replaceChildren(s("rect", { class: "query-col", x: c.sx(q), y: 0, width: Math.max(1.5, colW), height: c.h }));
  };
}

/** The panel of the clicked query: its prediction and every hypothesis' match on that row. */
function showSelection(el, loc, byQuery, q) {
  const p = byQuery.get(q);
  const rows = loc.hypotheses.map((hyp) => {
    const row = hyp.rows.find((r) => r.query === q);
    const what = !row || !row.matches.length ? "hidden (no match)" : row.matches.map((m) => `reference ${m.ref} (ĉ ${fmtNum(m.similarity)})`).join(", ");
    return [`Hypothesis ${hyp.rank}`, what];
  });
  fill(
    el,
    h("h3", {}, `Query ${q}`),
    p
      ? h("p", { class: "match" }, "Matched to ", h("strong", { class: "matched-ref" }, `reference ${p.ref}`), typeof p.p_correct === "number" ? ` with p_correct ${fmtNum(p.p_correct, 2)} (the probability that it is within ${loc.params.tolerance || 1} image${(loc.params.tolerance || 1) === 1 ? "" : "s"} of the true place; confidence ${fmtConf(p.confidence)}).` : ` with confidence ${fmtConf(p.confidence)}.`)
      : h("p", { class: "match" }, "No prediction: this query is off the map in every hypothesis."),
    facts(rows),
    p ? h("div", { class: "selected-thumb" }, thumbnail(loc.map_id, p.ref, `reference ${p.ref} (matched)`)) : null,
  );
}

/** How much of the matrix one picture pixel covers, when it is more than one cell. */
function blockText(loc) {
  const br = Math.ceil(loc.query_count / loc.picture.rows);
  const bc = Math.ceil(loc.reference_count / loc.picture.cols);
  return br === 1 && bc === 1 ? "" : `; each pixel shows the largest value of up to ${br} × ${bc} cells`;
}
