//! Stage `select` (section 5: "data is then collected from all images in which a particular
//! location on the object was illuminated yielding an incident light position x_i [...] we select
//! for each vertex in the mesh the closest light position x_i"): registered frames whose x_i agree
//! within the pooling tolerance form one light position ([`lights::pool`]); vertices
//! that chose the same light position per channel form a group and share one fit; a group's
//! samples are read from every frame of its light positions.
//!
//! Owns which samples a fit sees (and in which direction φ around x_i each lies); never fits.

pub mod lights;

use std::collections::BTreeMap;

use crate::geometry::{Scene, V3, dist};
use crate::model::TangentFrame;
use crate::samples::{Sample, SampleCounts};
use lights::{Light, pool, select};

use super::findings::FailReason;
use super::load::Context;
use super::register::RegisteredFrame;

/// One sample of a group in one colour channel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GroupSample {
    /// |x_o − x_i|, mm.
    pub r: f64,
    /// s(x_i, x_o), radiance.
    pub s: f64,
    /// The vertex x_o (in the lattice pass, [`super::detail`]: the surface point's index).
    pub vertex: u32,
    /// The registered frame (index into the registered frames) the sample was read from: with
    /// `vertex`, it identifies one observation, whose channels form one row of the joint fit.
    pub frame: u32,
    /// Direction of x_o around x_i in the tangent frame at x_i (Eq. 3); `None` at x_i itself.
    pub phi: Option<f64>,
}

/// A group's samples per colour channel r, g, b.
pub type ChannelSamples = [Vec<GroupSample>; 3];

/// The light positions a group selected, per channel: the registered frames pooled into each.
#[derive(Debug, Clone, Default, PartialEq, Eq, PartialOrd, Ord)]
pub struct GroupKey {
    /// Per channel: indices into the registered frames of the light position that channel
    /// selected (every member frame; a frame contributes only the channels it measured).
    pub frames: [Vec<u32>; 3],
    /// Per channel: the member frame whose x_i is closest to the light position's mean (for the
    /// red channel's, the tangent frame at x_i is taken there).
    pub anchors: [u32; 3],
}

/// The selection: groups of vertices sharing their closest light position per channel.
#[derive(Debug, Clone, Default)]
pub struct Groups {
    /// Per group: the frames of its light positions, per channel.
    pub keys: Vec<GroupKey>,
    /// Per group: its vertices.
    pub members: Vec<Vec<u32>>,
    /// Per vertex: no light within the selection distance for some channel.
    pub no_data: Vec<bool>,
    /// How the registered frames were pooled into light positions.
    pub pooling: Pooling,
}

/// What pooling did (reported in `fit-report.json`, `frames.pooling`).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct Pooling {
    /// Frames whose x_i lie within this distance (mm) of a light position's first frame joined it.
    pub tolerance_mm: f64,
    /// Light positions some group uses.
    pub light_positions: usize,
    /// Registered frames some group uses.
    pub frames: usize,
    /// Of those, frames that share their light position with another frame (before pooling,
    /// selection kept only the frame closest to each vertex and dropped the others' samples).
    pub pooled_frames: usize,
}

