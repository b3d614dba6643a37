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
