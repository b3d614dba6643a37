//! End-to-end simulated scans through the library: plan → `scan::run` over the in-process
//! simulated rig (virtual time) with the simulated camera → a dataset the reader accepts.
use crate::fixture::{Planner, rig_scan};
use subsurf::calib::Calibration;
use subsurf::dataset::Dataset;
use subsurf::rig::{ClientConfig, RigClient};
use subsurf::scan::driver::{ScanConfig, run};
use subsurf::scan::plan::{PlanOptions, PlanScene, coverage_plan, estimate_duration};
use subsurf::scan::setup::{builtin_object, camera_from_spec, rig_timing};
use subsurf::sim::{SimLink, SimParams, VirtualRig};

fn setup(exposure: f64) -> (ScanConfig, subsurf::dataset::Mesh, tempfile::TempDir) {
    rig_scan(
        48,
        Planner::Coverage,
        PlanOptions {
            angles: 3,
            raster: 10,
            target_mm: 1.5,
            exposures_s: vec![exposure],
            ..PlanOptions::default()
        },
    )
}

#[test]
fn simulated_scan_writes_a_readable_dataset_in_the_planned_time() {
    let (cfg, mesh, _dir) = setup(0.2);
    let mut camera = camera_from_spec(
        "sim",
        &mesh,
        &cfg.calib,
        3,
        std::time::Duration::from_secs(1),
    )
    .unwrap();
    let params = SimParams::default();
    let link = SimLink::clean(VirtualRig::new(params));
    let mut rig = RigClient::connect_with_seq(link, ClientConfig::default(), 9).unwrap();
    let summary = run(&cfg, &mut rig, camera.as_mut(), &()).unwrap();
    assert_eq!(summary.frames_written, cfg.plan.frame_count());
    let ds = Dataset::open(&cfg.out).unwrap();
    assert_eq!(ds.spec.frames.len(), cfg.plan.frame_count());
    let img = ds.read_frame(0).unwrap();
    assert_eq!((img.width, img.height), (48, 48));
    assert!(img.data.iter().any(|v| *v > 0.0));
    // Laser off at the end, and it never fired outside a capture.
    let rig_state = rig.link().rig();
    assert_eq!(rig_state.status().lasers, 0);
    assert!(!rig_state.laser_log().is_empty());
    // The plan's duration estimate against the rig's virtual clock.
    let t = rig_timing(&params.profile, None, None, 0);
    let est = estimate_duration(&cfg.plan, &t, 0).total_s();
    let err = (summary.rig_seconds - est).abs() / summary.rig_seconds;
    assert!(
        err < 0.10,
        "estimated {est:.3} s, rig took {:.3} s",
        summary.rig_seconds
    );
}

#[test]
fn hdr_brackets_merge_into_radiance_frames() {
    let (mut cfg, mesh, _dir) = setup(0.01);
    cfg.plan.exposures_s = vec![0.01, 0.1, 1.0];
    cfg.plan.angles.truncate(1);
    cfg.plan.angles[0].targets.truncate(3);
    let mut camera = camera_from_spec(
        "sim",
        &mesh,
        &cfg.calib,
        3,
        std::time::Duration::from_secs(1),
    )
    .unwrap();
    let link = SimLink::clean(VirtualRig::new(SimParams::default()));
    let mut rig = RigClient::connect_with_seq(link, ClientConfig::default(), 9).unwrap();
    run(&cfg, &mut rig, camera.as_mut(), &()).unwrap();
    let ds = Dataset::open(&cfg.out).unwrap();
    assert_eq!(ds.spec.frames.len(), 3);
    assert!(ds.spec.frames.iter().all(|f| f.exposure_s == 1.0));
    // Three exposures per frame reached the rig, and two dark frames per exposure before them.
    let triggers = rig
        .link()
        .rig()
        .trigger_log()
        .iter()
        .filter(|e| e.value)
        .count();
    assert_eq!(triggers, 9 + 2 * 3);
    // With no floor given, scan.json's is the dark frames' (the longest
    // exposure's, 1 s), and it is the sensor's: 3 read-noise σ, within 8 % of the level where
    // one pixel's SNR (shot noise too) is 3. The laser never came on before the first frame's
    // capture program.
    assert_eq!(ds.spec.dark_frames.len(), 3);
    for d in &ds.spec.dark_frames {
        let img = subsurf::dataset::read_image(&cfg.out.join(&d.image)).unwrap();
        assert_eq!((img.width, img.height), (48, 48));
    }
    let longest = &ds.spec.dark_frames[2];
    assert_eq!(longest.exposure_s, 1.0);
    assert_eq!(ds.spec.noise_floor, Some(longest.floor));
    let sensor = subsurf::scan::setup::sim_sensor();
    assert!(
        (longest.sigma / sensor.read_noise - 1.0).abs() < 0.05,
        "{longest:?}"
    );
    let snr3 = subsurf::simulate::Sensor {
        exposure_s: 1.0,
        ..sensor
    }
    .radiance_at_snr(3.0);
    let ratio = longest.floor / snr3;
    assert!((0.85..1.0).contains(&ratio), "{longest:?} vs {snr3:e}");
    let first_lit = rig
        .link()
        .rig()
        .laser_log()
        .iter()
        .find(|e| e.value != 0)
        .map(|e| e.at)
        .unwrap();
    let dark_triggers: Vec<u64> = rig
        .link()
        .rig()
        .trigger_log()
        .iter()
        .filter(|e| e.value)
        .map(|e| e.at)
        .take(3)
        .collect();
    assert!(
        dark_triggers.iter().all(|&t| t < first_lit),
        "{dark_triggers:?} {first_lit}"
    );
}

