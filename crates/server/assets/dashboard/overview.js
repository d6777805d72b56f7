// `/`: every map, the trips that are open now, and the latest localizations; refreshed every
// 10 s. Trips are listed per map (the API lists trips by map), only for maps that can have
// trips (HOG and CNN maps with images).

import { getJson, listPages, mapLimited, seg } from "./api.js";
import { crumbs, describeDescriptor, fill, fmtInt, fmtNum, fmtTime, h, section, shortId, statusBadge, table } from "./ui.js";

/** Trips read per map for the "open now" list (newest first). */
const TRIPS_PER_MAP = 200;
/** Latest localizations shown. */
const LATEST = 10;

export async function render(main) {
  document.title = "seasonloc — overview";
  crumbs([["Overview", null]]);
  const maps = h("div", { id: "maps" });
  const trips = h("div", { id: "open-trips" });
  const locs = h("div", { id: "latest-localizations" });
  fill(
    main,
    h("h1", {}, "Overview"),
    section("Maps", maps),
    section("Open trips", trips),
    section("Latest localizations", locs),
  );

  async function refresh() {
    const [mapList, latest] = await Promise.all([
      getJson("/v1/maps"),
      getJson(`/v1/localizations?limit=${LATEST}`),
    ]);
    const byId = new Map(mapList.maps.map((m) => [m.id, m]));
    const tripMaps = mapList.maps.filter(
      (m) => m.image_count > 0 && (m.descriptor.kind === "hog" || m.descriptor.kind === "cnn"),
    );
    const perMap = await mapLimited(tripMaps, 4, (m) => listPages(`/v1/maps/${seg(m.id)}/trips`, TRIPS_PER_MAP));
    const open = perMap
      .flatMap((p) => p.items)
      .filter((t) => t.closed_at_ms === null)
      .sort((a, b) => b.created_at_ms - a.created_at_ms);

    const mapLink = (id) => {
      const m = byId.get(id);
      return h("a", { href: `/maps/${id}`, title: id }, m ? m.name : shortId(id));
    };
    fill(
      maps,
      table(
        [
          { label: "Name", cell: (m) => h("a", { href: `/maps/${m.id}`, title: m.id, class: "map-name" }, m.name) },
          { label: "Kind", cell: (m) => m.descriptor.kind },
          { label: "Images", cls: "num", cell: (m) => h("span", { class: "image-count" }, fmtInt(m.image_count)) },
          { label: "Descriptor", cell: (m) => describeDescriptor(m.descriptor) + (m.descriptor_dim ? ` · ${fmtInt(m.descriptor_dim)}-D` : "") },
          { label: "Created", cell: (m) => fmtTime(m.created_at_ms) },
        ],
        mapList.maps,
        "No maps yet. Create one with POST /v1/maps.",
      ),
    );
    fill(
      trips,
      table(
        [
          { label: "Trip", cell: (t) => h("a", { href: `/trips/${t.id}`, title: t.id }, shortId(t.id)) },
          { label: "Map", cell: (t) => mapLink(t.map_id) },
          { label: "Status", cell: (t) => statusBadge(t.status, false) },
          { label: "Frames", cls: "num", cell: (t) => fmtInt(t.frame_count) },
          { label: "Opened", cell: (t) => fmtTime(t.created_at_ms) },
        ],
        open,
        "No trip is open.",
      ),
    );
    fill(
      locs,
      table(
        [
          { label: "Localization", cell: (l) => h("a", { href: `/localizations/${l.id}`, title: l.id }, shortId(l.id)) },
          { label: "Map", cell: (l) => mapLink(l.map_id) },
          { label: "Queries", cls: "num", cell: (l) => fmtInt(l.query_count) },
          { label: "Predicted", cls: "num", cell: (l) => fmtInt(l.predictions.length) },
          { label: "Hypotheses", cls: "num", cell: (l) => fmtInt(l.hypotheses.length) },
          { label: "W", cls: "num", cell: (l) => fmtNum(l.params.hidden_cost) },
          { label: "Created", cell: (l) => fmtTime(l.created_at_ms) },
        ],
        latest.items,
        "No localization yet.",
      ),
    );
  }

  await refresh();
  return { refresh, interval: 10000 };
}
