//! The scenario interface of the binary: `list`, `--print-config`, `--set`,
//! unknown keys and bad files.

mod common;

use common::{run_in, scratch_dir};
use serde_json::Value;

#[test]
fn scenario_interface() {
    let dir = scratch_dir("scenarios_interface");
    let list = run_in(&dir, &["list"]);
    assert!(list.status.success());
    for (sc, _) in bayes_cbf_scenario::scenario::BUILTIN {
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
