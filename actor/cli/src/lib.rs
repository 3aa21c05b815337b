//! Process plumbing that every crawler binary shares (`actor`, `learner`, `eval`, `plot`,
//! `render`, and the test helpers `probe` and `garbage`): logging, the mutual-TLS flags, the
//! `--zenoh KEY=JSON5` overrides, the TLS-link workaround, and stopping on a signal.
//!
//! It lives in its own crate, not in the actor's library, so that the learner and the tools
//! depend on it without depending on each other.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

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

/// The zenoh runtime setting under which a TLS link's reads and writes never run at the same
/// time: the links' receive tasks are handed over to the single-threaded transmit runtime.
pub const SERIAL_TLS_RUNTIME: &str = "(rx: (handover: tx))";

/// Works around zenoh 1.10's TLS link, which reads and writes one rustls stream from two
/// threads at once (eclipse-zenoh/zenoh#2557, open): under two-way load the stream's state
/// breaks ("TX task failed: handshake not complete") and the link drops, every few seconds
/// with two busy actors. Running zenoh's receive tasks on its one transmit thread
/// (`ZENOH_RUNTIME`) makes them take turns; measured on loopback with the smoke preset and two
/// TLS actors: 0 drops in 20 s instead of 21 in 10 s, at the same throughput.
///
/// Only when an endpoint is `tls/` and `ZENOH_RUNTIME` is not already set (a user's own
/// setting wins). Call first thing in `main`, before any thread exists: zenoh reads the
/// variable when it starts its runtimes, and changing the environment is only sound while
/// the process has a single thread.
pub fn serialize_tls_link_io(endpoints: &[String]) {
    if endpoints.iter().any(|e| is_tls_endpoint(e)) && std::env::var_os(ZENOH_RUNTIME_VARIABLE).is_none() {
        #[allow(unsafe_code)]
        // SAFETY: called at the start of `main`, while the process has one thread, so nothing
        // can read the environment concurrently.
        unsafe {
            std::env::set_var(ZENOH_RUNTIME_VARIABLE, SERIAL_TLS_RUNTIME);
        }
    }
}

/// The environment variable zenoh reads its runtime settings from.
const ZENOH_RUNTIME_VARIABLE: &str = "ZENOH_RUNTIME";

/// Whether a zenoh endpoint is a TLS one.
fn is_tls_endpoint(endpoint: &str) -> bool {
    endpoint.starts_with("tls/")
}

/// A list of strings as a zenoh JSON5 setting takes it (`connect/endpoints`,
/// `listen/endpoints`): each quoted and escaped.
pub fn zenoh_string_list(items: &[String]) -> String {
    let quoted: Vec<String> = items.iter().map(|s| format!("{s:?}")).collect();
    format!("[{}]", quoted.join(","))
}

/// Splits `--zenoh KEY=JSON5` arguments into pairs; the error names the bad argument.
pub fn zenoh_overrides(pairs: &[String]) -> Result<Vec<(String, String)>, ZenohOverrideError> {
    pairs
        .iter()
        .map(|pair| {
            pair.split_once('=')
                .map(|(k, v)| (k.trim().to_string(), v.trim().to_string()))
                .ok_or_else(|| ZenohOverrideError { pair: pair.clone() })
        })
        .collect()
}

/// A `--zenoh` value that is not KEY=JSON5.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("--zenoh {pair:?}: expected KEY=JSON5, e.g. transport/link/tls/enable_mtls=true")]
pub struct ZenohOverrideError {
    pub pair: String,
}

/// Which side of a TLS link a process is on: the learner listens, actors connect.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TlsSide {
    Listen,
    Connect,
}

/// The mutual-TLS material of one process (as `deploy/make-tls.sh` makes it): the CA that
/// signs every certificate of the deployment, this process's certificate and its key.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TlsFiles {
    pub ca_certificate: std::path::PathBuf,
    pub certificate: std::path::PathBuf,
    pub private_key: std::path::PathBuf,
}

