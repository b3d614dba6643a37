//! Small facts about the running process, for reports.

/// Peak resident set size of this process (`VmHWM` of `/proc/self/status`), MiB; `None` where
/// the kernel does not say (not Linux).
pub fn peak_rss_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

/// CPU time (user + system) of this process so far, seconds, from `/proc/self/stat` (clock ticks
/// of 1/100 s, the Linux default `USER_HZ`); `None` where the kernel does not say.
pub fn cpu_seconds() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the command name (in parentheses, which may hold spaces): utime is the 14th
    // field of the line, stime the 15th.
    let rest = &s[s.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let utime: f64 = f.get(11)?.parse().ok()?;
    let stime: f64 = f.get(12)?.parse().ok()?;
    Some((utime + stime) / 100.0)
}

/// Defines a private `StepContext` trait for `Result`s whose `step(|| what)` wraps any error
/// convertible into `$error` in its `Step { what, source }` variant, naming the step that
/// failed as `anyhow::Context` does in the binary: one definition for the library's step-wise
/// procedures (the demo, `fit_scan`, calibration, `bench tradeoff`).
macro_rules! step_context {
    ($error:ident) => {
        /// Names the step that failed, as `anyhow::Context` does in the binary.
        trait StepContext<T> {
            fn step(self, what: impl FnOnce() -> String) -> Result<T, $error>;
        }

        impl<T, E: Into<$error>> StepContext<T> for Result<T, E> {
            fn step(self, what: impl FnOnce() -> String) -> Result<T, $error> {
                self.map_err(|e| $error::Step {
                    what: what(),
                    source: Box::new(e.into()),
                })
            }
        }
    };
}
pub(crate) use step_context;
