//! Helpers for integration tests and benchmarks that run the real `learner` and `actor`
//! binaries (built by `cargo build --workspace --bins`, which `scripts/test` runs) on loopback.
//! Test support: failures here are test failures, so they panic with a message.

#![allow(clippy::unwrap_used, clippy::missing_panics_doc)]

use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use crawler_env::OBS_DIM;

/// A workspace binary of the same profile as the running test or bench, or from
/// `CRAWLER_BIN_DIR` when set (long experiments run from a copy, so rebuilding the workspace
/// meanwhile does not swap binaries under them).
pub fn binary(name: &str) -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    // Tests and benches run from <target>/<profile>/deps/.
    let dir = match std::env::var_os("CRAWLER_BIN_DIR") {
        Some(dir) => PathBuf::from(dir),
        None => exe.parent().and_then(Path::parent).unwrap().to_path_buf(),
    };
    let path = dir.join(name);
    assert!(path.exists(), "{} is missing: run `cargo build --workspace --bins` (scripts/test does)", path.display());
    path
}

/// The repository root (for configs/).
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap().to_path_buf()
}

/// TLS material for a deployment, made by `deploy/make-tls.sh DIR LEARNER_HOST ACTORS`.
pub fn make_tls(dir: &Path, learner_host: &str, actors: u32) -> PathBuf {
    let status = Command::new("bash")
        .arg(repo_root().join("deploy/make-tls.sh"))
        .arg(dir)
        .args([learner_host, &actors.to_string()])
        .status()
        .unwrap();
    assert!(status.success(), "make-tls.sh failed");
    dir.to_path_buf()
}

/// A loopback TCP port that was free a moment ago.
pub fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// A learner process that is killed if the test ends early.
#[derive(Debug)]
pub struct Learner {
    pub child: Child,
    pub runs_dir: PathBuf,
    pub run: String,
    pub port: u16,
}

/// How to start a test [`Learner`]: `Learner::builder(runs_dir, run)` is
/// `learner --config configs/smoke.toml --run <run> --actors 0` on a free loopback port, with
/// `runs_dir` as its runs directory; each method changes one thing.
#[derive(Debug, Clone)]
pub struct LearnerBuilder<'a> {
    runs_dir: &'a Path,
    run: &'a str,
    config: &'a str,
    resume: bool,
    port: Option<u16>,
    actors: usize,
    args: Vec<&'a str>,
    env: Vec<(&'a str, &'a str)>,
}

impl<'a> LearnerBuilder<'a> {
    /// Another preset (a path relative to the repository root).
    pub fn config(mut self, config: &'a str) -> Self {
        self.config = config;
        self
    }

    /// `--resume <run>` with the run's own stored config instead of a preset.
    pub fn resume(mut self) -> Self {
        self.resume = true;
        self
    }

    /// Listen on `port` (actors connected to an earlier learner there reconnect).
    pub fn port(mut self, port: u16) -> Self {
        self.port = Some(port);
        self
    }

    /// Local actor processes (`--actors N`).
    pub fn actors(mut self, actors: usize) -> Self {
        self.actors = actors;
        self
    }

    /// More learner arguments (`--set key=value`, …).
    pub fn args(mut self, args: &[&'a str]) -> Self {
        self.args.extend_from_slice(args);
        self
    }

    /// Environment variables of the learner process (test hooks such as `FAILPOINTS`).
    pub fn env(mut self, env: &[(&'a str, &'a str)]) -> Self {
        self.env.extend_from_slice(env);
        self
    }

    pub fn start(self) -> Learner {
        let port = self.port.unwrap_or_else(free_port);
        let listen = format!("learner.listen=[\"tcp/127.0.0.1:{port}\"]");
        let runs = format!("learner.runs_dir=\"{}\"", self.runs_dir.display());
        let mode: Vec<&str> =
            if self.resume { vec!["--resume", self.run] } else { vec!["--config", self.config, "--run", self.run] };
        let child = Command::new(binary("learner"))
            .current_dir(repo_root())
            .args(mode)
            .args(["--actors", &self.actors.to_string()])
            .args(["--set", &listen, "--set", &runs])
            .args(["--actor-bin", binary("actor").to_str().unwrap()])
            .args(&self.args)
            .envs(self.env.iter().copied())
            .stdout(Stdio::null())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap();
        Learner { child, runs_dir: self.runs_dir.to_path_buf(), run: self.run.to_string(), port }
    }
}

impl Learner {
    /// A learner to start; see [`LearnerBuilder`].
    pub fn builder<'a>(runs_dir: &'a Path, run: &'a str) -> LearnerBuilder<'a> {
        LearnerBuilder {
            runs_dir,
            run,
            config: "configs/smoke.toml",
            resume: false,
            port: None,
            actors: 0,
            args: Vec::new(),
            env: Vec::new(),
        }
    }

