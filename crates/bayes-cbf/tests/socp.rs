//! The safety SOCP: constraints and KKT conditions at the solution, an
//! independent one-dimensional solution, the deterministic limit, and typed
//! infeasibility with the largest feasible probability `p*`.

mod common;

use bayes_cbf::barrier::{quantile_factor, ConditionMoments};
use bayes_cbf::control::{
    ControlOutput, ControlStatus, Fallback, KktData, SafetyFilter, SafetySettings,
};
use clarabel::solver::SupportedConeT;
use common::{c_reference, normal_quantile};
use nalgebra::{DMatrix, DVector};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn random_moments(m: usize, rng: &mut ChaCha8Rng, r: usize, scale: f64) -> ConditionMoments {
    let p = m + 1;
    let e: Vec<f64> = (0..p).map(|_| rng.random_range(-1.0..1.0)).collect();
    let c = DMatrix::from_fn(p, p, |_, _| rng.random_range(-1.0..1.0)) * scale;
    ConditionMoments::from_parts(e, &c * c.transpose(), r).unwrap()
}

/// `c(p)` at `p = 0.9` for relative degree 1: the standard normal quantile
/// `Φ⁻¹(0.9)` (tables; also `common::normal_quantile`).
const GAUSS_C_0_9: f64 = 1.2815515655446004;
/// `Φ⁻¹(0.99)`.
const GAUSS_C_0_99: f64 = 2.3263478740408408;
/// `c(p)` at `p = 0.9` for relative degree ≥ 2 (Cantelli): `√(0.9/0.1) = 3`.
const CANTELLI_C_0_9: f64 = 3.0;

/// `c(p)` against literal constants and the independent references: a
/// Cantelli factor without its square root (`p/(1−p)`, 9 at `p = 0.9`) or a
/// wrong quantile fails here.
#[test]
fn safety_factor_matches_literal_constants() {
    let close = |got: f64, want: f64, what: &str| {
        assert!(
            (got - want).abs() <= 1e-12 * want.abs().max(1.0),
            "{what}: {got} vs {want}"
        );
    };
    close(quantile_factor(0.9, 1).unwrap(), GAUSS_C_0_9, "Φ⁻¹(0.9)");
    close(quantile_factor(0.99, 1).unwrap(), GAUSS_C_0_99, "Φ⁻¹(0.99)");
    close(quantile_factor(0.5, 1).unwrap(), 0.0, "Φ⁻¹(0.5)");
    close(
        quantile_factor(0.9, 2).unwrap(),
        CANTELLI_C_0_9,
        "Cantelli 0.9",
    );
    close(
        quantile_factor(0.99, 2).unwrap(),
        99f64.sqrt(),
        "Cantelli 0.99",
    );
    close(quantile_factor(0.5, 2).unwrap(), 1.0, "Cantelli 0.5");
    // relative degree above 2 uses Cantelli as well
    close(
        quantile_factor(0.9, 3).unwrap(),
        CANTELLI_C_0_9,
        "Cantelli r = 3",
    );
    // the independent quantile reproduces the tables (to its quadrature error)
    for (p, want) in [
        (0.9, GAUSS_C_0_9),
        (0.99, GAUSS_C_0_99),
        (0.975, 1.959963984540054),
        (0.75, 0.6744897501960817),
    ] {
        let got = normal_quantile(p);
        assert!(
            (got - want).abs() < 1e-10,
            "reference Φ⁻¹({p}) = {got} vs {want}"
        );
    }
    for i in 0..=40 {
        let p = 0.5 + 0.499 * i as f64 / 40.0;
        for r in [1, 2] {
            let (got, want) = (quantile_factor(p, r).unwrap(), c_reference(p, r));
            assert!(
                (got - want).abs() <= 1e-10 * want.max(1.0),
                "p = {p}, r = {r}: {got} vs {want}"
            );
        }
    }
}

/// Checks `s = b − Ax ∈ K`, `z ∈ K*`, `Px + q + Aᵀz = 0`, `sᵀz = 0`.
fn check_kkt(filter: &SafetyFilter, tol: f64) {
    check_kkt_to(filter, tol, tol);
}

/// [`check_kkt`] with tolerance `tol` and `gap` for `|sᵀz|` (of the size
/// of the objective's value times the solver's relative gap).
fn check_kkt_to(filter: &SafetyFilter, tol: f64, gap: f64) {
    let KktData {
        a,
        b,
        p,
        q,
        cones,
        x,
        s,
        z,
    } = filter.kkt_data();
    let (xv, sv, zv) = (
        DVector::from_vec(x),
        DVector::from_vec(s),
        DVector::from_vec(z),
    );
    let resid = DVector::from_vec(b) - &a * &xv;
    assert!(
        (&resid - &sv).amax() < tol,
        "primal residual {}",
        (&resid - &sv).amax()
    );
    let stat = &p * &xv + DVector::from_vec(q) + a.transpose() * &zv;
    assert!(stat.amax() < tol, "stationarity {}", stat.amax());
    assert!(sv.dot(&zv).abs() < gap, "complementarity {}", sv.dot(&zv));
    let mut row = 0;
    for cone in cones {
        match cone {
            SupportedConeT::SecondOrderConeT(d) => {
                for v in [&sv, &zv] {
                    let t = v[row];
                    let nrm = v.rows(row + 1, d - 1).norm();
                    assert!(t >= nrm - tol, "SOC membership {t} < {nrm}");
                }
                row += d;
            }
            SupportedConeT::NonnegativeConeT(d) => {
                for i in row..row + d {
                    assert!(sv[i] >= -tol && zv[i] >= -tol);
                }
                row += d;
            }
            _ => unreachable!(),
        }
    }
    // the cones cover every row
    assert_eq!(row, sv.len(), "cones of {row} rows for {} rows", sv.len());
}

