//! The last stage of the Dockerfile, parsed (no Docker engine in CI): what the image runs and
//! with which environment. Shared by the Dockerfile's tests and the Kubernetes manifests' tests
//! (a pod's environment starts from the image's `ENV`).

use std::collections::HashMap;
use std::path::Path;

pub struct Runtime {
    pub env: HashMap<String, String>,
    pub user: String,
    pub expose: Vec<String>,
    pub volumes: Vec<String>,
    pub healthcheck: Vec<String>,
    pub entrypoint: Vec<String>,
    pub cmd: Vec<String>,
    pub stages: usize,
}

fn json_array(s: &str) -> Vec<String> {
    serde_json::from_str(s.trim()).unwrap_or_else(|e| panic!("exec form expected ({e}): {s}"))
}

/// Parses the last stage of the Dockerfile (continuation lines joined).
pub fn runtime_stage() -> Runtime {
    let text =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("Dockerfile")).unwrap();
    let joined = text.replace("\\\n", " ");
    let lines: Vec<&str> = joined
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .collect();
    let stages = lines.iter().filter(|l| l.starts_with("FROM ")).count();
    let last = lines.iter().rposition(|l| l.starts_with("FROM ")).unwrap();
    let mut rt = Runtime {
        env: HashMap::new(),
        user: "root".into(),
        expose: vec![],
        volumes: vec![],
        healthcheck: vec![],
        entrypoint: vec![],
        cmd: vec![],
        stages,
    };
    for l in &lines[last + 1..] {
        let (instr, rest) = l.split_once(' ').unwrap_or((l, ""));
        match instr {
            "ENV" => {
                let (k, v) = rest.split_once('=').unwrap();
                rt.env.insert(k.trim().into(), v.trim().into());
            }
            "USER" => rt.user = rest.trim().into(),
            "EXPOSE" => rt.expose.push(rest.trim().into()),
            "VOLUME" => rt.volumes.push(rest.trim().into()),
            "HEALTHCHECK" => {
                let cmd = rest.split_once("CMD").unwrap().1;
                rt.healthcheck = json_array(cmd);
            }
            "ENTRYPOINT" => rt.entrypoint = json_array(rest),
            "CMD" => rt.cmd = json_array(rest),
            _ => {}
        }
    }
    rt
}
