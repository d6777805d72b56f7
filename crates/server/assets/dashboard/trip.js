// `/trips/{id}`: where a vehicle is now. The reference index against the frame (the route as
// localized so far), the trip's status and the latest frame's (localized / uncertain / off_map /
// lost), the calibrated p_correct of recent frames on one fixed 0-1 scale, and the reference
// matched now. Polls the trip every 2 s while it is open and redraws
// only when a batch arrived; stops once the trip is closed.

import { getJson, seg } from "./api.js";
import { chart, legend, pathData, probabilityColors, s, thin, widthOf } from "./plot.js";
import { thumbnail } from "./thumbs.js";
import { crumbs, facts, fill, fmtConf, fmtInt, fmtNum, fmtTime, h, section, shortId, stat, statusBadge } from "./ui.js";

/** Poll period while the trip is open. */
const POLL_MS = 2000;
/** What each frame status means for the vehicle (the page's words for the API's). */
const MEANING = {
  localized: "localized: act on it",
  uncertain: "uncertain: a guess, not to be acted on",
  off_map: "off the map: not on the mapped route",
  lost: "lost: not enough evidence yet, or relocalizing",
};

/** Frames in the recent-p_correct chart. */
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
  const frameStatus = h("span", { id: "frame-status" });
  const stats = h("div", { class: "stats", id: "trip-stats" });
  const now = h("div", { class: "now", id: "trip-now" });
  const position = h("div", { class: "figure", id: "position-chart" });
  const recent = h("div", { class: "figure", id: "recent-confidence" });
  const legendRow = h("div", { class: "legend-row" });
  const params = h("div");
  fill(
    main,
    h("h1", {}, `Trip ${shortId(trip.id)} `, status, " ", frameStatus),
    h("p", { class: "subtitle" }, "on map ", h("a", { href: `/maps/${trip.map_id}`, id: "map-link" }, mapName), ` · opened ${fmtTime(trip.created_at_ms)}`),
    stats,
    section("Now", now),
    section("Position along the route", position, legendRow),
    h("div", { class: "columns" }, section(`p_correct of the last ${RECENT} frames`, recent), section("Parameters", params)),
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
    const colors = probabilityColors();
    const latestStatus = latest ? latest.status : null;
    fill(status, statusBadge(t.status, t.closed_at_ms !== null));
    fill(frameStatus, latestStatus ? h("span", { class: `badge status-${latestStatus}`, title: MEANING[latestStatus] || latestStatus, "data-status": latestStatus }, `frame: ${latestStatus.replace("_", " ")}`) : null);
    fill(
      stats,
      stat("frames", fmtInt(t.frame_count), "frame-count"),
      stat("reference now", latest && latest.ref !== null ? fmtInt(latest.ref) : "off map", "current-ref"),
      stat("p_correct now", latest && latest.ref !== null ? fmtNum(latest.p_correct, 2) : "—", "current-p-correct"),
      stat("confidence now", latest && latest.ref !== null ? fmtConf(latest.confidence) : "—", "current-confidence"),
      stat("map references", fmtInt(t.reference_count)),
    );
    const where = latest && latest.ref !== null ? [h("strong", {}, `reference ${fmtInt(latest.ref)}`), ` of ${fmtInt(t.reference_count)} (p_correct ${fmtNum(latest.p_correct, 2)}, the probability that it is within ${t.params.tolerance} image${t.params.tolerance === 1 ? "" : "s"} of the true place)`] : [];
    fill(
      now,
      !latest
        ? h("p", { class: "muted" }, "No frame yet: the page updates by itself when the vehicle posts its first batch.")
        : latestStatus === "off_map"
          ? h("p", {}, `Frame ${fmtInt(latest.frame)} is off the map: the evidence says the vehicle is not on the mapped route.`)
          : latestStatus === "localized"
            ? h("p", {}, `Frame ${fmtInt(latest.frame)} is localized at `, ...where, ".")
            : latestStatus === "uncertain"
              ? h("p", {}, `Frame ${fmtInt(latest.frame)} is uncertain: its best guess is `, ...where, `, below the trip's threshold of ${fmtNum(t.params.threshold, 2)}; not to be acted on.`)
              : h("p", {}, `Frame ${fmtInt(latest.frame)} is lost: not enough evidence yet (the trip's first frames, or the path is relocalizing)` + (latest.ref !== null ? "; its best guess is " : "."), ...(latest.ref !== null ? [...where, "."] : [])),
      t.status === "relocalized" ? h("p", {}, "The last batch relocalized: the path re-entered the map elsewhere.") : null,
      t.closed_at_ms !== null ? h("p", { class: "muted" }, `Closed ${fmtTime(t.closed_at_ms)}.`) : null,
      nowThumb(latest),
    );
    const w = widthOf(position);
    fill(position, positionChart(t, est, colors, w));
    fill(legendRow, legend(colors, "p_correct", Math.min(w, 460)), h("span", { class: "legend-note" }, "▮ red ticks: off the map · grey ticks: lost"));
    fill(recent, recentChart(est, colors, widthOf(recent), t.params.threshold));
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
        ["Tolerance", `${p.tolerance} image${p.tolerance === 1 ? "" : "s"} (what p_correct is the probability of)`],
        ["Localized from", `p_correct ≥ ${fmtNum(p.threshold, 2)}`],
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
  const est = t.estimates || [];
  const latest = est.length ? est[est.length - 1].status : "";
  return `${t.frame_count}|${t.status}|${latest}|${t.closed_at_ms}`;
}

