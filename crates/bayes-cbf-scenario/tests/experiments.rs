//! The Monte Carlo experiments through the library: the quick calibration
//! (rates, intervals, ordering of the controllers, independence of the
//! thread count) and a soak with a small window.

use bayes_cbf_scenario::experiments::{self, ExperimentArgs, Sizes};
use serde_json::Value;

/// The rows of a calibration summary by (system, truth, controller).
fn calibration_row<'a>(s: &'a Value, system: &str, truth: &str, controller: &str) -> &'a Value {
    s["rows"]
        .as_array()
        .unwrap()
        .iter()
        .find(|r| r["system"] == system && r["truth"] == truth && r["controller"] == controller)
        .unwrap_or_else(|| panic!("no row {system} / {truth} / {controller}"))
}

fn rate(v: &Value) -> f64 {
    v["rate"]
        .as_f64()
        .unwrap_or_else(|| panic!("no rate in {v}"))
}

#[test]
fn quick_calibration() {
    // the same seed on one and on two threads
    let on = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                experiments::run(
                    "calibration",
                    &ExperimentArgs {
                        seed: 3,
                        quick: true,
                    },
                )
                .unwrap()
            })
    };
    let (one, two) = (on(1), on(2));
    let s = one.summary();
    assert_eq!(s["scenario"], "calibration");
    assert_eq!(
        (s["seed"].as_u64(), s["quick"].as_bool()),
        (Some(3), Some(true))
    );
    assert_eq!(
        s["rows"],
        two.summary()["rows"],
        "results depend on the thread count"
    );
    assert!(
        s["errors"].as_array().unwrap().is_empty(),
        "{}",
        s["errors"]
    );
    let rows = s["rows"].as_array().unwrap();
    assert_eq!(
        rows.len(),
        2 * 2 * 4,
        "2 systems × 2 truths × 4 controllers"
    );
    for r in rows {
        assert_eq!(r["non_finite_records"], 0, "{r}");
        for key in [
            "episodes_violating_h",
            "steps_violating_h",
            "infeasible_steps",
        ] {
            let ci = r[key]["ci95"].as_array().unwrap();
            let (lo, hi) = (ci[0].as_f64().unwrap(), ci[1].as_f64().unwrap());
            assert!(
                0.0 <= lo && lo <= rate(&r[key]) && rate(&r[key]) <= hi && hi <= 1.0,
                "{key}: {r}"
            );
        }
        assert!(
            r["true_condition_violated"]["solved_steps"]["of"]
                .as_u64()
                .unwrap()
                > 0
        );
        assert!(
            r["standardised_condition"]["solved_steps"]["sd"]
                .as_f64()
                .unwrap()
                > 0.0
        );
    }
    let bayes = ["bayes-cbf p=0.9", "bayes-cbf p=0.99", "bayes-cbf p=0.999"];
    for system in ["ackermann", "pendulum"] {
        for truth in ["well_specified", "mis_specified"] {
            // the promised condition fails less often as p grows, and the
            // mean CBF (no margin) fails it most often
            let solved = |c: &str| {
                rate(
                    &calibration_row(&s, system, truth, c)["true_condition_violated"]
                        ["solved_steps"],
                )
            };
            let (r9, r99, r999, mean) = (
                solved(bayes[0]),
                solved(bayes[1]),
                solved(bayes[2]),
                solved("mean-cbf"),
            );
            assert!(
                mean > r99 && r9 >= r99 && r99 >= r999,
                "{system} {truth}: {mean} {r9} {r99} {r999}"
            );
        }
    }
    // the well-specified vehicle: calibrated on the active steps (where the
    // promise is tight) within a loose bound, the mean CBF near one half
    let active = |c: &str| {
        rate(
            &calibration_row(&s, "ackermann", "well_specified", c)["true_condition_violated"]
                ["active_steps"],
        )
    };
    assert!(active(bayes[1]) < 0.05, "{}", active(bayes[1]));
    assert!(active("mean-cbf") > 0.3, "{}", active("mean-cbf"));
    // paired episodes: the mean CBF violates h where the Bayes CBF does not
    // at least as often as the other way round
    for p in s["paired_mean_vs_bayes"].as_array().unwrap() {
        if p["system"] == "ackermann" && p["truth"] == "well_specified" {
            assert!(
                p["only_mean_cbf_violates"].as_u64() >= p["only_bayes_cbf_violates"].as_u64(),
                "{p}"
            );
        }
    }
    let csv = &one.tables()[0].csv;
    assert_eq!(
        csv.lines().count(),
        1 + 2 * 2 * 4 * s["episodes"].as_u64().unwrap() as usize
    );
}

#[test]
fn soak_with_a_window() {
    let r = experiments::run_sized(
        "soak",
        &ExperimentArgs::default(),
        &Sizes {
            steps: Some(1500),
            window: Some(120),
            ..Sizes::default()
        },
        &|_, _| {},
    )
    .unwrap();
    let s = r.summary();
    assert_eq!(s["scenario"], "soak");
    assert_eq!(
        (s["steps"].as_u64(), s["window"].as_u64()),
        (Some(1500), Some(120))
    );
    assert_eq!(s["non_finite"], 0);
    assert_eq!(
        s["final_model_observations"], 120,
        "the window bounds the model"
    );
    assert_eq!(s["refits"], 10, "one refit per tenth");
    let tenths = s["tenths"].as_array().unwrap();
    assert_eq!(tenths.len(), 10);
    for t in tenths {
        let p50 = t["control_step_us"]["p50"].as_f64().unwrap();
        let p99 = t["control_step_us"]["p99"].as_f64().unwrap();
        assert!(p50 > 0.0 && p99 >= p50, "{t}");
    }
    assert_eq!(tenths[9]["steps_done"], 1500);
    if cfg!(target_os = "linux") {
        for at in ["at_10_percent", "at_50_percent", "at_100_percent"] {
            assert!(s["memory_kb"][at]["peak"].as_u64().unwrap() > 0, "{at}");
        }
    }
}
