//! Progress of long work, as the library reports it: a small trait with no-op defaults.
//!
//! The library never draws anything: it says what it is doing and how far it got; the binary
//! decides how to show it (an `indicatif` bar). `()` is the silent implementation (tests, batch
//! runs, nested calls).

/// Receives progress reports. Every method defaults to doing nothing; implementations must be
/// cheap and thread-safe (stages report from worker threads).
pub trait Progress: Sync {
    /// Names the current step (e.g. `registration`, `fit (round 2)`).
    fn set_message(&self, _msg: &str) {}
    /// The number of units of the current step.
    fn set_length(&self, _len: u64) {}
    /// Units of the current step already done.
    fn set_position(&self, _pos: u64) {}
    /// `n` more units done.
    fn inc(&self, _n: u64) {}
    /// A line for the user, shown without disturbing the progress display.
    fn println(&self, _line: &str) {}
    /// Starts a step: its name and length, position 0.
    fn start(&self, msg: &str, len: u64) {
        self.set_message(msg);
        self.set_length(len);
        self.set_position(0);
    }
}

/// Silent progress.
impl Progress for () {}

/// Long work of several stages shown one progress display per stage (`subsurf demo`, `bench
/// tradeoff`, `fit`): each stage gets its own receiver, whose display goes when the stage ends,
/// and lines for the user go where the binary prints them.
pub trait Stages {
    /// The progress receiver of one stage.
    type Bar: Progress;
    /// A new stage of `len` units (0: unknown) named `msg`.
    fn stage(&self, len: u64, msg: &str) -> Self::Bar;
    /// The stage is over: its display goes.
    fn finish(&self, _bar: Self::Bar) {}
    /// A line for the user (stdout in the binary); nothing by default.
    fn say(&self, _line: &str) {}
    /// A warning for the user (stderr in the binary); nothing by default.
    fn warn(&self, _line: &str) {}
}

/// Silent stages.
impl Stages for () {
    type Bar = ();
    fn stage(&self, _len: u64, _msg: &str) {}
}

/// How much a progress display says off a terminal.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verbosity {
    /// No progress at all; results and warnings only (`--quiet`).
    Quiet,
    /// One line per stage when it ends, with its time, and a line every [`HEARTBEAT`] while a
    /// stage runs long.
    Normal,
    /// As `Normal`, and each stage's start and its count every [`VERBOSE_EVERY`] (`--verbose`).
    Verbose,
}

/// Least time between two "still running" lines of one stage off a terminal: a fit of a large
/// mesh can spend minutes in one stage, and a batch log should not fall silent for that long.
pub const HEARTBEAT: std::time::Duration = std::time::Duration::from_secs(60);
/// Least time between two count lines of one stage with [`Verbosity::Verbose`].
pub const VERBOSE_EVERY: std::time::Duration = std::time::Duration::from_secs(10);

/// Progress as plain lines, for a display that cannot redraw (a pipe, a log file, CI): where a
/// bar would redraw on every update, each stage says once, when it ends, what it did and how
/// long it took (`[   12.3 s] fit 98/98 in 4.1 s`). The lines go to the sink it was made with.
pub struct Lines {
    started: std::time::Instant,
    verbosity: Verbosity,
    /// Whether a stage's end is said (not when an enclosing stage says its own).
    ends: bool,
    sink: Box<dyn Fn(&str) + Send + Sync>,
    state: std::sync::Mutex<LineState>,
}

struct LineState {
    stage: String,
    len: u64,
    pos: u64,
    since: std::time::Instant,
    last: std::time::Instant,
    open: bool,
}

impl Lines {
    /// Lines at `verbosity` into `sink`; `ends`: whether each stage's end is said (with
    /// [`Verbosity::Verbose`] always).
    pub fn new(
        verbosity: Verbosity,
        ends: bool,
        sink: impl Fn(&str) + Send + Sync + 'static,
    ) -> Lines {
        let now = std::time::Instant::now();
        Lines {
            started: now,
            verbosity,
            ends: ends || verbosity == Verbosity::Verbose,
            sink: Box::new(sink),
            state: std::sync::Mutex::new(LineState {
                stage: String::new(),
                len: 0,
                pos: 0,
                since: now,
                last: now,
                open: false,
            }),
        }
    }

