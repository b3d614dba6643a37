//! Pictures: every plot the project draws goes through here so that text renders the same on every
//! machine, without a system font library.

use std::sync::Once;

/// DejaVu Sans, bundled so plots need no fontconfig (licence in `host/assets/fonts/`).
const DEJAVU_SANS: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");

static REGISTER: Once = Once::new();

/// Registers the bundled font as plotters' `sans-serif` family. Call before drawing any text;
/// calling it again is free.
pub fn register_font() {
    REGISTER.call_once(|| {
        // The font is compiled in and known to be valid; a failure here would be a build defect,
        // and plotters then falls back to drawing no text rather than failing.
        let _ = plotters::style::register_font(
            "sans-serif",
            plotters::style::FontStyle::Normal,
            DEJAVU_SANS,
        );
    });
}
