//! `p*` of an infeasible step (Remark 2) against an independent reference:
//! for one control in a box, the worst margin at probability `p` is
//! `max_u min_i (E[C_i](u) − ζ − c_i(p) √Var[C_i](u))` on a fine grid of
//! `u`, and `p*` is where it crosses zero (bisection on `p`). One and two
//! barriers, relative degrees 1 and 2 mixed, and the inverse of `c(p)`
//! against literal values.

mod common;

use bayes_cbf::barrier::{factor_probability, ConditionMoments};
use bayes_cbf::control::{ControlOutput, ControlStatus, Fallback, SafetyFilter, SafetySettings};
use common::c_reference;
use nalgebra::DMatrix;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn random_moments(rng: &mut ChaCha8Rng, r: usize) -> ConditionMoments {
    let e: Vec<f64> = (0..2).map(|_| rng.random_range(-1.0..1.0)).collect();
    let c = DMatrix::from_fn(2, 2, |_, _| rng.random_range(-1.0..1.0)) * 0.8;
    ConditionMoments::from_parts(e, &c * c.transpose(), r).unwrap()
}

#[test]
fn factor_probability_inverts_the_safety_factor() {
    // literal values: Φ(1.2815515655446004) = 0.9, Φ(2.3263478740408408) = 0.99;
    // Cantelli c = 3 ↔ p = 0.9, c = √99 ↔ p = 0.99
    let v = factor_probability(1.281_551_565_544_600_4, 1);
    assert!((v - 0.9).abs() < 1e-10, "{v}");
    assert!((factor_probability(2.326_347_874_040_840_8, 1) - 0.99).abs() < 1e-10);
    assert!((factor_probability(0.0, 1) - 0.5).abs() < 1e-15);
    assert!((factor_probability(3.0, 2) - 0.9).abs() < 1e-15);
    assert!((factor_probability(99f64.sqrt(), 2) - 0.99).abs() < 1e-14);
    assert_eq!(factor_probability(-0.5, 2), 0.0);
    assert_eq!(factor_probability(f64::INFINITY, 2), 1.0);
    assert_eq!(factor_probability(f64::INFINITY, 1), 1.0);
    assert_eq!(factor_probability(f64::NEG_INFINITY, 1), 0.0);
}

#[test]
fn p_star_matches_a_grid_reference() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    // a box that is not symmetric, so that the maximum of E[C](u) over it
    // depends on which end each coefficient's sign picks
    let (lo, hi, zeta, p) = (-1.5, 1.2, 0.05, 0.999);
    let grid: Vec<f64> = (0..=20_000)
        .map(|i| lo + (hi - lo) * i as f64 / 20_000.0)
        .collect();
    let mut checked = [0usize; 2];
    let mut hopeless = 0;
    for trial in 0..150 {
        let nb = 1 + trial % 2;
        let moms: Vec<ConditionMoments> = (0..nb)
            .map(|i| {
                let mut m = random_moments(&mut rng, 1 + (trial / 2 + i) % 2);
                m.e[0] = rng.random_range(-0.3..0.3);
                m
            })
            .collect();
        let best_margin = |q: f64| {
            let cs: Vec<f64> = moms
                .iter()
                .map(|m| c_reference(q, m.relative_degree))
                .collect();
            grid.iter()
                .map(|&u| {
                    moms.iter()
                        .zip(&cs)
                        .map(|(m, c)| m.mean(&[u]) - zeta - c * m.variance(&[u]).sqrt())
                        .fold(f64::INFINITY, f64::min)
                })
                .fold(f64::NEG_INFINITY, f64::max)
        };
        let p_lo = if moms.iter().any(|m| m.relative_degree == 1) {
            0.5
        } else {
            1e-9
        };
        if best_margin(p) >= 0.0 {
            continue;
        }
        let mut settings = SafetySettings::new(1);
        settings.probability = p;
        settings.zeta = zeta;
        settings.u_min = Some(vec![lo]);
        settings.u_max = Some(vec![hi]);
        settings.fallback = Fallback::Relax;
        let mut filter = SafetyFilter::new(1, nb, false, settings).unwrap();
        let mut out = ControlOutput::new(1, nb);
        filter.solve(&moms, None, &[0.5], &mut out).unwrap();
        if best_margin(p_lo) < -1e-6 {
            // no probability is feasible, not even the lowest
            match &out.status {
                ControlStatus::Infeasible(info) => {
                    assert_eq!(info.p_star, None, "trial {trial}")
                }
                s => panic!("trial {trial}: expected infeasible, got {s:?}"),
            }
            hopeless += 1;
            continue;
        }
        if best_margin(p_lo) < 1e-6 {
            // too close to the lowest probability for the grid to decide
            continue;
        }
        let a = common::bisect_p_star(best_margin, p_lo, p);
        let ps = match &out.status {
            ControlStatus::Infeasible(info) => info.p_star.expect("feasible at the lower end"),
            s => panic!("trial {trial}: expected infeasible, got {s:?}"),
        };
        // p* is within the tolerance (1e-5) of the reference, up to the
        // grid's resolution in u
        assert!(
            (ps - a).abs() < 5e-5,
            "trial {trial}: p* {ps}, reference {a}"
        );
        // and the relaxed control meets every constraint at p*
        for m in &moms {
            let c = c_reference(ps, m.relative_degree);
            let slack = m.mean(&out.u) - zeta - c * m.variance(&out.u).sqrt();
            assert!(slack >= -1e-6, "trial {trial}: slack {slack} at p* {ps}");
        }
        checked[nb - 1] += 1;
    }
    assert!(
        checked[0] >= 10 && checked[1] >= 10 && hopeless >= 10,
        "infeasible instances: {checked:?}, {hopeless} with no p*"
    );
}

/// A condition without variance that the box can meet affords every
/// probability: beside a random infeasible one, `p*` is that one's alone.
#[test]
fn a_condition_without_variance_does_not_limit_p_star() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let exact = ConditionMoments::from_parts(vec![0.5, 0.1], DMatrix::zeros(2, 2), 1).unwrap();
    let mut compared = 0;
    for _ in 0..40 {
        let mom = random_moments(&mut rng, 1);
        let p_star = |moms: &[ConditionMoments]| {
            let mut settings = SafetySettings::new(1);
            settings.probability = 0.999;
            settings.u_min = Some(vec![-1.0]);
            settings.u_max = Some(vec![1.0]);
            let mut filter = SafetyFilter::new(1, moms.len(), false, settings).unwrap();
            let mut out = ControlOutput::new(1, moms.len());
            filter.solve(moms, None, &[0.0], &mut out).unwrap();
            match out.status {
                ControlStatus::Infeasible(info) => info.p_star,
                _ => None,
            }
        };
        if let Some(alone) = p_star(std::slice::from_ref(&mom)) {
            let both = p_star(&[exact.clone(), mom]).expect("a p* with the exact condition");
            assert!((both - alone).abs() < 1e-4, "{both} vs {alone}");
            compared += 1;
        }
    }
    assert!(compared >= 5, "{compared}");
}
