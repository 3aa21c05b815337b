//! `learner`: trains the crawler. Owns replay and the DQN, runs the zenoh router actors
//! connect to, and with `--actors N` starts N local actor processes: the one-command job.

use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use clap::Parser;
use crawler_cli::{TlsArgs, TlsSide, check_tls_endpoints};
use crawler_learner::checkpoint;
use crawler_learner::service::access_control;
use crawler_learner::service::{self, ServiceOptions};
use crawler_run::config::TrainConfig;
use tracing::{info, warn};

#[derive(Debug, Parser)]
#[command(version, about = "Train the crawler: replay, Double DQN and the zenoh router actors connect to")]
struct Args {
    /// TOML preset (see configs/).
    #[arg(long, default_value = "configs/default.toml")]
    config: PathBuf,
    /// Override a setting, KEY=VALUE in TOML syntax (repeatable), e.g. --set dqn.lr=1e-3.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    overrides: Vec<String>,
    /// Local actor processes to start (0: only remote actors).
    #[arg(long, default_value_t = 2)]
    actors: usize,
    /// Name of a new run (default: run-<unix time>).
    #[arg(long, conflicts_with = "resume")]
    run: Option<String>,
    /// With --run: if the run already has checkpoints, resume it instead of refusing (for
    /// restart policies, e.g. docker compose's).
    #[arg(long, requires = "run")]
    or_resume: bool,
    /// Continue run RUN from its newest checkpoint, with the config it was started with.
    #[arg(long, value_name = "RUN")]
    resume: Option<String>,
    /// Start a new run from another run's weights (transfer, e.g. backward from a forward
    /// checkpoint): a checkpoint directory or a directory of them (the newest). The online and
    /// target networks are copied; the optimiser, replay and counters start fresh.
    #[arg(long, value_name = "CHECKPOINT", conflicts_with = "resume")]
    init_from: Option<PathBuf>,
    /// Mutual TLS for remote actors (--tls-ca, --tls-cert, --tls-key): requires client
    /// certificates and turns on the access-control policy; learner.listen must then hold only
    /// tls/ endpoints.
    #[command(flatten)]
    tls: TlsArgs,
    /// Allow a plain-TCP (unauthenticated) listener on an address other than loopback, as
    /// `learner.allow_plain_remote = true` does: anyone who reaches the port can then join as an
    /// actor. For trusted networks only (a compose bridge network); elsewhere use mutual TLS.
    #[arg(long)]
    allow_plain_remote: bool,
    /// Extra zenoh settings, KEY=JSON5; applied last, so they override the TLS settings.
    #[arg(long = "zenoh", value_name = "KEY=JSON5", value_delimiter = ';')]
    zenoh: Vec<String>,
    /// The actor executable (default: `actor` beside this one).
    #[arg(long)]
    actor_bin: Option<PathBuf>,
}

fn main() -> anyhow::Result<()> {
    crawler_cli::init_logging();
    // Fail points (FAILPOINTS=…) exist only in `fault-injection` builds, the tests'; in any
    // other build this reads nothing.
    let _fail_points = fail::FailScenario::setup();
    let mut args = Args::parse();
    let (config, run_id, resume) = run_to_start(&mut args)?;
    let run_dir = Path::new(&config.learner.runs_dir).join(&run_id);
    if resume.is_none() && run_dir.join("checkpoints").exists() {
        bail!(
            "run `{run_id}` already has checkpoints in {}: use --resume {run_id}, or another --run",
            run_dir.display()
        );
    }
    // Before the async runtime or libtorch start any thread.
    crawler_cli::serialize_tls_link_io(&config.learner.listen);
    let (identity, mut zenoh_overrides) = network_access(&args, &config)?;
    zenoh_overrides.extend(crawler_cli::zenoh_overrides(&args.zenoh)?);
    let init_from = args.init_from.as_deref().map(|path| transfer_source(path, &config)).transpose()?;

    let stop = Arc::new(AtomicBool::new(false));
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let children = start_local_actors(&args, &config, &run_id)?;
    let options =
        ServiceOptions { config, run_id: run_id.clone(), run_dir, resume, init_from, identity, zenoh_overrides };
    let outcome = runtime.block_on(async {
        tokio::spawn(crawler_cli::stop_on_signal(Arc::clone(&stop)));
        service::run(options, Arc::clone(&stop)).await
    });
    stop.store(true, Ordering::SeqCst);
    // After a clean end the actors heard the learner's stop; after an error nobody told
    // them, so they are stopped at once rather than left to wait for a learner that is gone.
    reap(children, if outcome.is_ok() { Duration::from_secs(10) } else { Duration::ZERO });
    let outcome = outcome?;
    info!(
        run = %run_id,
        updates = outcome.progress.updates,
        env_steps = outcome.progress.env_steps,
        "done; checkpoint {}",
        outcome.last_checkpoint.map(|p| p.display().to_string()).unwrap_or_default()
    );
    Ok(())
}

