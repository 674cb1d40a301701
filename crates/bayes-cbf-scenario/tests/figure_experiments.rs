//! The quick `covariance-shapes` (paper, Fig. 1) and `ackermann-triggering`
//! (Fig. 2) through the library: the MVGP's column covariances share one
//! shape and the CoGP's do not; the self-triggered loop's holds are the
//! corrected Prop. 3 recomputed from the parts it reports.

use bayes_cbf_scenario::experiments::{self, ExperimentArgs, ExperimentResult};
use bayes_cbf_scenario::scenario::trajectory_csv;

const QUICK: ExperimentArgs = ExperimentArgs {
    seed: 0,
    quick: true,
};

#[test]
fn covariance_shapes_quick() {
    let s = experiments::run("covariance-shapes", &QUICK)
        .unwrap()
        .summary();
    assert_eq!(s["scenario"], "covariance-shapes");
    let models = s["models"].as_array().unwrap();
    let spread = |name: &str| {
        models.iter().find(|m| m["model"] == name).unwrap()["shape_spread"]
            .as_f64()
            .unwrap()
    };
    // B_k ⊗ A: every column has the shape of A
    assert!(spread("MVGP") < 1e-9, "{}", spread("MVGP"));
    // Σ k0: the blocks are free, and the fit uses that freedom
    assert!(spread("CoGP") > 1e-2, "{}", spread("CoGP"));
    for m in models {
        let cols = m["column_covariances"].as_array().unwrap();
        assert_eq!(cols.len(), 3);
        for c in cols {
            assert!(c["trace"].as_f64().unwrap() > 0.0);
        }
    }
}

/// A column of a CSV table by name (words that are not numbers are NaN).
fn column(csv: &str, name: &str) -> Vec<String> {
    let mut lines = csv.lines();
    let i = lines.next().unwrap().split(',').position(|h| h == name);
    let i = i.unwrap_or_else(|| panic!("no column {name}"));
    lines
        .map(|l| l.split(',').nth(i).unwrap().to_string())
        .collect()
}

fn numbers(csv: &str, name: &str) -> Vec<f64> {
    let words = column(csv, name);
    words
        .iter()
        .map(|w| w.parse().unwrap_or(f64::NAN))
        .collect()
}

#[test]
fn ackermann_triggering_quick() {
    let result = experiments::run("ackermann-triggering", &QUICK).unwrap();
    let s = result.summary();
    let ExperimentResult::AckermannTriggering(r) = result else {
        panic!("not the triggering result")
    };
    assert_eq!(s["scenario"], "ackermann-triggering");
    let horizon = s["horizon_s"].as_f64().unwrap();
    assert_eq!(s["fixed_step"]["self_triggered"], false);
    for run in ["fixed_step", "self_triggered", "self_triggered_numerical"] {
        // the numerical estimate never exceeds the analytic bound
        assert_eq!(s[run]["trigger"]["numerical_above_analytic"], 0, "{run}");
        assert!(s[run]["triggers"].as_u64().unwrap() > 0);
    }
    // the self-triggered loop stays safe on the fine integration grid
    let st = &s["self_triggered"];
    assert_eq!(
        (&st["self_triggered"], &st["collided"]),
        (&true.into(), &false.into())
    );
    for h in st["min_barrier"].as_array().unwrap() {
        assert!(h.as_f64().unwrap() >= 0.0, "{st}");
    }
    // per-step records: both estimates, analytic ≥ numerical, holds add up
    // to the horizon
    for (sub, self_triggered) in [("fixed-step", false), ("self-triggered", true)] {
        let csv = trajectory_csv(r.run(sub).unwrap());
        let col = |name: &str| numbers(&csv, name);
        let (la, ln, ta, hold) = (
            col("lipschitz_analytic"),
            col("lipschitz_numerical"),
            col("tau_analytic"),
            col("hold"),
        );
        assert_eq!(la.len(), csv.lines().count() - 1);
        for (k, (a, n)) in la.iter().zip(&ln).enumerate() {
            assert!(
                a.is_finite() && n.is_finite() && n <= a,
                "{sub} row {k}: {n} > {a}"
            );
        }
        // τ_k recomputed from its reported parts: the corrected Prop. 3 for
        // each barrier (relative degree 1, α = 5 in the scenario) with its
        // certified margin, then the cuboid time
        let (tau_c, xdot) = (col("tau_cuboid"), col("xdot_norm"));
        let status = column(&csv, "status");
        let parts: Vec<[Vec<f64>; 3]> = (0..2)
            .map(|i| ["l_h", "l_grad_h", "margin"].map(|name| col(&format!("{name}{i}"))))
            .collect();
        for k in 0..la.len() {
            let l = la[k];
            let by_barriers = parts
                .iter()
                .map(|[lh, lg, m]| {
                    let (lh, lg, m) = (lh[k], lg[k], m[k]);
                    let a = m.max(0.0) / ((lh * (l + 5.0) + lg * xdot[k]) * xdot[k]);
                    (l * a).ln_1p() / l
                })
                .fold(f64::INFINITY, f64::min);
            let want = by_barriers.min(tau_c[k]);
            assert!(
                (ta[k] - want).abs() <= 1e-9 * want.max(1e-12),
                "{sub} row {k}: τ {} vs {want}",
                ta[k]
            );
            assert!(ta[k] >= 0.0);
            if self_triggered && k + 1 < la.len() {
                // the hold: the clamp of τ_k, or τ_min after an infeasible SOCP
                let want_hold = if status[k] == "infeasible" {
                    1e-3
                } else {
                    ta[k].clamp(1e-3, 0.1)
                };
                assert!((hold[k] - want_hold).abs() < 1e-12, "{sub} row {k}");
            }
        }
        let total: f64 = hold.iter().sum();
        assert!(
            (total - horizon).abs() < 1e-6,
            "{sub}: holds {total} vs {horizon}"
        );
        let last = hold.len() - 1;
        if self_triggered {
            // held for τ_k clamped to [τ_min, τ_max] = [1 ms, 0.1 s]
            assert!(hold[..last]
                .iter()
                .all(|h| (1e-3 - 1e-12..=0.1).contains(h)));
        } else {
            assert!(hold.iter().all(|h| (h - 0.01).abs() < 1e-12));
        }
    }
    // the ζ sweep ran; on the same data a larger margin gives a longer τ
    assert!(s["zeta_sweep"].as_array().unwrap().len() >= 2);
    let curve = s["tau_vs_zeta_on_self_triggered_data"].as_array().unwrap();
    let tau = |i: usize, k: &str| curve[i][k].as_f64().unwrap();
    for i in 1..curve.len() {
        for k in ["tau_analytic_median_s", "tau_numerical_median_s"] {
            assert!(tau(i, k) > tau(i - 1, k), "{k}: {curve:?}");
        }
        assert!(tau(i, "tau_analytic_median_s") <= tau(i, "tau_numerical_median_s"));
    }
}
