//! `compose.yaml` and `deploy/nginx.conf`: the deployment of two replicas on PostgreSQL behind a
//! load balancer. It cannot be started here (no images), so what matters is checked by reading
//! the files; where `docker-compose` or `docker compose` is installed it also validates the file
//! (CI installs Debian's `docker-compose` and sets `FACEGATE_REQUIRE_COMPOSE`, so there it must).
//!
//! `deploy/kubernetes`: the kustomize base (one replica on SQLite) and the `postgres` overlay
//! (replicas on an external PostgreSQL), rendered with `kubectl kustomize`, validated against the
//! Kubernetes schemas by `kubernetes-validate` and read back for what matters (the Dockerfile's
//! user and port, both probes, requests and limits, the keys from Secrets, the autoscaler and the
//! disruption budget). Without the tools these skip with the reason; CI has kubectl, installs
//! kubernetes-validate and sets `FACEGATE_REQUIRE_KUBERNETES`, so there they must run.

use std::io::Write;
use std::path::Path;
use std::process::{Command, Stdio};

use serde::Deserialize;
use serde_json::Value;

const REPLICAS: [&str; 2] = ["facegate-a", "facegate-b"];

fn compose() -> Value {
    let text = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("compose.yaml")).unwrap();
    serde_norway::from_str(&text).expect("compose.yaml parses as YAML")
}

#[test]
fn compose_runs_two_replicas_on_postgres_behind_the_balancer() {
    let compose = compose();
    let services = compose["services"].as_object().expect("services");
    let mut names: Vec<&str> = services.keys().map(String::as_str).collect();
    names.sort_unstable();
    assert_eq!(names, ["facegate-a", "facegate-b", "lb", "postgres"]);
    assert!(services["postgres"]["image"].as_str().unwrap().starts_with("postgres:"));
    assert!(services["postgres"]["healthcheck"]["test"].to_string().contains("pg_isready"));
    let secrets = compose["secrets"].as_object().expect("top-level secrets");
    for replica in REPLICAS {
        let service = &services[replica];
        assert_eq!(service["build"], ".", "{replica} is built from the Dockerfile");
        let command: Vec<&str> = service["command"].as_array().unwrap().iter().map(|v| v.as_str().unwrap()).collect();
        assert_eq!(command[0], "serve");
        let url = command[command.iter().position(|&a| a == "--database").expect("--database") + 1];
        assert!(url.starts_with("postgres://") && url.contains("@postgres:5432/"), "{replica}: {url}");
        let user = url.trim_start_matches("postgres://").split('@').next().unwrap();
        assert!(!user.contains(':'), "{replica}: no password in the URL: {url}");
        let env = &service["environment"];
        assert!(env["FACEGATE_BIND"].as_str().unwrap().ends_with(":8080"));
        // Every file the replica is pointed at is one of its secrets, declared at the top level.
        let mounted: Vec<&str> = service["secrets"].as_array().unwrap().iter().map(|v| v.as_str().unwrap()).collect();
        for variable in ["FACEGATE_TEMPLATE_KEY_FILE", "FACEGATE_API_KEYS_FILE", "PGPASSFILE"] {
            let path = env[variable].as_str().unwrap_or_else(|| panic!("{replica}: {variable}"));
            let secret = path.strip_prefix("/run/secrets/").unwrap_or_else(|| panic!("{replica}: {variable} is a secret: {path}"));
            assert!(mounted.contains(&secret) && secrets.contains_key(secret), "{replica}: secret {secret}");
        }
        assert_eq!(service["depends_on"]["postgres"]["condition"], "service_healthy");
        assert!(service["healthcheck"]["test"].to_string().contains("--healthcheck"));
        assert!(service.get("ports").is_none(), "{replica} is reached through the balancer only");
    }
    let lb = &services["lb"];
    assert!(lb["image"].as_str().unwrap().starts_with("nginx:"));
    assert!(lb["ports"].as_array().unwrap().iter().any(|p| p.as_str().unwrap().ends_with(":80")));
    for replica in REPLICAS {
        assert_eq!(lb["depends_on"][replica]["condition"], "service_healthy");
    }
    let config = lb["volumes"].as_array().unwrap().iter().find_map(|v| v.as_str()?.strip_suffix(":/etc/nginx/nginx.conf:ro")).unwrap();
    assert_eq!(config, "./deploy/nginx.conf");
}

