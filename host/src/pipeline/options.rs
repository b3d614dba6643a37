//! Every setting of the pipeline, and the policies that derive them: defaults from a dataset's
//! noise floor and saturation, the speed/accuracy presets, the direction-segment choice.
use crate::dataset::Dataset;
use crate::fit::{FitOptions, Preset};
use crate::model::IntensityWindow;
use crate::modelfile::ColourMode;
use crate::samples::SampleOptions;
use crate::spot::SpotOptions;

/// Which model variant each vertex gets.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct ModelChoice {
    /// Shared colour (Eq. 5/9) or per channel (Eq. 3).
    pub colour: ColourMode,
    /// Direction segments m (Eq. 3); 1 = isotropic (Eq. 9, the paper's choice for objects).
    pub segments: usize,
}

/// Eq. 6's upper threshold t1 as a share of a light position's brightest sample (per channel,
/// [`crate::model::IntensityWindow::for_light`]) when none is chosen: none. t1 is meant to keep
/// the near field of x_i (single scattering, first-surface light, "dominated by multiple
/// scattering", section 4.2) out of alpha; whether that pays differs by scan, so `subsurf fit`
/// chooses it per scan by cross-validation on the training frames, none against
/// [`crate::crossval::T1_CANDIDATE`] (the evidence is there and in docs/validation.md);
/// `--alpha-t1-share` fixes it.
pub const ALPHA_T1_SHARE: f64 = f64::INFINITY;

/// Every setting of the pipeline.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct PipelineOptions {
    /// Spot detection and the laser cross-check.
    pub spot: SpotOptions,
    /// Sample extraction.
    pub samples: SampleOptions,
    /// A vertex whose closest x_i is farther than this (mm) has no data.
    pub max_select_mm: f64,
    /// Frames whose x_i agree within this distance (mm) are one light position and are fitted
    /// together (section 5: "all images in which a particular location on the object was
    /// illuminated"); `None`: half the mesh's median edge length
    /// ([`super::select::default_pool_mm`]); 0 pools only identical x_i.
    pub pool_mm: Option<f64>,
    /// The model variant; its `segments` is the largest m a light position may use.
    pub model: ModelChoice,
    /// "Model only what the scene requires", per light position: n (up to the fitter's) and m
    /// (up to `model.segments`) chosen by [`crate::order::choose`]; `None` fits every light
    /// position at the maximum order (unsupported terms still dropped).
    pub order: Option<crate::order::OrderRule>,
    /// Fits with log E(x_i) (Eq. 8, mean over channels) above this fail.
    pub max_log_e: f64,
    /// Fits with log E(x_i) above this multiple of the median over all fits (and above
    /// [`super::OUTLIER_MIN_LOG_E`]) fail too: outliers, interpolated from neighbours;
    /// `f64::INFINITY` disables the rule.
    pub outlier_factor: f64,
    /// Eq. 6 window (t2, t1) for alpha(x_o): t2 from the noise floor, t1 relative to each light
    /// position's brightest sample ([`ALPHA_T1_SHARE`]).
    pub alpha_window: IntensityWindow,
    /// Eq. 8 threshold t.
    pub error_threshold: f64,
    /// At most this many extra fit rounds on samples divided by the previous round's alpha(x_o)
    /// (Eq. 6); 0 fits once and treats the modulation texture as noise.
    pub alpha_rounds: usize,
    /// The rounds stop early once alpha has converged: the RMS change of ln alpha(x_o) over the
    /// vertices between two rounds is below this. Fit and Eq. 6 are a block coordinate descent
    /// that converges linearly, so a fixed small round count leaves part of the modulation
    /// texture in the fall-off (measured on the built-in scan: held-out log E 0.026 after one
    /// round, 0.014 after four); the tolerance pays only for the rounds the data need.
    pub alpha_tolerance: f64,
    /// alpha finer than the mesh (section 5: "the modulation texture alpha(x_o) is determined
    /// as higher resolution texture"): Eq. 6 per point of a per-face lattice after the rounds
    /// ([`super::detail`]), written as the model file's `face_alpha` where the images support it.
    pub alpha_lattice: AlphaLattice,
    /// Eq. 6's shrinkage towards alpha = 1: this multiple of the empirical-Bayes pseudo-count
    /// ([`crate::model::empirical_prior`], noise over the texture's spread) at the vertices and
    /// at the lattice points; 1 = the empirical one, 0 = none (the plain geometric mean),
    /// infinite = no texture (alpha = 1). Chosen by cross-validation (`crate::crossval`).
    pub alpha_shrinkage: f64,
    /// Frames whose laser spot the camera sees at a grazing angle (cos θ between the normal at
    /// the laser's hit and the direction to the camera below this) are not fitted: their spot is
    /// foreshortened and its back-projected x_i least certain. Registration keeps such frames
    /// down to [`crate::spot::SPOT_COS_FLOOR`], so whether they help is a choice of the
    /// fit ([`crate::spot::SPOT_COS_MIN`] by default, chosen by cross-validation).
    pub spot_cos_min: f64,
    /// The fit's computational path: the default's cuts, or the exact reference.
    pub speed: Speed,
}

