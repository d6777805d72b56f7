// The dashboard's only way to the server: GETs of the public JSON API on this origin.
// Errors keep the API's shape ({"error": {"code", "message"}}) so pages can show the
// server's own message ("map `…` does not exist") instead of a generic failure.
//
// API keys: when the server answers 401, the person is asked for a key once; it is kept in
// sessionStorage (this tab's browser session only, never on disk beyond it, never in a URL)
// and sent as `Authorization: Bearer <key>` with every request. A reader key is enough for
// every page. A key the server refuses (401 again) is dropped and asked for again.

const KEY_ITEM = "seasonloc.api-key";

/** A failed API call: HTTP status, the API's stable code and its message. */
export class ApiError extends Error {
  constructor(status, code, message) {
    super(message);
    this.status = status;
    this.code = code;
  }
}

/** The key of this browser session, or null. */
export function storedKey() {
  try {
    return sessionStorage.getItem(KEY_ITEM);
  } catch (_) {
    return null; // storage disabled: the key lives only in `memoryKey`
  }
}

let memoryKey = null;

function currentKey() {
  return storedKey() || memoryKey;
}

function keepKey(key) {
  memoryKey = key;
  try {
    if (key) sessionStorage.setItem(KEY_ITEM, key);
    else sessionStorage.removeItem(KEY_ITEM);
  } catch (_) {
    // Private mode without storage: the key lasts until the page is closed.
  }
  const button = document.getElementById("key-button");
  if (button) button.hidden = !key;
}

/** Forgets the key (the header's "API key" button); the next call asks again. */
export function forgetKey() {
  keepKey(null);
}

/** One prompt at a time: requests that meet a 401 together wait for the same answer. */
let asking = null;

function askForKey(reason) {
  if (asking) return asking;
  asking = new Promise((resolve) => {
    const dialog = document.getElementById("key-dialog");
    const input = document.getElementById("key-input");
    const note = document.getElementById("key-reason");
    note.textContent = reason;
    input.value = "";
    const done = (ev) => {
      ev.preventDefault();
      const key = input.value.trim();
      if (!key) return;
      dialog.close();
      form.removeEventListener("submit", done);
      asking = null;
      resolve(key);
    };
    const form = dialog.querySelector("form");
    form.addEventListener("submit", done);
    dialog.showModal();
    input.focus();
  });
  return asking;
}

async function send(path, accept) {
  const headers = { Accept: accept };
  const key = currentKey();
  if (key) headers.Authorization = `Bearer ${key}`;
  // JSON is live data (never from the cache); pictures never change and may be cached.
  const cache = accept === "application/json" ? "no-store" : "default";
  try {
    return await fetch(path, { headers, cache, credentials: "omit" });
  } catch (e) {
    throw new ApiError(0, "unreachable", `the server did not answer (${e.message})`);
  }
}

async function errorOf(r) {
  let code = "http_" + r.status;
  let message = `${r.status} ${r.statusText}`;
  try {
    const body = await r.json();
    if (body && body.error) {
      code = body.error.code;
      message = body.error.message;
    }
  } catch (_) {
    // Not our error shape (e.g. a proxy's page): keep the status line.
  }
  return new ApiError(r.status, code, message);
}

/** GET with the session's key, asking for one on 401; returns the OK response. */
async function authorized(path, accept) {
  for (;;) {
    const r = await send(path, accept);
    if (r.status !== 401) {
      if (!r.ok) throw await errorOf(r);
      return r;
    }
    const err = await errorOf(r);
    const had = currentKey();
    keepKey(null);
    const reason = had
      ? `The server refused the key (${err.message}). Enter another one.`
      : "This server needs an API key. A reader key is enough to see every page.";
    keepKey(await askForKey(reason));
  }
}

/** GET `path` (a `/v1/...` path on this origin) as JSON; throws ApiError. */
export async function getJson(path) {
  const r = await authorized(path, "application/json");
  return r.json();
}

/**
 * GET a picture (thumbnail, matrix picture) as an object URL for <img>/<image>: fetched with
 * the key header, which an `src` attribute could not send. Null when the server has none (404).
 */
export async function getImageUrl(path) {
  try {
    const r = await authorized(path, "image/*");
    return URL.createObjectURL(await r.blob());
  } catch (e) {
    if (e instanceof ApiError && e.status === 404) return null;
    throw e;
  }
}

/** Encodes one path segment (ids come from the page URL, which a person can edit). */
export function seg(s) {
  return encodeURIComponent(s);
}

/**
 * Follows a newest-first paginated listing (`items` + `next` cursor) until `max` items or
 * the last page, whichever comes first.
 */
export async function listPages(path, max) {
  const items = [];
  let before = null;
  const sep = path.includes("?") ? "&" : "?";
  for (;;) {
    const limit = Math.min(100, max - items.length);
    const url = `${path}${sep}limit=${limit}` + (before ? `&before=${seg(before)}` : "");
    const page = await getJson(url);
    items.push(...page.items);
    if (!page.next || items.length >= max) {
      return { items, more: Boolean(page.next) };
    }
    before = page.next;
  }
}

/** Runs `f` over `xs` with at most `n` calls in flight; results keep the input order. */
export async function mapLimited(xs, n, f) {
  const out = new Array(xs.length);
  let next = 0;
  async function worker() {
    while (next < xs.length) {
      const i = next++;
      out[i] = await f(xs[i], i);
    }
  }
  await Promise.all(Array.from({ length: Math.min(n, xs.length) }, worker));
  return out;
}

/** Shows the header's key button when a key is in use; clicking it forgets the key. */
export function setUpKeyButton() {
  const button = document.getElementById("key-button");
  if (!button) return;
  button.hidden = !currentKey();
  button.addEventListener("click", () => {
    forgetKey();
    location.reload();
  });
}
