//! The library's progress reports ([`subsurf::progress::Progress`]) drawn as an `indicatif` bar:
//! the only place the binary's progress display meets the library.
//!
//! When stderr is not a terminal (a batch job, a pipe, CI), `indicatif` draws nothing, and a long
//! fit used to print nothing for minutes (issue 40: a 650,000-vertex mesh, 20 minutes of
//! silence). There the bar becomes plain lines on stderr: one per stage as it starts, a count at
//! most every [`PLAIN_EVERY`], and every `println` line.
use std::io::IsTerminal;
use std::sync::Mutex;
use std::time::{Duration, Instant};
use subsurf::progress::{Progress, Stages};

/// Least time between two count lines of one stage in plain mode.
const PLAIN_EVERY: Duration = Duration::from_secs(10);

/// An `indicatif` bar as the library's progress receiver (dereferences to the bar for styling
/// and finishing).
pub struct Bar(pub indicatif::ProgressBar, Option<Plain>);

/// Plain lines for a stderr that is no terminal.
struct Plain {
    started: Instant,
    state: Mutex<PlainState>,
}

#[derive(Default)]
struct PlainState {
    stage: String,
    len: u64,
    pos: u64,
    last: Option<Instant>,
}

impl Plain {
    /// `None` when stderr is a terminal (the bar draws) or the bar is hidden on purpose.
    fn for_stderr(hidden: bool) -> Option<Plain> {
        (!hidden && !std::io::stderr().is_terminal()).then(|| Plain {
            started: Instant::now(),
            state: Mutex::new(PlainState::default()),
        })
    }

    fn line(&self, s: &PlainState) {
        let t = self.started.elapsed().as_secs_f64();
        if s.len > 0 {
            eprintln!("[{t:7.1} s] {} {}/{}", s.stage, s.pos, s.len);
        } else {
            eprintln!("[{t:7.1} s] {}", s.stage);
        }
    }

    fn with(&self, f: impl FnOnce(&mut PlainState) -> bool) {
        let Ok(mut s) = self.state.lock() else {
            return;
        };
        if f(&mut s) {
            s.last = Some(Instant::now());
            self.line(&s);
        }
    }
}

impl Bar {
    /// A bar from `bar` (plain lines instead when stderr is no terminal).
    pub fn new(bar: indicatif::ProgressBar) -> Bar {
        Bar(bar, Plain::for_stderr(false))
    }

    /// A bar drawn with `template` (the default style if the template is invalid).
    pub fn with_template(template: &str) -> Bar {
        let style = indicatif::ProgressStyle::with_template(template)
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar());
        Bar::new(indicatif::ProgressBar::new(0).with_style(style))
    }

    /// A bar that draws nothing (`--quiet`): no plain lines either.
    pub fn hidden() -> Bar {
        Bar(indicatif::ProgressBar::hidden(), Plain::for_stderr(true))
    }
}

impl std::ops::Deref for Bar {
    type Target = indicatif::ProgressBar;
    fn deref(&self) -> &indicatif::ProgressBar {
        &self.0
    }
}

impl Progress for Bar {
    fn set_message(&self, msg: &str) {
        self.0.set_message(msg.to_string());
        if let Some(p) = &self.1 {
            p.with(|s| {
                let new = s.stage != msg;
                if new {
                    s.stage = msg.to_string();
                    s.pos = 0;
                    s.len = 0;
                }
                new
            });
        }
    }
    fn set_length(&self, len: u64) {
        self.0.set_length(len);
        if let Some(p) = &self.1 {
            p.with(|s| {
                s.len = len;
                false
            });
        }
    }
    fn set_position(&self, pos: u64) {
        self.0.set_position(pos);
        if let Some(p) = &self.1 {
            p.with(|s| {
                s.pos = pos;
                false
            });
        }
    }
    fn inc(&self, n: u64) {
        self.0.inc(n);
        if let Some(p) = &self.1 {
            p.with(|s| {
                s.pos = s.pos.saturating_add(n);
                let due = s.last.is_none_or(|t| t.elapsed() >= PLAIN_EVERY);
                due || (s.len > 0 && s.pos == s.len)
            });
        }
    }
    fn start(&self, msg: &str, len: u64) {
        self.0.set_message(msg.to_string());
        self.0.set_length(len);
        self.0.set_position(0);
        if let Some(p) = &self.1 {
            p.with(|s| {
                s.stage = msg.to_string();
                s.len = len;
                s.pos = 0;
                true
            });
        }
    }
    fn println(&self, line: &str) {
        match &self.1 {
            // A bar that draws nothing prints nothing either.
            Some(_) => eprintln!("{line}"),
            None => self.0.println(line),
        }
    }
}

/// One bar per stage drawn with the template it holds, cleared when the stage ends; the
/// library's lines printed on stdout, its warnings on stderr (`subsurf demo`, `bench tradeoff`,
/// `fit`).
pub struct StageBars(pub &'static str);

impl Stages for StageBars {
    type Bar = Bar;
    fn stage(&self, len: u64, msg: &str) -> Bar {
        let p = Bar::with_template(self.0);
        // The bar's own length and name (no plain line yet: the stage's work reports that).
        p.0.set_length(len);
        p.0.set_message(msg.to_string());
        p
    }
    fn finish(&self, bar: Bar) {
        bar.finish_and_clear();
    }
    fn say(&self, line: &str) {
        println!("{line}");
    }
    fn warn(&self, line: &str) {
        eprintln!("{line}");
    }
}
