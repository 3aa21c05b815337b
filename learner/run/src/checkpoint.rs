//! Checkpoints: everything needed to resume a run, written atomically.
//!
//! A checkpoint is a directory `step-<updates>` holding:
//! - `weights.safetensors`: the online network, named as a PyTorch `nn.Sequential` of the same
//!   layers names its `state_dict` (see [`NetworkSpec`]), so `load_state_dict` takes it as is;
//! - `target.safetensors`: the target network, same names;
//! - `optimizer.safetensors`: Adam's `exp_avg` and `exp_avg_sq`, flat, in parameter order;
//! - `replay.bin` (optional): a bincode snapshot of the replay buffer;
//! - `meta.json`: format and layout versions, network spec, counters, ε, the run's config, and
//!   the size and CRC-32 of every file above, so corruption and truncation are caught by name.
//!
//! It is written into a temporary sibling directory and renamed into place, so a crash during
//! a write leaves the previous checkpoints untouched; leftovers are removed on the next save.
//!
//! This module is the format alone, over plain `f32` slices: it links no libtorch, so `eval`,
//! `plot` and `render` read checkpoints anywhere. The learner's `checkpoint` module turns its
//! DQN and replay into a [`Snapshot`] and back.

use std::collections::BTreeMap;
use std::fs;
use std::io::{BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use crawler_env::OBS_LAYOUT_VERSION;
use crawler_env::policy::NetworkSpec;
use safetensors::tensor::TensorView;
use safetensors::{Dtype, SafeTensors};
use serde::{Deserialize, Serialize};

/// Version of this on-disk layout.
pub const CHECKPOINT_FORMAT: u32 = 1;

const META: &str = "meta.json";
const WEIGHTS: &str = "weights.safetensors";
const TARGET: &str = "target.safetensors";
const OPTIMIZER: &str = "optimizer.safetensors";
const REPLAY: &str = "replay.bin";
const PREFIX: &str = "step-";
/// The most bytes a `meta.json` may hold (the run's config and the file table take a few kB).
const MAX_META_BYTES: u64 = 16 << 20;
/// The largest counter a checkpoint may hold: 2⁵³, exact in every JSON reader, and beyond
/// anything a run reaches (10⁶ updates a second for 285 years).
pub const MAX_COUNTER: u64 = 1 << 53;
const TEMP_MARKER: &str = ".partial-";

/// The fail point between writing a checkpoint's files and renaming them into place, so a
/// test can kill the process in the middle of a checkpoint
/// (`FAILPOINTS=checkpoint-before-rename=sleep(400)`). It exists only in builds with the
/// `fault-injection` feature (what `scripts/test` builds); elsewhere it compiles to nothing.
pub const FAIL_BEFORE_RENAME: &str = "checkpoint-before-rename";

#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error("cannot {action} {path}: {source}")]
    Io { action: &'static str, path: PathBuf, source: std::io::Error },
    #[error("checkpoint file {path} is corrupt: {reason}")]
    Corrupt { path: PathBuf, reason: String },
    #[error("checkpoint file {path} passed its checksum but is not this version's replay layout: {reason}")]
    ReplayLayout { path: PathBuf, reason: String },
    #[error("checkpoint file {path} holds a replay that fails its checks: {reason}")]
    ReplayContent { path: PathBuf, reason: String },
    #[error("checkpoint {path} does not fit this run: its {what} is {found}, this run needs {expected}")]
    Mismatch { path: PathBuf, what: &'static str, found: String, expected: String },
    #[error("no checkpoint found in {0}; train first, or point at a `step-*` directory")]
    NotFound(PathBuf),
    #[error("refusing to save a checkpoint in {0}: the {1} network holds NaN or infinite weights")]
    NonFinite(PathBuf, &'static str),
    #[error("checkpoint {path} did not load back after writing, so it was removed: {source}")]
    Unreadable { path: PathBuf, source: Box<CheckpointError> },
}

fn io(action: &'static str, path: &Path) -> impl FnOnce(std::io::Error) -> CheckpointError + use<> {
    let path = path.to_path_buf();
    move |source| CheckpointError::Io { action, path, source }
}

/// The error for a file whose content is wrong, naming the file and what is wrong with it.
pub fn corrupt(path: &Path, reason: impl ToString) -> CheckpointError {
    CheckpointError::Corrupt { path: path.to_path_buf(), reason: reason.to_string() }
}

/// Size and checksum of one file of a checkpoint.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileDigest {
    pub bytes: u64,
    pub crc32: u32,
}

/// Counters a run keeps across restarts.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Progress {
    /// Gradient updates done.
    pub updates: u64,
    /// Environment steps (decisions) received from actors.
    pub env_steps: u64,
    /// Physics steps simulated by actors.
    pub physics_steps: u64,
    /// Version of the last weights published.
    pub weights_version: u64,
    /// The learner process of the run that wrote this (see `proto::Weights::learner_session`).
    #[serde(default)]
    pub learner_session: u64,
    /// ε of the exploration schedule at this point.
    pub epsilon: f64,
    /// Seconds of training behind this checkpoint, over all sessions of the run.
    pub train_seconds: f64,
}

/// The `meta.json` of a checkpoint.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckpointMeta {
    pub format: u32,
    pub obs_layout_version: u32,
    pub run_id: String,
    pub network: NetworkSpec,
    pub progress: Progress,
    pub adam_step: u64,
    /// The run's full configuration, for the record and for `--resume`.
    pub config: serde_json::Value,
    pub files: BTreeMap<String, FileDigest>,
    /// The checkpoints whose weights this one averages (`crate::average`), oldest first;
    /// empty for a checkpoint the learner wrote from its own weights.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub averaged_from: Vec<String>,
}

