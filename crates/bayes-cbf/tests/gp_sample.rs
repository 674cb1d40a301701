//! Monte Carlo check of [`GpSample`]: over many seeds, the draws of
//! `vec F(x)` have the prior's mean `vec M0(x)` and covariance
//! `Cov(vec F(x), vec F(x')) = B k0(φ(x), φ(x')) ⊗ A` (paper, Sec. IV).
//!
//! Tolerance: each estimated mean and covariance entry must agree with the
//! closed form within 4 standard errors, the standard error being estimated
//! from the same draws (`sd(samples)/√N` for means, `sd(products)/√N` for
//! covariances). With `N = 20 000` draws the relative standard error of a
//! variance is about `√(2/N)` = 1 %, so a wrong factor (`A` and `B`
//! swapped, `ω` scaled by `ℓ` instead of `1/ℓ`, a missing `√s`) is far
//! outside the tolerance.

use bayes_cbf::gp::{InputMap, Kernel, MvgpHyper, Rbf};
use bayes_cbf::systems::{Ackermann, DynSystem, GpSample, Pendulum};
use nalgebra::DMatrix;

const DRAWS: usize = 20_000;
const FEATURES: usize = 64;
const Z_TOL: f64 = 4.0;

/// Mean and standard error of `v`.
fn mean_se(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0);
    (m, (var / n).sqrt())
}

/// Checks mean and cross-covariances of `vec F` at `points` over `DRAWS`
/// draws made by `draw(seed)`, against `mean0` and `A B k0`.
/// `|diff| / se`; a quantity without spread (a known row) must match exactly.
/// (Differences below 1e-9, far under the Monte Carlo error, count as 0.)
fn zscore(diff: f64, se: f64) -> f64 {
    if diff.abs() <= 1e-9 {
        0.0
    } else if se > 0.0 {
        diff.abs() / se
    } else {
        f64::INFINITY
    }
}

#[allow(non_snake_case)]
fn check_moments(
    draw: impl Fn(u64) -> Box<dyn DynSystem>,
    hyper: &MvgpHyper<Rbf>,
    map: &InputMap,
    mean0: &dyn DynSystem,
    points: &[Vec<f64>],
) {
    let n = mean0.state_dim();
    let p = mean0.control_dim() + 1;
    let np = n * p;
    // samples[point][entry][draw]
    let mut samples = vec![vec![Vec::with_capacity(DRAWS); np]; points.len()];
    let mut f = vec![0.0; np];
    for seed in 0..DRAWS as u64 {
        let s = draw(seed);
        for (a, x) in points.iter().enumerate() {
            s.eval_f64(x, &mut f);
            for r in 0..np {
                samples[a][r].push(f[r]);
            }
        }
    }
    let mut worst: f64 = 0.0;
    let mut m0 = vec![0.0; np];
    for (a, x) in points.iter().enumerate() {
        mean0.eval_f64(x, &mut m0);
        for r in 0..np {
            let (m, se) = mean_se(&samples[a][r]);
            let z = zscore(m - m0[r], se);
            worst = worst.max(z);
            assert!(
                z < Z_TOL,
                "mean at point {a} entry {r}: {m} vs {} (z = {z:.2})",
                m0[r]
            );
        }
    }
    let d = map.output_dim(n);
    let (mut za, mut zb) = (vec![0.0; d], vec![0.0; d]);
    for a in 0..points.len() {
        for b in a..points.len() {
            map.apply(&points[a], &mut za);
            map.apply(&points[b], &mut zb);
            let k0 = hyper.kernel.value(&za, &zb);
            for r in 0..np {
                for s in 0..np {
                    // vec index r = i + n c
                    let (i, c) = (r % n, r / n);
                    let (j, dd) = (s % n, s / n);
                    let want = hyper.A[(i, j)] * hyper.B[(c, dd)] * k0;
                    let (ma, _) = mean_se(&samples[a][r]);
                    let (mb, _) = mean_se(&samples[b][s]);
                    let prods: Vec<f64> = samples[a][r]
                        .iter()
                        .zip(&samples[b][s])
                        .map(|(u, v)| (u - ma) * (v - mb))
                        .collect();
                    let (cov, se) = mean_se(&prods);
                    let z = zscore(cov - want, se);
                    worst = worst.max(z);
                    assert!(
                        z < Z_TOL,
                        "Cov(F[{r}](x{a}), F[{s}](x{b})) = {cov:.5} vs prior {want:.5} (z = {z:.2}, se {se:.2e})"
                    );
                    if a == b && r == s && want > 0.0 {
                        assert!(se < 0.03 * want, "standard error {se} too large for {want}");
                    }
                }
            }
        }
    }
    eprintln!("largest deviation: {worst:.2} standard errors");
}

