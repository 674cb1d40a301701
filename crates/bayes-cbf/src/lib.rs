//! # bayes-cbf
//!
//! Learn the dynamics of a control-affine robot `ẋ = f(x) + g(x)u` online with
//! a matrix-variate Gaussian process (MVGP) and keep it safe while it learns,
//! following Dhiman, Khojasteh, Franceschetti and Atanasov, *Control Barriers
//! in Bayesian Learning of System Dynamics*, IEEE TAC 2021.
//!
//! ## Modules
//! - [`systems`]: the [`systems::ControlAffine`] trait and built-in systems.
//! - [`sim`]: zero-order-hold simulation, datasets, references (planner,
//!   ε-greedy) and the closed loop with online learning.
//! - [`gp`]: MVGP and CoGP regression, kernels, input maps, hyperparameter
//!   learning, the joint posterior of `F` and its Jacobian, error metrics.
//! - [`barrier`]: barrier and Lyapunov functions and the moments of their
//!   conditions (exact for relative degree 1 and 2, Monte Carlo beyond).
//! - [`expr`]: the expression language of user-written systems, barriers
//!   and Lyapunov functions, evaluated over dual numbers.
//! - [`autodiff`]: seeding dual numbers for derivatives of user functions.
//! - [`control`]: the chance-constrained SOCP safety filter (Clarabel),
//!   infeasibility outcomes and fallbacks.
//!
//! ## Error policy
//! Programming errors (a slice of the wrong length passed between internal
//! layers) panic with `#[track_caller]` assertions. Everything that can be
//! caused by user input or by numerics returns `Result`: bad shapes or
//! non-finite values in user data ([`error::InputError`]), matrices that are
//! not positive definite, Gram matrices that cannot be factorised even after
//! bounded jitter ([`error::GpError`]). Factorisations are never `.expect()`ed.

#![warn(missing_docs)]
// Index loops mirror the subscripts of the maths in the docs.
#![allow(clippy::needless_range_loop)]

pub mod autodiff;
pub mod barrier;
pub mod control;
pub mod error;
pub mod expr;
pub mod gp;
pub mod sim;
pub mod systems;
pub mod warnings;

pub use error::{ControlError, Error, GpError, InputError};

// The crates whose types the public API takes and returns (matrices, dual
// numbers for user functions, the random streams of references and the
// simulator), re-exported so that a user's code names the same versions.
pub use nalgebra;
pub use num_dual;
pub use rand;
pub use rand_chacha;
