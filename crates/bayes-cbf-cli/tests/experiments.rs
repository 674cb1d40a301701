//! The experiments through the binary: the files each writes beside its
//! `summary.json`, and the options that size them. Their numbers are
//! checked through the library (`bayes-cbf-scenario`: the experiments'
//! unit tests and `tests/experiments.rs`, `tests/figure_experiments.rs`).

mod common;

use common::{assert_fails, is_png, run, run_into, words};

#[test]
fn experiments_write_their_files() {
    let (_dir, out, s) = run_into("pendulum-learning", &["--seed", "1"]);
    assert_eq!(s["seed"], 1);
    for model in ["MVGP", "CoGP"] {
        let vwe = s["models"][model]["heldout"]["variance_weighted_error"].as_f64();
        assert!(vwe.is_some_and(|v| v.is_finite() && v > 0.0), "{model}");
    }
    for f in ["pendulum_f.png", "pendulum_g.png", "pendulum_std.png"] {
        assert!(is_png(&out.join(f)), "{f}");
    }
    assert!(out.join("trajectory.csv").exists() && out.join("grid.csv").exists());

    let (_dir, out, s) = run_into("speed-test", &["--quick"]);
    assert_eq!(s["quick"], true);
    assert_eq!(s["table"].as_array().unwrap().len(), 16);
    assert!(is_png(&out.join("speed_test.png")) && is_png(&out.join("speed_ratio.png")));
    // the training samples at the largest k of each system: the pendulum
    // leaves the third state and the second control empty
    let samples = std::fs::read_to_string(out.join("trajectory.csv")).unwrap();
    let mut lines = samples.lines();
    assert_eq!(
        lines.next(),
        Some("system,x1,x2,x3,u1,u2,xdot1,xdot2,xdot3")
    );
    let largest = |system: &str| {
        s["ks"][system]
            .as_array()
            .and_then(|ks| ks.iter().filter_map(|k| k.as_u64()).max())
            .unwrap() as usize
    };
    let rows: Vec<&str> = lines.collect();
    for system in ["pendulum", "ackermann"] {
        let of = rows.iter().filter(|r| r.starts_with(&format!("{system},")));
        assert_eq!(of.count(), largest(system), "{system}");
    }
    assert!(rows[0].starts_with("pendulum,") && rows[0].split(',').nth(3) == Some(""));

    let (_dir, out, s) = run_into("covariance-shapes", &["--quick"]);
    assert_eq!(s["models"].as_array().unwrap().len(), 2);
    assert!(is_png(&out.join("covariance-shapes.png")));
    // the k Ackermann samples both models are fitted to
    let samples = std::fs::read_to_string(out.join("trajectory.csv")).unwrap();
    assert!(samples.starts_with("x1,x2,x3,u1,u2,xdot1,xdot2,xdot3\n"));
    assert_eq!(
        samples.lines().count(),
        1 + s["k"].as_u64().unwrap() as usize
    );

    let (_dir, out, s) = run_into("calibration", &["--quick", "--episodes", "1"]);
    assert_eq!(s["fallback"], "relax");
    assert!(is_png(&out.join("calibration.png")));
    let csv = std::fs::read_to_string(out.join("episodes.csv")).unwrap();
    // one line per (system, truth, episode, controller): 10 controllers
    assert_eq!(csv.lines().count(), 1 + 2 * 2 * 10);

    let (_dir, _, s) = run_into(
        "calibration",
        &["--quick", "--episodes", "1", "--fallback", "relax"],
    );
    assert_eq!(s["fallback"], "relax");

    let (_dir, _, s) = run_into("soak", &["--steps", "200"]);
    assert_eq!(s["steps"], 200);
}

#[test]
fn experiment_sizes_are_checked() {
    for (args, want) in [
        ("run calibration --episodes 0", "episodes = 0: must be ≥ 1"),
        ("run soak --steps 5", "steps = 5: must be ≥ 10"),
        ("run soak --window 1 --steps 100", "window = 1: must be ≥ 2"),
        (
            "run speed-test --episodes 3",
            "episodes applies to the experiment(s) calibration",
        ),
        (
            "run calibration --window 30",
            "window applies to the experiment(s) soak",
        ),
        (
            "run pendulum-safe --steps 30",
            "--steps and --window apply to the experiments",
        ),
        ("run calibration --episodes -2", "episodes"),
        (
            "run calibration --fallback slow",
            "max_margin, brake, hold or relax",
        ),
        (
            "run soak --fallback relax",
            "fallback applies to the experiment(s) calibration",
        ),
        ("run pendulum-safe --fallback relax", "controller.fallback"),
        ("run pendulum-safe --quick", "--set steps=N"),
        ("run no-such-experiment", "no-such-experiment"),
    ] {
        assert_fails(&run(&words(args)), &[want], args);
    }
}
