//! The scan's own evidence of where the surface is: per frame, the laser spot found in the image
//! (registration's [`detect_spot`], which needs no mesh) gives a camera ray; the frame's laser
//! ray crosses it at the lit surface point. Triangulated in the world frame and turned back by
//! the frame's turntable angle, every such point lies on the object's surface in the object frame,
//! whatever the mesh's pose.
use rayon::prelude::*;

use crate::dataset::{Dataset, DatasetError, FrameSpec};
use crate::geometry::{Camera, V3, add_scaled, dist, dot, normalize, sub, world_to_turntable};
use crate::progress::Progress;
use crate::spot::{Spot, detect_spot};

/// One triangulated laser spot.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct SpotPoint {
    /// Index of the frame in `scan.json`.
    pub frame: usize,
    /// The surface point, object frame, mm: on the camera ray through the spot, where it passes
    /// closest to the laser ray. The camera ray, not the midpoint: the spot is seen along it to a
    /// fraction of a pixel, while a galvo calibration predicts the laser's line less well.
    pub point: V3,
    /// How far the two rays pass from each other, mm.
    pub gap_mm: f64,
    /// One pixel's footprint at the point, mm (distance along the ray / focal length): turns
    /// millimetres into image pixels.
    pub footprint_mm: f64,
    /// Unit direction from the point towards the camera centre, object frame.
    pub to_camera: V3,
    /// Unit direction from the point back along the laser ray, object frame.
    pub to_laser: V3,
    /// The spot's sub-pixel position in the image.
    pub uv: [f64; 2],
}

/// Why a frame gave no point.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum NoPoint {
    /// The frame has no `laser` ray to triangulate against.
    NoLaserRay,
    /// No pixel is bright enough to be the spot.
    NoSpot,
    /// The camera ray and the laser ray do not meet in front of both (parallel, or crossing
    /// behind one of them).
    RaysDoNotMeet,
    /// They pass farther apart than the bound: the brightest pixel is not the spot on the
    /// laser's line (the laser missed the object, or lit a part the camera cannot see).
    RaysApart,
}

/// Settings of the triangulation.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct EvidenceOptions {
    /// Smallest peak radiance (pixel / exposure) that counts as a spot.
    pub min_peak: f64,
    /// Raw pixel value at which the sensor clips.
    pub saturation: Option<f64>,
    /// Largest distance between the camera ray and the laser ray, in pixel footprints at the
    /// point.
    pub max_gap_px: f64,
}

/// The triangulated points of a set of frames, and what the other frames lacked.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct Evidence {
    /// The points, in frame order.
    pub points: Vec<SpotPoint>,
    /// Frames looked at.
    pub frames: usize,
    /// Frames without a laser ray.
    pub no_laser_ray: usize,
    /// Frames without a spot.
    pub no_spot: usize,
    /// Frames whose rays did not meet within the bound.
    pub rays_apart: usize,
}

/// Crosses the camera ray through `spot` with the frame's laser ray.
pub fn triangulate(
    frame: usize,
    spec: &FrameSpec,
    cam: &Camera,
    spot: &Spot,
    max_gap_px: f64,
) -> Result<SpotPoint, NoPoint> {
    let laser = spec.laser.as_ref().ok_or(NoPoint::NoLaserRay)?;
    let (o1, d1) = cam.ray(spot.u, spot.v).ok_or(NoPoint::RaysDoNotMeet)?;
    let d2 = normalize(laser.direction).ok_or(NoPoint::RaysDoNotMeet)?;
    let o2 = laser.origin;
    // Closest approach of o1 + s·d1 and o2 + t·d2 (both unit).
    let w = sub(o1, o2);
    let b = dot(d1, d2);
    let den = 1.0 - b * b;
    if den.is_nan() || den <= 1e-10 {
        return Err(NoPoint::RaysDoNotMeet);
    }
    let (d, e) = (dot(d1, w), dot(d2, w));
    let s = (b * e - d) / den;
    let t = (e - b * d) / den;
    if !(s > 0.0 && t > 0.0) {
        return Err(NoPoint::RaysDoNotMeet);
    }
    let on_camera = add_scaled(o1, s, d1);
    let gap_mm = dist(on_camera, add_scaled(o2, t, d2));
    let footprint_mm = s / cam.fx.min(cam.fy);
    if gap_mm.is_nan() || gap_mm > max_gap_px * footprint_mm {
        return Err(NoPoint::RaysApart);
    }
    let deg = spec.turntable_deg;
    Ok(SpotPoint {
        frame,
        point: world_to_turntable(on_camera, deg),
        gap_mm,
        footprint_mm,
        to_camera: world_to_turntable(d1.map(|x| -x), deg),
        to_laser: world_to_turntable(d2.map(|x| -x), deg),
        uv: [spot.u, spot.v],
    })
}

