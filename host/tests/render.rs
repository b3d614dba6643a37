//! End-to-end tests of the renderer and its pictures, through the public API and the binary.

use std::path::Path;
use std::process::Command;

use subsurf::render::{
    self, Camera, HierarchyParams, Light, Method, Quality, RenderOptions, image_stats,
};

/// A picture someone can look at: the right size, many colours, real contrast.
fn assert_picture(path: &Path, width: u32, height: u32) {
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

fn small_torus() -> render::VertexModel {
    render::synthetic::marble_torus(48, 20)
}

#[test]
fn render_writes_a_picture_and_a_linear_exr() {
    let dir = tempfile::tempdir().unwrap();
    let model = small_torus();
    let (lo, hi) = model.bounds();
    let cam = Camera::framing(lo, hi, render::DEFAULT_VIEW, 120, 90).unwrap();
    let lights: Vec<Light> = vec!["point:-60,-80,90:20000,20000,20000".parse().unwrap()];
    let out = render::render(&model, &lights, &cam, &RenderOptions::default()).unwrap();
    let png = dir.path().join("a.png");
    let exr = dir.path().join("a.exr");
    render::save_png(&out.image, None, &png).unwrap();
    render::save_exr(&out.image, &exr).unwrap();
    assert_picture(&png, 120, 90);
    let lin = image::open(&exr).unwrap().to_rgb32f();
    assert_eq!(lin.dimensions(), (120, 90));
    assert!(
        lin.pixels()
            .all(|p| p.0.iter().all(|v| v.is_finite() && *v >= 0.0))
    );
    let covered = out.image.covered.iter().filter(|c| **c).count();
    assert!(
        covered > 120 * 90 / 10,
        "the object fills a good part of the frame"
    );
    // The EXR holds the linear values, not the tone-mapped ones.
    let k = out.image.covered.iter().position(|c| *c).unwrap();
    let (x, y) = ((k % 120) as u32, (k / 120) as u32);
    assert_eq!(lin.get_pixel(x, y).0, out.image.pixels[k]);
}

#[test]
fn the_far_side_of_a_lit_object_is_darker_and_shadows_fall() {
    let model = small_torus();
    // Light straight down: the underside of the ring is in shadow; its light there arrives only
    // through transport, so it is much darker than the top.
    let lights: Vec<Light> = vec!["dir:0,0,-1".parse().unwrap()];
    let t = render::light_transport(&model, &lights, &RenderOptions::default()).unwrap();
    let (mut top, mut bottom) = (Vec::new(), Vec::new());
    for v in 0..model.len() {
        let nz = model.normals[v][2];
        if nz > 0.9 {
            top.push(t.exitance[v][0]);
        } else if nz < -0.9 {
            bottom.push(t.exitance[v][0]);
            assert_eq!(
                t.irradiance[v], [0.0; 3],
                "vertex {v} faces away from the light"
            );
        }
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    assert!(!top.is_empty() && !bottom.is_empty());
    assert!(
        mean(&top) > 20.0 * mean(&bottom),
        "top {} bottom {}",
        mean(&top),
        mean(&bottom)
    );
    assert!(mean(&bottom) > 0.0, "light scatters round to the underside");
    // Inner side of the ring facing the hole at the light's grazing angle: a vertex on the
    // inner equator facing +x at u = π is lit only from above, never through the ring.
    assert!(
        t.irradiance
            .iter()
            .all(|e| e.iter().all(|x| x.is_finite() && *x >= 0.0))
    );
}

#[test]
fn several_lights_add_up() {
    let model = render::synthetic::marble_torus(24, 10);
    let a: Light = "point:-60,-80,90:9000,9000,9000".parse().unwrap();
    let b: Light = "spot:80,0,60:-1,0,-0.5:40:0,3000,6000".parse().unwrap();
    let opts = RenderOptions {
        method: Method::Exact,
        eta: Some(1.3),
    };
    let ea = render::light_transport(&model, std::slice::from_ref(&a), &opts).unwrap();
    let eb = render::light_transport(&model, std::slice::from_ref(&b), &opts).unwrap();
    let both = render::light_transport(&model, &[a, b], &opts).unwrap();
    for v in 0..model.len() {
        for c in 0..3 {
            let sum = ea.exitance[v][c] + eb.exitance[v][c];
            assert!(
                (both.exitance[v][c] - sum).abs() <= 1e-9 * sum.max(1e-300),
                "vertex {v}"
            );
        }
    }
}

#[test]
fn balanced_quality_is_within_a_per_cent_of_the_exact_image() {
    let model = render::synthetic::marble_torus(60, 24);
    let (lo, hi) = model.bounds();
    let cam = Camera::framing(lo, hi, render::DEFAULT_VIEW, 80, 80).unwrap();
    let lights: Vec<Light> = vec!["point:-60,-80,90:20000,20000,20000".parse().unwrap()];
    let exact = render::render(
        &model,
        &lights,
        &cam,
        &RenderOptions {
            method: Method::Exact,
            eta: Some(1.3),
        },
    )
    .unwrap();
    let mut last = f64::INFINITY;
    for q in [Quality::Draft, Quality::Balanced, Quality::Best] {
        let opts = RenderOptions {
            method: Method::Hierarchical(q.params()),
            eta: Some(1.3),
        };
        let h = render::render(&model, &lights, &cam, &opts).unwrap();
        let err = render::relative_pixel_error(&h.image, &exact.image, 1e-3).unwrap();
        assert!(err <= last + 1e-12, "{q:?}: error {err} after {last}");
        last = err;
        if q != Quality::Draft {
            assert!(err < 0.01, "{q:?}: mean relative pixel error {err}");
        }
    }
    // The knob reaches the exact sum when it allows no approximation at all.
    let off = RenderOptions {
        method: Method::Hierarchical(HierarchyParams {
            max_solid_angle: 0.0,
            tail_tolerance: 0.0,
        }),
        eta: Some(1.3),
    };
    let h = render::render(&model, &lights, &cam, &off).unwrap();
    assert!(render::relative_pixel_error(&h.image, &exact.image, 0.0).unwrap() < 1e-6);
}

#[test]
fn subsurf_render_command_writes_png_and_exr() {
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("r.png");
    let exr = dir.path().join("r.exr");
    let out = Command::new(env!("CARGO_BIN_EXE_subsurf"))
        .args([
            "render",
            "--builtin",
            "torus:40,16",
            "--size",
            "96x72",
            "--quality",
            "draft",
        ])
        .args([
            "--light",
            "point:-60,-80,90:20000,20000,20000",
            "--light",
            "dir:1,0,-1:0.2,0.2,0.2",
        ])
        .arg("--out")
        .arg(&png)
        .arg("--exr")
        .arg(&exr)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_picture(&png, 96, 72);
    assert_eq!(
        image::open(&exr).unwrap().to_rgb32f().dimensions(),
        (96, 72)
    );
    // A bad light is a clear error, not a panic.
    let out = Command::new(env!("CARGO_BIN_EXE_subsurf"))
        .args([
            "render",
            "--builtin",
            "torus:20,8",
            "--light",
            "lamp:1,2,3",
            "--out",
        ])
        .arg(dir.path().join("x.png"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("lamp:1,2,3") && !err.contains("panicked"),
        "{err}"
    );
}
