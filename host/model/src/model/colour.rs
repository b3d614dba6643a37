//! Colour: per-channel fall-off (Eq. 3 per channel) or one shared fall-off scaled per channel
//! (Eq. 5, and Eq. 9 for the isotropic case used on arbitrary surfaces).

use serde::{Deserialize, Serialize};

use super::{Anisotropic, ModelError};

/// The RGB diffuse reflectance R_d at x_i.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum ColourModel {
    /// Eq. 3 fitted independently per channel (r, g, b).
    PerChannel {
        /// Fall-off per channel, in r, g, b order.
        channels: [Anisotropic; 3],
    },
    /// Eq. 5 / Eq. 9: (1, s_g, s_b)ᵀ · R_d, one fall-off for all channels (red scale is 1).
    Shared {
        /// The common fall-off (red channel).
        falloff: Anisotropic,
        /// Green scale s_g(x_i) > 0.
        s_g: f64,
        /// Blue scale s_b(x_i) > 0.
        s_b: f64,
    },
}

impl ColourModel {
    /// Checks every fall-off and scale.
    pub fn validate(&self) -> Result<(), ModelError> {
        match self {
            Self::PerChannel { channels } => channels.iter().try_for_each(Anisotropic::validate),
            Self::Shared { falloff, s_g, s_b } => {
                for (what, value) in [("s_g", *s_g), ("s_b", *s_b)] {
                    if !(value.is_finite() && value > 0.0) {
                        return Err(ModelError::BadScale { what, value });
                    }
                }
                falloff.validate()
            }
        }
    }

    /// ln R_d per channel at distance r and direction φ (see [`Anisotropic::ln_eval`]).
    pub fn ln_eval(&self, r: f64, phi: Option<f64>) -> [f64; 3] {
        match self {
            Self::PerChannel { channels } => [0, 1, 2].map(|c| channels[c].ln_eval(r, phi)),
            Self::Shared { falloff, s_g, s_b } => {
                let l = falloff.ln_eval(r, phi);
                [l, l + s_g.ln(), l + s_b.ln()]
            }
        }
    }

    /// ln R_d of one channel (0 = r, 1 = g, 2 = b): `self.ln_eval(r, phi)[channel]` to the bit,
    /// without the other channels' evaluations (the fit's hottest loops take one channel's
    /// samples at a time, and evaluated all three for each). NaN for a channel index above 2.
    pub fn ln_eval_channel(&self, channel: usize, r: f64, phi: Option<f64>) -> f64 {
        match self {
            Self::PerChannel { channels } => channels
                .get(channel)
                .map_or(f64::NAN, |c| c.ln_eval(r, phi)),
            Self::Shared { falloff, s_g, s_b } => match channel {
                0 => falloff.ln_eval(r, phi),
                1 => falloff.ln_eval(r, phi) + s_g.ln(),
                2 => falloff.ln_eval(r, phi) + s_b.ln(),
                _ => f64::NAN,
            },
        }
    }

    /// The model ready for many evaluations: ln s_g, ln s_b and every term's ln c_k taken once,
    /// not at every evaluation (at n = 3 terms an evaluation took 4 logs and 2 exps, now 1 and
    /// 2, on the fit's hottest path). Its evaluations are [`ColourModel::ln_eval`]'s and
    /// [`ColourModel::ln_eval_channel`]'s to the bit.
    pub fn ln_evaluator(&self) -> LnEvaluator<'_> {
        let ln_scale = match self {
            Self::PerChannel { .. } => [0.0; 2],
            Self::Shared { s_g, s_b, .. } => [s_g.ln(), s_b.ln()],
        };
        let falloffs: &[Anisotropic] = match self {
            Self::PerChannel { channels } => channels,
            Self::Shared { falloff, .. } => std::slice::from_ref(falloff),
        };
        let mut ln_c = Vec::new();
        let mut starts = Vec::new();
        let mut first = [0; 3];
        for (f, a) in falloffs.iter().enumerate() {
            first[f] = starts.len();
            for e in &a.segments {
                starts.push(ln_c.len());
                ln_c.extend(e.terms.iter().map(|t| t.c.ln()));
            }
        }
        starts.push(ln_c.len());
        LnEvaluator {
            model: self,
            ln_scale,
            ln_c,
            starts,
            first,
        }
    }

    /// R_d per channel at distance r and direction φ.
    pub fn eval(&self, r: f64, phi: Option<f64>) -> [f64; 3] {
        self.ln_eval(r, phi).map(f64::exp)
    }

    /// The fall-off model of one channel (0 = r, 1 = g, 2 = b), scales applied; `None` for a
    /// channel index above 2.
    pub fn channel(&self, channel: usize) -> Option<Anisotropic> {
        match self {
            Self::PerChannel { channels } => channels.get(channel).cloned(),
            Self::Shared { falloff, s_g, s_b } => {
                let s = [1.0, *s_g, *s_b].get(channel).copied()?;
                Some(Anisotropic {
                    segments: falloff.segments.iter().map(|e| e.scaled(s)).collect(),
                })
            }
        }
    }
}