/// Program `trial` of the random strictly feasible family: `m = 1 + trial % 3`
/// controls, `1 + trial % 2` barriers of relative degree 1 or 2 that `u = 0`
/// meets with room to spare at `p = 0.9`, `ζ = 0.05`, a CLF, bounds ±3 and a
/// random reference in `[−5, 5]^m`.
fn feasible_program(
    trial: usize,
    rng: &mut ChaCha8Rng,
) -> (
    Vec<ConditionMoments>,
    ConditionMoments,
    SafetyFilter,
    Vec<f64>,
) {
    let m = 1 + trial % 3;
    let nb = 1 + trial % 2;
    let mut cbcs: Vec<ConditionMoments> = (0..nb)
        .map(|i| random_moments(m, rng, 1 + (i + trial) % 2, 0.3))
        .collect();
    for c in cbcs.iter_mut() {
        // u = 0 strictly feasible
        let cp = if c.relative_degree == 1 {
            GAUSS_C_0_9
        } else {
            CANTELLI_C_0_9
        };
        c.e[0] = 0.05 + cp * c.cov[(0, 0)].sqrt() + 0.5;
    }
    let clc = random_moments(m, rng, 1, 0.3);
    let mut settings = SafetySettings::new(m);
    settings.probability = 0.9;
    settings.zeta = 0.05;
    settings.u_min = Some(vec![-3.0; m]);
    settings.u_max = Some(vec![3.0; m]);
    let filter = SafetyFilter::new(m, nb, true, settings).unwrap();
    let u_ref: Vec<f64> = (0..m).map(|_| rng.random_range(-5.0..5.0)).collect();
    (cbcs, clc, filter, u_ref)
}

/// Solves `trials` random strictly feasible programs ([`feasible_program`]),
/// checks that each is `Optimal` and satisfies the KKT conditions to 10⁻⁶,
/// and hands each program's barrier moments and output to `check`.
fn solve_feasible_programs(
    seed: u64,
    trials: usize,
    mut check: impl FnMut(usize, &[ConditionMoments], &ControlOutput),
) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    for trial in 0..trials {
        let (cbcs, clc, mut filter, u_ref) = feasible_program(trial, &mut rng);
        let (m, nb) = (u_ref.len(), cbcs.len());
        let mut out = ControlOutput::new(m, nb);
        filter.solve(&cbcs, Some(&clc), &u_ref, &mut out).unwrap();
        assert_eq!(out.status, ControlStatus::Optimal, "trial {trial}");
        check_kkt(&filter, 1e-6);
        check(trial, &cbcs, &out);
    }
}

#[test]
fn solution_satisfies_constraints_and_kkt() {
    solve_feasible_programs(1, 20, |trial, cbcs, out| {
        for (k, rep) in out.constraints.iter().enumerate() {
            assert!(
                rep.slack >= -1e-6,
                "trial {trial} barrier {k} slack {}",
                rep.slack
            );
            let want = if cbcs[k].relative_degree == 1 {
                GAUSS_C_0_9
            } else {
                CANTELLI_C_0_9
            };
            assert!((rep.c - want).abs() < 1e-12, "c = {} vs {want}", rep.c);
            // the report at the applied control, ζ = 0.05
            let (mean, std) = (cbcs[k].mean(&out.u), cbcs[k].variance(&out.u).sqrt());
            assert_eq!((rep.mean, rep.std), (mean, std));
            let slack = mean - 0.05 - want * std;
            assert!((rep.slack - slack).abs() <= 1e-12 * (1.0 + slack.abs()));
        }
        assert!(!out.is_infeasible());
        assert!(out.clf.unwrap().slack >= -1e-6);
        // within the bounds as set, not to the solver's tolerance
        assert!(out.u.iter().all(|u| (-3.0..=3.0).contains(u)));
    });
}

/// The objective `‖R(u − û)‖² + λδ²` and `‖cR(u − û)‖² + c²λδ²` have one
/// minimiser: scaling the weights by `c` (here 10⁻⁶ to 10⁴, on random
/// invertible `R`) leaves the control as it is. Before the objective was
/// normalised, `R = 10⁻⁵` gave objective values of 10⁻¹⁰ that met the
/// solver's absolute gap tolerance at once, and a control far from the
/// minimiser reported optimal. Equal bounds give the bound exactly.
#[test]
fn the_scale_of_the_weights_does_not_move_the_control() {
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    for trial in 0..24 {
        let (cbcs, clc, filter, u_ref) = feasible_program(trial, &mut rng);
        let (m, nb) = (u_ref.len(), cbcs.len());
        let r = DMatrix::from_fn(m, m, |i, j| {
            f64::from(u8::from(i == j)) + 0.3 * rng.random_range(-1.0..1.0)
        });
        let lambda = rng.random_range(0.2..5.0);
        let solve = |c: f64| {
            let mut settings = filter.settings().clone();
            settings.r = &r * c;
            settings.lambda = lambda * c * c;
            let mut f = SafetyFilter::new(m, nb, true, settings).unwrap();
            let mut out = ControlOutput::new(m, nb);
            f.solve(&cbcs, Some(&clc), &u_ref, &mut out).unwrap();
            assert_eq!(out.status, ControlStatus::Optimal, "trial {trial}, c = {c}");
            out.u
        };
        let base = solve(1.0);
        for c in [1e-6, 1e-3, 1e2, 1e4] {
            let u = solve(c);
            for (a, b) in u.iter().zip(&base) {
                assert!(
                    (a - b).abs() <= 1e-6 * (1.0 + b.abs()),
                    "trial {trial}, c = {c}: u {u:?} vs {base:?}"
                );
            }
        }
    }
    // a control pinned by equal bounds is the bound, to the last bit
    let mom = ConditionMoments::from_parts(vec![1.0, 1.0, -0.5], DMatrix::identity(3, 3) * 0.01, 1)
        .unwrap();
    let mut settings = SafetySettings::new(2);
    settings.u_min = Some(vec![-2.0, 0.5]);
    settings.u_max = Some(vec![2.0, 0.5]);
    let mut filter = SafetyFilter::new(2, 1, false, settings).unwrap();
    let mut out = ControlOutput::new(2, 1);
    filter
        .solve(std::slice::from_ref(&mom), None, &[3.0, 3.0], &mut out)
        .unwrap();
    assert_eq!(out.status, ControlStatus::Optimal);
    assert_eq!(out.u[1], 0.5);
    assert!((-2.0..=2.0).contains(&out.u[0]));
}

