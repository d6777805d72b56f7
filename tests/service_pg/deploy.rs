//! The Kubernetes manifests (`deploy/`) as a cluster would run them, without a cluster: the
//! objects `kubectl apply -k deploy/` creates, plus the Secrets of `secret.example.yaml`, are
//! read; a container is assembled from them the way the kubelet does (the image's `ENV`, then
//! `envFrom`, then `env`; Secret volumes as files at their mount paths, here under a temporary
//! root); and the real binary is started with that environment on this test's PostgreSQL
//! server. What the manifests promise is then asked of it: the probes' paths answer, access
//! control is on, nothing is written outside the mounts (the root file system is read-only in
//! the pod), and SIGTERM ends it cleanly within the grace period.
//!
//! Only the listen address is changed (loopback, an ephemeral port: servers that tests start
//! stay on 127.0.0.1), and the placeholders of the example Secrets (the database URL, the key
//! digests) are replaced with working values, after checking that the example as shipped
//! cannot start a replica.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Deserialize;
use serde_yaml::Value;
use sha2::{Digest, Sha256};

use crate::common::{engine_database, Process};
use crate::dockerfile::runtime_stage;

fn deploy_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy")
}

/// Every document of a YAML file.
fn documents(file: &Path) -> Vec<Value> {
    let text = std::fs::read_to_string(file).unwrap_or_else(|e| panic!("{}: {e}", file.display()));
    serde_yaml::Deserializer::from_str(&text)
        .map(|d| Value::deserialize(d).unwrap_or_else(|e| panic!("{}: {e}", file.display())))
        .filter(|v| !v.is_null())
        .collect()
}

/// The objects of the kustomization (its `resources`) and of the example Secrets.
struct Manifests {
    objects: Vec<Value>,
}

impl Manifests {
    fn load() -> Manifests {
        let dir = deploy_dir();
        let kustomization = &documents(&dir.join("kustomization.yaml"))[0];
        let mut objects = Vec::new();
        for r in seq(&kustomization["resources"]) {
            objects.extend(documents(&dir.join(str_of(r))));
        }
        objects.extend(documents(&dir.join("secret.example.yaml")));
        Manifests { objects }
    }

    fn one(&self, kind: &str) -> &Value {
        let found: Vec<&Value> = self.objects.iter().filter(|o| o["kind"] == kind).collect();
        assert_eq!(found.len(), 1, "exactly one {kind} expected");
        found[0]
    }

    fn named(&self, kind: &str, name: &str) -> &Value {
        self.objects
            .iter()
            .find(|o| o["kind"] == kind && o["metadata"]["name"] == name)
            .unwrap_or_else(|| panic!("{kind} `{name}` is referenced but not in deploy/"))
    }
}

fn seq(v: &Value) -> &[Value] {
    v.as_sequence().map(Vec::as_slice).unwrap_or(&[])
}

fn str_of(v: &Value) -> &str {
    v.as_str()
        .unwrap_or_else(|| panic!("a string expected, got {v:?}"))
}

/// `stringData` of a Secret or `data` of a ConfigMap, as strings.
fn string_map(v: &Value) -> BTreeMap<String, String> {
    v.as_mapping()
        .map(|m| {
            m.iter()
                .map(|(k, v)| (str_of(k).to_string(), str_of(v).to_string()))
                .collect()
        })
        .unwrap_or_default()
}

/// `matchLabels` `selector` picks the pod template's labels.
fn selects(selector: &Value, labels: &Value) {
    let (want, have) = (string_map(selector), string_map(labels));
    assert!(!want.is_empty(), "empty selector");
    for (k, v) in &want {
        assert_eq!(
            have.get(k),
            Some(v),
            "selector {k}={v} does not match the pods"
        );
    }
}

/// The container as the kubelet would run it.
struct Container {
    env: BTreeMap<String, String>,
    /// Mount path -> files (name -> content) of the Secret mounted there (none for an
    /// emptyDir).
    mounts: Vec<(String, BTreeMap<String, String>)>,
    port: u16,
    readiness: String,
    liveness: String,
    grace_secs: u64,
}

