//! `docker compose up` on this machine's Docker engine, exactly as deploy/README.md says to
//! run it (the default runs location, `deploy/runs`, no permission changes), with the images
//! that `deploy/build-images.sh` builds: the learner turns healthy, transitions flow and
//! actors get weights; a killed actor container leaves training going and rejoins with the
//! latest weights when started again; an actor cut off the network recovers when
//! reconnected; `eval` runs on a checkpoint by the documented command; `stop` leaves a final
//! checkpoint on the host.
//!
//! Ignored unless asked for (`--ignored`): it needs an engine and the images. scripts/test
//! builds them and runs it wherever `docker info` answers; elsewhere it is reported as
//! ignored, never as passed. Asked for, a missing engine or image is a failure that says
//! what to do.

#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::Duration;

use crawler_tests::{free_port, make_tls, read_status, repo_root, u64_at, wait_for_status};

fn compose_tool() -> Vec<String> {
    let plugin = Command::new("docker").args(["compose", "version"]).output().is_ok_and(|o| o.status.success());
    if plugin { vec!["docker".into(), "compose".into()] } else { vec!["docker-compose".into()] }
}

/// One compose project of this checkout's `deploy/` files, driven by the compose tool.
struct Compose {
    tool: Vec<String>,
    project: String,
    /// The compose file, relative to the repository root.
    file: &'static str,
    /// The run's name: its directory under deploy/runs.
    run: String,
    /// Settings as deploy/README.md documents them (CRAWLER_*).
    env: Vec<(&'static str, String)>,
    /// One-off containers (`compose run -d --name …`), removed with the project.
    one_off: std::cell::RefCell<Vec<String>>,
}

impl Compose {
    fn new(file: &'static str, project: String, run: &str, env: Vec<(&'static str, String)>) -> Self {
        Self { tool: compose_tool(), project, file, run: run.to_string(), env, one_off: Default::default() }
    }

    fn invoke(&self, args: &[&str]) -> Output {
        Command::new(&self.tool[0])
            .args(&self.tool[1..])
            .args(["-p", &self.project, "-f"])
            .arg(repo_root().join(self.file))
            .args(args)
            .env_remove("CRAWLER_RUNS")
            .env("CRAWLER_RUN", &self.run)
            .envs(self.env.iter().map(|(key, value)| (key, value)))
            .output()
            .unwrap()
    }

    fn command(&self, args: &[&str]) -> Output {
        let output = self.invoke(args);
        assert!(output.status.success(), "compose {args:?}: {}", String::from_utf8_lossy(&output.stderr));
        output
    }

    /// Starts a one-off container of `service` (`compose run -d`) with `extra` compose-run
    /// options and this command line; returns its name.
    fn run_detached(&self, name: &str, extra: &[&str], service: &str, command: &[&str]) -> String {
        let name = format!("{}-{name}", self.project);
        self.one_off.borrow_mut().push(name.clone());
        let mut args = vec!["run", "-d", "--name", &name];
        args.extend_from_slice(extra);
        args.push(service);
        args.extend_from_slice(command);
        self.command(&args);
        name
    }

    /// The run's directory on the host: compose's default, deploy/runs/<run>.
    fn run_dir(&self) -> PathBuf {
        repo_root().join("deploy/runs").join(&self.run)
    }

    fn status_path(&self) -> PathBuf {
        self.run_dir().join("status.json")
    }

    fn status(&self) -> Option<serde_json::Value> {
        read_status(&self.status_path())
    }

    fn wait_for(&self, timeout: Duration, what: &str, done: impl Fn(&serde_json::Value) -> bool) -> serde_json::Value {
        wait_for_status(&self.status_path(), timeout, what, done, || None)
    }

    fn container(&self, service: &str, index: u32) -> String {
        // Compose v1 names containers <project>_<service>_<n>, v2 <project>-<service>-<n>.
        let ps = self.command(&["ps", "-q", service]);
        let ids: Vec<String> = String::from_utf8_lossy(&ps.stdout).lines().map(String::from).collect();
        let named = |separator: &str| format!("{}{separator}{service}{separator}{index}", self.project);
        for id in &ids {
            let name = docker(&["inspect", "--format", "{{.Name}}", id]);
            let name = name.trim().trim_start_matches('/');
            if name == named("_") || name == named("-") {
                return id.clone();
            }
        }
        panic!("no container {service} #{index} among {ids:?}");
    }
}

impl Drop for Compose {
    fn drop(&mut self) {
        for name in self.one_off.borrow().iter() {
            let _ = Command::new("docker").args(["rm", "-f", name]).output();
        }
        let _ = self.invoke(&["down", "--timeout", "5"]);
        let _ = std::fs::remove_dir_all(self.run_dir());
    }
}

