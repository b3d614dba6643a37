//! Stage `select` (section 5: "we select for each vertex in the mesh the closest light position
//! x_i"): vertices that chose the same registered frame per channel form a group and share one
//! fit; a group's samples are read from those frames.
//!
//! Owns which samples a fit sees (and in which direction φ around x_i each lies); never fits.
use std::collections::BTreeMap;

use crate::model::TangentFrame;
use crate::samples::SampleCounts;
use crate::selection::{Light, select};

use super::load::Context;
use super::register::RegisteredFrame;
use super::report::FailReason;

/// One sample of a group in one colour channel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GroupSample {
    /// |x_o − x_i|, mm.
    pub r: f64,
    /// s(x_i, x_o), radiance.
    pub s: f64,
    /// The vertex x_o.
    pub vertex: u32,
    /// The registered frame (index into the registered frames) the sample was read from: with
    /// `vertex`, it identifies one observation, whose channels form one row of the joint fit.
    pub frame: u32,
    /// Direction of x_o around x_i in the tangent frame at x_i (Eq. 3); `None` at x_i itself.
    pub phi: Option<f64>,
}

/// A group's samples per colour channel r, g, b.
pub type ChannelSamples = [Vec<GroupSample>; 3];

/// The selection: groups of vertices sharing their closest light per channel.
#[derive(Debug, Clone, Default)]
pub struct Groups {
    /// Per group: the index into the registered frames of its light, per channel.
    pub keys: Vec<[u32; 3]>,
    /// Per group: its vertices.
    pub members: Vec<Vec<u32>>,
    /// Per vertex: no light within the selection distance for some channel.
    pub no_data: Vec<bool>,
}

/// Selects for every vertex its closest registered light per channel (within
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
    let sel = select(&ctx.ds.mesh.positions, &lights, ctx.opts.max_select_mm);
    let mut groups: BTreeMap<[u32; 3], Vec<u32>> = BTreeMap::new();
    let mut no_data = vec![false; sel.len()];
    for (v, s) in sel.iter().enumerate() {
        match s {
            [Some(a), Some(b), Some(c)] => groups.entry([*a, *b, *c]).or_default().push(v as u32),
            _ => no_data[v] = true,
        }
    }
    let (keys, members) = groups.into_iter().unzip();
    Groups {
        keys,
        members,
        no_data,
    }
}

/// The samples of the group with lights `key`: each distinct frame read once, channel c taken
/// from the frame channel c selected, directions φ in the tangent frame at the red light's x_i.
pub fn group_samples(
    ctx: &Context,
    regs: &[RegisteredFrame],
    key: &[u32; 3],
) -> Result<(ChannelSamples, SampleCounts), FailReason> {
    let mut data: ChannelSamples = Default::default();
    let mut counts = SampleCounts::default();
    let red = regs[key[0] as usize];
    let frame = TangentFrame::from_normal(ctx.normal_at(red.triangle, red.x_i))
        .map_err(|_| FailReason::NonPhysical)?;
    let mut distinct = key.to_vec();
    distinct.sort_unstable();
    distinct.dedup();
    for l in distinct {
        let reg = &regs[l as usize];
        let (s, c) = ctx.samples(reg).map_err(|_| FailReason::FrameUnreadable)?;
        counts.add(&c);
        for x in s {
            let (_, phi) = frame.polar(reg.x_i, ctx.ds.mesh.positions[x.vertex as usize]);
            for (ch, slot) in data.iter_mut().enumerate() {
                if key[ch] == l && x.valid & (1 << ch) != 0 {
                    slot.push(GroupSample {
                        r: x.r,
                        s: x.value[ch],
                        vertex: x.vertex,
                        frame: l,
                        phi,
                    });
                }
            }
        }
    }
    Ok((data, counts))
}