fn container(m: &Manifests) -> Container {
    let deployment = m.one("Deployment");
    let spec = &deployment["spec"];
    let pod = &spec["template"]["spec"];
    selects(
        &spec["selector"]["matchLabels"],
        &spec["template"]["metadata"]["labels"],
    );
    let containers = seq(&pod["containers"]);
    assert_eq!(containers.len(), 1, "one container per pod");
    let c = &containers[0];

    // The image's ENV, then envFrom in order, then env.
    let mut env: BTreeMap<String, String> = runtime_stage().env.into_iter().collect();
    for from in seq(&c["envFrom"]) {
        let (kind, field, r) = if from["configMapRef"].is_mapping() {
            ("ConfigMap", "data", &from["configMapRef"])
        } else {
            ("Secret", "stringData", &from["secretRef"])
        };
        env.extend(string_map(&m.named(kind, str_of(&r["name"]))[field]));
    }
    for e in seq(&c["env"]) {
        env.insert(str_of(&e["name"]).into(), str_of(&e["value"]).into());
    }

    // Secret volumes: their files at the mount paths.
    let mut mounts = Vec::new();
    for vm in seq(&c["volumeMounts"]) {
        let name = &vm["name"];
        let volume = seq(&pod["volumes"])
            .iter()
            .find(|v| &v["name"] == name)
            .unwrap_or_else(|| panic!("volumeMount {name:?} has no volume"));
        // A writable scratch folder (the root file system is read-only): empty at the start.
        if volume["emptyDir"].is_mapping() {
            mounts.push((str_of(&vm["mountPath"]).to_string(), BTreeMap::new()));
            continue;
        }
        let secret = &volume["secret"];
        assert!(
            secret.is_mapping(),
            "only Secret and emptyDir volumes are modelled here"
        );
        let data = string_map(&m.named("Secret", str_of(&secret["secretName"]))["stringData"]);
        let files = match secret["items"].as_sequence() {
            Some(items) => items
                .iter()
                .map(|it| {
                    let key = str_of(&it["key"]);
                    let content = data
                        .get(key)
                        .unwrap_or_else(|| panic!("the Secret has no key `{key}`"));
                    (str_of(&it["path"]).to_string(), content.clone())
                })
                .collect(),
            None => data,
        };
        assert!(
            vm["subPath"].is_null(),
            "a subPath mount never sees a changed Secret"
        );
        mounts.push((str_of(&vm["mountPath"]).to_string(), files));
    }

    // Ports and probes: named ports of this container.
    let ports = seq(&c["ports"]);
    let named_port = |name: &Value| -> u16 {
        let p = ports
            .iter()
            .find(|p| &p["name"] == name)
            .unwrap_or_else(|| panic!("no container port named {name:?}"));
        p["containerPort"].as_u64().unwrap() as u16
    };
    let probe = |which: &str| -> (String, u16) {
        let get = &c[which]["httpGet"];
        (str_of(&get["path"]).to_string(), named_port(&get["port"]))
    };
    let (readiness, rp) = probe("readinessProbe");
    let (liveness, lp) = probe("livenessProbe");
    let port = named_port(&Value::from("http"));
    assert_eq!((rp, lp), (port, port));
    Container {
        env,
        mounts,
        port,
        readiness,
        liveness,
        grace_secs: pod["terminationGracePeriodSeconds"].as_u64().unwrap_or(30),
    }
}