#[test]
fn the_balancer_sends_to_both_replicas() {
    let text = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/nginx.conf")).unwrap();
    let upstream = text.split("upstream facegate {").nth(1).expect("an upstream block").split('}').next().unwrap();
    let servers: Vec<&str> =
        upstream.lines().filter_map(|l| l.trim().strip_prefix("server ")).map(|s| s.split_whitespace().next().unwrap()).collect();
    assert_eq!(servers, REPLICAS.map(|r| format!("{r}:8080")));
    assert!(text.contains("proxy_pass http://facegate;"));
    assert!(text.contains("listen 80;"));
    // Larger than facegate's own body limit, so that facegate answers an oversized body itself.
    let limit = text.split("client_max_body_size ").nth(1).unwrap().split('m').next().unwrap().parse::<usize>().unwrap();
    assert!(limit > facegate::config::Settings::default().max_body_mb, "{limit}");
}

/// `docker compose config` where the tool is installed (the secret files need not exist for it).
#[test]
fn compose_config_validates_where_the_tool_is_installed() {
    let root = env!("CARGO_MANIFEST_DIR");
    let tools: [&[&str]; 2] = [&["docker-compose"], &["docker", "compose"]];
    for tool in tools {
        let Ok(out) = Command::new(tool[0]).args(&tool[1..]).args(["-f", "compose.yaml", "config", "-q"]).current_dir(root).output() else {
            continue;
        };
        let stderr = String::from_utf8_lossy(&out.stderr);
        if !out.status.success()
            && (stderr.contains("unknown command")
                || stderr.contains("is not a docker command")
                || stderr.contains("unknown shorthand flag"))
        {
            continue;
        }
        assert!(out.status.success(), "{} config: {stderr}", tool.join(" "));
        return;
    }
    let why = "neither docker-compose nor `docker compose` is installed";
    if std::env::var_os("FACEGATE_REQUIRE_COMPOSE").is_some_and(|v| !v.is_empty() && v != "0") {
        panic!("compose.yaml must be validated (FACEGATE_REQUIRE_COMPOSE) but {why}");
    }
    eprintln!("NOT VALIDATED compose.yaml with docker compose: {why} (parsed only)");
}

/// The oldest Kubernetes the manifests are validated against (kubernetes-validate's own schemas:
/// no cluster, no download); the API versions used are the same in every later one.
const KUBERNETES_VERSION: &str = "1.30.0";
const BASE: &str = "deploy/kubernetes/base";
const OVERLAY: &str = "deploy/kubernetes/postgres";

/// Print why a Kubernetes check is skipped; panic instead when `FACEGATE_REQUIRE_KUBERNETES` is set.
fn kubernetes_skip(what: &str, why: &str) {
    if std::env::var_os("FACEGATE_REQUIRE_KUBERNETES").is_some_and(|v| !v.is_empty() && v != "0") {
        panic!("{what} must be checked (FACEGATE_REQUIRE_KUBERNETES) but {why}");
    }
    eprintln!("NOT CHECKED {what}: {why}");
}

/// `kubectl kustomize DIR` (or `kustomize build DIR`): the rendered YAML, or why neither runs.
fn kustomize(dir: &str) -> Result<String, String> {
    let tools: [&[&str]; 2] = [&["kubectl", "kustomize"], &["kustomize", "build"]];
    for tool in tools {
        let Ok(out) = Command::new(tool[0]).args(&tool[1..]).arg(dir).current_dir(env!("CARGO_MANIFEST_DIR")).output() else {
            continue;
        };
        assert!(out.status.success(), "{} {dir}: {}", tool.join(" "), String::from_utf8_lossy(&out.stderr));
        return Ok(String::from_utf8(out.stdout).expect("UTF-8 YAML"));
    }
    Err("neither kubectl nor kustomize is installed".into())
}

/// The resources of a multi-document YAML stream.
fn documents(yaml: &str) -> Vec<Value> {
    serde_norway::Deserializer::from_str(yaml)
        .map(|document| Value::deserialize(document).expect("the rendered YAML parses"))
        .filter(|value| !value.is_null())
        .collect()
}