/// Triangulates the spot of every frame in `frames` (read one at a time per worker and
/// dropped). A frame that cannot be read is an error; a frame without a usable spot is counted.
pub fn spot_points(
    ds: &Dataset,
    frames: &[usize],
    opts: &EvidenceOptions,
    progress: &dyn Progress,
) -> Result<Evidence, DatasetError> {
    progress.start("laser spots", frames.len() as u64);
    let outcomes: Vec<Result<SpotPoint, NoPoint>> = frames
        .par_iter()
        .map(|&k| {
            let spec = &ds.spec.frames[k];
            let out = if spec.laser.is_none() {
                Err(NoPoint::NoLaserRay)
            } else {
                let img = ds.read_frame(k)?;
                let cam = &ds.spec.cameras[spec.camera];
                match detect_spot(&img, opts.min_peak * spec.exposure_s, opts.saturation) {
                    None => Err(NoPoint::NoSpot),
                    Some(spot) => triangulate(k, spec, cam, &spot, opts.max_gap_px),
                }
            };
            progress.inc(1);
            Ok(out)
        })
        .collect::<Result<_, DatasetError>>()?;
    let mut ev = Evidence {
        frames: frames.len(),
        ..Evidence::default()
    };
    for o in outcomes {
        match o {
            Ok(p) => ev.points.push(p),
            Err(NoPoint::NoLaserRay) => ev.no_laser_ray += 1,
            Err(NoPoint::NoSpot) => ev.no_spot += 1,
            Err(NoPoint::RaysDoNotMeet | NoPoint::RaysApart) => ev.rays_apart += 1,
        }
    }
    Ok(ev)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::{FrameChannel, LaserRay};
    use crate::geometry::turntable_to_world;

    fn frame(deg: f64, origin: V3, target: V3) -> FrameSpec {
        FrameSpec {
            image: "f.exr".into(),
            camera: 0,
            turntable_deg: deg,
            exposure_s: 1.0,
            channel: FrameChannel::Rgb,
            laser: Some(LaserRay {
                origin,
                direction: sub(target, origin),
            }),
            galvo: None,
            levels: Default::default(),
            brackets: Vec::new(),
        }
    }

    fn spot_at(cam: &Camera, p: V3) -> Spot {
        let [u, v] = cam.project(p).unwrap();
        Spot {
            u,
            v,
            peak: 1.0,
            saturated: false,
            peak_fit: 1.0,
            sigma_px: 1.0,
        }
    }

    #[test]
    fn a_seen_spot_on_the_laser_ray_triangulates_to_its_object_point() {
        let cam = Camera::look_at(
            [0.0, -500.0, 300.0],
            [0.0; 3],
            [0.0, 0.0, 1.0],
            1500.0,
            128,
            128,
        )
        .unwrap();
        let obj = [3.0, -2.0, 5.0];
        for deg in [0.0, 45.0, 250.0] {
            let world = turntable_to_world(obj, deg);
            let f = frame(deg, [0.0, -600.0, 500.0], world);
            let p = triangulate(7, &f, &cam, &spot_at(&cam, world), 2.0).unwrap();
            assert!(dist(p.point, obj) < 1e-9, "{p:?}");
            assert!(p.gap_mm < 1e-9);
            assert!((p.footprint_mm - dist(cam.center(), world) / 1500.0).abs() < 1e-9);
            // A spot beside the laser's line (here 5 px off) is not on it.
            let mut off = spot_at(&cam, world);
            off.u += 5.0;
            assert_eq!(triangulate(7, &f, &cam, &off, 2.0), Err(NoPoint::RaysApart));
        }
        let mut f = frame(0.0, [0.0; 3], [1.0, 0.0, 0.0]);
        f.laser = None;
        assert_eq!(
            triangulate(0, &f, &cam, &spot_at(&cam, obj), 2.0),
            Err(NoPoint::NoLaserRay)
        );
    }
}
