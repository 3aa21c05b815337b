//! `actor`: simulates crawlers and feeds a learner over zenoh.
//!
//! `actor --connect tcp/LEARNER:7447 --id 3` joins the learner's run, acts with the weights
//! it broadcasts and publishes transitions until the learner stops the run or it gets Ctrl-C.
//! Across machines: `actor --connect tls/LEARNER:7447 --tls-ca ca.pem --tls-cert actor-3.pem
//! --tls-key actor-3.key` (mutual TLS; the certificate names the id, 3; see deploy/README.md).

use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use anyhow::Context;
use clap::Parser;
use crawler_actor::node::{self, ActorOptions};
use crawler_cli::{TlsArgs, TlsSide, check_tls_endpoints};
use crawler_proto::identity::Certified;

#[derive(Debug, Parser)]
#[command(version, about = "Simulate crawlers and feed a crawler learner over zenoh")]
struct Args {
    /// Learner endpoint(s), e.g. tcp/127.0.0.1:7447 or tls/learner.example:7447.
    #[arg(long, required = true, env = "CRAWLER_CONNECT", value_delimiter = ',')]
    connect: Vec<String>,
    /// This actor's index, which also picks its ε on the Ape-X ladder and its seeds; `auto`
    /// asks the learner for a free one (for replicas started alike, e.g. by docker compose).
    /// Under mutual TLS the certificate names the id (`crawler-actor-<id>`,
    /// `crawler-evaluator-<id>`): `auto` or no flag takes it, another number is refused.
    /// Default: 0 over plain TCP.
    #[arg(long, env = "CRAWLER_ACTOR_ID", value_parser = parse_id)]
    id: Option<ActorId>,
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

/// The id a certificate lets this process use. The learner's router lets a certificate put
/// and declare only under its own id's keys, so any other id would be silently denied
/// there: refusing it here says why.
fn certified_id(certified: Certified, asked: Option<ActorId>, evaluator: bool) -> anyhow::Result<u32> {
    let id = match (certified, evaluator) {
        (Certified::Actor(id), false) | (Certified::Evaluator(id), true) => id,
        (Certified::Actor(id), true) => anyhow::bail!(
            "--tls-cert names actor {id}, which may not run an evaluator: pass an evaluator's certificate \
             (crawler-evaluator-<id>, from deploy/make-tls.sh) or drop --evaluator"
        ),
        (Certified::Evaluator(id), false) => anyhow::bail!(
            "--tls-cert names evaluator {id}: pass --evaluator, or an actor's certificate (crawler-actor-<id>)"
        ),
        (Certified::Observer, _) => anyhow::bail!(
            "--tls-cert is an observer's certificate, which may only watch: pass an actor's (crawler-actor-<id>)"
        ),
    };
    match asked {
        Some(ActorId::Fixed(other)) if other != id => anyhow::bail!(
            "--id {other}, but --tls-cert names id {id}, and the learner accepts nothing else from it: \
             pass --id {id} or --id auto, or the certificate of id {other}"
        ),
        _ => Ok(id),
    }
}

fn main() -> anyhow::Result<()> {
    crawler_cli::init_logging();
    let args = Args::parse();
    crawler_cli::serialize_tls_link_io(&args.connect);
    let mut zenoh_overrides = Vec::new();
    let mut id = args.id;
    if let Some(tls) = args.tls.files()? {
        check_tls_endpoints(&args.connect, "--connect")?;
        id = Some(ActorId::Fixed(certified_id(tls.certified()?, args.id, args.evaluator)?));
        zenoh_overrides.extend(tls.zenoh_settings(TlsSide::Connect));
    }
    // Explicit --zenoh settings come last, so they win.
    zenoh_overrides.extend(crawler_cli::zenoh_overrides(&args.zenoh)?);
    let options = ActorOptions {
        connect: args.connect,
        id: match id.unwrap_or(ActorId::Fixed(0)) {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_certificate_fixes_the_id_and_the_role() {
        assert_eq!(certified_id(Certified::Actor(3), None, false).unwrap(), 3);
        assert_eq!(certified_id(Certified::Actor(3), Some(ActorId::Auto), false).unwrap(), 3);
        assert_eq!(certified_id(Certified::Actor(3), Some(ActorId::Fixed(3)), false).unwrap(), 3);
        assert_eq!(certified_id(Certified::Evaluator(1000), None, true).unwrap(), 1000);
        let refused = |certified, asked, evaluator| certified_id(certified, asked, evaluator).unwrap_err().to_string();
        assert!(
            refused(Certified::Actor(3), Some(ActorId::Fixed(4)), false).contains("--id 4, but --tls-cert names id 3")
        );
        assert!(refused(Certified::Actor(3), None, true).contains("may not run an evaluator"));
        assert!(refused(Certified::Evaluator(1000), None, false).contains("pass --evaluator"));
        assert!(refused(Certified::Observer, None, false).contains("observer"));
    }
}