/// The rendered resources of a kustomization; `None` (skipped, with the reason) without the tool.
fn rendered(dir: &str) -> Option<Vec<Value>> {
    match kustomize(dir) {
        Ok(yaml) => Some(documents(&yaml)),
        Err(why) => {
            kubernetes_skip(dir, &why);
            None
        }
    }
}

fn kinds(resources: &[Value]) -> Vec<&str> {
    let mut kinds: Vec<&str> = resources.iter().map(|r| r["kind"].as_str().unwrap()).collect();
    kinds.sort_unstable();
    kinds
}

fn one<'a>(resources: &'a [Value], kind: &str) -> &'a Value {
    let mut found = resources.iter().filter(|r| r["kind"] == kind);
    let resource = found.next().unwrap_or_else(|| panic!("a {kind}"));
    assert!(found.next().is_none(), "one {kind}");
    resource
}

/// Every label the selector names is on the pod, with the same value.
fn selects(selector: &Value, labels: &Value) -> bool {
    selector.as_object().is_some_and(|s| !s.is_empty() && s.iter().all(|(k, v)| &labels[k] == v))
}

/// The named entry of a list of `{name: …}` objects (env, volumes).
fn named<'a>(list: &'a Value, name: &str) -> &'a Value {
    list.as_array().unwrap().iter().find(|e| e["name"] == name).unwrap_or_else(|| panic!("{name} in {list}"))
}

/// The argument of the Dockerfile's last `INSTRUCTION` line (`USER`, `EXPOSE`).
fn dockerfile(instruction: &str) -> String {
    let text = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("Dockerfile")).unwrap();
    let prefix = format!("{instruction} ");
    text.lines().filter_map(|l| l.strip_prefix(&prefix)).last().unwrap_or_else(|| panic!("{instruction}")).trim().to_string()
}

/// A resource quantity in cores or bytes: `2`, `500m`, `512Mi`, `1Gi`, `1G`.
fn quantity(value: &Value) -> f64 {
    let text = value.as_str().map(str::to_string).unwrap_or_else(|| value.to_string());
    let units = [("Ki", 1024f64), ("Mi", 1024f64.powi(2)), ("Gi", 1024f64.powi(3)), ("m", 1e-3), ("k", 1e3), ("M", 1e6), ("G", 1e9)];
    for (unit, factor) in units {
        if let Some(number) = text.strip_suffix(unit) {
            return number.parse::<f64>().unwrap() * factor;
        }
    }
    text.parse().unwrap_or_else(|_| panic!("a quantity: {text}"))
}

/// How long a probe keeps failing before it acts (Kubernetes' defaults: 3 failures, 10 s apart).
fn patience_secs(probe: &Value) -> u64 {
    probe["failureThreshold"].as_u64().unwrap_or(3) * probe["periodSeconds"].as_u64().unwrap_or(10)
}

/// The Secret a file the container is pointed at comes from: the file is in a read-only mount of
/// a projected or secret volume that has it as an item.
fn secret_of_file(pod: &Value, container: &Value, path: &str) -> String {
    let (dir, file) = path.rsplit_once('/').unwrap();
    let mount = container["volumeMounts"].as_array().unwrap().iter().find(|m| m["mountPath"] == dir).unwrap_or_else(|| panic!("{dir}"));
    assert_eq!(mount["readOnly"], true, "{path} is mounted read-only");
    let volume = named(&pod["volumes"], mount["name"].as_str().unwrap());
    let secrets: Vec<&Value> = match volume["projected"]["sources"].as_array() {
        Some(sources) => sources.iter().map(|s| &s["secret"]).filter(|s| s.is_object()).collect(),
        None => vec![&volume["secret"]],
    };
    let secret = secrets
        .into_iter()
        .find(|s| s["items"].as_array().is_some_and(|items| items.iter().any(|i| i["path"] == file)))
        .unwrap_or_else(|| panic!("{path} comes from a Secret: {volume}"));
    secret["name"].as_str().or_else(|| secret["secretName"].as_str()).unwrap().to_string()
}

