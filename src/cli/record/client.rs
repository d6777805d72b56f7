//! A small blocking client of the service's HTTP API for `import` and `drive` (ureq): the key
//! as a bearer token, JSON bodies, multipart image batches with an `Idempotency-Key`, and the
//! API's error body turned into one line (`409 idempotency_key_reused: ...`).

use std::time::Duration;

use anyhow::{bail, Context, Result};
use serde_json::Value;

/// The service at `base` (`http://host:port`), with an optional API key.
pub struct Client {
    agent: ureq::Agent,
    base: String,
    key: Option<String>,
}

/// One part of a multipart body.
pub enum Part<'a> {
    /// An `image` part.
    Image {
        /// File name sent with it.
        name: &'a str,
        /// The file's bytes.
        bytes: &'a [u8],
    },
    /// A JSON part (`metadata`).
    Json {
        /// The part's name.
        name: &'a str,
        /// Its value.
        value: &'a Value,
    },
}

impl Client {
    /// A client of `base` (no trailing slash needed).
    pub fn new(base: &str, key: Option<String>) -> Result<Client> {
        let base = base.trim_end_matches('/').to_string();
        if !(base.starts_with("http://") || base.starts_with("https://")) {
            bail!("--server `{base}` is not an http:// or https:// URL");
        }
        let agent: ureq::Agent = ureq::Agent::config_builder()
            .http_status_as_error(false)
            .timeout_global(Some(Duration::from_secs(300)))
            .build()
            .into();
        Ok(Client { agent, base, key })
    }

    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    /// `req` with the key as a bearer token, when there is one.
    fn authorized<B>(&self, req: ureq::RequestBuilder<B>) -> ureq::RequestBuilder<B> {
        match &self.key {
            Some(k) => req.header("Authorization", format!("Bearer {k}")),
            None => req,
        }
    }

    fn answer(
        &self,
        what: &str,
        response: std::result::Result<ureq::http::Response<ureq::Body>, ureq::Error>,
    ) -> Result<Value> {
        let mut response =
            response.with_context(|| format!("{what}: cannot reach {}", self.base))?;
        let status = response.status().as_u16();
        let text = response
            .body_mut()
            .with_config()
            .limit(256 * 1024 * 1024)
            .read_to_string()
            .with_context(|| format!("{what}: reading the answer"))?;
        let body: Value = serde_json::from_str(&text).unwrap_or(Value::String(text));
        if !(200..300).contains(&status) {
            let code = body["error"]["code"].as_str().unwrap_or("");
            let message = body["error"]["message"].as_str().unwrap_or("");
            bail!("{what}: the service answered {status} {code}: {message}");
        }
        Ok(body)
    }

    /// `GET path` as JSON.
    pub fn get(&self, path: &str) -> Result<Value> {
        let req = self.authorized(self.agent.get(self.url(path)));
        self.answer(&format!("GET {path}"), req.call())
    }

    /// `POST path` with a JSON body (or none) and an optional idempotency key.
    pub fn post_json(&self, path: &str, body: Option<&Value>, key: Option<&str>) -> Result<Value> {
        let mut req = self.authorized(self.agent.post(self.url(path)));
        if let Some(k) = key {
            req = req.header("Idempotency-Key", k);
        }
        let what = format!("POST {path}");
        match body {
            Some(b) => {
                let bytes = serde_json::to_vec(b)?;
                let req = req.header("Content-Type", "application/json");
                self.answer(&what, req.send(&bytes[..]))
            }
            None => self.answer(&what, req.send_empty()),
        }
    }

    /// `POST path` with a multipart body and an idempotency key.
    pub fn post_multipart(&self, path: &str, parts: &[Part<'_>], key: &str) -> Result<Value> {
        let boundary = "seasonloc-boundary-7f3a9c1e5b2d4086";
        let mut body = Vec::new();
        for part in parts {
            body.extend_from_slice(format!("--{boundary}\r\n").as_bytes());
            match part {
                Part::Image { name, bytes } => {
                    let quoted = name.replace(['"', '\r', '\n'], "_");
                    body.extend_from_slice(
                        format!(
                            "Content-Disposition: form-data; name=\"image\"; filename=\"{quoted}\"\r\n\
                             Content-Type: application/octet-stream\r\n\r\n"
                        )
                        .as_bytes(),
                    );
                    body.extend_from_slice(bytes);
                }
                Part::Json { name, value } => {
                    body.extend_from_slice(
                        format!(
                            "Content-Disposition: form-data; name=\"{name}\"\r\n\
                             Content-Type: application/json\r\n\r\n"
                        )
                        .as_bytes(),
                    );
                    body.extend_from_slice(&serde_json::to_vec(value)?);
                }
            }
            body.extend_from_slice(b"\r\n");
        }
        body.extend_from_slice(format!("--{boundary}--\r\n").as_bytes());
        let req = self
            .authorized(self.agent.post(self.url(path)))
            .header(
                "Content-Type",
                format!("multipart/form-data; boundary={boundary}"),
            )
            .header("Idempotency-Key", key);
        self.answer(&format!("POST {path}"), req.send(&body[..]))
    }
}
