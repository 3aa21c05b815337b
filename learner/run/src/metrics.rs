//! Training metrics: TensorBoard event files and a CSV, both in the run directory.
//!
//! `tensorboard --logdir runs/` reads the event files live (they are flushed every second).
//! The CSV (`metrics.csv`: `wall_time,train_seconds,env_steps,tag,value`, one scalar per
//! row) is what `plot` reads; a resumed run appends to both.
//!
//! The event format is TensorFlow's: a sequence of TFRecords, each a little-endian u64
//! length, its masked CRC-32C, the payload (an `Event` protobuf) and the payload's masked
//! CRC-32C. The two protobuf messages needed are declared here with prost; they are a file
//! format, not part of the actor–learner wire contract.

use std::fs::{File, OpenOptions};
use std::io::{BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use prost::Message;

#[derive(Debug, thiserror::Error)]
pub enum MetricsError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: record at byte {offset}: {problem}")]
    Corrupt { path: PathBuf, offset: u64, problem: String },
    #[error("{path}: line {line}: {problem}")]
    Csv { path: PathBuf, line: usize, problem: String },
}

/// `tensorflow.Event`, reduced to the fields written here.
#[derive(Clone, PartialEq, prost::Message)]
pub struct Event {
    #[prost(double, tag = "1")]
    pub wall_time: f64,
    #[prost(int64, tag = "2")]
    pub step: i64,
    #[prost(string, optional, tag = "3")]
    pub file_version: Option<String>,
    #[prost(message, optional, tag = "5")]
    pub summary: Option<Summary>,
}

/// `tensorflow.Summary`.
#[derive(Clone, PartialEq, prost::Message)]
pub struct Summary {
    #[prost(message, repeated, tag = "1")]
    pub value: Vec<SummaryValue>,
}

/// `tensorflow.Summary.Value` with a simple (scalar) value.
#[derive(Clone, PartialEq, prost::Message)]
pub struct SummaryValue {
    #[prost(string, tag = "1")]
    pub tag: String,
    /// A oneof member in TensorFlow's schema, so it is written even when 0.
    #[prost(float, optional, tag = "2")]
    pub simple_value: Option<f32>,
}

/// One scalar observation.
#[derive(Debug, Clone, PartialEq)]
pub struct Scalar {
    pub wall_time: f64,
    pub train_seconds: f64,
    pub env_steps: u64,
    pub tag: String,
    pub value: f64,
}

const CASTAGNOLI: u32 = 0x82F6_3B78;

const fn crc32c_table() -> [u32; 256] {
    let mut table = [0u32; 256];
    let mut i = 0;
    while i < 256 {
        let mut crc = i as u32;
        let mut bit = 0;
        while bit < 8 {
            crc = if crc & 1 == 1 { (crc >> 1) ^ CASTAGNOLI } else { crc >> 1 };
            bit += 1;
        }
        table[i] = crc;
        i += 1;
    }
    table
}

static CRC32C_TABLE: [u32; 256] = crc32c_table();

/// CRC-32C (Castagnoli), as TFRecord uses.
pub fn crc32c(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &byte in bytes {
        crc = CRC32C_TABLE[((crc ^ u32::from(byte)) & 0xFF) as usize] ^ (crc >> 8);
    }
    !crc
}

/// TFRecord's masking, so that a CRC of data holding CRCs stays well distributed.
pub fn masked_crc32c(bytes: &[u8]) -> u32 {
    let crc = crc32c(bytes);
    (crc.rotate_right(15)).wrapping_add(0xA282_EAD8)
}

fn unix_now() -> f64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0.0, |d| d.as_secs_f64())
}

/// Writes scalars to a fresh event file and appends them to `metrics.csv`.
#[derive(Debug)]
pub struct MetricsWriter {
    events: BufWriter<File>,
    events_path: PathBuf,
    csv: BufWriter<File>,
    csv_path: PathBuf,
}

