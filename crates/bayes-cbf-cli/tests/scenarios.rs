//! The scenario interface of the binary: `list`, `--print-config`, `--set`,
//! unknown keys and bad files.

mod common;

use common::{assert_fails, read_json, run_in, scratch_dir, words, BARE_CART};

#[test]
fn scenario_interface() {
    let dir = scratch_dir("scenarios_interface");
    let list = run_in(&dir, &["list"]);
    assert!(list.status.success());
    for (sc, _) in bayes_cbf_scenario::scenario::BUILTIN {
        assert!(list.stdout.contains(sc), "{}", list.stdout);
    }
    // --print-config gives a file that runs, with overrides applied
    let set = "run ackermann-bayes-cbf --print-config --set steps=50 --set";
    let cfg = run_in(&dir, &words(&format!("{set} controller.probability=0.9")));
    assert!(cfg.status.success(), "{}", cfg.stderr);
    std::fs::write(dir.join("my.toml"), &cfg.stdout).unwrap();
    let out = dir.join("mine");
    let r = run_in(&dir, &["run", "my.toml", "--out", &out.to_string_lossy()]);
    assert!(r.status.success(), "{}", r.stderr);
    let s = read_json(&out.join("summary.json"));
    assert_eq!(s["steps"], 50);
    assert_eq!(s["probability"], 0.9);
    // errors: one line naming the key, no panic, no output
    let fails = |args: &str, want: &str| assert_fails(&run_in(&dir, &words(args)), &[want], args);
    for (set, want) in [
        ("controller.probabilty=0.9", "probabilty"),
        ("controller.probability=1.5", "probability"),
        ("steps=0", "steps"),
        ("start=[1.0]", "start"),
        ("controller.u_min=[6.0,6.0]", "u_min"),
        ("gp.lengthscales=[0.0]", "lengthscales"),
        ("controller.fallback=explode", "fallback"),
        ("learning.window=100 --set learning.budget=100", "not both"),
        ("learning.budget=1", "budget"),
    ] {
        fails(&format!("run ackermann-bayes-cbf --set {set}"), want);
    }
    fails("run no-such-scenario", "unknown scenario");
    fails("run my.toml --set gp.A.scale=-1", "scale");
    std::fs::write(
        dir.join("bad.toml"),
        "name = \"x\"\ndt = 0.01\nsteps = 5\nstart = [0.0, 0.0\n",
    )
    .unwrap();
    let r = run_in(&dir, &["run", "bad.toml"]);
    assert!(
        !r.status.success() && r.stderr.contains("bad.toml") && r.stderr.contains("line"),
        "{}",
        r.stderr
    );
}

/// A barrier of relative degree 3 runs (its moments by Monte Carlo) and
/// says so, naming the barrier by its `h`; the first steps' few
/// observations raise no known-row warning.
#[test]
fn a_barrier_beyond_relative_degree_two_is_announced() {
    let dir = scratch_dir("scenarios_rd3");
    let barrier = r#"barriers.0={ type = "expression", h = "1 - p", relative_degree = 3, k_alpha = [1.0, 3.0, 3.0] }"#;
    let r = run_in(
        &dir,
        &[
            "run",
            "double-integrator",
            "--set",
            "steps=3",
            "--set",
            barrier,
            "--out",
            "o",
        ],
    );
    assert!(r.status.success(), "{}", r.stderr);
    for part in [
        "barrier[0] '1 - p' has relative degree 3",
        "joint posterior draws",
    ] {
        assert!(r.stderr.contains(part), "{part}: {}", r.stderr);
    }
    assert!(!r.stderr.contains("known_rows"), "{}", r.stderr);
}

/// The bare cart pushed at its wall (relative degree 2), with a prior whose
/// input gain is off, under the paper's latent condition and process noise
/// on its velocity: where the noise takes `h` below zero within a step that
/// met its condition, from inside the set the gains keep, the run says so
/// and names the latent condition.
#[test]
fn a_relative_degree_two_crossing_in_a_met_step_is_warned_of() {
    let dir = scratch_dir("scenarios_met_crossing");
    std::fs::write(dir.join("cart.toml"), BARE_CART).unwrap();
    let prior = r#"gp.prior_mean={ type = "expression", params = { k = 1.0 }, f = ["v", "0"], g = [["0"], ["k"]] }"#;
    let mut args = vec!["run", "cart.toml", "--seeds", "0..10", "--out", "o"];
    for set in [
        "controller.predictive=false",
        "sim.process_noise=0.1",
        prior,
        "gp.known_rows=[0]",
        "gp.input_map=[1]",
        "gp.lengthscales=[2.0]",
        "gp.B=[[0.5, 0.0], [0.0, 0.01]]",
        "reference.target=[4.0, 0.0]",
    ] {
        args.extend(["--set", set]);
    }
    let r = run_in(&dir, &args);
    let said = |part: &str| r.stderr.contains(part);
    assert!(
        r.status.success()
            && said("that met its condition (relative degree 2)")
            && said("use controller.predictive = true"),
        "{}",
        r.stderr
    );
}
