// Thumbnails of reference images (`GET /v1/maps/{id}/images/{index}/thumbnail`), loaded when
// they scroll into view, fetched with the session's key (so as blob URLs) and released when
// replaced. Maps created before thumbnails existed have none: the box then says so.

import { getImageUrl, seg } from "./api.js";
import { h } from "./ui.js";

const seen = new IntersectionObserver(
  (entries) => {
    for (const e of entries) {
      if (e.isIntersecting) {
        seen.unobserve(e.target);
        load(e.target);
      }
    }
  },
  { rootMargin: "200px" },
);

async function load(box) {
  const { map, index } = box.dataset;
  try {
    const url = await getImageUrl(`/v1/maps/${seg(map)}/images/${index}/thumbnail`);
    if (!url) {
      box.classList.add("missing");
      box.querySelector(".thumb-img").replaceWith(h("span", { class: "thumb-img none" }, "no thumbnail"));
      return;
    }
    const img = h("img", { class: "thumb-img", alt: `reference image ${index}`, src: url });
    img.addEventListener("load", () => URL.revokeObjectURL(url), { once: true });
    box.querySelector(".thumb-img").replaceWith(img);
    box.classList.add("loaded");
  } catch (e) {
    box.classList.add("missing");
    box.querySelector(".thumb-img").replaceWith(h("span", { class: "thumb-img none" }, e.message));
  }
}

/** A figure with reference `index`'s thumbnail of map `map`, labelled "reference N". */
export function thumbnail(map, index, caption) {
  const box = h(
    "figure",
    { class: "thumb", "data-map": map, "data-index": index },
    h("span", { class: "thumb-img pending" }),
    h("figcaption", {}, caption || `reference ${Number(index).toLocaleString("en-US")}`),
  );
  seen.observe(box);
  return box;
}

/** `count` indices spread evenly over `0..n` (all of them when n <= count). */
export function spread(n, count) {
  if (n <= count) return Array.from({ length: n }, (_, i) => i);
  return Array.from({ length: count }, (_, k) => Math.round((k * (n - 1)) / (count - 1)));
}
