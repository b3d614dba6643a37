//! Stage `register` (sections 4.1 and 5): the laser spot of every frame, found once, and its
//! light position x_i on the mesh.
//!
//! Owns what registration means for the fit: a [`RegisteredFrame`] carries the spot, and every
//! later stage uses that one instead of detecting it again. The spot is detected once per frame,
//! when the extraction pass decodes it ([`super::extract`]); this stage reads the outcome from the
//! run's sample store. Never keeps an image.
use crate::geometry::V3;
use crate::spot::{RegistrationOutcome, Spot};

use super::findings::FrameCounts;
use super::load::Context;

/// A frame whose spot lies on the object: its light position x_i and the spot it was found at.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RegisteredFrame {
    /// Frame index in the dataset.
    pub frame: usize,
    /// The light position x_i (object frame, mm).
    pub x_i: V3,
    /// Triangle of the mesh that holds x_i.
    pub triangle: u32,
    /// The spot in the frame's image (its light is excluded from the samples).
    pub spot: Spot,
    /// Bit c set = the frame measured colour channel c.
    pub channels: u8,
}

impl RegisteredFrame {
    /// The registered frame of an outcome, if registration found the spot on the object.
    fn of(ctx: &Context, k: usize, outcome: &RegistrationOutcome) -> Option<RegisteredFrame> {
        let RegistrationOutcome::Registered {
            x_i,
            triangle,
            spot,
            ..
        } = *outcome
        else {
            return None;
        };
        let channels = ctx.ds.spec.frames[k].channel.channels();
        Some(RegisteredFrame {
            frame: k,
            x_i,
            triangle,
            spot,
            channels: channels.iter().fold(0u8, |m, c| m | (1 << c)),
        })
    }
}

/// Whether the camera sees frame `reg`'s spot more grazing than the run's `spot_cos_min`
/// ([`crate::spot::spot_cos`]): registration keeps such frames down to
/// [`crate::spot::SPOT_COS_FLOOR`], the run decides whether to use them.
pub fn too_grazing(ctx: &Context, reg: &RegisteredFrame) -> bool {
    let min = ctx.opts.spot_cos_min;
    if min <= crate::spot::SPOT_COS_FLOOR {
        return false;
    }
    let f = &ctx.ds.spec.frames[reg.frame];
    crate::spot::spot_cos(&ctx.scene, f, ctx.camera(f.camera), reg.x_i, reg.triangle)
        .is_none_or(|c| c < min)
}

/// Registers frame `k` alone (evaluation, prediction, pictures); the reason as text if the frame
/// is not registered (or its spot is seen more grazing than the run's `spot_cos_min`) or cannot
/// be read.
pub fn register_one(ctx: &Context, k: usize) -> Result<RegisteredFrame, String> {
    let outcome = ctx.register(k)?;
    let reg = RegisteredFrame::of(ctx, k, &outcome).ok_or_else(|| {
        format!(
            "not registered: {}",
            outcome.why_not().unwrap_or_else(|| format!("{outcome:?}"))
        )
    })?;
    if too_grazing(ctx, &reg) {
        return Err(format!(
            "spot seen at a grazing angle (cos θ below {})",
            ctx.opts.spot_cos_min
        ));
    }
    Ok(reg)
}

/// The registered frames among `frames` (in the order given), from the run's sample store
/// ([`super::extract`]: each frame was registered once, when it was decoded); frames that are
/// not registered are counted in `counts` by reason. Without a store (or for a frame it lacks)
/// the frame is read and registered here. Frames whose spot is seen more grazing than the run's
/// `spot_cos_min` are counted (`grazing`) and left out.
pub fn registered(
    ctx: &Context,
    frames: &[usize],
    counts: &mut FrameCounts,
) -> Vec<RegisteredFrame> {
    let mut out = Vec::new();
    for &k in frames {
        match ctx.register(k) {
            Ok(o) => match o {
                RegistrationOutcome::Registered { .. } => match RegisteredFrame::of(ctx, k, &o) {
                    Some(r) if too_grazing(ctx, &r) => counts.grazing += 1,
                    Some(r) => {
                        counts.registered += 1;
                        out.push(r);
                    }
                    None => {}
                },
                RegistrationOutcome::NoSpot => {
                    counts.no_spot += 1;
                    counts.no_spot_frames.push(k);
                }
                RegistrationOutcome::SpotOffObject => counts.spot_off_object += 1,
                RegistrationOutcome::LaserMismatch { .. } => counts.laser_mismatch += 1,
            },
            Err(e) => {
                counts.unreadable += 1;
                if counts.unreadable_errors.len() < 10 {
                    counts.unreadable_errors.push(e);
                }
            }
        }
    }
    out
}
