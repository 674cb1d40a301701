//! Held-out metrics (paper, Sec. VII-A, Eq. 33) against hand-computed values
//! on tiny cases, against the prior of real models, and a calibration
//! property: for errors drawn from the posterior, `err² ≈ n(1+m)`.

use bayes_cbf::gp::metrics::{
    held_out_errors, mahalanobis_sq, relative_rmse_fu, rmse_f, rmse_fu, variance_weighted_error,
};
use bayes_cbf::gp::{
    Cogp, CogpHyper, DynamicsModel, FitReport, InputMap, ModelFitSettings, Mvgp, MvgpHyper,
    PriorMean, Rbf,
};
use bayes_cbf::systems::{ControlAffine, DynSystem, Pendulum};
use bayes_cbf::{Error, InputError};
use nalgebra::{DMatrix, DVector};
use num_dual::DualNum;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

/// A model that answers from a table of `(x, mean, cov)`.
struct Table {
    n: usize,
    m: usize,
    rows: Vec<(Vec<f64>, DMatrix<f64>, DMatrix<f64>)>,
}

impl DynamicsModel for Table {
    fn state_dim(&self) -> usize {
        self.n
    }
    fn control_dim(&self) -> usize {
        self.m
    }
    fn len(&self) -> usize {
        0
    }
    fn set_data(&mut self, _: &[f64], _: &[f64], _: &[f64]) -> Result<(), Error> {
        Ok(())
    }
    fn fit(&mut self, _: &ModelFitSettings) -> Result<FitReport, Error> {
        Err(bayes_cbf::GpError::NoData.into())
    }
    fn posterior_vec(&self, x: &[f64]) -> Result<(DMatrix<f64>, DMatrix<f64>), InputError> {
        self.rows
            .iter()
            .find(|r| r.0 == x)
            .map(|r| (r.1.clone(), r.2.clone()))
            .ok_or_else(|| InputError::invalid("x", x[0], "not in the table"))
    }
    fn log_marginal_likelihood(&self) -> f64 {
        0.0
    }
    fn name(&self) -> &str {
        "table"
    }
}

/// `ẋ = x + 2u`: `F(x) = [x, 2]`.
struct Line;

impl ControlAffine for Line {
    fn state_dim(&self) -> usize {
        1
    }
    fn control_dim(&self) -> usize {
        1
    }
    fn dynamics<D: DualNum<Primitive = f64> + Copy>(&self, x: &[D], out: &mut [D]) {
        out[0] = x[0];
        out[1] = D::from(2.0);
    }
}

fn close(a: f64, b: f64, what: &str) {
    assert!(
        (a - b).abs() < 1e-12 * (1.0 + b.abs()),
        "{what}: {a} vs {b}"
    );
}

/// Two points `x = 1, 2` with errors `e = (0.1 x, −0.2)` and covariance
/// `[[0.02, 0.01], [0.01, 0.04]]`: `eᵀK⁻¹e = 16/7` and `32/7`.
#[test]
fn metrics_match_hand_computed_values() {
    let cov = DMatrix::from_row_slice(2, 2, &[0.02, 0.01, 0.01, 0.04]);
    let rows = [1.0, 2.0]
        .iter()
        .map(|&x| {
            let mean = DMatrix::from_row_slice(1, 2, &[x + 0.1 * x, 2.0 - 0.2]);
            (vec![x], mean, cov.clone())
        })
        .collect();
    let model = Table { n: 1, m: 1, rows };
    let (xs, us) = ([1.0, 2.0], [1.0, -0.5]);
    close(
        variance_weighted_error(&model, &xs, &Line).unwrap(),
        (24.0f64 / 7.0).sqrt(),
        "variance-weighted error",
    );
    // Σ‖e‖² = 0.05 + 0.08 over 2 points × 2 entries
    close(
        rmse_f(&model, &xs, &Line).unwrap(),
        0.0325f64.sqrt(),
        "rmse_f",
    );
    // (M − F)u̲ = −0.1, 0.3; F u̲ = 3, 1
    close(
        rmse_fu(&model, &xs, &us, &Line).unwrap(),
        0.05f64.sqrt(),
        "rmse_fu",
    );
    close(
        relative_rmse_fu(&model, &xs, &us, &Line).unwrap(),
        0.1,
        "relative",
    );
    let all = held_out_errors(&model, &xs, &us, &Line).unwrap();
    close(all.variance_weighted, (24.0f64 / 7.0).sqrt(), "all.vwe");
    close(all.rmse_f, 0.0325f64.sqrt(), "all.rmse_f");
    close(all.rmse_fu, 0.05f64.sqrt(), "all.rmse_fu");
    close(all.relative_rmse_fu, 0.1, "all.relative");
    assert_eq!(all.points, 2);
    close(
        mahalanobis_sq(&cov, &[0.1, -0.2]).unwrap(),
        16.0 / 7.0,
        "mahalanobis",
    );
}

