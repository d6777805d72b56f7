//! A real browser for the dashboard tests: headless Chromium driven over the DevTools protocol.
//!
//! The protocol runs over `--remote-debugging-pipe` (NUL-terminated JSON on file descriptors
//! 3 and 4, the transport Puppeteer uses): no port to pick, nothing listening, no WebSocket
//! client. The tests need seven commands (`Target.createTarget`, `Target.attachToTarget`,
//! `Page.navigate`, `Runtime.evaluate`, `Input.dispatchMouseEvent`,
//! `Emulation.setDeviceMetricsOverride`, `Page.captureScreenshot`), so a few lines of
//! `serde_json` replace a CDP crate and its generated bindings of the whole protocol.
//!
//! Every exception thrown by a page's scripts, every console error and every request the
//! page makes is recorded, so tests can assert that a page ran cleanly and stayed on its
//! origin. [`Browser::launch`] returns `None` with a `SKIPPED` line when no Chromium is
//! installed, except under `CI=true`, where `.ci/run` installs Debian's `chromium` and a
//! missing browser fails the test.

use std::collections::VecDeque;
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError};
use std::time::{Duration, Instant};

use base64::Engine as _;
use serde_json::{json, Value};

/// How long one protocol command may take.
const COMMAND_TIMEOUT: Duration = Duration::from_secs(60);

/// The Chromium to use: `SEASONLOC_CHROMIUM`, else the first of the usual names on `PATH`.
pub fn chromium() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("SEASONLOC_CHROMIUM") {
        return Some(PathBuf::from(p));
    }
    let path = std::env::var_os("PATH")?;
    for dir in std::env::split_paths(&path) {
        for name in ["chromium", "chromium-browser", "google-chrome"] {
            let candidate = dir.join(name);
            if candidate.is_file() {
                return Some(candidate);
            }
        }
    }
    None
}

/// Where screenshots of test runs go (`target/tmp/dashboard-shots`).
pub fn shots_dir() -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("dashboard-shots");
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// One headless Chromium with one page (tab).
pub struct Browser {
    child: Child,
    stdin: ChildStdin,
    incoming: Receiver<Value>,
    next_id: u64,
    session: String,
    /// Events received while waiting for answers, oldest first.
    events: VecDeque<Value>,
    /// URLs of every request the page made.
    pub requests: Vec<String>,
    /// Uncaught exceptions and console errors of the page's scripts.
    pub errors: Vec<String>,
    _profile: tempfile::TempDir,
}

