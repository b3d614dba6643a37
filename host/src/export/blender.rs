//! Running Blender on an export folder: its `build_blend.py` writes the `.blend` and, asked to,
//! renders the scene in Cycles into a linear EXR, which comes back as a [`crate::render::Image`]
//! (coverage from its alpha) to compare with the renderer's own picture.

use std::path::{Path, PathBuf};
use std::process::Command;

use super::{BUILD_SCRIPT, ExportError};
use crate::progress::Progress;
use crate::render::Image;

/// The environment variable naming the Blender executable to use.
pub const BLENDER_ENV: &str = "SUBSURF_BLENDER";

/// The environment variable giving Blender's render threads when a [`Run`] asks for none
/// (`threads: 0`): unset or 0, Blender's own default (all cores). A machine shared with other
/// work (benchmarks, CI runners) limits Cycles with it, as Blender's `-t N` does by hand.
pub const THREADS_ENV: &str = "SUBSURF_BLENDER_THREADS";

/// The render threads a run uses: `requested` when it is not 0, else [`THREADS_ENV`] (0 when
/// unset: Blender's default). A value that is not a count is an error naming the variable,
/// rather than a silently unlimited render.
pub fn render_threads(requested: usize) -> Result<usize, ExportError> {
    if requested > 0 {
        return Ok(requested);
    }
    match std::env::var(THREADS_ENV) {
        Err(std::env::VarError::NotPresent) => Ok(0),
        Ok(v) => parse_threads(&v),
        Err(e) => Err(ExportError::Blender(format!("{THREADS_ENV}: {e}"))),
    }
}

/// [`THREADS_ENV`]'s value as a thread count (empty: 0, Blender's default).
fn parse_threads(v: &str) -> Result<usize, ExportError> {
    if v.trim().is_empty() {
        return Ok(0);
    }
    v.trim()
        .parse()
        .map_err(|_| ExportError::Blender(format!("{THREADS_ENV}={v:?} is not a thread count")))
}

/// The oldest Blender whose Cycles the export was written against (its kernel's subsurface
/// code is `export::cycles`'s reading).
pub const MIN_VERSION: (u32, u32) = (3, 4);

/// How a [`Blender`] runs a script.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Kind {
    /// A Blender executable: `blender -b --factory-startup --python script -- …`.
    #[default]
    Binary,
    /// A Python that imports `bpy` (the `bpy` module from PyPI): `python script -- …`.
    Python,
}

/// A Blender executable (or a Python with the `bpy` module) and its version.
#[derive(Clone, Debug, PartialEq)]
pub struct Blender {
    /// The executable.
    pub path: PathBuf,
    /// Blender itself or a Python importing `bpy`.
    pub kind: Kind,
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
    let (kind, line) = version_line(&path)?;
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
        kind,
        version,
        version_line: line,
    }))
}

/// Asks `path` for its version: as Blender (`-b --factory-startup --version`), else as a Python
/// importing `bpy` (which prints `Blender X.Y.Z` from `bpy.app.version_string`).
fn version_line(path: &Path) -> Result<(Kind, String), ExportError> {
    let first_line = |out: &std::process::Output| {
        String::from_utf8_lossy(&out.stdout)
            .lines()
            .find(|l| l.trim_start().starts_with("Blender "))
            .map(|l| l.trim().to_string())
    };
    let running =
        |e: std::io::Error| ExportError::Blender(format!("running {}: {e}", path.display()));
    let out = Command::new(path)
        .args(["-b", "--factory-startup", "--version"])
        .output()
        .map_err(running)?;
    if let Some(line) = first_line(&out) {
        return Ok((Kind::Binary, line));
    }
    let out = Command::new(path)
        .args(["-c", "import bpy; print('Blender', bpy.app.version_string)"])
        .output()
        .map_err(running)?;
    first_line(&out).map(|l| (Kind::Python, l)).ok_or_else(|| {
        ExportError::Blender(format!(
            "{} is neither Blender (--version printed no `Blender X.Y` line) nor a Python \
             that imports bpy: {}",
            path.display(),
            String::from_utf8_lossy(&out.stderr)
                .lines()
                .last()
                .unwrap_or("")
        ))
    })
}

