//! `compose.yaml` and `deploy/nginx.conf`: the deployment of two replicas on PostgreSQL behind a
//! load balancer. It cannot be started here (no images), so what matters is checked by reading
//! the files; where `docker-compose` or `docker compose` is installed it also validates the file
//! (CI installs Debian's `docker-compose` and sets `FACEGATE_REQUIRE_COMPOSE`, so there it must).

use std::path::Path;
use std::process::Command;

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
