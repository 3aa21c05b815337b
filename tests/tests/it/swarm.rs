//! `deploy/stack.yml` on a single-node Docker Swarm, as deploy/README.md ("A cluster") runs
//! it, with the images `deploy/build-images.sh` builds: the learner turns healthy; actors
//! scaled 2 → 6 → 3 while it trains show up in `status.json`'s `connected_actors`; a killed
//! actor container is replaced by the swarm and accepted by the learner; `docker stack rm`
//! leaves a final checkpoint in the stack's volume that `eval` loads.
//!
//! The node is left as it was found: a swarm this test created is left again, a label it
//! added is removed, and so are the stack and its volume.
//!
//! Ignored unless asked for (`--ignored`), like the compose tests.

#![allow(clippy::unwrap_used)]

use std::collections::BTreeSet;
use std::process::Command;
use std::time::{Duration, Instant};

use crawler_tests::{repo_root, u64_at};

use crate::docker::{assert_docker_ready, docker, eval_in_actor_image, wait_healthy};

/// The node label that places the learner (deploy/stack.yml).
const LEARNER_LABEL: &str = "crawler.learner";

/// A stack deployed on this node's swarm, removed with what the test changed.
struct Stack {
    name: String,
    run: String,
    created_swarm: bool,
    added_label: Option<String>,
}

impl Stack {
    /// Joins (or makes) a single-node swarm, labels this node for the learner, and deploys
    /// the stack with `env` as `docker stack deploy`'s environment.
    fn deploy(name: String, run: &str, env: &[(&str, String)]) -> Self {
        let state = docker(&["info", "--format", "{{.Swarm.LocalNodeState}}"]);
        let created_swarm = state.trim() == "inactive";
        if created_swarm {
            docker(&["swarm", "init", "--advertise-addr", "127.0.0.1"]);
        }
        let node = docker(&["info", "--format", "{{.Swarm.NodeID}}"]).trim().to_string();
        let labels = docker(&["node", "inspect", "--format", "{{json .Spec.Labels}}", &node]);
        let added_label = (!labels.contains(LEARNER_LABEL)).then(|| {
            docker(&["node", "update", "--label-add", &format!("{LEARNER_LABEL}=true"), &node]);
            node.clone()
        });
        let stack = Self { name, run: run.to_string(), created_swarm, added_label };
        let output = Command::new("docker")
            .args(["stack", "deploy", "--resolve-image", "never", "-c"])
            .arg(repo_root().join("deploy/stack.yml"))
            .arg(&stack.name)
            .env("CRAWLER_RUN", run)
            .envs(env.iter().map(|(k, v)| (k, v)))
            .output()
            .unwrap();
        assert!(output.status.success(), "stack deploy: {}", String::from_utf8_lossy(&output.stderr));
        stack
    }

    fn service(&self, service: &str) -> String {
        format!("{}_{service}", self.name)
    }

    /// Running containers of `service`.
    fn containers(&self, service: &str) -> BTreeSet<String> {
        let filter = format!("label=com.docker.swarm.service.name={}", self.service(service));
        docker(&["ps", "-q", "--filter", &filter, "--filter", "status=running"]).lines().map(String::from).collect()
    }

    fn learner(&self, timeout: Duration) -> String {
        let start = Instant::now();
        loop {
            if let Some(id) = self.containers("learner").into_iter().next() {
                return id;
            }
            assert!(start.elapsed() < timeout, "no learner container after {timeout:?}: {}", self.tasks("learner"));
            std::thread::sleep(Duration::from_secs(1));
        }
    }

    /// `docker service ps` of a service, for failure messages.
    fn tasks(&self, service: &str) -> String {
        let output = Command::new("docker").args(["service", "ps", "--no-trunc", &self.service(service)]).output();
        output.map(|o| String::from_utf8_lossy(&o.stdout).into_owned()).unwrap_or_default()
    }

    /// The learner's status.json, read inside its container.
    fn status(&self, learner: &str) -> Option<serde_json::Value> {
        let path = format!("/runs/{}/status.json", self.run);
        let output = Command::new("docker").args(["exec", learner, "cat", &path]).output().ok()?;
        serde_json::from_slice(&output.stdout).ok()
    }

    fn wait_for(
        &self,
        learner: &str,
        timeout: Duration,
        what: &str,
        done: impl Fn(&serde_json::Value) -> bool,
    ) -> serde_json::Value {
        let start = Instant::now();
        loop {
            let status = self.status(learner);
            if let Some(status) = status.as_ref().filter(|s| done(s)) {
                return status.clone();
            }
            assert!(
                start.elapsed() < timeout,
                "waited {timeout:?} for {what}; status: {status:#?}\nactor tasks:\n{}",
                self.tasks("actor")
            );
            std::thread::sleep(Duration::from_millis(500));
        }
    }

    fn scale(&self, actors: u32) {
        docker(&["service", "scale", "--detach", &format!("{}={actors}", self.service("actor"))]);
    }

    /// Removes the stack and waits until its containers are gone.
    fn remove(&self, timeout: Duration) {
        docker(&["stack", "rm", &self.name]);
        let filter = format!("label=com.docker.stack.namespace={}", self.name);
        let start = Instant::now();
        while !docker(&["ps", "-aq", "--filter", &filter]).trim().is_empty() {
            assert!(start.elapsed() < timeout, "the stack's containers outlived {timeout:?}");
            std::thread::sleep(Duration::from_secs(1));
        }
    }

