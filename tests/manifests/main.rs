//! The Kubernetes manifests of `deploy/` and its Grafana dashboard, checked field by field
//! without a cluster (issue 45). Each YAML file is parsed (every document of it) and the fields
//! a cluster depends on are asserted:
//!
//! * the kustomization lists files that exist and leaves the optional ones (the ServiceMonitor,
//!   a CRD; the Ingress example; the example Secrets) out of the default `kubectl apply -k`;
//! * the image is a pinned registry image, set by the kustomization's `images:` entry;
//! * the pod meets the `restricted` Pod Security Standard, its root file system is read-only
//!   and it writes only to `emptyDir` volumes (`/tmp`);
//! * Prometheus scrapes the container's port (annotations, and the optional ServiceMonitor with
//!   a `reader` key, since `/metrics` needs one);
//! * the HPA scales the Deployment on CPU, the NetworkPolicy admits only the Service's port and
//!   lets out only the database and DNS, the Ingress example terminates TLS in front of the
//!   Service;
//! * the Grafana dashboard parses, takes its data source from a variable, and queries only the
//!   metric families the service exports (so a renamed metric breaks this test).
//!
//! `tests/service_pg/deploy.rs` starts a replica from the same files; `.ci/run` also validates
//! them against the Kubernetes API schemas (`kubernetes-validate --strict`).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use serde::Deserialize;
use serde_yaml::Value;

/// The histogram families the service exports (queried as `_bucket`, `_sum`, `_count`).
const HISTOGRAMS: &[&str] = &[
    "seasonloc_http_request_duration_seconds",
    "seasonloc_stage_duration_seconds",
    "seasonloc_trip_batch_duration_seconds",
    "seasonloc_trip_frame_confidence",
    "seasonloc_localize_queue_wait_seconds",
    "seasonloc_store_operation_duration_seconds",
];

/// The other metric families the service exports (counters and gauges), process metrics
/// included.
const FAMILIES: &[&str] = &[
    "seasonloc_http_requests_total",
    "seasonloc_images_ingested_total",
    "seasonloc_queries_localized_total",
    "seasonloc_localize_rejected_total",
    "seasonloc_build_info",
    "seasonloc_trips_open",
    "seasonloc_trip_batches_total",
    "seasonloc_trip_frames_total",
    "seasonloc_trip_frames_by_status_total",
    "seasonloc_localize_queue_depth",
    "seasonloc_descriptor_cache_bytes",
    "seasonloc_descriptor_cache_maps",
    "process_resident_memory_bytes",
    "process_cpu_seconds_total",
    "process_open_fds",
    "process_max_fds",
    "process_start_time_seconds",
];

/// Files of `deploy/` that are deliberately not among the kustomization's resources.
const OPTIONAL: &[&str] = &[
    "secret.example.yaml",
    "servicemonitor.yaml",
    "ingress.example.yaml",
];

fn deploy_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy")
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Every document of a YAML file of `deploy/`.
fn documents(name: &str) -> Vec<Value> {
    let path = deploy_dir().join(name);
    let text = read(&path);
    serde_yaml::Deserializer::from_str(&text)
        .map(|d| Value::deserialize(d).unwrap_or_else(|e| panic!("{}: {e}", path.display())))
        .filter(|v| !v.is_null())
        .collect()
}

/// The one object of a file of `deploy/`, of kind `kind`.
fn object(name: &str, kind: &str) -> Value {
    let mut docs = documents(name);
    assert_eq!(docs.len(), 1, "{name}: one object expected");
    let doc = docs.remove(0);
    assert_eq!(doc["kind"].as_str(), Some(kind), "{name}: the kind");
    doc
}

fn seq(v: &Value) -> &[Value] {
    v.as_sequence().map(Vec::as_slice).unwrap_or(&[])
}

fn text<'a>(v: &'a Value, what: &str) -> &'a str {
    v.as_str()
        .unwrap_or_else(|| panic!("{what}: a string expected, got {v:?}"))
}

fn number(v: &Value, what: &str) -> u64 {
    v.as_u64()
        .unwrap_or_else(|| panic!("{what}: a number expected, got {v:?}"))
}

/// A mapping of strings (labels, `matchLabels`, `stringData`).
fn string_map(v: &Value) -> BTreeMap<String, String> {
    v.as_mapping()
        .map(|m| {
            m.iter()
                .map(|(k, v)| (text(k, "a key").to_string(), text(v, "a value").to_string()))
                .collect()
        })
        .unwrap_or_default()
}

