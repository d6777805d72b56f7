// Entry point of every dashboard page: picks the page from the URL path, draws it, and keeps
// live pages fresh. Pages are modules exporting `render(main, id)`, which returns an optional
// `{refresh, interval}` to poll while the page is visible.

import { setUpKeyButton } from "./api.js";
import { errorBox, fill, h, crumbs, liveStatus } from "./ui.js";
import * as overview from "./overview.js";
import * as map from "./map.js";
import * as localization from "./localization.js";
import * as trip from "./trip.js";

const PAGES = [
  [/^\/$/, overview],
  [/^\/maps\/([^/]+)\/?$/, map],
  [/^\/localizations\/([^/]+)\/?$/, localization],
  [/^\/trips\/([^/]+)\/?$/, trip],
];

function clock() {
  const d = new Date();
  const p = (n) => String(n).padStart(2, "0");
  return `${p(d.getHours())}:${p(d.getMinutes())}:${p(d.getSeconds())}`;
}

/** Polls `live.refresh` every `live.interval` ms while the tab is visible; backs off on errors. */
function keepFresh(live) {
  let failures = 0;
  let timer = null;
  const schedule = () => {
    clearTimeout(timer);
    const wait = live.interval * Math.min(8, 2 ** failures);
    timer = setTimeout(tick, wait);
  };
  async function tick() {
    if (document.hidden) return; // resumed by visibilitychange
    try {
      const more = await live.refresh();
      failures = 0;
      if (more === false) {
        liveStatus(`not live (${live.doneText || "finished"}) · updated ${clock()}`);
        return;
      }
      liveStatus(`live · updated ${clock()}`);
    } catch (e) {
      failures += 1;
      liveStatus(`update failed: ${e.message} · retrying`, true);
    }
    schedule();
  }
  document.addEventListener("visibilitychange", () => {
    if (!document.hidden) tick();
  });
  liveStatus(`live · updated ${clock()}`);
  schedule();
}

async function main() {
  setUpKeyButton();
  const root = document.getElementById("main");
  const path = decodeURI(location.pathname);
  const found = PAGES.map(([re, page]) => [path.match(re), page]).find(([m]) => m);
  try {
    if (!found) {
      crumbs([["Overview", "/"], ["Not found", null]]);
      fill(root, h("h1", {}, "No such page"), h("p", {}, "The dashboard has no page at ", h("code", {}, path), "."));
      return;
    }
    const [m, page] = found;
    const live = await page.render(root, m[1]);
    if (live) keepFresh(live);
  } catch (e) {
    fill(root, h("h1", {}, "Could not load this page"), errorBox(e));
  } finally {
    root.setAttribute("aria-busy", "false");
    document.body.dataset.ready = "1";
  }
}

main();
