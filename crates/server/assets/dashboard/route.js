// The map page's route: a strip of reference thumbnails spread along the route, and the route
// itself on a plain x/y plot of the images' latitude/longitude (when the images carry GPS
// metadata, read page by page from `GET /v1/maps/{id}/images`). Clicking the plot shows the
// nearest image's thumbnail and metadata.

import { getJson, mapLimited, seg } from "./api.js";
import { chart, pathData, s, thin, widthOf } from "./plot.js";
import { facts, fill, fmtInt, h } from "./ui.js";
import { spread, thumbnail } from "./thumbs.js";

/** Thumbnails in the strip. */
const STRIP = 16;
/** Metadata entries per request (the route's maximum page). */
const PAGE = 1000;
/** Most route points drawn (evenly thinned beyond). */
const MAX_POINTS = 5000;

/** The strip of thumbnails along the route. */
export function strip(map) {
  if (!map.image_count) return h("p", { class: "muted" }, "No reference images yet.");
  return h(
    "div",
    { class: "strip", id: "thumb-strip" },
    spread(map.image_count, STRIP).map((i) => thumbnail(map.id, i)),
  );
}

/** Every image's metadata, in route order (pages fetched four at a time). */
async function metadata(map) {
  const starts = [];
  for (let from = 0; from < map.image_count; from += PAGE) starts.push(from);
  const pages = await mapLimited(starts, 4, (from) =>
    getJson(`/v1/maps/${seg(map.id)}/images?from=${from}&limit=${PAGE}`),
  );
  return pages.flatMap((p) => p.items);
}

/** The x/y plot of the route from GPS metadata, drawn into `el` (a message when there is none). */
export async function gpsRoute(el, map) {
  if (!map.image_count) {
    fill(el, h("p", { class: "muted" }, "No reference images yet."));
    return;
  }
  const items = await metadata(map);
  const pts = items.filter((m) => Number.isFinite(m.latitude) && Number.isFinite(m.longitude));
  if (pts.length < 2) {
    fill(
      el,
      h(
        "p",
        { class: "muted", id: "no-gps" },
        `No GPS route: ${fmtInt(pts.length)} of ${fmtInt(items.length)} images carry latitude and longitude (send them as metadata with the images).`,
      ),
    );
    return;
  }
  const draw = () => fill(el, plot(map, pts, widthOf(el)));
  draw();
  let resized = null;
  window.addEventListener("resize", () => {
    clearTimeout(resized);
    resized = setTimeout(draw, 150);
  });
}

function plot(map, pts, width) {
  const lats = pts.map((p) => p.latitude);
  const lons = pts.map((p) => p.longitude);
  let [y0, y1] = [Math.min(...lats), Math.max(...lats)];
  let [x0, x1] = [Math.min(...lons), Math.max(...lons)];
  const k = Math.cos((((y0 + y1) / 2) * Math.PI) / 180) || 1;
  const m = { top: 12, right: 16, bottom: 40, left: 72 };
  const w = width - m.left - m.right;
  const height = Math.round(Math.min(520, Math.max(260, w * 0.6)));
  const hh = height - m.top - m.bottom;
  // Equal scale on both axes (a metre east looks as long as a metre north), with a margin.
  let dx = Math.max(x1 - x0, 1e-6);
  let dy = Math.max(y1 - y0, 1e-6);
  if ((dx * k) / dy > w / hh) dy = (dx * k * hh) / w;
  else dx = (dy * w) / (hh * k);
  const cx = (x0 + x1) / 2;
  const cy = (y0 + y1) / 2;
  [x0, x1] = [cx - 0.55 * dx, cx + 0.55 * dx];
  [y0, y1] = [cy - 0.55 * dy, cy + 0.55 * dy];
  const c = chart({ width, height, x: [x0, x1], y: [y0, y1], xLabel: "longitude (°)", yLabel: "latitude (°)", margin: m, title: `Route of ${fmtInt(pts.length)} images from their GPS metadata` });
  c.svg.classList.add("gps", "clickable");
  const xy = (p) => [c.sx(p.longitude), c.sy(p.latitude)];
  const g = s("g", { class: "route" });
  g.append(s("path", { class: "gps-route", d: pathData(thin(pts, MAX_POINTS).map(xy)) }));
  const byIndex = new Map(pts.map((p) => [p.index, p]));
  for (const i of spread(map.image_count, STRIP)) {
    const p = byIndex.get(i);
    if (p) g.append(s("circle", { class: "gps-mark", cx: xy(p)[0], cy: xy(p)[1], r: 3.5 }, s("title", {}, `reference ${i}`)));
  }
  const [sx0, sy0] = xy(pts[0]);
  const [sx1, sy1] = xy(pts[pts.length - 1]);
  g.append(
    s("circle", { class: "gps-start", cx: sx0, cy: sy0, r: 6 }, s("title", {}, `start: reference ${pts[0].index}`)),
    s("circle", { class: "gps-end", cx: sx1, cy: sy1, r: 6 }, s("title", {}, `end: reference ${pts[pts.length - 1].index}`)),
  );
  const picked = s("g", { class: "marks" });
  c.plot.append(g, picked);
  const panel = h("div", { class: "picked", id: "gps-picked" }, h("p", { class: "muted" }, "Click the route to see the nearest reference image."));
  c.svg.addEventListener("click", (ev) => {
    const box = c.svg.getBoundingClientRect();
    const px = ev.clientX - box.left - c.m.left;
    const py = ev.clientY - box.top - c.m.top;
    let best = null;
    let dist = Infinity;
    for (const p of pts) {
      const [x, y] = xy(p);
      const d = (x - px) ** 2 + (y - py) ** 2;
      if (d < dist) [best, dist] = [p, d];
    }
    const [bx, by] = xy(best);
    picked.replaceChildren(s("circle", { class: "current", cx: bx, cy: by, r: 8 }));
    fill(
      panel,
      thumbnail(map.id, best.index),
      facts([
        ["Reference", fmtInt(best.index)],
        ["Latitude, longitude", `${best.latitude.toFixed(6)}, ${best.longitude.toFixed(6)}`],
        ...(best.timestamp ? [["Time", best.timestamp]] : []),
        ...(best.label ? [["Label", best.label]] : []),
      ]),
    );
  });
  return h("div", { class: "gps-wrap" }, c.svg, panel);
}