/// Random moments of one barrier condition on one control, of relative
/// degree 1 or 2 by `trial`, with `p ∈ [0.6, 0.99)` and its factor `c`,
/// that `u = 0` meets by 0.3.
fn one_control_barrier(trial: usize, rng: &mut ChaCha8Rng) -> (ConditionMoments, f64, f64) {
    let r = 1 + trial % 2;
    let mut mom = random_moments(1, rng, r, 0.5);
    let p = rng.random_range(0.6..0.99);
    let c = c_reference(p, r);
    mom.e[0] = c * mom.cov[(0, 0)].sqrt() + 0.3;
    (mom, p, c)
}

/// One control, one barrier: the feasible set is an interval (the SCBC is
/// concave in u); the solution is the projection of û onto it, found here by
/// bisection on the scalar constraint function. Barriers of relative degree
/// 1 (Gaussian quantile) and 2 (Cantelli factor) alternate.
#[test]
fn one_dimensional_problem_matches_independent_solution() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    for trial in 0..30 {
        let (mom, p, c) = one_control_barrier(trial, &mut rng);
        let scbc = |u: f64| mom.mean(&[u]) - c * mom.variance(&[u]).sqrt();
        let u_ref = rng.random_range(-20.0..20.0);
        let mut settings = SafetySettings::new(1);
        settings.probability = p;
        let mut filter = SafetyFilter::new(1, 1, false, settings).unwrap();
        let mut out = ControlOutput::new(1, 1);
        filter
            .solve(std::slice::from_ref(&mom), None, &[u_ref], &mut out)
            .unwrap();
        // û itself, or the end of the interval between the feasible 0 and û
        let expected = feasible_end(scbc, 0.0, u_ref);
        assert!(
            (out.u[0] - expected).abs() < 1e-6 * (1.0 + expected.abs()),
            "u {} expected {expected}",
            out.u[0]
        );
    }
}

/// Minimiser of a convex function on `[lo, hi]` by golden-section search.
fn golden_section(f: impl Fn(f64) -> f64, mut lo: f64, mut hi: f64) -> f64 {
    let g = (5f64.sqrt() - 1.0) / 2.0;
    let (mut a, mut b) = (hi - g * (hi - lo), lo + g * (hi - lo));
    let (mut fa, mut fb) = (f(a), f(b));
    for _ in 0..300 {
        if fa <= fb {
            hi = b;
            (b, fb) = (a, fa);
            a = hi - g * (hi - lo);
            fa = f(a);
        } else {
            lo = a;
            (a, fa) = (b, fb);
            b = lo + g * (hi - lo);
            fb = f(b);
        }
    }
    0.5 * (lo + hi)
}

/// The end of the feasible interval `{u : g(u) ≥ 0}` of a concave `g` in the
/// direction of `far`, starting from the feasible `inside` (bisection).
fn feasible_end(g: impl Fn(f64) -> f64, inside: f64, far: f64) -> f64 {
    if g(far) >= 0.0 {
        return far;
    }
    let (mut a, mut b) = (inside, far);
    for _ in 0..200 {
        let mid = 0.5 * (a + b);
        if g(mid) >= 0.0 {
            a = mid;
        } else {
            b = mid;
        }
    }
    a
}

