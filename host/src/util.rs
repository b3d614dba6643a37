//! Small facts about the running process, for reports.

/// Peak resident set size of this process (`VmHWM` of `/proc/self/status`), MiB; `None` where
/// the kernel does not say (not Linux).
pub fn peak_rss_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}