/// The config, run id and (for `--resume`, or `--or-resume` of a run with checkpoints) the
/// checkpoint to continue from. Run ids are checked before any path is built from them.
fn run_to_start(args: &mut Args) -> anyhow::Result<(TrainConfig, String, Option<checkpoint::Checkpoint>)> {
    for run in [&args.run, &args.resume].into_iter().flatten() {
        crawler_proto::keys::check_run_id(run)?;
    }
    if args.or_resume
        && let Some(run) = &args.run
    {
        let runs_dir = runs_dir_of(args)?;
        if checkpoint::list(&runs_dir.join(run).join("checkpoints")).is_ok_and(|l| !l.is_empty()) {
            info!(run = %run, "the run has checkpoints: resuming it");
            args.resume = args.run.take();
        }
    }
    Ok(match &args.resume {
        Some(run) => {
            let runs_dir = runs_dir_of(args)?;
            let checkpoint = checkpoint::load(&runs_dir.join(run).join("checkpoints"))
                .with_context(|| format!("resuming run `{run}`"))?;
            let mut config =
                TrainConfig::from_json(&checkpoint.meta.config, "the checkpoint's config", &args.overrides)?;
            keep_access_to_the_command_line(args, &mut config, &checkpoint.path.join("meta.json"))?;
            (config, run.clone(), Some(checkpoint))
        }
        None => {
            let config = TrainConfig::load(&args.config, &args.overrides)?;
            (config, args.run.clone().unwrap_or_else(default_run_id), None)
        }
    })
}

/// A resumed run's config comes from its checkpoint, a file anyone with write access to the
/// runs directory may have edited: it never widens who may connect. Its
/// `learner.allow_plain_remote` holds only when the command line says so too; with a plain
/// listener beyond loopback the resume is refused, naming the flag.
fn keep_access_to_the_command_line(args: &Args, config: &mut TrainConfig, meta: &Path) -> anyhow::Result<()> {
    let said_here = args.allow_plain_remote
        || args
            .overrides
            .iter()
            .any(|o| o.split('=').next().is_some_and(|key| key.trim() == "learner.allow_plain_remote"));
    if !config.learner.allow_plain_remote || said_here {
        return Ok(());
    }
    if args.tls.files()?.is_none() && service::listens_beyond_loopback(&config.learner.listen) {
        bail!(
            "{}: learner.allow_plain_remote = true with learner.listen {:?}; a checkpoint does not decide who may \
             connect. Pass --allow-plain-remote to resume with that listener, or \
             --set 'learner.listen=[\"tcp/127.0.0.1:7447\"]' to resume on loopback",
            meta.display(),
            config.learner.listen
        );
    }
    config.learner.allow_plain_remote = false;
    Ok(())
}

/// Who may connect, and the zenoh settings for it: mutual TLS with roles by certificate, or
/// plain TCP, which beyond loopback needs an explicit opt-in.
fn network_access(
    args: &Args,
    config: &TrainConfig,
) -> anyhow::Result<(access_control::Identity, Vec<(String, String)>)> {
    if let Some(tls) = args.tls.files()? {
        check_tls_endpoints(&config.learner.listen, "learner.listen")?;
        if args.actors > 0 {
            bail!(
                "with mutual TLS the learner starts no local actors (they would need certificates of their own): \
                 pass --actors 0 and start actors with --tls-ca/--tls-cert/--tls-key"
            );
        }
        info!(
            "mutual TLS on; access control: each certificate speaks only for the actor or evaluator id its CN names (crawler-actor-<id>, crawler-evaluator-<id>), observers read, everything else denied"
        );
        return Ok((access_control::Identity::Certificates, tls.zenoh_settings(TlsSide::Listen)));
    }
    if service::listens_beyond_loopback(&config.learner.listen) {
        if !(args.allow_plain_remote || config.learner.allow_plain_remote) {
            bail!(
                "learner.listen {:?} accepts unauthenticated plain TCP from other hosts: anyone who reaches the \
                 port could join as an actor and feed replay. Listen on 127.0.0.1, use mutual TLS \
                 (--tls-ca/--tls-cert/--tls-key, see deploy/README.md), or on a trusted network opt in with \
                 --allow-plain-remote (learner.allow_plain_remote = true)",
                config.learner.listen
            );
        }
        warn!(
            listen = ?config.learner.listen,
            "plain TCP beyond loopback (--allow-plain-remote): anyone who reaches this port can join as an actor \
             and feed replay; use mutual TLS on untrusted networks"
        );
    }
    Ok((access_control::Identity::None, Vec::new()))
}

