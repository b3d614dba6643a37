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
    /// without the other channels' evaluations (the fit's loops take one channel's samples at a
    /// time, and evaluated all three for each: issue 23). NaN for a channel index above 2.
    pub fn ln_eval_channel(&self, channel: usize, r: f64, phi: Option<f64>) -> f64 {
        self.ln_evaluator().ln_eval_channel(channel, r, phi)
    }

    /// The model ready for many evaluations: ln s_g and ln s_b taken once, not at every
    /// evaluation (two logs against the fall-off's own one: issue 23). Its evaluations are
    /// [`ColourModel::ln_eval`]'s and [`ColourModel::ln_eval_channel`]'s to the bit.
    pub fn ln_evaluator(&self) -> LnEvaluator<'_> {
        let ln_scale = match self {
            Self::PerChannel { .. } => [0.0; 2],
            Self::Shared { s_g, s_b, .. } => [s_g.ln(), s_b.ln()],
        };
        LnEvaluator {
            model: self,
            ln_scale,
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

/// [`ColourModel::ln_evaluator`]: a colour model with the logarithms of its channel scales taken.
#[derive(Debug, Clone, Copy)]
pub struct LnEvaluator<'a> {
    model: &'a ColourModel,
    /// ln s_g, ln s_b (shared colour; unused per channel).
    ln_scale: [f64; 2],
}

impl LnEvaluator<'_> {
    /// [`ColourModel::ln_eval`], the same bits.
    pub fn ln_eval(&self, r: f64, phi: Option<f64>) -> [f64; 3] {
        match self.model {
            ColourModel::PerChannel { channels } => [0, 1, 2].map(|c| channels[c].ln_eval(r, phi)),
            ColourModel::Shared { falloff, .. } => {
                let l = falloff.ln_eval(r, phi);
                [l, l + self.ln_scale[0], l + self.ln_scale[1]]
            }
        }
    }

    /// [`ColourModel::ln_eval_channel`], the same bits.
    pub fn ln_eval_channel(&self, channel: usize, r: f64, phi: Option<f64>) -> f64 {
        match self.model {
            ColourModel::PerChannel { channels } => channels
                .get(channel)
                .map_or(f64::NAN, |c| c.ln_eval(r, phi)),
            ColourModel::Shared { falloff, .. } => match channel {
                0 => falloff.ln_eval(r, phi),
                1 | 2 => falloff.ln_eval(r, phi) + self.ln_scale[channel - 1],
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
        for m in [1, 2, 4] {
            let models = [
                ColourModel::PerChannel {
                    channels: [aniso(m, 0.0), aniso(m, 1.0), aniso(m, 2.0)],
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
                        for (ch, want) in all.iter().enumerate() {
                            let got = model.ln_eval_channel(ch, r, phi);
                            assert_eq!(got.to_bits(), want.to_bits(), "m {m} r {r} phi {phi:?}");
                            let got = ev.ln_eval_channel(ch, r, phi);
                            assert_eq!(got.to_bits(), want.to_bits(), "m {m} r {r} phi {phi:?}");
                            assert_eq!(all_ev[ch].to_bits(), want.to_bits());
                        }
                        assert!(model.ln_eval_channel(3, r, phi).is_nan());
                        assert!(ev.ln_eval_channel(3, r, phi).is_nan());
                    }
                }
            }
        }
    }
}
