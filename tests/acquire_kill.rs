//! Crash safety: `subsurf scan` killed with SIGKILL at random moments, then re-run, ends with a
//! dataset byte-identical to an uninterrupted scan — same frames, same images, nothing lost or
//! duplicated.
use rand::{Rng, SeedableRng};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const ARGS: &[&str] = &[
    "scan",
    "--sim",
    "--camera",
    "sim",
    "--quiet",
    "--size",
    "24",
    "--angles",
    "2",
    "--raster",
    "5",
    "--target-mm",
    "2",
    "--exposure",
    "0.01",
];

fn scan(out: &Path) -> std::process::Child {
    Command::new(env!("CARGO_BIN_EXE_subsurf"))
        .args(ARGS)
        .arg("--out")
        .arg(out)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

/// Entries in the dataset's `frames/` folder (0 before it exists).
fn count_frames(dir: &Path) -> usize {
    std::fs::read_dir(dir.join("frames"))
        .map(|d| d.count())
        .unwrap_or(0)
}

/// Every file under `dir` (relative path, bytes), sorted.
fn snapshot(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            // The sample cache is derived data (its manifest records the frames' file times).
            if p.file_name().is_some_and(|n| n == ".subsurf-cache") {
                continue;
            }
            if p.is_dir() {
                stack.push(p);
            } else {
                let rel = p.strip_prefix(dir).unwrap().to_string_lossy().to_string();
                out.push((rel, std::fs::read(&p).unwrap()));
            }
        }
    }
    out.sort();
    out
}

#[test]
fn killed_at_twenty_random_points_the_resumed_scan_equals_an_uninterrupted_one() {
    let tmp = tempfile::tempdir().unwrap();
    let reference = tmp.path().join("reference");
    let t0 = Instant::now();
    let out = scan(&reference).wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let full = t0.elapsed();
    let want = snapshot(&reference);
    let frames = want
        .iter()
        .filter(|(p, _)| p.starts_with("frames/"))
        .count();
    assert!(
        frames >= 8,
        "scan too small to interrupt meaningfully: {frames} frames"
    );

    let resumed = tmp.path().join("resumed");
    let mut rng = rand::rngs::StdRng::seed_from_u64(20);
    let mut kills = 0;
    let mut mid_scan = 0;
    let mut attempts = 0;
    while kills < 20 {
        attempts += 1;
        assert!(
            attempts < 200,
            "the scan finished before it could be killed 20 times"
        );
        // Every other kill waits until the scan has written one or two more frames, so kills land
        // mid-scan however fast or loaded the machine is; the others land at a random moment of
        // an uninterrupted run's duration (start-up and homing included).
        let before = count_frames(&resumed);
        let wait_frames = if kills % 2 == 0 {
            rng.random_range(1..=2)
        } else {
            0
        };
        let mut child = scan(&resumed);
        let at = full.mul_f64(rng.random_range(0.05..1.0));
        let start = Instant::now();
        let mut finished = false;
        loop {
            if child.try_wait().unwrap().is_some() {
                finished = true;
                break;
            }
            let due = if wait_frames > 0 {
                count_frames(&resumed) >= before + wait_frames
            } else {
                start.elapsed() >= at
            };
            if due {
                break;
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        if finished {
            // Completed before the kill: start over so every kill lands in a running scan.
            std::fs::remove_dir_all(&resumed).unwrap();
            continue;
        }
        child.kill().unwrap(); // SIGKILL
        child.wait().unwrap();
        kills += 1;
        let done = count_frames(&resumed);
        if done > 0 && done < frames {
            mid_scan += 1;
        }
    }
    let out = scan(&resumed).wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(mid_scan >= 5, "only {mid_scan} of 20 kills landed mid-scan");
    let got = snapshot(&resumed);
    let names = |s: &[(String, Vec<u8>)]| s.iter().map(|(p, _)| p.clone()).collect::<Vec<_>>();
    assert_eq!(names(&got), names(&want));
    for ((p, a), (_, b)) in got.iter().zip(&want) {
        assert!(a == b, "{p} differs after resuming");
    }
}