    fn say(&self, s: &LineState, tail: &str) {
        if self.verbosity == Verbosity::Quiet || s.stage.is_empty() {
            return;
        }
        let count = if s.len > 0 {
            format!(" {}/{}", s.pos, s.len)
        } else {
            String::new()
        };
        let t = self.started.elapsed().as_secs_f64();
        (self.sink)(&format!("[{t:7.1} s] {}{count}{tail}", s.stage));
    }

    fn with(&self, f: impl FnOnce(&mut LineState)) {
        if let Ok(mut s) = self.state.lock() {
            f(&mut s);
        }
    }

    fn close(&self, s: &mut LineState) {
        if s.open && self.ends {
            let dt = s.since.elapsed().as_secs_f64();
            self.say(s, &format!(" in {dt:.1} s"));
        }
        s.open = false;
    }

    fn begin(&self, s: &mut LineState, stage: &str, len: u64) {
        self.close(s);
        let now = std::time::Instant::now();
        (s.stage, s.len, s.pos, s.since, s.last, s.open) =
            (stage.to_string(), len, 0, now, now, true);
        if self.verbosity == Verbosity::Verbose {
            self.say(s, " ...");
        }
    }

    fn tick(&self, s: &mut LineState) {
        let every = match self.verbosity {
            Verbosity::Verbose => VERBOSE_EVERY,
            _ => HEARTBEAT,
        };
        if s.open && s.last.elapsed() >= every {
            s.last = std::time::Instant::now();
            self.say(s, " ...");
        }
    }

    /// The current stage is over: its line, if not said yet.
    pub fn finish(&self) {
        self.with(|s| self.close(s));
    }
}

impl Progress for Lines {
    fn set_message(&self, msg: &str) {
        self.with(|s| {
            if s.stage != msg {
                self.begin(s, msg, 0);
            }
        });
    }
    fn set_length(&self, len: u64) {
        self.with(|s| s.len = len);
    }
    fn set_position(&self, pos: u64) {
        self.with(|s| {
            s.pos = pos;
            self.tick(s);
        });
    }
    fn inc(&self, n: u64) {
        self.with(|s| {
            s.pos = s.pos.saturating_add(n);
            self.tick(s);
        });
    }
    fn println(&self, line: &str) {
        if self.verbosity != Verbosity::Quiet {
            (self.sink)(line);
        }
    }
    fn start(&self, msg: &str, len: u64) {
        self.with(|s| self.begin(s, msg, len));
    }
}

impl Drop for Lines {
    fn drop(&mut self) {
        self.finish();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::{Arc, Mutex};

    fn collect(v: Verbosity, ends: bool) -> (Lines, Arc<Mutex<Vec<String>>>) {
        let got = Arc::new(Mutex::new(Vec::new()));
        let sink = got.clone();
        let lines = Lines::new(v, ends, move |l| sink.lock().unwrap().push(l.to_string()));
        (lines, got)
    }

    /// Work of two stages, each counting 98 units one at a time.
    fn work(p: &impl Progress) {
        for stage in ["evaluate", "fit"] {
            p.start(stage, 98);
            for _ in 0..98 {
                p.inc(1);
            }
        }
    }

    #[test]
    fn each_stage_says_one_line_when_it_ends() {
        let (lines, got) = collect(Verbosity::Normal, true);
        work(&lines);
        drop(lines);
        let got = got.lock().unwrap();
        assert_eq!(got.len(), 2, "{got:?}");
        assert!(
            got[0].contains("evaluate 98/98 in ") && got[0].ends_with(" s"),
            "{got:?}"
        );
        assert!(got[1].contains("fit 98/98 in "), "{got:?}");
    }

    #[test]
    fn quiet_says_nothing_and_verbose_says_each_start() {
        let (lines, got) = collect(Verbosity::Quiet, true);
        work(&lines);
        lines.println("a line");
        drop(lines);
        assert!(got.lock().unwrap().is_empty());
        let (lines, got) = collect(Verbosity::Verbose, false);
        work(&lines);
        drop(lines);
        let got = got.lock().unwrap();
        assert_eq!(got.len(), 4, "{got:?}");
        assert!(got[0].ends_with("evaluate 0/98 ..."), "{got:?}");
    }

    #[test]
    fn within_a_stage_that_says_its_own_end_steps_are_silent() {
        let (lines, got) = collect(Verbosity::Normal, false);
        work(&lines);
        drop(lines);
        assert!(got.lock().unwrap().is_empty());
    }
}