/// What both layouts share; returns the pod's labels.
fn check_pod(deployment: &Value, dir: &str) -> Value {
    let labels = deployment["spec"]["template"]["metadata"]["labels"].clone();
    assert!(selects(&deployment["spec"]["selector"]["matchLabels"], &labels), "{dir}: the Deployment selects its pods");
    let pod = &deployment["spec"]["template"]["spec"];
    let containers = pod["containers"].as_array().unwrap();
    assert_eq!(containers.len(), 1, "{dir}: one container");
    let c = &containers[0];
    let image = c["image"].as_str().unwrap();
    assert!(image.contains(':') && !image.ends_with(":latest"), "{dir}: a set image tag: {image}");
    // The Dockerfile's user, not root; nothing written outside the mounted volumes.
    let user = dockerfile("USER");
    let (uid, gid) = user.split_once(':').unwrap();
    assert_eq!(pod["securityContext"]["runAsNonRoot"], true, "{dir}");
    assert_eq!(c["securityContext"]["runAsNonRoot"], true, "{dir}");
    assert_eq!(pod["securityContext"]["runAsUser"].to_string(), uid, "{dir}");
    assert_eq!(pod["securityContext"]["runAsGroup"].to_string(), gid, "{dir}");
    assert_eq!(c["securityContext"]["readOnlyRootFilesystem"], true, "{dir}");
    assert_eq!(c["securityContext"]["allowPrivilegeEscalation"], false, "{dir}");
    assert_eq!(c["securityContext"]["capabilities"]["drop"], serde_json::json!(["ALL"]), "{dir}");
    assert_eq!(pod["securityContext"]["seccompProfile"]["type"], "RuntimeDefault", "{dir}");
    for mount in c["volumeMounts"].as_array().unwrap() {
        let volume = named(&pod["volumes"], mount["name"].as_str().unwrap());
        if mount["readOnly"] != true {
            assert!(volume["emptyDir"].is_object() || volume["persistentVolumeClaim"].is_object(), "{dir}: writable {mount}");
        }
    }
    let tmp = c["volumeMounts"].as_array().unwrap().iter().find(|m| m["mountPath"] == "/tmp").expect("/tmp");
    assert!(named(&pod["volumes"], tmp["name"].as_str().unwrap())["emptyDir"].is_object(), "{dir}: /tmp is an emptyDir");
    // The port the Dockerfile exposes, named for the probes and the Service.
    let port = named(&c["ports"], "http");
    assert_eq!(port["containerPort"].to_string(), dockerfile("EXPOSE"), "{dir}");
    let env = &c["env"];
    assert!(named(env, "FACEGATE_BIND")["value"].as_str().unwrap().ends_with(&format!(":{}", port["containerPort"])), "{dir}");
    // Ready when the database answers (/health); alive when the process answers (/livez), which a
    // busy replica or one without its database still does.
    let ready = &c["readinessProbe"];
    assert_eq!(ready["httpGet"]["path"], "/health", "{dir}");
    assert!(ready["timeoutSeconds"].as_u64().unwrap_or(1) > 1, "{dir}: /health may take its 1 s for the database");
    for (name, least) in [("livenessProbe", 60), ("startupProbe", 120)] {
        let probe = &c[name];
        assert_eq!(probe["httpGet"]["path"], "/livez", "{dir}: {name}");
        assert_eq!(probe["httpGet"]["port"], "http", "{dir}: {name}");
        // A minute of no answer before a restart; the start-up (a ten-million-template gallery
        // took 20-30 s to load) given four times that.
        assert!(patience_secs(probe) >= least, "{dir}: {name} gives up after {} s", patience_secs(probe));
    }
    assert_eq!(ready["httpGet"]["port"], "http", "{dir}");
    // Requests and limits for both, the requests within the limits, one worker per core.
    for resource in ["cpu", "memory"] {
        let request = quantity(&c["resources"]["requests"][resource]);
        let limit = quantity(&c["resources"]["limits"][resource]);
        assert!(request > 0.0 && request <= limit, "{dir}: {resource} {request} within {limit}");
    }
    assert_eq!(named(env, "FACEGATE_WORKERS")["valueFrom"]["resourceFieldRef"]["resource"], "limits.cpu", "{dir}");
    // The keys from Secrets, as files.
    for variable in ["FACEGATE_TEMPLATE_KEY_FILE", "FACEGATE_API_KEYS_FILE"] {
        let path = named(env, variable)["value"].as_str().unwrap();
        assert!(!secret_of_file(pod, c, path).is_empty(), "{dir}: {variable}");
    }
    // The pod outlives facegate's own drain of its connections after SIGTERM.
    let grace = pod["terminationGracePeriodSeconds"].as_f64().unwrap_or(30.0);
    assert!(grace > facegate::config::Settings::default().shutdown_grace_secs, "{dir}: {grace} s");
    labels
}