/// The newest usable Blender among `$SUBSURF_BLENDER`, `blender` on the `PATH` and the
/// Pythons on the `PATH` (`python3`, `python`) that import `bpy`; `None` when there is none.
/// A candidate that is not a Blender is passed over; when none is usable, the first error.
pub fn find_newest_blender() -> Result<Option<Blender>, ExportError> {
    // (candidate, whether it must be a Blender: a Python without bpy is merely passed over).
    let mut candidates: Vec<(PathBuf, bool)> = std::env::var_os(BLENDER_ENV)
        .map(|p| (PathBuf::from(p), true))
        .into_iter()
        .collect();
    if let Some(paths) = std::env::var_os("PATH") {
        for (name, must) in [("blender", true), ("python3", false), ("python", false)] {
            if let Some(p) = std::env::split_paths(&paths)
                .map(|d| d.join(name))
                .find(|p| p.is_file())
            {
                candidates.push((p, must));
            }
        }
    }
    let (mut best, mut first_error): (Option<Blender>, Option<ExportError>) = (None, None);
    for (c, must) in candidates {
        match find_blender(Some(&c)) {
            Ok(Some(b)) if best.as_ref().is_none_or(|x| b.version > x.version) => best = Some(b),
            Ok(_) => {}
            Err(e) if must => {
                first_error.get_or_insert(e);
            }
            Err(_) => {}
        }
    }
    match (best, first_error) {
        (Some(b), _) => Ok(Some(b)),
        (None, Some(e)) => Err(e),
        (None, None) => Ok(None),
    }
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
    /// Render threads (0: [`THREADS_ENV`], else Blender's default, all cores).
    pub threads: usize,
    /// Cycles' seed.
    pub seed: u32,
    /// Build and render the scene of this scan frame (`frames.json`, [`super::frames`])
    /// instead of `scene.json`'s.
    pub frame: Option<usize>,
    /// Instead of any scene: measure Cycles' subsurface response (the half-lit slab's edge
    /// response per method and albedo, [`Blender::measure`]) into this JSON file.
    pub measure: Option<PathBuf>,
}

impl Blender {
    /// Runs the export folder's build script: writes its `.blend` and, with `run.render`, the
    /// Cycles render. Blender's own output goes into `blender.log` in the folder.
    pub fn run(&self, dir: &Path, run: &Run) -> Result<(), ExportError> {
        self.run_with(dir, run, &())
    }