/// The `--init-from` checkpoint, whose network must be this config's.
fn transfer_source(path: &Path, config: &TrainConfig) -> anyhow::Result<checkpoint::Checkpoint> {
    let checkpoint = checkpoint::load(path).with_context(|| format!("--init-from {}", path.display()))?;
    if checkpoint.meta.network != config.network_spec() {
        bail!(
            "--init-from {}: its network {:?} differs from this config's {:?}; set network.* to match",
            path.display(),
            checkpoint.meta.network,
            config.network_spec()
        );
    }
    Ok(checkpoint)
}

/// Starts `--actors N` local actor processes on the learner's first endpoint; if one fails
/// to start, those already started are stopped.
fn start_local_actors(args: &Args, config: &TrainConfig, run_id: &str) -> anyhow::Result<Vec<Child>> {
    let mut children = Vec::new();
    if args.actors == 0 {
        return Ok(children);
    }
    let local_endpoint = local_endpoint(&config.learner.listen[0])?;
    let actor_bin = match &args.actor_bin {
        Some(path) => path.clone(),
        None => std::env::current_exe()?.with_file_name("actor"),
    };
    for id in 0..args.actors {
        match spawn_actor(&actor_bin, &local_endpoint, id, run_id) {
            Ok(child) => children.push(child),
            Err(e) => {
                reap(children, Duration::ZERO);
                return Err(e);
            }
        }
    }
    info!(count = args.actors, endpoint = %local_endpoint, "started local actors");
    Ok(children)
}

fn runs_dir_of(args: &Args) -> anyhow::Result<PathBuf> {
    // The runs directory comes from the preset (and overrides), as for a new run.
    let config = TrainConfig::load(&args.config, &args.overrides)
        .or_else(|_| TrainConfig::from_toml("", "defaults", &args.overrides))?;
    Ok(PathBuf::from(config.learner.runs_dir))
}

fn default_run_id() -> String {
    let seconds = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs());
    format!("run-{seconds}")
}

/// Where local actors reach a router listening on `listen` (e.g. tcp/0.0.0.0:7447).
fn local_endpoint(listen: &str) -> anyhow::Result<String> {
    let (protocol, address) =
        listen.split_once('/').with_context(|| format!("learner.listen `{listen}` is not PROTOCOL/HOST:PORT"))?;
    let port = address.rsplit(':').next().and_then(|p| p.parse::<u16>().ok());
    let port = port.with_context(|| format!("learner.listen `{listen}` has no port"))?;
    Ok(format!("{protocol}/127.0.0.1:{port}"))
}

fn spawn_actor(binary: &Path, endpoint: &str, id: usize, run: &str) -> anyhow::Result<Child> {
    let mut command = Command::new(binary);
    command.args(["--connect", endpoint, "--id", &id.to_string(), "--run", run]);
    if std::env::var_os("RUST_LOG").is_none() {
        // The learner's status line reports actors; their own logs stay quiet unless asked.
        command.env("RUST_LOG", "warn");
    }
    command.spawn().with_context(|| {
        format!("starting actor {id} from {} (build it with `cargo build --release`)", binary.display())
    })
}

/// Waits up to `grace` for local actors to exit after the learner's stop message, then kills
/// the rest.
fn reap(mut children: Vec<Child>, grace: Duration) {
    let deadline = Instant::now() + grace;
    while Instant::now() < deadline && children.iter_mut().any(|c| matches!(c.try_wait(), Ok(None))) {
        std::thread::sleep(Duration::from_millis(100));
    }
    for mut child in children {
        if matches!(child.try_wait(), Ok(None)) {
            warn!(pid = child.id(), "actor did not exit; killing it");
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}
