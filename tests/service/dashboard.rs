//! The dashboard in a real browser (headless Chromium, [`crate::browser`]) against a running
//! server: what a person sees on `/`, `/maps/{id}`, `/localizations/{id}` and `/trips/{id}`,
//! that a trip's page follows new frames without a reload, that the pages stay on their own
//! origin, run without script errors and fit a tablet's width. Screenshots of every page go
//! to `target/tmp/dashboard-shots/`; `SEASONLOC_UPDATE_DOCS=1` also refreshes the ones in
//! `docs/` (the README shows them).
//!
//! The files themselves (types, policies, caching, 404s) are checked over plain HTTP and run
//! everywhere; the browser tests skip with a message when Chromium is not installed, the
//! Nordland one also when `../shared` is absent.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::time::Duration;

use serde_json::{json, Value};

use crate::browser::{shots_dir, Browser};
use crate::common::{create_hog_map, nordland, nordland_files, Route, Server};
use crate::http::{Client, Part};
use crate::spec::check;

/// A laptop's viewport and a tablet's (portrait), in CSS pixels.
const LAPTOP: (u32, u32) = (1280, 800);
const TABLET: (u32, u32) = (768, 1024);
/// Longest a page may take to show new frames (it polls every 2 s).
const LIVE_WAIT: Duration = Duration::from_secs(20);

fn body(r: &crate::http::Response) -> String {
    String::from_utf8_lossy(&r.body).into_owned()
}

fn base(c: &Client) -> String {
    format!("http://{}", c.addr)
}

/// The screenshots the README shows (`docs/dashboard-NAME.png`): one of each page on a laptop.
const DOC_SHOTS: &[&str] = &["overview", "map", "map-gps", "localization", "trip"];

/// Saves a screenshot of the current page as `name.png` under the test artifacts and, with
/// `SEASONLOC_UPDATE_DOCS=1`, the ones in [`DOC_SHOTS`] under `docs/`.
fn shoot(b: &mut Browser, name: &str) -> PathBuf {
    let path = shots_dir().join(format!("{name}.png"));
    b.screenshot(&path);
    if std::env::var_os("SEASONLOC_UPDATE_DOCS").is_some() && DOC_SHOTS.contains(&name) {
        let docs = Path::new(env!("CARGO_MANIFEST_DIR")).join("docs");
        std::fs::copy(&path, docs.join(format!("dashboard-{name}.png"))).unwrap();
    }
    path
}

/// Every request of the page went to the server under test.
fn assert_same_origin(b: &Browser, origin: &str) {
    let foreign: Vec<&String> = b
        .requests
        .iter()
        .filter(|u| !u.starts_with(origin) && !u.starts_with("data:") && !u.starts_with("blob:"))
        .collect();
    assert!(foreign.is_empty(), "requests to other hosts: {foreign:?}");
}

/// The page is no wider than the viewport: nothing to scroll sideways on a tablet (wide
/// tables scroll inside their own box).
fn assert_fits_width(b: &mut Browser, page: &str) {
    let v = b.eval("[document.documentElement.scrollWidth, window.innerWidth]");
    let (scroll, inner) = (v[0].as_f64().unwrap(), v[1].as_f64().unwrap());
    assert!(
        scroll <= inner + 1.0,
        "{page}: {scroll} px wide in a {inner} px viewport"
    );
}

fn upload(c: &Client, map: &str, parts: &[Part]) {
    let r = c.post_multipart(&format!("/v1/maps/{map}/images"), parts);
    assert_eq!(r.status, 200, "{}", body(&r));
}

fn nordland_parts(files: &[PathBuf], range: std::ops::Range<usize>) -> Vec<Part> {
    files[range]
        .iter()
        .map(|p| {
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            Part::image(&name, std::fs::read(p).unwrap())
        })
        .collect()
}

fn post_frames(c: &Client, trip: &str, parts: &[Part]) -> Value {
    let r = c.post_multipart(&format!("/v1/trips/{trip}/frames"), parts);
    assert_eq!(r.status, 200, "{}", body(&r));
    r.json()
}

