//! How much memory this machine has, to refuse sizes it cannot hold before anything starts.
//!
//! Read from `/proc/meminfo` (Linux) rather than through a system-information crate: it is one
//! line of one file, and elsewhere the check is skipped (None), never guessed.

/// Total physical memory in bytes, or None where it cannot be read.
pub fn total_bytes() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    parse_mem_total(&text)
}

fn parse_mem_total(meminfo: &str) -> Option<u64> {
    let line = meminfo.lines().find(|l| l.starts_with("MemTotal:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    kib.checked_mul(1024)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_mem_total() {
        assert_eq!(parse_mem_total("MemTotal:       24576000 kB\nMemFree: 1 kB\n"), Some(24_576_000 * 1024));
        assert_eq!(parse_mem_total("nothing here"), None);
    }
}
