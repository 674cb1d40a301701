//! The built-in closed-loop scenarios through the real binary: each shows
//! its expected outcome at the default seed and on at least 9 of 10 seeds;
//! the scenario interface (`list`, `--print-config`, `--set`, unknown keys).

mod common;

use common::{run_in, scratch_dir};
use serde_json::Value;
use std::path::Path;

fn run_summary(dir: &Path, scenario: &str, seed: Option<u64>) -> Value {
    let out = dir.join(format!(
        "{scenario}-{}",
        seed.map(|s| s.to_string())
            .unwrap_or_else(|| "default".into())
    ));
    let out_s = out.to_string_lossy().to_string();
    let seed_s = seed.map(|s| s.to_string());
    let mut args = vec!["run", scenario, "--out", &out_s];
    if let Some(s) = &seed_s {
        args.extend(["--seed", s]);
    }
    let r = run_in(dir, &args);
    assert!(r.status.success(), "{scenario}: {}", r.stderr);
    assert!(out.join("trajectory.csv").is_file());
    serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap()
}

fn f(v: &Value, k: &str) -> f64 {
    v[k].as_f64()
        .unwrap_or_else(|| panic!("{k} missing in {v}"))
}

fn outcome(scenario: &str, s: &Value) -> bool {
    match scenario {
        "ackermann-mean-cbf" => s["collided"] == true && f(s, "min_obstacle_distance") < 0.0,
        "ackermann-bayes-cbf" => s["collided"] == false && f(s, "min_obstacle_distance") >= 0.0,
        "ackermann-no-learning" => {
            s["collided"] == false
                && f(s, "min_obstacle_distance") >= 0.0
                && f(s, "final_goal_distance") > 1.5
        }
        "ackermann-learning" => {
            s["collided"] == false
                && f(s, "min_obstacle_distance") >= 0.0
                && f(s, "final_goal_distance") < 1.0
        }
        "pendulum-safe" => s["min_barrier"][0].as_f64().unwrap() >= 0.0 && s["safe"] == true,
        _ => unreachable!(),
    }
}

const SCENARIOS: [&str; 5] = [
    "ackermann-mean-cbf",
    "ackermann-bayes-cbf",
    "ackermann-no-learning",
    "ackermann-learning",
    "pendulum-safe",
];

#[test]
fn every_scenario_shows_its_outcome_at_the_default_seed() {
    let dir = scratch_dir("scenarios_default");
    for sc in SCENARIOS {
        let s = run_summary(&dir, sc, None);
        for key in [
            "scenario",
            "seed",
            "steps",
            "dt",
            "collided",
            "min_barrier",
            "final_state",
            "infeasible_steps",
            "triggers",
            "control_step_us",
        ] {
            assert!(!s[key].is_null(), "{sc}: {key} missing");
        }
        assert_eq!(s["scenario"], sc);
        assert!(outcome(sc, &s), "{sc}: {s:#}");
    }
}

#[test]
fn outcomes_hold_on_nine_of_ten_seeds() {
    let dir = scratch_dir("scenarios_seeds");
    std::thread::scope(|scope| {
        let handles: Vec<_> = SCENARIOS
            .iter()
            .map(|&sc| {
                let dir = &dir;
                scope.spawn(move || {
                    let ok = (0..10u64)
                        .filter(|&seed| outcome(sc, &run_summary(dir, sc, Some(seed))))
                        .count();
                    (sc, ok)
                })
            })
            .collect();
        for h in handles {
            let (sc, ok) = h.join().unwrap();
            assert!(ok >= 9, "{sc}: expected outcome on {ok}/10 seeds");
        }
    });
}