    /// [`Blender::run`], reporting the render's samples to `progress` as Cycles prints them
    /// (`… | Sample 12/64`): a render takes a minute and its caller would otherwise show nothing.
    /// A backup Blender left beside a `.blend` it wrote (`model.blend1`: the script turns
    /// backups off, but a Blender whose preferences keep them still writes one) is removed: the
    /// export folder holds what the export made, and the `.blend` is rewritten on every run.
    pub fn run_with(
        &self,
        dir: &Path,
        run: &Run,
        progress: &dyn Progress,
    ) -> Result<(), ExportError> {
        let script = dir.join(BUILD_SCRIPT);
        let threads = render_threads(run.threads)?;
        let mut cmd = Command::new(&self.path);
        match self.kind {
            Kind::Binary => {
                cmd.args(["-b", "--factory-startup"]);
                if threads > 0 {
                    // Blender's own option as well as the script's: it also bounds the threads
                    // Blender starts before the script runs.
                    cmd.args(["-t", &threads.to_string()]);
                }
                cmd.args(["--python-exit-code", "1", "--python"]);
            }
            // The module runs the script as any Python does; a failing script exits non-zero.
            Kind::Python => {}
        }
        cmd.arg(&script).arg("--").arg("--dir").arg(dir);
        if let Some(exr) = &run.render {
            cmd.arg("--render").arg(exr);
        }
        if let Some(s) = run.samples {
            cmd.args(["--samples", &s.to_string()]);
        }
        if run.compare {
            cmd.arg("--compare");
        }
        cmd.args(["--threads", &threads.to_string()]);
        cmd.args(["--seed", &run.seed.to_string()]);
        if let Some(k) = run.frame {
            cmd.args(["--frame", &k.to_string()]);
        }
        if let Some(m) = &run.measure {
            cmd.arg("--measure").arg(m);
        }
        let (status, text) = run_reporting(cmd, progress)
            .map_err(|e| ExportError::Blender(format!("running {}: {e}", self.path.display())))?;
        let log = dir.join("blender.log");
        std::fs::write(&log, &text).map_err(|e| ExportError::io(&log, e))?;
        let printed = String::from_utf8_lossy(&text);
        for blend in printed
            .lines()
            .filter_map(|l| l.strip_prefix("SUBSURF wrote "))
        {
            let backup = PathBuf::from(format!("{}1", blend.trim()));
            if backup.extension().is_some_and(|e| e == "blend1") && backup.is_file() {
                std::fs::remove_file(&backup).map_err(|e| ExportError::io(&backup, e))?;
            }
        }
        let rendered = run
            .render
            .as_ref()
            .is_none_or(|_| printed.contains("SUBSURF rendered"));
        if !status.success() || !printed.contains("SUBSURF wrote") || !rendered {
            let tail: Vec<&str> = printed.lines().rev().take(12).collect();
            return Err(ExportError::Blender(format!(
                "{} failed ({}); see {}:\n{}",
                self.version_line,
                status,
                log.display(),
                tail.into_iter().rev().collect::<Vec<_>>().join("\n")
            )));
        }
        Ok(())
    }
}

/// One row of [`Blender::measure`]: a method at an albedo, the Christensen-Burley shape fitted
/// to the half-lit slab's edge response (radius 1).
#[derive(Clone, Debug, PartialEq, serde::Deserialize, serde::Serialize)]
pub struct ResponseRow {
    /// The Principled BSDF's `subsurface_method`.
    pub method: String,
    /// The albedo (3.x: Subsurface Color; v2: Base Color).
    pub albedo: f64,
    /// The fitted Burley `d` over the Subsurface Radius.
    pub d_per_radius: f64,
    /// The plateau of the lit side times π over the albedo (1: a point scatters its albedo).
    pub plateau_pi_per_albedo: f64,
    /// RMS residual of the fit relative to the plateau (how far from the Burley shape).
    pub shape_rms: f64,
}

/// What [`Blender::measure`] writes (`subsurf-cycles-response/1`).
#[derive(Clone, Debug, PartialEq, serde::Deserialize, serde::Serialize)]
pub struct Response {
    /// Blender's version string.
    pub blender: String,
    /// Samples per pixel of the renders.
    pub samples: u32,
    /// Per method and albedo.
    pub rows: Vec<ResponseRow>,
}

impl Response {
    /// The rows as a table, one per method and albedo.
    pub fn text(&self) -> String {
        let mut o = format!(
            "{} ({} samples): method, albedo, d / radius, plateau π / albedo, shape RMS\n",
            self.blender, self.samples
        );
        for x in &self.rows {
            o += &format!(
                "{:<26} {:.2} {:.4} {:.4} {:.4}\n",
                x.method, x.albedo, x.d_per_radius, x.plateau_pi_per_albedo, x.shape_rms
            );
        }
        o
    }
}