pub(crate) fn docker(args: &[&str]) -> String {
    let output = Command::new("docker").args(args).output().unwrap();
    assert!(output.status.success(), "docker {args:?}: {}", String::from_utf8_lossy(&output.stderr));
    String::from_utf8_lossy(&output.stdout).into_owned()
}

pub(crate) fn assert_docker_ready() {
    let engine = Command::new("docker").arg("info").output();
    assert!(
        engine.is_ok_and(|o| o.status.success()),
        "no Docker engine answers `docker info`: start one, or set CRAWLER_DOCKER_TESTS=0 to skip these tests"
    );
    for image in ["crawler-learner:latest", "crawler-actor:latest"] {
        let found = Command::new("docker").args(["image", "inspect", image]).output().unwrap().status.success();
        assert!(found, "image {image} is missing: run deploy/build-images.sh (scripts/test does)");
    }
}

/// Waits for the learner container's health check to pass.
pub(crate) fn wait_healthy(container: &str, timeout: Duration) {
    let start = std::time::Instant::now();
    loop {
        let health = docker(&["inspect", "--format", "{{.State.Health.Status}}", container]);
        if health.trim() == "healthy" {
            return;
        }
        assert!(start.elapsed() < timeout, "the learner is `{}` after {timeout:?}", health.trim());
        std::thread::sleep(Duration::from_secs(2));
    }
}

fn transitions_of(status: &serde_json::Value) -> u64 {
    status["actors"].as_object().map_or(0, |actors| actors.values().map(|a| u64_at(a, "/transitions")).sum())
}

#[test]
#[ignore = "needs a Docker engine and the images; scripts/test runs it where `docker info` answers"]
fn compose_trains_and_survives_a_killed_and_a_disconnected_actor() {
    assert_docker_ready();
    let compose = Compose::new(
        "deploy/docker-compose.yml",
        format!("crawlertest{}", std::process::id()),
        &format!("docker-test-{}", std::process::id()),
        vec![
            ("CRAWLER_PORT", free_port().to_string()),
            ("CRAWLER_CONFIG", "smoke.toml".into()),
            ("CRAWLER_SET", "learner.status_every_s=0.5".into()),
        ],
    );
    compose.command(&["up", "-d"]);
    wait_healthy(&compose.container("learner", 1), Duration::from_secs(150));
    for image in ["crawler-learner", "crawler-actor"] {
        assert_eq!(docker(&["inspect", "--format", "{{.Config.User}}", image]).trim(), "10001:10001", "{image}");
    }
    // Every program runs unprivileged and cannot gain privileges, the learner included,
    // whose entry point starts as root to hand ./runs over.
    for service in ["learner", "actor"] {
        let process = docker(&["exec", &compose.container(service, 1), "cat", "/proc/1/status"]);
        let field = |name: &str| {
            process.lines().find_map(|l| l.strip_prefix(name)).map(|v| v.split_whitespace().collect::<Vec<_>>())
        };
        let uid = field("Uid:").unwrap_or_default();
        assert!(!uid.is_empty() && uid.iter().all(|id| *id != "0"), "{service} runs as root: {process}");
        assert_eq!(field("NoNewPrivs:"), Some(vec!["1"]), "{service}: {process}");
        assert_eq!(field("CapEff:"), Some(vec!["0000000000000000"]), "{service}: {process}");
    }

    // Transitions flow from both actors (ids assigned by the learner) and weights reach them.
    compose.wait_for(Duration::from_secs(120), "two actors training with fresh weights", |s| {
        s["connected_actors"] == serde_json::json!([0, 1])
            && (0..2).all(|id| {
                u64_at(s, &format!("/actors/{id}/transitions")) > 0
                    && u64_at(s, &format!("/actors/{id}/weights_version")) >= 3
            })
    });

    // Kill one actor container: training goes on with the other.
    let victim = compose.container("actor", 2);
    docker(&["kill", &victim]);
    let status = compose.wait_for(Duration::from_secs(60), "the killed actor to leave", |s| {
        s["connected_actors"].as_array().is_some_and(|a| a.len() == 1)
    });
    let (updates, transitions) = (u64_at(&status, "/updates"), transitions_of(&status));
    compose.wait_for(Duration::from_secs(60), "training with one actor", |s| {
        u64_at(s, "/updates") > updates + 50 && transitions_of(s) > transitions
    });

    // Start it again: it rejoins and has the latest weights at once (from the queryable).
    let published = u64_at(&compose.status().unwrap(), "/weights_version");
    docker(&["start", &victim]);
    let rejoined = compose.wait_for(Duration::from_secs(60), "the restarted actor back", |s| {
        s["connected_actors"].as_array().is_some_and(|a| a.len() == 2)
    });
    let ids: Vec<u64> = rejoined["connected_actors"].as_array().unwrap().iter().filter_map(|v| v.as_u64()).collect();
    compose.wait_for(Duration::from_secs(30), "the restarted actor acting on current weights", |s| {
        ids.iter().all(|id| u64_at(s, &format!("/actors/{id}/weights_version")) >= published)
    });

    // Cut the other actor off the network for longer than zenoh's lease, then reconnect it.
    let cut = compose.container("actor", 1);
    let network = format!("{}_default", compose.project);
    docker(&["network", "disconnect", &network, &cut]);
    std::thread::sleep(Duration::from_secs(15));
    let before = transitions_of(&compose.status().unwrap());
    docker(&["network", "connect", &network, &cut]);
    compose.wait_for(Duration::from_secs(90), "the reconnected actor sending again", |s| {
        s["connected_actors"].as_array().is_some_and(|a| a.len() == 2) && transitions_of(s) > before + 1000
    });
    let status = compose.status().unwrap();
    assert_eq!(status["dropped_batches"], 0, "{status:#}");

    // A checkpoint on the host, and `eval` on it by the documented command.
    let checkpoints = compose.run_dir().join("checkpoints");
    assert!(crawler_learner::checkpoint::load(&checkpoints).is_ok(), "no checkpoint in {}", checkpoints.display());
    let in_container = format!("/runs/{}/checkpoints", compose.run);
    let eval =
        compose.command(&["run", "--rm", "-T", "learner", "eval", &in_container, "--episodes", "1", "--seconds", "2"]);
    let report: serde_json::Value = serde_json::from_slice(&eval.stdout)
        .unwrap_or_else(|e| panic!("eval printed no JSON ({e}): {}", String::from_utf8_lossy(&eval.stdout)));
    assert!(report.to_string().contains("speed"), "{report}");

    // The tools link no libtorch, so the small actor image evaluates checkpoints too.
    let libraries = docker(&["run", "--rm", "--entrypoint", "ldd", "crawler-actor", "/usr/local/bin/eval"]);
    assert!(!libraries.contains("torch") && !libraries.contains("not found"), "eval in the actor image: {libraries}");
    let mount = format!("{}:/runs:ro", compose.run_dir().parent().unwrap().display());
    let report = eval_in_actor_image(&mount, &in_container);
    assert!(report["episodes"].as_array().is_some_and(|e| e.len() == 1), "{report}");

    // A graceful stop leaves a final checkpoint.
    compose.command(&["stop", "--timeout", "60", "learner"]);
    let checkpoint = crawler_learner::checkpoint::load(&checkpoints).unwrap();
    assert!(checkpoint.meta.progress.updates >= updates);
    assert!(Path::new(&compose.run_dir().join("metrics.csv")).exists());
}