/// The hyperparameters of the pendulum draws: a periodic angle (three
/// kernel inputs) and correlated `A` and `B`.
fn pendulum_hyper() -> MvgpHyper {
    MvgpHyper {
        kernel: Rbf::new(vec![0.7, 1.3, 0.9], 1.7).unwrap(),
        A: DMatrix::from_row_slice(2, 2, &[0.3, 0.1, 0.1, 0.2]),
        B: DMatrix::from_row_slice(2, 2, &[1.0, 0.4, 0.4, 0.5]),
        sigma: 0.1,
    }
}

#[test]
fn pendulum_draws_have_the_prior_mean_and_covariance() {
    let hyper = pendulum_hyper();
    let map = InputMap::periodic(2, &[0]);
    let pend = Pendulum {
        mass: 1.3,
        length: 0.8,
        gravity: 10.0,
    };
    // the third point is across the ±π wrap from the first
    let points = vec![vec![0.3, -0.5], vec![0.9, 0.1], vec![0.3 - 6.0, -0.1]];
    check_moments(
        |seed| Box::new(GpSample::draw(2, 1, Some(pend), &hyper, &map, FEATURES, seed).unwrap()),
        &hyper,
        &map,
        &pend,
        &points,
    );
}

/// Draws of the structured prior (`θ̇ = ω` known): the known row is the
/// prior's, exactly, and the moments are those of `B ⊗ A` with `A`'s row
/// and column 0 zeroed.
#[test]
#[allow(non_snake_case)]
fn known_row_draws_have_the_structured_prior_moments() {
    let hyper = pendulum_hyper();
    let A = hyper.A.clone();
    let map = InputMap::periodic(2, &[0]);
    let pend = Pendulum::default();
    let draw = |seed| {
        GpSample::draw(2, 1, Some(pend), &hyper, &map, FEATURES, seed)
            .unwrap()
            .with_known_rows(&[0])
            .unwrap()
    };
    let points = vec![vec![0.3, -0.5], vec![0.9, 0.1]];
    let (mut f, mut f0) = (vec![0.0; 4], vec![0.0; 4]);
    for seed in 0..20 {
        let s = draw(seed);
        for x in &points {
            s.eval_f64(x, &mut f);
            pend.eval_f64(x, &mut f0);
            assert_eq!((f[0], f[2]), (f0[0], f0[2]), "known row at {x:?}");
        }
    }
    let mut a_eff = A;
    a_eff.row_mut(0).fill(0.0);
    a_eff.column_mut(0).fill(0.0);
    let expected = MvgpHyper {
        A: a_eff,
        ..hyper.clone()
    };
    check_moments(|seed| Box::new(draw(seed)), &expected, &map, &pend, &points);
    assert!(GpSample::draw(2, 1, Some(pend), &hyper, &map, FEATURES, 0)
        .unwrap()
        .with_known_rows(&[2])
        .is_err());
}

#[test]
#[allow(non_snake_case)]
fn ackermann_draws_have_the_prior_mean_and_covariance() {
    // kernel on the heading only (shift invariance), non-diagonal A and B
    let A = DMatrix::from_row_slice(3, 3, &[0.5, 0.1, 0.0, 0.1, 0.4, -0.1, 0.0, -0.1, 0.3]);
    let B = DMatrix::from_row_slice(3, 3, &[0.6, 0.2, 0.0, 0.2, 1.0, 0.3, 0.0, 0.3, 0.8]);
    let hyper = MvgpHyper {
        kernel: Rbf::new(vec![0.6], 0.9).unwrap(),
        A,
        B,
        sigma: 0.1,
    };
    let map = InputMap::Select(vec![2]);
    let car = Ackermann { wheelbase: 2.0 };
    let points = vec![vec![0.0, 0.0, 0.2], vec![5.0, -1.0, 0.7]];
    check_moments(
        |seed| Box::new(GpSample::draw(3, 2, Some(car), &hyper, &map, FEATURES, seed).unwrap()),
        &hyper,
        &map,
        &car,
        &points,
    );
}
