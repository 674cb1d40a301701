//! Gaussian-process models of `F(x)`: the matrix-variate GP (paper, Sec. IV),
//! its scalar kernels, input maps, prior means and hyperparameter learning.

mod factor;
mod input_map;
mod joint;
mod kernel;
mod mvgp;
mod prior;
mod training;

pub use factor::{CholFactor, JITTER_LEVELS};
pub use input_map::InputMap;
pub use joint::{JointPosterior, JointWorkspace};
pub use kernel::{Kernel, Rbf};
pub use mvgp::{check_spd, Mvgp, MvgpHyper, Posterior, PosteriorWorkspace};
pub use prior::PriorMean;
pub use training::{fit, FitReport, FitSettings, Rank};
