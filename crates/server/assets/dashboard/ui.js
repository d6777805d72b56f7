// DOM helpers shared by the pages. Every text from the server (map names, labels, messages)
// goes in as a text node, never as HTML, so a map called "<script>" is shown, not run.

/** Creates an element: `h("a", {href: "/"}, "text", child, ...)`. */
export function h(tag, attrs, ...children) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === null || v === undefined || v === false) continue;
    if (k === "class") el.className = v;
    else if (k.startsWith("on")) el.addEventListener(k.slice(2), v);
    else el.setAttribute(k, v === true ? "" : String(v));
  }
  append(el, children);
  return el;
}

function append(el, children) {
  for (const c of children.flat(Infinity)) {
    if (c === null || c === undefined || c === false) continue;
    el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
}

/** Replaces the children of `el`. */
export function fill(el, ...children) {
  el.replaceChildren();
  append(el, children);
  return el;
}

/** Milliseconds since the epoch as local date and time, e.g. "2026-11-23 12:04:05". */
export function fmtTime(ms) {
  if (ms === null || ms === undefined) return "—";
  const d = new Date(ms);
  const p = (n) => String(n).padStart(2, "0");
  return (
    `${d.getFullYear()}-${p(d.getMonth() + 1)}-${p(d.getDate())} ` +
    `${p(d.getHours())}:${p(d.getMinutes())}:${p(d.getSeconds())}`
  );
}

/** An integer with thousands separators: 30000 -> "30,000". */
export function fmtInt(n) {
  return n === null || n === undefined ? "—" : Number(n).toLocaleString("en-US");
}

/** A number with `digits` significant decimals, "—" for null. */
export function fmtNum(x, digits = 3) {
  if (x === null || x === undefined || !Number.isFinite(x)) return "—";
  if (Math.abs(x) >= 1000) return fmtInt(Math.round(x));
  return Number(x.toPrecision(digits)).toString();
}

/** A confidence: three decimals (local min-marginal ratios differ in the second or third). */
export function fmtConf(x) {
  if (x === null || x === undefined || !Number.isFinite(x)) return "—";
  return Math.abs(x) >= 1000 ? fmtInt(Math.round(x)) : x.toFixed(3);
}

/** Seconds for people: "0.42 s", "12 ms". */
export function fmtSeconds(s) {
  if (s === null || s === undefined) return "—";
  return s < 1 ? `${fmtNum(s * 1000, 3)} ms` : `${fmtNum(s, 3)} s`;
}

/** A short form of an id for tables (the full id stays in the link and its title). */
export function shortId(id) {
  const s = id.replace(/^0+(?=.{4})/, "");
  return s.length > 8 ? s.slice(0, 8) + "…" : s;
}

/** A map's descriptor in a few words: "HOG, 8 px cells". */
export function describeDescriptor(d) {
  switch (d.kind) {
    case "hog":
      return `HOG, ${d.cell_size} px cells` + (d.resize ? `, resized to ${d.resize[0]}×${d.resize[1]}` : "");
    case "cnn":
      return `CNN ${d.layer}` + (d.input_size ? `, ${d.input_size[0]}×${d.input_size[1]}` : "") + (d.resize ? `, ${d.resize}` : "");
    case "cooc":
      return "co-occurrence map";
    case "precomputed":
      return `client descriptors, ${d.dim}-D`;
    default:
      return d.kind;
  }
}

/** A trip's status as a coloured badge (text stays the API's word: localized/lost/relocalized). */
export function statusBadge(status, closed) {
  const word = status || "no frames yet";
  const cls = status ? `badge status-${status}` : "badge status-none";
  return h("span", { class: cls, "data-status": status || "" }, closed ? `${word} · closed` : word);
}

/** A table: `columns` = [{label, cell: row => node|string, cls}] (cls: "num" right-aligns). */
export function table(columns, rows, empty) {
  if (!rows.length) return h("p", { class: "muted empty" }, empty);
  return h(
    "div",
    { class: "table-wrap" },
    h(
      "table",
      {},
      h("thead", {}, h("tr", {}, columns.map((c) => h("th", { class: c.cls, scope: "col" }, c.label)))),
      h(
        "tbody",
        {},
        rows.map((r) => h("tr", {}, columns.map((c) => h("td", { class: c.cls }, c.cell(r))))),
      ),
    ),
  );
}

/** A definition list of [label, value] pairs. */
export function facts(pairs) {
  return h(
    "dl",
    { class: "facts" },
    pairs.map(([k, v]) => [h("dt", {}, k), h("dd", {}, v)]),
  );
}

/** A headline number with its label, e.g. "2,400" over "images". */
export function stat(label, value, id) {
  return h("div", { class: "stat" }, h("span", { class: "stat-value", id }, value), h("span", { class: "stat-label" }, label));
}

/** A section with a heading. */
export function section(title, ...children) {
  return h("section", { class: "card" }, h("h2", {}, title), ...children);
}

/** The page's error box, with the API's code for people who report it. */
export function errorBox(err) {
  const code = err && err.code ? ` (${err.code})` : "";
  return h("div", { class: "error", role: "alert" }, h("strong", {}, "Could not load: "), `${err.message}${code}`);
}

/** Sets the breadcrumbs: [[label, href|null], ...]. */
export function crumbs(items) {
  fill(
    document.getElementById("crumbs"),
    items.map(([label, href], i) => [
      i ? h("span", { class: "sep", "aria-hidden": "true" }, "›") : null,
      href ? h("a", { href }, label) : h("span", { "aria-current": "page" }, label),
    ]),
  );
}

/** Shows "live · updated 12:04:05" (or an error) in the header. */
export function liveStatus(text, bad) {
  const el = document.getElementById("live");
  el.textContent = text;
  el.classList.toggle("bad", Boolean(bad));
}