fn kustomization() -> Value {
    object("kustomization.yaml", "Kustomization")
}

/// The labels the kustomization adds to every object (and, with `includeSelectors`, to the
/// selectors).
fn common_labels(k: &Value) -> BTreeMap<String, String> {
    let mut labels = BTreeMap::new();
    for entry in seq(&k["labels"]) {
        labels.extend(string_map(&entry["pairs"]));
    }
    labels.extend(string_map(&k["commonLabels"]));
    labels
}

fn service() -> Value {
    object("service.yaml", "Service")
}

/// `selector` (a `matchLabels`) is not empty and picks objects with `labels`.
fn assert_selects(what: &str, selector: &Value, labels: &BTreeMap<String, String>) {
    let want = string_map(selector);
    assert!(
        !want.is_empty(),
        "{what}: an empty selector selects everything"
    );
    for (k, v) in &want {
        assert_eq!(
            labels.get(k),
            Some(v),
            "{what}: {k}={v} is not among the labels {labels:?}"
        );
    }
}

/// The Deployment, with its pods' labels as the cluster sees them (the kustomization's added).
struct Server {
    deployment: Value,
    labels: BTreeMap<String, String>,
}

impl Server {
    fn load() -> Server {
        let deployment = object("deployment.yaml", "Deployment");
        let mut labels = string_map(&deployment["spec"]["template"]["metadata"]["labels"]);
        labels.extend(common_labels(&kustomization()));
        Server { deployment, labels }
    }

    fn name(&self) -> &str {
        text(
            &self.deployment["metadata"]["name"],
            "the Deployment's name",
        )
    }

    fn pod(&self) -> &Value {
        &self.deployment["spec"]["template"]["spec"]
    }

    fn container(&self) -> &Value {
        let containers = seq(&self.pod()["containers"]);
        assert_eq!(containers.len(), 1, "one container per pod");
        &containers[0]
    }

    /// The number of the container's port named `name`.
    fn port(&self, name: &str) -> u64 {
        let port = seq(&self.container()["ports"])
            .iter()
            .find(|p| p["name"].as_str() == Some(name))
            .unwrap_or_else(|| panic!("no container port named {name}"));
        number(&port["containerPort"], "containerPort")
    }
}

/// The pod's volume named `name`.
fn volume<'a>(pod: &'a Value, name: &str) -> &'a Value {
    seq(&pod["volumes"])
        .iter()
        .find(|v| v["name"].as_str() == Some(name))
        .unwrap_or_else(|| panic!("no volume named {name}"))
}

/// An image reference's name and tag (`None` without one); a digest is ignored.
fn split_image(image: &str) -> (&str, Option<&str>) {
    let without_digest = image.split('@').next().unwrap_or(image);
    match without_digest.rsplit_once(':') {
        Some((name, tag)) if !tag.contains('/') => (name, Some(tag)),
        _ => (without_digest, None),
    }
}

/// The numbers given to `flag` (`--uid`, `--gid`) in the Dockerfile.
fn dockerfile_ids(flag: &str) -> Vec<u64> {
    let text = read(&Path::new(env!("CARGO_MANIFEST_DIR")).join("Dockerfile"));
    text.match_indices(flag)
        .filter_map(|(at, _)| {
            text[at + flag.len()..]
                .trim_start()
                .chars()
                .take_while(char::is_ascii_digit)
                .collect::<String>()
                .parse()
                .ok()
        })
        .collect()
}

/// (protocol, port) of each entry of a NetworkPolicy rule's `ports` (TCP when not named).
fn rule_ports(rule: &Value) -> Vec<(String, u64)> {
    seq(&rule["ports"])
        .iter()
        .map(|p| {
            (
                p["protocol"].as_str().unwrap_or("TCP").to_string(),
                number(&p["port"], "a policy port"),
            )
        })
        .collect()
}

