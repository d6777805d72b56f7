// `/trips/{id}`: where a vehicle is now. The reference index against the frame (the route as
// localized so far), the status (localized / lost / relocalized), the confidence of recent
// frames and the reference matched now. Polls the trip every 2 s while it is open and redraws
// only when a batch arrived; stops once the trip is closed.

import { getJson, seg } from "./api.js";
import { chart, confidenceColors, confidenceRange, legend, pathData, s, thin, widthOf } from "./plot.js";
import { thumbnail } from "./thumbs.js";
import { crumbs, facts, fill, fmtConf, fmtInt, fmtNum, fmtTime, h, section, shortId, stat, statusBadge } from "./ui.js";

/** Poll period while the trip is open. */
const POLL_MS = 2000;
/** Frames in the recent-confidence chart. */
const RECENT = 60;
/** Most position dots drawn (evenly thinned beyond; the latest frames are always drawn). */
const MAX_DOTS = 4000;

export async function render(main, id) {
  crumbs([["Overview", "/"], ["Trip", null]]);
  let trip = await getJson(`/v1/trips/${seg(id)}`);
  let map = null;
  try {
    map = await getJson(`/v1/maps/${seg(trip.map_id)}`);
  } catch (_) {
    // A deleted map: show its id.
  }
  const mapName = map ? map.name : shortId(trip.map_id);
  document.title = `seasonloc — trip ${shortId(trip.id)} on ${mapName}`;
  crumbs([["Overview", "/"], [mapName, `/maps/${trip.map_id}`], [`Trip ${shortId(trip.id)}`, null]]);

  const status = h("span", { id: "trip-status" });
  const stats = h("div", { class: "stats", id: "trip-stats" });
  const now = h("div", { class: "now", id: "trip-now" });
  const position = h("div", { class: "figure", id: "position-chart" });
  const recent = h("div", { class: "figure", id: "recent-confidence" });
  const legendRow = h("div", { class: "legend-row" });
  const params = h("div");
  fill(
    main,
    h("h1", {}, `Trip ${shortId(trip.id)} `, status),
    h("p", { class: "subtitle" }, "on map ", h("a", { href: `/maps/${trip.map_id}`, id: "map-link" }, mapName), ` · opened ${fmtTime(trip.created_at_ms)}`),
    stats,
    section("Now", now),
    section("Position along the route", position, legendRow),
    h("div", { class: "columns" }, section(`Confidence of the last ${RECENT} frames`, recent), section("Parameters", params)),
  );

  // The thumbnail of the reference matched now, kept while the reference does not change.
  let thumbOf = null;
  let thumbBox = null;
  function nowThumb(latest) {
    if (!latest || latest.ref === null) return null;
    if (thumbOf !== latest.ref) {
      thumbOf = latest.ref;
      thumbBox = thumbnail(trip.map_id, latest.ref, `reference ${fmtInt(latest.ref)} (matched now)`);
    }
    return h("div", { class: "now-thumb" }, thumbBox);
  }

  let shown = "";
  function draw() {
    const t = trip;
    const est = t.estimates || [];
    const latest = est.length ? est[est.length - 1] : null;
    const colors = confidenceColors(est.filter((e) => e.ref !== null).map((e) => e.confidence));
    fill(status, statusBadge(t.status, t.closed_at_ms !== null));
    fill(
      stats,
      stat("frames", fmtInt(t.frame_count), "frame-count"),
      stat("reference now", latest && latest.ref !== null ? fmtInt(latest.ref) : "off map", "current-ref"),
      stat("confidence now", latest && latest.ref !== null ? fmtConf(latest.confidence) : "—", "current-confidence"),
      stat("map references", fmtInt(t.reference_count)),
    );
    fill(
      now,
      !latest
        ? h("p", { class: "muted" }, "No frame yet: the page updates by itself when the vehicle posts its first batch.")
        : latest.ref === null
          ? h("p", {}, `Frame ${fmtInt(latest.frame)} is off the map (no reference matches it).`)
          : t.status === "lost"
            ? h("p", {}, `Lost: frame ${fmtInt(latest.frame)} has no local support; its best guess is `, h("strong", {}, `reference ${fmtInt(latest.ref)}`), ` of ${fmtInt(t.reference_count)} (confidence ${fmtConf(latest.confidence)}).`)
            : h("p", {}, `Frame ${fmtInt(latest.frame)} is at `, h("strong", {}, `reference ${fmtInt(latest.ref)}`), ` of ${fmtInt(t.reference_count)}, confidence ${fmtConf(latest.confidence)}` + (t.status === "relocalized" ? " (relocalized: the vehicle re-entered the map elsewhere)." : ".")),
      t.closed_at_ms !== null ? h("p", { class: "muted" }, `Closed ${fmtTime(t.closed_at_ms)}.`) : null,
      nowThumb(latest),
    );
    const w = widthOf(position);
    fill(position, positionChart(t, est, colors, w));
    fill(legendRow, legend(colors, "confidence", Math.min(w, 460)), h("span", { class: "legend-note" }, "▮ red ticks: frames off the map"));
    fill(recent, recentChart(est, colors, widthOf(recent)));
    const p = t.params;
    fill(
      params,
      facts([
        ["Fan-out K", p.fan_out],
        ["Hidden cost W", p.hidden_cost === null ? "auto (from the first batch)" : fmtNum(p.hidden_cost, 4)],
        ["Horizontal edges", p.horizontal ? "on" : "off"],
        ["Lag window", `${p.lag} frames`],
        ["Relocalization cost R", p.relocalization_cost === null ? "off" : fmtNum(p.relocalization_cost)],
        ["Prior weight", `${fmtNum(p.prior_weight)} frames`],
        ["Online normalisation", p.normalize ? "on" : "off"],
      ]),
    );
    shown = signature(t);
  }
  draw();

  let resized = null;
  window.addEventListener("resize", () => {
    clearTimeout(resized);
    resized = setTimeout(draw, 150);
  });

  // Polls ask only for the frames that can have changed: those from the start of the lag
  // window (whose estimates a batch may revise) on; the rest are kept from earlier answers.
  async function refresh() {
    const known = (trip.estimates || []).length;
    const since = Math.max(0, known - trip.params.lag);
    const next = await getJson(`/v1/trips/${seg(id)}?since=${since}`);
    next.estimates = (trip.estimates || []).slice(0, since).concat(next.estimates || []);
    trip = next;
    if (signature(next) !== shown) draw();
    return next.closed_at_ms === null;
  }
  if (trip.closed_at_ms !== null) return null;
  return { refresh, interval: POLL_MS, doneText: "trip closed" };
}

