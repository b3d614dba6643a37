//! The library's progress reports ([`subsurf::progress::Progress`]) shown to a person: an
//! `indicatif` bar when stderr is a terminal, the library's plain [`Lines`] when it is not (a
//! pipe, a log file, CI: one line per stage when it ends). The only place the binary's progress
//! display meets the library.
use std::io::IsTerminal;
use std::sync::atomic::{AtomicU8, Ordering};
use std::time::Instant;
use subsurf::progress::{Lines, Progress, Stages, Verbosity};

static VERBOSITY: AtomicU8 = AtomicU8::new(1);

/// Sets the verbosity of every display (from `--quiet` and `--verbose`).
pub fn set_verbosity(v: Verbosity) {
    VERBOSITY.store(v as u8, Ordering::Relaxed);
}

fn verbosity() -> Verbosity {
    match VERBOSITY.load(Ordering::Relaxed) {
        0 => Verbosity::Quiet,
        1 => Verbosity::Normal,
        _ => Verbosity::Verbose,
    }
}

/// Whether progress is shown as lines: stderr is no terminal and progress is not off.
fn as_lines() -> bool {
    verbosity() != Verbosity::Quiet && !std::io::stderr().is_terminal()
}

/// An `indicatif` bar as the library's progress receiver (dereferences to the bar for styling);
/// off a terminal the bar draws nothing and the stages' lines go to stderr.
pub struct Bar(
    pub indicatif::ProgressBar,
    Option<Lines>,
    Option<(String, Instant)>,
);

impl Bar {
    /// A bar from `bar` (lines instead when stderr is no terminal; nothing with `--quiet`).
    pub fn new(bar: indicatif::ProgressBar) -> Bar {
        Bar::with_lines(bar, true)
    }

    /// `ends`: whether off a terminal each step says its end (not where its stage says its own).
    fn with_lines(bar: indicatif::ProgressBar, ends: bool) -> Bar {
        match verbosity() {
            Verbosity::Quiet => Bar::hidden(),
            v => Bar(
                bar,
                as_lines().then(|| Lines::new(v, ends, |l| eprintln!("{l}"))),
                None,
            ),
        }
    }

    /// A bar drawn with `template` (the default style if the template is invalid).
    pub fn with_template(template: &str) -> Bar {
        Bar::new(styled(template))
    }

    /// A bar that draws nothing: no lines either.
    pub fn hidden() -> Bar {
        Bar(indicatif::ProgressBar::hidden(), None, None)
    }

    /// Ends the display: the bar goes; off a terminal the current step's line.
    pub fn finish_and_clear(&self) {
        if let Some(l) = &self.1 {
            l.finish();
        }
        self.0.finish_and_clear();
    }
}

fn styled(template: &str) -> indicatif::ProgressBar {
    let style = indicatif::ProgressStyle::with_template(template)
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar());
    indicatif::ProgressBar::new(0).with_style(style)
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
        self.1.as_ref().inspect(|l| l.set_message(msg));
    }
    fn set_length(&self, len: u64) {
        self.0.set_length(len);
        self.1.as_ref().inspect(|l| l.set_length(len));
    }
    fn set_position(&self, pos: u64) {
        self.0.set_position(pos);
        self.1.as_ref().inspect(|l| l.set_position(pos));
    }
    fn inc(&self, n: u64) {
        self.0.inc(n);
        self.1.as_ref().inspect(|l| l.inc(n));
    }
    fn start(&self, msg: &str, len: u64) {
        self.0.set_message(msg.to_string());
        self.0.set_length(len);
        self.0.set_position(0);
        self.1.as_ref().inspect(|l| l.start(msg, len));
    }
    fn println(&self, line: &str) {
        match &self.1 {
            Some(l) => l.println(line),
            None if verbosity() == Verbosity::Quiet => {}
            None => self.0.println(line),
        }
    }
}

/// One bar per stage drawn with the template it holds, cleared when the stage ends; off a
/// terminal one line per stage when it ends, with its time. The library's lines are printed on
/// stdout, its warnings on stderr (`subsurf demo`, `bench tradeoff`, `fit`).
pub struct StageBars(pub &'static str);

impl Stages for StageBars {
    type Bar = Bar;
    fn stage(&self, len: u64, msg: &str) -> Bar {
        // Off a terminal a named stage says its end, the steps within it only with --verbose;
        // an unnamed one (a whole `subsurf fit`) is its steps, and each says its end.
        let mut bar = Bar::with_lines(styled(self.0), msg.is_empty());
        bar.0.set_length(len);
        bar.0.set_message(msg.to_string());
        bar.2 = (!msg.is_empty()).then(|| (msg.to_string(), Instant::now()));
        bar
    }
    fn finish(&self, bar: Bar) {
        bar.finish_and_clear();
        if let (Some((name, since)), true) = (&bar.2, as_lines()) {
            eprintln!("{name} in {:.1} s", since.elapsed().as_secs_f64());
        }
    }
    fn say(&self, line: &str) {
        println!("{line}");
    }
    fn warn(&self, line: &str) {
        eprintln!("{line}");
    }
}
