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
