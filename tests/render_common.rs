//! Set-up shared by the render test files (`mod render_common;` in each; not every file uses
//! every helper).
#![allow(dead_code)]

use std::path::Path;
use std::process::Command;

use subsurf::modelfile::ModelFile;
use subsurf::render::{self, Camera, image_stats};

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

/// The `subsurf` binary under test, ready for arguments.
pub fn subsurf() -> Command {
    Command::new(env!("CARGO_BIN_EXE_subsurf"))
}

/// Runs `cmd`, which must succeed; returns its standard output.
pub fn ok(cmd: &mut Command) -> String {
    let o = cmd.output().expect("run subsurf");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// Runs `cmd`, which must fail with an error rather than a panic; returns its standard error.
pub fn fails(cmd: &mut Command) -> String {
    let o = cmd.output().expect("run subsurf");
    assert!(
        !o.status.success(),
        "{}",
        String::from_utf8_lossy(&o.stdout)
    );
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(!err.contains("panicked"), "{err}");
    err
}

/// A camera framing `model` from the default view.
pub fn framed(model: &ModelFile, width: u32, height: u32) -> Camera {
    let (lo, hi) = model.bounds();
    Camera::framing(lo, hi, render::DEFAULT_VIEW, width, height).expect("camera")
}