/// One control with a barrier, an active CLF and every weight of the
/// objective different from one (`R = [r]`, `r ≠ 1`; `λ ≠ 1`). The SOCP
/// (module docs of `control::socp`) is
///
/// `min r²(u − û)² + λδ²` s.t. `SCBC(u) = e_b·u̲ − ζ − c_b‖V_b u̲‖ ≥ 0`,
/// `δ ≥ SCLC(u) = e_V·u̲ + c₁‖V_V u̲‖`.
///
/// For fixed `u` the best slack is `δ(u) = max(SCLC(u), 0)`, so the problem is
/// the one-dimensional convex minimisation of
/// `φ(u) = r²(u − û)² + λ max(SCLC(u), 0)²` over the interval `SCBC ≥ 0`,
/// solved here by golden-section search with `c` from the independent
/// reference. The solver's tolerances (relative gap 10⁻⁸) make φ exact to
/// 10⁻⁸ but the minimiser only to about 10⁻⁴, so the comparison is on φ. The CLF is made active (`SCLC > 0` near `û`), so a slack
/// weighted `λ/2` (or `R` entering other than as `RᵀR`) moves `u`.
#[test]
fn clf_slack_and_objective_weights_match_independent_solution() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (mut clf_trades_off, mut barrier_active) = (0, 0);
    for trial in 0..40 {
        let rb = 1 + trial % 2;
        let p = [0.9, 0.95, 0.99][trial % 3];
        let zeta = 0.1;
        let mut cbc = random_moments(1, &mut rng, rb, 0.5);
        let cb = c_reference(p, rb);
        cbc.e[0] = zeta + cb * cbc.cov[(0, 0)].sqrt() + rng.random_range(0.1..1.0);
        let mut clc = random_moments(1, &mut rng, 1, 0.4);
        let c1 = c_reference(p, 1);
        // the Lyapunov condition wants V to decrease: a positive E[CLC] at
        // u = 0 that the control can lower, so the slack is active
        clc.e[0] = rng.random_range(0.5..2.0);
        let r = if trial % 2 == 0 {
            rng.random_range(0.3..0.7)
        } else {
            rng.random_range(1.5..3.0)
        };
        let lambda = if trial % 4 < 2 {
            rng.random_range(0.2..0.6)
        } else {
            rng.random_range(2.0..6.0)
        };
        let u_ref = rng.random_range(-4.0..4.0);

        let scbc = |u: f64| cbc.mean(&[u]) - zeta - cb * cbc.variance(&[u]).sqrt();
        let sclc = |u: f64| clc.mean(&[u]) + c1 * clc.variance(&[u]).sqrt();
        let phi = |u: f64| (r * (u - u_ref)).powi(2) + lambda * sclc(u).max(0.0).powi(2);
        let (lo, hi) = (
            feasible_end(scbc, 0.0, -100.0),
            feasible_end(scbc, 0.0, 100.0),
        );
        let expected = golden_section(phi, lo, hi);
        let expected_delta = sclc(expected).max(0.0);

        let mut settings = SafetySettings::new(1);
        settings.probability = p;
        settings.zeta = zeta;
        settings.lambda = lambda;
        settings.r = DMatrix::from_element(1, 1, r);
        let mut filter = SafetyFilter::new(1, 1, true, settings).unwrap();
        let mut out = ControlOutput::new(1, 1);
        filter
            .solve(std::slice::from_ref(&cbc), Some(&clc), &[u_ref], &mut out)
            .unwrap();
        assert_eq!(out.status, ControlStatus::Optimal, "trial {trial}");
        // Clarabel stops at relative gap and feasibility 10⁻⁸: the objective
        // is that exact (either side: an active barrier may be crossed by
        // 10⁻⁹), the minimiser (where φ is flat) to about √10⁻⁸
        let (got, best) = (phi(out.u[0]), phi(expected));
        assert!(
            (got - best).abs() <= 1e-8 * (1.0 + best),
            "trial {trial}: φ(u) = {got} vs min φ = {best} (r {r}, λ {lambda})"
        );
        // φ is strongly convex with modulus 2r², so φ(u) − min φ ≥ r²(u − u*)²
        assert!(
            (r * (out.u[0] - expected)).powi(2) <= 1e-8 * (1.0 + best),
            "trial {trial}: u {} expected {expected} (r {r}, λ {lambda})",
            out.u[0]
        );
        assert!(scbc(out.u[0]) >= -1e-7, "trial {trial}: barrier violated");
        // δ is the CLF condition at the returned u, and the reference's
        assert!(
            (out.delta - sclc(out.u[0]).max(0.0)).abs() < 1e-7 * (1.0 + out.delta),
            "trial {trial}: δ {} vs SCLC(u) {}",
            out.delta,
            sclc(out.u[0])
        );
        assert!(
            (out.delta - expected_delta).abs() < 1e-3 * (1.0 + expected_delta),
            "trial {trial}: δ {} expected {expected_delta}",
            out.delta
        );
        assert!(expected_delta > 1e-3, "trial {trial}: CLF not active");
        // the reported CLF slack δ − E − c·std is zero when active
        assert!(out.clf.unwrap().slack.abs() < 1e-6, "trial {trial}");
        check_kkt(&filter, 1e-6);
        // instances where the CLF weight decides u: the barrier is not active
        // and the minimiser is away from û
        if scbc(expected) > 1e-3 && (expected - u_ref).abs() > 1e-2 {
            clf_trades_off += 1;
        }
        if scbc(expected).abs() < 1e-6 {
            barrier_active += 1;
        }
    }
    assert!(
        clf_trades_off >= 10 && barrier_active >= 3,
        "{clf_trades_off} trade-off and {barrier_active} barrier-active instances"
    );
}

/// With zero variance, or with p = 0.5 at relative degree 1, the SOCP is the
/// deterministic CBF-QP: the projection of û onto the half-space
/// `{u : e_0 + e_uᵀu ≥ ζ}`.
#[test]
fn deterministic_limit_is_the_cbf_qp() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for trial in 0..20 {
        let m = 1 + trial % 3;
        let mut mom = random_moments(m, &mut rng, 1, if trial % 2 == 0 { 0.0 } else { 0.7 });
        let p = if trial % 2 == 0 { 0.999 } else { 0.5 };
        let zeta = 0.1;
        mom.e[0] = rng.random_range(-2.0..2.0);
        let u_ref: Vec<f64> = (0..m).map(|_| rng.random_range(-3.0..3.0)).collect();
        let eu = DVector::from_column_slice(&mom.e[1..]);
        let ur = DVector::from_column_slice(&u_ref);
        let viol = zeta - (mom.e[0] + eu.dot(&ur));
        let expected = if viol > 0.0 {
            &ur + &eu * (viol / eu.norm_squared())
        } else {
            ur.clone()
        };
        let mut settings = SafetySettings::new(m);
        settings.probability = p;
        settings.zeta = zeta;
        let mut filter = SafetyFilter::new(m, 1, false, settings).unwrap();
        let mut out = ControlOutput::new(m, 1);
        filter
            .solve(std::slice::from_ref(&mom), None, &u_ref, &mut out)
            .unwrap();
        let got = DVector::from_column_slice(&out.u);
        assert!(
            (&got - &expected).amax() < 1e-6,
            "trial {trial}: {got} vs {expected}"
        );
    }
}

