//! Prior means `M0(x)` of the MVGP.

use crate::systems::DynSystem;
use num_dual::Dual64;
use std::sync::Arc;

/// Prior mean `M0(x)` of `F(x)`: zero, or a parametric model of the system
/// (any [`ControlAffine`](crate::systems::ControlAffine)).
#[derive(Clone, Default)]
pub enum PriorMean {
    /// `M0(x) = 0`.
    #[default]
    Zero,
    /// `M0(x) = F_model(x)` of a parametric system model.
    System(Arc<dyn DynSystem>),
}

impl std::fmt::Debug for PriorMean {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PriorMean::Zero => write!(f, "Zero"),
            PriorMean::System(s) => write!(f, "System(n={}, m={})", s.state_dim(), s.control_dim()),
        }
    }
}

/// Largest state dimension, `1 + control_dim`, and CoGP output count
/// `n(1 + m)`: the models hold dense matrices of these sides (`A`, `B`,
/// `Σ`), and a GP of a robot needs far fewer.
pub const MAX_DIMENSION: usize = 10_000;

/// Checks `n, m ≥ 1`, `n ≤ MAX_DIMENSION` and `1 + m ≤ MAX_DIMENSION`
/// (so `n(1 + m)` cannot overflow), naming the field.
pub fn check_dims(n: usize, m: usize) -> Result<(), crate::error::InputError> {
    use crate::error::InputError;
    for (field, v) in [("state_dim", n), ("control_dim", m)] {
        if v == 0 {
            return Err(InputError::invalid(field, 0.0, "must be ≥ 1"));
        }
    }
    for (field, v, big) in [
        ("state_dim", n, n > MAX_DIMENSION),
        ("control_dim", m, m >= MAX_DIMENSION),
    ] {
        if big {
            return Err(InputError::invalid_shown(
                field,
                v,
                &format!("too large: state_dim and 1 + control_dim are at most {MAX_DIMENSION}"),
            ));
        }
    }
    Ok(())
}

/// Checks the dimensions shared by every model of `F(x)`: `n, m ≥ 1`
/// ([`check_dims`]), the input map against `n`, and a system prior mean
/// against `(n, m)`.
pub(crate) fn check_model_dims(
    n: usize,
    m: usize,
    input_map: &super::InputMap,
    prior: &PriorMean,
) -> Result<(), crate::error::InputError> {
    use crate::error::InputError;
    check_dims(n, m)?;
    input_map.validate(n)?;
    if let Some((pn, pm)) = prior.dims() {
        if (pn, pm) != (n, m) {
            return Err(InputError::shape(
                "prior_mean",
                format!("system with n = {n}, m = {m}"),
                format!("n = {pn}, m = {pm}"),
            ));
        }
    }
    Ok(())
}

impl PriorMean {
    /// Writes `vec M0(x)` (column-major `n × (1+m)`) into `out`.
    #[inline]
    pub fn eval(&self, x: &[f64], out: &mut [f64]) {
        match self {
            PriorMean::Zero => out.fill(0.0),
            PriorMean::System(s) => s.eval_f64(x, out),
        }
    }

    /// Writes `∂ vec M0/∂x` (column-major `n(1+m) × n`) into `jac`.
    pub fn jacobian(&self, x: &[f64], jac: &mut [f64], sx: &mut [Dual64], so: &mut [Dual64]) {
        match self {
            PriorMean::Zero => jac.fill(0.0),
            PriorMean::System(s) => s.jacobian_into(x, jac, sx, so),
        }
    }

    /// The first failed evaluation of a system prior since the last call
    /// ([`DynSystem::take_error`]).
    pub fn take_error(&self) -> Option<String> {
        match self {
            PriorMean::Zero => None,
            PriorMean::System(s) => s.take_error().map(|m| format!("prior mean: {m}")),
        }
    }

    /// [`take_error`](Self::take_error) as an [`InputError::Evaluation`].
    pub(crate) fn check(&self) -> Result<(), crate::error::InputError> {
        match self.take_error() {
            None => Ok(()),
            Some(m) => Err(crate::error::InputError::Evaluation(m)),
        }
    }

    /// Dimensions `(n, m)` of a system prior, `None` for zero.
    pub fn dims(&self) -> Option<(usize, usize)> {
        match self {
            PriorMean::Zero => None,
            PriorMean::System(s) => Some((s.state_dim(), s.control_dim())),
        }
    }
}