#[test]
fn the_objects_fit_together() {
    let m = Manifests::load();
    let c = container(&m);
    let deployment = m.one("Deployment");
    let labels = &deployment["spec"]["template"]["metadata"]["labels"];
    // The Service and the PodDisruptionBudget select the Deployment's pods.
    let service = m.one("Service");
    selects(&service["spec"]["selector"], labels);
    assert!(seq(&service["spec"]["ports"])
        .iter()
        .all(|p| p["targetPort"] == "http"));
    let pdb = m.one("PodDisruptionBudget");
    selects(&pdb["spec"]["selector"]["matchLabels"], labels);
    let replicas = deployment["spec"]["replicas"].as_u64().unwrap();
    let min_available = pdb["spec"]["minAvailable"].as_u64().unwrap();
    assert!(min_available < replicas, "a drain could never evict a pod");
    // The container listens where its port says.
    let addr = &c.env["SEASONLOC_ADDR"];
    assert_eq!(addr, &format!("0.0.0.0:{}", c.port));
    // The service's own drain ends before the kubelet's SIGKILL.
    let drain: u64 = c.env["SEASONLOC_SHUTDOWN_TIMEOUT_SECS"].parse().unwrap();
    assert!(
        drain < c.grace_secs,
        "drain {drain} s >= grace period {} s",
        c.grace_secs
    );
    // Every absolute path the service is given exists in the pod: a mounted file, or (the
    // embedded store's folder, unused on PostgreSQL) on the image.
    let keys = &c.env["SEASONLOC_API_KEYS"];
    assert!(
        c.mounts
            .iter()
            .any(|(at, files)| files.keys().any(|f| &format!("{at}/{f}") == keys)),
        "SEASONLOC_API_KEYS={keys} is not a file of any mounted Secret: the replicas could not start"
    );
    assert!(
        c.env.contains_key("SEASONLOC_DATABASE_URL"),
        "replicas need the shared database"
    );
    // Unless the pod opts out, the kubelet mounts an API token at
    // /var/run/secrets/kubernetes.io/serviceaccount. On the Debian image /var/run is /run, so a
    // volume mounted at /run/secrets (or above it) leaves no place to create that mount point
    // (the volume is read-only) and the container never starts (kubernetes/kubernetes#65835).
    let token = "/run/secrets/kubernetes.io/serviceaccount";
    let under_run = |at: &str| -> String {
        let at = at.trim_end_matches('/');
        at.strip_prefix("/var")
            .filter(|rest| rest.starts_with("/run"))
            .unwrap_or(at)
            .to_string()
    };
    if let Some((at, _)) = c.mounts.iter().find(|(at, _)| {
        let at = under_run(at);
        token == at || token.starts_with(&format!("{at}/"))
    }) {
        assert_eq!(
            deployment["spec"]["template"]["spec"]["automountServiceAccountToken"],
            Value::Bool(false),
            "a volume at {at} covers the API token's mount point: the pod must not mount a token"
        );
    }
    // Every setting is one the binary reads: an unknown name (a typo) would be ignored silently.
    let help = std::process::Command::new(env!("CARGO_BIN_EXE_seasonloc"))
        .args(["serve", "--help"])
        .output()
        .unwrap();
    let help = String::from_utf8_lossy(&help.stdout);
    for name in c.env.keys().filter(|k| k.starts_with("SEASONLOC_")) {
        assert!(
            help.contains(&format!("[env: {name}")),
            "{name} is set by the manifests but `seasonloc serve` has no such setting"
        );
    }
}

/// Where a path of the pod lands under `root`: mounts under `root/mounts`, the rest of the
/// (read-only) image file system under `root/image`.
fn host_path(root: &Path, c: &Container, path: &str) -> PathBuf {
    for (i, (at, _)) in c.mounts.iter().enumerate() {
        if let Some(rest) = path.strip_prefix(at.as_str()) {
            return root
                .join(format!("mounts/{i}"))
                .join(rest.trim_start_matches('/'));
        }
    }
    root.join("image").join(path.trim_start_matches('/'))
}

/// The container's environment with its paths moved under `root` and the listen address on
/// loopback.
fn host_env(root: &Path, c: &Container) -> Vec<(String, String)> {
    for (i, (_, files)) in c.mounts.iter().enumerate() {
        let dir = root.join(format!("mounts/{i}"));
        std::fs::create_dir_all(&dir).unwrap();
        for (name, content) in files {
            std::fs::write(dir.join(name), content).unwrap();
        }
    }
    std::fs::create_dir_all(root.join("image")).unwrap();
    c.env
        .iter()
        .map(|(k, v)| {
            let v = if k == "SEASONLOC_ADDR" {
                "127.0.0.1:0".to_string()
            } else if v.starts_with('/') {
                host_path(root, c, v).to_string_lossy().into_owned()
            } else {
                v.clone()
            };
            (k.clone(), v)
        })
        .collect()
}