/// Independent p*: for one control in a box, the best margin at probability
/// p is `max_u e·u̲ − ζ − c(p)‖V u̲‖` on a fine grid, and p* is where it
/// crosses zero (bisection on p).
#[test]
fn infeasible_step_reports_fallback_and_p_star() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let mut checked = 0;
    for trial in 0..40 {
        let mut mom = random_moments(1, &mut rng, 1 + trial % 2, 0.8);
        mom.e[0] = rng.random_range(-0.3..0.3);
        let (lo, hi) = (-1.0, 1.0);
        let zeta = 0.05;
        let best_margin = |p: f64| {
            let c = c_reference(p, mom.relative_degree);
            (0..=20000)
                .map(|i| lo + (hi - lo) * i as f64 / 20000.0)
                .map(|u| mom.mean(&[u]) - zeta - c * mom.variance(&[u]).sqrt())
                .fold(f64::NEG_INFINITY, f64::max)
        };
        let p = 0.999;
        let p_lo = if mom.relative_degree == 1 { 0.5 } else { 1e-9 };
        if best_margin(p) >= 0.0 || best_margin(p_lo) < 0.0 {
            continue;
        }
        let a = common::bisect_p_star(best_margin, p_lo, p);
        for fallback in [
            Fallback::MaxMargin,
            Fallback::Brake,
            Fallback::Hold,
            Fallback::Relax,
        ] {
            let mut settings = SafetySettings::new(1);
            settings.probability = p;
            settings.zeta = zeta;
            settings.u_min = Some(vec![lo]);
            settings.u_max = Some(vec![hi]);
            settings.fallback = fallback;
            let mut filter = SafetyFilter::new(1, 1, false, settings).unwrap();
            let mut out = ControlOutput::new(1, 1);
            filter
                .solve(std::slice::from_ref(&mom), None, &[0.5], &mut out)
                .unwrap();
            assert!(out.is_infeasible());
            match &out.status {
                ControlStatus::Infeasible(info) => {
                    assert_eq!(info.fallback, fallback);
                    assert_eq!(info.violated, vec![0]);
                    let ps = info.p_star.expect("feasible for small p");
                    assert!((ps - a).abs() < 1e-3, "p* {ps} expected {a}");
                }
                s => panic!("expected infeasible, got {s:?}"),
            }
            match fallback {
                Fallback::MaxMargin => {
                    let c = c_reference(p, mom.relative_degree);
                    let got = mom.mean(&out.u) - zeta - c * mom.variance(&out.u).sqrt();
                    assert!(
                        (got - best_margin(p)).abs() < 1e-4,
                        "max margin {got} vs {}",
                        best_margin(p)
                    );
                }
                Fallback::Brake => assert_eq!(out.u, vec![0.0]),
                Fallback::Relax => {
                    // the SOCP at p* is feasible: the condition holds there
                    let ps = match &out.status {
                        ControlStatus::Infeasible(info) => info.p_star.unwrap(),
                        _ => unreachable!(),
                    };
                    let c = c_reference(ps, mom.relative_degree);
                    let slack = mom.mean(&out.u) - zeta - c * mom.variance(&out.u).sqrt();
                    assert!(slack >= -1e-5, "relaxed slack {slack}");
                    assert!(out.u[0] >= lo - 1e-7 && out.u[0] <= hi + 1e-7);
                }
                Fallback::Hold => assert_eq!(out.u, vec![0.0]), // nothing applied before
            }
        }
        checked += 1;
    }
    assert!(
        checked >= 5,
        "only {checked} infeasible instances generated"
    );
}

/// The hold fallback stays within the bounds: before any control was
/// applied it brakes (zero, clamped), afterwards it repeats the last control
/// (clamped too).
#[test]
fn hold_stays_within_the_bounds() {
    // E[C] = −1 + u, no variance: feasible for u ≥ 1 + ζ
    let mom = ConditionMoments::from_parts(vec![-1.0, 1.0], DMatrix::zeros(2, 2), 1).unwrap();
    let mut settings = SafetySettings::new(1);
    settings.probability = 0.9;
    settings.zeta = 0.0;
    settings.u_min = Some(vec![0.5]);
    settings.u_max = Some(vec![2.0]);
    settings.fallback = Fallback::Hold;
    let mut filter = SafetyFilter::new(1, 1, false, settings).unwrap();
    let mut out = ControlOutput::new(1, 1);
    // infeasible at the first step (ζ = 5 > what u ≤ 2 affords): nothing to hold
    let hard = ConditionMoments::from_parts(vec![-5.0, 1.0], DMatrix::zeros(2, 2), 1).unwrap();
    filter
        .solve(std::slice::from_ref(&hard), None, &[5.0], &mut out)
        .unwrap();
    assert!(out.is_infeasible());
    assert_eq!(out.u, vec![0.5], "braking, clamped into [0.5, 2]");
    // a feasible step applies u = 1.5, then an infeasible one holds it
    filter
        .solve(std::slice::from_ref(&mom), None, &[1.5], &mut out)
        .unwrap();
    assert!(!out.is_infeasible());
    assert!((out.u[0] - 1.5).abs() < 1e-6, "{:?}", out.u);
    filter
        .solve(std::slice::from_ref(&hard), None, &[5.0], &mut out)
        .unwrap();
    assert!(out.is_infeasible());
    assert!((out.u[0] - 1.5).abs() < 1e-6, "held {:?}", out.u);
}

#[test]
fn bad_settings_are_rejected() {
    let mut s = SafetySettings::new(2);
    s.probability = 1.0;
    assert!(SafetyFilter::new(2, 1, false, s.clone())
        .unwrap_err()
        .to_string()
        .contains("probability"));
    s.probability = 0.3;
    let mut f = SafetyFilter::new(2, 1, false, s.clone()).unwrap();
    let mom =
        ConditionMoments::from_parts(vec![1.0, 0.0, 1.0], DMatrix::identity(3, 3), 1).unwrap();
    let err = f
        .solve(
            std::slice::from_ref(&mom),
            None,
            &[0.0, 0.0],
            &mut ControlOutput::new(2, 1),
        )
        .unwrap_err();
    assert!(err.to_string().contains("probability"), "{err}");
    s.probability = 0.9;
    s.u_min = Some(vec![1.0, 0.0]);
    s.u_max = Some(vec![0.0, 1.0]);
    assert!(SafetyFilter::new(2, 1, false, s.clone())
        .unwrap_err()
        .to_string()
        .contains("u_min[0]"));
    s.u_min = Some(vec![0.0]);
    assert!(SafetyFilter::new(2, 1, false, s.clone())
        .unwrap_err()
        .to_string()
        .contains("u_min"));
    s.u_min = None;
    s.u_max = None;
    s.zeta = -1.0;
    assert!(SafetyFilter::new(2, 1, false, s)
        .unwrap_err()
        .to_string()
        .contains("zeta"));
    assert!(ConditionMoments::from_parts(
        vec![1.0, 2.0],
        DMatrix::from_row_slice(2, 2, &[1.0, 0.0, 0.0, -1.0]),
        1
    )
    .is_err());
}

/// Random strictly feasible programs (u = 0 meets every barrier with room to
/// spare, CLF slack free) are all solved to full accuracy with KKT residuals
/// below 10⁻⁶. Guards the solver settings: without iterative refinement of
/// the KKT solves about one in six of these ends `AlmostSolved` (13 %) or in
/// a false infeasibility (3 %).
#[test]
fn random_feasible_programs_are_solved_to_full_accuracy() {
    solve_feasible_programs(11, 600, |_, _, _| {});
}

