//! `actor`: simulates crawlers and feeds a learner over zenoh.
//!
//! `actor --connect tcp/LEARNER:7447 --id 3` joins the learner's run, acts with the weights
//! it broadcasts and publishes transitions until the learner stops the run or it gets Ctrl-C.

use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use anyhow::Context;
use clap::Parser;
use crawler_actor::node::{self, ActorOptions};

#[derive(Debug, Parser)]
#[command(version, about = "Simulate crawlers and feed a crawler learner over zenoh")]
struct Args {
    /// Learner endpoint(s), e.g. tcp/127.0.0.1:7447 or tls/learner.example:7447.
    #[arg(long, required = true, env = "CRAWLER_CONNECT", value_delimiter = ',')]
    connect: Vec<String>,
    /// This actor's index; also picks its ε on the Ape-X ladder and its seeds.
    #[arg(long, env = "CRAWLER_ACTOR_ID", default_value_t = 0)]
    id: u32,
    /// Run to join (default: whichever run the learner serves).
    #[arg(long, env = "CRAWLER_RUN")]
    run: Option<String>,
    /// Act greedily (ε = 0) and publish evaluation stats only.
    #[arg(long)]
    evaluator: bool,
    /// Extra zenoh settings, KEY=JSON5 (e.g. transport/link/tls/root_ca_certificate="/ca.pem").
    #[arg(long = "zenoh", value_name = "KEY=JSON5", env = "CRAWLER_ZENOH", value_delimiter = ';')]
    zenoh: Vec<String>,
    /// Stop after this many decisions per crawler.
    #[arg(long)]
    max_steps: Option<u64>,
}

fn main() -> anyhow::Result<()> {
    crawler_actor::cli::init_logging();
    let args = Args::parse();
    let zenoh_overrides = crawler_actor::cli::zenoh_overrides(&args.zenoh).map_err(anyhow::Error::msg)?;
    let options = ActorOptions {
        connect: args.connect,
        id: args.id,
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
        tokio::spawn(node::stop_on_signal(Arc::clone(&stop)));
        node::run(options, stop).await
    });
    // A connect still waiting for an absent learner holds a blocking thread: do not wait for it.
    runtime.shutdown_timeout(std::time::Duration::from_secs(1));
    Ok(result?)
}
