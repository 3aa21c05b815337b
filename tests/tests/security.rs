//! The secured link, with real processes: a learner on a `tls/` endpoint with mutual TLS and
//! its access-control policy, actors and probes holding certificates from
//! `deploy/make-tls.sh`. zenoh drops denied messages without telling the sender, so every
//! assertion is about what arrived: at the learner (status.json), at a genuine actor (its
//! log and reported weights version) and at an observer subscribed to the whole run.

#![allow(clippy::unwrap_used)]

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crawler_tests::{Actor, FORGED_VERSION, Learner, binary, free_port, repo_root, u64_at};

const SMOKE: &str = "configs/smoke.toml";

/// TLS material for a deployment: `make-tls.sh DIR localhost 2`.
fn make_tls(dir: &Path) -> PathBuf {
    let status = Command::new("bash")
        .arg(repo_root().join("deploy/make-tls.sh"))
        .args([dir.to_str().unwrap(), "localhost", "2"])
        .status()
        .unwrap();
    assert!(status.success(), "make-tls.sh failed");
    dir.to_path_buf()
}

/// `--tls-ca/--tls-cert/--tls-key` for certificate `name` (learner, actor-0, observer…).
fn tls_flags(ca: &Path, material: &Path, name: &str) -> Vec<String> {
    vec![
        "--tls-ca".into(),
        ca.join("ca.pem").display().to_string(),
        "--tls-cert".into(),
        material.join(format!("{name}.pem")).display().to_string(),
        "--tls-key".into(),
        material.join(format!("{name}.key")).display().to_string(),
    ]
}

fn start_learner(port: u16, runs: &Path, run: &str, tls: &Path) -> Learner {
    let listen = format!("learner.listen=[\"tls/127.0.0.1:{port}\"]");
    let mut extra = vec!["--set".to_string(), listen];
    extra.extend(tls_flags(tls, tls, "learner"));
    let extra: Vec<&str> = extra.iter().map(String::as_str).collect();
    Learner::start_on(port, SMOKE, runs, run, 0, &extra)
}

fn start_actor(port: u16, id: u32, run: &str, tls: Vec<String>, log_dir: &Path) -> Actor {
    let connect = format!("tls/localhost:{port}");
    let mut args = vec!["--connect".to_string(), connect, "--id".into(), id.to_string(), "--run".into(), run.into()];
    args.extend(tls);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    Actor::start_args(&args, log_dir)
}

/// A `probe listen` process; the JSON lines it prints are collected as they come.
struct Listener {
    child: Child,
    lines: Arc<Mutex<Vec<serde_json::Value>>>,
}

impl Listener {
    fn start(port: u16, key: &str, tls: Vec<String>) -> Self {
        let mut child = Command::new(binary("probe"))
            .args(["--connect", &format!("tls/localhost:{port}")])
            .args(tls)
            .args(["listen", key])
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap();
        let stdout = child.stdout.take().unwrap();
        let lines = Arc::new(Mutex::new(Vec::new()));
        let sink = Arc::clone(&lines);
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                sink.lock().unwrap().push(serde_json::from_str(&line).unwrap());
            }
        });
        Self { child, lines }
    }

    fn received(&self) -> Vec<serde_json::Value> {
        self.lines.lock().unwrap().clone()
    }

    fn count(&self, matches: impl Fn(&serde_json::Value) -> bool) -> usize {
        self.received().iter().filter(|l| matches(l)).count()
    }

    fn wait_for(&self, timeout: Duration, what: &str, matches: impl Fn(&serde_json::Value) -> bool) {
        let start = Instant::now();
        while self.count(&matches) == 0 {
            assert!(start.elapsed() < timeout, "the observer saw no {what} in {timeout:?}");
            std::thread::sleep(Duration::from_millis(100));
        }
    }
}