/** Reference index against frame: one dot per frame with a reference, coloured by p_correct. */
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
      g.append(s("circle", { class: `position-dot dot-${e.status}`, cx: c.sx(e.frame + 0.5), cy: c.sy(e.ref + 0.5), r, fill: colors(e.p_correct) }));
    }
  }
  const latest = est[est.length - 1];
  if (latest && latest.ref !== null) {
    g.append(s("circle", { class: "current", cx: c.sx(latest.frame + 0.5), cy: c.sy(latest.ref + 0.5), r: r + 4 }, s("title", {}, `frame ${latest.frame}: reference ${latest.ref}`)));
  }
  c.plot.append(g);
  return c.svg;
}

/** The last RECENT frames' p_correct on 0-1, with the trip's threshold (off-map frames as red ticks, lost ones as grey). */
function recentChart(est, colors, width, threshold) {
  const last = est.slice(-RECENT);
  const first = last.length ? last[0].frame : 0;
  const c = chart({
    width,
    height: 200,
    x: [first, first + RECENT],
    y: [0, 1],
    xLabel: "frame",
    yLabel: "p_correct",
    title: `p_correct of the last ${RECENT} frames`,
  });
  const bw = c.w / RECENT;
  const g = s("g", { class: "confidence" });
  g.append(s("line", { class: "threshold-line", x1: 0, x2: c.w, y1: c.sy(threshold), y2: c.sy(threshold) }, s("title", {}, `localized from p_correct ${threshold}`)));
  g.append(s("path", { class: "confidence-line", d: pathData(last.map((e) => (e.ref === null ? null : [c.sx(e.frame + 0.5), c.sy(e.p_correct)]))) }));
  for (const e of last) {
    if (e.ref === null) {
      g.append(s("rect", { class: e.status === "lost" ? "lost-tick" : "off-map", x: c.sx(e.frame), y: c.h - 4, width: Math.max(1, bw - 1), height: 4 }, s("title", {}, `frame ${e.frame}: ${MEANING[e.status] || e.status}`)));
    } else {
      g.append(s("circle", { class: `confidence-dot dot-${e.status}`, cx: c.sx(e.frame + 0.5), cy: c.sy(e.p_correct), r: Math.max(2, Math.min(4, bw * 0.35)), fill: colors(e.p_correct) }, s("title", {}, `frame ${e.frame}: p_correct ${fmtNum(e.p_correct, 2)}, ${MEANING[e.status] || e.status} (confidence ${fmtConf(e.confidence)})`)));
    }
  }
  c.plot.append(g);
  return c.svg;
}