/// How the fit computes what the reference computes exactly (the rule for a cut: the same
/// predictions, not the same bits); the cross-validation's folds and the final fit take the same path, so
/// the folds score the procedure that ships.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Speed {
    /// The default: the fills (failed vertices, alpha) solved by a sparse Cholesky factor of
    /// their Laplace rows (`crate::interpolate::Laplace`; conjugate gradients to [`FILL_TOLERANCE`]
    /// where it cannot be had), and in the cross-validation's folds only at the vertices their
    /// held-out frames read, as weights of the known vertices kept from round to round
    /// (`pipeline::fill::FillHow`).
    #[default]
    Default,
    /// The exact path without the cuts (`subsurf fit --preset reference`): every solve from
    /// scratch to the solvers' own tolerances.
    Reference,
}

/// The fill's relative residual in the default path: ln R_d on the curve grid is then within
/// about 1e-8 of the exact harmonic interpolation, six orders below the smallest held-out
/// difference the cross-validation resolves (1e-3); the reference solves to 1e-13.
pub const FILL_TOLERANCE: f64 = 1e-9;

/// Whether and how finely alpha is estimated between the vertices (`subsurf fit --alpha-lattice`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum AlphaLattice {
    /// Per vertex only: no lattice pass, no `face_alpha` element (the behaviour before format 5).
    Off,
    /// Each face's level from the pixel footprint ([`super::detail::face_levels`]), at most
    /// [`crate::lattice::MAX_LEVEL`].
    Auto,
    /// As `Auto`, at most this level (1..=[`crate::lattice::MAX_LEVEL`]).
    Max(u8),
}

impl AlphaLattice {
    /// The largest level a face may get; `None` when off.
    pub fn max_level(self) -> Option<u8> {
        match self {
            AlphaLattice::Off => None,
            AlphaLattice::Auto => Some(crate::lattice::MAX_LEVEL),
            AlphaLattice::Max(k) => Some(k.clamp(1, crate::lattice::MAX_LEVEL)),
        }
    }
}

impl std::str::FromStr for AlphaLattice {
    type Err = String;

    /// `auto`, `off`, or a level 1..=8.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "auto" => Ok(AlphaLattice::Auto),
            "off" => Ok(AlphaLattice::Off),
            k => k
                .parse::<u8>()
                .ok()
                .filter(|k| (1..=crate::lattice::MAX_LEVEL).contains(k))
                .map(AlphaLattice::Max)
                .ok_or_else(|| {
                    format!(
                        "--alpha-lattice must be auto, off or a level 1..={}, got {s:?}",
                        crate::lattice::MAX_LEVEL
                    )
                }),
        }
    }
}

impl PipelineOptions {
    /// Defaults for a dataset: noise floor and saturation from `scan.json` (for camera files the
    /// white level: `Dataset::saturation`).
    pub fn for_dataset(ds: &Dataset) -> PipelineOptions {
        let floor = ds.spec.noise_floor.unwrap_or(0.0);
        PipelineOptions {
            spot: SpotOptions {
                min_peak: 0.0,
                saturation: ds.saturation(),
                laser_tolerance_mm: 2.0,
            },
            samples: SampleOptions {
                saturation: ds.saturation(),
                ..SampleOptions::default()
            },
            max_select_mm: 2.0,
            pool_mm: None,
            model: ModelChoice {
                colour: ColourMode::Shared,
                segments: 1,
            },
            order: Some(crate::order::OrderRule::default()),
            max_log_e: 1.0,
            outlier_factor: 3.0,
            alpha_window: IntensityWindow {
                t2: 0.0,
                t1: f64::INFINITY,
                t1_share: ALPHA_T1_SHARE,
            },
            error_threshold: 0.0,
            alpha_rounds: 8,
            alpha_tolerance: 2e-3,
            alpha_lattice: AlphaLattice::Auto,
            alpha_shrinkage: 1.0,
            spot_cos_min: crate::spot::SPOT_COS_MIN,
            speed: Speed::Default,
        }
        .with_noise_floor(floor)
    }

