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

use crawler_tests::{Actor, FORGED_VERSION, Learner, binary, free_port, make_tls, u64_at};

const SMOKE: &str = "configs/smoke.toml";

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
    Learner::builder(runs, run).port(port).config(SMOKE).args(&extra).start()
}

/// A learner on a mutual-TLS loopback endpoint, with `make-tls.sh` material for `actors`
/// actors in a temporary directory that lives as long as this.
struct TlsLearner {
    dir: tempfile::TempDir,
    tls: PathBuf,
    port: u16,
    learner: Learner,
}

fn tls_learner(run: &str, actors: u32) -> TlsLearner {
    let dir = tempfile::tempdir().unwrap();
    let tls = make_tls(&dir.path().join("tls"), "localhost", actors);
    let port = free_port();
    let learner = start_learner(port, &dir.path().join("runs"), run, &tls);
    TlsLearner { dir, tls, port, learner }
}

fn start_actor(port: u16, id: u32, run: &str, tls: Vec<String>, log_dir: &Path) -> Actor {
    start_actor_at(&format!("tls/localhost:{port}"), &id.to_string(), run, &tls, log_dir)
}

/// `actor --connect ENDPOINT --id ID --run RUN` plus TLS flags (`ID` may be `auto`).
fn start_actor_at(endpoint: &str, id: &str, run: &str, tls: &[String], log_dir: &Path) -> Actor {
    let mut args: Vec<&str> = vec!["--connect", endpoint, "--id", id, "--run", run];
    args.extend(tls.iter().map(String::as_str));
    Actor::start_args(&args, log_dir)
}

/// A `probe listen` process; the JSON lines it prints are collected as they come.
struct Listener {
    child: Child,
    lines: Arc<Mutex<Vec<serde_json::Value>>>,
}