impl Blender {
    /// Measures this Blender's subsurface response: `build_blend.py --measure` renders a slab
    /// much larger than the profile, half of it lit from above by a sun of strength 1, seen
    /// across the edge, for each method (Christensen-Burley and both random walks) at six
    /// albedos, and fits the Burley shape to each edge response. The export's radius
    /// (`cycles::RADIUS_PER_D`) and colour assume what its Christensen-Burley rows show: `d =
    /// radius / (4π)` and a plateau of `albedo / π`; [`super::cycles::MEASURED_BURLEY`] keeps
    /// the figures of the versions measured. The script is written into `dir`, the figures to
    /// `dir/cycles-response.json`.
    pub fn measure(&self, dir: &Path, samples: u32) -> Result<Response, ExportError> {
        std::fs::create_dir_all(dir).map_err(|e| ExportError::io(dir, e))?;
        let script = dir.join(BUILD_SCRIPT);
        std::fs::write(&script, super::BUILD_BLEND_PY).map_err(|e| ExportError::io(&script, e))?;
        let out = dir.join("cycles-response.json");
        let run = Run {
            samples: Some(samples),
            measure: Some(out.clone()),
            ..Run::default()
        };
        self.run(dir, &run)?;
        let text = std::fs::read_to_string(&out).map_err(|e| ExportError::io(&out, e))?;
        serde_json::from_str(&text)
            .map_err(|e| ExportError::Blender(format!("{}: {e}", out.display())))
    }
}

/// Runs `cmd`, its stdout read line by line as it comes so the samples Cycles reports reach
/// `progress`; returns the exit status and stdout followed by stderr (read on a thread of its
/// own, so neither pipe fills while the other is read).
fn run_reporting(
    mut cmd: Command,
    progress: &dyn Progress,
) -> std::io::Result<(std::process::ExitStatus, Vec<u8>)> {
    use std::io::{BufRead, Read};
    use std::process::Stdio;
    let mut child = cmd.stdout(Stdio::piped()).stderr(Stdio::piped()).spawn()?;
    let mut err_pipe = child.stderr.take();
    let err = std::thread::spawn(move || {
        let mut buf = Vec::new();
        if let Some(p) = err_pipe.as_mut() {
            let _ = p.read_to_end(&mut buf);
        }
        buf
    });
    let mut text = Vec::new();
    if let Some(out) = child.stdout.take() {
        let mut reader = std::io::BufReader::new(out);
        let (mut line, mut last) = (Vec::new(), 0);
        while reader.read_until(b'\n', &mut line)? > 0 {
            if let Some((done, of)) = samples_done(&String::from_utf8_lossy(&line)) {
                progress.set_length(of);
                // Forward as increments, which a display without a terminal prints now and
                // then; a new tile or pass starting over sets the position.
                if done >= last {
                    progress.inc(done - last);
                } else {
                    progress.set_position(done);
                }
                last = done;
            }
            text.append(&mut line);
        }
    }
    let status = child.wait()?;
    text.extend(err.join().unwrap_or_default());
    Ok((status, text))
}