/// References and box bounds far beyond the conditions' unit order (a
/// reference of 10⁹, bounds of 10³⁰⁰ meaning "no bound") give the
/// projection of `û` onto the feasible interval clamped into the box, as at
/// unit order: the solvers alone misread such programs as unbounded
/// (reference ≥ 10⁶, bounds ≥ 10⁹) and the fallback replaced the control.
/// One control, one barrier, against the bisection of
/// [`feasible_end`]; answers up to 10⁷ in magnitude.
#[test]
fn far_references_and_bounds_give_the_projection() {
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let mut checked = 0;
    for trial in 0..12 {
        let (mom, p, c) = one_control_barrier(trial, &mut rng);
        let scbc = |u: f64| mom.mean(&[u]) - c * mom.variance(&[u]).sqrt();
        for u_ref in [-1e9, -1e7, -3e5, 3e5, 1e7, 1e9] {
            for bound in [None, Some(20.0), Some(1e8), Some(1e12), Some(1e300)] {
                let mut settings = SafetySettings::new(1);
                settings.probability = p;
                settings.u_min = bound.map(|b| vec![-b]);
                settings.u_max = bound.map(|b| vec![b]);
                let mut filter = SafetyFilter::new(1, 1, false, settings).unwrap();
                let mut out = ControlOutput::new(1, 1);
                filter
                    .solve(std::slice::from_ref(&mom), None, &[u_ref], &mut out)
                    .unwrap();
                let b = bound.unwrap_or(f64::INFINITY);
                let end = feasible_end(scbc, 0.0, u_ref.clamp(-b, b));
                if end.abs() > 1e7 {
                    continue; // beyond the solvers' range
                }
                checked += 1;
                assert!(
                    matches!(
                        out.status,
                        ControlStatus::Optimal | ControlStatus::AlmostOptimal
                    ) && (out.u[0] - end).abs() <= 1e-6 * (1.0 + end.abs()),
                    "trial {trial}, û = {u_ref:e}, bound {bound:?}: {:?} u = {} against {end}",
                    out.status,
                    out.u[0]
                );
            }
        }
    }
    assert!(checked >= 200, "{checked} programs checked");
}

/// Two controls, two barriers, a reference of up to 10⁹ and no bounds or
/// bounds of ±20, ±10⁸ (lowered while solving) or ±10³⁰⁰: the rescaled
/// program's solution meets the KKT conditions
/// of the program as set, to 10⁻⁷ relative to the objective's gradient
/// (and its value, for the complementarity), with
/// the duals scaled back; a reference the barriers admit is returned as
/// it is.
#[test]
fn far_references_meet_the_kkt_conditions_of_the_program_as_set() {
    let mut rng = ChaCha8Rng::seed_from_u64(22);
    let m = 2;
    let (mut checked, mut checked_far) = (0, 0);
    for trial in 0..20 {
        let cbcs: Vec<ConditionMoments> = (0..2)
            .map(|i| {
                let mut c = random_moments(m, &mut rng, 1 + i, 0.3);
                c.e[0] = 0.5 + 3.0 * c.cov[(0, 0)].sqrt();
                c
            })
            .collect();
        let scale = [1e5, 1e7, 1e9][trial % 3];
        let dir: f64 = rng.random_range(0.0..std::f64::consts::TAU);
        let u_ref = [scale * dir.cos(), scale * dir.sin()];
        for bound in [None, Some(20.0), Some(1e8), Some(1e300)] {
            let mut settings = SafetySettings::new(m);
            settings.probability = 0.9;
            settings.u_min = bound.map(|b| vec![-b; m]);
            settings.u_max = bound.map(|b| vec![b; m]);
            let mut filter = SafetyFilter::new(m, 2, false, settings).unwrap();
            let mut out = ControlOutput::new(m, 2);
            filter.solve(&cbcs, None, &u_ref, &mut out).unwrap();
            if bound.is_none() && out.u.iter().any(|v| v.abs() > 1e7) {
                // a minimiser beyond the solvers' range, with bounds of
                // 10⁸ or more too
                checked_far += 1;
                break;
            }
            checked += 1;
            assert!(
                !out.is_infeasible(),
                "trial {trial}, û = {u_ref:?}, bound {bound:?}: {:?}",
                out.status
            );
            if out.u == u_ref {
                assert!(out.constraints.iter().all(|c| c.slack >= 0.0));
                check_kkt(&filter, 1e-9);
            } else {
                // ‖q‖ = 2‖û‖; the objective's value ~‖û‖²
                check_kkt_to(&filter, 1e-7 * 2.0 * scale, 1e-7 * scale * scale);
            }
        }
    }
    assert!(
        checked >= 50 && checked_far <= 8,
        "{checked} checked, {checked_far} beyond range"
    );
}

/// Far-out programs the solvers cannot resolve are not reported solved,
/// nor infeasible ones misread: a reference of 10¹⁶⁰ (whose squares
/// overflow) that the condition rejects far out is not returned as the
/// control, and a program infeasible within any bounds is `Infeasible`
/// at bounds of 10³⁰⁰ as at 10, so that the fallback's `p*` is computed.
#[test]
fn far_out_programs_are_neither_solved_wrongly_nor_misread() {
    // mean 1 − u, variance 0.1 + u²: feasible near u = −0.6, not far out
    // (mean/std → 1 < c(0.99) = 2.33)
    let mom = ConditionMoments::from_parts(
        vec![1.0, -1.0],
        DMatrix::from_row_slice(2, 2, &[0.1, 0.0, 0.0, 1.0]),
        1,
    )
    .unwrap();
    for u_ref in [-1e100, -1e160, -1e300] {
        let mut settings = SafetySettings::new(1);
        settings.probability = 0.99;
        let mut filter = SafetyFilter::new(1, 1, false, settings).unwrap();
        let mut out = ControlOutput::new(1, 1);
        let r = filter.solve(std::slice::from_ref(&mom), None, &[u_ref], &mut out);
        if r.is_ok() && !out.is_infeasible() {
            assert!(
                out.u[0].abs() < 10.0 && out.constraints[0].slack >= -1e-6,
                "û = {u_ref:e}: {:?} u = {}",
                out.status,
                out.u[0]
            );
        }
    }
    // u ≥ 5 is needed (mean u − 5, no spread) and u ≤ 1 is allowed: no
    // control within the box, however far its other side
    let need = ConditionMoments::from_parts(vec![-5.0, 1.0], DMatrix::zeros(2, 2), 1).unwrap();
    for lower in [-10.0, -1e8, -1e300] {
        let mut settings = SafetySettings::new(1);
        settings.u_min = Some(vec![lower]);
        settings.u_max = Some(vec![1.0]);
        let mut filter = SafetyFilter::new(1, 1, false, settings).unwrap();
        let mut out = ControlOutput::new(1, 1);
        filter
            .solve(std::slice::from_ref(&need), None, &[0.0], &mut out)
            .unwrap();
        match &out.status {
            ControlStatus::Infeasible(info) => assert_eq!(
                info.solver,
                bayes_cbf::control::SolveStatus::Infeasible,
                "u_min = {lower:e}"
            ),
            s => panic!("u_min = {lower:e}: {s:?}"),
        }
    }
}