impl Drop for Listener {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Runs `probe forge` with a certificate; returns what it says it sent.
fn forge(port: u16, run: &str, id: u32, tls: Vec<String>) -> serde_json::Value {
    let output = Command::new(binary("probe"))
        .args(["--connect", &format!("tls/localhost:{port}")])
        .args(tls)
        .args(["forge", "--run", run, "--id", &id.to_string(), "--seconds", "3"])
        .stderr(Stdio::inherit())
        .output()
        .unwrap();
    assert!(output.status.success(), "probe forge failed");
    serde_json::from_slice(&output.stdout).unwrap()
}

fn key_is(line: &serde_json::Value, key: &str) -> bool {
    line["key"] == key
}

#[test]
fn only_actors_with_a_certificate_from_the_runs_ca_connect() {
    let dir = tempfile::tempdir().unwrap();
    let tls = make_tls(&dir.path().join("tls"));
    // A second CA: its certificates are well-formed but signed by the wrong authority.
    let rogue = make_tls(&dir.path().join("rogue"));
    let runs = dir.path().join("runs");
    let port = free_port();
    let run = "tls-connect";
    let mut learner = start_learner(port, &runs, run, &tls);

    let genuine = start_actor(port, 0, run, tls_flags(&tls, &tls, "actor-0"), dir.path());
    // It trusts the learner (right CA) but presents a certificate of another CA.
    let mut wrong_ca = start_actor(port, 5, run, tls_flags(&tls, &rogue, "actor-0"), dir.path());
    // It trusts the learner but presents no certificate at all.
    let no_certificate_setting =
        format!("transport/link/tls/root_ca_certificate={:?}", tls.join("ca.pem").display().to_string());
    let mut no_certificate = start_actor(port, 6, run, vec!["--zenoh".into(), no_certificate_setting], dir.path());

    learner.wait_for(Duration::from_secs(120), "the genuine actor training", |s| {
        u64_at(s, "/actors/0/transitions") > 0 && u64_at(s, "/updates") > 20
    });
    // Both refused actors retry every second or so; give them several attempts.
    std::thread::sleep(Duration::from_secs(6));
    let status = learner.status().unwrap();
    assert_eq!(status["connected_actors"], serde_json::json!([0]), "{status:#}");
    for id in ["5", "6"] {
        assert!(status["actors"].get(id).is_none(), "actor {id} reached the learner: {status:#}");
    }
    for (name, actor) in [("wrong CA", &mut wrong_ca), ("no certificate", &mut no_certificate)] {
        assert!(actor.is_running(), "the {name} actor gave up instead of waiting: {}", actor.log_text());
        let log = actor.log_text();
        assert!(!log.contains("joined run") && !log.contains("first weights"), "the {name} actor got in: {log}");
    }
    drop(genuine);
}

#[test]
fn an_authenticated_actor_cannot_forge_weights_or_put_outside_its_rights() {
    let dir = tempfile::tempdir().unwrap();
    let tls = make_tls(&dir.path().join("tls"));
    let runs = dir.path().join("runs");
    let port = free_port();
    let run = "tls-forge";
    let mut learner = start_learner(port, &runs, run, &tls);
    let mut genuine = start_actor(port, 0, run, tls_flags(&tls, &tls, "actor-0"), dir.path());
    let observer = Listener::start(port, &format!("crawler/{run}/**"), tls_flags(&tls, &tls, "observer"));
    learner.wait_for(Duration::from_secs(120), "training with published weights", |s| {
        u64_at(s, "/actors/0/transitions") > 0 && u64_at(s, "/weights_version") >= 2
    });
    let weights_key = format!("crawler/{run}/weights");
    // Positive controls: the observer's subscription works for what is allowed.
    observer.wait_for(Duration::from_secs(30), "genuine weights", |l| key_is(l, &weights_key));
    observer.wait_for(Duration::from_secs(30), "the genuine actor's transitions", |l| {
        key_is(l, &format!("crawler/{run}/transitions/0"))
    });

    // Actor 1 holds a valid actor certificate and turns bad.
    let sent = forge(port, run, 1, tls_flags(&tls, &tls, "actor-1"));
    eprintln!("forger sent {sent}");
    for what in ["forged_weights", "forged_stop", "forged_info", "own_transitions"] {
        assert!(sent[what].as_u64().unwrap() >= 5, "the forger sent too few {what}: {sent}");
    }
    // An observer may read, not write: its puts go nowhere either.
    let observer_sent = forge(port, run, 2, tls_flags(&tls, &tls, "observer"));
    assert!(observer_sent["own_transitions"].as_u64().unwrap() >= 5, "{observer_sent}");
    std::thread::sleep(Duration::from_secs(2));

    // Inside its rights: the forger's own transitions arrived.
    let own = observer.count(|l| key_is(l, &format!("crawler/{run}/transitions/1")));
    assert!(own >= 5, "the forger's allowed puts did not arrive ({own}); the denials below would prove nothing");
    // Outside them: nothing arrived, anywhere.
    let received = observer.received();
    let forged: Vec<_> = received.iter().filter(|l| l["weights_version"] == FORGED_VERSION).collect();
    assert!(forged.is_empty(), "{} times forged weights reached the observer, e.g. {:?}", forged.len(), forged.first());
    let control: Vec<_> = received.iter().filter(|l| key_is(l, &format!("crawler/{run}/control"))).collect();
    assert!(
        control.is_empty(),
        "{} times a forged stop reached the observer, e.g. {:?}",
        control.len(),
        control.first()
    );
    let info: Vec<_> = received.iter().filter(|l| key_is(l, &format!("crawler/{run}/info"))).collect();
    assert!(info.is_empty(), "{} times a forged run info reached the observer, e.g. {:?}", info.len(), info.first());
    let from_observer = observer.count(|l| key_is(l, &format!("crawler/{run}/transitions/2")));
    assert_eq!(from_observer, 0, "the observer's own puts arrived");

    // The genuine actor never took the forged weights or the forged stop, and trains on.
    assert!(genuine.is_running(), "the genuine actor stopped: {}", genuine.log_text());
    let log = genuine.log_text();
    assert!(!log.contains("learner says stop"), "{log}");
    assert!(!log.contains(&FORGED_VERSION.to_string()), "{log}");
    let status = learner.wait_for(Duration::from_secs(30), "the genuine actor reporting again", |s| {
        u64_at(s, "/actors/0/weights_version") >= 2
    });
    let acted_on = u64_at(&status, "/actors/0/weights_version");
    assert!(acted_on < FORGED_VERSION && acted_on <= u64_at(&status, "/weights_version"), "{status:#}");
    // The learner took the forger's batches like any actor's (they pass validation), and
    // nothing of the observer's.
    assert!(status["actors"].get("1").is_some(), "{status:#}");
    assert!(status["actors"].get("2").is_none(), "{status:#}");
}
