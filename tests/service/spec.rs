//! `openapi/openapi.yaml` kept honest: the routes it lists are exactly the router's, the served
//! `/openapi.json` is the same document, and every response the other tests receive is checked
//! against the schema the document declares for that route and status (a small JSON-schema
//! validator for the subset the document uses).

use std::sync::OnceLock;

use serde_json::Value;

use crate::common::Server;
use crate::http::Response;

pub fn doc() -> &'static Value {
    static DOC: OnceLock<Value> = OnceLock::new();
    DOC.get_or_init(|| {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/openapi/openapi.yaml");
        let text = std::fs::read_to_string(path).unwrap();
        serde_yaml::from_str(&text).unwrap()
    })
}

fn resolve<'a>(doc: &'a Value, v: &'a Value) -> &'a Value {
    match v.get("$ref").and_then(Value::as_str) {
        Some(r) => {
            let pointer = r.strip_prefix('#').expect("local refs only");
            resolve(
                doc,
                doc.pointer(pointer)
                    .unwrap_or_else(|| panic!("dangling $ref {r}")),
            )
        }
        None => v,
    }
}

/// Checks `value` against `schema`; the error names the JSON path.
pub fn validate(schema: &Value, value: &Value, path: &str) -> Result<(), String> {
    let doc = doc();
    let schema = resolve(doc, schema);
    if value.is_null() {
        if schema["nullable"] == Value::Bool(true) {
            return Ok(());
        }
        if schema.get("type").is_some() || schema.get("allOf").is_some() {
            return Err(format!("{path}: null but not nullable"));
        }
    }
    if let Some(all) = schema.get("allOf").and_then(Value::as_array) {
        for s in all {
            validate(s, value, path)?;
        }
    }
    if let Some(any) = schema.get("oneOf").and_then(Value::as_array) {
        let ok = any
            .iter()
            .filter(|s| validate(s, value, path).is_ok())
            .count();
        if ok != 1 {
            return Err(format!("{path}: {value} matches {ok} of the oneOf schemas"));
        }
    }
    if let Some(e) = schema.get("enum").and_then(Value::as_array) {
        if !e.contains(value) {
            return Err(format!("{path}: {value} not in {e:?}"));
        }
    }
    let Some(ty) = schema.get("type").and_then(Value::as_str) else {
        return Ok(());
    };
    let type_ok = match ty {
        "object" => value.is_object(),
        "array" => value.is_array(),
        "string" => value.is_string(),
        "integer" => value.is_u64() || value.is_i64(),
        "number" => value.is_number(),
        "boolean" => value.is_boolean(),
        other => {
            return Err(format!(
                "{path}: schema type {other} unsupported by the checker"
            ))
        }
    };
    if !type_ok {
        return Err(format!("{path}: expected {ty}, got {value}"));
    }
    if let Some(p) = schema.get("pattern").and_then(Value::as_str) {
        // The document's patterns: the id format, and "not all blank" on names.
        let s = value.as_str().unwrap_or("");
        match p {
            "^[0-9a-f]{16}$" => {
                if !(s.len() == 16
                    && s.bytes()
                        .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b)))
                {
                    return Err(format!("{path}: {s:?} is not an id"));
                }
            }
            "\\S" => {
                if s.chars().all(char::is_whitespace) {
                    return Err(format!("{path}: {s:?} is blank"));
                }
            }
            other => panic!("pattern {other:?} unsupported by the checker"),
        }
    }
    if let Some(min) = schema.get("minimum").and_then(Value::as_f64) {
        if value.as_f64().is_some_and(|v| v < min) {
            return Err(format!("{path}: {value} < {min}"));
        }
    }
    if let Some(max) = schema.get("maximum").and_then(Value::as_f64) {
        if value.as_f64().is_some_and(|v| v > max) {
            return Err(format!("{path}: {value} > {max}"));
        }
    }
    if ty == "object" {
        let obj = value.as_object().expect("checked above");
        let props = schema.get("properties").and_then(Value::as_object);
        for r in schema
            .get("required")
            .and_then(Value::as_array)
            .into_iter()
            .flatten()
        {
            let r = r.as_str().unwrap();
            if !obj.contains_key(r) {
                return Err(format!("{path}: missing required `{r}`"));
            }
        }
        for (k, v) in obj {
            match props.and_then(|p| p.get(k)) {
                Some(s) => validate(s, v, &format!("{path}.{k}"))?,
                None if schema["additionalProperties"] == Value::Bool(false) => {
                    return Err(format!("{path}: `{k}` is not in the schema"))
                }
                None => {}
            }
        }
    }
    if ty == "array" {
        if let Some(items) = schema.get("items") {
            for (i, v) in value.as_array().expect("checked above").iter().enumerate() {
                validate(items, v, &format!("{path}[{i}]"))?;
            }
        }
    }
    Ok(())
}

