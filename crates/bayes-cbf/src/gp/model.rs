//! A common interface to the GP models of `F(x)` (MVGP and CoGP), so that
//! experiments, metrics and controllers can take either.

use super::cogp::Cogp;
use super::cogp_training::{fit_cogp, CogpFitSettings};
use super::kernel::Kernel;
use super::mvgp::Mvgp;
use super::training::{fit, FitReport, FitSettings, Rank};
use crate::error::{Error, InputError};
use nalgebra::DMatrix;

/// Settings of [`DynamicsModel::fit`], common to both models.
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct ModelFitSettings {
    /// Structure of the large covariance: `B` (`(1+m)²`) for the MVGP, `Σ`
    /// (`(n(1+m))²`) for the CoGP. `Rank::Diagonal` gives the paper's "diag"
    /// variants (Sec. VII-A).
    pub rank_big: Rank,
    /// Structure of the small covariance: `A` for the MVGP (row covariance,
    /// noise `σ² A`), the noise covariance `S` for the CoGP.
    pub rank_small: Rank,
    /// L-BFGS iterations per start.
    pub max_iters: u64,
    /// Extra random restarts besides the data-driven start.
    pub restarts: usize,
    /// Seed of the random initialisation and restarts.
    pub seed: u64,
}

impl Default for ModelFitSettings {
    fn default() -> Self {
        Self {
            rank_big: Rank::Full,
            rank_small: Rank::Full,
            max_iters: 100,
            restarts: 0,
            seed: 0,
        }
    }
}

impl ModelFitSettings {
    /// Both covariances diagonal (the paper's "diag" models).
    pub fn diagonal() -> Self {
        Self {
            rank_big: Rank::Diagonal,
            rank_small: Rank::Diagonal,
            ..Self::default()
        }
    }

    /// Checks the settings.
    pub fn validate(&self) -> Result<(), InputError> {
        self.to_mvgp().validate()?;
        self.to_cogp().validate()
    }

    /// The equivalent [`FitSettings`] of the MVGP trainer
    /// (`rank_b = rank_big`, `rank_a = rank_small`, `A` learned).
    pub fn to_mvgp(&self) -> FitSettings {
        FitSettings {
            rank_a: self.rank_small,
            rank_b: self.rank_big,
            max_iters: self.max_iters,
            restarts: self.restarts,
            seed: self.seed,
            learn_a: true,
            warm_start: false,
            ..FitSettings::default()
        }
    }

    /// The equivalent [`CogpFitSettings`]
    /// (`rank_sigma = rank_big`, `rank_s = rank_small`).
    pub fn to_cogp(&self) -> CogpFitSettings {
        CogpFitSettings {
            rank_sigma: self.rank_big,
            rank_s: self.rank_small,
            max_iters: self.max_iters,
            restarts: self.restarts,
            seed: self.seed,
            ..CogpFitSettings::default()
        }
    }
}

/// A learned model of `F(x) = [f(x) g(x)]` giving a Gaussian posterior
/// `vec F(x) ~ N(vec M_k(x), K_k(x, x))` (`vec` column-major: entry `(i, c)`
/// at `i + n c`).
///
/// Implemented for [`Mvgp`] (`K_k = B_k(x, x) ⊗ A`, Prop. 1) and [`Cogp`]
/// (`K_k` of the Appendix lemma, Eq. `coregionalization-posterior`).
pub trait DynamicsModel {
    /// State dimension `n`.
    fn state_dim(&self) -> usize;
    /// Control dimension `m`.
    fn control_dim(&self) -> usize;
    /// Number of observations `k`.
    fn len(&self) -> usize;
    /// No observations.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Replaces the training data (row-major `k × n`, `k × m`, `k × n`).
    fn set_data(&mut self, xs: &[f64], us: &[f64], xdot: &[f64]) -> Result<(), Error>;
    /// Learns the hyperparameters by maximising the marginal likelihood.
    fn fit(&mut self, settings: &ModelFitSettings) -> Result<FitReport, Error>;
    /// `(M_k(x), Cov(vec F(x)))`: mean `n × (1+m)`, covariance `n(1+m)` square.
    fn posterior_vec(&self, x: &[f64]) -> Result<(DMatrix<f64>, DMatrix<f64>), InputError>;
    /// Posterior mean `M_k(x)` only (cheaper where the model allows).
    fn posterior_mean(&self, x: &[f64]) -> Result<DMatrix<f64>, InputError> {
        Ok(self.posterior_vec(x)?.0)
    }
    /// Log marginal likelihood of the data under the current hyperparameters.
    fn log_marginal_likelihood(&self) -> f64;
    /// Short model name for reports ("MVGP", "CoGP").
    fn name(&self) -> &str;
}

/// Implements [`DynamicsModel`] for a GP model type by its own methods,
/// with `$fit` (settings from [`ModelFitSettings::$settings`]) and
/// `$posterior_vec`.
macro_rules! dynamics_model {
    ($model:ident, $name:literal, $fit:ident, $settings:ident, $posterior_vec:ident) => {
        impl<K: Kernel> DynamicsModel for $model<K> {
            fn state_dim(&self) -> usize {
                $model::state_dim(self)
            }
            fn control_dim(&self) -> usize {
                $model::control_dim(self)
            }
            fn len(&self) -> usize {
                $model::len(self)
            }
            fn set_data(&mut self, xs: &[f64], us: &[f64], xdot: &[f64]) -> Result<(), Error> {
                $model::set_data(self, xs, us, xdot)
            }
            fn fit(&mut self, settings: &ModelFitSettings) -> Result<FitReport, Error> {
                settings.validate()?;
                $fit(self, &settings.$settings())
            }
            fn posterior_vec(&self, x: &[f64]) -> Result<(DMatrix<f64>, DMatrix<f64>), InputError> {
                $posterior_vec(self, x)
            }
            fn posterior_mean(&self, x: &[f64]) -> Result<DMatrix<f64>, InputError> {
                $model::posterior_mean(self, x)
            }
            fn log_marginal_likelihood(&self) -> f64 {
                $model::log_marginal_likelihood(self)
            }
            fn name(&self) -> &str {
                $name
            }
        }
    };
}

/// `(M_k(x), B_k(x, x) ⊗ A)`.
fn mvgp_posterior_vec<K: Kernel>(
    model: &Mvgp<K>,
    x: &[f64],
) -> Result<(DMatrix<f64>, DMatrix<f64>), InputError> {
    let post = model.posterior(x)?;
    let cov = post.B.kronecker(model.row_cov());
    Ok((post.mean, cov))
}

/// `(M_k(x), K_k(x, x))`.
fn cogp_posterior_vec<K: Kernel>(
    model: &Cogp<K>,
    x: &[f64],
) -> Result<(DMatrix<f64>, DMatrix<f64>), InputError> {
    let post = model.posterior(x)?;
    Ok((post.mean, post.cov))
}

dynamics_model!(Mvgp, "MVGP", fit, to_mvgp, mvgp_posterior_vec);
dynamics_model!(Cogp, "CoGP", fit_cogp, to_cogp, cogp_posterior_vec);