impl CheckpointMeta {
    /// Checks every counter and clock against what a run can reach, as wire data is checked:
    /// a resumed run takes them as they are.
    pub fn check_ranges(&self) -> Result<(), String> {
        let p = &self.progress;
        for (field, value) in [
            ("progress.updates", p.updates),
            ("progress.env_steps", p.env_steps),
            ("progress.physics_steps", p.physics_steps),
            ("progress.weights_version", p.weights_version),
            ("progress.learner_session", p.learner_session),
            ("adam_step", self.adam_step),
        ] {
            if value > MAX_COUNTER {
                return Err(format!("{field} is {value}, beyond the {MAX_COUNTER} a run can reach"));
            }
        }
        if !(0.0..=1.0).contains(&p.epsilon) {
            return Err(format!("progress.epsilon is {}, outside [0, 1]", p.epsilon));
        }
        // A century of training.
        if !(0.0..=3.2e9).contains(&p.train_seconds) {
            return Err(format!("progress.train_seconds is {}, outside [0, 3.2e9]", p.train_seconds));
        }
        Ok(())
    }
}

/// A loaded checkpoint.
#[derive(Debug, Clone)]
pub struct Checkpoint {
    pub path: PathBuf,
    pub meta: CheckpointMeta,
    pub online: Vec<f32>,
    pub target: Vec<f32>,
    pub exp_avg: Vec<f32>,
    pub exp_avg_sq: Vec<f32>,
}

/// Writes a file's content (the replay snapshot's, say) into a checkpoint.
pub type FileWriter<'a> = &'a dyn Fn(&mut dyn Write) -> std::io::Result<()>;

/// What a checkpoint holds, as the learner hands it over: flat parameter vectors in the
/// spec's order, Adam's moments, and the replay snapshot's writer, if any.
pub struct Snapshot<'a> {
    pub network: &'a NetworkSpec,
    pub online: &'a [f32],
    pub target: &'a [f32],
    pub exp_avg: &'a [f32],
    pub exp_avg_sq: &'a [f32],
    pub adam_step: u64,
    /// Writes `replay.bin`; None: the checkpoint has no replay.
    pub replay: Option<FileWriter<'a>>,
}

impl std::fmt::Debug for Snapshot<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Snapshot")
            .field("network", self.network)
            .field("parameters", &self.online.len())
            .field("adam_step", &self.adam_step)
            .field("replay", &self.replay.is_some())
            .finish()
    }
}

/// Flat parameters (in `spec` order) as safetensors bytes named as PyTorch's `state_dict`
/// (also what the learner broadcasts). Values beyond the spec's parameters are ignored.
pub fn encode_weights(spec: &NetworkSpec, flat: &[f32]) -> Vec<u8> {
    let mut offset = 0;
    let bytes: Vec<(String, Vec<usize>, Vec<u8>)> = spec
        .params()
        .into_iter()
        .map(|info| {
            let end = (offset + info.numel()).min(flat.len());
            let values = &flat[offset.min(end)..end];
            offset = end;
            (info.name, info.shape, f32_bytes(values))
        })
        .collect();
    serialize(bytes.iter().map(|(n, s, b)| (n.as_str(), s.clone(), b.as_slice())))
}

