//! Replay (a recorded dataset as rig and camera) and the adaptive planner. A replay
//! copies exactly the frames it asked for into a normal dataset; an adaptive scan killed and
//! resumed ends with the same frames as one not killed; a stalled error stops a scan only on
//! enough folds. Every scan here is small (a 48 px simulated bead): seconds in a debug
//! build.
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use subsurf::dataset::Dataset;
use subsurf::scan::adaptive::AcquisitionReport;

fn subsurf(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_subsurf"))
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "subsurf {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// A small simulated bead (`--vertices`, 4 angles × `raster`² laser targets, 48 px) with the
/// material `field` (`subsurf simulate` flags).
fn bead(dir: &Path, vertices: usize, raster: usize, field: &[&str]) {
    bead_at(dir, "4", vertices, raster, field)
}

/// [`bead`] with `angles` turntable angles.
fn bead_at(dir: &Path, angles: &str, vertices: usize, raster: usize, field: &[&str]) {
    let mut args = vec![
        "simulate".to_string(),
        "--out".into(),
        dir.display().to_string(),
        "--object".into(),
        "sphere".into(),
        "--vertices".into(),
        vertices.to_string(),
        "--size".into(),
        "48".into(),
        "--angles".into(),
        angles.into(),
        "--raster".into(),
        raster.to_string(),
        "--anisotropy".into(),
        "0".into(),
    ];
    args.extend(field.iter().map(|s| s.to_string()));
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    subsurf(&args);
}

const HOMOGENEOUS: &[&str] = &["--heterogeneity", "0", "--alpha-amplitude", "0"];
const VEINED: &[&str] = &[
    "--heterogeneity",
    "2",
    "--alpha-amplitude",
    "1",
    "--vein-wavelength",
    "2.5",
];

fn replay(src: &Path, out: &Path, planner: &str, extra: &[&str]) -> String {
    let mut args = vec![
        "scan",
        "--replay",
        src.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--planner",
        planner,
        "--quiet",
    ];
    args.extend_from_slice(extra);
    subsurf(&args)
}

/// The report's frame order, checked against the dataset: frame k is a byte copy of the
/// recorded frame the order names, with the same scan.json entry but its file name.
fn check_copies(src: &Path, out: &Path) -> Vec<usize> {
    let rep = AcquisitionReport::load(out).unwrap().unwrap();
    let order = rep.order();
    let a = Dataset::open(src).unwrap();
    let b = Dataset::open(out).unwrap();
    assert_eq!(b.spec.frames.len(), order.len(), "{order:?}");
    assert_eq!(a.spec.cameras, b.spec.cameras);
    assert_eq!(a.spec.noise_floor, b.spec.noise_floor);
    for (k, &f) in order.iter().enumerate() {
        let (fa, fb) = (&a.spec.frames[f], &b.spec.frames[k]);
        assert_eq!(
            std::fs::read(src.join(&fa.image)).unwrap(),
            std::fs::read(out.join(&fb.image)).unwrap(),
            "frame {k} = recorded {f}"
        );
        let mut renamed = fa.clone();
        renamed.image = fb.image.clone();
        assert_eq!(&renamed, fb, "frame {k} = recorded {f}");
    }
    order
}

/// A replay copies exactly the frames asked for (never an excluded one), and the result reads as
/// a normal dataset: `subsurf fit` fits it.
#[test]
fn a_replay_copies_exactly_the_frames_asked_for() {
    let tmp = tempfile::tempdir().unwrap();
    let src = tmp.path().join("bead");
    bead(&src, 400, 4, HOMOGENEOUS);
    let out = tmp.path().join("replayed");
    let said = replay(&src, &out, "coverage", &["--exclude-frames", "0-3,40-47"]);
    assert!(said.contains("coverage planner"), "{said}");
    let order = check_copies(&src, &out);
    let n = Dataset::open(&src).unwrap().spec.frames.len();
    assert!(!order.is_empty() && order.len() < n - 12, "{order:?}");
    assert!(
        order
            .iter()
            .all(|f| !(0..4).contains(f) && !(40..48).contains(f))
    );
    // Run again: resumed, nothing copied twice.
    replay(&src, &out, "coverage", &["--exclude-frames", "0-3,40-47"]);
    assert_eq!(check_copies(&src, &out), order);
    // Another exclusion is another replay: refused in the same directory.
    let again = Command::new(env!("CARGO_BIN_EXE_subsurf"))
        .args(["scan", "--replay", src.to_str().unwrap(), "--out"])
        .arg(&out)
        .args(["--planner", "coverage", "--quiet"])
        .output()
        .unwrap();
    assert!(!again.status.success());
    let model = tmp.path().join("m.ply");
    subsurf(&[
        "fit",
        "--scan",
        out.to_str().unwrap(),
        "--out",
        model.to_str().unwrap(),
        "--preset",
        "draft",
        "--no-pictures",
    ]);
    assert!(model.exists());
}

/// An adaptive replay killed (SIGKILL) after its first assessment and run again ends with the
/// same frames, in the same order, as one never killed; its learning curve is the same.
#[test]
fn an_adaptive_scan_killed_and_resumed_ends_with_the_same_frames() {
    let tmp = tempfile::tempdir().unwrap();
    let src = tmp.path().join("bead");
    bead(&src, 400, 4, VEINED);
    let whole = tmp.path().join("whole");
    let said = replay(&src, &whole, "adaptive", &[]);
    assert!(said.contains("batch 2:"), "{said}");
    let want = AcquisitionReport::load(&whole).unwrap().unwrap();
    assert!(want.curve.len() >= 2 && want.stopped.is_some(), "{want:?}");

    let cut = tmp.path().join("cut");
    let mut child = Command::new(env!("CARGO_BIN_EXE_subsurf"))
        .args(["scan", "--replay", src.to_str().unwrap(), "--out"])
        .arg(&cut)
        .args(["--planner", "adaptive", "--quiet"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    // Killed once the first batch is assessed and the second asked for (mid-scan).
    let t0 = Instant::now();
    loop {
        let asked = AcquisitionReport::load(&cut)
            .ok()
            .flatten()
            .is_some_and(|r| r.batches.len() >= 2);
        if asked || t0.elapsed() > Duration::from_secs(120) {
            break;
        }
        if child.try_wait().unwrap().is_some() {
            break;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    let _ = child.kill();
    let _ = child.wait();
    let partial = AcquisitionReport::load(&cut).unwrap().unwrap();
    assert!(
        partial.stopped.is_none(),
        "the kill came too late to test a resume: {partial:?}"
    );
    replay(&src, &cut, "adaptive", &[]);
    let got = AcquisitionReport::load(&cut).unwrap().unwrap();
    assert_eq!(got.batches, want.batches);
    assert_eq!(got.stopped, want.stopped);
    let curve = |r: &AcquisitionReport| -> Vec<(usize, Option<f64>)> {
        r.curve.iter().map(|p| (p.frames, p.cv_log_e)).collect()
    };
    assert_eq!(curve(&got), curve(&want));
    assert_eq!(check_copies(&src, &cut), check_copies(&src, &whole));
}

/// A stalled error stops the scan only once the comparison with the best rests on enough folds
/// (five, the default `min_clusters`). A homogeneous bead of 4 turntable angles (at most 4
/// folds) whose cross-validated error stops falling after a few batches runs on to the budget,
/// where the old rule stopped it on comparisons of 4 clusters; the same stall on a bead of 6
/// angles stops it. Patience 1 and small batches keep both scans short.
#[test]
fn a_stall_stops_the_scan_only_on_enough_folds() {
    let tmp = tempfile::tempdir().unwrap();
    let run = |angles: &str, raster: usize, field: &[&str], extra: &[&str]| -> AcquisitionReport {
        let src = tmp.path().join(format!("bead-{angles}"));
        bead_at(&src, angles, 600, raster, field);
        let out = tmp.path().join(format!("bead-{angles}-adaptive"));
        let mut args = vec!["--patience", "1"];
        args.extend_from_slice(extra);
        replay(&src, &out, "adaptive", &args);
        AcquisitionReport::load(&out).unwrap().unwrap()
    };
    let four = run(
        "4",
        6,
        HOMOGENEOUS,
        &[
            "--start-frames",
            "26",
            "--batch",
            "13",
            "--max-frames",
            "91",
        ],
    );
    let stalled = four
        .curve
        .iter()
        .any(|p| p.batch > p.best_batch && p.cv_log_e.is_some());
    assert!(stalled, "the 4-angle bead should stall: {:?}", four.curve);
    assert!(four.curve.iter().all(|p| p.gain_clusters <= 4));
    assert!(
        four.stopped
            .as_deref()
            .is_some_and(|s| s.contains("max-frames")),
        "{:?}",
        four.stopped
    );
    let six = run("6", 4, VEINED, &["--start-frames", "16", "--batch", "16"]);
    assert!(
        six.stopped
            .as_deref()
            .is_some_and(|s| s.contains("stopped falling")),
        "{:?}",
        six.stopped
    );
    assert!(six.order().len() < 96, "{}", six.order().len());
}