/// Asserts that `r` is a response the document declares for `method template` and matches
/// its JSON schema.
pub fn check(method: &str, template: &str, r: &Response) {
    let doc = doc();
    let op = &doc["paths"][template][method.to_ascii_lowercase()];
    assert!(op.is_object(), "openapi.yaml has no {method} {template}");
    let status = r.status.to_string();
    let declared = resolve(doc, &op["responses"][&status]);
    assert!(
        declared.is_object(),
        "openapi.yaml does not declare status {status} for {method} {template}: {}",
        String::from_utf8_lossy(&r.body)
    );
    match declared["content"].get("application/json") {
        Some(content) => {
            let body = r.json();
            if let Err(e) = validate(&content["schema"], &body, "$") {
                panic!(
                    "{method} {template} {status}: response drifted from openapi.yaml: {e}\n{body}"
                );
            }
        }
        None => {
            if declared.get("content").is_none() {
                assert!(
                    r.body.is_empty(),
                    "{method} {template} {status}: undeclared body"
                );
            }
        }
    }
}

/// Every documented (method, path) pair.
fn documented() -> Vec<(String, String)> {
    let mut out = Vec::new();
    for (path, item) in doc()["paths"].as_object().unwrap() {
        for method in ["get", "post", "put", "patch", "delete"] {
            if item.get(method).is_some() {
                out.push((method.to_string(), path.clone()));
            }
        }
    }
    out.sort();
    out
}

#[test]
fn documented_routes_are_exactly_the_routers() {
    let mut routes: Vec<(String, String)> = seasonloc_server::api::ROUTES
        .iter()
        .map(|(m, p)| (m.to_string(), p.to_string()))
        .collect();
    routes.sort();
    assert_eq!(documented(), routes);
}

#[test]
fn every_documented_route_is_served() {
    let server = Server::start();
    let c = server.client;
    for (method, path) in documented() {
        let concrete = path.replace("{id}", "00000000ffffffff");
        let r = c.request(
            &method.to_ascii_uppercase(),
            &concrete,
            Some("application/json"),
            b"{}",
        );
        assert!(r.status != 405, "{method} {path} is not routed");
        if r.status == 404 {
            assert_ne!(r.code(), "route_not_found", "{method} {path} is not routed");
        }
        check(&method, &path, &r);
    }
    let r = c.get("/v1/nothing-here");
    assert_eq!((r.status, r.code().as_str()), (404, "route_not_found"));
    let r = c.request("PUT", "/v1/maps", None, b"");
    assert_eq!((r.status, r.code().as_str()), (405, "method_not_allowed"));
}

/// The error codes the document lists are exactly the one table's (`seasonloc_app::ErrorCode`).
#[test]
fn documented_error_codes_are_exactly_the_tables() {
    let listed: std::collections::BTreeSet<String> = doc()["components"]["schemas"]["Error"]
        ["properties"]["error"]["properties"]["code"]["enum"]
        .as_array()
        .expect("openapi.yaml lists the error codes")
        .iter()
        .map(|c| c.as_str().unwrap().to_string())
        .collect();
    let table: std::collections::BTreeSet<String> = seasonloc_app::ErrorCode::ALL
        .iter()
        .map(|c| c.as_str().to_string())
        .collect();
    assert_eq!(listed, table);
}

#[test]
fn served_openapi_json_is_the_shipped_yaml() {
    let server = Server::start();
    let r = server.client.get("/openapi.json");
    assert_eq!(r.status, 200);
    assert_eq!(&r.json(), doc());
}

#[test]
fn the_checker_catches_drift() {
    let map = serde_json::json!({"id": "0000000000000001", "name": "a", "descriptor": {"kind": "hog"},
        "descriptor_dim": null, "image_count": 0, "created_at_ms": 1});
    let schema = serde_json::json!({"$ref": "#/components/schemas/Map"});
    validate(&schema, &map, "$").unwrap();
    let mut extra = map.clone();
    extra["surprise"] = serde_json::json!(1);
    assert!(validate(&schema, &extra, "$").is_err());
    let mut missing = map.clone();
    missing.as_object_mut().unwrap().remove("image_count");
    assert!(validate(&schema, &missing, "$").is_err());
    let mut wrong = map;
    wrong["id"] = serde_json::json!("xyz");
    assert!(validate(&schema, &wrong, "$").is_err());
    // Numeric bounds on both sides: a CNN divisor is a normal f32 of either sign.
    let cnn = serde_json::json!({"$ref": "#/components/schemas/CnnDescriptor"});
    let with_scale = |s: f64| serde_json::json!({"kind": "cnn", "layer": "x", "scale": [s, 1, 1]});
    validate(&cnn, &with_scale(128.0), "$").unwrap();
    validate(&cnn, &with_scale(-0.5), "$").unwrap();
    assert!(validate(&cnn, &with_scale(0.0), "$").is_err());
    assert!(validate(&cnn, &with_scale(1e39), "$").is_err());
}
