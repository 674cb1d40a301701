//! Self-triggered control through the binary: `bayes-cbf run
//! ackermann-triggering --quick` (paper, Fig. 2) and the scenario
//! `ackermann-self-triggered` with its `[trigger]` settings.

use serde_json::Value;
use std::path::Path;

mod common;

use common::{run, scratch_dir};

fn json(path: &Path) -> Value {
    let text = std::fs::read_to_string(path).expect("summary.json written");
    serde_json::from_str(&text).expect("summary.json is JSON")
}

fn is_png(path: &Path) -> bool {
    std::fs::read(path).is_ok_and(|b| b.len() > 1000 && &b[1..4] == b"PNG")
}

/// Rows of a CSV file as (header, rows of strings).
fn csv(path: &Path) -> (Vec<String>, Vec<Vec<String>>) {
    let text = std::fs::read_to_string(path).expect("trajectory.csv written");
    let mut lines = text.lines();
    let head = lines.next().unwrap().split(',').map(String::from).collect();
    let rows = lines
        .map(|l| l.split(',').map(String::from).collect())
        .collect();
    (head, rows)
}

fn column_words(head: &[String], rows: &[Vec<String>], name: &str) -> Vec<String> {
    let i = head.iter().position(|h| h == name).expect(name);
    rows.iter().map(|r| r[i].clone()).collect()
}

fn column(head: &[String], rows: &[Vec<String>], name: &str) -> Vec<f64> {
    let i = head.iter().position(|h| h == name).expect(name);
    rows.iter()
        .map(|r| r[i].parse::<f64>().unwrap_or(f64::NAN))
        .collect()
}

#[test]
fn ackermann_triggering_quick() {
    let dir = scratch_dir("ackermann-triggering");
    let out = dir.join("out");
    let r = run(&[
        "run",
        "ackermann-triggering",
        "--quick",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(r.status.success(), "stderr: {}", r.stderr);
    let s = json(&out.join("summary.json"));
    assert_eq!(s["scenario"], "ackermann-triggering");
    let horizon = s["horizon_s"].as_f64().unwrap();
    for f in ["lipschitz.png", "tau-vs-zeta.png"] {
        assert!(is_png(&out.join(f)), "{f}");
    }
    let fixed = &s["fixed_step"];
    assert_eq!(fixed["self_triggered"], false);
    for run in ["fixed_step", "self_triggered", "self_triggered_numerical"] {
        let r = &s[run];
        // the numerical estimate never exceeds the analytic bound
        assert_eq!(r["trigger"]["numerical_above_analytic"], 0, "{run}");
        assert!(r["triggers"].as_u64().unwrap() > 0);
    }
    // the self-triggered loop stays safe on the fine integration grid
    let st = &s["self_triggered"];
    assert_eq!(st["self_triggered"], true);
    assert_eq!(st["collided"], false);
    for h in st["min_barrier"].as_array().unwrap() {
        assert!(h.as_f64().unwrap() >= 0.0, "{st}");
    }
    // per-step records: both estimates, analytic ≥ numerical, holds add up
    // to the horizon
    for (sub, self_triggered) in [("fixed-step", false), ("self-triggered", true)] {
        let (head, rows) = csv(&out.join(sub).join("trajectory.csv"));
        let la = column(&head, &rows, "lipschitz_analytic");
        let ln = column(&head, &rows, "lipschitz_numerical");
        let ta = column(&head, &rows, "tau_analytic");
        let hold = column(&head, &rows, "hold");
        assert_eq!(la.len(), rows.len());
        for (k, (a, n)) in la.iter().zip(&ln).enumerate() {
            assert!(
                a.is_finite() && n.is_finite() && n <= a,
                "{sub} row {k}: {n} > {a}"
            );
        }
        // τ_k recomputed from its reported parts: the corrected Prop. 3 for
        // each barrier (relative degree 1, α = 5 in the scenario) with its
        // certified margin, then the cuboid time
        let tau_c = column(&head, &rows, "tau_cuboid");
        let xdot = column(&head, &rows, "xdot_norm");
        let status = column_words(&head, &rows, "status");
        for k in 0..rows.len() {
            let l = la[k];
            let by_barriers = (0..2)
                .map(|i| {
                    let part = |name: &str| column(&head, &rows, &format!("{name}{i}"))[k];
                    let (lh, lg, m) = (part("l_h"), part("l_grad_h"), part("margin"));
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
            if self_triggered && k + 1 < rows.len() {
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
        if self_triggered {
            // held for τ_k clamped to [τ_min, τ_max] = [1 ms, 0.1 s]
            let last = hold.len() - 1;
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

#[test]
fn trigger_settings_are_validated() {
    let dir = scratch_dir("trigger-errors");
    for (set, needle) in [
        ("trigger.delta_l=0", "delta_l"),
        ("trigger.delta_l=1.5", "delta_l"),
        ("trigger.cuboid=[0.2, 0.2]", "trigger.cuboid"),
        ("trigger.grid=1", "grid"),
        ("trigger.tau_min=0", "trigger.tau_min"),
        ("trigger.tau_max=0.0001", "trigger.tau_max"),
        ("trigger.tau_from=\"guess\"", "trigger.tau_from"),
        ("controller.zeta=0", "controller.zeta"),
        ("controller.probability=0.99995", "controller.probability"),
        ("trigger.bogus=1", "bogus"),
    ] {
        let r = run(&[
            "run",
            "ackermann-self-triggered",
            "--out",
            dir.join("out").to_str().unwrap(),
            "--set",
            set,
        ]);
        assert!(!r.status.success(), "{set} accepted");
        assert!(r.stderr.contains(needle), "{set}: {}", r.stderr);
        assert!(!r.stderr.contains("panicked"), "{set}: {}", r.stderr);
    }
}