/// `(done, of)` from a Cycles status line ending `| Sample 12/64`.
fn samples_done(line: &str) -> Option<(u64, u64)> {
    let (_, rest) = line.rsplit_once("Sample ")?;
    let (done, of) = rest.trim().split_once('/')?;
    Some((done.parse().ok()?, of.trim().parse().ok()?))
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

    /// The samples of a Cycles status line; other lines have none.
    #[test]
    fn samples_are_read_from_status_lines() {
        let l = "Fra:1 Mem:19.23M (Peak 24.55M) | Time:00:00.16 | Remaining:00:00.10 | \
                 Mem:4.58M, Peak:4.58M | subsurf, ViewLayer | Sample 12/64";
        assert_eq!(samples_done(l), Some((12, 64)));
        assert_eq!(samples_done("Blender quit"), None);
    }

    /// Records what a run reported.
    #[derive(Default)]
    struct Seen(std::sync::Mutex<Vec<(u64, u64)>>);
    impl Progress for Seen {
        fn set_position(&self, pos: u64) {
            self.0.lock().unwrap().push((pos, 0));
        }
        fn set_length(&self, len: u64) {
            self.0.lock().unwrap().push((len, 1));
        }
        fn inc(&self, n: u64) {
            self.0.lock().unwrap().push((n, 2));
        }
    }

    /// A run reports Cycles' samples as they are printed, and leaves no `.blend1`
    /// beside the `.blend` it wrote (a stand-in Blender that writes one, as a Blender keeping
    /// backups does).
    #[cfg(unix)]
    #[test]
    fn a_run_reports_samples_and_leaves_no_backup() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let fake = dir.path().join("blender");
        std::fs::write(
            &fake,
            "#!/bin/sh\n\
             while [ \"$1\" != --dir ]; do shift; done; d=\"$2\"\n\
             touch \"$d/model.blend\" \"$d/model.blend1\" \"$d/keep.blend1\"\n\
             echo 'Fra:1 | subsurf, ViewLayer | Sample 3/8'\n\
             echo 'Fra:1 | subsurf, ViewLayer | Sample 8/8'\n\
             echo \"SUBSURF wrote $d/model.blend\"\n",
        )
        .unwrap();
        std::fs::set_permissions(&fake, std::fs::Permissions::from_mode(0o755)).unwrap();
        let b = Blender {
            path: fake,
            kind: Kind::Binary,
            version: (3, 4),
            version_line: "Blender 3.4.1".into(),
        };
        let seen = Seen::default();
        b.run_with(dir.path(), &Run::default(), &seen).unwrap();
        assert!(dir.path().join("model.blend").is_file());
        assert!(!dir.path().join("model.blend1").exists());
        // Only the backup of what this run wrote.
        assert!(dir.path().join("keep.blend1").is_file());
        let seen = seen.0.into_inner().unwrap();
        assert_eq!(seen, [(8, 1), (3, 2), (8, 1), (5, 2)]);
    }

    /// The thread count from the environment: a number, empty for Blender's default, anything
    /// else an error naming the variable.
    #[test]
    fn thread_counts_parse() {
        assert_eq!(parse_threads("1").unwrap(), 1);
        assert_eq!(parse_threads(" 4 ").unwrap(), 4);
        assert_eq!(parse_threads("").unwrap(), 0);
        let e = parse_threads("all").unwrap_err();
        assert!(e.to_string().contains(THREADS_ENV), "{e}");
        assert_eq!(render_threads(3).unwrap(), 3);
    }

    /// A Python that imports `bpy` is found by its `bpy.app.version_string` and runs the script
    /// itself (`python build_blend.py -- …`), without Blender's own options; a stand-in Python
    /// that refuses Blender's options, as a real one does.
    #[cfg(unix)]
    #[test]
    fn a_python_with_bpy_is_a_blender() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let fake = dir.path().join("python3");
        std::fs::write(
            &fake,
            "#!/bin/sh\n\
             case \"$1\" in -b) echo 'unknown option --factory-startup' >&2; exit 2;;\n\
             -c) echo 'Blender 5.0.1'; exit 0;; esac\n\
             case \"$1\" in */build_blend.py) ;; *) exit 3;; esac\n\
             [ \"$2\" = -- ] || exit 4\n\
             while [ \"$1\" != --dir ]; do shift; done; d=\"$2\"\n\
             touch \"$d/model.blend\"; echo \"SUBSURF wrote $d/model.blend\"\n",
        )
        .unwrap();
        std::fs::set_permissions(&fake, std::fs::Permissions::from_mode(0o755)).unwrap();
        let b = find_blender(Some(&fake)).unwrap().unwrap();
        assert_eq!(b.kind, Kind::Python);
        assert_eq!(b.version, (5, 0));
        assert_eq!(b.version_line, "Blender 5.0.1");
        b.run(dir.path(), &Run::default()).unwrap();
        assert!(dir.path().join("model.blend").is_file());
    }

    /// A missing executable is an error naming it, not a panic.
    #[test]
    fn a_missing_blender_is_an_error() {
        let e = find_blender(Some(Path::new("/nonexistent/blender"))).unwrap_err();
        assert!(e.to_string().contains("/nonexistent/blender"), "{e}");
    }
}