#[test]
fn coverage_planner_needs_at_most_half_the_dense_frames_on_built_in_objects() {
    use subsurf::scan::plan::{dense_for_target, predict_coverage};
    use subsurf::simulate::SimObject;
    for obj in [
        builtin_object(),
        SimObject::Torus {
            major: 12.0,
            minor: 5.0,
            segments: 12,
        },
    ] {
        let mesh = obj.mesh();
        let (centre, radius) = obj.bounds();
        let calib = Calibration::builtin_for(centre, radius, 64);
        let scene = PlanScene::new(&mesh.positions, &mesh.triangles, &calib).unwrap();
        let opts = PlanOptions {
            angles: 6,
            raster: 16,
            target_mm: 2.5,
            coverage: 0.95,
            ..PlanOptions::default()
        };
        let dense = dense_for_target(&scene, &opts).unwrap();
        let cov = coverage_plan(&scene, &opts).unwrap();
        let (dc, cc) = (
            predict_coverage(&scene, &dense, opts.raster),
            predict_coverage(&scene, &cov, opts.raster),
        );
        assert!(
            dc.fraction() >= 0.95 && cc.fraction() >= 0.95,
            "{dc:?} {cc:?}"
        );
        assert!(
            2 * cov.frame_count() <= dense.frame_count(),
            "{obj:?}: coverage {} frames vs dense {}",
            cov.frame_count(),
            dense.frame_count()
        );
    }
}

/// A camera whose offset is not removed (a dark level of 5 % of the fall-off tail's level on
/// every pixel, at the longest exposure) fits, once the scan's dark frames are subtracted, as the
/// same scan without the offset does: held-out green within 1 %, judged on the clean scan's
/// frames. Without the dark frames (nothing to subtract), the offset biases every dim sample
/// and the held-out error moves by more.
#[test]
fn a_dark_offset_is_subtracted_and_fits_as_without_it() {
    use subsurf::scan::setup::sim_noise_floor;
    let scan = |camera: &str, dark: bool| -> (tempfile::TempDir, std::path::PathBuf) {
        let (mut cfg, mesh, dir) = rig_scan(
            48,
            Planner::Coverage,
            PlanOptions {
                angles: 4,
                raster: 6,
                target_mm: 1.5,
                exposures_s: vec![0.2],
                ..PlanOptions::default()
            },
        );
        cfg.noise_floor = Some(sim_noise_floor(&cfg.plan.exposures_s));
        cfg.dark_frames = dark;
        let mut cam = camera_from_spec(
            camera,
            &mesh,
            &cfg.calib,
            3,
            std::time::Duration::from_secs(1),
        )
        .unwrap();
        let link = SimLink::clean(VirtualRig::new(SimParams::default()));
        let mut rig = RigClient::connect_with_seq(link, ClientConfig::default(), 9).unwrap();
        run(&cfg, &mut rig, cam.as_mut(), &()).unwrap();
        let out = cfg.out.clone();
        (dir, out)
    };
    // The tail's level: ten times the floor (radiance); the offset in raw units at 0.2 s.
    let floor = sim_noise_floor(&[0.2]);
    let offset = 0.05 * 10.0 * floor * 0.2;
    let (_a, clean) = scan("sim", true);
    let (_b, subtracted) = scan(&format!("sim+dark={offset}"), true);
    let (_c, kept) = scan(&format!("sim+dark={offset}"), false);
    let ds = Dataset::open(&subtracted).unwrap();
    assert!(
        ds.spec
            .dark_frames
            .iter()
            .all(|d| d.subtracted.is_some() && d.second.is_some()),
        "{:?}",
        ds.spec.dark_frames
    );
    let median = ds.spec.dark_frames[0].median;
    assert!(
        (median / offset - 1.0).abs() < 0.1,
        "{median} against {offset}"
    );
    let n = Dataset::open(&clean).unwrap().spec.frames.len();
    let held = format!("{}-{}", 3 * n / 4, n - 1);
    let bin = env!("CARGO_BIN_EXE_subsurf");
    let green = |scan: &std::path::Path| -> f64 {
        let model = scan.join("m.ply");
        let fit = std::process::Command::new(bin)
            .args(["--quiet", "fit", "--scan"])
            .arg(scan)
            .arg("--out")
            .arg(&model)
            .args(["--exclude-frames", &held, "--no-pictures", "--cache", "off"])
            .output()
            .unwrap();
        assert!(
            fit.status.success(),
            "{}",
            String::from_utf8_lossy(&fit.stderr)
        );
        let ev = std::process::Command::new(bin)
            .args(["evaluate", "--model"])
            .arg(&model)
            .arg("--scan")
            .arg(&clean)
            .args(["--frames", &held, "--json", "--cache", "off"])
            .output()
            .unwrap();
        assert!(
            ev.status.success(),
            "{}",
            String::from_utf8_lossy(&ev.stderr)
        );
        let v: serde_json::Value = serde_json::from_slice(&ev.stdout).unwrap();
        v["mean_log_e"][1].as_f64().unwrap()
    };
    let (g_clean, g_sub, g_kept) = (green(&clean), green(&subtracted), green(&kept));
    eprintln!(
        "held-out green on the clean frames: clean {g_clean:.4}, offset subtracted {g_sub:.4} \
         ({:+.2} %), offset kept {g_kept:.4} ({:+.2} %)",
        100.0 * (g_sub / g_clean - 1.0),
        100.0 * (g_kept / g_clean - 1.0)
    );
    assert!((g_sub / g_clean - 1.0).abs() <= 0.01, "{g_sub} {g_clean}");
    assert!((g_kept / g_clean - 1.0).abs() > 0.01, "{g_kept} {g_clean}");
}
