//! Set-up shared by the render test files (`mod render_common;` in each).

use std::path::Path;

use subsurf::render::image_stats;

/// A picture someone can look at: it decodes, has the right size, many colours, real contrast.
pub fn assert_picture(path: &Path, width: u32, height: u32) {
    let s = image_stats(path).unwrap_or_else(|e| panic!("{} does not decode: {e}", path.display()));
    assert_eq!((s.width, s.height), (width, height), "{}", path.display());
    assert!(
        s.distinct_colours > 20,
        "{}: only {} colours",
        path.display(),
        s.distinct_colours
    );
    assert!(
        s.luma_std > 5.0,
        "{}: flat (luma std {})",
        path.display(),
        s.luma_std
    );
}
