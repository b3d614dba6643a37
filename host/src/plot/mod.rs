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

mod alignment;
mod curves;
mod difference;
mod figures;
mod surface;

pub use alignment::alignment_picture;
pub use curves::{
    Curve, LearningCurve, TradeoffPoint, falloff_plot, learning_curves, pareto_front, pareto_plot,
    tradeoff_curve,
};
pub use difference::{Compared, DifferenceStats, difference_picture, difference_picture_of};
pub use figures::{ERROR_MAP_TITLE, FalloffSummary, error_maps, falloff_figure};
pub use surface::{
    MeshView, Panel, PanelData, STATUS_LEGEND, front_and_back, model_viewer, surface_panels,
    surface_picture_size, viridis,
};

/// Why a picture could not be drawn.
#[non_exhaustive]
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// The data has nothing to show (no finite, positive values on a log axis, no vertices…).
    #[error("nothing to plot: {0}")]
    Empty(String),
    /// The drawing backend failed (usually writing the file).
    #[error("drawing {path}: {message}")]
    Draw {
        /// The file being drawn.
        path: std::path::PathBuf,
        /// The backend's message.
        message: String,
    },
    /// Rendering the mesh for a surface map failed.
    #[error(transparent)]
    Render(#[from] crate::render::RenderError),
}

pub(crate) fn draw_err<E: std::fmt::Display>(
    path: &std::path::Path,
) -> impl Fn(E) -> PlotError + '_ {
    move |e| PlotError::Draw {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}
