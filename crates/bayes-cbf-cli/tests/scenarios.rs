//! The scenario interface of the binary: `list`, `--print-config`, `--set`,
//! unknown keys and bad files.

mod common;

use common::{assert_fails, read_json, run_in, scratch_dir, words};

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