/// [`ColourModel::ln_evaluator`]: a colour model with the logarithms of its channel scales and
/// of its terms' amplitudes taken.
#[derive(Debug, Clone)]
pub struct LnEvaluator<'a> {
    model: &'a ColourModel,
    /// ln s_g, ln s_b (shared colour; unused per channel).
    ln_scale: [f64; 2],
    /// ln c_k of every term, fall-off by fall-off (one shared, or r, g, b), segment by segment.
    ln_c: Vec<f64>,
    /// Where each segment's ln c_k start in `ln_c` (one more entry: the end).
    starts: Vec<usize>,
    /// Per fall-off, the index in `starts` of its first segment.
    first: [usize; 3],
}

impl LnEvaluator<'_> {
    /// Whether φ changes any evaluation: a fall-off of more than one segment (Eq. 3). With one
    /// segment, [`LnEvaluator::ln_eval`] at any φ (or none) is the same bits, so a caller may
    /// skip measuring it (an atan2 per sample: an eighth of the lattice pass at 1024 px).
    pub fn uses_direction(&self) -> bool {
        let falloffs: &[Anisotropic] = match self.model {
            ColourModel::PerChannel { channels } => channels,
            ColourModel::Shared { falloff, .. } => std::slice::from_ref(falloff),
        };
        falloffs.iter().any(|a| a.segments.len() > 1)
    }

    /// ln R_d of fall-off `f` (Eq. 3), its segments evaluated with their ln c_k taken.
    fn falloff(&self, f: usize, a: &Anisotropic, r: f64, phi: Option<f64>) -> f64 {
        let at = self.first[f];
        a.ln_eval_by(phi, |l| {
            let (i, j) = (self.starts[at + l], self.starts[at + l + 1]);
            a.segments[l].ln_eval_with(&self.ln_c[i..j], r)
        })
    }

    /// [`ColourModel::ln_eval`], the same bits.
    pub fn ln_eval(&self, r: f64, phi: Option<f64>) -> [f64; 3] {
        match self.model {
            ColourModel::PerChannel { channels } => {
                [0, 1, 2].map(|c| self.falloff(c, &channels[c], r, phi))
            }
            ColourModel::Shared { falloff, .. } => {
                let l = self.falloff(0, falloff, r, phi);
                [l, l + self.ln_scale[0], l + self.ln_scale[1]]
            }
        }
    }

    /// Shared colour (Eq. 5): the ln s_c that channel 1 or 2 adds to channel 0's ln R_d, so that
    /// `ln_eval_channel(c, r, φ)` is `ln_eval_channel(0, r, φ) + offset` to the bit and a caller
    /// with several channels observed at one (r, φ) evaluates the fall-off once. `None` per
    /// channel and for channels 0 and above 2.
    pub fn shared_offset(&self, channel: usize) -> Option<f64> {
        match (self.model, channel) {
            (ColourModel::Shared { .. }, 1 | 2) => Some(self.ln_scale[channel - 1]),
            _ => None,
        }
    }

    /// [`LnEvaluator::ln_eval_channel`] of an isotropic fall-off (one segment, where φ
    /// changes nothing) at every distance of `r`, into `out`, vectorised
    /// ([`super::ExpSum::ln_eval_many`]: within a few ulp, not the same bits). `false`, and `out`
    /// untouched, where channel `channel`'s fall-off has more than one segment or there is no
    /// such channel: the caller evaluates per sample.
    pub fn ln_eval_channel_many(&self, channel: usize, r: &[f64], out: &mut [f64]) -> bool {
        let (f, a, offset) = match self.model {
            ColourModel::PerChannel { channels } => match channels.get(channel) {
                Some(a) => (channel, a, 0.0),
                None => return false,
            },
            ColourModel::Shared { falloff, .. } => match channel {
                0 => (0, falloff, 0.0),
                1 | 2 => (0, falloff, self.ln_scale[channel - 1]),
                _ => return false,
            },
        };
        let [seg] = a.segments.as_slice() else {
            return false;
        };
        let at = self.starts[self.first[f]];
        let ln_c = &self.ln_c[at..self.starts[self.first[f] + 1]];
        seg.ln_eval_many(ln_c, r, out);
        if offset != 0.0 {
            for o in out.iter_mut() {
                *o += offset;
            }
        }
        true
    }

    /// [`ColourModel::ln_eval_channel`], the same bits.
    pub fn ln_eval_channel(&self, channel: usize, r: f64, phi: Option<f64>) -> f64 {
        match self.model {
            ColourModel::PerChannel { channels } => channels
                .get(channel)
                .map_or(f64::NAN, |c| self.falloff(channel, c, r, phi)),
            ColourModel::Shared { falloff, .. } => match channel {
                0 => self.falloff(0, falloff, r, phi),
                1 | 2 => self.falloff(0, falloff, r, phi) + self.ln_scale[channel - 1],
                _ => f64::NAN,
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{ExpSum, Term};

    #[test]
    fn shared_scales_channels() {
        let f = Anisotropic::isotropic(ExpSum::new(vec![Term { c: 2.0, d: -0.5 }]).unwrap());
        let m = ColourModel::Shared {
            falloff: f,
            s_g: 0.5,
            s_b: 0.25,
        };
        m.validate().unwrap();
        let v = m.eval(2.0, None);
        let base = 2.0 * (-1.0f64).exp();
        assert!((v[0] - base).abs() < 1e-14);
        assert!((v[1] - 0.5 * base).abs() < 1e-14);
        assert!((v[2] - 0.25 * base).abs() < 1e-14);
        let g = m.channel(1).unwrap();
        assert!((g.eval(2.0, None) - v[1]).abs() < 1e-14);
        assert!(m.channel(3).is_none());
        let bad = ColourModel::Shared {
            falloff: m.channel(0).unwrap(),
            s_g: 0.0,
            s_b: 1.0,
        };
        assert!(bad.validate().is_err());
        let json = serde_json::to_string(&m).unwrap();
        assert_eq!(serde_json::from_str::<ColourModel>(&json).unwrap(), m);
    }

    /// One channel's evaluation is the full evaluation's entry to the bit, for per-channel and
    /// shared colour, one and several segments, with and without a direction.
    #[test]
    fn one_channel_and_the_evaluator_are_the_full_evaluation_to_the_bit() {
        let seg = |k: f64| {
            ExpSum::new(vec![
                Term {
                    c: 3.0 + k,
                    d: -0.4 - 0.1 * k,
                },
                Term {
                    c: 0.2 * (1.0 + k),
                    d: -2.5 - k,
                },
            ])
            .unwrap()
        };
        let aniso = |m: usize, k: f64| Anisotropic {
            segments: (0..m).map(|l| seg(k + l as f64)).collect(),
        };
        // Segments of different orders (a term dropped in one): the evaluator's ln c_k are
        // found per segment.
        let one = |c: f64| ExpSum::new(vec![Term { c, d: -0.9 }]).unwrap();
        let mixed = |m: usize, k: f64| Anisotropic {
            segments: (0..m)
                .map(|l| {
                    if l % 2 == 0 {
                        seg(k + l as f64)
                    } else {
                        one(1.5 + k)
                    }
                })
                .collect(),
        };
        for m in [1, 2, 3, 4] {
            let models = [
                ColourModel::PerChannel {
                    channels: [aniso(m, 0.0), aniso(m, 1.0), aniso(m, 2.0)],
                },
                ColourModel::PerChannel {
                    channels: [mixed(m, 0.0), aniso(m, 1.0), mixed(m, 2.0)],
                },
                ColourModel::Shared {
                    falloff: mixed(m, 0.5),
                    s_g: 1.7,
                    s_b: 0.03,
                },
                ColourModel::Shared {
                    falloff: aniso(m, 0.5),
                    s_g: 0.7,
                    s_b: 0.3,
                },
            ];
            for model in &models {
                for r in [0.0, 1e-9, 0.37, 3.0, 40.0, 4000.0] {
                    for phi in [None, Some(0.0), Some(1.1), Some(-2.9), Some(f64::NAN)] {
                        let all = model.ln_eval(r, phi);
                        let ev = model.ln_evaluator();
                        let all_ev = ev.ln_eval(r, phi);
                        // A model that does not use φ evaluates the same without it.
                        assert_eq!(ev.uses_direction(), m > 1);
                        if !ev.uses_direction() {
                            let none = ev.ln_eval(r, None).map(f64::to_bits);
                            assert_eq!(none, all.map(f64::to_bits), "r {r} phi {phi:?}");
                        }
                        for (ch, want) in all.iter().enumerate() {
                            let got = model.ln_eval_channel(ch, r, phi);
                            assert_eq!(got.to_bits(), want.to_bits(), "m {m} r {r} phi {phi:?}");
                            let got = ev.ln_eval_channel(ch, r, phi);
                            assert_eq!(got.to_bits(), want.to_bits(), "m {m} r {r} phi {phi:?}");
                            assert_eq!(all_ev[ch].to_bits(), want.to_bits());
                            if let Some(k) = ev.shared_offset(ch) {
                                let got = ev.ln_eval_channel(0, r, phi) + k;
                                assert_eq!(got.to_bits(), want.to_bits());
                            }
                        }
                        assert!(model.ln_eval_channel(3, r, phi).is_nan());
                        assert!(ev.ln_eval_channel(3, r, phi).is_nan());
                    }
                }
            }
        }
    }
}
