//! End-to-end runs of the learning experiments through the binary:
//! `bayes-cbf run pendulum-learning` (paper, Fig. 4) and
//! `bayes-cbf run speed-test --quick` (Fig. 5, reduced), checking the files
//! and the `summary.json` fields of `interfaces.md`.

use serde_json::Value;
use std::path::Path;

mod common;

use common::{run, scratch_dir};

fn summary(dir: &Path) -> Value {
    let text = std::fs::read_to_string(dir.join("summary.json")).expect("summary.json written");
    serde_json::from_str(&text).expect("summary.json is JSON")
}

fn is_png(path: &Path) -> bool {
    std::fs::read(path).is_ok_and(|b| b.len() > 1000 && &b[1..4] == b"PNG")
}

#[test]
fn pendulum_learning_through_the_binary() {
    let dir = scratch_dir("pendulum-learning");
    let out = dir.join("out");
    let r = run(&[
        "run",
        "pendulum-learning",
        "--out",
        out.to_str().unwrap(),
        "--seed",
        "1",
    ]);
    assert!(r.status.success(), "stderr: {}", r.stderr);
    let s = summary(&out);
    assert_eq!(s["scenario"], "pendulum-learning");
    assert_eq!(s["seed"], 1);
    for model in ["MVGP", "CoGP"] {
        let m = &s["models"][model];
        let vwe = m["heldout"]["variance_weighted_error"].as_f64().unwrap();
        assert!(vwe.is_finite() && vwe > 0.0, "{model}: {vwe}");
        assert!(m["grid"]["rmse_F"].as_f64().unwrap() < 1.0, "{model}");
        assert!(m["fit_seconds"].as_f64().unwrap() > 0.0);
    }
    for f in ["pendulum_f.png", "pendulum_g.png", "pendulum_std.png"] {
        assert!(is_png(&out.join(f)), "{f}");
    }
    assert!(out.join("trajectory.csv").exists() && out.join("grid.csv").exists());
}

#[test]
fn quick_speed_test_through_the_binary() {
    let dir = scratch_dir("speed-test");
    let out = dir.join("out");
    let r = run(&[
        "run",
        "speed-test",
        "--quick",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(r.status.success(), "stderr: {}", r.stderr);
    let s = summary(&out);
    assert_eq!(s["scenario"], "speed-test");
    assert_eq!(s["quick"], true);
    let table = s["table"].as_array().unwrap();
    assert_eq!(table.len(), 16, "2 systems × 2 k × MVGP/CoGP × full/diag");
    for row in table {
        assert!(row["fit_seconds"]["median"].as_f64().unwrap() > 0.0);
        assert!(row["predict_seconds"]["median"].as_f64().unwrap() > 0.0);
    }
    assert!(is_png(&out.join("speed_test.png")) && is_png(&out.join("speed_ratio.png")));
}

#[test]
fn unknown_experiment_fails_with_one_line() {
    let r = run(&["run", "no-such-experiment"]);
    assert!(!r.status.success());
    assert_eq!(r.stderr.trim().lines().count(), 1, "{}", r.stderr);
}

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
fn quick_calibration_through_the_binary() {
    let dir = scratch_dir("calibration");
    let (one, two) = (dir.join("one"), dir.join("two"));
    // the same seed on one and on two threads
    for (out, threads) in [(&one, "1"), (&two, "2")] {
        let r = std::process::Command::new(env!("CARGO_BIN_EXE_bayes-cbf"))
            .args(["run", "calibration", "--quick", "--seed", "3", "--out"])
            .arg(out)
            .env("RAYON_NUM_THREADS", threads)
            .output()
            .unwrap();
        assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    }
    let s = summary(&one);
    assert_eq!(s["scenario"], "calibration");
    assert_eq!(
        (s["seed"].as_u64(), s["quick"].as_bool()),
        (Some(3), Some(true))
    );
    assert_eq!(
        s["rows"],
        summary(&two)["rows"],
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
    assert!(is_png(&one.join("calibration.png")));
    let csv = std::fs::read_to_string(one.join("episodes.csv")).unwrap();
    assert_eq!(
        csv.lines().count(),
        1 + 2 * 2 * 4 * s["episodes"].as_u64().unwrap() as usize
    );
}

#[test]
fn quick_soak_through_the_binary() {
    let dir = scratch_dir("soak");
    let out = dir.join("out");
    let r = run(&[
        "run",
        "soak",
        "--steps",
        "1500",
        "--window",
        "120",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(r.status.success(), "stderr: {}", r.stderr);
    let s = summary(&out);
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

#[test]
fn experiment_sizes_are_checked() {
    for (args, want) in [
        (vec!["run", "calibration", "--episodes", "0"], "--episodes"),
        (vec!["run", "soak", "--steps", "5"], "--steps"),
        (
            vec!["run", "soak", "--window", "1", "--steps", "100"],
            "--window",
        ),
        (vec!["run", "speed-test", "--episodes", "3"], "--episodes"),
        (vec!["run", "calibration", "--window", "30"], "--window"),
        (vec!["run", "pendulum-safe", "--steps", "30"], "--steps"),
        (vec!["run", "calibration", "--episodes", "-2"], "--episodes"),
    ] {
        let r = run(&args);
        assert!(!r.status.success(), "{args:?}");
        assert_eq!(r.stderr.trim().lines().count(), 1, "{args:?}: {}", r.stderr);
        assert!(r.stderr.contains(want), "{args:?}: {}", r.stderr);
    }
}
