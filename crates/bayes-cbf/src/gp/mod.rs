//! Gaussian-process models of `F(x)`: the matrix-variate GP (paper, Sec. IV),
//! its scalar kernels, input maps, prior means and hyperparameter learning.

mod cogp;
mod cogp_training;
mod data;
mod factor;
mod input_map;
mod joint;
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

pub use cogp::{Cogp, CogpGradient, CogpHyper, CogpPosterior};
pub use cogp_training::{fit_cogp, CogpFitSettings};
pub use factor::{CholFactor, JITTER_LEVELS};
pub use input_map::{Feature, InputMap};
pub use joint::{JointPosterior, JointWorkspace};
pub use kernel::{Kernel, Rbf};
pub use lipschitz::{
    factor_bounds, kernel_constants, FactorBounds, LipschitzEstimate, LipschitzSettings,
};
pub use metrics::{held_out_errors, variance_weighted_error, HeldOutErrors};
pub use model::{DynamicsModel, ModelFitSettings};
pub use mvgp::{check_spd, Mvgp, MvgpHyper, Posterior, PosteriorWorkspace};
pub use prior::PriorMean;
pub use training::{fit, FitReport, FitSettings, MvgpLikelihood, Rank};