/// Guards `kubectl apply -k deploy/`: every resource it lists exists, every YAML file of
/// `deploy/` parses into objects with `apiVersion` and `kind`, and the optional files (a CRD
/// that would fail the apply on clusters without the Prometheus Operator, examples to fill in)
/// stay out of the default resources.
#[test]
fn the_kustomization_lists_existing_files_and_leaves_the_optional_ones_out() {
    let k = kustomization();
    let resources: Vec<&str> = seq(&k["resources"])
        .iter()
        .map(|r| text(r, "a resource"))
        .collect();
    assert!(
        !resources.is_empty(),
        "the kustomization lists no resources"
    );
    for r in &resources {
        assert!(
            deploy_dir().join(r).is_file(),
            "kustomization.yaml lists {r}, which is not in deploy/"
        );
        assert!(
            !OPTIONAL.contains(r),
            "{r} is optional and must stay out of the default resources"
        );
    }
    let mut files: Vec<String> = std::fs::read_dir(deploy_dir())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".yaml") || n.ends_with(".yml"))
        .collect();
    files.sort();
    for f in &files {
        let docs = documents(f);
        assert!(!docs.is_empty(), "deploy/{f} holds no object");
        for d in &docs {
            assert!(
                d["apiVersion"].is_string() && d["kind"].is_string(),
                "deploy/{f}: an object without apiVersion or kind"
            );
        }
        let f = f.as_str();
        assert!(
            f == "kustomization.yaml" || resources.contains(&f) || OPTIONAL.contains(&f),
            "deploy/{f} is neither a resource of the kustomization nor a known optional file"
        );
    }
    for o in OPTIONAL {
        assert!(
            files.iter().any(|f| f.as_str() == *o),
            "deploy/{o} is missing"
        );
    }
}

/// Guards the image pull: a registry image with a fixed tag (not `latest`, pulled once per
/// node), and the kustomization's `images:` entry names it, so `kustomize edit set image`
/// changes it; the entry and the Deployment agree on the default.
#[test]
fn the_image_is_pinned_and_set_by_the_kustomization() {
    let server = Server::load();
    let c = server.container();
    let image = text(&c["image"], "the container's image");
    let (name, tag) = split_image(image);
    let registry = name.split('/').next().unwrap_or("");
    assert!(
        name.contains('/')
            && (registry.contains('.') || registry.contains(':') || registry == "localhost"),
        "{image}: the image names no registry"
    );
    let tag = tag.unwrap_or_else(|| panic!("{image}: no tag"));
    assert_ne!(tag, "latest", "{image}: a moving tag");
    assert_eq!(
        c["imagePullPolicy"].as_str(),
        Some("IfNotPresent"),
        "imagePullPolicy"
    );

    let k = kustomization();
    let entries = seq(&k["images"]);
    assert_eq!(entries.len(), 1, "one images entry expected");
    let entry = &entries[0];
    assert_eq!(
        entry["name"].as_str(),
        Some(name),
        "the images entry does not name the Deployment's image {image}: kustomize would not \
         replace it"
    );
    let new_name = text(&entry["newName"], "the images entry's newName");
    let new_tag = text(
        &entry["newTag"],
        "the images entry's newTag (quote a numeric tag)",
    );
    assert_ne!(new_tag, "latest", "the images entry sets a moving tag");
    assert_eq!(
        format!("{new_name}:{new_tag}"),
        image,
        "deployment.yaml and the kustomization's images entry disagree on the image"
    );
}