/// The Service, the disruption budget and the network policy select the pods; the policy lets in
/// the service port only and out the `egress` ports only.
fn check_around_the_pods(resources: &[Value], labels: &Value, egress: &[(u64, &str)], dir: &str) {
    let service = one(resources, "Service");
    assert!(selects(&service["spec"]["selector"], labels), "{dir}: the Service selects the pods");
    assert_eq!(service["spec"]["ports"][0]["targetPort"], "http", "{dir}");
    let pdb = one(resources, "PodDisruptionBudget");
    assert!(selects(&pdb["spec"]["selector"]["matchLabels"], labels), "{dir}: the PodDisruptionBudget selects the pods");
    assert_eq!(pdb["spec"]["maxUnavailable"], 1, "{dir}: one replica at a time, never blocking a drain");
    let policy = one(resources, "NetworkPolicy");
    assert!(selects(&policy["spec"]["podSelector"]["matchLabels"], labels), "{dir}: the NetworkPolicy selects the pods");
    assert_eq!(policy["spec"]["policyTypes"], serde_json::json!(["Ingress", "Egress"]), "{dir}");
    for rule in policy["spec"]["ingress"].as_array().unwrap() {
        assert_eq!(rule["ports"], serde_json::json!([{"port": "http", "protocol": "TCP"}]), "{dir}: ingress to the service port only");
    }
    let mut ports: Vec<(u64, &str)> = policy["spec"]["egress"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|rule| rule["ports"].as_array().expect("every egress rule names its ports").iter())
        .map(|p| (p["port"].as_u64().unwrap(), p["protocol"].as_str().unwrap()))
        .collect();
    ports.sort_unstable();
    assert_eq!(ports, egress, "{dir}: egress");
}

#[test]
fn kubernetes_base_is_one_replica_on_sqlite() {
    let Some(resources) = rendered(BASE) else { return };
    assert_eq!(kinds(&resources), ["Deployment", "NetworkPolicy", "PersistentVolumeClaim", "PodDisruptionBudget", "Service"]);
    let deployment = one(&resources, "Deployment");
    let labels = check_pod(deployment, BASE);
    // SQLite is one process's: one replica, the old one gone before the new one opens the file.
    assert_eq!(deployment["spec"]["replicas"], 1);
    assert_eq!(deployment["spec"]["strategy"]["type"], "Recreate");
    let pod = &deployment["spec"]["template"]["spec"];
    let c = &pod["containers"][0];
    let url = named(&c["env"], "FACEGATE_DATABASE_URL")["value"].as_str().unwrap();
    let file = url.strip_prefix("sqlite://").expect("SQLite");
    let data = c["volumeMounts"].as_array().unwrap().iter().find(|m| file.starts_with(&format!("{}/", m["mountPath"].as_str().unwrap())));
    let data = data.unwrap_or_else(|| panic!("{url} is on a mounted volume"));
    let claim = &named(&pod["volumes"], data["name"].as_str().unwrap())["persistentVolumeClaim"]["claimName"];
    assert_eq!(&one(&resources, "PersistentVolumeClaim")["metadata"]["name"], claim, "the database is on the claim");
    assert_eq!(pod["securityContext"]["fsGroup"].to_string(), dockerfile("USER").split(':').nth(1).unwrap(), "the claim is writable");
    check_around_the_pods(&resources, &labels, &[(53, "TCP"), (53, "UDP")], BASE);
}

