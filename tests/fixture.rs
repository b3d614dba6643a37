//! The scans the tests share, so that each is set up in one place and built once.
//!
//! - [`rig_scan`]: the built-in object on the simulated rig, its calibration and a plan: what every
//!   acquisition test scans (each picks the image size, the planner and the plan options).
//! - [`small_slab`]: a small simulated slab dataset (16 frames), built once per test process
//!   (`OnceLock`) and only read; a test that breaks a dataset on purpose copies it first
//!   ([`small_slab_copy`]).
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use subsurf::calib::Calibration;
use subsurf::dataset::Mesh;
use subsurf::scan::driver::ScanConfig;
use subsurf::scan::plan::{PlanOptions, PlanScene, coverage_plan, dense_raster};
use subsurf::scan::setup::builtin_object;
use subsurf::simulate::{SimConfig, SimObject, simulate};

/// Which planner [`rig_scan`] plans with.
#[derive(Debug, Clone, Copy)]
pub enum Planner {
    /// `dense_raster`: every raster target at every angle.
    Dense,
    /// `coverage_plan`: the greedy set cover.
    Coverage,
}

/// A scan of the built-in object into a fresh temporary directory (`<tmp>/ds`): the calibration
/// frames the object in a `size`² image, the plan comes from `planner` with `opts`.
pub fn rig_scan(
    size: u32,
    planner: Planner,
    opts: PlanOptions,
) -> (ScanConfig, Mesh, tempfile::TempDir) {
    let obj = builtin_object();
    let mesh = obj.mesh();
    let (centre, radius) = obj.bounds();
    let calib = Calibration::builtin_for(centre, radius, size);
    let scene = PlanScene::new(&mesh.positions, &mesh.triangles, &calib).unwrap();
    let plan = match planner {
        Planner::Dense => dense_raster(&scene, &opts),
        Planner::Coverage => coverage_plan(&scene, &opts),
    }
    .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let cfg = ScanConfig::new(
        dir.path().join("ds"),
        plan,
        calib,
        subsurf::dataset::obj_bytes(&mesh),
    );
    (cfg, mesh, dir)
}

/// The small slab dataset (8 mm, 9×9 vertices, one 64² camera, a 4×4 laser raster), simulated
/// once per test process. Read it; never change it.
pub fn small_slab() -> &'static Path {
    static DIR: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    &DIR.get_or_init(|| {
        let tmp = tempfile::Builder::new()
            .prefix("fixture-")
            .tempdir_in(env!("CARGO_TARGET_TMPDIR"))
            .unwrap();
        let dir = tmp.path().join("small-slab");
        let cfg = SimConfig::for_object(SimObject::Slab { size: 8.0, n: 9 }, 64, 1, 4);
        simulate(&cfg, &dir, &()).unwrap();
        (tmp, dir)
    })
    .1
}

/// A private copy of [`small_slab`] at `dir`, for tests that break it on purpose.
pub fn small_slab_copy(dir: &Path) {
    copy_dir(small_slab(), dir);
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            copy_dir(&p, &to.join(e.file_name()));
        } else {
            std::fs::copy(&p, to.join(e.file_name())).unwrap();
        }
    }
}