/// Guards admission under the `restricted` Pod Security Standard: a non-root user (the
/// Dockerfile's uid), `seccompProfile: RuntimeDefault`, no privilege escalation, every
/// capability dropped, a read-only root file system, no host namespaces, paths or ports.
#[test]
fn the_pod_meets_the_restricted_pod_security_standard() {
    let server = Server::load();
    let pod = server.pod();
    let sc = &pod["securityContext"];
    assert_eq!(sc["runAsNonRoot"].as_bool(), Some(true), "pod runAsNonRoot");
    let uid = *dockerfile_ids("--uid")
        .first()
        .expect("the Dockerfile creates its user with --uid N");
    assert_eq!(
        number(&sc["runAsUser"], "the pod's runAsUser"),
        uid,
        "the pod's user is not the image's"
    );
    let gid = number(&sc["runAsGroup"], "the pod's runAsGroup");
    assert_ne!(gid, 0, "the pod runs in group root");
    if let Some(image_gid) = dockerfile_ids("--gid").first() {
        assert_eq!(gid, *image_gid, "the pod's group is not the image's");
    }
    assert_eq!(
        sc["seccompProfile"]["type"].as_str(),
        Some("RuntimeDefault"),
        "the pod's seccompProfile"
    );
    for key in ["hostNetwork", "hostPID", "hostIPC"] {
        assert_ne!(pod[key].as_bool(), Some(true), "{key}");
    }
    for v in seq(&pod["volumes"]) {
        assert!(v["hostPath"].is_null(), "a hostPath volume: {v:?}");
    }
    for c in seq(&pod["containers"])
        .iter()
        .chain(seq(&pod["initContainers"]))
    {
        let name = text(&c["name"], "a container's name");
        let sc = &c["securityContext"];
        assert_eq!(
            sc["allowPrivilegeEscalation"].as_bool(),
            Some(false),
            "{name}: allowPrivilegeEscalation"
        );
        assert_eq!(
            sc["readOnlyRootFilesystem"].as_bool(),
            Some(true),
            "{name}: readOnlyRootFilesystem"
        );
        assert_ne!(sc["privileged"].as_bool(), Some(true), "{name}: privileged");
        assert_ne!(
            sc["runAsNonRoot"].as_bool(),
            Some(false),
            "{name}: runAsNonRoot"
        );
        assert_ne!(sc["runAsUser"].as_u64(), Some(0), "{name}: runs as root");
        let dropped: Vec<&str> = seq(&sc["capabilities"]["drop"])
            .iter()
            .map(|d| text(d, "a capability"))
            .collect();
        assert_eq!(dropped, ["ALL"], "{name}: capabilities.drop");
        assert!(
            seq(&sc["capabilities"]["add"]).is_empty(),
            "{name}: capabilities added"
        );
        let profile = &sc["seccompProfile"]["type"];
        assert!(
            profile.is_null() || profile.as_str() == Some("RuntimeDefault"),
            "{name}: seccompProfile {profile:?}"
        );
        for p in seq(&c["ports"]) {
            assert!(p["hostPort"].is_null(), "{name}: a hostPort");
        }
    }
}

/// Guards the read-only root file system: the process can still write where it writes
/// (`/tmp`, an `emptyDir`), and every other mount is read-only.
#[test]
fn the_process_writes_only_to_empty_dirs() {
    let server = Server::load();
    let pod = server.pod();
    let mut writable = Vec::new();
    for m in seq(&server.container()["volumeMounts"]) {
        let at = text(&m["mountPath"], "a mountPath");
        let v = volume(pod, text(&m["name"], "a mount's volume"));
        if v["emptyDir"].is_mapping() {
            assert_ne!(
                m["readOnly"].as_bool(),
                Some(true),
                "{at}: a read-only emptyDir"
            );
            writable.push(at);
        } else {
            assert!(
                v["secret"].is_mapping() || v["configMap"].is_mapping(),
                "{at}: only Secrets, ConfigMaps and emptyDirs are expected"
            );
            assert_eq!(m["readOnly"].as_bool(), Some(true), "{at}: not read-only");
        }
    }
    assert!(
        writable.contains(&"/tmp"),
        "no emptyDir at /tmp (the root file system is read-only): {writable:?}"
    );
}

/// Guards scraping by annotation: `prometheus.io/*` on the pod template, with the container's
/// port and the metrics path.
#[test]
fn prometheus_scrapes_the_container_port() {
    let server = Server::load();
    let a = &server.deployment["spec"]["template"]["metadata"]["annotations"];
    assert_eq!(a["prometheus.io/scrape"].as_str(), Some("true"));
    assert_eq!(a["prometheus.io/path"].as_str(), Some("/metrics"));
    let port = server.port("http");
    assert_eq!(
        a["prometheus.io/port"].as_str(),
        Some(port.to_string().as_str()),
        "prometheus.io/port is not the container's port"
    );
}

