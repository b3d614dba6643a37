//! The volume model's forward model against renders made by others: Mitsuba 3's volumetric path
//! tracer on a box and a sphere (the same mesh, medium, light and camera), and the outside
//! renderer's sample-slab with the medium its README publishes.

use std::path::{Path, PathBuf};
use std::process::Command;
use subsurf::dataset::{Dataset, Mesh, read_image, write_obj};
use subsurf::geometry::{Camera, Scene, shapes};
use subsurf::volume::dielectric::Surface;
use subsurf::volume::fit::{FrameRings, frame_geometry, model_rings, ring_edge};
use subsurf::volume::local::image_rings;
use subsurf::volume::medium::{GridChannel, grid_image};
use subsurf::volume::trace::{Boundary, FrameGeometry, TraceSettings, trace_frame};

pub(crate) fn workspace() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
}

/// The Python with Mitsuba 3: `$SUBSURF_MITSUBA_PYTHON`, else the venv `.ci/run` makes. `None`
/// (after printing `SKIPPED:`) when absent and CI is not set.
pub(crate) fn mitsuba() -> Option<PathBuf> {
    let py = std::env::var_os("SUBSURF_MITSUBA_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace().join(".ci/.venv-mitsuba/bin/python"));
    let ok = py.is_file()
        && Command::new(&py)
            .args(["-c", "import mitsuba"])
            .output()
            .is_ok_and(|o| o.status.success());
    if !ok {
        let ci = std::env::var_os("CI").is_some_and(|v| !v.is_empty());
        assert!(!ci, "CI is set but {} cannot import mitsuba", py.display());
        eprintln!(
            "SKIPPED: no Python with mitsuba ({}; `bash .ci/run` makes the venv, or set \
             $SUBSURF_MITSUBA_PYTHON) and CI is not set",
            py.display()
        );
        return None;
    }
    Some(py)
}

/// Runs the script `tests/outside/NAME` with Mitsuba's Python on `args`; its output, after
/// asserting that it succeeded.
pub(crate) fn run_mitsuba(py: &Path, name: &str, args: &[&Path]) -> std::process::Output {
    let o = Command::new(py)
        .arg(workspace().join("tests/outside").join(name))
        .args(args)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "mitsuba: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    o
}

/// A box [-15, 15]² × [-15, 0] mm: its top face at z = 0.
fn block() -> Mesh {
    shapes::block([-15.0, -15.0, -15.0], [15.0, 15.0, 0.0])
}

/// A sphere of radius `r` with its top at z = 0: an icosahedron subdivided `n` times.
fn sphere(r: f64, n: usize) -> Mesh {
    let m = shapes::icosphere(r, n);
    let p = m.positions.iter().map(|v| [v[0], v[1], v[2] - r]).collect();
    Mesh::new(p, m.triangles).0
}

struct Case {
    name: &'static str,
    mesh: Mesh,
    sigma_t: f64,
    albedo: [f64; 3],
    g: f64,
    /// A heterogeneous medium instead of (sigma_t, albedo): per cell σ_t and albedo.
    grid: Option<GridChannel>,
    /// Per cell the albedo of each channel, beside `grid` (whose own albedo is unused).
    grid_albedo: Vec<[f64; 3]>,
    /// A rough dielectric boundary (index inside, GGX α) instead of an index-matched one.
    dielectric: Option<(f64, f64)>,
}

/// Renders `case` in Mitsuba and in subsurf's tracer and compares their ring sums around x_i
/// (log-spaced, 4 per factor e, from 0.5 mm): per ring its inner edge, Mitsuba's and subsurf's
/// sums, channel by channel (one seed of each).
fn compare(py: &Path, dir: &Path, case: &Case) -> Vec<(f64, [f64; 3], [f64; 3])> {
    compare_seeds(py, dir, case, &[3], &[5])
        .into_iter()
        .map(|(r, data, model)| (r, data[0], model[0]))
        .collect()
}

/// One ring's inner edge (mm), its sums in each Mitsuba render and in each trace.
type SeededRing = (f64, Vec<[f64; 3]>, Vec<[f64; 3]>);

/// [`compare`] with a Mitsuba render per seed of `mitsuba_seeds` and a trace (200,000 photons)
/// per seed of `trace_seeds`: per ring the sums of each render and of each trace, so that both
/// renderers' own noise can be told from a difference between them.
fn compare_seeds(
    py: &Path,
    dir: &Path,
    case: &Case,
    mitsuba_seeds: &[u32],
    trace_seeds: &[u64],
) -> Vec<SeededRing> {
    let mesh_path = dir.join(format!("{}.obj", case.name));
    write_obj(&mesh_path, &case.mesh).unwrap();
    let (w, h, f) = (64u32, 64u32, 400.0);
    let tilt = 20f64.to_radians();
    let eye = [0.0, -150.0 * tilt.sin(), 150.0 * tilt.cos()];
    let cam = Camera::look_at(eye, [0.0; 3], [0.0, 1.0, 0.0], f, w, h).unwrap();
    // A wide spot (25° at 4 mm: a disc of 1.9 mm radius) so that Mitsuba's camera paths find
    // the lit volume often enough: with a 5° spot its two-seed ring noise at 512 samples a
    // pixel was 5-15 %, with this one 1-2.5 % out to 4 mm.
    let (light, cutoff_deg) = ([0.0, 0.0, 4.0], 25.0f64);
    let scene = Scene::new(case.mesh.clone()).unwrap();
    let mut geo = FrameGeometry::new(&scene, &cam, 0.0, light, [0.0, 0.0, -1.0]).unwrap();
    geo.cone = cutoff_deg.to_radians();
    let renders: Vec<_> = mitsuba_seeds
        .iter()
        .map(|&seed| {
            let mut spec = serde_json::json!({
                "mesh": mesh_path,
                "sigma_t": case.sigma_t,
                "albedo": case.albedo,
                "g": case.g,
                "camera": {
                    "width": w, "height": h,
                    "fov_x_deg": 2.0 * (w as f64 / 2.0 / f).atan().to_degrees(),
                    "origin": eye, "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0],
                },
                "spot": {"position": light, "target": [0.0, 0.0, 0.0], "cutoff_deg": cutoff_deg},
                "spp": 1536,
                "seed": seed,
            });
            if let Some((ior, alpha)) = case.dielectric {
                spec["bsdf"] = serde_json::json!({
                    "type": "roughdielectric", "distribution": "ggx", "alpha": alpha,
                    "int_ior": ior, "ext_ior": 1.0,
                });
            }
            if let Some(g) = &case.grid {
                spec["grid"] = serde_json::json!({
                    "origin": g.origin, "cell_mm": g.cell_mm, "dims": g.dims,
                    "sigma_t": g.sigma_t, "albedo": case.grid_albedo,
                });
            }
            let spec_path = dir.join(format!("{}-{seed}.json", case.name));
            std::fs::write(&spec_path, spec.to_string()).unwrap();
            let exr = dir.join(format!("{}-{seed}.exr", case.name));
            run_mitsuba(py, "mitsuba_volume.py", &[&spec_path, &exr]);
            FrameRings::new(&scene, geo.clone(), 0, &read_image(&exr).unwrap(), 1.0)
        })
        .collect();
    let frame = &renders[0];
    let traces: Vec<Vec<[f64; 3]>> = trace_seeds
        .iter()
        .map(|&seed| match &case.grid {
            Some(g) => {
                let channels: [GridChannel; 3] = std::array::from_fn(|c| GridChannel {
                    albedo: case.grid_albedo.iter().map(|a| a[c]).collect(),
                    ..g.clone()
                });
                let ours = grid_image(
                    &scene,
                    Boundary::of(&scene),
                    &geo,
                    &channels,
                    case.g,
                    Surface::IndexMatched,
                    200_000,
                    seed,
                    0,
                );
                image_rings(frame, &ours)
            }
            None => {
                let mut settings = TraceSettings::for_medium(
                    [case.sigma_t; 3],
                    case.albedo,
                    case.g,
                    200_000,
                    seed,
                );
                if let Some((ior, alpha)) = case.dielectric {
                    settings.surface = Surface::RoughDielectric { ior, alpha };
                }
                let records = trace_frame(&scene, Boundary::of(&scene), &geo, &settings, 0);
                model_rings(frame, &records, &settings, [case.sigma_t; 3], case.albedo)
            }
        })
        .collect();
    (0..frame.rings)
        .filter(|&j| frame.count[j] > 0)
        .map(|j| {
            (
                ring_edge(j as u32),
                renders.iter().map(|r| r.data[j]).collect(),
                traces.iter().map(|t| t[j]).collect(),
            )
        })
        .collect()
}

/// Mitsuba 3's volumetric path tracer and subsurf's light tracer agree on the ring sums of a
/// box (isotropic), a sphere (forward-scattering, curved, light leaving through its sides) and
/// a box of heterogeneous layers (delta tracking, the transmittance to the camera cell by cell)
/// within 5 % where the rings hold at least 5 % of the brightest ring's light: two
/// estimators from opposite ends of the path, so a wrong pinhole factor, filter, phase function
/// or boundary crossing shows as a ratio away from 1.
#[test]
fn mitsuba_renders_of_a_box_and_a_sphere_agree_with_the_tracer() {
    let Some(py) = mitsuba() else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let cases = [
        Case {
            name: "box",
            mesh: block(),
            sigma_t: 1.0,
            albedo: [0.95, 0.9, 0.8],
            g: 0.0,
            grid: None,
            grid_albedo: Vec::new(),
            dielectric: None,
        },
        Case {
            name: "sphere",
            mesh: sphere(6.0, 3),
            sigma_t: 1.0,
            albedo: [0.95, 0.9, 0.8],
            g: 0.3,
            grid: None,
            grid_albedo: Vec::new(),
            dielectric: None,
        },
        // Heterogeneous: the box in 2 × 1 × 3 cells, the top 5 mm denser on one side of the
        // spot than on the other, its albedo different again, over a middle and a deep layer.
        Case {
            name: "layers",
            mesh: block(),
            sigma_t: 1.0,
            albedo: [0.95, 0.9, 0.8],
            g: 0.3,
            grid: Some(GridChannel {
                origin: [-15.0, -15.0, -15.0],
                cell_mm: [15.0, 30.0, 5.0],
                dims: [2, 1, 3],
                sigma_t: vec![1.5, 1.5, 0.7, 0.7, 2.5, 1.0],
                albedo: Vec::new(),
            }),
            grid_albedo: vec![
                [0.95, 0.9, 0.8],
                [0.95, 0.9, 0.8],
                [0.99, 0.97, 0.9],
                [0.99, 0.97, 0.9],
                [0.9, 0.85, 0.7],
                [0.97, 0.95, 0.9],
            ],
            dielectric: None,
        },
    ];
    for case in &cases {
        let rings = compare(&py, tmp.path(), case);
        let top: [f64; 3] =
            std::array::from_fn(|c| rings.iter().map(|r| r.1[c]).fold(0.0, f64::max));
        let (mut judged, mut off) = (0, Vec::new());
        for (r, data, model) in &rings {
            let ratio: [f64; 3] = std::array::from_fn(|c| model[c] / data[c]);
            eprintln!(
                "{} ring {r:.2} mm: subsurf / mitsuba {ratio:.3?}",
                case.name
            );
            // Rings with at least 5 % of the brightest ring's light: beyond, Mitsuba's own
            // noise (camera paths that rarely reach the lit volume) exceeds the tolerance.
            for c in 0..3 {
                if data[c] > 0.05 * top[c] {
                    judged += 1;
                    if (ratio[c] - 1.0).abs() >= 0.05 {
                        off.push((*r, c, ratio[c]));
                    }
                }
            }
        }
        assert!(
            off.is_empty(),
            "{}: rings off by 5 % or more: {off:?}",
            case.name
        );
        assert!(judged >= 15, "{}: {judged} rings judged", case.name);
    }
}

/// The mean of `x` and its standard error.
fn mean_se(x: &[f64]) -> (f64, f64) {
    let n = x.len() as f64;
    let m = x.iter().sum::<f64>() / n;
    let var = x.iter().map(|v| (v - m).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
    (m, (var / n).sqrt())
}

/// The two-sided 95 % t value at `dof` degrees of freedom (1 to 10; beyond, 10's).
fn t95(dof: usize) -> f64 {
    const T: [f64; 10] = [
        12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228,
    ];
    T[dof.clamp(1, 10) - 1]
}

/// Judges seeded rings ([`compare_seeds`]): every ring holding at least `share` of the
/// brightest ring's light, and the rings in `band` (mm) summed, are off when their ratio of
/// means (subsurf / Mitsuba) is further from 1 than 2 % plus the 95 % t-interval of both
/// sides' seed spreads (its degrees of freedom those of the fewer seeds, Mitsuba's). Returns the rings off (ring, channel, ratio, se) and how many
/// ring-channels were judged to within ±5 % (so that a test cannot pass by noise alone).
fn judge_seeded(
    name: &str,
    rings: &[SeededRing],
    share: f64,
    band: (f64, f64),
) -> (Vec<(f64, usize, f64, f64)>, usize) {
    let ratio = |data: &[f64], model: &[f64]| {
        let ((m, se_m), (t, se_t)) = (mean_se(data), mean_se(model));
        let r = t / m;
        (r, r * ((se_m / m).powi(2) + (se_t / t).powi(2)).sqrt())
    };
    let channel = |v: &[[f64; 3]], c: usize| v.iter().map(|x| x[c]).collect::<Vec<_>>();
    let top: [f64; 3] = std::array::from_fn(|c| {
        rings
            .iter()
            .map(|r| mean_se(&channel(&r.1, c)).0)
            .fold(0.0, f64::max)
    });
    let t = t95(rings[0].1.len().min(rings[0].2.len()) - 1);
    let (mut off, mut sharp) = (Vec::new(), 0);
    for (r, data, model) in rings {
        let judged: Vec<(f64, f64)> = (0..3)
            .map(|c| ratio(&channel(data, c), &channel(model, c)))
            .collect();
        eprintln!("{name} ring {r:.2} mm: subsurf / mitsuba (ratio, se) {judged:.3?}");
        for (c, (q, se)) in judged.iter().enumerate() {
            if mean_se(&channel(data, c)).0 > share * top[c] {
                sharp += usize::from(t * se < 0.05);
                if (q - 1.0).abs() > 0.02 + t * se {
                    off.push((*r, c, *q, *se));
                }
            }
        }
    }
    let rows: Vec<usize> = (0..rings.len())
        .filter(|&j| (band.0..band.1).contains(&rings[j].0))
        .collect();
    // Per seed, the band's sum: Mitsuba's renders (`model` false) or subsurf's traces.
    let sum = |model: bool, c: usize| -> Vec<f64> {
        let side = |j: usize| if model { &rings[j].2 } else { &rings[j].1 };
        (0..side(rows[0]).len())
            .map(|s| rows.iter().map(|&j| side(j)[s][c]).sum())
            .collect()
    };
    for c in 0..3 {
        let (q, se) = ratio(&sum(false, c), &sum(true, c));
        eprintln!(
            "{name} band {:.1}-{:.1} mm, channel {c}: subsurf / mitsuba {q:.3} ± {se:.3}",
            band.0, band.1
        );
        if (q - 1.0).abs() > 0.02 + t * se {
            off.push((band.0, c, q, se));
        }
    }
    (off, sharp)
}

/// sample-torus's mesh (a ring: light leaves the tube and meets the ring again across its
/// hole) under the spot, its tube's top at the origin: Mitsuba 3 and subsurf's tracer on every
/// ring holding at least 1 % of the brightest ring's light, the far ones included, and on the
/// band 3.7–10 mm as a whole, each within 2 % plus the 95 % t-interval of the two renderers'
/// seed noise (three Mitsuba seeds, eight traces: 2 degrees of freedom, t95 4.30). One trace against one render is not enough out there: a single trace's rings at
/// 5–10 mm range 0.79–1.19 of Mitsuba's mean over six seeds, and one seed read as a 5–11 %
/// deficit until its own noise was measured (docs/volume.md). Ignored for its time (three
/// Mitsuba renders, about 4 minutes); run it with `--ignored` to see the rings.
#[test]
#[ignore = "about 4 minutes: three Mitsuba renders of the torus"]
fn mitsuba_and_the_tracer_agree_on_a_torus_far_from_the_spot() {
    let Some(py) = mitsuba() else {
        return;
    };
    let dir = workspace().join("../shared/data/sample-torus");
    if !dir.join("scan.json").is_file() {
        eprintln!("SKIPPED: {} is absent", dir.display());
        return;
    }
    let ds = Dataset::open(&dir).unwrap();
    // The tube's top (ρ = 13 mm, z = 12 mm) moved to the origin, under the spot.
    let p = ds
        .mesh
        .positions
        .iter()
        .map(|v| [v[0] - 13.0, v[1], v[2] - 12.0])
        .collect();
    let mesh = Mesh::new(p, ds.mesh.triangles.clone()).0;
    let tmp = tempfile::tempdir().unwrap();
    let case = Case {
        name: "torus",
        mesh,
        sigma_t: 2.0,
        albedo: [0.97, 0.95, 0.9],
        g: 0.0,
        grid: None,
        grid_albedo: Vec::new(),
        dielectric: None,
    };
    let rings = compare_seeds(
        &py,
        tmp.path(),
        &case,
        &[3, 4, 5],
        &[1, 2, 3, 4, 5, 6, 7, 8],
    );
    let (off, sharp) = judge_seeded("torus", &rings, 0.01, (3.7, 10.0));
    assert!(
        off.is_empty(),
        "torus: rings beyond their noise (ring, channel, ratio, se): {off:?}"
    );
    assert!(sharp >= 18, "only {sharp} ring-channels judged within ±5 %");
}

/// The box-and-sphere test's sphere (radius 6 mm, σ_t 1/mm, albedo 0.95 / 0.9 / 0.8, g 0.3)
/// behind sample-pebble's boundary, a rough dielectric (index 1.55, GGX α 0.2): Mitsuba 3's
/// `volpath` with its `roughdielectric` and subsurf's tracer, next events from the surface, on
/// every ring holding at least 5 % of the brightest ring's light and on the band 1–6 mm, within
/// 2 % plus the 95 % t-interval of both renderers' seed noise (eight Mitsuba seeds, eight
/// traces: 7 degrees of freedom, t95 2.36). Ignored for its time (eight Mitsuba renders, about
/// 2 minutes).
#[test]
#[ignore = "about 2 minutes: eight Mitsuba renders behind a rough dielectric"]
fn mitsuba_and_the_tracer_agree_behind_a_rough_dielectric() {
    let Some(py) = mitsuba() else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let case = Case {
        name: "glass-sphere",
        mesh: sphere(6.0, 3),
        sigma_t: 1.0,
        albedo: [0.95, 0.9, 0.8],
        g: 0.3,
        grid: None,
        grid_albedo: Vec::new(),
        dielectric: Some((1.55, 0.2)),
    };
    let seeds: Vec<u32> = (3..11).collect();
    let rings = compare_seeds(&py, tmp.path(), &case, &seeds, &[1, 2, 3, 4, 5, 6, 7, 8]);
    let (off, sharp) = judge_seeded("dielectric sphere", &rings, 0.05, (1.0, 6.0));
    assert!(
        off.is_empty(),
        "rings beyond their noise (ring, channel, ratio, se): {off:?}"
    );
    assert!(sharp >= 15, "only {sharp} ring-channels judged within ±5 %");
}

/// The outside renderer's sample-slab (a homogeneous slab, σ_t = 2/mm, albedo 0.99 / 0.985 /
/// 0.98, isotropic, index-matched, as its README gives them) is predicted from the published
/// medium alone: frame 4's ring sums from 0.5 to 4.5 mm within 5 % in every channel, with the
/// slab's open top face bounding the medium as far as it reaches.
#[test]
fn sample_slab_rings_follow_from_its_published_medium() {
    let dir = workspace().join("../shared/data/sample-slab");
    if !dir.join("scan.json").is_file() {
        eprintln!("SKIPPED: {} is absent", dir.display());
        return;
    }
    let ds = Dataset::open(&dir).unwrap();
    let scene = Scene::new(ds.mesh.clone()).unwrap();
    assert_eq!(Boundary::of(&scene), Boundary::Open);
    let k = 4;
    let geo = frame_geometry(&scene, &ds, k).unwrap();
    let settings = TraceSettings::for_medium([2.0; 3], [0.99, 0.985, 0.98], 0.0, 60_000, 11);
    let records = trace_frame(&scene, Boundary::Open, &geo, &settings, k);
    let img = ds.read_frame(k).unwrap();
    let frame = FrameRings::new(&scene, geo, k, &img, ds.spec.frames[k].exposure_s);
    let model = model_rings(&frame, &records, &settings, [2.0; 3], [0.99, 0.985, 0.98]);
    let mut judged = 0;
    for (j, m) in model.iter().enumerate() {
        let r = ring_edge(j as u32);
        if frame.count[j] == 0 || r > 4.5 {
            continue;
        }
        let ratio: [f64; 3] = std::array::from_fn(|c| m[c] / frame.data[j][c]);
        eprintln!(
            "ring {r:.2} mm ({} px): model / data {ratio:.3?}",
            frame.count[j]
        );
        for (c, x) in ratio.iter().enumerate() {
            assert!(
                (x - 1.0).abs() < 0.05,
                "ring {r:.2} mm channel {c}: {ratio:?}"
            );
            judged += 1;
        }
    }
    assert!(judged >= 15, "{judged}");
}

/// The fit recovers sample-slab's published medium (σ_t = 2/mm, albedo 0.99 / 0.985 / 0.98)
/// from its training frames alone, started well away from it (1.3/mm, 0.96): σ_t within 5 % and
/// albedo within 0.004 in every channel. (Measured in release, 1,000 photons a frame and 12
/// rounds: σ_t 2.044 / 1.990 / 1.988, albedo 0.9930 / 0.9875 / 0.9827.)
#[test]
fn the_fit_recovers_sample_slabs_published_medium() {
    use subsurf::volume::fit::{HomogeneousFit, fit_homogeneous};
    let dir = workspace().join("../shared/data/sample-slab");
    if !dir.join("scan.json").is_file() {
        eprintln!("SKIPPED: {} is absent", dir.display());
        return;
    }
    let ds = Dataset::open(&dir).unwrap();
    let opts = HomogeneousFit {
        photons: 1000,
        rounds: 12,
        g: 0.0,
        start: (1.3, 0.96),
        floor: ds.spec.noise_floor.unwrap(),
        seed: 1,
        surface: Surface::IndexMatched,
    };
    let m = fit_homogeneous(&ds, &[0, 2, 3, 4, 6, 7, 8], &opts, &|r, m| {
        eprintln!("round {r}: {:?} {:?}", m.sigma_t, m.albedo);
    })
    .unwrap();
    let truth = [0.99, 0.985, 0.98];
    for (c, t) in truth.iter().enumerate() {
        assert!((m.sigma_t[c] / 2.0 - 1.0).abs() < 0.05, "{m:?}");
        assert!((m.albedo[c] - t).abs() < 0.004, "{m:?}");
    }
}

/// sample-slab, or `None` (after printing `SKIPPED:`) where the shared data is absent.
fn sample_slab() -> Option<PathBuf> {
    let dir = workspace().join("../shared/data/sample-slab");
    if dir.join("scan.json").is_file() {
        Some(dir)
    } else {
        eprintln!("SKIPPED: {} is absent", dir.display());
        None
    }
}

/// A volume model read back from its file predicts the same images as the fit's `predict` with
/// the same medium on the dataset's mesh, bit for bit; a grid whose cells differ is refused
/// with the typed error until the tracer follows it.
#[test]
fn a_volume_model_from_its_file_predicts_as_the_fit_does() {
    use subsurf::volume::fit::{Homogeneous, predict};
    use subsurf::volume::{FitInfo, MediumGrid, VolumeModel, predict_model};
    let Some(dir) = sample_slab() else {
        return;
    };
    let ds = Dataset::open(&dir).unwrap();
    let medium = Homogeneous {
        sigma_t: [2.0, 1.9, 2.1],
        albedo: [0.99, 0.985, 0.98],
        g: 0.2,
        loss: [(0.0, 0); 3],
        surface: Surface::IndexMatched,
    };
    let info = FitInfo {
        frames: vec![0],
        photons: 1,
        rounds: 1,
        loss: [0.0; 3],
        rings: [0; 3],
        seconds: 0.0,
        subsurf_version: "test".into(),
    };
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("v.json");
    VolumeModel::homogeneous(&ds.mesh, &medium, info)
        .write(&path)
        .unwrap();
    let model = VolumeModel::read(&path).unwrap();
    let ours = predict_model(&ds, &[4, 6], &model, 3000, 5).unwrap();
    let theirs = predict(&ds, &[4, 6], &medium, 3000, 5).unwrap();
    assert_eq!(ours.len(), 2);
    for ((k, a), (j, b)) in ours.iter().zip(&theirs) {
        assert_eq!(k, j);
        assert!(a.data.iter().any(|&v| v > 0.0), "frame {k} is black");
        assert_eq!(a.data, b.data, "frame {k}");
    }
    let mut grid = model.clone();
    let (lo, hi) = model.mesh.bounds();
    grid.grid = MediumGrid::homogeneous(lo, hi, medium.sigma_t, medium.albedo);
    grid.grid.dims = [2, 1, 1];
    grid.grid.cell_mm[0] /= 2.0;
    grid.grid.sigma_t = vec![[2.0; 3], [3.0; 3]];
    grid.grid.albedo = vec![[0.99; 3]; 2];
    // Cells that differ are traced by delta tracking: a lit, finite image.
    let img = &predict_model(&ds, &[4], &grid, 3000, 5).unwrap()[0].1;
    assert!(img.data.iter().all(|v| v.is_finite()));
    assert!(
        img.data.iter().any(|&v| v > 0.0),
        "the heterogeneous frame is black"
    );
}

/// `subsurf` with `args`, its output whatever it is.
fn run(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_subsurf"))
        .args(args)
        .output()
        .unwrap()
}

/// `subsurf predict` of the volume model `model` writes frame `frame` of `scan` as a finite
/// image with light in it.
fn predicts_a_lit_frame(model: &Path, scan: &str, frame: &str, photons: &str, dir: &Path) {
    let img = dir.join("p.exr");
    let o = run(&[
        "predict",
        "--model",
        model.to_str().unwrap(),
        "--scan",
        scan,
        "--frame",
        frame,
        "--photons",
        photons,
        "--out",
        img.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let img = read_image(&img).unwrap();
    assert!(img.data.iter().all(|v| v.is_finite()));
    assert!(img.data.iter().any(|&v| v > 0.0));
}

/// `subsurf fit --model-kind volume` on sample-slab's training frames (few photons and rounds:
/// a check of the plumbing, not of the figures) writes a volume model that reads back, and
/// `evaluate` and `predict` take it: finite figures on frames it was fitted to, a lit image.
#[test]
fn fit_evaluate_and_predict_take_a_volume_model() {
    use subsurf::volume::VolumeModel;
    let Some(dir) = sample_slab() else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("slab.json");
    let scan = dir.to_str().unwrap();
    let fit = |out: &Path| {
        run(&[
            "fit",
            "--scan",
            scan,
            "--model-kind",
            "volume",
            "--exclude-frames",
            "1,5",
            "--volume-photons",
            "300",
            "--volume-rounds",
            "2",
            "--out",
            out.to_str().unwrap(),
        ])
    };
    let refused = fit(&tmp.path().join("slab.ply"));
    assert!(!refused.status.success());
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(err.contains(".json"), "{err}");
    let o = fit(&out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let said = String::from_utf8_lossy(&o.stdout);
    assert!(said.contains("volume: σ_t"), "{said}");
    let model = VolumeModel::read(&out).unwrap();
    assert_eq!(model.fit.frames, [0, 2, 3, 4, 6, 7, 8]);
    assert_eq!((model.fit.photons, model.fit.rounds), (300, 2));
    assert!(model.grid.is_uniform());
    assert!(
        model.grid.sigma_t[0]
            .iter()
            .all(|s| s.is_finite() && *s > 0.0)
    );
    let o = run(&[
        "evaluate",
        "--model",
        out.to_str().unwrap(),
        "--scan",
        scan,
        "--frames",
        "3,4",
        "--photons",
        "3000",
        "--json",
        "--cache",
        "off",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["volume_photons"], 3000, "{v}");
    assert_eq!(v["in_sample_frames"], serde_json::json!([3, 4]), "{v}");
    for c in 0..3 {
        let m = v["in_sample"]["mean_log_e"][c].as_f64();
        assert!(m.is_some_and(|m| m.is_finite() && m > 0.0), "{v}");
    }
    predicts_a_lit_frame(&out, scan, "4", "2000", tmp.path());
}

/// A grid fitted cell by cell (`volume::gridfit`, the settings `--volume-cells` uses) to
/// sample-slab's training frames, whose medium is homogeneous (σ_t = 2/mm, albedo 0.99 /
/// 0.985 / 0.98), finds no heterogeneity the frames do not have: every cell the training light
/// reached stays near the published medium, and the rings fit as well as the homogeneous
/// medium's do.
#[test]
fn a_grid_fitted_to_the_homogeneous_slab_stays_at_its_published_medium() {
    use subsurf::volume::fit::{HomogeneousFit, fit_homogeneous};
    use subsurf::volume::gridfit::{GridFit, fit_grid};
    let Some(dir) = sample_slab() else {
        return;
    };
    let ds = Dataset::open(&dir).unwrap();
    let train = [0, 2, 3, 4, 6, 7, 8];
    let opts = HomogeneousFit {
        photons: 1500,
        rounds: 12,
        g: 0.0,
        start: (2.0, 0.98),
        floor: ds.spec.noise_floor.unwrap(),
        seed: 1,
        surface: Surface::IndexMatched,
    };
    let global = fit_homogeneous(&ds, &train, &opts, &|_, _| {}).unwrap();
    let fitted = fit_grid(&ds, &train, &global, &GridFit::defaults(opts, 6), &|s| {
        eprintln!("{s}")
    })
    .unwrap();
    assert!(fitted.active >= 4, "{} cells fitted", fitted.active);
    let truth = [0.99, 0.985, 0.98];
    let (mut s_dev, mut a_dev) = (0.0f64, 0.0f64);
    for (c, g) in fitted.grid.iter().enumerate() {
        for (s, a) in g.sigma_t.iter().zip(&g.albedo) {
            s_dev = s_dev.max((s / 2.0).ln().abs());
            a_dev = a_dev.max(((1.0 - a) / (1.0 - truth[c])).ln().abs());
        }
    }
    eprintln!("largest deviation: ln σ_t {s_dev:.3}, ln(1 − α) {a_dev:.3}");
    eprintln!(
        "ring loss grid {:?}, homogeneous {:?}",
        fitted.loss, global.loss
    );
    assert!(s_dev < 0.15, "σ_t off by {s_dev} in ln");
    assert!(a_dev < 0.35, "1 − albedo off by {a_dev} in ln");
    for c in 0..3 {
        assert!(
            fitted.loss[c].0 <= 1.5 * global.loss[c].0 + 0.01,
            "{:?} {:?}",
            fitted.loss,
            global.loss
        );
    }
}

/// Behind the rough dielectric its README describes (index 1.55, GGX width 0.2, g = 0.3),
/// `subsurf fit --model-kind volume --volume-boundary dielectric:1.55:0.2` fits a quarter of
/// sample-pebble's training frames with a medium inside the README's published ranges (σ_t
/// 0.94–3.6/mm, albedo 0.90–0.995 in every channel), where the index-matched fit of the same
/// frames puts σ_t below them (the light the dielectric keeps inside by internal reflection is
/// read as a thinner medium). The file keeps the boundary and `predict` traces it; a grid
/// fitted behind it does the same.
#[test]
fn behind_its_rough_dielectric_the_pebble_fits_inside_its_published_medium() {
    use subsurf::volume::VolumeModel;
    use subsurf::volume::model::BoundaryModel;
    let dir = workspace().join("../shared/data/sample-pebble");
    if !dir.join("scan.json").is_file() {
        eprintln!("SKIPPED: {} is absent", dir.display());
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let scan = dir.to_str().unwrap();
    let frames: Vec<String> = (0..96).step_by(4).map(|k| k.to_string()).collect();
    let frames = frames.join(",");
    let fit = |name: &str, extra: &[&str]| {
        let out = tmp.path().join(name);
        let mut a = vec!["fit", "--scan", scan, "--model-kind", "volume", "--frames"];
        a.extend([
            frames.as_str(),
            "--volume-photons",
            "3000",
            "--volume-rounds",
            "8",
        ]);
        a.extend(["--out", out.to_str().unwrap()]);
        a.extend(extra);
        let o = run(&a);
        (out, o)
    };
    let dielectric = [
        "--volume-boundary",
        "dielectric:1.55:0.2",
        "--volume-g",
        "0.3",
    ];
    let (out, o) = fit("pebble.json", &dielectric);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let m = VolumeModel::read(&out).unwrap();
    assert_eq!(
        m.boundary,
        BoundaryModel::Dielectric {
            ior: 1.55,
            roughness: 0.2
        }
    );
    assert_eq!(m.g, 0.3);
    let (s, a) = (m.grid.sigma_t[0], m.grid.albedo[0]);
    eprintln!("behind the dielectric: σ_t {s:.4?} /mm, albedo {a:.4?}");
    for c in 0..3 {
        assert!((0.94..=3.6).contains(&s[c]), "σ_t {s:?}");
        assert!((0.90..=0.995).contains(&a[c]), "albedo {a:?}");
    }
    let (out_im, o) = fit("pebble-im.json", &[]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let im = VolumeModel::read(&out_im).unwrap();
    eprintln!(
        "index-matched: σ_t {:.4?} /mm, albedo {:.4?}",
        im.grid.sigma_t[0], im.grid.albedo[0]
    );
    assert!(im.grid.sigma_t[0].iter().all(|&s| s < 0.94), "{im:?}");
    predicts_a_lit_frame(&out, scan, "97", "20000", tmp.path());
    // A grid behind the same boundary: its cells differ, stay inside the published ranges,
    // and the file traces behind the dielectric.
    let (out_grid, o) = fit(
        "grid.json",
        &[&dielectric[..], &["--volume-cells", "4"]].concat(),
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let gm = VolumeModel::read(&out_grid).unwrap();
    assert_eq!(gm.boundary, m.boundary);
    assert!(
        gm.grid.cells() > 1 && !gm.grid.is_uniform(),
        "{:?}",
        gm.grid
    );
    for (s, a) in gm.grid.sigma_t.iter().zip(&gm.grid.albedo) {
        for c in 0..3 {
            assert!((0.94..=3.6).contains(&s[c]), "a cell's σ_t {s:?}");
            assert!((0.90..=0.995).contains(&a[c]), "a cell's albedo {a:?}");
        }
    }
    predicts_a_lit_frame(&out_grid, scan, "97", "20000", tmp.path());
}
