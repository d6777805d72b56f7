// `/maps/{id}`: one map: its settings, its trips and its localizations.

import { getJson, listPages, seg } from "./api.js";
import { gpsRoute, strip } from "./route.js";
import { crumbs, describeDescriptor, facts, fill, fmtInt, fmtNum, fmtTime, h, section, shortId, stat, statusBadge, table } from "./ui.js";

/** Most trips and localizations listed on the page (newest first). */
const LISTED = 100;

export async function render(main, id) {
  crumbs([["Overview", "/"], ["Map", null]]);
  const map = await getJson(`/v1/maps/${seg(id)}`);
  document.title = `seasonloc — ${map.name}`;
  crumbs([["Overview", "/"], [map.name, null]]);
  const canTrip = map.descriptor.kind === "hog" || map.descriptor.kind === "cnn";
  const [trips, locs] = await Promise.all([
    canTrip ? listPages(`/v1/maps/${seg(id)}/trips`, LISTED) : Promise.resolve({ items: [], more: false }),
    listPages(`/v1/localizations?map=${seg(id)}`, LISTED),
  ]);
  const open = trips.items.filter((t) => t.closed_at_ms === null).length;
  const gps = h("div", { class: "figure", id: "gps-route" }, h("p", { class: "muted" }, "Loading the images' GPS metadata…"));
  const more = (list, what) => (list.more ? h("p", { class: "muted" }, `Showing the newest ${LISTED} ${what}.`) : null);

  fill(
    main,
    h("h1", { id: "map-name" }, map.name),
    h(
      "div",
      { class: "stats" },
      stat("reference images", fmtInt(map.image_count), "image-count"),
      stat("descriptor length", map.descriptor_dim ? fmtInt(map.descriptor_dim) : "—"),
      stat(open === 1 ? "open trip" : "open trips", fmtInt(open)),
      stat(locs.items.length === 1 ? "localization" : "localizations", fmtInt(locs.items.length) + (locs.more ? "+" : "")),
    ),
    section("Along the route", strip(map)),
    section("Route", gps),
    section(
      "Settings",
      facts([
        ["Id", h("code", {}, map.id)],
        ["Kind", map.descriptor.kind],
        ["Descriptor", describeDescriptor(map.descriptor)],
        ["Created", fmtTime(map.created_at_ms)],
      ]),
    ),
    section(
      "Trips",
      canTrip
        ? table(
            [
              { label: "Trip", cell: (t) => h("a", { href: `/trips/${t.id}`, title: t.id }, shortId(t.id)) },
              { label: "Status", cell: (t) => statusBadge(t.status, t.closed_at_ms !== null) },
              { label: "Frames", cls: "num", cell: (t) => fmtInt(t.frame_count) },
              { label: "References", cls: "num", cell: (t) => fmtInt(t.reference_count) },
              { label: "Opened", cell: (t) => fmtTime(t.created_at_ms) },
              { label: "Closed", cell: (t) => fmtTime(t.closed_at_ms) },
            ],
            trips.items,
            "No trip on this map yet.",
          )
        : h("p", { class: "muted" }, `A ${map.descriptor.kind} map has no trips.`),
      more(trips, "trips"),
    ),
    section(
      "Localizations",
      table(
        [
          { label: "Localization", cell: (l) => h("a", { href: `/localizations/${l.id}`, title: l.id }, shortId(l.id)) },
          { label: "Queries", cls: "num", cell: (l) => fmtInt(l.query_count) },
          { label: "References", cls: "num", cell: (l) => fmtInt(l.reference_count) },
          { label: "Predicted", cls: "num", cell: (l) => fmtInt(l.predictions.length) },
          { label: "Hypotheses", cls: "num", cell: (l) => fmtInt(l.hypotheses.length) },
          { label: "W", cls: "num", cell: (l) => fmtNum(l.params.hidden_cost) },
          { label: "Created", cell: (l) => fmtTime(l.created_at_ms) },
        ],
        locs.items,
        "No localization against this map yet.",
      ),
      more(locs, "localizations"),
    ),
  );
  await gpsRoute(gps, map);
  return null;
}