/// The filter solves each step's own data: the answer to a program does not
/// depend on the programs solved before it by the same (warm, updated in
/// place) solver, here one with moments scaled by 10³.
#[test]
fn solution_does_not_depend_on_earlier_steps() {
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let m = 2;
    let mut settings = SafetySettings::new(m);
    settings.probability = 0.95;
    settings.u_min = Some(vec![-3.0; m]);
    settings.u_max = Some(vec![3.0; m]);
    for trial in 0..20 {
        let mut make = |scale: f64| {
            let mut c = random_moments(m, &mut rng, 1, 0.3 * scale);
            c.e.iter_mut().for_each(|v| *v *= scale);
            c.e[0] = scale * (0.5 + 2.0 * c.cov[(0, 0)].sqrt() / scale);
            c
        };
        let first = [make(1e3), make(1e3)];
        let target = [make(1.0), make(1.0)];
        let u_ref = [rng.random_range(-5.0..5.0), rng.random_range(-5.0..5.0)];
        let mut fresh = SafetyFilter::new(m, 2, false, settings.clone()).unwrap();
        let mut warm = SafetyFilter::new(m, 2, false, settings.clone()).unwrap();
        let (mut a, mut b) = (ControlOutput::new(m, 2), ControlOutput::new(m, 2));
        warm.solve(&first, None, &u_ref, &mut b).unwrap();
        warm.solve(&target, None, &u_ref, &mut b).unwrap();
        fresh.solve(&target, None, &u_ref, &mut a).unwrap();
        assert_eq!(a.status, b.status, "trial {trial}");
        for (x, y) in a.u.iter().zip(&b.u) {
            assert!((x - y).abs() <= 1e-12, "trial {trial}: {x} vs {y}");
        }
    }
}

/// The fallbacks' names, as files and reports write them, parse back to
/// the same fallback; any other name is an error naming the field.
#[test]
fn fallback_names_round_trip() {
    use bayes_cbf::control::Fallback;
    for (f, name) in [
        (Fallback::MaxMargin, "max_margin"),
        (Fallback::Brake, "brake"),
        (Fallback::Hold, "hold"),
        (Fallback::Relax, "relax"),
    ] {
        assert_eq!(f.name(), name);
        assert_eq!(Fallback::parse(name).unwrap(), f);
    }
    let e = Fallback::parse("pray").unwrap_err().to_string();
    assert!(e.contains("fallback") && e.contains("pray"), "{e}");
}

/// The defaults promise the conditions as realised (predictive), the
/// paper's settings the latent ones and nothing else differs; each check
/// of `validate` holds at its boundary and fails just past it.
#[test]
fn safety_settings_defaults_and_boundaries() {
    let m = 2;
    let new = SafetySettings::new(m);
    assert!(new.predictive);
    let paper = SafetySettings::paper(m);
    assert!(!paper.predictive);
    assert_eq!(
        SafetySettings {
            predictive: true,
            ..paper
        },
        new
    );
    let ok = |s: &SafetySettings| s.validate(m).is_ok();
    let with = |f: &dyn Fn(&mut SafetySettings)| {
        let mut s = SafetySettings::new(m);
        f(&mut s);
        s
    };
    // R: RᵀR must be positive definite, R itself need not be
    assert!(ok(&with(&|s| s.r = -DMatrix::identity(m, m))));
    assert!(ok(&with(
        &|s| s.r = DMatrix::from_row_slice(2, 2, &[0.0, 1.0, 1.0, 0.0])
    )));
    // a singular R, whose RᵀR a plain Cholesky accepts on a rounding error
    assert!(!ok(&with(
        &|s| s.r = DMatrix::from_row_slice(2, 2, &[1.0, 1.0, 1.0, 1.0])
    )));
    assert!(!ok(&with(&|s| s.r = DMatrix::zeros(m, m))));
    assert!(ok(&with(
        &|s| s.r = DMatrix::from_diagonal_element(m, m, 1e-3)
    )));
    // weights 10³ apart are solved (with a warning), 3×10³ and 10⁷ apart refused by
    // how far apart they are, not as an indefinite matrix
    let spread = |w: f64| with(&move |s| s.r = DMatrix::from_row_slice(2, 2, &[1.0, 0.0, 0.0, w]));
    assert!(ok(&spread(1e3)));
    let e = spread(1e7).validate(m).unwrap_err().to_string();
    assert!(e.starts_with("invalid R = weights 1.0e7 apart: "), "{e}");
    let e = with(&|s| s.r = DMatrix::zeros(m, m))
        .validate(m)
        .unwrap_err();
    assert!(e.to_string().starts_with("invalid R = singular: "), "{e}");
    assert!(!ok(&spread(3e3)), "3e3 apart: 38% off on random programs");
    // the objective is divided by max diag RᵀR: λ over it must stay finite
    let tiny = with(&|s| s.r = DMatrix::from_diagonal_element(m, m, 1e-155));
    let e = tiny.validate(m).unwrap_err().to_string();
    assert!(
        e.contains("its scale against lambda is beyond the range of f64"),
        "{e}"
    );
    // equal bounds pin the control; crossed ones are an error
    let bounds = |lo: f64, hi: f64| {
        with(&move |s: &mut SafetySettings| {
            s.u_min = Some(vec![lo; 2]);
            s.u_max = Some(vec![hi; 2]);
        })
    };
    assert!(ok(&bounds(1.0, 1.0)));
    assert!(!ok(&bounds(1.0, 1.0 - 1e-12)));
    // a control free on one side is told to take a finite bound
    let e = bounds(f64::NEG_INFINITY, 1.0)
        .validate(m)
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("invalid u_min[0] = -inf: must be finite: bounds are given for every control, and a control free on one side takes a finite bound there, such as its actuator's limit"), "{e}");
    // p*'s tolerance in (0, 0.1)
    for (tol, good) in [
        (0.0, false),
        (1e-12, true),
        (0.0999, true),
        (0.1, false),
        (-1.0, false),
        (1.0, false),
    ] {
        assert_eq!(ok(&with(&|s| s.p_star_tol = tol)), good, "p_star_tol {tol}");
    }
}