    pub fn status_path(&self) -> PathBuf {
        self.runs_dir.join(&self.run).join("status.json")
    }

    /// The latest status.json, if one was written.
    pub fn status(&self) -> Option<serde_json::Value> {
        read_status(&self.status_path())
    }

    /// Polls status.json until `done` holds; panics with the last status after `timeout`, or
    /// at once if the learner exits.
    pub fn wait_for(
        &mut self,
        timeout: Duration,
        what: &str,
        done: impl Fn(&serde_json::Value) -> bool,
    ) -> serde_json::Value {
        let path = self.status_path();
        let child = &mut self.child;
        wait_for_status(&path, timeout, what, done, || {
            child.try_wait().ok().flatten().map(|exit| format!("learner exited ({exit})"))
        })
    }

    /// Waits for the learner to exit by itself (a configured limit).
    pub fn wait_for_exit(&mut self, timeout: Duration) -> ExitStatus {
        self.wait_exit(timeout, "learner still running")
    }

    /// Sends SIGTERM and waits for a clean exit.
    pub fn terminate(&mut self, timeout: Duration) -> ExitStatus {
        signal(self.child.id(), "TERM");
        self.wait_exit(timeout, "learner did not exit after SIGTERM")
    }

    fn wait_exit(&mut self, timeout: Duration, what: &str) -> ExitStatus {
        let start = Instant::now();
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return status;
            }
            assert!(start.elapsed() < timeout, "{what} after {timeout:?}; last status {:?}", self.status());
            std::thread::sleep(Duration::from_millis(100));
        }
    }
}

/// A status.json, if it exists and parses.
pub fn read_status(path: &Path) -> Option<serde_json::Value> {
    serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()
}