/// The default pooling tolerance: half the mesh's median edge length, at most `max_select_mm`.
///
/// The model lives on the mesh's vertices, so the mesh resolves light positions only to about
/// an edge: frames whose x_i are closer than half an edge would be selected by the same or
/// adjacent vertices, each fitting a share of the samples of what is, at the model's resolution,
/// one light position. Every sample keeps its own frame's x_i for |x_o − x_i|, so pooling moves
/// no distance; it only moves where the joint fit is stored, by less than the selection
/// already does (a vertex takes its closest x_i up to `max_select_mm` away). On sample-torus
/// (edges 0.6–2.0 mm, median ~1.3) the inner ring is lit from three turntable angles at points
/// 0.23–0.25 mm apart, pooled; the next-closest spots are 1.29 mm apart (an edge) and stay apart.
pub fn default_pool_mm(scene: &Scene, max_select_mm: f64) -> f64 {
    let pos = &scene.mesh.positions;
    let mut edges: Vec<f64> = (0..pos.len())
        .flat_map(|v| {
            scene
                .neighbours(v)
                .iter()
                .filter(move |&&w| (w as usize) > v)
                .map(move |&w| dist(pos[v], pos[w as usize]))
        })
        .filter(|e| e.is_finite())
        .collect();
    if edges.is_empty() {
        return 0.0;
    }
    let mid = edges.len() / 2;
    let (_, median, _) = edges.select_nth_unstable_by(mid, f64::total_cmp);
    (0.5 * *median).min(max_select_mm).max(0.0)
}

/// Pools the registered frames into light positions (tolerance `pool_mm`, else
/// [`default_pool_mm`]), selects for every vertex its closest light position per channel (within
/// `max_select_mm`) and groups the vertices by that choice, in a deterministic order.
pub fn select_groups(ctx: &Context, regs: &[RegisteredFrame]) -> Groups {
    let lights: Vec<Light> = regs
        .iter()
        .map(|r| Light {
            frame: r.frame,
            x_i: r.x_i,
            channels: r.channels,
        })
        .collect();
    let tolerance_mm = ctx
        .opts
        .pool_mm
        .unwrap_or_else(|| default_pool_mm(&ctx.scene, ctx.opts.max_select_mm));
    let pooled = pool(&lights, tolerance_mm);
    let positions: Vec<Light> = pooled
        .iter()
        .map(|p| Light {
            frame: p.anchor as usize,
            x_i: p.x_i,
            channels: p.channels,
        })
        .collect();
    let sel = select(&ctx.ds.mesh.positions, &positions, ctx.opts.max_select_mm);
    let mut groups: BTreeMap<[u32; 3], Vec<u32>> = BTreeMap::new();
    let mut no_data = vec![false; sel.len()];
    for (v, s) in sel.iter().enumerate() {
        match s {
            [Some(a), Some(b), Some(c)] => groups.entry([*a, *b, *c]).or_default().push(v as u32),
            _ => no_data[v] = true,
        }
    }
    let mut used = vec![false; pooled.len()];
    let mut keys = Vec::with_capacity(groups.len());
    let mut members = Vec::with_capacity(groups.len());
    for (key, verts) in groups {
        for &l in &key {
            used[l as usize] = true;
        }
        keys.push(GroupKey {
            frames: key.map(|l| pooled[l as usize].members.clone()),
            anchors: key.map(|l| pooled[l as usize].anchor),
        });
        members.push(verts);
    }
    let used_lights = pooled.iter().zip(&used).filter(|(_, u)| **u);
    let pooling = Pooling {
        tolerance_mm,
        light_positions: used_lights.clone().count(),
        frames: used_lights.clone().map(|(p, _)| p.members.len()).sum(),
        pooled_frames: used_lights
            .map(|(p, _)| p.members.len())
            .filter(|&n| n > 1)
            .sum(),
    };
    Groups {
        keys,
        members,
        no_data,
        pooling,
    }
}