/// Without data both models return the prior `N(0, Σ k0(x, x))` with
/// `Σ = c I` (`B ⊗ A` with `A = c I`, `B = I` for the MVGP), so
/// `err² = mean ‖vec F(x)‖² / (c s)` for kernel variance `s`.
#[test]
fn prior_models_give_the_closed_form_error() {
    let (c, s) = (2.0, 1.5);
    let kernel = Rbf::new(vec![0.7, 1.1], s).unwrap();
    let cogp = Cogp::new(
        2,
        1,
        CogpHyper {
            kernel: kernel.clone(),
            Sigma: DMatrix::identity(4, 4) * c,
            S: DMatrix::identity(2, 2) * 0.1,
        },
        PriorMean::Zero,
        InputMap::Identity,
    )
    .unwrap();
    let mvgp = Mvgp::new(
        2,
        1,
        MvgpHyper {
            kernel,
            A: DMatrix::identity(2, 2) * c,
            B: DMatrix::identity(2, 2),
            sigma: 0.3,
        },
        PriorMean::Zero,
        InputMap::Identity,
    )
    .unwrap();
    let sys = Pendulum::default();
    let xs = [0.5, 1.0, -1.0, 2.0];
    // ‖vec F‖² = ω² + 100 sin²θ + 0 + 1
    let f2 = |th: f64, om: f64| om * om + 100.0 * th.sin().powi(2) + 1.0;
    let expect = ((f2(0.5, 1.0) + f2(-1.0, 2.0)) / 2.0 / (c * s)).sqrt();
    let rmse = ((f2(0.5, 1.0) + f2(-1.0, 2.0)) / 8.0).sqrt();
    let models: [&dyn DynamicsModel; 2] = [&cogp, &mvgp];
    for model in models {
        close(
            variance_weighted_error(model, &xs, &sys).unwrap(),
            expect,
            model.name(),
        );
        close(rmse_f(model, &xs, &sys).unwrap(), rmse, model.name());
    }
}

/// For means drawn as `vec M = vec F + L ξ`, `L Lᵀ = K`, `ξ ~ N(0, I)`, the
/// squared error averages `n(1+m)`.
#[test]
fn error_of_posterior_draws_is_calibrated() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let sys = Pendulum::default();
    let (n, np, t) = (2, 4, 4000);
    let mut rows = Vec::with_capacity(t);
    let mut xs = Vec::with_capacity(t * n);
    let mut f = vec![0.0; np];
    for _ in 0..t {
        let x: Vec<f64> = (0..n).map(|_| rng.random_range(-3.0..3.0)).collect();
        let c = DMatrix::from_fn(np, np, |_, _| rng.random_range(-1.0..1.0));
        let cov = &c * c.transpose() + DMatrix::identity(np, np) * 0.05;
        let l = cov.clone().cholesky().unwrap().l();
        let xi = DVector::from_fn(np, |_, _| StandardNormal.sample(&mut rng));
        sys.eval_f64(&x, &mut f);
        let mean = DVector::from_column_slice(&f) + l * xi;
        rows.push((
            x.clone(),
            DMatrix::from_column_slice(n, 2, mean.as_slice()),
            cov,
        ));
        xs.extend_from_slice(&x);
    }
    let model = Table { n, m: 1, rows };
    let e = variance_weighted_error(&model, &xs, &sys).unwrap();
    // err² = mean of χ²_4: standard deviation √(8/4000) ≈ 0.045
    assert!((e * e - 4.0).abs() < 0.2, "err² = {}", e * e);
}

#[test]
fn bad_inputs_name_the_field() {
    let model = Table {
        n: 1,
        m: 1,
        rows: vec![],
    };
    let field = |r: Result<f64, Error>| match r.unwrap_err() {
        Error::Input(InputError::Shape { field, .. } | InputError::Invalid { field, .. }) => field,
        e => panic!("unexpected {e:?}"),
    };
    assert_eq!(field(rmse_f(&model, &[], &Line)), "xs");
    assert_eq!(field(rmse_f(&model, &[0.0], &Pendulum::default())), "truth");
    assert_eq!(field(rmse_fu(&model, &[0.0, 1.0], &[1.0], &Line)), "us");
    assert_eq!(
        field(variance_weighted_error(
            &model,
            &[0.0, f64::INFINITY],
            &Line
        )),
        "xs[1][0]"
    );
    // a singular posterior covariance beyond the jitter levels is an error
    let zero = Table {
        n: 1,
        m: 1,
        rows: vec![(vec![0.0], DMatrix::zeros(1, 2), -DMatrix::identity(2, 2))],
    };
    assert!(matches!(
        variance_weighted_error(&zero, &[0.0], &Line),
        Err(Error::Gp(_))
    ));
}