impl Listener {
    fn start(port: u16, keys: &[String], tls: Vec<String>) -> Self {
        let mut child = Command::new(binary("probe"))
            .args(["--connect", &format!("tls/localhost:{port}")])
            .args(tls)
            .arg("listen")
            .args(keys)
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
    let run = "tls-connect";
    let TlsLearner { dir, tls, port, mut learner } = tls_learner(run, 2);
    // A second CA: its certificates are well-formed but signed by the wrong authority.
    let rogue = make_tls(&dir.path().join("rogue"), "localhost", 2);

    let genuine = start_actor(port, 0, run, tls_flags(&tls, &tls, "actor-0"), dir.path());
    // It trusts the learner (right CA) but presents a certificate of another CA.
    let mut wrong_ca = start_actor(port, 1, run, tls_flags(&tls, &rogue, "actor-1"), dir.path());
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
    for id in ["1", "6"] {
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
    let run = "tls-forge";
    let TlsLearner { dir, tls, port, mut learner } = tls_learner(run, 2);
    let mut genuine = start_actor(port, 0, run, tls_flags(&tls, &tls, "actor-0"), dir.path());
    // Everything an observer may read: all but transitions (a stalled reader of those would
    // block the actors).
    let readable =
        ["weights", "control", "info", "stats/*", "status/*"].map(|key| format!("crawler/{run}/{key}")).to_vec();
    let observer = Listener::start(port, &readable, tls_flags(&tls, &tls, "observer"));
    learner.wait_for(Duration::from_secs(120), "training with published weights", |s| {
        u64_at(s, "/actors/0/transitions") > 0 && u64_at(s, "/weights_version") >= 2
    });
    let weights_key = format!("crawler/{run}/weights");
    // Positive controls: the observer's subscription works for what is allowed.
    observer.wait_for(Duration::from_secs(30), "genuine weights", |l| key_is(l, &weights_key));
    observer.wait_for(Duration::from_secs(30), "the genuine actor's status", |l| {
        key_is(l, &format!("crawler/{run}/status/0"))
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

    // Inside its rights: the forger's own transitions arrived (at the learner: no remote
    // session may subscribe to transitions).
    let status = learner.status().unwrap();
    let own = u64_at(&status, "/actors/1/batches");
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
    assert!(status["actors"].get("2").is_none(), "the observer's own puts arrived: {status:#}");
}

/// Actor 0's certificate, used as actor 1 while the genuine actor 1 trains: its token, puts,
/// credit subscription and queryables under actor 1's keys reach nobody, while the same
/// session's own actor-0 traffic gets through (the positive control).
#[test]
fn a_certificate_cannot_put_declare_or_reply_as_another_actor() {
    let run = "tls-as-another";
    let TlsLearner { dir, tls, port, mut learner } = tls_learner(run, 2);
    let victim = start_actor(port, 1, run, tls_flags(&tls, &tls, "actor-1"), dir.path());
    learner.wait_for(Duration::from_secs(120), "actor 1 training", |s| {
        u64_at(s, "/actors/1/transitions") > 0 && u64_at(s, "/updates") > 20
    });

    let mut attacker = Command::new(binary("probe"))
        .args(["--connect", &format!("tls/localhost:{port}")])
        .args(tls_flags(&tls, &tls, "actor-0"))
        .args(["attack", "as-another", "--run", run, "--id", "0", "--victim", "1", "--seconds", "40"])
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap();
    let mut first = String::new();
    BufReader::new(attacker.stdout.take().unwrap()).read_line(&mut first).unwrap();
    let report: serde_json::Value = serde_json::from_str(&first).unwrap();
    eprintln!("attack as-another: {report}");
    assert!(report["sent"].as_u64().unwrap() >= 30, "{report}");

    // Put: the poisoned batches and NaN statuses under actor 1's keys would each be counted
    // had one arrived; actor 0's own batches arrived.
    let status =
        learner.wait_for(Duration::from_secs(30), "actor 0's own batches", |s| u64_at(s, "/actors/0/batches") >= 1);
    for kind in ["non_finite", "out_of_range", "not_live", "key_mismatch", "incarnation_busy", "retired_incarnation"] {
        assert_eq!(
            rejected(&status, kind),
            0,
            "a message under actor 1's keys reached the learner ({kind}): {status:#}"
        );
    }
    // Subscribe: actor 1's insert credit never reached the attacker; its own did.
    assert_eq!(report["victim_credits"], 0, "{report}");
    assert!(report["own_credits"].as_u64().unwrap() >= 1, "no credit for the attacker's own id: {report}");
    // Reply: the attacker's queryables answer nobody; the learner's do.
    let asked = Command::new(binary("probe"))
        .args(["--connect", &format!("tls/localhost:{port}")])
        .args(tls_flags(&tls, &tls, "actor-1"))
        .args(["query", &format!("crawler/{run}/info"), &format!("crawler/{run}/weights")])
        .stderr(Stdio::inherit())
        .output()
        .unwrap();
    assert!(asked.status.success());
    for line in String::from_utf8_lossy(&asked.stdout).lines() {
        let answer: serde_json::Value = serde_json::from_str(line).unwrap();
        assert_eq!(answer["forged"], 0, "the attacker's queryable answered: {answer}");
        assert!(answer["replies"].as_u64().unwrap() >= 1, "the learner did not answer: {answer}");
    }
    // Declare: with the genuine actor 1 gone, the attacker's token for actor 1 (still held)
    // keeps nothing on the learner's books.
    drop(victim);
    let gone = learner.wait_for(Duration::from_secs(30), "actor 1 off the books", |s| {
        s["connected_actors"].as_array().is_some_and(|c| !c.contains(&1.into()))
    });
    assert!(gone["connected_actors"].as_array().unwrap().contains(&0.into()), "{gone:#}");
    let _ = attacker.kill();
    let _ = attacker.wait();
}

// ---------------------------------------------------------------------------------------------
// The attack suite: every attack of docs/SECURITY.md's table, by a real process, while a
// learner and two actors train; once over plain TCP on loopback (any session is an actor of
// any id there) and once over mutual TLS with an attacker holding a valid actor certificate
// (then the router denies whatever it does under another id, and the suite checks that).

/// How the attacker and the extra actors connect.
struct Link {
    endpoint: String,
    /// Over mutual TLS, the directory of `make-tls.sh`'s material; over plain TCP none.
    tls: Option<PathBuf>,
}

/// The certificate the attacker holds over mutual TLS: a genuine actor's, gone bad.
const ATTACKER_CERTIFICATE_ID: u32 = 2;
/// Actors that join during the suite: under a forged run info, with `--id auto`, and after
/// squatters (each its own certificate over mutual TLS).
const JOINER_ID: u32 = 3;
const AUTO_CERTIFICATE_ID: u32 = 4;
const LATE_ID: u32 = 5;

impl Link {
    /// Whether sessions are told apart by certificate: then the router denies everything
    /// the attacker does under another id before the learner sees it.
    fn certified(&self) -> bool {
        self.tls.is_some()
    }

    /// The attacker's own id: the one its certificate names, or any id over plain TCP.
    fn attacker_id(&self) -> u32 {
        if self.certified() { ATTACKER_CERTIFICATE_ID } else { 900 }
    }

    /// TLS flags of actor `id`'s certificate (none over plain TCP).
    fn actor_flags(&self, id: u32) -> Vec<String> {
        self.tls.as_ref().map(|tls| tls_flags(tls, tls, &format!("actor-{id}"))).unwrap_or_default()
    }

    /// `probe attack KIND` over this link, as the attacker.
    fn probe_attack(&self, run: &str, kind: &str, seconds: f64) -> Command {
        let mut command = Command::new(binary("probe"));
        command
            .args(["--connect", &self.endpoint])
            .args(self.actor_flags(ATTACKER_CERTIFICATE_ID))
            .args(["attack", kind, "--run", run, "--seconds", &seconds.to_string()])
            .args(["--id", &self.attacker_id().to_string()])
            .stderr(Stdio::inherit());
        command
    }

    /// `actor --id ID` (or `auto`) over this link, with its own certificate over TLS.
    fn start_actor(&self, id: &str, certificate_id: u32, run: &str, log_dir: &Path) -> Actor {
        start_actor_at(&self.endpoint, id, run, &self.actor_flags(certificate_id), log_dir)
    }
}

/// `probe attack KIND`; returns the JSON it printed.
fn attack(link: &Link, run: &str, kind: &str, seconds: f64) -> serde_json::Value {
    let output = link.probe_attack(run, kind, seconds).output().unwrap();
    assert!(output.status.success(), "probe attack {kind} failed");
    let report: serde_json::Value =
        serde_json::from_slice(output.stdout.split(|b| *b == b'\n').next().unwrap()).unwrap();
    eprintln!("attack {kind}: {report}");
    report
}

/// `probe attack KIND` left running (it holds something); its first stdout line, once printed,
/// is readable through the returned receiver.
fn attack_in_background(
    link: &Link,
    run: &str,
    kind: &str,
    seconds: f64,
) -> (Child, std::sync::mpsc::Receiver<String>) {
    let mut child = link.probe_attack(run, kind, seconds).stdout(Stdio::piped()).spawn().unwrap();
    let stdout = child.stdout.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    (child, rx)
}

fn rejected(status: &serde_json::Value, kind: &str) -> u64 {
    u64_at(status, &format!("/rejected/{kind}"))
}

/// Both genuine actors are connected and act on weights the learner published after it had
/// published version `since`, and no newer than its current version.
fn actors_follow_the_learner(status: &serde_json::Value, since: u64) -> bool {
    let learner_version = u64_at(status, "/weights_version");
    status["connected_actors"].as_array().is_some_and(|c| c.contains(&0.into()) && c.contains(&1.into()))
        && (0..2).all(|id| {
            let version = u64_at(status, &format!("/actors/{id}/weights_version"));
            version > since && version <= learner_version
        })
}

fn attack_suite(learner: &mut Learner, link: &Link, run: &str, log_dir: &Path) {
    let warm = learner.wait_for(Duration::from_secs(120), "training with both actors", |s| {
        u64_at(s, "/updates") > 50 && actors_follow_the_learner(s, 2)
    });
    let pid = learner.child.id();
    let hwm_before = crawler_tests::peak_rss_mib(pid).unwrap();

    // Steering the actors: forged weights and a forged stop reach nobody (the ACL denies
    // remote puts on both keys).
    attack(link, run, "forged-weights", 0.0);
    attack(link, run, "stop", 0.0);
    // Poisoning: NaN/∞/7 ε in status, finite but huge observations, another actor's id.
    attack(link, run, "nan-epsilon", 0.0);
    attack(link, run, "huge-observations", 0.0);
    attack(link, run, "impersonate", 0.0);
    // Memory: a 200 MiB message, 100 000 distinct status ids, 20 000 distinct streams.
    attack(link, run, "huge-message", 0.0);
    attack(link, run, "flood", 0.0);
    let status = learner.wait_for(Duration::from_secs(60), "every attack counted", |s| {
        rejected(s, "non_finite") >= 10 && rejected(s, "out_of_range") >= 35 && rejected(s, "key_mismatch") >= 20
    });
    eprintln!("rejected after the first attacks: {}", status["rejected"]);
    // ε NaN and ∞ (non_finite), 7 (out_of_range); 30 batches of 3e38 (out_of_range).
    assert!(rejected(&status, "non_finite") >= 10 && rejected(&status, "out_of_range") >= 35, "{status:#}");
    // 20 messages under the attacker's own key in actor 0's name.
    assert!(rejected(&status, "key_mismatch") >= 20, "{status:#}");
    // Its 10 batches under actor 0's own key: over plain TCP they reach the learner and, from
    // an incarnation of their own, take nothing over while the genuine actor 0 sends
    // (incarnation_busy, or over_credit once the one introduction per 250 ms is used); under
    // mutual TLS the router denies them (the attacker's certificate names another id).
    let taken_over = rejected(&status, "incarnation_busy") + rejected(&status, "over_credit");
    if link.certified() {
        assert_eq!(taken_over, 0, "batches under actor 0's key reached the learner: {status:#}");
    } else {
        assert!(taken_over >= 10, "{status:#}");
    }
    // The flood: env ids beyond the run's crawlers per actor, under the attacker's own id;
    // 100 000 status reports and 10 000 batches under ids without a token (not_live over
    // plain TCP, denied by the router under mutual TLS).
    assert!(rejected(&status, "env_id") >= 1000, "{status:#}");
    if link.certified() {
        assert!(rejected(&status, "not_live") < 100, "other ids' messages reached the learner: {status:#}");
    } else {
        assert!(rejected(&status, "not_live") >= 1000, "{status:#}");
    }
    assert!(status["actors"].as_object().unwrap().keys().all(|id| id.parse::<u32>().unwrap() < 1000), "{status:#}");

    // A subscriber to transitions that never reads: denied, so ingest keeps flowing.
    let before = learner.status().unwrap();
    let since = u64_at(&before, "/weights_version");
    let (mut stalled, _) = attack_in_background(link, run, "stalled-subscriber", 6.0);
    std::thread::sleep(Duration::from_secs(4));
    let during = learner.wait_for(Duration::from_secs(30), "ingest during the stalled subscriber", |s| {
        (0..2).all(|id| {
            let pointer = format!("/actors/{id}/transitions");
            u64_at(s, &pointer) > u64_at(&before, &pointer)
        })
    });
    assert!(actors_follow_the_learner(&during, since), "{during:#}");
    assert!(stalled.wait().unwrap().success());

    // A forged run-info queryable while a new actor joins: the actor gets the real settings
    // and trains (with the forged 3 action levels it could not use the learner's weights).
    let (mut forged_info, _) = attack_in_background(link, run, "forged-info", 15.0);
    std::thread::sleep(Duration::from_secs(2));
    let mut joiner = link.start_actor(&JOINER_ID.to_string(), JOINER_ID, run, log_dir);
    learner.wait_for(Duration::from_secs(60), "the actor that joined under a forged info to train", |s| {
        u64_at(s, &format!("/actors/{JOINER_ID}/transitions")) > 0
    });
    assert!(joiner.is_running(), "{}", joiner.log_text());
    assert!(forged_info.wait().unwrap().success());
    drop(joiner);

    // 50 made-up liveliness tokens and 3 000 `assign` queries, then a genuine `--id auto`
    // actor: it gets a small id (pending reservations are capped at 16; under mutual TLS the
    // tokens are denied and the id is the one its certificate names) and trains.
    let (mut tokens, lines) = attack_in_background(link, run, "tokens", 30.0);
    let first = lines.recv_timeout(Duration::from_secs(120)).unwrap();
    eprintln!("attack tokens: {first}");
    let mut auto = link.start_actor("auto", AUTO_CERTIFICATE_ID, run, log_dir);
    let joined = auto.wait_for_log(Duration::from_secs(60), "joined run");
    let id = crawler_tests::log_field(&joined, "id").unwrap();
    assert!(id < 2 + 16 + 1, "the auto actor got id {id}: {joined}");
    if link.certified() {
        assert_eq!(id, u64::from(AUTO_CERTIFICATE_ID), "the auto actor did not take its certificate's id: {joined}");
    }
    let trained = learner.wait_for(Duration::from_secs(60), "the auto actor to train", |s| {
        u64_at(s, &format!("/actors/{id}/transitions")) > 0
    });
    // 50 + 3 live tokens fit under learner.max_actors (64); beyond it they would be ignored
    // and counted (unit-tested in service.rs).
    assert_eq!(u64_at(&trained, "/ignored_tokens"), 0, "{trained:#}");
    drop(auto);
    let _ = tokens.kill();
    let _ = tokens.wait();

    // Tokens under other spellings of the genuine actors' ids (`00`, `+1`), declared and
    // dropped: refused by name (over plain TCP; under mutual TLS the router denies them, as
    // no certificate names those keys), and both genuine actors stay on the books.
    let before = learner.status().unwrap();
    let since = u64_at(&before, "/weights_version");
    attack(link, run, "alias-tokens", 0.0);
    let after_aliases = if link.certified() {
        std::thread::sleep(Duration::from_secs(2));
        let status = learner.status().unwrap();
        assert_eq!(rejected(&status, "non_canonical_id"), 0, "aliased tokens reached the learner: {status:#}");
        status
    } else {
        learner
            .wait_for(Duration::from_secs(30), "the aliased tokens counted", |s| rejected(s, "non_canonical_id") >= 10)
    };
    std::thread::sleep(Duration::from_secs(2));
    let since_aliases = learner.wait_for(Duration::from_secs(30), "the genuine actors after the aliases", |s| {
        actors_follow_the_learner(s, since)
            && (0..2).all(|id| {
                let pointer = format!("/actors/{id}/transitions");
                u64_at(s, &pointer) > u64_at(&after_aliases, &pointer)
            })
    });
    assert_eq!(rejected(&since_aliases, "not_live"), rejected(&after_aliases, "not_live"), "{since_aliases:#}");

    // An incarnation played back after another replaced it: refused, whatever its sequence.
    attack(link, run, "replay-incarnation", 0.0);
    learner.wait_for(Duration::from_secs(30), "the played-back batches refused", |s| {
        rejected(s, "retired_incarnation") >= 10
    });

    // Squatters take every free slot while a new actor joins; it waits, and takes a slot as
    // soon as they leave, without a restart. Under mutual TLS the squatters' tokens are
    // denied (no certificate names them), and the late actor trains at once.
    let (mut squat, lines) = attack_in_background(link, run, "squat", 12.0);
    let first = lines.recv_timeout(Duration::from_secs(60)).unwrap();
    eprintln!("attack squat: {first}");
    let ignored_before = u64_at(&learner.status().unwrap(), "/ignored_tokens");
    let mut late = link.start_actor(&LATE_ID.to_string(), LATE_ID, run, log_dir);
    let late_transitions = format!("/actors/{LATE_ID}/transitions");
    if link.certified() {
        let trained = learner.wait_for(Duration::from_secs(60), "the late actor to train beside the squatters", |s| {
            u64_at(s, &late_transitions) > 0
        });
        assert_eq!(u64_at(&trained, "/ignored_tokens"), ignored_before, "squatters' tokens arrived: {trained:#}");
        assert!(squat.wait().unwrap().success());
    } else {
        let waiting = learner.wait_for(Duration::from_secs(30), "the late actor turned away", |s| {
            u64_at(s, "/ignored_tokens") > ignored_before
        });
        assert!(u64_at(&waiting, &late_transitions) == 0, "{waiting:#}");
        assert!(squat.wait().unwrap().success());
        learner.wait_for(Duration::from_secs(60), "the late actor to take a freed slot and train", |s| {
            u64_at(s, &late_transitions) > 0
        });
    }
    assert!(late.is_running(), "{}", late.log_text());
    drop(late);

    // A live sender floods valid episode statistics and status reports: it takes its share
    // of the metrics and its rate of status, the excess is dropped and counted under its
    // name, and the genuine actors' data and reports go on as before.
    let before = learner.status().unwrap();
    let (mut hog, lines) = attack_in_background(link, run, "hog", 15.0);
    let hog_name = format!("/over_share/actor-{}", link.attacker_id());
    let during = learner.wait_for(Duration::from_secs(30), "the hog's excess counted under its name", |s| {
        u64_at(s, &format!("{hog_name}/statuses")) >= 100
            && u64_at(s, &format!("{hog_name}/episodes")) >= 100
            && (0..2).all(|id| {
                let pointer = format!("/actors/{id}/transitions");
                u64_at(s, &pointer) > u64_at(&before, &pointer)
            })
    });
    eprintln!("over share during the hog: {}", during["over_share"]);
    let genuine = during["over_share"].as_object().unwrap();
    assert!(!genuine.contains_key("actor-0") && !genuine.contains_key("actor-1"), "{during:#}");
    assert!(rejected(&during, "over_share") >= 200, "{during:#}");
    assert!(hog.wait().unwrap().success());
    drop(lines);

    // Training went on, the genuine actors follow the learner, state stayed bounded.
    let now = learner.status().unwrap();
    let (updates, since) = (u64_at(&now, "/updates"), u64_at(&now, "/weights_version"));
    let after = learner.wait_for(Duration::from_secs(60), "training after the attacks", |s| {
        u64_at(s, "/updates") > updates + 50 && actors_follow_the_learner(s, since)
    });
    assert!(u64_at(&after, "/updates") > u64_at(&warm, "/updates"));
    assert_eq!(u64_at(&after, "/skipped_updates"), 0, "a bad batch reached training: {after:#}");
    assert!(!after["loss"].is_null() && after["loss"].as_f64().unwrap().is_finite(), "{after:#}");
    let status_bytes = std::fs::metadata(learner.status_path()).unwrap().len();
    assert!(status_bytes < 64 << 10, "status.json grew to {status_bytes} bytes");
    let hwm_after = crawler_tests::peak_rss_mib(pid).unwrap();
    eprintln!("learner VmHWM {hwm_before:.0} MiB before the attacks, {hwm_after:.0} MiB after");
    // Had zenoh buffered the 200 MiB message, the peak would have grown by at least that.
    assert!(hwm_after - hwm_before < 100.0, "learner VmHWM {hwm_before:.0} → {hwm_after:.0} MiB");

    // Every checkpoint kept loads, in eval too, with finite weights.
    assert!(learner.terminate(Duration::from_secs(60)).success());
    let checkpoints = learner.runs_dir.join(run).join("checkpoints");
    let kept = crawler_learner::checkpoint::list(&checkpoints).unwrap();
    assert!(!kept.is_empty());
    for path in &kept {
        let saved = crawler_learner::checkpoint::load(path).unwrap();
        assert!(saved.online.iter().chain(&saved.target).all(|v| v.is_finite()), "{}", path.display());
        assert!(saved.meta.progress.epsilon.is_finite());
        let eval = Command::new(binary("eval"))
            .arg(path)
            .args(["--episodes", "1", "--seconds", "1"])
            .stderr(Stdio::null())
            .output()
            .unwrap();
        assert!(eval.status.success(), "eval refused {}", path.display());
    }
}

#[test]
fn attacks_over_plain_tcp_leave_training_intact() {
    let dir = tempfile::tempdir().unwrap();
    let runs = dir.path().join("runs");
    let port = free_port();
    let run = "attacked-tcp";
    let mut learner = Learner::builder(&runs, run).port(port).config(SMOKE).actors(2).start();
    let link = Link { endpoint: format!("tcp/127.0.0.1:{port}"), tls: None };
    attack_suite(&mut learner, &link, run, dir.path());
}

#[test]
fn attacks_by_a_certified_actor_leave_training_intact() {
    let run = "attacked-tls";
    let TlsLearner { dir, tls, port, mut learner } = tls_learner(run, LATE_ID + 1);
    let _genuine: Vec<Actor> = (0..2)
        .map(|id| start_actor(port, id, run, tls_flags(&tls, &tls, &format!("actor-{id}")), dir.path()))
        .collect();
    let link = Link { endpoint: format!("tls/localhost:{port}"), tls: Some(tls) };
    attack_suite(&mut learner, &link, run, dir.path());
}

/// A checkpoint's `meta.json` is a file anyone with write access to the runs directory can
/// edit: one that asks for a plain listener on every interface does not get it on a resume
/// unless the command line asks too.
#[test]
fn a_checkpoint_cannot_widen_who_may_connect_on_a_resume() {
    let dir = tempfile::tempdir().unwrap();
    let runs = dir.path().join("runs");
    let port = free_port();
    let widened = ["learner.allow_plain_remote=true".to_string(), format!("learner.listen=[\"tcp/0.0.0.0:{port}\"]")];
    let config = crawler_run::config::TrainConfig::load(&crawler_tests::repo_root().join(SMOKE), &widened).unwrap();
    let dqn = crawler_learner::algo::dqn::Dqn::new(config.network_spec(), config.dqn.clone());
    let progress = crawler_learner::checkpoint::Progress { updates: 1, ..Default::default() };
    let config_json = serde_json::to_value(&config).unwrap();
    let checkpoints = runs.join("widened").join("checkpoints");
    crawler_learner::checkpoint::save(&checkpoints, &dqn, "widened", &progress, &config_json, None, 1).unwrap();

    let resume = |extra: &[&str]| {
        let mut command = Command::new(binary("learner"));
        command
            .current_dir(crawler_tests::repo_root())
            .args(["--resume", "widened", "--actors", "0"])
            .args(["--set", &format!("learner.runs_dir=\"{}\"", runs.display())])
            .args(extra)
            .stdout(Stdio::null())
            .stderr(Stdio::piped());
        command
    };
    let refused = resume(&[]).output().unwrap();
    let message = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success(), "the resume took the file's listener: {message}");
    assert!(
        message.contains("meta.json")
            && message.contains("learner.allow_plain_remote")
            && message.contains("--allow-plain-remote"),
        "{message}"
    );
    // Asked for on the command line, the same resume starts.
    let mut learner = resume(&["--allow-plain-remote"]).stderr(Stdio::inherit()).spawn().unwrap();
    let status_path = runs.join("widened").join("status.json");
    let started = crawler_tests::wait_for_status(
        &status_path,
        Duration::from_secs(60),
        "the resume with --allow-plain-remote to start",
        |_| true,
        || None,
    );
    let _ = learner.kill();
    let _ = learner.wait();
    assert_eq!(u64_at(&started, "/updates"), 1, "{started:#}");
}