function signature(t) {
  return `${t.frame_count}|${t.status}|${t.closed_at_ms}`;
}

/** Reference index against frame: one dot per frame, coloured by confidence. */
function positionChart(t, est, colors, width) {
  const F = Math.max(10, t.frame_count);
  const D = Math.max(1, t.reference_count);
  const c = chart({
    width,
    height: 320,
    x: [0, F],
    y: [0, D],
    xLabel: "frame",
    yLabel: "reference image",
    title: `Reference index against frame for ${fmtInt(t.frame_count)} frames`,
  });
  const tail = est.slice(-200);
  const head = thin(est.slice(0, Math.max(0, est.length - tail.length)), MAX_DOTS);
  const on = [...head, ...tail];
  const path = on.map((e) => (e.ref === null ? null : [c.sx(e.frame + 0.5), c.sy(e.ref + 0.5)]));
  const g = s("g", { class: "positions" });
  g.append(s("path", { class: "trip-path", d: pathData(path) }));
  const r = Math.max(1.5, Math.min(4, (c.w / F) * 0.6));
  for (const e of on) {
    if (e.ref === null) {
      g.append(s("rect", { class: "off-map", x: c.sx(e.frame), y: c.h - 6, width: Math.max(1, c.w / F), height: 6 }));
    } else {
      g.append(s("circle", { class: "position-dot", cx: c.sx(e.frame + 0.5), cy: c.sy(e.ref + 0.5), r, fill: colors(e.confidence) }));
    }
  }
  const latest = est[est.length - 1];
  if (latest && latest.ref !== null) {
    g.append(s("circle", { class: "current", cx: c.sx(latest.frame + 0.5), cy: c.sy(latest.ref + 0.5), r: r + 4 }, s("title", {}, `frame ${latest.frame}: reference ${latest.ref}`)));
  }
  c.plot.append(g);
  return c.svg;
}

/** The last RECENT frames' confidences (off-map frames as red ticks). */
function recentChart(est, colors, width) {
  const last = est.slice(-RECENT);
  const first = last.length ? last[0].frame : 0;
  const on = last.filter((e) => e.ref !== null);
  const c = chart({
    width,
    height: 200,
    x: [first, first + RECENT],
    y: confidenceRange(on.map((e) => e.confidence)),
    xLabel: "frame",
    yLabel: "confidence",
    title: `Confidence of the last ${RECENT} frames`,
  });
  const bw = c.w / RECENT;
  const g = s("g", { class: "confidence" });
  g.append(s("path", { class: "confidence-line", d: pathData(last.map((e) => (e.ref === null ? null : [c.sx(e.frame + 0.5), c.sy(e.confidence)]))) }));
  for (const e of last) {
    if (e.ref === null) {
      g.append(s("rect", { class: "off-map", x: c.sx(e.frame), y: c.h - 4, width: Math.max(1, bw - 1), height: 4 }, s("title", {}, `frame ${e.frame}: off the map`)));
    } else {
      g.append(s("circle", { class: "confidence-dot", cx: c.sx(e.frame + 0.5), cy: c.sy(e.confidence), r: Math.max(2, Math.min(4, bw * 0.35)), fill: colors(e.confidence) }, s("title", {}, `frame ${e.frame}: confidence ${fmtConf(e.confidence)}`)));
    }
  }
  c.plot.append(g);
  return c.svg;
}