    /// Every setting that follows from the radiance noise floor: samples below it are dropped,
    /// a spot must be 10× above it, Eq. 6 uses samples 10× above it (t2) and Eq. 8 compares
    /// samples above it (t).
    pub fn with_noise_floor(mut self, floor: f64) -> PipelineOptions {
        self.samples.noise_floor = floor;
        self.spot.min_peak = 10.0 * floor;
        self.alpha_window.t2 = 10.0 * floor;
        self.error_threshold = floor;
        self
    }

    /// The model variant and the solver settings of a speed/accuracy preset: the one definition
    /// `subsurf fit --preset` and `subsurf bench tradeoff` share. `None` is the exact default:
    /// all samples, n = 3 ([`FitOptions::default`]), isotropic.
    pub fn with_preset(mut self, preset: Option<Preset>) -> (PipelineOptions, FitOptions) {
        match preset {
            None => {
                self.model.segments = 1;
                (self, FitOptions::default())
            }
            Some(p) => {
                self.model.segments = p.segments();
                (self, p.options())
            }
        }
    }
}

/// The largest m any fit accepts (the model file and the renderer hold up to it).
pub const MAX_SEGMENTS: usize = 64;

/// What a model was fitted with that judging it depends on, for its file
/// ([`crate::modelfile::FitRecord`]): `subsurf evaluate` reads frames by these rules unless told
/// otherwise, so a model is judged on the fit's terms.
pub fn fit_record(opts: &PipelineOptions) -> crate::modelfile::FitRecord {
    crate::modelfile::FitRecord {
        noise_floor: opts.samples.noise_floor,
        exclusion_radius_mm: opts.samples.exclusion_radius_mm,
        cos_min: opts.samples.cos_min,
        coverage: opts.samples.coverage,
        laser_tolerance_mm: opts.spot.laser_tolerance_mm,
        spot_cos_min: opts.spot_cos_min,
    }
}

impl PipelineOptions {
    /// The evaluation protocol of dataset `ds`: the rules every model of the dataset is judged
    /// by (`subsurf evaluate`, the cross-validation's folds, `subsurf fit --validate`), whatever
    /// options it was fitted with. The noise floor is the dataset's (Eq. 8's threshold t and
    /// the samples kept), the exclusion radius around x_i, the samples' and the spot's grazing
    /// limits and the laser cross-check are this version's defaults for the dataset. A fit's
    /// options change the model, never which samples judge it: two models fitted with different
    /// exclusion radii are compared on the same samples (docs/validation.md, "The evaluation
    /// protocol").
    pub fn evaluation_protocol(ds: &Dataset) -> PipelineOptions {
        PipelineOptions::for_dataset(ds)
    }

    /// These options with the judging rules of `protocol` (sample rules, spot detection, the
    /// spot's grazing limit, Eq. 8's threshold) and every fit setting of `self`.
    pub fn judged_by(self, protocol: &PipelineOptions) -> PipelineOptions {
        PipelineOptions {
            spot: protocol.spot,
            samples: protocol.samples,
            spot_cos_min: protocol.spot_cos_min,
            error_threshold: protocol.error_threshold,
            ..self
        }
    }

    /// These options with the rules a model was fitted with ([`fit_record`]).
    pub fn with_fit_record(self, r: &crate::modelfile::FitRecord) -> PipelineOptions {
        let mut o = self.with_noise_floor(r.noise_floor);
        o.samples.exclusion_radius_mm = r.exclusion_radius_mm;
        o.samples.cos_min = r.cos_min;
        o.samples.coverage = r.coverage;
        o.spot.laser_tolerance_mm = r.laser_tolerance_mm;
        o.spot_cos_min = r.spot_cos_min;
        o
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `--alpha-lattice`: auto and a cap estimate, off does not; levels outside 1..=8 are refused.
    #[test]
    fn alpha_lattice_parses_auto_off_and_levels() {
        assert_eq!("auto".parse(), Ok(AlphaLattice::Auto));
        assert_eq!("off".parse(), Ok(AlphaLattice::Off));
        assert_eq!("3".parse(), Ok(AlphaLattice::Max(3)));
        for bad in ["0", "9", "-1", "fine", ""] {
            assert!(bad.parse::<AlphaLattice>().is_err(), "{bad}");
        }
        assert_eq!(
            AlphaLattice::Auto.max_level(),
            Some(crate::lattice::MAX_LEVEL)
        );
        assert_eq!(AlphaLattice::Max(3).max_level(), Some(3));
        assert_eq!(AlphaLattice::Off.max_level(), None);
    }
}
