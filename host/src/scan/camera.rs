//! Cameras behind one trait.
//!
//! A camera is either triggered by the rig (the `sim` camera and `dir:PATH`: the rig's queued
//! capture program fires the trigger, the host then collects the image of each capture) or timed
//! by the host (`cmd:"…"`: the host points the galvo, switches the laser on, runs the command,
//! switches the laser off). HDR comes from [`crate::dataset::merge_hdr`] over exposure brackets
//! when the camera is not HDR itself.

use crate::dataset::{Image, Levels};
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant, SystemTime};

/// Why a camera gave no image.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum CameraError {
    /// No image arrived in time.
    #[error("camera {camera}: no image for frame {frame} within {waited:?}")]
    Timeout {
        /// Camera description.
        camera: String,
        /// The frame.
        frame: usize,
        /// How long we waited.
        waited: Duration,
    },
    /// The capture command failed.
    #[error("camera {camera}: capture command failed for frame {frame}: {message}")]
    Command {
        /// Camera description.
        camera: String,
        /// The frame.
        frame: usize,
        /// Exit status and standard error.
        message: String,
    },
    /// The image could not be read.
    #[error("camera {camera}: image {path} unreadable: {message}")]
    Image {
        /// Camera description.
        camera: String,
        /// The file.
        path: String,
        /// The decoder's message.
        message: String,
    },
    /// The camera specification is wrong.
    #[error("camera: {0}")]
    Spec(String),
    /// The images on disk do not match the rig's exposure count (an image without a confirmed
    /// exposure, or one missing between two confirmed ones).
    #[error("camera {camera}: {message}")]
    Mismatch {
        /// Camera description.
        camera: String,
        /// What did not match.
        message: String,
    },
}

/// Who times the exposure.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Timing {
    /// The rig's capture program triggers the camera; the host collects images afterwards.
    RigTriggered,
    /// The host runs the exposure itself while the laser is held on.
    HostTimed,
}

/// One exposure the camera is asked for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Shot {
    /// Frame number in the plan.
    pub frame: usize,
    /// Bracket index within the frame.
    pub bracket: usize,
    /// Turntable angle the rig reported (degrees).
    pub turntable_deg: f64,
    /// Galvo codes the rig reported.
    pub galvo: [u16; 2],
    /// Laser channel fired.
    pub channel: u8,
    /// Exposure (s).
    pub exposure_s: f64,
    /// Rig clock at the trigger (µs), when rig-triggered.
    pub triggered_at_us: Option<u64>,
    /// The camera's exposure count for this shot as the rig confirmed it from the
    /// exposure-active output (rig-triggered only): which image belongs to this shot.
    pub exposure_count: Option<u32>,
    /// The rig's boot nonce when it counted that exposure: its count restarts at 0 when the rig
    /// reboots, the camera's does not.
    pub rig_boot: Option<u32>,
    /// Every laser off: a dark frame ([`crate::scan::dark`]), `frame` is then its bracket.
    pub dark: bool,
}

/// A camera.
pub trait Camera: Send {
    /// Short description for messages.
    fn describe(&self) -> String;
    /// Who times the exposure.
    fn timing(&self) -> Timing;
    /// Whether images are already HDR (no bracketing needed).
    fn is_hdr(&self) -> bool {
        false
    }
    /// Whether `capture` returns within a few milliseconds (then the driver does not keep the
    /// rig's heartbeat going from a second thread meanwhile, which keeps virtual time exact).
    fn is_quick(&self) -> bool {
        false
    }
    /// Sensor value at saturation (for bracket merging).
    fn saturation(&self) -> f32 {
        1.0
    }
    /// Called before a batch of rig-triggered shots is fired.
    fn begin_batch(&mut self) -> Result<(), CameraError> {
        Ok(())
    }
    /// The image of `shot`; for host-timed cameras this performs the exposure.
    fn capture(&mut self, shot: &Shot) -> Result<Image, CameraError>;
}

