//! Without a reference, the safety controller evaluates its CLF at
//! `x_d = ẋ_d = 0` of the state dimension, for any state dimension:
//! regression for a fixed 16-entry zero buffer, which gave a reference of
//! the wrong length (and an input error) for more than 16 states.

use bayes_cbf::barrier::{DynLyapunov, Lyapunov};
use bayes_cbf::control::{ControlOutput, SafetyController, SafetySettings};
use bayes_cbf::gp::{InputMap, Mvgp, MvgpHyper, PriorMean, Rbf};
use nalgebra::DMatrix;
use num_dual::DualNum;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::sync::Arc;

/// `V = ½ ‖x − x_d‖²`.
struct Distance {
    n: usize,
    gamma: f64,
}

impl Lyapunov for Distance {
    fn state_dim(&self) -> usize {
        self.n
    }
    fn v<D: DualNum<Primitive = f64> + Copy>(&self, x: &[D], xd: &[D]) -> D {
        x.iter()
            .zip(xd)
            .fold(D::from(0.0), |s, (a, b)| s + (*a - *b) * (*a - *b) * 0.5)
    }
    fn gamma(&self) -> f64 {
        self.gamma
    }
}

/// An MVGP of the chain of integrators `ẋ_i = x_{i+1}`, `ẋ_n = u`, fitted
/// to `k` noise-free observations.
fn integrator_chain(n: usize, k: usize) -> Mvgp {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let hyper = MvgpHyper {
        kernel: Rbf::new(vec![2.0; n], 1.0).unwrap(),
        A: DMatrix::identity(n, n),
        B: DMatrix::identity(2, 2),
        sigma: 0.1,
    };
    let mut model = Mvgp::new(n, 1, hyper, PriorMean::Zero, InputMap::Identity).unwrap();
    let xs: Vec<f64> = (0..k * n).map(|_| rng.random_range(-1.0..1.0)).collect();
    let us: Vec<f64> = (0..k).map(|_| rng.random_range(-1.0..1.0)).collect();
    let mut xdot = vec![0.0; k * n];
    for j in 0..k {
        for i in 0..n - 1 {
            xdot[j * n + i] = xs[j * n + i + 1];
        }
        xdot[j * n + n - 1] = us[j];
    }
    model.set_data(&xs, &us, &xdot).unwrap();
    model
}

#[test]
fn clf_without_reference_works_beyond_sixteen_states() {
    for n in [3, 16, 17, 18] {
        let model = integrator_chain(n, 30);
        let clf: Arc<dyn DynLyapunov> = Arc::new(Distance { n, gamma: 1.0 });
        let mut ctrl =
            SafetyController::new(n, 1, vec![], Some(clf), SafetySettings::new(1)).unwrap();
        let x: Vec<f64> = (0..n).map(|i| 0.1 * (i as f64 + 1.0).sin()).collect();
        let mut out = ControlOutput::new(1, 0);
        ctrl.step(&model, &x, &[0.5], None, &mut out)
            .unwrap_or_else(|e| panic!("n = {n}: {e}"));
        let report = out.clf.expect("a CLF report");
        assert!(report.mean.is_finite() && report.std.is_finite(), "n = {n}");
        assert!(out.u[0].is_finite(), "n = {n}");
        // the same as an explicit zero reference
        let zeros = vec![0.0; n];
        let mut explicit = ControlOutput::new(1, 0);
        ctrl.step(&model, &x, &[0.5], Some((&zeros, &zeros)), &mut explicit)
            .unwrap();
        assert_eq!(out, explicit, "n = {n}");
    }
}
