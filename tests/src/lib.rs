//! Helpers for integration tests and benchmarks that run the real `learner` and `actor`
//! binaries (built by `cargo build --workspace --bins`, which `scripts/test` runs) on loopback.
//! Test support: failures here are test failures, so they panic with a message.

#![allow(clippy::unwrap_used, clippy::missing_panics_doc)]

use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

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

impl Learner {
    /// `learner --config configs/smoke.toml --actors <actors>` on a fresh port and runs dir.
    pub fn start(runs_dir: &Path, run: &str, actors: usize, extra: &[&str]) -> Self {
        Self::start_with("configs/smoke.toml", runs_dir, run, actors, extra)
    }

    /// Like [`Learner::start`] with another preset.
    pub fn start_with(config: &str, runs_dir: &Path, run: &str, actors: usize, extra: &[&str]) -> Self {
        Self::launch(&["--config", config, "--run", run], runs_dir, run, actors, extra)
    }

    /// `learner --resume <run>` with its own stored config (plus a fresh port and `extra`).
    pub fn resume(runs_dir: &Path, run: &str, actors: usize, extra: &[&str]) -> Self {
        Self::launch(&["--resume", run], runs_dir, run, actors, extra)
    }

    fn launch(mode: &[&str], runs_dir: &Path, run: &str, actors: usize, extra: &[&str]) -> Self {
        let port = free_port();
        let listen = format!("learner.listen=[\"tcp/127.0.0.1:{port}\"]");
        let runs = format!("learner.runs_dir=\"{}\"", runs_dir.display());
        let mut command = Command::new(binary("learner"));
        command
            .current_dir(repo_root())
            .args(mode)
            .args(["--actors", &actors.to_string()])
            .args(["--set", &listen, "--set", &runs])
            .args(["--actor-bin", binary("actor").to_str().unwrap()])
            .args(extra)
            .stdout(Stdio::null())
            .stderr(Stdio::inherit());
        let child = command.spawn().unwrap();
        Self { child, runs_dir: runs_dir.to_path_buf(), run: run.to_string(), port }
    }

    pub fn status_path(&self) -> PathBuf {
        self.runs_dir.join(&self.run).join("status.json")
    }

    /// The latest status.json, if one was written.
    pub fn status(&self) -> Option<serde_json::Value> {
        let text = std::fs::read_to_string(self.status_path()).ok()?;
        serde_json::from_str(&text).ok()
    }

    /// Polls status.json until `done` holds; panics with the last status after `timeout`.
    pub fn wait_for(
        &mut self,
        timeout: Duration,
        what: &str,
        done: impl Fn(&serde_json::Value) -> bool,
    ) -> serde_json::Value {
        let start = Instant::now();
        loop {
            if let Some(status) = self.status()
                && done(&status)
            {
                return status;
            }
            if let Ok(Some(exit)) = self.child.try_wait() {
                panic!("learner exited ({exit}) while waiting for {what}; last status {:?}", self.status());
            }
            assert!(start.elapsed() < timeout, "timed out waiting for {what}; last status: {:#?}", self.status());
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    /// Waits for the learner to exit by itself (a configured limit).
    pub fn wait_for_exit(&mut self, timeout: Duration) -> ExitStatus {
        let start = Instant::now();
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return status;
            }
            assert!(
                start.elapsed() < timeout,
                "learner still running after {timeout:?}; last status {:?}",
                self.status()
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// Sends SIGTERM and waits for a clean exit.
    pub fn terminate(&mut self, timeout: Duration) -> ExitStatus {
        let pid = self.child.id().to_string();
        Command::new("kill").args(["-TERM", &pid]).status().unwrap();
        let start = Instant::now();
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return status;
            }
            assert!(start.elapsed() < timeout, "learner did not exit within {timeout:?} of SIGTERM");
            std::thread::sleep(Duration::from_millis(100));
        }
    }
}

impl Drop for Learner {
    fn drop(&mut self) {
        if matches!(self.child.try_wait(), Ok(None)) {
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
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// Child processes of `pid`, from /proc.
pub fn children_of(pid: u32) -> Vec<u32> {
    let Ok(entries) = std::fs::read_dir("/proc") else { return Vec::new() };
    entries
        .filter_map(Result::ok)
        .filter_map(|e| e.file_name().to_str()?.parse::<u32>().ok())
        .filter(|child| {
            std::fs::read_to_string(format!("/proc/{child}/stat"))
                .ok()
                .and_then(|stat| stat.rsplit(')').next()?.split_whitespace().nth(1)?.parse::<u32>().ok())
                == Some(pid)
        })
        .collect()
}