/// The filter's own checks: `p < 0.5` only without relative-degree-1
/// conditions (a barrier of degree 1 or a CLF makes `c(p) < 0`
/// non-convex), `set_probability` validates and takes effect, moments of
/// the wrong length name the expected one, and the filter prints its
/// shape and settings.
#[test]
fn filter_checks_probability_shapes_and_prints_itself() {
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let m = 2;
    let low = SafetySettings {
        probability: 0.3,
        ..SafetySettings::new(m)
    };
    let rd2 = random_moments(m, &mut rng, 2, 0.3);
    let rd1 = random_moments(m, &mut rng, 1, 0.3);
    let mut out = ControlOutput::new(m, 1);
    let solve = |clf: bool, mom: &ConditionMoments, out: &mut ControlOutput| {
        let mut f = SafetyFilter::new(m, 1, clf, low.clone()).unwrap();
        let clc = clf.then(|| rd1.clone());
        f.solve(std::slice::from_ref(mom), clc.as_ref(), &[0.0; 2], out)
    };
    assert!(solve(false, &rd2, &mut out).is_ok());
    for (clf, mom) in [(false, &rd1), (true, &rd2)] {
        let e = solve(clf, mom, &mut out).unwrap_err().to_string();
        assert!(e.contains("probability"), "{e}");
    }
    let mut f = SafetyFilter::new(m, 1, false, SafetySettings::new(m)).unwrap();
    assert!(f.set_probability(1.0).is_err());
    assert_eq!(f.settings().probability, 0.99);
    f.set_probability(0.9).unwrap();
    assert_eq!(f.settings().probability, 0.9);
    f.solve(std::slice::from_ref(&rd1), None, &[0.0; 2], &mut out)
        .unwrap();
    assert!((out.constraints[0].c - GAUSS_C_0_9).abs() < 1e-12);
    let short = ConditionMoments::from_parts(vec![0.0; 2], DMatrix::identity(2, 2), 1).unwrap();
    let e = f
        .solve(std::slice::from_ref(&short), None, &[0.0; 2], &mut out)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("moments[0].e") && e.contains('3') && e.contains('2'),
        "{e}"
    );
    // an output of another shape is resized
    for (mu, nb) in [(1, 1), (2, 3)] {
        let mut other = ControlOutput::new(mu, nb);
        f.solve(std::slice::from_ref(&rd1), None, &[0.0; 2], &mut other)
            .unwrap();
        assert_eq!((other.u.len(), other.constraints.len()), (2, 1));
        assert_eq!(other, out);
    }
    let shown = format!("{f:?}");
    assert!(
        shown.starts_with("SafetyFilter") && shown.contains("probability: 0.9"),
        "{shown}"
    );
}

/// An infeasible step's report: the barriers whose condition the fallback
/// control breaks, at `ζ = 0.2` and `c(0.99)`, and the brake's control, the
/// point of the box nearest zero.
#[test]
fn the_fallback_reports_exactly_the_violated_barriers() {
    let exact = |e: [f64; 2], std: f64| {
        let mut cov = DMatrix::zeros(2, 2);
        cov[(0, 0)] = std * std;
        ConditionMoments::from_parts(e.to_vec(), cov, 1).unwrap()
    };
    let moms = [
        // met without ζ, broken with it: 0.1 − 0.2 − 2.33·0.01 < 0
        exact([0.1, 0.0], 0.01),
        // met: 0.5 − 0.2 − 2.33·0.1 = 0.067
        exact([0.5, 0.0], 0.1),
        // no control in the box meets it
        exact([-5.0, 0.1], 0.0),
    ];
    for (lo, hi, brake) in [(-1.0, 1.0, 0.0), (0.5, 1.0, 0.5), (-1.0, -0.25, -0.25)] {
        let mut settings = SafetySettings::new(1);
        settings.zeta = 0.2;
        settings.u_min = Some(vec![lo]);
        settings.u_max = Some(vec![hi]);
        settings.fallback = Fallback::Brake;
        let mut filter = SafetyFilter::new(1, 3, false, settings).unwrap();
        let mut out = ControlOutput::new(1, 3);
        filter.solve(&moms, None, &[0.3], &mut out).unwrap();
        assert_eq!(out.u, vec![brake]);
        match &out.status {
            ControlStatus::Infeasible(info) => {
                let want: Vec<usize> = (0..3)
                    .filter(|&k| {
                        let m = &moms[k];
                        let std = m.variance(&out.u).sqrt();
                        m.mean(&out.u) - 0.2 - GAUSS_C_0_99 * std < 0.0
                    })
                    .collect();
                assert_eq!(info.violated, want);
                if brake == 0.0 {
                    assert_eq!(info.violated, vec![0, 2]);
                }
            }
            s => panic!("expected infeasible, got {s:?}"),
        }
    }
}