impl Browser {
    /// Starts Chromium with a fresh profile and opens one blank page of `width` x `height`
    /// CSS pixels; `None` (after printing why) when no Chromium is installed.
    pub fn launch(width: u32, height: u32) -> Option<Browser> {
        let Some(chrome) = chromium() else {
            let why = "no chromium on PATH (apt-get install chromium, or set SEASONLOC_CHROMIUM)";
            // CI installs chromium: there a missing browser is a failure, never a silent skip.
            assert!(
                std::env::var("CI").as_deref() != Ok("true"),
                "CI=true but {why}"
            );
            eprintln!("SKIPPED: {why}");
            return None;
        };
        let profile = tempfile::tempdir().unwrap();
        static LAUNCHES: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let n = LAUNCHES.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let log_name = format!("chromium-{}-{n}.log", std::process::id());
        let log = std::fs::File::create(shots_dir().join(log_name)).unwrap();
        // `sh` moves our pipes to fds 3 (commands in) and 4 (answers out), then becomes Chromium.
        let mut child = Command::new("sh")
            .arg("-c")
            .arg(r#"exec "$0" "$@" 3<&0 4>&1 </dev/null >/dev/null"#)
            .arg(&chrome)
            .args([
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-quic",
                "--no-first-run",
                "--no-default-browser-check",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--disable-extensions",
                "--disable-default-apps",
                "--disable-dev-shm-usage",
                "--hide-scrollbars",
                "--mute-audio",
                "--remote-debugging-pipe",
            ])
            .arg(format!("--user-data-dir={}", profile.path().display()))
            .arg(format!("--window-size={width},{height}"))
            .arg("about:blank")
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(log)
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {}: {e}", chrome.display()));
        let stdin = child.stdin.take().unwrap();
        let stdout = child.stdout.take().unwrap();
        let (tx, incoming) = mpsc::channel();
        std::thread::spawn(move || {
            let mut reader = BufReader::new(stdout);
            let mut buf = Vec::new();
            loop {
                buf.clear();
                match reader.read_until(0, &mut buf) {
                    Ok(0) | Err(_) => return,
                    Ok(_) => {
                        if buf.last() == Some(&0) {
                            buf.pop();
                        }
                        let Ok(v) = serde_json::from_slice::<Value>(&buf) else {
                            continue;
                        };
                        if tx.send(v).is_err() {
                            return;
                        }
                    }
                }
            }
        });
        let mut b = Browser {
            child,
            stdin,
            incoming,
            next_id: 0,
            session: String::new(),
            events: VecDeque::new(),
            requests: Vec::new(),
            errors: Vec::new(),
            _profile: profile,
        };
        let target = b.send(None, "Target.createTarget", json!({"url": "about:blank"}));
        let target = target["targetId"].as_str().unwrap().to_string();
        let attached = b.send(
            None,
            "Target.attachToTarget",
            json!({"targetId": target, "flatten": true}),
        );
        b.session = attached["sessionId"].as_str().unwrap().to_string();
        for domain in [
            "Page.enable",
            "Runtime.enable",
            "Network.enable",
            "Log.enable",
        ] {
            b.call(domain, json!({}));
        }
        b.viewport(width, height);
        Some(b)
    }

    /// Sends one command (to the page's session unless `session` is `None`) and waits for its
    /// answer; a protocol error fails the test.
    fn send(&mut self, session: Option<String>, method: &str, params: Value) -> Value {
        self.next_id += 1;
        let id = self.next_id;
        let mut msg = json!({"id": id, "method": method, "params": params});
        if let Some(s) = session {
            msg["sessionId"] = Value::String(s);
        }
        let mut bytes = serde_json::to_vec(&msg).unwrap();
        bytes.push(0);
        self.stdin
            .write_all(&bytes)
            .and_then(|()| self.stdin.flush())
            .unwrap_or_else(|e| panic!("chromium stopped reading commands ({method}): {e}"));
        let deadline = Instant::now() + COMMAND_TIMEOUT;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let v = match self.incoming.recv_timeout(left) {
                Ok(v) => v,
                Err(RecvTimeoutError::Timeout) => panic!("no answer to {method} in time"),
                Err(RecvTimeoutError::Disconnected) => {
                    panic!("chromium exited during {method}")
                }
            };
            if v["id"].as_u64() == Some(id) {
                if let Some(err) = v.get("error") {
                    panic!("{method} failed: {err}");
                }
                return v["result"].clone();
            }
            self.note(v);
        }
    }

    /// Records an event: requests, exceptions and console errors are kept.
    fn note(&mut self, v: Value) {
        match v["method"].as_str() {
            Some("Network.requestWillBeSent") => {
                if let Some(url) = v["params"]["request"]["url"].as_str() {
                    self.requests.push(url.to_string());
                }
            }
            Some("Runtime.exceptionThrown") => {
                let d = &v["params"]["exceptionDetails"];
                let text = d["exception"]["description"]
                    .as_str()
                    .or(d["text"].as_str())
                    .unwrap_or("exception");
                self.errors.push(format!("exception: {text}"));
            }
            Some("Runtime.consoleAPICalled") if v["params"]["type"] == "error" => {
                self.errors
                    .push(format!("console.error: {}", v["params"]["args"]));
            }
            Some("Log.entryAdded") if v["params"]["entry"]["level"] == "error" => {
                let e = &v["params"]["entry"];
                let url = e["url"].as_str().unwrap_or("");
                self.errors.push(format!("log: {} {url}", e["text"]));
            }
            _ => self.events.push_back(v),
        }
        while self.events.len() > 1000 {
            self.events.pop_front();
        }
    }

    /// A command on the page's session.
    pub fn call(&mut self, method: &str, params: Value) -> Value {
        let session = self.session.clone();
        self.send(Some(session), method, params)
    }

    /// Sets the page's size in CSS pixels (a laptop is 1280 x 800, a tablet 768 x 1024).
    pub fn viewport(&mut self, width: u32, height: u32) {
        self.call(
            "Emulation.setDeviceMetricsOverride",
            json!({"width": width, "height": height, "deviceScaleFactor": 1, "mobile": false}),
        );
    }