    fn volume(&self) -> String {
        format!("{}_runs", self.name)
    }
}

impl Drop for Stack {
    fn drop(&mut self) {
        let quiet = |args: &[&str]| {
            let _ = Command::new("docker").args(args).output();
        };
        quiet(&["stack", "rm", &self.name]);
        // The volume can go once the stack's containers have.
        let filter = format!("label=com.docker.stack.namespace={}", self.name);
        for _ in 0..60 {
            let left = Command::new("docker").args(["ps", "-aq", "--filter", &filter]).output();
            if left.is_ok_and(|o| o.stdout.is_empty()) {
                break;
            }
            std::thread::sleep(Duration::from_secs(1));
        }
        quiet(&["volume", "rm", &self.volume()]);
        if self.created_swarm {
            quiet(&["swarm", "leave", "--force"]);
        } else if let Some(node) = &self.added_label {
            quiet(&["node", "update", "--label-rm", LEARNER_LABEL, node]);
        }
    }
}

fn connected(status: &serde_json::Value) -> usize {
    status["connected_actors"].as_array().map_or(0, Vec::len)
}

#[test]
#[ignore = "needs a Docker engine and the images; scripts/test runs it where `docker info` answers"]
fn a_swarm_stack_scales_replaces_and_stops_with_a_checkpoint() {
    assert_docker_ready();
    let pid = std::process::id();
    let stack = Stack::deploy(
        format!("crawlertest{pid}"),
        "swarm-test",
        &[
            ("CRAWLER_CONFIG", "smoke.toml".into()),
            ("CRAWLER_SET", "learner.status_every_s=0.5".into()),
            ("CRAWLER_ACTORS", "2".into()),
            ("CRAWLER_MAX_ACTORS", "16".into()),
            // Eight containers share this machine's cores.
            ("CRAWLER_ACTOR_CPUS", "0.25".into()),
            ("CRAWLER_LEARNER_MEMORY", "2G".into()),
        ],
    );
    let learner = stack.learner(Duration::from_secs(120));
    wait_healthy(&learner, Duration::from_secs(150));
    stack.wait_for(&learner, Duration::from_secs(120), "two actors training", |s| {
        connected(s) == 2 && u64_at(s, "/updates") > 0
    });

    // Scale out, then in, while it trains: the learner's view follows.
    stack.scale(6);
    let six = stack.wait_for(&learner, Duration::from_secs(180), "six actors connected", |s| connected(s) == 6);
    stack.scale(3);
    stack.wait_for(&learner, Duration::from_secs(120), "three actors connected", |s| connected(s) == 3);
    let status = stack.wait_for(&learner, Duration::from_secs(60), "training on with three actors", |s| {
        connected(s) == 3 && u64_at(s, "/updates") > u64_at(&six, "/updates") + 50
    });
    assert_eq!(stack.containers("actor").len(), 3, "{}", stack.tasks("actor"));

    // Kill an actor's container: the swarm starts a replacement, and the learner takes it.
    let before = stack.containers("actor");
    let victim = before.iter().next().unwrap().clone();
    docker(&["kill", &victim]);
    let start = Instant::now();
    let replacement = loop {
        let now = stack.containers("actor");
        if let Some(new) = now.difference(&before).next()
            && now.len() == 3
        {
            break new.clone();
        }
        assert!(start.elapsed() < Duration::from_secs(120), "no replacement for {victim}: {}", stack.tasks("actor"));
        std::thread::sleep(Duration::from_secs(1));
    };
    let updates = u64_at(&status, "/updates");
    stack.wait_for(&learner, Duration::from_secs(120), "the replacement connected and training", |s| {
        connected(s) == 3 && u64_at(s, "/updates") > updates + 50
    });
    let logs = Command::new("docker").args(["logs", &replacement]).output().unwrap();
    let logs = String::from_utf8_lossy(&logs.stderr).into_owned() + &String::from_utf8_lossy(&logs.stdout);
    assert!(logs.contains("joined run"), "the replacement {replacement} never joined: {logs}");
    let last = stack.status(&learner).unwrap();

    // `docker stack rm`: the learner checkpoints on SIGTERM, and the volume keeps it.
    stack.remove(Duration::from_secs(180));
    let checkpoints = format!("/runs/{}/checkpoints", stack.run);
    let mount = format!("{}:/runs:ro", stack.volume());
    let listing = docker(&["run", "--rm", "-v", &mount, "--entrypoint", "ls", "crawler-actor", &checkpoints]);
    let newest = listing
        .lines()
        .filter_map(|name| name.strip_prefix("step-")?.parse::<u64>().ok())
        .max()
        .unwrap_or_else(|| panic!("no checkpoint in the volume: {listing}"));
    assert!(newest >= u64_at(&last, "/updates"), "newest checkpoint step {newest}, last status {last:#}");
    let report = eval_in_actor_image(&mount, &checkpoints);
    assert!(report["episodes"].as_array().is_some_and(|e| e.len() == 1), "{report}");
}