#[test]
fn a_replica_starts_from_the_manifests_and_serves_with_keys() {
    let Some(url) = engine_database() else { return };
    let m = Manifests::load();
    let mut c = container(&m);
    let tmp = tempfile::tempdir().unwrap();
    let keys_at = c.env["SEASONLOC_API_KEYS"].clone();

    // As shipped, the example Secrets do not start a replica (placeholder digests).
    let root = tmp.path().join("as-shipped");
    let mut env = host_env(&root, &c);
    env.retain(|(k, _)| k != "SEASONLOC_DATABASE_URL");
    env.push(("SEASONLOC_DATABASE_URL".into(), url.clone()));
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_seasonloc"))
        .arg("serve")
        .env_clear()
        .envs(env.iter().map(|(k, v)| (k, v)))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success(),
        "the example key file was accepted:\n{err}"
    );
    assert!(
        err.contains("sha256") && err.contains("64 hexadecimal digits"),
        "{err}"
    );

    // With real digests it serves.
    let key = "k8s-test-admin-key";
    let digest: String = Sha256::digest(key.as_bytes())
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    // One admin key (the example's first entry) with a real digest.
    for (_, files) in &mut c.mounts {
        for content in files.values_mut() {
            let mut file: serde_json::Value = serde_json::from_str(content).unwrap();
            let entries = file["keys"].as_array_mut().unwrap();
            entries.truncate(1);
            assert_eq!(entries[0]["role"], "admin");
            entries[0]["sha256"] = digest.clone().into();
            *content = file.to_string();
        }
    }
    let root = tmp.path().join("pod");
    let mut env = host_env(&root, &c);
    env.retain(|(k, _)| k != "SEASONLOC_DATABASE_URL");
    env.push(("SEASONLOC_DATABASE_URL".into(), url));
    let env_refs: Vec<(&str, &str)> = env.iter().map(|(k, v)| (k.as_str(), v.as_str())).collect();
    let p = Process::start(&[], &env_refs, &tmp.path().join("log"));
    let log = || std::fs::read_to_string(tmp.path().join("log")).unwrap_or_default();
    assert!(log().contains("access control on"), "{}", log());
    assert!(log().contains(&host_path(&root, &c, &keys_at).display().to_string()));

    let client = p.client;
    assert_eq!(
        client.get(&c.readiness).status,
        200,
        "readiness {}",
        c.readiness
    );
    assert_eq!(
        client.get(&c.liveness).status,
        200,
        "liveness {}",
        c.liveness
    );
    let create = serde_json::json!({"name": "k8s", "descriptor": {"kind": "hog", "cell_size": 8}});
    let body = serde_json::to_vec(&create).unwrap();
    let anonymous = client.request("POST", "/v1/maps", Some("application/json"), &body);
    assert_eq!(
        anonymous.status, 401,
        "a change without a key was let through"
    );
    let bearer = format!("Bearer {key}");
    let auth = [("Authorization", bearer.as_str())];
    let made = client.request_with("POST", "/v1/maps", &auth, Some("application/json"), &body);
    assert_eq!(made.status, 201, "{}", String::from_utf8_lossy(&made.body));
    let listed = client.request_with("GET", "/v1/maps", &auth, None, &[]);
    assert_eq!(listed.status, 200);
    assert!(String::from_utf8_lossy(&listed.body).contains("\"k8s\""));

    // SIGTERM (what the kubelet sends first): a clean exit.
    assert!(p.terminate(), "{}", log());
    // Nothing was written outside the mounts: the pod's root file system is read-only.
    let written: Vec<_> = std::fs::read_dir(root.join("image")).unwrap().collect();
    assert!(
        written.is_empty(),
        "wrote to the image's file system: {written:?}"
    );
}