/// `eval` of `checkpoints` (a path inside the container) for one 2 s episode, run from the
/// actor image with `mount` (`-v` syntax); its JSON report.
pub(crate) fn eval_in_actor_image(mount: &str, checkpoints: &str) -> serde_json::Value {
    let eval = docker(&[
        "run",
        "--rm",
        "--entrypoint",
        "eval",
        "-v",
        mount,
        "crawler-actor",
        checkpoints,
        "--episodes",
        "1",
        "--seconds",
        "2",
    ]);
    serde_json::from_str(&eval).unwrap_or_else(|e| panic!("eval in the actor image printed no JSON ({e}): {eval}"))
}

/// The names of the Docker networks a container is attached to.
fn networks_of(container: &str) -> Vec<String> {
    docker(&["inspect", "--format", "{{range $name, $_ := .NetworkSettings.Networks}}{{$name}} {{end}}", container])
        .split_whitespace()
        .map(String::from)
        .collect()
}

#[test]
#[ignore = "needs a Docker engine and the images; scripts/test runs it where `docker info` answers"]
fn actors_of_another_compose_project_join_over_mutual_tls_and_nothing_else_does() {
    assert_docker_ready();
    let pid = std::process::id();
    let material = tempfile::tempdir().unwrap();
    // As deploy/README.md says: make-tls.sh with the name the actors dial. Here both projects
    // share one machine, so the actors dial the host's published port as host.docker.internal.
    let tls = make_tls(&material.path().join("tls"), "host.docker.internal", 2);
    let other_ca = make_tls(&material.path().join("other-ca"), "host.docker.internal", 1);
    let port = free_port();
    let run = format!("docker-tls-test-{pid}");

    // The learner host: compose.learner-tls.yml, its TLS port published on the host.
    let learner = Compose::new(
        "deploy/compose.learner-tls.yml",
        format!("crawlertls{pid}learner"),
        &run,
        vec![
            ("CRAWLER_PORT", port.to_string()),
            ("CRAWLER_TLS", tls.display().to_string()),
            ("CRAWLER_CONFIG", "smoke.toml".into()),
            ("CRAWLER_SET", "learner.status_every_s=0.5".into()),
        ],
    );
    learner.command(&["up", "-d"]);
    let learner_container = learner.container("learner", 1);
    wait_healthy(&learner_container, Duration::from_secs(150));

    // The actor host: compose.actors.yml in a project of its own, on its own network.
    let actors = Compose::new(
        "deploy/compose.actors.yml",
        format!("crawlertls{pid}actors"),
        &run,
        vec![("CRAWLER_LEARNER", format!("host.docker.internal:{port}")), ("CRAWLER_TLS", tls.display().to_string())],
    );
    actors.command(&["up", "-d"]);
    // A second actor on that machine: its own certificate, in a project of its own, as the
    // file's header says (a certificate names one actor).
    let second = Compose::new(
        "deploy/compose.actors.yml",
        format!("crawlertls{pid}actors1"),
        &run,
        vec![
            ("CRAWLER_LEARNER", format!("host.docker.internal:{port}")),
            ("CRAWLER_TLS", tls.display().to_string()),
            ("CRAWLER_TLS_NAME", "actor-1".into()),
        ],
    );
    second.command(&["up", "-d", "actor"]);
    let actor_networks = networks_of(&actors.container("actor", 1));
    let learner_networks = networks_of(&learner_container);
    assert!(
        actor_networks.iter().all(|n| !learner_networks.contains(n)),
        "the projects share a network: actors {actor_networks:?}, learner {learner_networks:?}"
    );

    let joined = learner.wait_for(Duration::from_secs(120), "two remote actors training with fresh weights", |s| {
        s["connected_actors"] == serde_json::json!([0, 1])
            && (0..2).all(|id| {
                u64_at(s, &format!("/actors/{id}/transitions")) > 0
                    && u64_at(s, &format!("/actors/{id}/weights_version")) >= 3
            })
    });
    learner.wait_for(Duration::from_secs(60), "a greedy evaluation from the remote evaluator", |s| {
        s["last_evaluation_speed"].is_number()
    });

    // Two actor containers of the actors' project that must never join: one trusts the CA
    // but has no certificate of its own, one presents a certificate from another CA.
    let learner_address = format!("--connect=tls/host.docker.internal:{port}");
    let run_flag = format!("--run={run}");
    let no_certificate = actors.run_detached(
        "no-certificate",
        &[],
        "actor",
        &[
            &learner_address,
            &run_flag,
            "--id=auto",
            "--zenoh",
            r#"transport/link/tls/root_ca_certificate="/tls/ca.pem""#,
        ],
    );
    let other_ca_mount = format!("{}:/other:ro", other_ca.display());
    let foreign_certificate = actors.run_detached(
        "other-ca",
        &["-v", &other_ca_mount],
        "actor",
        &[
            &learner_address,
            &run_flag,
            "--id=auto",
            "--tls-ca=/tls/ca.pem",
            "--tls-cert=/other/actor-0.pem",
            "--tls-key=/other/actor-0.key",
        ],
    );

    // For 30 s of their retrying, the learner's liveliness view holds the two genuine actors
    // only, and training goes on.
    let updates = u64_at(&joined, "/updates");
    let watch = std::time::Instant::now();
    while watch.elapsed() < Duration::from_secs(30) {
        let status = learner.status().unwrap();
        assert_eq!(status["connected_actors"], serde_json::json!([0, 1]), "{status:#}");
        assert!(status["actors"].as_object().is_some_and(|a| a.keys().all(|id| id == "0" || id == "1")), "{status:#}");
        std::thread::sleep(Duration::from_millis(500));
    }
    let status =
        learner.wait_for(Duration::from_secs(30), "training going on", |s| u64_at(s, "/updates") > updates + 50);
    assert_eq!(status["connected_actors"], serde_json::json!([0, 1]), "{status:#}");

    // The rogues really tried, at the learner's address, all along: still running (an actor
    // keeps retrying a learner it cannot reach), and never joined the run.
    for rogue in [&no_certificate, &foreign_certificate] {
        assert_eq!(docker(&["inspect", "--format", "{{.State.Running}}", rogue]).trim(), "true", "{rogue} exited");
        let logs = Command::new("docker").args(["logs", rogue]).output().unwrap();
        let logs = String::from_utf8_lossy(&logs.stderr).into_owned() + &String::from_utf8_lossy(&logs.stdout);
        assert!(
            logs.contains("connecting to the learner") && logs.contains(&format!("host.docker.internal:{port}")),
            "{rogue}: {logs}"
        );
        assert!(!logs.contains("joined run"), "{rogue}: {logs}");
    }
}