/// Guards autoscaling: the HPA targets this Deployment by name, on CPU utilization (a share of
/// the CPU request, which must be set), never below the PodDisruptionBudget (a drain must be
/// able to evict), and scales down only after a stabilization window.
#[test]
fn the_hpa_scales_the_deployment_on_cpu() {
    let server = Server::load();
    let hpa = object("hpa.yaml", "HorizontalPodAutoscaler");
    assert_eq!(hpa["apiVersion"].as_str(), Some("autoscaling/v2"));
    let spec = &hpa["spec"];
    let target = &spec["scaleTargetRef"];
    assert_eq!(target["apiVersion"].as_str(), Some("apps/v1"));
    assert_eq!(target["kind"].as_str(), Some("Deployment"));
    assert_eq!(
        target["name"].as_str(),
        Some(server.name()),
        "the HPA scales another Deployment"
    );
    let min = number(&spec["minReplicas"], "minReplicas");
    let max = number(&spec["maxReplicas"], "maxReplicas");
    assert!(min >= 2 && max > min, "replicas {min}..{max}");
    let pdb = object("pdb.yaml", "PodDisruptionBudget");
    let min_available = number(&pdb["spec"]["minAvailable"], "minAvailable");
    assert!(
        min > min_available,
        "at minReplicas {min} the PodDisruptionBudget (minAvailable {min_available}) blocks \
         every drain"
    );
    let replicas = number(&server.deployment["spec"]["replicas"], "replicas");
    assert!(
        (min..=max).contains(&replicas),
        "the Deployment's {replicas} replicas are outside the HPA's range"
    );
    let cpu = seq(&spec["metrics"])
        .iter()
        .find(|m| {
            m["type"].as_str() == Some("Resource") && m["resource"]["name"].as_str() == Some("cpu")
        })
        .expect("the HPA has no CPU metric");
    let goal = &cpu["resource"]["target"];
    assert_eq!(goal["type"].as_str(), Some("Utilization"));
    let utilization = number(&goal["averageUtilization"], "averageUtilization");
    assert!((1..=100).contains(&utilization), "{utilization}%");
    assert!(
        !server.container()["resources"]["requests"]["cpu"].is_null(),
        "CPU utilization is a share of the CPU request: the container sets none"
    );
    let window = number(
        &spec["behavior"]["scaleDown"]["stabilizationWindowSeconds"],
        "the scale-down stabilizationWindowSeconds",
    );
    assert!(window >= 60, "scale-down window {window} s");
}

/// Guards the NetworkPolicy: it selects the server's pods, admits only TCP on the container
/// port the Service targets, and lets out only the database (TCP 5432, to a named destination)
/// and DNS (53 over UDP and TCP).
#[test]
fn the_network_policy_admits_the_service_port_and_lets_out_only_the_database_and_dns() {
    let server = Server::load();
    let np = object("networkpolicy.yaml", "NetworkPolicy");
    assert_eq!(np["apiVersion"].as_str(), Some("networking.k8s.io/v1"));
    let spec = &np["spec"];
    assert_selects(
        "the NetworkPolicy's podSelector",
        &spec["podSelector"]["matchLabels"],
        &server.labels,
    );
    let types: Vec<&str> = seq(&spec["policyTypes"])
        .iter()
        .map(|t| text(t, "a policy type"))
        .collect();
    assert!(
        types.contains(&"Ingress") && types.contains(&"Egress"),
        "policyTypes {types:?}"
    );

    let port = server.port("http");
    let service = service();
    for p in seq(&service["spec"]["ports"]) {
        let t = &p["targetPort"];
        let target = t
            .as_u64()
            .unwrap_or_else(|| server.port(text(t, "targetPort")));
        assert_eq!(target, port, "the Service targets another port");
    }
    let ingress = seq(&spec["ingress"]);
    assert!(
        !ingress.is_empty(),
        "no ingress rule: nothing reaches the pods"
    );
    for rule in ingress {
        assert_eq!(
            rule_ports(rule),
            [("TCP".to_string(), port)],
            "an ingress rule admits more than TCP {port}"
        );
    }

    let mut egress: BTreeSet<(String, u64)> = BTreeSet::new();
    for rule in seq(&spec["egress"]) {
        let ports = rule_ports(rule);
        assert!(
            !ports.is_empty(),
            "an egress rule without ports lets out every port"
        );
        if ports.iter().any(|(_, p)| *p == 5432) {
            assert!(
                !seq(&rule["to"]).is_empty(),
                "the database rule names no destination"
            );
        }
        egress.extend(ports);
    }
    let want: BTreeSet<(String, u64)> = [("TCP", 5432), ("UDP", 53), ("TCP", 53)]
        .into_iter()
        .map(|(protocol, n)| (protocol.to_string(), n))
        .collect();
    assert_eq!(egress, want, "egress");
    let url = documents("secret.example.yaml")
        .into_iter()
        .find(|s| s["metadata"]["name"].as_str() == Some("seasonloc-db"))
        .map(|s| {
            text(
                &s["stringData"]["SEASONLOC_DATABASE_URL"],
                "the database URL",
            )
            .to_string()
        })
        .expect("the Secret seasonloc-db in secret.example.yaml");
    assert!(
        url.contains(":5432/"),
        "the example database is not on the port the policy lets out: {url}"
    );
}

