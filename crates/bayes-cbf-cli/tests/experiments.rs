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

/// The calibration and soak results are checked through the library
/// (`bayes-cbf-scenario/tests/experiments.rs`); here, the files the binary
/// writes for them.
#[test]
fn calibration_and_soak_write_their_files() {
    let dir = scratch_dir("calibration-files");
    let out = dir.join("cal");
    let r = run(&[
        "run",
        "calibration",
        "--quick",
        "--episodes",
        "1",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(r.status.success(), "stderr: {}", r.stderr);
    let s = summary(&out);
    assert_eq!(s["scenario"], "calibration");
    assert!(is_png(&out.join("calibration.png")));
    let csv = std::fs::read_to_string(out.join("episodes.csv")).unwrap();
    assert_eq!(csv.lines().count(), 1 + 2 * 2 * 7);
    let out = dir.join("soak");
    let r = run(&[
        "run",
        "soak",
        "--steps",
        "200",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(r.status.success(), "stderr: {}", r.stderr);
    assert_eq!(summary(&out)["steps"], 200);
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