/// `dir:PATH`: a camera program writes each triggered image into a folder, named with the
/// camera's frame counter (the last run of digits in the file name, e.g. `img_000123.exr`).
///
/// Images are matched to captures by count, not by file-name order: the rig confirms every
/// exposure from the camera's exposure-active output and reports its running count
/// ([`Shot::exposure_count`]); the offset between the camera's counter and the rig's is learned
/// from the first image, and from then on the image for count `k` must carry number
/// `k + offset`. An image with an unexpected number (the camera exposed without a trigger, or
/// an image is missing) is a [`CameraError::Mismatch`], never a silent shift. The rig's count
/// restarts when it reboots (its boot nonce changes, [`Shot::rig_boot`]) while the camera's does
/// not, so the offset is learned again then. Without counts (host-timed use) or without numbers
/// in the names, images are taken in name order.
pub struct DirCamera {
    dir: PathBuf,
    timeout: Duration,
    seen: BTreeSet<PathBuf>,
    since: SystemTime,
    /// Camera frame number minus the rig's exposure count, once known.
    offset: Option<i64>,
    /// Black and white level of the camera's TIFF or PNG files.
    levels: Levels,
    /// The rig boot the offset belongs to.
    boot: Option<u32>,
}

/// The camera's frame number in a file name: its last run of decimal digits.
fn frame_number(p: &Path) -> Option<i64> {
    let stem = p.file_stem()?.to_string_lossy().into_owned();
    let digits: String = stem
        .chars()
        .rev()
        .skip_while(|c| !c.is_ascii_digit())
        .take_while(|c| c.is_ascii_digit())
        .collect::<Vec<_>>()
        .into_iter()
        .rev()
        .collect();
    digits.parse().ok()
}

impl DirCamera {
    /// Watches `dir`; waits up to `timeout` for each image.
    pub fn new(dir: &Path, timeout: Duration) -> Result<Self, CameraError> {
        if !dir.is_dir() {
            return Err(CameraError::Spec(format!(
                "dir:{}: the folder does not exist",
                dir.display()
            )));
        }
        let mut cam = DirCamera {
            dir: dir.to_path_buf(),
            timeout,
            seen: BTreeSet::new(),
            since: SystemTime::UNIX_EPOCH,
            offset: None,
            levels: Levels::default(),
            boot: None,
        };
        // Files already there belong to earlier runs.
        cam.seen = cam.listing().into_iter().collect();
        cam.since = SystemTime::now();
        Ok(cam)
    }

    /// The camera's TIFF or PNG files have these black and white levels (raw files carry their
    /// own): images are decoded to `(DN − black) / (white − black)`, so the sensor clips at 1,
    /// the default [`Camera::saturation`].
    pub fn with_levels(mut self, levels: Levels) -> Self {
        self.levels = levels;
        self
    }

    fn listing(&self) -> Vec<PathBuf> {
        let mut v: Vec<PathBuf> = std::fs::read_dir(&self.dir)
            .map(|rd| {
                rd.flatten()
                    .map(|e| e.path())
                    .filter(|p| {
                        p.is_file()
                            && !p
                                .file_name()
                                .is_some_and(|n| n.to_string_lossy().starts_with('.'))
                    })
                    .collect()
            })
            .unwrap_or_default();
        v.sort();
        v
    }
}