    /// Loads `url` and waits until the dashboard's script has drawn the page
    /// (`body[data-ready]`).
    pub fn goto(&mut self, url: &str) {
        let r = self.call("Page.navigate", json!({"url": url}));
        if let Some(e) = r.get("errorText") {
            panic!("navigating to {url}: {e}");
        }
        self.wait_for(
            "document.readyState === 'complete' && document.body && document.body.dataset.ready === '1'",
            Duration::from_secs(30),
        )
        .unwrap_or_else(|e| panic!("{url} did not finish drawing: {e}"));
    }

    /// Evaluates `expression` in the page (awaiting a promise) and returns its JSON value;
    /// an exception fails the test with its message.
    pub fn eval(&mut self, expression: &str) -> Value {
        let r = self.call(
            "Runtime.evaluate",
            json!({"expression": expression, "returnByValue": true, "awaitPromise": true}),
        );
        if let Some(e) = r.get("exceptionDetails") {
            panic!("evaluating `{expression}`: {e}");
        }
        r["result"]["value"].clone()
    }

    /// The text a person sees on the page.
    pub fn text(&mut self) -> String {
        self.eval("document.body.innerText")
            .as_str()
            .unwrap_or("")
            .to_string()
    }

    /// The visible text of the first element matching `selector` (`None` when absent).
    pub fn text_of(&mut self, selector: &str) -> Option<String> {
        let js = format!(
            "(() => {{ const e = document.querySelector({}); return e ? e.innerText : null; }})()",
            Value::String(selector.to_string())
        );
        self.eval(&js).as_str().map(str::to_string)
    }

    /// Polls `condition` (a JS expression) every 100 ms until it is true; `Err` with the page's
    /// text when `timeout` passes first.
    pub fn wait_for(&mut self, condition: &str, timeout: Duration) -> Result<(), String> {
        let deadline = Instant::now() + timeout;
        let js = format!("Boolean({condition})");
        loop {
            let r = self.call(
                "Runtime.evaluate",
                json!({"expression": js, "returnByValue": true}),
            );
            if r["result"]["value"] == Value::Bool(true) {
                return Ok(());
            }
            if Instant::now() > deadline {
                let text = self
                    .call(
                        "Runtime.evaluate",
                        json!({"expression": "document.body ? document.body.innerText : ''", "returnByValue": true}),
                    )["result"]["value"]
                    .clone();
                return Err(format!("`{condition}` still false; the page shows: {text}"));
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// A real mouse click (press and release) at viewport coordinates.
    pub fn click(&mut self, x: f64, y: f64) {
        for kind in ["mouseMoved", "mousePressed", "mouseReleased"] {
            self.call(
                "Input.dispatchMouseEvent",
                json!({"type": kind, "x": x, "y": y, "button": "left", "clickCount": 1}),
            );
        }
    }

    /// Scrolls `selector` into view and returns the viewport centre of its box.
    pub fn center_of(&mut self, selector: &str) -> (f64, f64) {
        let js = format!(
            "(() => {{ const e = document.querySelector({}); if (!e) return null; \
             e.scrollIntoView({{block: 'center'}}); const r = e.getBoundingClientRect(); \
             return [r.left + r.width / 2, r.top + r.height / 2]; }})()",
            Value::String(selector.to_string())
        );
        let v = self.eval(&js);
        let xy = v
            .as_array()
            .unwrap_or_else(|| panic!("no element {selector} on the page"));
        (xy[0].as_f64().unwrap(), xy[1].as_f64().unwrap())
    }

    /// Saves a PNG of the whole page (not only the viewport) to `path`.
    pub fn screenshot(&mut self, path: &Path) {
        let r = self.call(
            "Page.captureScreenshot",
            json!({"format": "png", "captureBeyondViewport": true}),
        );
        let data = r["data"].as_str().expect("screenshot data");
        let png = base64::engine::general_purpose::STANDARD
            .decode(data)
            .expect("screenshot is base64");
        std::fs::write(path, png).unwrap();
    }

    /// The errors recorded since the last call (collecting what arrived until now).
    pub fn take_errors(&mut self) -> Vec<String> {
        self.eval("0");
        std::mem::take(&mut self.errors)
    }

    /// Fails the test if the page's scripts threw or logged an error since the last check.
    pub fn assert_no_script_errors(&mut self, page: &str) {
        let errors = self.take_errors();
        assert!(errors.is_empty(), "{page}: script errors: {errors:#?}");
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let mut bytes = serde_json::to_vec(&json!({"id": 0, "method": "Browser.close"})).unwrap();
        bytes.push(0);
        let _ = self.stdin.write_all(&bytes);
        let _ = self.stdin.flush();
        let deadline = Instant::now() + Duration::from_secs(10);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