fn f32_bytes(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

fn serialize<'a>(tensors: impl Iterator<Item = (&'a str, Vec<usize>, &'a [u8])>) -> Vec<u8> {
    let views: Vec<(String, TensorView<'a>)> = tensors
        .filter_map(|(name, shape, data)| TensorView::new(Dtype::F32, shape, data).ok().map(|v| (name.to_string(), v)))
        .collect();
    // Serialising well-formed F32 views into memory cannot fail.
    safetensors::serialize(views, None).unwrap_or_default()
}

/// Writes a checkpoint of `snapshot` under `dir` and keeps the newest `keep` of them.
pub fn save(
    dir: &Path,
    snapshot: &Snapshot<'_>,
    run_id: &str,
    progress: &Progress,
    config: &serde_json::Value,
    keep: usize,
) -> Result<PathBuf, CheckpointError> {
    let name = format!("{PREFIX}{:012}", progress.updates);
    let final_path = write_named(dir, &name, snapshot, run_id, progress, config, Vec::new())?;
    prune(dir, keep)?;
    Ok(final_path)
}

/// Writes a checkpoint of `snapshot` as `dir/name`, replacing one of that name whole: its
/// files go to a temporary directory first, which is renamed into place once complete and
/// kept only if it loads back. `averaged_from` goes to `meta.json` as it is.
pub(crate) fn write_named(
    dir: &Path,
    name: &str,
    snapshot: &Snapshot<'_>,
    run_id: &str,
    progress: &Progress,
    config: &serde_json::Value,
    averaged_from: Vec<String>,
) -> Result<PathBuf, CheckpointError> {
    for (values, which) in [(snapshot.online, "online"), (snapshot.target, "target")] {
        if !values.iter().all(|v| v.is_finite()) {
            return Err(CheckpointError::NonFinite(dir.to_path_buf(), which));
        }
    }
    fs::create_dir_all(dir).map_err(io("create", dir))?;
    let final_path = dir.join(name);
    let temp = dir.join(format!("{name}{TEMP_MARKER}{}", std::process::id()));
    if temp.exists() {
        fs::remove_dir_all(&temp).map_err(io("remove", &temp))?;
    }
    fs::create_dir(&temp).map_err(io("create", &temp))?;

    let mut files = BTreeMap::new();
    let mut write = |file: &str, fill: &dyn Fn(&mut dyn Write) -> std::io::Result<()>| {
        let digest = write_synced(&temp.join(file), fill)?;
        files.insert(file.to_string(), digest);
        Ok::<(), CheckpointError>(())
    };
    write(WEIGHTS, &|w| w.write_all(&encode_weights(snapshot.network, snapshot.online)))?;
    write(TARGET, &|w| w.write_all(&encode_weights(snapshot.network, snapshot.target)))?;
    let exp_avg = f32_bytes(snapshot.exp_avg);
    let exp_avg_sq = f32_bytes(snapshot.exp_avg_sq);
    let optimizer = serialize(
        [
            ("exp_avg", vec![snapshot.exp_avg.len()], &exp_avg[..]),
            ("exp_avg_sq", vec![snapshot.exp_avg_sq.len()], &exp_avg_sq[..]),
        ]
        .into_iter(),
    );
    write(OPTIMIZER, &|w| w.write_all(&optimizer))?;
    if let Some(replay) = snapshot.replay {
        write(REPLAY, replay)?;
    }
    let meta = CheckpointMeta {
        format: CHECKPOINT_FORMAT,
        obs_layout_version: OBS_LAYOUT_VERSION,
        run_id: run_id.to_string(),
        network: snapshot.network.clone(),
        progress: progress.clone(),
        adam_step: snapshot.adam_step,
        config: config.clone(),
        files,
        averaged_from,
    };
    let json = serde_json::to_vec_pretty(&meta).map_err(|e| corrupt(&temp.join(META), e))?;
    write_synced(&temp.join(META), &|w| w.write_all(&json))?;

    fail::fail_point!(FAIL_BEFORE_RENAME);
    if final_path.exists() {
        remove_atomically(&final_path)?;
    }
    fs::rename(&temp, &final_path).map_err(io("rename into place", &final_path))?;
    if let Ok(parent) = fs::File::open(dir) {
        let _ = parent.sync_all();
    }
    // Only a checkpoint that loads back counts; older ones are pruned only after that, so
    // the newest good checkpoint is never the one removed.
    if let Err(error) = verify_saved(&final_path) {
        // Out of the listing first, as every removal: a reader may have found it already.
        let _ = remove_atomically(&final_path);
        return Err(CheckpointError::Unreadable { path: final_path, source: Box::new(error) });
    }
    Ok(final_path)
}

/// Reads a checkpoint back as `eval` and `--resume` will: every file against its checksum,
/// the weights finite.
fn verify_saved(path: &Path) -> Result<(), CheckpointError> {
    let checkpoint = load(path)?;
    if !checkpoint.online.iter().chain(&checkpoint.target).all(|v| v.is_finite()) {
        return Err(corrupt(path, "non-finite weights"));
    }
    if let Some(digest) = checkpoint.meta.files.get(REPLAY) {
        read_verified(&path.join(REPLAY), digest)?;
    }
    Ok(())
}

/// Counts and checksums bytes on their way to a writer.
struct DigestWriter<W> {
    inner: W,
    hasher: crc32fast::Hasher,
    bytes: u64,
}

impl<W: Write> Write for DigestWriter<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.hasher.update(&buf[..n]);
        self.bytes += n as u64;
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

/// Writes a file through `fill`, syncs it to disk and returns its size and checksum.
fn write_synced(
    path: &Path,
    fill: &dyn Fn(&mut dyn Write) -> std::io::Result<()>,
) -> Result<FileDigest, CheckpointError> {
    let file = fs::File::create(path).map_err(io("create", path))?;
    let mut writer =
        DigestWriter { inner: BufWriter::with_capacity(1 << 20, file), hasher: crc32fast::Hasher::new(), bytes: 0 };
    fill(&mut writer).and_then(|()| writer.flush()).map_err(io("write", path))?;
    let DigestWriter { inner, hasher, bytes } = writer;
    let file = inner.into_inner().map_err(|e| io("write", path)(e.into_error()))?;
    file.sync_all().map_err(io("sync", path))?;
    Ok(FileDigest { bytes, crc32: hasher.finalize() })
}

/// Checkpoint directories under `dir`, oldest first. Partial writes are not listed.
pub fn list(dir: &Path) -> Result<Vec<PathBuf>, CheckpointError> {
    if !dir.exists() {
        return Ok(Vec::new());
    }
    let mut found: Vec<PathBuf> = fs::read_dir(dir)
        .map_err(io("read", dir))?
        .filter_map(Result::ok)
        .map(|entry| entry.path())
        .filter(|path| {
            let name = path.file_name().and_then(|n| n.to_str()).unwrap_or_default();
            name.starts_with(PREFIX) && !name.contains(TEMP_MARKER) && path.join(META).is_file()
        })
        .collect();
    found.sort();
    Ok(found)
}

/// The newest complete checkpoint under `dir`.
pub fn latest(dir: &Path) -> Result<PathBuf, CheckpointError> {
    list(dir)?.pop().ok_or_else(|| CheckpointError::NotFound(dir.to_path_buf()))
}

/// Removes the checkpoint `path` so that a reader sees it whole or not at all: it is renamed
/// out of the listing in one step (a name [`list`] skips), then deleted. Deleting in place
/// would let a reader find `meta.json` while the files it names are already gone.
fn remove_atomically(path: &Path) -> Result<(), CheckpointError> {
    let mut doomed = path.as_os_str().to_owned();
    doomed.push(format!("{TEMP_MARKER}{}.removed", std::process::id()));
    let doomed = PathBuf::from(doomed);
    fs::rename(path, &doomed).map_err(io("move out of the way", path))?;
    fs::remove_dir_all(&doomed).map_err(io("remove", &doomed))
}

/// Removes all but the newest `keep` checkpoints, and leftovers of interrupted writes.
fn prune(dir: &Path, keep: usize) -> Result<(), CheckpointError> {
    let complete = list(dir)?;
    let excess = complete.len().saturating_sub(keep.max(1));
    for old in &complete[..excess] {
        remove_atomically(old)?;
    }
    let own = format!("{TEMP_MARKER}{}", std::process::id());
    for entry in fs::read_dir(dir).map_err(io("read", dir))?.filter_map(Result::ok) {
        let name = entry.file_name().to_string_lossy().to_string();
        if name.contains(TEMP_MARKER) && !name.ends_with(&own) {
            let _ = fs::remove_dir_all(entry.path());
        }
    }
    Ok(())
}

/// How often [`load`] takes the newest checkpoint again when the one it was reading was
/// pruned or replaced under it. Each retry needs a live learner to finish a whole save during
/// one read, so a handful is plenty.
const RELOADS_AFTER_PRUNING: usize = 8;

/// Loads a checkpoint: `path` is a `step-*` directory or a directory of them (the newest is
/// taken). Every file is checked against the sizes and checksums in `meta.json`.
///
/// A directory of checkpoints may belong to a learner that is still running: it prunes the
/// oldest as it saves, so the newest one listed can vanish (or be replaced by a final
/// checkpoint of the same step) while it is read. Then the newest is taken again; an error is
/// reported only for a checkpoint that stayed in place while it failed to load.
pub fn load(path: &Path) -> Result<Checkpoint, CheckpointError> {
    // Any entry named meta.json makes this one checkpoint, so that a meta.json that is no
    // regular file is refused by name rather than read as a directory of checkpoints.
    if path.join(META).symlink_metadata().is_ok() {
        return load_one(path.to_path_buf());
    }
    let mut reloads = 0;
    loop {
        let newest = match latest(path) {
            Ok(newest) => newest,
            // A live learner that keeps one checkpoint can empty the listing for an instant:
            // the directory was read while only the old checkpoint was in it, and that one was
            // pruned before its `meta.json` was looked at. A `step-*` name of any kind (one
            // being written or removed) says a learner is at work there, so list again.
            Err(CheckpointError::NotFound(_)) if reloads < RELOADS_AFTER_PRUNING && holds_checkpoint_names(path) => {
                tracing::debug!(dir = %path.display(), "no complete checkpoint listed while one is written or pruned; listing again");
                reloads += 1;
                continue;
            }
            Err(error) => return Err(error),
        };
        let meta_before = read_capped(&newest.join(META), MAX_META_BYTES).ok();
        match load_one(newest.clone()) {
            Err(error) if reloads < RELOADS_AFTER_PRUNING => {
                let meta_after = read_capped(&newest.join(META), MAX_META_BYTES).ok();
                if meta_before.is_some() && meta_before == meta_after {
                    return Err(error);
                }
                tracing::debug!(checkpoint = %newest.display(), %error, "checkpoint pruned or replaced while read; taking the newest again");
                reloads += 1;
            }
            result => return result,
        }
    }
}

/// Whether `dir` holds any `step-*` entry: a checkpoint, or one being written or removed.
fn holds_checkpoint_names(dir: &Path) -> bool {
    fs::read_dir(dir).is_ok_and(|entries| {
        entries.filter_map(Result::ok).any(|entry| entry.file_name().to_string_lossy().starts_with(PREFIX))
    })
}

/// Loads the checkpoint in the `step-*` directory `path`.
fn load_one(path: PathBuf) -> Result<Checkpoint, CheckpointError> {
    let meta_path = path.join(META);
    let meta_bytes = read_capped(&meta_path, MAX_META_BYTES)?;
    let meta: CheckpointMeta = serde_json::from_slice(&meta_bytes).map_err(|e| corrupt(&meta_path, e))?;
    meta.check_ranges().map_err(|reason| corrupt(&meta_path, reason))?;
    for (what, found, expected) in [
        ("format version", meta.format, CHECKPOINT_FORMAT),
        ("observation layout version", meta.obs_layout_version, OBS_LAYOUT_VERSION),
    ] {
        if found != expected {
            return Err(CheckpointError::Mismatch {
                path,
                what,
                found: found.to_string(),
                expected: expected.to_string(),
            });
        }
    }
    meta.network.validate().map_err(|e| corrupt(&meta_path, e))?;
    let n = meta.network.num_params();
    // Safetensors headers name a few tensors; 1 MiB is far more than they take.
    let header = 1 << 20;
    let read = |file: &str, values: usize| -> Result<Vec<u8>, CheckpointError> {
        let digest = meta.files.get(file).ok_or_else(|| corrupt(&meta_path, format!("no entry for {file}")))?;
        let most = (values as u64).saturating_mul(4).saturating_add(header);
        if digest.bytes > most {
            return Err(corrupt(
                &meta_path,
                format!(
                    "files.{file}.bytes is {}, more than the {most} its network's {values} values take",
                    digest.bytes
                ),
            ));
        }
        read_verified(&path.join(file), digest)
    };
    let online = decode_weights(&read(WEIGHTS, n)?, &meta.network, &path.join(WEIGHTS))?;
    let target = decode_weights(&read(TARGET, n)?, &meta.network, &path.join(TARGET))?;
    let optimizer_path = path.join(OPTIMIZER);
    let optimizer = read(OPTIMIZER, 2 * n)?;
    let tensors = SafeTensors::deserialize(&optimizer).map_err(|e| corrupt(&optimizer_path, e))?;
    let flat = |name: &str| -> Result<Vec<f32>, CheckpointError> {
        let view = tensors.tensor(name).map_err(|e| corrupt(&optimizer_path, e))?;
        let values = to_f32(view.data());
        if values.len() != n {
            return Err(corrupt(&optimizer_path, format!("{name} has {} values, the network {n}", values.len())));
        }
        Ok(values)
    };
    let (exp_avg, exp_avg_sq) = (flat("exp_avg")?, flat("exp_avg_sq")?);
    Ok(Checkpoint { path, meta, online, target, exp_avg, exp_avg_sq })
}

/// A checkpoint file's bytes, checked against its size and checksum. The size is checked
/// before anything is read, so a file that links to a device or grew past its entry costs
/// nothing.
fn read_verified(path: &Path, digest: &FileDigest) -> Result<Vec<u8>, CheckpointError> {
    let bytes = read_capped(path, digest.bytes)?;
    verify(path, &bytes, digest)?;
    Ok(bytes)
}

/// Reads a regular file of at most `most` bytes (links are followed; devices, pipes and
/// directories are refused), reading no more than that even if it grows meanwhile.
fn read_capped(path: &Path, most: u64) -> Result<Vec<u8>, CheckpointError> {
    let file = fs::File::open(path).map_err(io("open", path))?;
    let metadata = file.metadata().map_err(io("inspect", path))?;
    if !metadata.is_file() {
        return Err(corrupt(path, "not a regular file"));
    }
    if metadata.len() > most {
        return Err(corrupt(path, format!("{} bytes, more than the {most} it may hold", metadata.len())));
    }
    let mut bytes = Vec::with_capacity(metadata.len() as usize);
    file.take(most.saturating_add(1)).read_to_end(&mut bytes).map_err(io("read", path))?;
    if bytes.len() as u64 > most {
        return Err(corrupt(path, format!("grew past the {most} bytes it may hold while read")));
    }
    Ok(bytes)
}

fn verify(path: &Path, bytes: &[u8], digest: &FileDigest) -> Result<(), CheckpointError> {
    if bytes.len() as u64 != digest.bytes {
        return Err(corrupt(path, format!("{} bytes, expected {} (truncated?)", bytes.len(), digest.bytes)));
    }
    let crc = crc32fast::hash(bytes);
    if crc != digest.crc32 {
        return Err(corrupt(path, format!("CRC-32 {crc:08x}, expected {:08x}", digest.crc32)));
    }
    Ok(())
}

fn to_f32(bytes: &[u8]) -> Vec<f32> {
    bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()
}

/// Flat parameter values, in spec order, from safetensors bytes named as the spec says.
pub fn decode_weights(bytes: &[u8], spec: &NetworkSpec, path: &Path) -> Result<Vec<f32>, CheckpointError> {
    let tensors = SafeTensors::deserialize(bytes).map_err(|e| corrupt(path, e))?;
    let mut flat = Vec::with_capacity(spec.num_params());
    for info in spec.params() {
        let view = tensors.tensor(&info.name).map_err(|_| corrupt(path, format!("no tensor `{}`", info.name)))?;
        if view.dtype() != Dtype::F32 || view.shape() != info.shape.as_slice() {
            return Err(corrupt(
                path,
                format!("`{}` is {:?} {:?}, expected F32 {:?}", info.name, view.dtype(), view.shape(), info.shape),
            ));
        }
        flat.extend(to_f32(view.data()));
    }
    Ok(flat)
}

/// The replay snapshot of a checkpoint (`replay.bin`, checked against its size and checksum)
/// and its path, or None when the checkpoint holds no replay.
/// A snapshot whose entry says it is over `most` bytes is not read: it cannot be a replay of
/// the run's configuration.
pub fn replay_bytes(checkpoint: &Checkpoint, most: u64) -> Result<Option<(PathBuf, Vec<u8>)>, CheckpointError> {
    let Some(digest) = checkpoint.meta.files.get(REPLAY) else { return Ok(None) };
    let path = checkpoint.path.join(REPLAY);
    if digest.bytes > most {
        let reason = format!("{} bytes, more than the {most} a replay of this run's size takes", digest.bytes);
        return Err(CheckpointError::ReplayContent { path, reason });
    }
    let bytes = read_verified(&path, digest)?;
    Ok(Some((path, bytes)))
}
