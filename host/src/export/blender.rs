//! Running Blender on an export folder: its `build_blend.py` writes the `.blend` and, asked to,
//! renders the scene in Cycles into a linear EXR, which comes back as a [`crate::render::Image`]
//! (coverage from its alpha) to compare with the renderer's own picture.

use std::path::{Path, PathBuf};
use std::process::Command;

use super::{BUILD_SCRIPT, ExportError};
use crate::render::Image;

/// The environment variable naming the Blender executable to use.
pub const BLENDER_ENV: &str = "SUBSURF_BLENDER";

/// The oldest Blender whose Cycles the export was written against (its kernel's subsurface
/// code is `export::cycles`'s reading).
pub const MIN_VERSION: (u32, u32) = (3, 4);

/// A Blender executable and its version.
#[derive(Clone, Debug, PartialEq)]
pub struct Blender {
    /// The executable.
    pub path: PathBuf,
    /// `(major, minor)` from `blender --version`.
    pub version: (u32, u32),
    /// The version line as Blender prints it.
    pub version_line: String,
}

/// `explicit`, else `$SUBSURF_BLENDER`, else `blender` on the `PATH`; `None` when there is none
/// (the caller decides whether that is an error: the export works without Blender).
pub fn find_blender(explicit: Option<&Path>) -> Result<Option<Blender>, ExportError> {
    let candidate = explicit
        .map(Path::to_path_buf)
        .or_else(|| std::env::var_os(BLENDER_ENV).map(PathBuf::from))
        .or_else(|| {
            std::env::var_os("PATH").and_then(|paths| {
                std::env::split_paths(&paths)
                    .map(|d| d.join("blender"))
                    .find(|p| p.is_file())
            })
        });
    let Some(path) = candidate else {
        return Ok(None);
    };
    let out = Command::new(&path)
        .args(["-b", "--factory-startup", "--version"])
        .output()
        .map_err(|e| ExportError::Blender(format!("running {}: {e}", path.display())))?;
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text
        .lines()
        .find(|l| l.trim_start().starts_with("Blender "))
        .ok_or_else(|| {
            ExportError::Blender(format!(
                "{} --version printed no `Blender X.Y` line",
                path.display()
            ))
        })?
        .trim()
        .to_string();
    let version = parse_version(&line)
        .ok_or_else(|| ExportError::Blender(format!("cannot read a version from `{line}`")))?;
    if version < MIN_VERSION {
        return Err(ExportError::Blender(format!(
            "{line} is older than Blender {}.{}, whose Cycles the export targets",
            MIN_VERSION.0, MIN_VERSION.1
        )));
    }
    Ok(Some(Blender {
        path,
        version,
        version_line: line,
    }))
}

fn parse_version(line: &str) -> Option<(u32, u32)> {
    let v = line.split_whitespace().nth(1)?;
    let mut it = v.split('.');
    Some((it.next()?.parse().ok()?, it.next()?.parse().ok()?))
}

/// What one run of `build_blend.py` should do besides writing the `.blend`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Run {
    /// Render the scene into this EXR.
    pub render: Option<PathBuf>,
    /// Samples per pixel (the scene's when `None`).
    pub samples: Option<u32>,
    /// Render as the subsurf renderer draws (point-sampled pixels, no bounced light).
    pub compare: bool,
    /// Render threads (0: all cores).
    pub threads: usize,
    /// Cycles' seed.
    pub seed: u32,
    /// Build and render the scene of this scan frame (`frames.json`, [`super::frames`])
    /// instead of `scene.json`'s.
    pub frame: Option<usize>,
}

impl Blender {
    /// Runs the export folder's build script: writes its `.blend` and, with `run.render`, the
    /// Cycles render. Blender's own output goes into `blender.log` in the folder.
    pub fn run(&self, dir: &Path, run: &Run) -> Result<(), ExportError> {
        let script = dir.join(BUILD_SCRIPT);
        let mut cmd = Command::new(&self.path);
        cmd.args([
            "-b",
            "--factory-startup",
            "--python-exit-code",
            "1",
            "--python",
        ])
        .arg(&script)
        .arg("--")
        .arg("--dir")
        .arg(dir);
        if let Some(exr) = &run.render {
            cmd.arg("--render").arg(exr);
        }
        if let Some(s) = run.samples {
            cmd.args(["--samples", &s.to_string()]);
        }
        if run.compare {
            cmd.arg("--compare");
        }
        cmd.args(["--threads", &run.threads.to_string()]);
        cmd.args(["--seed", &run.seed.to_string()]);
        if let Some(k) = run.frame {
            cmd.args(["--frame", &k.to_string()]);
        }
        let out = cmd
            .output()
            .map_err(|e| ExportError::Blender(format!("running {}: {e}", self.path.display())))?;
        let log = dir.join("blender.log");
        let mut text = out.stdout.clone();
        text.extend_from_slice(&out.stderr);
        std::fs::write(&log, &text).map_err(|e| ExportError::io(&log, e))?;
        let printed = String::from_utf8_lossy(&text);
        let rendered = run
            .render
            .as_ref()
            .is_none_or(|_| printed.contains("SUBSURF rendered"));
        if !out.status.success() || !printed.contains("SUBSURF wrote") || !rendered {
            let tail: Vec<&str> = printed.lines().rev().take(12).collect();
            return Err(ExportError::Blender(format!(
                "{} failed ({}); see {}:\n{}",
                self.version_line,
                out.status,
                log.display(),
                tail.into_iter().rev().collect::<Vec<_>>().join("\n")
            )));
        }
        Ok(())
    }
}

/// A Cycles render read back: linear radiance, covered where its alpha is at least ½.
pub fn read_render(path: &Path) -> Result<Image, ExportError> {
    let (img, alpha) = crate::dataset::read_exr_with_alpha(path).map_err(ExportError::Image)?;
    if img.channels != 3 {
        return Err(ExportError::Blender(format!(
            "{}: {} channels, expected R, G, B",
            path.display(),
            img.channels
        )));
    }
    let n = img.width * img.height;
    let pixels: Vec<[f32; 3]> = img
        .data
        .chunks_exact(3)
        .map(|p| [p[0], p[1], p[2]])
        .collect();
    let covered = match alpha {
        Some(a) => a.iter().map(|&x| x >= 0.5).collect(),
        None => pixels.iter().map(|p| p.iter().any(|&v| v > 0.0)).collect(),
    };
    if pixels.iter().flatten().any(|v| !v.is_finite()) {
        return Err(ExportError::Blender(format!(
            "{}: the render has non-finite pixels",
            path.display()
        )));
    }
    debug_assert_eq!(pixels.len(), n);
    Ok(Image {
        width: img.width as u32,
        height: img.height as u32,
        pixels,
        covered,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn versions_parse() {
        assert_eq!(parse_version("Blender 3.4.1"), Some((3, 4)));
        assert_eq!(parse_version("Blender 4.2.0 LTS"), Some((4, 2)));
        assert_eq!(parse_version("Blender"), None);
    }

    /// A missing executable is an error naming it, not a panic.
    #[test]
    fn a_missing_blender_is_an_error() {
        let e = find_blender(Some(Path::new("/nonexistent/blender"))).unwrap_err();
        assert!(e.to_string().contains("/nonexistent/blender"), "{e}");
    }
}