/// Guards the Ingress example: `networking.k8s.io/v1` with a class, TLS (a secretName) for every
/// host it serves, and every backend is the Service, by its name and one of its ports.
#[test]
fn the_ingress_example_terminates_tls_and_routes_to_the_service() {
    let ingress = object("ingress.example.yaml", "Ingress");
    assert_eq!(ingress["apiVersion"].as_str(), Some("networking.k8s.io/v1"));
    let spec = &ingress["spec"];
    assert!(!text(&spec["ingressClassName"], "ingressClassName").is_empty());
    let tls = seq(&spec["tls"]);
    assert!(!tls.is_empty(), "no tls");
    let mut tls_hosts = Vec::new();
    for t in tls {
        assert!(!text(&t["secretName"], "a tls secretName").is_empty());
        tls_hosts.extend(seq(&t["hosts"]).iter().map(|h| text(h, "a tls host")));
    }
    let service = service();
    let service_name = text(&service["metadata"]["name"], "the Service's name");
    let service_ports = seq(&service["spec"]["ports"]);
    let rules = seq(&spec["rules"]);
    assert!(!rules.is_empty(), "no rules");
    let mut backends = 0;
    for rule in rules {
        let host = text(&rule["host"], "a rule's host");
        assert!(tls_hosts.contains(&host), "{host} is served without TLS");
        for path in seq(&rule["http"]["paths"]) {
            let backend = &path["backend"]["service"];
            assert_eq!(
                backend["name"].as_str(),
                Some(service_name),
                "a backend is not the Service"
            );
            let port = &backend["port"];
            assert!(
                service_ports.iter().any(|p| {
                    (port["name"].is_string() && port["name"] == p["name"])
                        || (port["number"].is_u64() && port["number"] == p["port"])
                }),
                "the backend port {port:?} is not a port of the Service"
            );
            backends += 1;
        }
    }
    assert!(backends > 0, "no backend");
}

/// Guards the optional ServiceMonitor: it selects the Service by labels the Service has (with
/// the kustomization's), scrapes a port the Service names at `/metrics`, and sends a bearer key
/// from a Secret that `secret.example.yaml` shows (`/metrics` needs a `reader` key).
#[test]
fn the_service_monitor_scrapes_the_service_with_a_key() {
    let sm = object("servicemonitor.yaml", "ServiceMonitor");
    assert_eq!(sm["apiVersion"].as_str(), Some("monitoring.coreos.com/v1"));
    let service = service();
    let mut labels = string_map(&service["metadata"]["labels"]);
    labels.extend(common_labels(&kustomization()));
    assert_selects(
        "the ServiceMonitor's selector",
        &sm["spec"]["selector"]["matchLabels"],
        &labels,
    );
    let port_names: Vec<&str> = seq(&service["spec"]["ports"])
        .iter()
        .map(|p| text(&p["name"], "a Service port's name"))
        .collect();
    let endpoints = seq(&sm["spec"]["endpoints"]);
    assert!(!endpoints.is_empty(), "no endpoints");
    let secrets = documents("secret.example.yaml");
    for e in endpoints {
        let port = text(&e["port"], "an endpoint's port (a Service port's name)");
        assert!(
            port_names.contains(&port),
            "the Service has no port named {port}"
        );
        assert_eq!(e["path"].as_str(), Some("/metrics"));
        let auth = &e["authorization"];
        assert!(
            auth["type"].is_null() || auth["type"].as_str() == Some("Bearer"),
            "authorization type {:?}",
            auth["type"]
        );
        let name = text(&auth["credentials"]["name"], "the key Secret's name");
        let key = text(&auth["credentials"]["key"], "the key Secret's key");
        let secret = secrets
            .iter()
            .find(|s| s["metadata"]["name"].as_str() == Some(name))
            .unwrap_or_else(|| panic!("secret.example.yaml does not show the Secret {name}"));
        assert!(
            !secret["stringData"][key].is_null(),
            "the Secret {name} has no key {key}"
        );
    }
}