/// The samples of the group with light positions `key`: each distinct frame's from the store, channel
/// c taken from the frames of the light position channel c selected (every view of that x_i,
/// each sample at the distance from its own frame's x_i), directions φ in the tangent frame at
/// the red light position's anchor. `SampleCounts::pooled` counts the channel samples taken
/// from frames other than a light position's anchor. φ is measured only for a model of more
/// than one segment (`--segments`): of one, no fit, evaluation or bin reads it
/// ([`frame_observations`]), and its atan2 per sample was 2 % of a cross-validated fit at 1024 px.
pub fn group_samples(
    ctx: &Context,
    regs: &[RegisteredFrame],
    key: &GroupKey,
) -> Result<(ChannelSamples, SampleCounts), FailReason> {
    let mut data: ChannelSamples = Default::default();
    let mut counts = SampleCounts::default();
    let frame = group_frame(ctx, regs, key)?;
    let directions = ctx.opts.model.segments > 1;
    for l in group_frames(key) {
        let reg = &regs[l as usize];
        let fs = ctx.samples(reg).map_err(|_| FailReason::FrameUnreadable)?;
        counts.add(&fs.counts);
        add_frame_samples(
            &mut data,
            &mut counts,
            key,
            l,
            reg,
            &frame,
            &fs.samples,
            &ctx.ds.mesh.positions,
            directions,
        );
    }
    Ok((data, counts))
}

/// The tangent frame a group's directions φ are measured in (Eq. 3): at the red light
/// position's anchor x_i, from the interpolated normal there.
pub fn group_frame(
    ctx: &Context,
    regs: &[RegisteredFrame],
    key: &GroupKey,
) -> Result<TangentFrame, FailReason> {
    let red = regs[key.anchors[0] as usize];
    TangentFrame::from_normal(ctx.normal_at(red.triangle, red.x_i))
        .map_err(|_| FailReason::NonPhysical)
}

/// The distinct registered frames of a group's light positions, ascending.
pub fn group_frames(key: &GroupKey) -> Vec<u32> {
    let mut distinct: Vec<u32> = key.frames.iter().flatten().copied().collect();
    distinct.sort_unstable();
    distinct.dedup();
    distinct
}

/// Adds registered frame `l`'s samples `s` (read at `positions`: the mesh's vertices, or surface
/// points, whose index `Sample::vertex` is) to a group's channel samples, as
/// [`frame_observations`] measures them (φ with `directions`).
#[allow(clippy::too_many_arguments)]
pub fn add_frame_samples(
    data: &mut ChannelSamples,
    counts: &mut SampleCounts,
    key: &GroupKey,
    l: u32,
    reg: &RegisteredFrame,
    frame: &TangentFrame,
    s: &[Sample],
    positions: &[V3],
    directions: bool,
) {
    for (x, phi, takes) in frame_observations(key, l, reg, frame, s, positions, directions) {
        for (ch, slot) in data.iter_mut().enumerate() {
            if takes & (1 << ch) != 0 {
                slot.push(GroupSample {
                    r: x.r,
                    s: x.value[ch],
                    vertex: x.vertex,
                    frame: l,
                    phi,
                });
                counts.pooled += u64::from(key.anchors[ch] != l);
            }
        }
    }
}

/// How a group measures registered frame `l`'s samples `s` (read at `positions`): per sample,
/// its direction φ in `frame` ([`group_frame`]) around `l`'s own x_i (its distance `Sample::r`
/// is from that x_i too), and the channels the group takes from it (bit c: `l` belongs to the
/// light position channel c selected and the sample's channel c is valid). The one rule
/// [`group_samples`] and the lattice pass ([`super::detail`]) measure samples by. Without
/// `directions`, φ is not measured (`None`): for a model it cannot change
/// ([`crate::model::LnEvaluator::uses_direction`]).
pub fn frame_observations<'a>(
    key: &GroupKey,
    l: u32,
    reg: &'a RegisteredFrame,
    frame: &'a TangentFrame,
    s: &'a [Sample],
    positions: &'a [V3],
    directions: bool,
) -> impl Iterator<Item = (&'a Sample, Option<f64>, u8)> + 'a {
    let takes = (0..3).fold(0u8, |m, ch| {
        m | (u8::from(key.frames[ch].contains(&l)) << ch)
    });
    s.iter().filter_map(move |x| {
        let t = takes & x.valid;
        (t != 0).then(|| {
            let phi = directions
                .then(|| frame.direction(reg.x_i, positions[x.vertex as usize]))
                .flatten();
            (x, phi, t)
        })
    })
}