impl Camera for DirCamera {
    fn describe(&self) -> String {
        format!("dir:{}", self.dir.display())
    }
    fn timing(&self) -> Timing {
        Timing::RigTriggered
    }
    fn capture(&mut self, shot: &Shot) -> Result<Image, CameraError> {
        if shot.rig_boot.is_some() && shot.rig_boot != self.boot {
            // The rig rebooted: its exposure count started again at 0.
            self.offset = None;
            self.boot = shot.rig_boot;
        }
        let start = Instant::now();
        loop {
            let fresh: Vec<PathBuf> = self
                .listing()
                .into_iter()
                .filter(|p| {
                    !self.seen.contains(p)
                        && std::fs::metadata(p)
                            .and_then(|m| m.modified())
                            .is_ok_and(|t| t + Duration::from_secs(2) >= self.since)
                })
                .collect();
            let next = match shot.exposure_count {
                Some(count) if fresh.iter().all(|p| frame_number(p).is_some()) => {
                    let lowest = fresh.iter().filter_map(|p| frame_number(p)).min();
                    let offset = match (self.offset, lowest) {
                        (Some(o), _) => Some(o),
                        (None, Some(n)) => Some(n - i64::from(count)),
                        (None, None) => None,
                    };
                    let want = offset.map(|o| i64::from(count) + o);
                    if let (Some(want), Some(lowest)) = (want, lowest)
                        && lowest < want
                    {
                        return Err(CameraError::Mismatch {
                            camera: self.describe(),
                            message: format!(
                                "image number {lowest} arrived but the rig confirmed no exposure \
                                 for it (frame {} expects image {want})",
                                shot.frame
                            ),
                        });
                    }
                    if let Some(o) = offset {
                        self.offset = Some(o);
                    }
                    fresh.into_iter().find(|p| frame_number(p) == want)
                }
                _ => fresh.into_iter().next(),
            };
            if let Some(p) = next {
                // Wait until the writer is done: the size is stable across a short pause.
                let s1 = std::fs::metadata(&p).map(|m| m.len()).unwrap_or(0);
                std::thread::sleep(Duration::from_millis(20));
                let s2 = std::fs::metadata(&p).map(|m| m.len()).unwrap_or(0);
                if s1 == s2 && s1 > 0 {
                    self.seen.insert(p.clone());
                    let bytes = std::fs::read(&p).map_err(|e| CameraError::Image {
                        camera: self.describe(),
                        path: p.display().to_string(),
                        message: e.to_string(),
                    })?;
                    return Image::decode_with(&bytes, self.levels).map_err(|e| {
                        CameraError::Image {
                            camera: self.describe(),
                            path: p.display().to_string(),
                            message: e.to_string(),
                        }
                    });
                }
            }
            if start.elapsed() > self.timeout {
                return Err(CameraError::Timeout {
                    camera: self.describe(),
                    frame: shot.frame,
                    waited: self.timeout,
                });
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }
}

/// `cmd:"…"`: an external capture command (e.g. gphoto2), run by `sh -c` once per exposure while
/// the host holds the laser on. `{out}` is replaced by the image path to write, `{exposure}` by
/// the exposure in seconds, `{frame}` by the frame number.
pub struct CmdCamera {
    template: String,
    scratch: tempfile::TempDir,
    timeout: Duration,
    levels: Levels,
}

impl CmdCamera {
    /// A command camera; each run may take up to `timeout`.
    pub fn new(template: &str, timeout: Duration) -> Result<Self, CameraError> {
        if !template.contains("{out}") {
            return Err(CameraError::Spec(
                "cmd: the command must contain {out}, the path the image is to be written to"
                    .into(),
            ));
        }
        let scratch = tempfile::tempdir().map_err(|e| CameraError::Spec(e.to_string()))?;
        Ok(CmdCamera {
            template: template.to_string(),
            scratch,
            timeout,
            levels: Levels::default(),
        })
    }

    /// The command's TIFF or PNG files have these black and white levels (see
    /// [`DirCamera::with_levels`]).
    pub fn with_levels(mut self, levels: Levels) -> Self {
        self.levels = levels;
        self
    }
}

impl Camera for CmdCamera {
    fn describe(&self) -> String {
        format!("cmd:{:?}", self.template)
    }
    fn timing(&self) -> Timing {
        Timing::HostTimed
    }
    fn capture(&mut self, shot: &Shot) -> Result<Image, CameraError> {
        let out = self
            .scratch
            .path()
            .join(format!("shot-{}-{}.img", shot.frame, shot.bracket));
        let _ = std::fs::remove_file(&out);
        let cmd = self
            .template
            .replace("{out}", &out.display().to_string())
            .replace("{exposure}", &format!("{}", shot.exposure_s))
            .replace("{frame}", &shot.frame.to_string());
        let mut child = Command::new("sh")
            .arg("-c")
            .arg(&cmd)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .map_err(|e| CameraError::Command {
                camera: self.describe(),
                frame: shot.frame,
                message: format!("cannot start sh: {e}"),
            })?;
        let start = Instant::now();
        let status = loop {
            match child.try_wait() {
                Ok(Some(s)) => break s,
                Ok(None) if start.elapsed() > self.timeout => {
                    let _ = child.kill();
                    let _ = child.wait();
                    return Err(CameraError::Timeout {
                        camera: self.describe(),
                        frame: shot.frame,
                        waited: self.timeout,
                    });
                }
                Ok(None) => std::thread::sleep(Duration::from_millis(5)),
                Err(e) => {
                    return Err(CameraError::Command {
                        camera: self.describe(),
                        frame: shot.frame,
                        message: e.to_string(),
                    });
                }
            }
        };
        if !status.success() {
            let mut err = String::new();
            if let Some(mut s) = child.stderr.take() {
                use std::io::Read;
                let _ = s.read_to_string(&mut err);
            }
            return Err(CameraError::Command {
                camera: self.describe(),
                frame: shot.frame,
                message: format!("{status}: {}", err.trim()),
            });
        }
        let bytes = std::fs::read(&out).map_err(|e| CameraError::Image {
            camera: self.describe(),
            path: out.display().to_string(),
            message: format!("the command did not write it ({e})"),
        })?;
        Image::decode_with(&bytes, self.levels).map_err(|e| CameraError::Image {
            camera: self.describe(),
            path: out.display().to_string(),
            message: e.to_string(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shot(frame: usize) -> Shot {
        Shot {
            frame,
            bracket: 0,
            turntable_deg: 0.0,
            galvo: [0, 0],
            channel: 0,
            exposure_s: 0.01,
            triggered_at_us: None,
            exposure_count: None,
            rig_boot: None,
            dark: false,
        }
    }

    fn exr(v: f32) -> Vec<u8> {
        let mut i = Image::new(2, 2, 3);
        i.data.fill(v);
        crate::dataset::encode_exr(&i).unwrap()
    }

    #[test]
    fn dir_camera_takes_new_images_in_order_and_times_out() {
        let d = tempfile::tempdir().unwrap();
        std::fs::write(d.path().join("old.exr"), exr(9.0)).unwrap();
        let mut cam = DirCamera::new(d.path(), Duration::from_millis(150)).unwrap();
        std::fs::write(d.path().join("b.exr"), exr(2.0)).unwrap();
        std::fs::write(d.path().join("a.exr"), exr(1.0)).unwrap();
        assert_eq!(cam.capture(&shot(0)).unwrap().data[0], 1.0);
        assert_eq!(cam.capture(&shot(1)).unwrap().data[0], 2.0);
        let e = cam.capture(&shot(2)).unwrap_err().to_string();
        assert!(e.contains("no image for frame 2"), "{e}");
    }

    #[test]
    fn dir_camera_matches_images_by_exposure_count_not_name_order() {
        let d = tempfile::tempdir().unwrap();
        let mut cam = DirCamera::new(d.path(), Duration::from_millis(150)).unwrap();
        let counted = |frame, count| Shot {
            exposure_count: Some(count),
            ..shot(frame)
        };
        // The camera's counter is at 100 when the rig's is at 7; names sort differently from
        // numbers ("img_99" > "img_100" as text).
        std::fs::write(d.path().join("img_101.exr"), exr(2.0)).unwrap();
        std::fs::write(d.path().join("img_100.exr"), exr(1.0)).unwrap();
        assert_eq!(cam.capture(&counted(0, 7)).unwrap().data[0], 1.0);
        assert_eq!(cam.capture(&counted(1, 8)).unwrap().data[0], 2.0);
        // The rig saw count 9 unconfirmed (missed trigger) and moved on to 10: image 103 is the
        // one for it, and a stray image 102 (no confirmed exposure) is a mismatch, not a shift.
        std::fs::write(d.path().join("img_102.exr"), exr(3.0)).unwrap();
        std::fs::write(d.path().join("img_103.exr"), exr(4.0)).unwrap();
        let e = cam.capture(&counted(2, 10)).unwrap_err().to_string();
        assert!(e.contains("image number 102"), "{e}");
        // Without numbers in the names (or without counts) name order still works.
        assert_eq!(frame_number(Path::new("a/shot.exr")), None);
        assert_eq!(frame_number(Path::new("cam0-000042.tiff")), Some(42));
    }

    /// Cameras deliver what cameras write: a 16-bit PNG with the camera's black and white level
    /// reads linear with the white level at 1 (the default saturation); a JPEG is refused with
    /// the reason.
    #[test]
    fn cameras_decode_sixteen_bit_files_with_their_levels_and_refuse_jpeg() {
        let d = tempfile::tempdir().unwrap();
        let mut cam = DirCamera::new(d.path(), Duration::from_millis(150))
            .unwrap()
            .with_levels(Levels {
                black: Some(256.0),
                white: Some(4352.0),
            });
        let mut png = Vec::new();
        image::DynamicImage::ImageRgb16(image::ImageBuffer::from_pixel(
            2,
            2,
            image::Rgb([256u16, 2304, 4352]),
        ))
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
        std::fs::write(d.path().join("a.png"), &png).unwrap();
        let img = cam.capture(&shot(0)).unwrap();
        assert_eq!(&img.data[..3], &[0.0, 0.5, 1.0]);
        assert_eq!(cam.saturation(), 1.0);
        std::fs::write(d.path().join("b.jpg"), [0xff, 0xd8, 0xff, 0xe0, 0, 16]).unwrap();
        let e = cam.capture(&shot(1)).unwrap_err().to_string();
        assert!(e.contains("JPEG") && e.contains("16-bit"), "{e}");
    }

    /// The offset must not outlive a rig reboot, whose exposure count restarts
    /// at 0 while the camera keeps counting: otherwise every image after the reconnect is a
    /// mismatch.
    #[test]
    fn dir_camera_learns_the_offset_again_after_a_rig_reboot() {
        let d = tempfile::tempdir().unwrap();
        let mut cam = DirCamera::new(d.path(), Duration::from_millis(150)).unwrap();
        let counted = |frame, count, boot| Shot {
            exposure_count: Some(count),
            rig_boot: Some(boot),
            ..shot(frame)
        };
        std::fs::write(d.path().join("img_100.exr"), exr(1.0)).unwrap();
        std::fs::write(d.path().join("img_101.exr"), exr(2.0)).unwrap();
        assert_eq!(cam.capture(&counted(0, 1, 0xaaaa)).unwrap().data[0], 1.0);
        assert_eq!(cam.capture(&counted(1, 2, 0xaaaa)).unwrap().data[0], 2.0);
        // The rig rebooted: its count starts at 1 again, the camera's goes on at 102.
        std::fs::write(d.path().join("img_102.exr"), exr(3.0)).unwrap();
        std::fs::write(d.path().join("img_103.exr"), exr(4.0)).unwrap();
        assert_eq!(cam.capture(&counted(2, 1, 0xbbbb)).unwrap().data[0], 3.0);
        assert_eq!(cam.capture(&counted(3, 2, 0xbbbb)).unwrap().data[0], 4.0);
    }

    #[test]
    fn cmd_camera_runs_the_command_and_reports_failures() {
        let src = tempfile::NamedTempFile::new().unwrap();
        std::fs::write(src.path(), exr(3.0)).unwrap();
        let mut cam = CmdCamera::new(
            &format!("cp {} {{out}}", src.path().display()),
            Duration::from_secs(5),
        )
        .unwrap();
        assert_eq!(cam.capture(&shot(0)).unwrap().data[0], 3.0);
        let mut bad = CmdCamera::new(
            "echo lens cap on >&2; exit 3 # {out}",
            Duration::from_secs(5),
        )
        .unwrap();
        let e = bad.capture(&shot(4)).unwrap_err().to_string();
        assert!(e.contains("frame 4") && e.contains("lens cap on"), "{e}");
        assert!(CmdCamera::new("gphoto2", Duration::from_secs(1)).is_err());
    }
}
