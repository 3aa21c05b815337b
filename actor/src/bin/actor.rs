//! `actor`: simulates crawlers and feeds a learner over zenoh.
//!
//! `actor --connect tcp/LEARNER:7447 --id 3` joins the learner's run, acts with the weights
//! it broadcasts and publishes transitions until the learner stops the run or it gets Ctrl-C.
//! Across machines: `actor --connect tls/LEARNER:7447 --tls-ca ca.pem --tls-cert actor-0.pem
//! --tls-key actor-0.key` (mutual TLS; see deploy/README.md).

use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use anyhow::Context;
use clap::Parser;
use crawler_actor::node::{self, ActorOptions};
use crawler_cli::{TlsArgs, TlsSide, check_tls_endpoints};

#[derive(Debug, Parser)]
#[command(version, about = "Simulate crawlers and feed a crawler learner over zenoh")]
struct Args {
    /// Learner endpoint(s), e.g. tcp/127.0.0.1:7447 or tls/learner.example:7447.
    #[arg(long, required = true, env = "CRAWLER_CONNECT", value_delimiter = ',')]
    connect: Vec<String>,
    /// This actor's index, which also picks its ε on the Ape-X ladder and its seeds; `auto`
    /// asks the learner for a free one (for replicas started alike, e.g. by docker compose).
    #[arg(long, env = "CRAWLER_ACTOR_ID", default_value = "0", value_parser = parse_id)]
    id: ActorId,
    /// A file touched at every status report, for container health checks.
    #[arg(long, env = "CRAWLER_HEARTBEAT")]
    heartbeat: Option<std::path::PathBuf>,
    /// Run to join (default: whichever run the learner serves).
    #[arg(long, env = "CRAWLER_RUN")]
    run: Option<String>,
    /// Act greedily (ε = 0) and publish evaluation stats only.
    #[arg(long)]
    evaluator: bool,
    #[command(flatten)]
    tls: TlsArgs,
    /// Extra zenoh settings, KEY=JSON5 (e.g. transport/link/tls/root_ca_certificate="/ca.pem").
    #[arg(long = "zenoh", value_name = "KEY=JSON5", env = "CRAWLER_ZENOH", value_delimiter = ';')]
    zenoh: Vec<String>,
    /// Stop after this many decisions per crawler.
    #[arg(long)]
    max_steps: Option<u64>,
}

#[derive(Debug, Clone, Copy)]
enum ActorId {
    Fixed(u32),
    Auto,
}

fn parse_id(text: &str) -> Result<ActorId, String> {
    if text == "auto" {
        return Ok(ActorId::Auto);
    }
    text.parse().map(ActorId::Fixed).map_err(|_| format!("expected a number in 0..=4294967295 or `auto`, got {text:?}"))
}

fn main() -> anyhow::Result<()> {
    crawler_cli::init_logging();
    let args = Args::parse();
    crawler_cli::serialize_tls_link_io(&args.connect);
    let mut zenoh_overrides = Vec::new();
    if let Some(tls) = args.tls.files()? {
        check_tls_endpoints(&args.connect, "--connect")?;
        zenoh_overrides.extend(tls.zenoh_settings(TlsSide::Connect));
    }
    // Explicit --zenoh settings come last, so they win.
    zenoh_overrides.extend(crawler_cli::zenoh_overrides(&args.zenoh)?);
    let options = ActorOptions {
        connect: args.connect,
        id: match args.id {
            ActorId::Fixed(id) => Some(id),
            ActorId::Auto => None,
        },
        heartbeat: args.heartbeat,
        run: args.run,
        evaluator: args.evaluator,
        zenoh_overrides,
        max_steps: args.max_steps,
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let result = runtime.block_on(async {
        let stop = Arc::new(AtomicBool::new(false));
        tokio::spawn(crawler_cli::stop_on_signal(Arc::clone(&stop)));
        node::run(options, stop).await
    });
    // A connect still waiting for an absent learner holds a blocking thread: do not wait for it.
    runtime.shutdown_timeout(std::time::Duration::from_secs(1));
    Ok(result?)
}