/// Polls the status.json at `path` until `done` holds; panics with the last status after
/// `timeout`, or as soon as `gone` names a reason the writer is no longer there.
pub fn wait_for_status(
    path: &Path,
    timeout: Duration,
    what: &str,
    done: impl Fn(&serde_json::Value) -> bool,
    mut gone: impl FnMut() -> Option<String>,
) -> serde_json::Value {
    let start = Instant::now();
    loop {
        if let Some(status) = read_status(path)
            && done(&status)
        {
            return status;
        }
        if let Some(reason) = gone() {
            panic!("{reason} while waiting for {what}; last status {:?}", read_status(path));
        }
        assert!(start.elapsed() < timeout, "timed out waiting for {what}; last status: {:#?}", read_status(path));
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// Sends `signal` (e.g. "KILL", "TERM") to `pid`.
pub fn signal(pid: u32, signal: &str) {
    Command::new("kill").args([&format!("-{signal}"), &pid.to_string()]).status().unwrap();
}

/// An actor process started on its own (not by the learner), logging at info level to a
/// file; killed if the test ends early.
#[derive(Debug)]
pub struct Actor {
    pub child: Child,
    pub log: PathBuf,
}

impl Actor {
    /// `actor --connect tcp/127.0.0.1:<port> --id <id> --run <run>`, its log in `log_dir`.
    pub fn start(port: u16, id: u32, run: &str, log_dir: &Path) -> Self {
        let connect = format!("tcp/127.0.0.1:{port}");
        Self::start_args(&["--connect", &connect, "--id", &id.to_string(), "--run", run], log_dir)
    }

    /// `actor <args>`, its log in `log_dir`.
    pub fn start_args(args: &[&str], log_dir: &Path) -> Self {
        let log = log_dir.join(format!(
            "actor-{}.log",
            std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos()
        ));
        let file = std::fs::File::create(&log).unwrap();
        let child = Command::new(binary("actor"))
            .args(args)
            .env("RUST_LOG", "info,zenoh=warn")
            .stdout(Stdio::null())
            .stderr(file)
            .spawn()
            .unwrap();
        Self { child, log }
    }

    /// The log so far.
    pub fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// Whether the process is still running.
    pub fn is_running(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }

    /// Polls the log until a line contains `needle`; returns that line.
    pub fn wait_for_log(&mut self, timeout: Duration, needle: &str) -> String {
        let start = Instant::now();
        loop {
            if let Some(line) = self.log_text().lines().find(|l| l.contains(needle)) {
                return line.to_string();
            }
            assert!(self.is_running(), "actor exited before logging {needle:?}: {}", self.log_text());
            assert!(
                start.elapsed() < timeout,
                "no {needle:?} in the actor's log after {timeout:?}: {}",
                self.log_text()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

impl Drop for Actor {
    fn drop(&mut self) {
        if matches!(self.child.try_wait(), Ok(None)) {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

/// The number after `key=` in a log line (`version=12`), if any.
pub fn log_field(line: &str, key: &str) -> Option<u64> {
    let start = line.find(&format!("{key}="))? + key.len() + 1;
    line[start..].chars().take_while(char::is_ascii_digit).collect::<String>().parse().ok()
}

impl Drop for Learner {
    fn drop(&mut self) {
        if matches!(self.child.try_wait(), Ok(None)) {
            // Its actors too: killed, the learner cannot reap them, and actors outlive a
            // learner on purpose (they wait for it to come back).
            for child in children_of(self.child.id()) {
                // Not `signal`: a panic while dropping during a failed test would abort.
                let _ = Command::new("kill").args(["-KILL", &child.to_string()]).status();
            }
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

pub fn u64_at(value: &serde_json::Value, pointer: &str) -> u64 {
    value.pointer(pointer).and_then(serde_json::Value::as_u64).unwrap_or(0)
}

/// Resident set size of process `pid` in MiB, from /proc.
pub fn rss_mib(pid: u32) -> Option<f64> {
    proc_status_mib(pid, "VmRSS")
}

/// Peak resident set size ("high water mark") of process `pid` in MiB, from /proc.
pub fn peak_rss_mib(pid: u32) -> Option<f64> {
    proc_status_mib(pid, "VmHWM")
}

/// A `kB` field of `/proc/<pid>/status`, in MiB.
fn proc_status_mib(pid: u32, field: &str) -> Option<f64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status.lines().find(|l| l.strip_prefix(field).is_some_and(|rest| rest.starts_with(':')))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// The fields of `/proc/<pid>/stat` after the command name (field 3, the state, first).
fn stat_fields(pid: u32) -> Vec<String> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
    stat.rsplit(')').next().unwrap_or("").split_whitespace().map(String::from).collect()
}

/// Child processes of `pid`, from /proc.
pub fn children_of(pid: u32) -> Vec<u32> {
    let Ok(entries) = std::fs::read_dir("/proc") else { return Vec::new() };
    entries
        .filter_map(Result::ok)
        .filter_map(|e| e.file_name().to_str()?.parse::<u32>().ok())
        .filter(|&child| stat_fields(child).get(1).and_then(|ppid| ppid.parse::<u32>().ok()) == Some(pid))
        .collect()
}

/// CPU seconds (user + system) process `pid` has used, from /proc: stat's fields 14 and 15
/// (utime, stime), in clock ticks of 1/100 s.
pub fn cpu_seconds(pid: u32) -> f64 {
    let ticks: f64 = stat_fields(pid).get(11..13).map_or(0.0, |f| f.iter().filter_map(|v| v.parse::<f64>().ok()).sum());
    ticks / 100.0
}

/// This machine's CPU model, from /proc/cpuinfo (empty where it says none), for the header of
/// a benchmark's table.
pub fn cpu_model() -> String {
    let info = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let model = info.lines().find(|l| l.starts_with("model name")).and_then(|l| l.split(':').nth(1));
    model.unwrap_or("").trim().to_string()
}

/// The environment variable `name` parsed, or `default` when it is unset or does not parse
/// (benchmarks' knobs).
pub fn env_or<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}

/// The version `probe forge` stamps on forged weights: far above anything a test run publishes.
pub const FORGED_VERSION: u64 = 4_000_000_000;

/// A transition batch of `n` transitions that passes every check of the learner's ingest
/// (for the bad-input injector and the forging probe, which alter it or put it where it does
/// not belong).
pub fn valid_batch(run: &str, id: u32, sequence: u64, n: usize) -> crawler_proto::TransitionBatch {
    crawler_proto::TransitionBatch {
        protocol_version: crawler_proto::PROTOCOL_VERSION,
        run_id: run.to_string(),
        actor_id: id,
        sequence,
        incarnation: 7,
        obs_dim: OBS_DIM as u32,
        env_ids: vec![0; n],
        observations: vec![0.5; n * OBS_DIM],
        next_observations: vec![0.5; n * OBS_DIM],
        actions: vec![1; n],
        rewards: vec![0.1; n],
        terminated: vec![false; n],
        truncated: vec![false; n],
        priorities: vec![],
        weights_version: 1,
        physics_steps: n as u64 * 10,
        count: n as u32,
    }
}