impl MetricsWriter {
    /// Opens `dir/events.out.tfevents.<time>.<host>.<pid>` (new) and `dir/metrics.csv`
    /// (appended, with a header when new).
    pub fn create(dir: &Path) -> Result<Self, MetricsError> {
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |source| MetricsError::Io { path, source }
        };
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        let host = std::fs::read_to_string("/etc/hostname")
            .ok()
            .map(|h| h.trim().chars().filter(|c| c.is_ascii_alphanumeric() || *c == '-').collect::<String>())
            .filter(|h| !h.is_empty())
            .unwrap_or_else(|| "crawler".into());
        let now = unix_now();
        let events_path = dir.join(format!("events.out.tfevents.{}.{host}.{}", now as u64, std::process::id()));
        let events = File::create(&events_path).map_err(io(&events_path))?;
        let csv_path = dir.join("metrics.csv");
        let is_new = std::fs::metadata(&csv_path).map_or(true, |m| m.len() == 0);
        let csv = OpenOptions::new().create(true).append(true).open(&csv_path).map_err(io(&csv_path))?;
        let mut writer = Self { events: BufWriter::new(events), events_path, csv: BufWriter::new(csv), csv_path };
        if is_new {
            writeln!(writer.csv, "wall_time,train_seconds,env_steps,tag,value").map_err(io(&writer.csv_path))?;
        }
        let header = Event { wall_time: now, step: 0, file_version: Some("brain.Event:2".into()), summary: None };
        writer.write_record(&header.encode_to_vec())?;
        writer.flush()?;
        Ok(writer)
    }

    pub fn events_path(&self) -> &Path {
        &self.events_path
    }

    fn write_record(&mut self, payload: &[u8]) -> Result<(), MetricsError> {
        let length = (payload.len() as u64).to_le_bytes();
        let result = (|| {
            self.events.write_all(&length)?;
            self.events.write_all(&masked_crc32c(&length).to_le_bytes())?;
            self.events.write_all(payload)?;
            self.events.write_all(&masked_crc32c(payload).to_le_bytes())
        })();
        result.map_err(|source| MetricsError::Io { path: self.events_path.clone(), source })
    }

    /// Writes the scalars of one moment: one event, and one CSV row each.
    /// Non-finite values are written to the CSV but left out of the event file.
    pub fn write(&mut self, train_seconds: f64, env_steps: u64, scalars: &[(&str, f64)]) -> Result<(), MetricsError> {
        if scalars.is_empty() {
            return Ok(());
        }
        let wall_time = unix_now();
        let event = Event {
            wall_time,
            step: i64::try_from(env_steps).unwrap_or(i64::MAX),
            file_version: None,
            summary: Some(Summary {
                value: scalars
                    .iter()
                    .filter(|(_, v)| v.is_finite())
                    .map(|&(tag, value)| SummaryValue { tag: tag.to_string(), simple_value: Some(value as f32) })
                    .collect(),
            }),
        };
        self.write_record(&event.encode_to_vec())?;
        for (tag, value) in scalars {
            writeln!(self.csv, "{wall_time:.3},{train_seconds:.3},{env_steps},{tag},{value}")
                .map_err(|source| MetricsError::Io { path: self.csv_path.clone(), source })?;
        }
        Ok(())
    }

    /// Makes everything written so far visible to readers.
    pub fn flush(&mut self) -> Result<(), MetricsError> {
        self.events.flush().map_err(|source| MetricsError::Io { path: self.events_path.clone(), source })?;
        self.csv.flush().map_err(|source| MetricsError::Io { path: self.csv_path.clone(), source })
    }
}

/// Reads an event file, checking every length and CRC; returns its scalars
/// (`train_seconds` is 0: event files do not hold it).
pub fn read_events(path: &Path) -> Result<Vec<Scalar>, MetricsError> {
    let mut bytes = Vec::new();
    File::open(path)
        .and_then(|mut f| f.read_to_end(&mut bytes))
        .map_err(|source| MetricsError::Io { path: path.to_path_buf(), source })?;
    let corrupt = |offset: usize, problem: String| MetricsError::Corrupt {
        path: path.to_path_buf(),
        offset: offset as u64,
        problem,
    };
    let mut scalars = Vec::new();
    let mut offset = 0;
    let mut first = true;
    while offset < bytes.len() {
        let header = bytes.get(offset..offset + 12).ok_or_else(|| corrupt(offset, "truncated header".into()))?;
        let (length_bytes, length_crc) = header.split_at(8);
        if masked_crc32c(length_bytes).to_le_bytes() != length_crc {
            return Err(corrupt(offset, "length CRC mismatch".into()));
        }
        let mut length = [0u8; 8];
        length.copy_from_slice(length_bytes);
        let length = usize::try_from(u64::from_le_bytes(length)).map_err(|e| corrupt(offset, e.to_string()))?;
        let start = offset + 12;
        let end = start.checked_add(length).filter(|&e| e + 4 <= bytes.len());
        let Some(end) = end else { return Err(corrupt(offset, format!("truncated payload of {length} bytes"))) };
        let payload = &bytes[start..end];
        if masked_crc32c(payload).to_le_bytes() != bytes[end..end + 4] {
            return Err(corrupt(offset, "payload CRC mismatch".into()));
        }
        let event = Event::decode(payload).map_err(|e| corrupt(offset, format!("not an Event: {e}")))?;
        if first && event.file_version.as_deref() != Some("brain.Event:2") {
            return Err(corrupt(offset, "the first event does not name the file version brain.Event:2".into()));
        }
        first = false;
        for value in event.summary.into_iter().flat_map(|s| s.value) {
            if let Some(v) = value.simple_value {
                scalars.push(Scalar {
                    wall_time: event.wall_time,
                    train_seconds: 0.0,
                    env_steps: u64::try_from(event.step).unwrap_or(0),
                    tag: value.tag,
                    value: f64::from(v),
                });
            }
        }
        offset = end + 4;
    }
    Ok(scalars)
}

