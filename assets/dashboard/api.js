// The dashboard's only way to the server: GETs of the public JSON API on this origin.
// Errors keep the API's shape ({"error": {"code", "message"}}) so pages can show the
// server's own message ("map `…` does not exist") instead of a generic failure.

/** A failed API call: HTTP status, the API's stable code and its message. */
export class ApiError extends Error {
  constructor(status, code, message) {
    super(message);
    this.status = status;
    this.code = code;
  }
}

/** GET `path` (a `/v1/...` path on this origin) as JSON; throws ApiError. */
export async function getJson(path) {
  let r;
  try {
    r = await fetch(path, { headers: { Accept: "application/json" }, cache: "no-store" });
  } catch (e) {
    throw new ApiError(0, "unreachable", `the server did not answer (${e.message})`);
  }
  if (!r.ok) {
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
    throw new ApiError(r.status, code, message);
  }
  return r.json();
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
