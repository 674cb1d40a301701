//! Helpers shared by the CLI integration tests: scratch directories and
//! runs of the real binary.

#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;

/// Captured result of one run of the binary.
pub struct Run {
    /// Exit status.
    pub status: std::process::ExitStatus,
    /// Standard output as text.
    pub stdout: String,
    /// Standard error as text.
    pub stderr: String,
}

/// A scratch directory, removed when dropped unless the test is failing
/// (so that its files can be inspected).
pub struct Scratch(PathBuf);

impl std::ops::Deref for Scratch {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.0
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        if !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.0);
            if let Some(parent) = self.0.parent() {
                let _ = std::fs::remove_dir(parent); // only if empty
            }
        }
    }
}

/// A fresh, empty directory unique to this test process and `name`.
pub fn scratch_dir(name: &str) -> Scratch {
    let dir = std::env::temp_dir()
        .join(format!("bayes-cbf-cli-tests-{}", std::process::id()))
        .join(name);
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    Scratch(dir)
}

/// Runs `bayes-cbf ARGS` in `cwd`.
pub fn run_in(cwd: &Path, args: &[&str]) -> Run {
    let out = Command::new(env!("CARGO_BIN_EXE_bayes-cbf"))
        .args(args)
        .current_dir(cwd)
        .output()
        .expect("the binary runs");
    Run {
        status: out.status,
        stdout: String::from_utf8_lossy(&out.stdout).into_owned(),
        stderr: String::from_utf8_lossy(&out.stderr).into_owned(),
    }
}

/// Runs `bayes-cbf ARGS` in the system temporary directory.
pub fn run(args: &[&str]) -> Run {
    run_in(&std::env::temp_dir(), args)
}

/// The JSON file at `path`.
pub fn read_json(path: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{path:?}: {e}"));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{path:?}: {e}"))
}

/// A PNG file of some size is at `path`.
pub fn is_png(path: &Path) -> bool {
    std::fs::read(path).is_ok_and(|b| b.len() > 1000 && &b[1..4] == b"PNG")
}

/// Runs `bayes-cbf run NAME --out DIR EXTRA...` into a fresh scratch
/// directory; returns it, `DIR` and the `summary.json` written there.
pub fn run_into(name: &str, extra: &[&str]) -> (Scratch, PathBuf, serde_json::Value) {
    let dir = scratch_dir(name);
    let out = dir.join("out");
    let mut args = vec!["run", name, "--out", out.to_str().unwrap()];
    args.extend_from_slice(extra);
    let r = run(&args);
    assert!(r.status.success(), "{args:?}: {}", r.stderr);
    let summary = read_json(&out.join("summary.json"));
    assert_eq!(summary["scenario"], name, "{summary}");
    (dir, out, summary)
}

/// The words of `line` (a command line whose values hold no spaces).
pub fn words(line: &str) -> Vec<&str> {
    line.split_whitespace().collect()
}

/// Asserts that `r` failed with one `error: ...` line on stderr (besides
/// warnings) containing every string of `expect`, and no panic.
#[track_caller]
pub fn assert_fails(r: &Run, expect: &[&str], case: &str) {
    assert!(!r.status.success(), "{case}: accepted");
    assert!(!r.stderr.contains("panicked"), "{case}: {}", r.stderr);
    // warnings of the scenario's design may come first
    let lines: Vec<&str> = r
        .stderr
        .lines()
        .filter(|l| !l.starts_with("warning: "))
        .collect();
    assert_eq!(
        lines.len(),
        1,
        "{case}: one error line expected: {}",
        r.stderr
    );
    assert!(lines[0].starts_with("error: "), "{case}: {}", r.stderr);
    for e in expect {
        assert!(
            r.stderr.contains(e),
            "{case}: expected '{e}' in: {}",
            r.stderr
        );
    }
}

/// A cart against a wall, written with nothing but its system, barrier,
/// bounds and reference: the defaults (a zero prior mean) leave the model
/// ignorant of `p' = v` and of the input, which the run warns of.
pub const BARE_CART: &str = r#"
start = [-0.5, 0.0]

[system]
type = "expression"
state = ["p", "v"]
control = ["F"]
params = { m = 1.5, c = 0.8 }
f = ["v", "-c/m*v"]
g = [["0"], ["1/m"]]

[[barriers]]
type = "expression"
h = "1 - p"
relative_degree = 2
k_alpha = [4.0, 4.0]

[controller]
u_min = [-5.0]
u_max = [5.0]

[reference]
type = "feedback"
u0 = [0.0]
gain = [[4.0, 3.0]]
target = [0.8, 0.0]
"#;