/// The three mutual-TLS flags every binary that talks to a learner takes (`#[command(flatten)]`).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct TlsArgs {
    /// Mutual TLS: the CA certificate (PEM) that signed every certificate of the deployment.
    /// With --tls-cert and --tls-key; every endpoint must then be tls/, and a learner enforces
    /// its access-control policy (learner/src/service/access_control.rs).
    #[arg(long, env = "CRAWLER_TLS_CA", value_name = "PEM")]
    pub tls_ca: Option<std::path::PathBuf>,
    /// Mutual TLS: this process's certificate (PEM, from deploy/make-tls.sh).
    #[arg(long, env = "CRAWLER_TLS_CERT", value_name = "PEM")]
    pub tls_cert: Option<std::path::PathBuf>,
    /// Mutual TLS: this process's private key (PEM).
    #[arg(long, env = "CRAWLER_TLS_KEY", value_name = "PEM")]
    pub tls_key: Option<std::path::PathBuf>,
}

/// TLS flags that cannot make a mutually authenticated link.
#[derive(Debug, thiserror::Error)]
pub enum TlsArgsError {
    #[error("mutual TLS needs --tls-ca, --tls-cert and --tls-key together; missing {} (deploy/make-tls.sh makes all three)", .missing.join(", "))]
    Incomplete { missing: Vec<&'static str> },
    #[error("{flag} {}: {source}", .path.display())]
    Unreadable { flag: &'static str, path: std::path::PathBuf, source: std::io::Error },
    #[error("{flag} {}: not a PEM file (expected a -----BEGIN … block)", .path.display())]
    NotPem { flag: &'static str, path: std::path::PathBuf },
    #[error("{flag} {endpoint:?} is not a tls/ endpoint, but TLS material was given; use e.g. tls/HOST:7447")]
    PlainEndpoint { flag: String, endpoint: String },
    #[error("{flag} {}: larger than {MAX_PEM_BYTES} bytes, which no certificate or key of ours is; pass the PEM file deploy/make-tls.sh wrote", .path.display())]
    TooLarge { flag: &'static str, path: std::path::PathBuf },
    #[error("--tls-cert {}: its first PEM block is not an X.509 certificate ({reason})", .path.display())]
    NotACertificate { path: std::path::PathBuf, reason: String },
    #[error("--tls-cert {}: the certificate's subject has no common name, so it names no actor; make it with deploy/make-tls.sh", .path.display())]
    NoCommonName { path: std::path::PathBuf },
    #[error("--tls-cert {}: {source}", .path.display())]
    Identity {
        path: std::path::PathBuf,
        #[source]
        source: crawler_proto::identity::IdentityError,
    },
}

/// Largest certificate or key file read, in bytes: a PEM chain of ours is a few kB, and a
/// path that links to an endless file (`/dev/zero`) must not be read without end.
pub const MAX_PEM_BYTES: u64 = 1 << 20;

/// Reads a file of at most [`MAX_PEM_BYTES`], whatever its metadata claims (a device or a pipe
/// reports no size).
fn read_pem_file(flag: &'static str, path: &std::path::Path) -> Result<Vec<u8>, TlsArgsError> {
    use std::io::Read;
    let unreadable = |source| TlsArgsError::Unreadable { flag, path: path.to_path_buf(), source };
    let file = std::fs::File::open(path).map_err(unreadable)?;
    let mut bytes = Vec::new();
    file.take(MAX_PEM_BYTES + 1).read_to_end(&mut bytes).map_err(unreadable)?;
    if bytes.len() as u64 > MAX_PEM_BYTES {
        return Err(TlsArgsError::TooLarge { flag, path: path.to_path_buf() });
    }
    Ok(bytes)
}

impl TlsArgs {
    /// All three paths or none: a half-configured link would silently fall back to no client
    /// certificate, so that is an error that says which flag is missing.
    pub fn files(&self) -> Result<Option<TlsFiles>, TlsArgsError> {
        match (&self.tls_ca, &self.tls_cert, &self.tls_key) {
            (None, None, None) => Ok(None),
            (Some(ca_certificate), Some(certificate), Some(private_key)) => {
                let files = TlsFiles {
                    ca_certificate: ca_certificate.clone(),
                    certificate: certificate.clone(),
                    private_key: private_key.clone(),
                };
                files.check_readable()?;
                Ok(Some(files))
            }
            (ca, cert, key) => {
                let missing: Vec<&'static str> =
                    [(ca.is_none(), "--tls-ca"), (cert.is_none(), "--tls-cert"), (key.is_none(), "--tls-key")]
                        .into_iter()
                        .filter_map(|(missing, flag)| missing.then_some(flag))
                        .collect();
                Err(TlsArgsError::Incomplete { missing })
            }
        }
    }
}

impl TlsFiles {
    fn check_readable(&self) -> Result<(), TlsArgsError> {
        for (flag, path) in
            [("--tls-ca", &self.ca_certificate), ("--tls-cert", &self.certificate), ("--tls-key", &self.private_key)]
        {
            let bytes = read_pem_file(flag, path)?;
            if !bytes.windows(11).any(|w| w == b"-----BEGIN ") {
                return Err(TlsArgsError::NotPem { flag, path: path.clone() });
            }
        }
        Ok(())
    }

    /// Who this process's certificate says it is: the role and id in its subject's first
    /// common name (what zenoh's TLS link reads, and what the learner's access-control policy
    /// matches; `crawler_proto::identity`).
    pub fn certified(&self) -> Result<crawler_proto::identity::Certified, TlsArgsError> {
        let path = &self.certificate;
        let bytes = read_pem_file("--tls-cert", path)?;
        let not_a_certificate = |reason: String| TlsArgsError::NotACertificate { path: path.clone(), reason };
        let (_, pem) = x509_parser::pem::parse_x509_pem(&bytes).map_err(|e| not_a_certificate(e.to_string()))?;
        let certificate = pem.parse_x509().map_err(|e| not_a_certificate(e.to_string()))?;
        let common_name = certificate
            .subject()
            .iter_common_name()
            .next()
            .and_then(|cn| cn.as_str().ok())
            .ok_or_else(|| TlsArgsError::NoCommonName { path: path.clone() })?;
        crawler_proto::identity::Certified::from_common_name(common_name)
            .map_err(|source| TlsArgsError::Identity { path: path.clone(), source })
    }

    /// zenoh settings (KEY, JSON5) for a TLS link that requires certificates on both ends.
    pub fn zenoh_settings(&self, side: TlsSide) -> Vec<(String, String)> {
        let (key, certificate) = match side {
            TlsSide::Listen => ("listen_private_key", "listen_certificate"),
            TlsSide::Connect => ("connect_private_key", "connect_certificate"),
        };
        let quoted = |path: &std::path::Path| format!("{:?}", path.display().to_string());
        vec![
            ("transport/link/tls/root_ca_certificate".into(), quoted(&self.ca_certificate)),
            (format!("transport/link/tls/{key}"), quoted(&self.private_key)),
            (format!("transport/link/tls/{certificate}"), quoted(&self.certificate)),
            ("transport/link/tls/enable_mtls".into(), "true".into()),
        ]
    }
}

/// Every endpoint must be a `tls/` one when TLS material is given: a `tcp/` endpoint beside
/// it would carry the same traffic unauthenticated.
pub fn check_tls_endpoints(endpoints: &[String], flag: &str) -> Result<(), TlsArgsError> {
    match endpoints.iter().find(|e| !is_tls_endpoint(e)) {
        Some(plain) => Err(TlsArgsError::PlainEndpoint { flag: flag.to_string(), endpoint: plain.clone() }),
        None => Ok(()),
    }
}

/// Waits for Ctrl-C or SIGTERM, then sets `stop`.
pub async fn stop_on_signal(stop: Arc<AtomicBool>) {
    let ctrl_c = tokio::signal::ctrl_c();
    #[cfg(unix)]
    {
        let mut term = match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(term) => term,
            Err(_) => {
                let _ = ctrl_c.await;
                stop.store(true, Ordering::SeqCst);
                return;
            }
        };
        tokio::select! {
            _ = ctrl_c => {}
            _ = term.recv() => {}
        }
    }
    #[cfg(not(unix))]
    let _ = ctrl_c.await;
    tracing::info!("signal received: stopping");
    stop.store(true, Ordering::SeqCst);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flags(ca: Option<&str>, cert: Option<&str>, key: Option<&str>) -> TlsArgs {
        TlsArgs { tls_ca: ca.map(Into::into), tls_cert: cert.map(Into::into), tls_key: key.map(Into::into) }
    }

    #[test]
    fn tls_flags_come_all_together_or_not_at_all() {
        assert!(matches!(flags(None, None, None).files(), Ok(None)));
        let error = flags(Some("ca.pem"), None, Some("a.key")).files().unwrap_err().to_string();
        assert!(error.contains("missing --tls-cert"), "{error}");
        let error = flags(Some("/nonexistent/ca.pem"), Some("a"), Some("b")).files().unwrap_err().to_string();
        assert!(error.contains("--tls-ca /nonexistent/ca.pem"), "{error}");
    }

    #[test]
    fn a_file_without_pem_blocks_is_named() {
        let dir = std::env::temp_dir().join(format!("crawler-tls-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let pem = dir.join("ok.pem");
        let junk = dir.join("junk.key");
        std::fs::write(&pem, "-----BEGIN CERTIFICATE-----\nAA==\n-----END CERTIFICATE-----\n").unwrap();
        std::fs::write(&junk, "not a key").unwrap();
        let (pem_path, junk_path) = (pem.to_str().unwrap(), junk.to_str().unwrap());
        let error = flags(Some(pem_path), Some(pem_path), Some(junk_path)).files().unwrap_err().to_string();
        assert!(error.starts_with("--tls-key") && error.contains("not a PEM file"), "{error}");
        let files = flags(Some(pem_path), Some(pem_path), Some(pem_path)).files().unwrap().unwrap();
        let settings = files.zenoh_settings(TlsSide::Connect);
        assert!(settings.iter().any(|(k, v)| k == "transport/link/tls/connect_certificate" && v.contains("ok.pem")));
        assert!(settings.iter().any(|(k, v)| k == "transport/link/tls/enable_mtls" && v == "true"));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// A self-signed certificate with subject `CN=common_name`, made by openssl as
    /// deploy/make-tls.sh makes its own.
    fn certificate(dir: &std::path::Path, common_name: &str) -> TlsFiles {
        let (pem, key) = (dir.join(format!("{common_name}.pem")), dir.join(format!("{common_name}.key")));
        let made = std::process::Command::new("openssl")
            .args(["req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes", "-days", "1"])
            .args(["-subj", &format!("/CN={common_name}")])
            .arg("-keyout")
            .arg(&key)
            .arg("-out")
            .arg(&pem)
            .output()
            .unwrap();
        assert!(made.status.success(), "openssl: {}", String::from_utf8_lossy(&made.stderr));
        TlsFiles { ca_certificate: pem.clone(), certificate: pem, private_key: key }
    }

    #[test]
    fn the_certificate_names_who_the_process_is() {
        use crawler_proto::identity::Certified;
        let dir = std::env::temp_dir().join(format!("crawler-tls-cn-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        assert_eq!(certificate(&dir, "crawler-actor-7").certified().unwrap(), Certified::Actor(7));
        assert_eq!(certificate(&dir, "crawler-evaluator-1000").certified().unwrap(), Certified::Evaluator(1000));
        // The one shared name of older deployments names no id.
        let error = certificate(&dir, "crawler-actor").certified().unwrap_err().to_string();
        assert!(error.contains("\"crawler-actor\" names no role"), "{error}");
        let error = certificate(&dir, "crawler-actor-07").certified().unwrap_err().to_string();
        assert!(error.contains("no valid id"), "{error}");
        // A PEM block that is no certificate, and a file without end.
        let mut files = certificate(&dir, "crawler-actor-1");
        files.certificate = files.private_key.clone();
        let error = files.certified().unwrap_err().to_string();
        assert!(error.contains("not an X.509 certificate"), "{error}");
        files.certificate = "/dev/zero".into();
        let error = files.certified().unwrap_err().to_string();
        assert!(error.contains("larger than"), "{error}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn plain_endpoints_beside_tls_material_are_refused() {
        assert!(check_tls_endpoints(&["tls/learner:7447".into()], "--connect").is_ok());
        let error = check_tls_endpoints(&["tls/a:1".into(), "tcp/b:2".into()], "--connect").unwrap_err().to_string();
        assert!(error.contains("\"tcp/b:2\""), "{error}");
    }
}
