//! Gaussian-process models of `F(x)`: the matrix-variate GP (paper, Sec. IV),
//! its scalar kernels, input maps, prior means and hyperparameter learning.

/// Accessors shared by the MVGP and the CoGP, whose structs hold the same
/// fields `n`, `m`, `hyper` (of type `$hyper`), `prior`, `input_map` and
/// `data`; each model has its own `len`.
macro_rules! shared_model_accessors {
    ($hyper:ty) => {
        /// State dimension `n`.
        pub fn state_dim(&self) -> usize {
            self.n
        }
        /// Control dimension `m`.
        pub fn control_dim(&self) -> usize {
            self.m
        }
        /// No observations.
        pub fn is_empty(&self) -> bool {
            self.len() == 0
        }
        /// Hyperparameters.
        pub fn hyper(&self) -> &$hyper {
            &self.hyper
        }
        /// Prior mean.
        pub fn prior(&self) -> &PriorMean {
            &self.prior
        }
        /// Input map.
        pub fn input_map(&self) -> &InputMap {
            &self.input_map
        }
        /// Training inputs (row-major `k × n`).
        pub fn xs(&self) -> &[f64] {
            &self.data.xs
        }
        /// Training targets `ẋ` (row-major `k × n`).
        pub fn xdot(&self) -> &[f64] {
            &self.data.xdot
        }
        /// Training controls without the leading 1 (`k × m`), freshly
        /// collected.
        pub fn controls(&self) -> Vec<f64> {
            let p = self.m + 1;
            self.data
                .us
                .chunks(p)
                .flat_map(|u| u[1..].to_vec())
                .collect()
        }
    };
}

mod cogp;
mod cogp_training;
mod data;
pub use data::MAX_DATA_MAGNITUDE;
mod factor;
mod input_map;
pub(crate) mod joint;
mod kernel;
pub(crate) mod lipschitz;
pub mod metrics;
mod model;
mod mvgp;
mod optimise;
mod prior;
mod psd;
mod simd;
mod theta;
mod training;

pub use cogp::{cogp_outputs, Cogp, CogpGradient, CogpHyper, CogpPosterior};
pub use cogp_training::{fit_cogp, fit_cogp_until, CogpFitSettings};
pub use factor::{CholFactor, JITTER_LEVELS};
pub use input_map::{Feature, InputMap};
pub use joint::{JointPosterior, JointWorkspace};
pub use kernel::{Kernel, Rbf};
pub use lipschitz::{
    factor_bounds, kernel_constants, FactorBounds, LipschitzEstimate, LipschitzSettings,
};
pub use metrics::{held_out_errors, variance_weighted_error, HeldOutErrors};
pub use model::{DynamicsModel, ModelFitSettings};
#[cfg(test)]
pub(crate) use mvgp::plain_model;
pub use mvgp::{
    check_spd, KnownRowMisfit, Mvgp, MvgpHyper, Posterior, PosteriorWorkspace,
    KNOWN_ROW_MIN_OBSERVATIONS,
};
pub use prior::{check_dims, PriorMean, MAX_DIMENSION};
pub use simd::set_linear_algebra_threads;
pub use training::{fit, fit_until, FitReport, FitSettings, MvgpLikelihood, Rank};