/// Reads `metrics.csv`.
pub fn read_csv(path: &Path) -> Result<Vec<Scalar>, MetricsError> {
    let text = std::fs::read_to_string(path).map_err(|source| MetricsError::Io { path: path.to_path_buf(), source })?;
    let mut scalars = Vec::new();
    for (index, line) in text.lines().enumerate().skip(1) {
        let bad =
            |problem: &str| MetricsError::Csv { path: path.to_path_buf(), line: index + 1, problem: problem.into() };
        if line.trim().is_empty() {
            continue;
        }
        let fields: Vec<&str> = line.split(',').collect();
        let [wall_time, train_seconds, env_steps, tag, value] = fields[..] else {
            return Err(bad("expected 5 fields: wall_time,train_seconds,env_steps,tag,value"));
        };
        scalars.push(Scalar {
            wall_time: wall_time.parse().map_err(|_| bad("wall_time is not a number"))?,
            train_seconds: train_seconds.parse().map_err(|_| bad("train_seconds is not a number"))?,
            env_steps: env_steps.parse().map_err(|_| bad("env_steps is not an integer"))?,
            tag: tag.to_string(),
            value: value.parse().map_err(|_| bad("value is not a number"))?,
        });
    }
    Ok(scalars)
}

/// The event files of a run directory, oldest first.
pub fn event_files(dir: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with("events.out.tfevents.")))
        .collect();
    files.sort();
    files
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc32c_matches_the_standard_check_value() {
        // The CRC-32C check value of "123456789" (RFC 3720, appendix B.4).
        assert_eq!(crc32c(b"123456789"), 0xE306_9283);
        assert_eq!(crc32c(b""), 0);
    }

    #[test]
    fn scalars_round_trip_through_events_and_csv() {
        let dir = tempfile::tempdir().unwrap();
        let mut writer = MetricsWriter::create(dir.path()).unwrap();
        writer.write(1.5, 100, &[("train/loss", 0.25), ("episode/speed", 0.0)]).unwrap();
        writer.write(2.5, 200, &[("train/loss", f64::NAN)]).unwrap();
        writer.flush().unwrap();
        let events = read_events(writer.events_path()).unwrap();
        let seen: Vec<(&str, u64, f64)> = events.iter().map(|s| (s.tag.as_str(), s.env_steps, s.value)).collect();
        assert_eq!(seen, vec![("train/loss", 100, 0.25), ("episode/speed", 100, 0.0)]);
        let csv = read_csv(&dir.path().join("metrics.csv")).unwrap();
        assert_eq!(csv.len(), 3);
        assert_eq!(csv[2].tag, "train/loss");
        assert!(csv[2].value.is_nan());
        assert!((csv[1].train_seconds - 1.5).abs() < 1e-9);
        assert_eq!(event_files(dir.path()), vec![writer.events_path().to_path_buf()]);

        // A second writer (a resumed run) appends to the CSV without a second header.
        drop(writer);
        let mut again = MetricsWriter::create(dir.path()).unwrap();
        again.write(3.0, 300, &[("train/loss", 0.5)]).unwrap();
        again.flush().unwrap();
        assert_eq!(read_csv(&dir.path().join("metrics.csv")).unwrap().len(), 4);
    }

    #[test]
    fn corrupt_event_files_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let mut writer = MetricsWriter::create(dir.path()).unwrap();
        writer.write(1.0, 1, &[("a", 1.0)]).unwrap();
        writer.flush().unwrap();
        let path = writer.events_path().to_path_buf();
        let mut bytes = std::fs::read(&path).unwrap();
        let last = bytes.len() - 6;
        bytes[last] ^= 0x40;
        std::fs::write(&path, &bytes).unwrap();
        let error = read_events(&path).unwrap_err().to_string();
        assert!(error.contains("payload CRC mismatch"), "{error}");
        std::fs::write(&path, &bytes[..bytes.len() - 2]).unwrap();
        let error = read_events(&path).unwrap_err().to_string();
        assert!(error.contains("truncated"), "{error}");
    }
}