/// Posts `parts` to `trip` and waits until the trip page open in `b` shows the answer's frame
/// count and status without a reload; returns that status.
fn post_frames_and_watch(b: &mut Browser, c: &Client, trip: &str, parts: &[Part]) -> String {
    let v = post_frames(c, trip, parts);
    let frames = v["frame_count"].as_u64().unwrap();
    let status = v["status"].as_str().unwrap().to_string();
    b.wait_for(
        &format!(
            "document.querySelector('#frame-count').innerText === '{frames}' && \
             document.querySelector('#trip-status').innerText === '{status}'"
        ),
        LIVE_WAIT,
    )
    .unwrap();
    status
}

/// One raw GET with extra headers; returns the status line's code and the head.
fn raw_get(c: &Client, path: &str, headers: &[(&str, &str)]) -> (u16, String) {
    let mut s = std::net::TcpStream::connect(c.addr).unwrap();
    let mut req = format!(
        "GET {path} HTTP/1.1\r\nHost: {}\r\nConnection: close\r\n",
        c.addr
    );
    for (k, v) in headers {
        req.push_str(&format!("{k}: {v}\r\n"));
    }
    req.push_str("\r\n");
    s.write_all(req.as_bytes()).unwrap();
    let mut raw = Vec::new();
    s.read_to_end(&mut raw).unwrap();
    let text = String::from_utf8_lossy(&raw).into_owned();
    let code = text.split(' ').nth(1).unwrap().parse().unwrap();
    let head = text.split("\r\n\r\n").next().unwrap().to_string();
    (code, head)
}

