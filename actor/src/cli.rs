//! Pieces both binaries (`actor`, `learner`) share.

/// Logs go to stderr through `tracing`, filtered by `RUST_LOG` (default: info, zenoh warn),
/// coloured only when stderr is a terminal (log files and `docker logs` stay plain).
pub fn init_logging() {
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info,zenoh=warn".into()),
        )
        .init();
}

/// Splits `--zenoh KEY=JSON5` arguments into pairs; the error names the bad argument.
pub fn zenoh_overrides(pairs: &[String]) -> Result<Vec<(String, String)>, String> {
    pairs
        .iter()
        .map(|pair| {
            pair.split_once('=').map(|(k, v)| (k.trim().to_string(), v.trim().to_string())).ok_or_else(|| {
                format!("--zenoh {pair:?}: expected KEY=JSON5, e.g. transport/link/tls/enable_mtls=true")
            })
        })
        .collect()
}