#[test]
fn learning_reduces_the_uncertainty() {
    let dir = scratch_dir("scenarios_trace");
    run_summary(&dir, "ackermann-learning", None);
    let csv =
        std::fs::read_to_string(dir.join("ackermann-learning-default/trajectory.csv")).unwrap();
    let mut lines = csv.lines();
    let head: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| head.iter().position(|h| *h == name).unwrap();
    let (tc, ds) = (col("trace_cov"), col("data_size"));
    let rows: Vec<Vec<String>> = lines
        .map(|l| l.split(',').map(String::from).collect())
        .collect();
    // tr(B_k ⊗ A) at the first step after each update against the last
    // step before it: adding data never raises the posterior variance, but
    // a refit of the hyperparameters may, so most (not all) updates drop it
    let (mut updates, mut drops) = (0, 0);
    for w in rows.windows(2) {
        let (a, b) = (&w[0], &w[1]);
        if a[ds] != b[ds] {
            let before: f64 = a[tc].parse().unwrap();
            let after: f64 = b[tc].parse().unwrap();
            updates += 1;
            if after < before {
                drops += 1;
            } else if updates == 1 {
                panic!("the first update must reduce the uncertainty: {before} → {after}");
            }
        }
    }
    assert!(updates >= 5, "only {updates} updates");
    // the refits share the update steps (every 40) and can raise the trace
    // once it is small: at seed 0 three of the nine updates raise it by ≤ 5 %
    // at the 3·10⁻⁶ level; which ones depends on controls at the 10⁻⁴ level
    assert!(
        2 * drops > updates,
        "trace dropped at {drops} of {updates} updates"
    );
    let first: f64 = rows[0][tc].parse().unwrap();
    let last: f64 = rows[rows.len() - 1][tc].parse().unwrap();
    assert!(last < first * 1e-3, "trace {first} → {last}");
}

#[test]
fn scenario_interface() {
    let dir = scratch_dir("scenarios_interface");
    let list = run_in(&dir, &["list"]);
    assert!(list.status.success());
    for sc in SCENARIOS {
        assert!(list.stdout.contains(sc), "{}", list.stdout);
    }
    // --print-config gives a file that runs, with overrides applied
    let cfg = run_in(
        &dir,
        &[
            "run",
            "ackermann-bayes-cbf",
            "--print-config",
            "--set",
            "steps=50",
            "--set",
            "controller.probability=0.9",
        ],
    );
    assert!(cfg.status.success(), "{}", cfg.stderr);
    std::fs::write(dir.join("my.toml"), &cfg.stdout).unwrap();
    let out = dir.join("mine");
    let r = run_in(&dir, &["run", "my.toml", "--out", &out.to_string_lossy()]);
    assert!(r.status.success(), "{}", r.stderr);
    let s: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(s["steps"], 50);
    assert_eq!(s["probability"], 0.9);
    // errors: one line naming the key, no panic, no output
    for (args, want) in [
        (
            vec![
                "run",
                "ackermann-bayes-cbf",
                "--set",
                "controller.probabilty=0.9",
            ],
            "probabilty",
        ),
        (
            vec![
                "run",
                "ackermann-bayes-cbf",
                "--set",
                "controller.probability=1.5",
            ],
            "probability",
        ),
        (
            vec!["run", "ackermann-bayes-cbf", "--set", "steps=0"],
            "steps",
        ),
        (
            vec!["run", "ackermann-bayes-cbf", "--set", "start=[1.0]"],
            "start",
        ),
        (
            vec![
                "run",
                "ackermann-bayes-cbf",
                "--set",
                "controller.u_min=[6.0, 6.0]",
            ],
            "u_min",
        ),
        (
            vec![
                "run",
                "ackermann-bayes-cbf",
                "--set",
                "gp.lengthscales=[0.0]",
            ],
            "lengthscales",
        ),
        (
            vec![
                "run",
                "ackermann-bayes-cbf",
                "--set",
                "controller.fallback=explode",
            ],
            "fallback",
        ),
        (
            vec![
                "run",
                "ackermann-bayes-cbf",
                "--set",
                "learning.window=100",
                "--set",
                "learning.budget=100",
            ],
            "not both",
        ),
        (
            vec!["run", "ackermann-bayes-cbf", "--set", "learning.budget=1"],
            "budget",
        ),
        (vec!["run", "no-such-scenario"], "unknown scenario"),
        (vec!["run", "my.toml", "--set", "gp.A.scale=-1"], "scale"),
    ] {
        let r = run_in(&dir, &args);
        assert!(!r.status.success(), "{args:?} should fail");
        assert!(r.stderr.contains(want), "{args:?}: {}", r.stderr);
        assert!(!r.stderr.contains("panicked"), "{args:?}: {}", r.stderr);
        assert_eq!(r.stderr.trim().lines().count(), 1, "{args:?}: {}", r.stderr);
    }
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