#[test]
fn dashboard_files_are_served_with_types_policies_and_etags() {
    let server = Server::start();
    let c = server.client;
    for (path, template) in [
        ("/", "/"),
        ("/maps/0000000000000001", "/maps/{id}"),
        ("/localizations/0000000000000001", "/localizations/{id}"),
        ("/trips/0000000000000001", "/trips/{id}"),
    ] {
        let r = c.get(path);
        check("GET", template, &r);
        assert_eq!(r.status, 200, "{path}");
        assert_eq!(r.header("content-type"), Some("text/html; charset=utf-8"));
        let csp = r.header("content-security-policy").unwrap_or("");
        assert!(
            csp.contains("default-src 'self'") && csp.contains("connect-src 'self'"),
            "{csp}"
        );
        assert_eq!(r.header("x-frame-options"), Some("DENY"));
        let html = body(&r);
        assert!(
            html.contains(r#"<script type="module" src="/assets/app.js">"#),
            "{html}"
        );
    }
    let r = c.get("/assets/app.js");
    check("GET", "/assets/{name}", &r);
    assert_eq!(r.status, 200);
    assert_eq!(
        r.header("content-type"),
        Some("text/javascript; charset=utf-8")
    );
    assert_eq!(r.header("x-content-type-options"), Some("nosniff"));
    assert_eq!(r.header("cache-control"), Some("no-cache"));
    let etag = r.header("etag").unwrap().to_string();
    assert_eq!(
        r.body,
        include_bytes!("../../crates/server/assets/dashboard/app.js"),
        "the served file is the embedded one"
    );
    let (code, _) = raw_get(&c, "/assets/app.js", &[("If-None-Match", &etag)]);
    assert_eq!(code, 304, "an unchanged file is not sent again");
    let (code, _) = raw_get(
        &c,
        "/assets/app.js",
        &[("If-None-Match", "\"0000000000000000\"")],
    );
    assert_eq!(code, 200, "a stale ETag gets the file");
    let r = c.get("/assets/dashboard.css");
    assert_eq!(r.header("content-type"), Some("text/css; charset=utf-8"));

    for missing in [
        "/assets/nope.js",
        "/assets/..%2FCargo.toml",
        "/assets/index.html",
    ] {
        let r = c.get(missing);
        check("GET", "/assets/{name}", &r);
        assert_eq!(
            (r.status, r.code().as_str()),
            (404, "asset_not_found"),
            "{missing}"
        );
    }
    // API paths keep their JSON 404s; the dashboard does not swallow them.
    let r = c.get("/v1/nothing");
    assert_eq!((r.status, r.code().as_str()), (404, "route_not_found"));
    let r = c.get("/maps");
    assert_eq!((r.status, r.code().as_str()), (404, "route_not_found"));
}

/// Generated images (no shared data needed): the overview lists a map whose name is markup
/// (shown as text, never run), a page for an unknown id shows the API's message, and a trip
/// page follows its first batches live, from "no frames yet" to localized.
#[test]
fn dashboard_pages_in_a_browser_on_generated_images() {
    let Some(mut b) = Browser::launch(LAPTOP.0, LAPTOP.1) else {
        return;
    };
    let server = Server::start();
    let c = server.client;
    let origin = base(&c);
    let route = Route::new(40, 11);
    let name = r#"<img src=x onerror="document.title='pwned'"> route"#;
    let r = c.post_json(
        "/v1/maps",
        &json!({"name": name, "descriptor": {"kind": "hog", "cell_size": 8}}),
    );
    assert_eq!(r.status, 201, "{}", body(&r));
    let map = r.json()["id"].as_str().unwrap().to_string();
    let mut parts: Vec<Part> = (0..40)
        .map(|i| Part::image(&format!("r{i}.png"), route.reference_png(i)))
        .collect();
    // GPS metadata along a quarter circle (so the plotted route is not a straight line).
    let metas: Vec<Value> = (0..40)
        .map(|i| {
            let a = f64::from(i) / 39.0 * std::f64::consts::FRAC_PI_2;
            json!({"latitude": 63.40 + 0.01 * a.sin(), "longitude": 10.40 + 0.02 * a.cos()})
        })
        .collect();
    parts.push(Part::json("metadata", &json!(metas)));
    upload(&c, &map, &parts);

    b.goto(&format!("{origin}/"));
    let row = b.eval(&format!(
        "(() => {{ const a = [...document.querySelectorAll('#maps a.map-name')].find(a => a.textContent === {}); \
         return a ? a.closest('tr').querySelector('.image-count').textContent : null; }})()",
        Value::String(name.into())
    ));
    assert_eq!(
        row, "40",
        "the overview lists the map by its name with its image count"
    );
    assert_ne!(
        b.eval("document.title"),
        "pwned",
        "a map's name is text, not markup"
    );
    assert_eq!(b.eval("document.querySelectorAll('#maps img').length"), 0);
    b.assert_no_script_errors("/");

    b.goto(&format!("{origin}/maps/00000000deadbeef"));
    assert!(
        b.text().contains("map `00000000deadbeef` does not exist"),
        "{}",
        b.text()
    );
    // The browser logs the API's 404 for that map, and nothing else.
    let errors = b.take_errors();
    assert!(
        errors.len() == 1
            && errors[0].contains("404")
            && errors[0].contains("/v1/maps/00000000deadbeef"),
        "{errors:#?}"
    );

    // `/maps/{id}`: the thumbnails along the route load (real pictures of the references,
    // 64 x 32 like the uploads), the rest as the strip scrolls, and the GPS route is drawn.
    b.goto(&format!("{origin}/maps/{map}"));
    let loaded = "[...document.querySelectorAll('#thumb-strip img.thumb-img')]\
                  .filter(i => i.complete && i.naturalWidth === 64 && i.naturalHeight === 32).length";
    b.wait_for(&format!("{loaded} >= 4"), Duration::from_secs(10))
        .unwrap();
    assert_eq!(
        b.eval("document.querySelectorAll('#thumb-strip figure.thumb').length"),
        16,
        "16 thumbnails spread along the route"
    );
    assert_eq!(
        b.eval("[...document.querySelectorAll('#thumb-strip figcaption')].map(f => f.innerText).join('|')"),
        (0..16)
            .map(|k| format!("reference {}", (k * 39 + 7) / 15))
            .collect::<Vec<_>>()
            .join("|"),
        "the strip spans the route from its first image to its last"
    );
    // Scroll the strip as a person would, a few hundred pixels at a time.
    b.eval(
        "(async () => { const s = document.querySelector('#thumb-strip'); \
         for (let k = 0; k < 40 && s.scrollLeft + s.clientWidth < s.scrollWidth - 1; k++) { s.scrollLeft += 300; \
         await new Promise(r => setTimeout(r, 80)); } return 1; })()",
    );
    b.wait_for(&format!("{loaded} === 16"), Duration::from_secs(10))
        .unwrap();
    b.wait_for(
        "document.querySelector('#gps-route path.gps-route') !== null",
        Duration::from_secs(10),
    )
    .unwrap();
    assert_eq!(
        b.eval("(document.querySelector('#gps-route path.gps-route').getAttribute('d').match(/[ML]/g) || []).length"),
        40,
        "one route point per image with GPS metadata"
    );
    // The quarter circle runs from east (start) to north (end): the start is drawn right of
    // and below the end.
    let (sx, sy) = b.center_of("#gps-route .gps-start");
    let (ex, ey) = b.center_of("#gps-route .gps-end");
    assert!(sx > ex && sy > ey, "start ({sx}, {sy}) end ({ex}, {ey})");
    shoot(&mut b, "map-gps");
    b.assert_no_script_errors("/maps/{id}");

    // A trip opened before any frame: the page shows that, then follows the batches.
    let r = c.request("POST", &format!("/v1/maps/{map}/trips"), None, &[]);
    assert_eq!(r.status, 201, "{}", body(&r));
    let trip = r.json()["id"].as_str().unwrap().to_string();
    b.goto(&format!("{origin}/trips/{trip}"));
    assert_eq!(b.text_of("#frame-count").as_deref(), Some("0"));
    assert_eq!(b.text_of("#trip-status").as_deref(), Some("no frames yet"));
    b.eval("window.__sameDocument = true");
    for batch in 0..2u32 {
        let parts: Vec<Part> = (batch * 10..batch * 10 + 10)
            .map(|i| Part::image(&format!("q{i}.png"), route.query_png(i)))
            .collect();
        post_frames_and_watch(&mut b, &c, &trip, &parts);
    }
    assert_eq!(b.text_of("#trip-status").as_deref(), Some("localized"));
    assert_eq!(
        b.eval("window.__sameDocument === true"),
        true,
        "the page updated without a reload"
    );
    let dots = b.eval("document.querySelectorAll('#position-chart .position-dot').length");
    assert_eq!(dots, 20, "one dot per frame on the map");
    // The thumbnail of the reference the vehicle is matched to now.
    let now = c.get(&format!("/v1/trips/{trip}?since=19")).json();
    let reference = now["estimates"][0]["ref"].as_u64().unwrap();
    b.wait_for(
        "(() => { const i = document.querySelector('.now-thumb img.thumb-img'); \
         return i !== null && i.complete && i.naturalWidth === 64; })()",
        Duration::from_secs(10),
    )
    .unwrap();
    assert_eq!(
        b.text_of(".now-thumb figcaption"),
        Some(format!("reference {reference} (matched now)"))
    );
    // Closing the trip stops the page's polling, and says so.
    let r = c.request("POST", &format!("/v1/trips/{trip}/close"), None, &[]);
    assert_eq!(r.status, 200, "{}", body(&r));
    b.wait_for(
        "document.querySelector('#trip-status').innerText === 'localized · closed' && \
         document.querySelector('#live').innerText.startsWith('not live')",
        LIVE_WAIT,
    )
    .unwrap();
    b.assert_no_script_errors("/trips/{id}");
    assert_same_origin(&b, &origin);
}

/// Real Nordland frames (summer map, winter queries): each page shows what a person looks for,
/// on a laptop and on a tablet, and the trip page follows new batches live.
#[test]
fn dashboard_pages_in_a_browser_on_nordland() {
    let Some(data) = nordland() else {
        return;
    };
    let Some(mut b) = Browser::launch(LAPTOP.0, LAPTOP.1) else {
        return;
    };
    let server = Server::start();
    let c = server.client;
    let origin = base(&c);
    let summer = nordland_files(&data.join("summer"));
    let winter = nordland_files(&data.join("winter"));
    let name = "Nordland summer 300-499";
    let map = create_hog_map(&c, name, 8);
    upload(&c, &map, &nordland_parts(&summer, 300..400));
    upload(&c, &map, &nordland_parts(&summer, 400..500));
    let r = c.post_multipart(
        &format!("/v1/maps/{map}/localize"),
        &nordland_parts(&winter, 350..410),
    );
    assert_eq!(r.status, 200, "{}", body(&r));
    let loc = r.json();
    let loc_id = loc["id"].as_str().unwrap().to_string();
    let r = c.request("POST", &format!("/v1/maps/{map}/trips"), None, &[]);
    assert_eq!(r.status, 201, "{}", body(&r));
    let trip = r.json()["id"].as_str().unwrap().to_string();
    let mut last = Value::Null;
    for lo in (360..390).step_by(10) {
        last = post_frames(&c, &trip, &nordland_parts(&winter, lo..lo + 10));
    }
    let first_status = last["status"].as_str().unwrap().to_string();

    for (label, (w, h)) in [("laptop", LAPTOP), ("tablet", TABLET)] {
        b.viewport(w, h);
        let suffix = if label == "laptop" {
            String::new()
        } else {
            format!("-{label}")
        };

        // `/`: the map with its image count, the open trip, the localization.
        b.goto(&format!("{origin}/"));
        let text = b.text();
        assert!(text.contains(name), "{label} /: {text}");
        let count = b.eval(
            "(() => { const a = [...document.querySelectorAll('#maps a.map-name')]\
             .find(a => a.textContent === 'Nordland summer 300-499'); \
             return a ? a.closest('tr').querySelector('.image-count').textContent : null; })()",
        );
        assert_eq!(count, "200", "{label} /");
        let short = short_id(&trip);
        assert_eq!(
            b.text_of(&format!("#open-trips a[href='/trips/{trip}']"))
                .as_deref(),
            Some(short.as_str()),
            "{label} /: the open trip is listed and linked"
        );
        assert_eq!(
            b.text_of(&format!(
                "#latest-localizations a[href='/localizations/{loc_id}']"
            ))
            .as_deref(),
            Some(short_id(&loc_id).as_str()),
            "{label} /: the localization is listed and linked"
        );
        assert_fits_width(&mut b, "/");
        shoot(&mut b, &format!("overview{suffix}"));

        // `/maps/{id}`: name and image count, its trip and localization.
        b.goto(&format!("{origin}/maps/{map}"));
        assert_eq!(b.text_of("#map-name").as_deref(), Some(name));
        assert_eq!(b.text_of("#image-count").as_deref(), Some("200"));
        let text = b.text();
        assert!(
            text.contains("HOG, 8 px cells") && text.contains(&short),
            "{label} map: {text}"
        );
        b.wait_for(
            "[...document.querySelectorAll('#thumb-strip img.thumb-img')]\
             .filter(i => i.complete && i.naturalWidth === 64).length >= 3",
            Duration::from_secs(10),
        )
        .unwrap();
        b.wait_for(
            "document.querySelector('#no-gps') !== null",
            Duration::from_secs(10),
        )
        .unwrap();
        assert!(
            b.text_of("#no-gps").unwrap().contains("0 of 200 images"),
            "{label}: Nordland frames carry no GPS metadata"
        );
        assert_fits_width(&mut b, "/maps/{id}");
        shoot(&mut b, &format!("map{suffix}"));

        // `/localizations/{id}`: the figure with the path and one dot per prediction.
        b.goto(&format!("{origin}/localizations/{loc_id}"));
        assert_eq!(b.text_of("#map-link").as_deref(), Some(name));
        let predictions = loc["predictions"].as_array().unwrap();
        let rank1 = &loc["hypotheses"][0]["rows"];
        let matched: usize = rank1
            .as_array()
            .unwrap()
            .iter()
            .map(|r| r["matches"].as_array().unwrap().len())
            .sum();
        assert!(matched > 30, "the winter frames are found on the map");
        let drawn = b.eval(
            "(() => { const p = document.querySelector('svg.matrix .hypothesis-path[data-rank=\"1\"]'); \
             return p ? (p.getAttribute('d').match(/[ML]/g) || []).length : 0; })()",
        );
        assert_eq!(
            drawn, matched,
            "{label}: the rank-1 path has a point per match"
        );
        assert_eq!(
            b.eval("document.querySelectorAll('svg.matrix .prediction-dot').length"),
            predictions.len(),
            "{label}: one dot per prediction"
        );
        // Under the paths: the similarity picture stored with the result, as a real image of
        // queries x references pixels (60 x 200: no downsampling needed at this size).
        let picture = b.eval(
            "(async () => { const i = document.querySelector('svg.matrix image.matrix-picture'); \
             if (!i) return null; const href = i.getAttribute('href'); \
             const img = new Image(); img.src = href; await img.decode(); \
             const paths = document.querySelector('svg.matrix .hypotheses'); \
             return { blob: href.startsWith('blob:'), w: img.naturalWidth, h: img.naturalHeight, \
               under: Boolean(i.compareDocumentPosition(paths) & Node.DOCUMENT_POSITION_FOLLOWING) }; })()",
        );
        assert_eq!(
            picture,
            json!({"blob": true, "w": loc["picture"]["cols"], "h": loc["picture"]["rows"], "under": true}),
            "{label}: the matrix picture is drawn under the route hypotheses"
        );
        assert_eq!(
            (
                loc["picture"]["rows"].as_u64(),
                loc["picture"]["cols"].as_u64()
            ),
            (Some(60), Some(200))
        );
        assert_eq!(
            b.eval("document.querySelectorAll('#confidence-chart .confidence-dot').length"),
            predictions.len()
        );
        // Clicking a prediction's dot selects its query and names the matched reference.
        let p = &predictions[predictions.len() / 2];
        let (x, y) = b.center_of(&format!(
            "svg.matrix .prediction-dot[data-query=\"{}\"]",
            p["query"]
        ));
        b.click(x, y);
        b.wait_for(
            &format!(
                "document.querySelector('#selected-query h3') && \
                 document.querySelector('#selected-query h3').innerText === 'Query {}'",
                p["query"]
            ),
            Duration::from_secs(5),
        )
        .unwrap();
        assert_eq!(
            b.text_of("#selected-query .matched-ref"),
            Some(format!("reference {}", p["ref"]))
        );
        // ... and shows that reference's thumbnail (a 64 x 32 Nordland frame).
        b.wait_for(
            "(() => { const i = document.querySelector('#selected-query .thumb img.thumb-img'); \
             return i !== null && i.complete && i.naturalWidth === 64 && i.naturalHeight === 32; })()",
            Duration::from_secs(10),
        )
        .unwrap();
        assert_eq!(
            b.text_of("#selected-query .thumb figcaption"),
            Some(format!("reference {} (matched)", p["ref"]))
        );
        assert_fits_width(&mut b, "/localizations/{id}");
        shoot(&mut b, &format!("localization{suffix}"));
        b.assert_no_script_errors("/localizations/{id}");
    }

    // `/trips/{id}`: frame count and status, then both follow new batches without a reload.
    b.viewport(LAPTOP.0, LAPTOP.1);
    b.goto(&format!("{origin}/trips/{trip}"));
    assert_eq!(b.text_of("#frame-count").as_deref(), Some("30"));
    assert_eq!(b.text_of("#trip-status"), Some(first_status.clone()));
    assert_eq!(b.text_of("#map-link").as_deref(), Some(name));
    b.wait_for(
        "(() => { const i = document.querySelector('.now-thumb img.thumb-img'); \
         return i !== null && i.complete && i.naturalWidth === 64; })()",
        Duration::from_secs(10),
    )
    .unwrap();
    shoot(&mut b, "trip");
    b.eval("window.__sameDocument = true");
    // Winter 1500-1519 is far past the map's end (summer 300-499): the vehicle leaves the
    // map, which the trip reports as lost within two batches.
    let mut statuses = vec![first_status];
    for lo in [1500, 1510] {
        let parts = nordland_parts(&winter, lo..lo + 10);
        let status = post_frames_and_watch(&mut b, &c, &trip, &parts);
        statuses.push(status);
    }
    assert_eq!(
        statuses.first().map(String::as_str),
        Some("localized"),
        "{statuses:?}"
    );
    assert_eq!(
        statuses.last().map(String::as_str),
        Some("lost"),
        "{statuses:?}"
    );
    assert_eq!(b.eval("window.__sameDocument === true"), true, "no reload");
    shoot(&mut b, "trip-lost");
    b.assert_no_script_errors("/trips/{id}");
    b.viewport(TABLET.0, TABLET.1);
    b.goto(&format!("{origin}/trips/{trip}"));
    assert_eq!(b.text_of("#frame-count").as_deref(), Some("50"));
    assert_fits_width(&mut b, "/trips/{id}");
    shoot(&mut b, "trip-tablet");
    b.assert_no_script_errors("/trips/{id}");
    assert_same_origin(&b, &origin);
}

/// How the dashboard shows an id (`shortId` in `assets/dashboard/ui.js`): leading zeros dropped
/// while four digits remain, then at most eight digits and an ellipsis.
fn short_id(id: &str) -> String {
    let mut s = id;
    while s.len() > 4 && s.starts_with('0') {
        s = &s[1..];
    }
    if s.len() > 8 {
        format!("{}\u{2026}", &s[..8])
    } else {
        s.to_string()
    }
}
