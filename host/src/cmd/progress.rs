//! The library's progress reports ([`subsurf::progress::Progress`]) drawn as an `indicatif` bar:
//! the only place the binary's progress display meets the library.
use subsurf::progress::Progress;

/// An `indicatif` bar as the library's progress receiver (dereferences to the bar for styling
/// and finishing).
pub struct Bar(pub indicatif::ProgressBar);

impl Bar {
    /// A bar drawn with `template` (the default style if the template is invalid).
    pub fn with_template(template: &str) -> Bar {
        let style = indicatif::ProgressStyle::with_template(template)
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar());
        Bar(indicatif::ProgressBar::new(0).with_style(style))
    }

    /// A bar that draws nothing.
    pub fn hidden() -> Bar {
        Bar(indicatif::ProgressBar::hidden())
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
    }
    fn set_length(&self, len: u64) {
        self.0.set_length(len);
    }
    fn set_position(&self, pos: u64) {
        self.0.set_position(pos);
    }
    fn inc(&self, n: u64) {
        self.0.inc(n);
    }
    fn println(&self, line: &str) {
        self.0.println(line);
    }
}
