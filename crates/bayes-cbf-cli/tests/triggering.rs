//! Self-triggered control through the binary: the files of `bayes-cbf run
//! ackermann-triggering --quick` (paper, Fig. 2; its numbers are checked in
//! `bayes-cbf-scenario/tests/figure_experiments.rs`) and the validation of
//! the `[trigger]` settings of the scenario `ackermann-self-triggered`.

mod common;

use common::{assert_fails, is_png, run, run_into, scratch_dir};

#[test]
fn ackermann_triggering_quick_writes_its_runs() {
    let (_dir, out, s) = run_into("ackermann-triggering", &["--quick"]);
    assert_eq!(s["self_triggered"]["collided"], false);
    for f in ["lipschitz.png", "tau-vs-zeta.png"] {
        assert!(is_png(&out.join(f)), "{f}");
    }
    for sub in ["fixed-step", "self-triggered", "self-triggered-numerical"] {
        let csv = std::fs::read_to_string(out.join(sub).join("trajectory.csv")).unwrap();
        let head = csv.lines().next().unwrap();
        for col in ["lipschitz_analytic", "tau_analytic", "hold", "margin0"] {
            assert!(head.split(',').any(|h| h == col), "{sub}: {col}");
        }
        assert!(csv.lines().count() > 2, "{sub}");
        assert!(out.join(sub).join("summary.json").is_file(), "{sub}");
    }
    // the top level's trajectory.csv is the self-triggered run's
    let top = std::fs::read_to_string(out.join("trajectory.csv")).unwrap();
    let sub = std::fs::read_to_string(out.join("self-triggered").join("trajectory.csv")).unwrap();
    assert_eq!(top, sub);
}

#[test]
fn trigger_settings_are_validated() {
    let dir = scratch_dir("trigger-errors");
    let out = dir.join("out");
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
        let args = ["run", "ackermann-self-triggered", "--set", set, "--out"];
        let r = run(&[&args[..], &[out.to_str().unwrap()]].concat());
        assert_fails(&r, &[needle], set);
    }
}