#[test]
fn kubernetes_postgres_overlay_scales_on_cpu() {
    let Some(resources) = rendered(OVERLAY) else { return };
    assert_eq!(kinds(&resources), ["Deployment", "HorizontalPodAutoscaler", "NetworkPolicy", "PodDisruptionBudget", "Service"]);
    let deployment = one(&resources, "Deployment");
    let labels = check_pod(deployment, OVERLAY);
    // The autoscaler owns the count; replicas sharing the database may overlap in a rollout.
    assert!(deployment["spec"].get("replicas").is_none(), "no replicas for `kubectl apply` to reset");
    assert_eq!(deployment["spec"]["strategy"]["type"], "RollingUpdate");
    assert_eq!(deployment["spec"]["strategy"]["rollingUpdate"]["maxUnavailable"], 0);
    let c = &deployment["spec"]["template"]["spec"]["containers"][0];
    let url = named(&c["env"], "FACEGATE_DATABASE_URL");
    assert!(url.get("value").is_none(), "the URL only in a Secret: {url}");
    let secret = &url["valueFrom"]["secretKeyRef"];
    assert!(secret["name"].is_string() && secret["key"].is_string(), "{url}");
    // The password never in a variable (which a crash-looping pod's start-up would not print
    // either, but `kubectl describe` and the process's environment would show): a file from the
    // same Secret, merged into the URL by facegate (--database-password-file).
    let pod = &deployment["spec"]["template"]["spec"];
    let password = named(&c["env"], "FACEGATE_DATABASE_PASSWORD_FILE")["value"].as_str().expect("a path");
    assert_eq!(secret_of_file(pod, c, password), secret["name"].as_str().unwrap(), "the password file from the database's Secret");
    assert!(!c["env"].as_array().unwrap().iter().any(|e| e["name"] == "PGPASSWORD"), "no password in the environment");
    assert!(!c["volumeMounts"].as_array().unwrap().iter().any(|m| m["mountPath"] == "/data"), "no SQLite volume");
    let hpa = one(&resources, "HorizontalPodAutoscaler");
    assert_eq!(hpa["apiVersion"], "autoscaling/v2");
    let target = &hpa["spec"]["scaleTargetRef"];
    assert_eq!((&target["kind"], &target["name"]), (&Value::from("Deployment"), &deployment["metadata"]["name"]));
    let min = hpa["spec"]["minReplicas"].as_u64().unwrap();
    assert!(min >= 2 && hpa["spec"]["maxReplicas"].as_u64().unwrap() > min, "{hpa}");
    let metrics = hpa["spec"]["metrics"].as_array().unwrap();
    assert!(
        metrics.iter().any(|m| m["type"] == "Resource"
            && m["resource"]["name"] == "cpu"
            && m["resource"]["target"]["type"] == "Utilization"
            && (1..=100).contains(&m["resource"]["target"]["averageUtilization"].as_u64().unwrap_or(0))),
        "scaled on CPU: {hpa}"
    );
    check_around_the_pods(&resources, &labels, &[(53, "TCP"), (53, "UDP"), (5432, "TCP")], OVERLAY);
}

/// `kubernetes-validate --strict` (its bundled schemas, offline) on both renderings: every
/// resource has a schema and passes, unknown fields included.
#[test]
fn kubernetes_manifests_validate_against_the_schemas() {
    for dir in [BASE, OVERLAY] {
        let yaml = match kustomize(dir) {
            Ok(yaml) => yaml,
            Err(why) => return kubernetes_skip(dir, &why),
        };
        let spawned = Command::new("kubernetes-validate")
            .args(["--kubernetes-version", KUBERNETES_VERSION, "--strict", "-"])
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn();
        let Ok(mut child) = spawned else {
            return kubernetes_skip(dir, "kubernetes-validate is not installed (pip install kubernetes-validate)");
        };
        child.stdin.take().unwrap().write_all(yaml.as_bytes()).unwrap();
        let out = child.wait_with_output().unwrap();
        let report = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
        assert!(out.status.success(), "{dir}: kubernetes-validate:\n{report}");
        let passed = report.lines().filter(|l| l.starts_with("INFO") && l.contains(" passed ")).count();
        assert_eq!(passed, documents(&yaml).len(), "{dir}: every resource has a schema and passes:\n{report}");
    }
}