/// The metric family `name` (as queried: a histogram's `_bucket`, `_sum` or `_count` series
/// included) belongs to, when the service exports it.
fn family(name: &str) -> Option<&'static str> {
    let exact = FAMILIES
        .iter()
        .chain(HISTOGRAMS)
        .copied()
        .find(|f| *f == name);
    exact.or_else(|| {
        ["_bucket", "_sum", "_count"]
            .into_iter()
            .filter_map(|suffix| name.strip_suffix(suffix))
            .find_map(|base| HISTOGRAMS.iter().copied().find(|h| *h == base))
    })
}

/// The names in a PromQL query that look like the service's metrics.
fn metric_names(query: &str) -> Vec<&str> {
    query
        .split(|c: char| !(c.is_ascii_alphanumeric() || c == '_' || c == ':'))
        .filter(|t| t.starts_with("seasonloc_") || t.starts_with("process_"))
        .collect()
}

/// Every query of the dashboard: panel targets' `expr`, template variables' `query` and
/// `definition`.
fn queries(v: &serde_json::Value, out: &mut Vec<String>) {
    match v {
        serde_json::Value::Object(m) => {
            for (k, child) in m {
                match child {
                    serde_json::Value::String(s)
                        if matches!(k.as_str(), "expr" | "query" | "definition") =>
                    {
                        out.push(s.clone());
                    }
                    _ => queries(child, out),
                }
            }
        }
        serde_json::Value::Array(a) => {
            for child in a {
                queries(child, out);
            }
        }
        _ => {}
    }
}

/// The data source every `datasource` field names (its uid, or the legacy name string).
fn datasources(v: &serde_json::Value, out: &mut Vec<String>) {
    match v {
        serde_json::Value::Object(m) => {
            match m.get("datasource") {
                Some(serde_json::Value::String(s)) => out.push(s.clone()),
                Some(ds) => out.push(ds["uid"].as_str().unwrap_or("<no uid>").to_string()),
                None => {}
            }
            for child in m.values() {
                datasources(child, out);
            }
        }
        serde_json::Value::Array(a) => {
            for child in a {
                datasources(child, out);
            }
        }
        _ => {}
    }
}

/// Guards the Grafana dashboard: it parses, takes its Prometheus data source from the
/// `datasource` variable (no uid of one Grafana's data source baked in), every panel queries
/// something, and every metric it queries is one the service exports, each of them shown
/// somewhere (a renamed or removed metric breaks this test).
#[test]
fn the_grafana_dashboard_queries_only_the_exported_metric_families() {
    let path = deploy_dir().join("grafana-dashboard.json");
    let dashboard: serde_json::Value =
        serde_json::from_str(&read(&path)).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert!(
        dashboard["schemaVersion"].as_u64().is_some_and(|v| v >= 36),
        "schemaVersion {}",
        dashboard["schemaVersion"]
    );
    let vars = dashboard["templating"]["list"]
        .as_array()
        .expect("templating variables");
    assert!(
        vars.iter().any(|v| v["name"] == "datasource"
            && v["type"] == "datasource"
            && v["query"] == "prometheus"),
        "no Prometheus `datasource` variable"
    );

    let mut sources = Vec::new();
    datasources(&dashboard, &mut sources);
    assert!(!sources.is_empty(), "no panel names a data source");
    for s in &sources {
        assert!(
            s.as_str() == "${datasource}" || s.as_str() == "-- Grafana --",
            "a hard-coded data source `{s}`: use the ${{datasource}} variable"
        );
    }

    let panels = dashboard["panels"].as_array().expect("panels");
    let mut ids = BTreeSet::new();
    for p in panels {
        let id = p["id"].as_u64().expect("a panel id");
        assert!(ids.insert(id), "panel id {id} twice");
        if p["type"] != "row" {
            let targets = p["targets"].as_array().map_or(0, Vec::len);
            assert!(targets > 0, "the panel {} queries nothing", p["title"]);
        }
    }

    let mut all = Vec::new();
    queries(&dashboard, &mut all);
    let mut used = BTreeSet::new();
    for q in &all {
        for name in metric_names(q) {
            let f = family(name).unwrap_or_else(|| {
                panic!(
                    "the dashboard queries `{name}`, which the service does not export (a \
                     renamed metric?): {q}"
                )
            });
            used.insert(f);
        }
    }
    for f in FAMILIES.iter().chain(HISTOGRAMS) {
        assert!(used.contains(f), "no panel shows {f}");
    }
}
