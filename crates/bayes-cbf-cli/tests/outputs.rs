//! Where the binary's outputs go: a run's directory gets all of its files or
//! none, an output path is never replaced by something of another kind, and
//! a full stdout or stderr is an error or ignored, never a panic.

mod common;

use common::{run_in, scratch_dir, words, Run, BARE_CART};
use std::process::{Command, Stdio};

/// A short run of the double integrator, extra arguments appended.
fn short_run<'a>(extra: &[&'a str]) -> Vec<&'a str> {
    let mut args = vec!["run", "double-integrator", "--set", "steps=20"];
    args.extend_from_slice(extra);
    args
}

/// [`short_run`] in `dir` with the override `set`, written to `out`.
fn short_run_set(dir: &std::path::Path, set: &str, out: &str) -> Run {
    run_in(dir, &short_run(&["--set", set, "--out", out]))
}

/// Three observations of a 2-state, 1-control system.
const DATA: &str =
    "x1,x2,u1,xdot1,xdot2\n0.1,0.2,0.5,0.2,-0.4\n0.3,-0.1,1.0,-0.1,-1.9\n0.5,0.4,-1.0,0.4,-3.0\n";

/// A short fit of `d.csv` (`DATA`) written to `out`.
fn fit_into(out: &str) -> Vec<&str> {
    let args = "fit --data d.csv --state-dim 2 --control-dim 1 --max-iters 3 --out";
    let mut v: Vec<&str> = args.split(' ').collect();
    v.push(out);
    v
}

#[test]
fn a_run_that_cannot_write_one_file_writes_none() {
    let dir = scratch_dir("outputs-partial");
    std::fs::create_dir_all(dir.join("out").join("summary.json")).unwrap();
    let r = run_in(&dir, &short_run(&["--out", "out"]));
    assert!(!r.status.success());
    assert!(
        r.stderr
            .contains("out/summary.json': a directory of that name exists"),
        "{}",
        r.stderr
    );
    let left: Vec<_> = std::fs::read_dir(dir.join("out"))
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(left, ["summary.json"], "files left behind");
    // nor a staging directory
    assert_eq!(std::fs::read_dir(&*dir).unwrap().count(), 1);
    // an output path that is a file is refused before the run
    std::fs::write(dir.join("file"), "keep").unwrap();
    let r = run_in(&dir, &short_run(&["--out", "file"]));
    assert!(r.stderr.contains("'file' exists and is not a directory"));
    assert_eq!(std::fs::read_to_string(dir.join("file")).unwrap(), "keep");
    // a complete run, into `--out .` as well
    std::fs::create_dir(dir.join("here")).unwrap();
    let r = run_in(&dir.join("here"), &short_run(&["--out", "."]));
    assert!(r.status.success(), "{}", r.stderr);
    assert!(dir.join("here").join("summary.json").is_file());
    assert_eq!(std::fs::read_dir(&*dir).unwrap().count(), 3, "staging left");
}

/// `fit --out` naming its own data file, or `predict --out` its model
/// file, is refused before anything is written: the input stays.
#[test]
fn an_output_that_is_an_input_is_refused() {
    let dir = scratch_dir("outputs-input");
    std::fs::write(dir.join("d.csv"), DATA).unwrap();
    let r = run_in(&dir, &fit_into("./d.csv"));
    assert!(
        r.stderr.contains("is the --data file 'd.csv'"),
        "{}",
        r.stderr
    );
    assert_eq!(std::fs::read_to_string(dir.join("d.csv")).unwrap(), DATA);
    std::fs::write(dir.join("prior.json"), r#"{"type": "zero"}"#).unwrap();
    let mut with_prior = fit_into("prior.json");
    with_prior.extend(["--prior-mean", "prior.json"]);
    let r = run_in(&dir, &with_prior);
    assert!(
        r.stderr.contains("is the --prior-mean file"),
        "{}",
        r.stderr
    );
    let r = run_in(&dir, &fit_into("m.json"));
    assert!(r.status.success(), "{}", r.stderr);
    let model = std::fs::read(dir.join("m.json")).unwrap();
    let predict = [
        "predict", "--model", "m.json", "--x", "0.1,0.2", "--out", "m.json",
    ];
    let r = run_in(&dir, &predict);
    assert!(
        r.stderr.contains("is the --model file 'm.json'"),
        "{}",
        r.stderr
    );
    assert_eq!(std::fs::read(dir.join("m.json")).unwrap(), model);
}

#[test]
fn merge_does_not_overwrite_a_shard() {
    let dir = scratch_dir("outputs-merge");
    for i in 0..2 {
        let shard = format!("{i}/2");
        let out = format!("s{i}");
        let mut args = short_run(&["--seeds", "0..4", "--shard", &shard, "--out", &out]);
        args[3] = "steps=10";
        let r = run_in(&dir, &args);
        assert!(r.status.success(), "{}", r.stderr);
    }
    let before = std::fs::read(dir.join("s0").join("shard.json")).unwrap();
    let r = run_in(&dir, &["merge", "s0", "s1", "--out", "./s0"]);
    assert!(r.stderr.contains("is the shard 's0'"), "{}", r.stderr);
    assert_eq!(
        std::fs::read(dir.join("s0").join("shard.json")).unwrap(),
        before
    );
    std::fs::write(dir.join("file"), "x").unwrap();
    let r = run_in(&dir, &["merge", "s0", "s1", "--out", "file"]);
    assert!(
        r.stderr.contains("--out: output directory 'file'"),
        "{}",
        r.stderr
    );
    let r = run_in(&dir, &["merge", "s0", "s1", "--out", "m"]);
    assert!(r.status.success(), "{}", r.stderr);
    assert!(dir.join("m").join("sweep_summary.json").is_file());
}

#[cfg(unix)]
#[test]
fn a_link_as_output_is_written_through() {
    let dir = scratch_dir("outputs-link");
    std::fs::write(dir.join("real.json"), "old").unwrap();
    std::os::unix::fs::symlink("real.json", dir.join("link.json")).unwrap();
    // d.csv does not exist yet
    let r = run_in(&dir, &fit_into("link.json"));
    // a failed command leaves both as they were
    assert!(!r.status.success());
    assert_eq!(
        std::fs::read_to_string(dir.join("real.json")).unwrap(),
        "old"
    );
    std::fs::write(dir.join("d.csv"), DATA).unwrap();
    let r = run_in(&dir, &fit_into("link.json"));
    assert!(r.status.success(), "{}", r.stderr);
    let link = std::fs::symlink_metadata(dir.join("link.json")).unwrap();
    assert!(link.file_type().is_symlink(), "the link was replaced");
    assert!(std::fs::read_to_string(dir.join("real.json"))
        .unwrap()
        .contains("\"state_dim\""));
}

#[cfg(target_os = "linux")]
#[test]
fn a_full_stream_is_not_a_panic() {
    let bin = env!("CARGO_BIN_EXE_bayes-cbf");
    // stdout on a full device: an error naming stdout
    let full = std::fs::OpenOptions::new().write(true).open("/dev/full");
    if let Ok(full) = full {
        let out = Command::new(bin)
            .arg("list")
            .stdout(Stdio::from(full))
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{stderr}");
        assert!(stderr.contains("cannot write to stdout"), "{stderr}");
        assert!(!stderr.contains("panicked"), "{stderr}");
    }
    // stderr on a full device: the exit status is the command's own
    if let Ok(full) = std::fs::OpenOptions::new().write(true).open("/dev/full") {
        let status = Command::new(bin)
            .args(["predict", "--model", "missing.json", "--x", "0.1"])
            .stdout(Stdio::null())
            .stderr(Stdio::from(full))
            .status()
            .unwrap();
        assert_eq!(status.code(), Some(1));
    }
}

/// `--out /dev/stdout` writes to the descriptor the shell set up: appended
/// to a log opened with `>>`, which is neither replaced nor overwritten.
#[cfg(target_os = "linux")]
#[test]
fn out_dev_stdout_appends_to_a_redirected_log() {
    let dir = scratch_dir("outputs-stdout");
    std::fs::write(dir.join("d.csv"), DATA).unwrap();
    std::fs::write(dir.join("log.txt"), "PREVIOUS\n").unwrap();
    let log = std::fs::OpenOptions::new()
        .append(true)
        .open(dir.join("log.txt"))
        .unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_bayes-cbf"))
        .args(fit_into("/dev/stdout"))
        .current_dir(&*dir)
        .stdout(Stdio::from(log))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = std::fs::read_to_string(dir.join("log.txt")).unwrap();
    assert!(text.starts_with("PREVIOUS\n{"), "{text}");
    assert!(text.contains("\"state_dim\": 2"), "{text}");
}

/// A run interrupted before its first output directory existed leaves its
/// stage beside it (`.NAME.tmp-PID-N`); the next run to the same `--out`,
/// given as a bare name relative to the working directory, removes it.
#[cfg(target_os = "linux")]
#[test]
fn the_stage_of_an_interrupted_run_is_removed_by_the_next() {
    let dir = scratch_dir("outputs-stale-stage");
    // a process id above the kernel's limit: no such process runs
    let stale = dir.join(".run1.tmp-4000000000-0");
    std::fs::create_dir_all(&stale).unwrap();
    std::fs::write(stale.join("trajectory.csv"), "partial").unwrap();
    let r = run_in(&dir, &short_run(&["--out", "run1"]));
    assert!(r.status.success(), "{}", r.stderr);
    assert!(dir.join("run1").join("summary.json").is_file());
    assert!(!stale.exists(), "the stale stage is still there");
}

/// A start far outside what the model can absorb: each step's observation
/// is skipped, and said so three times, not once a step; the start's h of
/// −10²⁰⁰ is printed in scientific notation, not in 200 digits.
#[test]
fn warnings_of_a_wild_start_are_few_and_short() {
    let dir = scratch_dir("outputs-wild-start");
    let r = short_run_set(&dir, "start.0=1e200", "out");
    assert!(r.status.success(), "{}", r.stderr);
    let skipped = r.stderr.matches("observation skipped").count();
    assert_eq!(skipped, 3, "{}", r.stderr);
    assert!(r
        .stderr
        .contains("later skipped observations of this run are not shown"));
    assert!(
        r.stderr
            .contains("outside the safe set (h = -1.000e200 < 0)"),
        "{}",
        r.stderr
    );
    assert!(r.stderr.lines().count() < 12, "{}", r.stderr);
    // the run's summary records the kind once
    let summary = std::fs::read_to_string(dir.join("out").join("summary.json")).unwrap();
    assert_eq!(
        summary.matches("\"observation_skipped\"").count(),
        1,
        "{summary}"
    );
}

/// Gains refused or warned of: complex roots are an error naming
/// `k_alpha`; real poles beyond `1/dt` (here a double pole at 200 /s with
/// dt = 0.01) run, with a warning that the hold lets h cross between steps,
/// which gains below `1/dt` and self-triggered holds do not get.
#[test]
fn gains_with_complex_roots_are_refused_and_fast_ones_warned_of() {
    let dir = scratch_dir("outputs-gains");
    let r = short_run_set(&dir, "barriers.0.k_alpha=[4.0, 1.0]", "a");
    assert!(!r.status.success());
    assert!(
        r.stderr
            .contains("barriers[0]: invalid k_alpha = [4.0, 1.0]")
            && r.stderr.contains("not all real"),
        "{}",
        r.stderr
    );
    assert!(!dir.join("a").exists());
    let r = short_run_set(&dir, "barriers.0.k_alpha=[40000.0, 400.0]", "b");
    assert!(r.status.success(), "{}", r.stderr);
    assert!(
        r.stderr
            .contains("a pole of 200.000 /s, beyond 1/dt = 100.000 /s"),
        "{}",
        r.stderr
    );
    let r = run_in(&dir, &short_run(&["--out", "c"]));
    succeeded_without(&r, "beyond 1/dt");
    // a trigger that only evaluates τ_k holds for dt and is warned of; a
    // self-triggered hold is sized to the gains and is not
    for (hold, warned) in [("false", true), ("true", false)] {
        let set = format!("trigger.self_triggered={hold}");
        let args = [
            "run",
            "ackermann-self-triggered",
            "--set",
            "barriers.0.alpha=300",
            "--set",
            "steps=5",
            "--set",
            &set,
            "--out",
            "d",
        ];
        let r = run_in(&dir, &args);
        assert!(r.status.success(), "{}", r.stderr);
        assert_eq!(
            r.stderr.contains("beyond 1/dt"),
            warned,
            "{hold}: {}",
            r.stderr
        );
    }
}

/// A single integrator kept inside a disc (concave `h`, relative degree
/// 1) and swirled along its wall at about 6 m/s.
const DISC: &str = r#"
name = "disc"
seed = 300000
dt = 0.01
steps = 320
start = [0.0, 0.0]
start_spread = [0.3, 0.3]
[system]
type = "expression"
state = ["x", "y"]
control = ["ux", "uy"]
params = { k = 0.8 }
f = ["0", "0"]
g = [["k", "0"], ["0", "k"]]
[gp]
prior_mean = { type = "expression", f = ["0", "0"], g = [["1", "0"], ["0", "1"]] }
lengthscales = [1.0, 1.0]
A = { type = "identity", scale = 1.0 }
B = { type = "rows", rows = [[0.1, 0.0, 0.0], [0.0, 0.05, 0.0], [0.0, 0.0, 0.05]] }
noise_sigma = 0.05
[learning]
update_every = 1
window = 300
[[barriers]]
type = "expression"
params = { R = 1.0 }
h = "R^2 - x^2 - y^2"
relative_degree = 1
alpha = 2.0
[controller]
probability = 0.99
u_min = [-10.0, -10.0]
u_max = [10.0, 10.0]
fallback = "relax"
[reference]
type = "feedback"
u0 = [0.0, 0.0]
gain = [[-0.5, -8.0], [8.0, -0.5]]
target = [0.0, 0.0]
[outputs]
animation = false
"#;

/// A barrier with a kink (`min`) is warned of, and so is a model noise
/// below the labels' (gone at the labels' level); a relative-degree-1
/// barrier that crosses in steps that met their condition is warned of
/// with its curvature over the hold and the margin `zeta` that covers it
/// (with which the run is safe); holds clamped up to `tau_min` are
/// counted, with what would lengthen them, and the margin raised for them
/// keeps the disc self-triggered at 10 ms safe.
#[test]
fn kinks_curvature_and_clamped_holds_are_warned_of() {
    let dir = scratch_dir("outputs-kinks");
    let r = short_run_set(&dir, "barriers.0.h=min(p_max - p, 2 - p)", "a");
    assert!(r.status.success(), "{}", r.stderr);
    assert!(
        r.stderr.contains("uses min: h has no derivative"),
        "{}",
        r.stderr
    );
    let r = run_in(&dir, &short_run(&["--out", "b"]));
    assert!(!r.stderr.contains("no derivative"), "{}", r.stderr);
    // the built-in's model noise (0.1) is its labels' (0.01/√0.01); half of
    // it is below
    assert!(!r.stderr.contains("is below the noise"), "{}", r.stderr);
    let r = short_run_set(&dir, "gp.noise_sigma=0.05", "b2");
    let below = "σ·√A_ii = 0.050, is below the noise sim.process_noise puts on the learning \
                 labels, σ_w/√τ = 0.100 with τ = dt = 0.010 s";
    assert!(r.stderr.contains(below), "{}", r.stderr);
    std::fs::write(dir.join("disc.toml"), DISC).unwrap();
    let r = run_in(&dir, &["run", "disc.toml", "--out", "d"]);
    assert!(r.status.success(), "{}", r.stderr);
    assert!(
        r.stderr.contains("h also moves by ½·τ²·ẋᵀ∇²h·ẋ = -0.004")
            && r.stderr.contains("controller.zeta ≥ ½·τ·|ẋᵀ∇²h·ẋ| = 0.4"),
        "{}",
        r.stderr
    );
    let d = summary_in(&dir, "d");
    assert!(d.contains("\"safe\": false"), "{d}");
    let run_set = |scenario, sets: &[&str], out| run_with(&dir, scenario, sets, out);
    let r = run_set("disc.toml", &["controller.zeta=0.5"], "e");
    assert!(!r.stderr.contains("crossed zero"), "{}", r.stderr);
    let e = summary_in(&dir, "e");
    assert!(e.contains("\"safe\": true"), "{e}");
    // the vehicle's holds at the paper's margin are clamped, and the
    // warning names the setting that raises it; raised (the default), its
    // seed 0 has none left among the steps that met their conditions
    let r = run_set(
        "ackermann-self-triggered",
        &[
            "outputs.animation=false",
            "trigger.margin_for_tau_min=false",
        ],
        "c",
    );
    succeeded_with(
        &r,
        &[
            "holds of steps that met their conditions were clamped up to tau_min = 0.001 s",
            "the margins were too small (set trigger.margin_for_tau_min = true",
        ],
    );
    let r = run_set(
        "ackermann-self-triggered",
        &["outputs.animation=false"],
        "c2",
    );
    succeeded_without(&r, "were clamped");
    // the disc self-triggered with 10 ms holds: crossed at the margin ζ,
    // safe with it raised, whose holds still clamped are those where the
    // state could leave the cuboid
    let trigger = [
        "controller.zeta=0.01",
        "trigger.cuboid=[0.2, 0.2]",
        "trigger.tau_min=0.01",
    ];
    let r = run_set(
        "disc.toml",
        &[&trigger[..], &["trigger.margin_for_tau_min=false"]].concat(),
        "f",
    );
    assert!(r.status.success(), "{}", r.stderr);
    summary_has(&dir, "f", "\"safe\": false");
    let r = run_set("disc.toml", &trigger, "g");
    succeeded_with(&r, &["the state could leave trigger.cuboid before tau_min"]);
    succeeded_without(&r, "margins were too small");
    summary_has(&dir, "g", "\"safe\": true");
    assert!(!summary_in(&dir, "g").contains("\"raised_margins\": 0,"));
}

/// Asserts that the run succeeded and that its stderr does not mention
/// `absent`.
fn succeeded_without(r: &Run, absent: &str) {
    assert!(r.status.success(), "{}", r.stderr);
    assert!(!r.stderr.contains(absent), "{absent}: {}", r.stderr);
}

/// `r` succeeded, and its stderr says each of `present`.
fn succeeded_with(r: &Run, present: &[&str]) {
    assert!(r.status.success(), "{}", r.stderr);
    for text in present {
        assert!(r.stderr.contains(text), "{text}: {}", r.stderr);
    }
}

/// The `summary.json` a run wrote to `dir/out`.
fn summary_in(dir: &std::path::Path, out: &str) -> String {
    std::fs::read_to_string(dir.join(out).join("summary.json")).unwrap()
}

/// The `summary.json` a run wrote to `dir/out` holds `text`.
fn summary_has(dir: &std::path::Path, out: &str, text: &str) {
    let summary = summary_in(dir, out);
    assert!(summary.contains(text), "{text}: {summary}");
}

/// `bayes-cbf run SCENARIO --out OUT --set S ...` in `dir`.
fn run_with(dir: &std::path::Path, scenario: &str, sets: &[&str], out: &str) -> Run {
    let mut args = vec!["run", scenario, "--out", out];
    for set in sets {
        args.extend(["--set", *set]);
    }
    run_in(dir, &args)
}

/// What a file left at its defaults is warned of: a zero prior mean under
/// a barrier of relative degree 2, a row declared known that the prior
/// gets wrong, a run whose steps were mostly infeasible; and none of it
/// once the prior has the kinematic row and the input's gain.
#[test]
fn a_bare_scenario_is_told_what_its_model_lacks() {
    let dir = scratch_dir("outputs-bare");
    std::fs::write(dir.join("cart.toml"), BARE_CART).unwrap();
    let run_set =
        |sets: &[&str], out| run_with(&dir, "cart.toml", &[&["steps=150"], sets].concat(), out);
    let r = run_set(&[], "a");
    succeeded_with(
        &r,
        &["gp.prior_mean is zero and barriers[0] has relative degree 2"],
    );
    summary_has(&dir, "a", "\"fallback\": \"relax\"");
    // without learning it never learns how the input acts: every step
    // falls back
    let r = run_set(&["learning.update_every=0"], "n");
    let want = "150 of 150 steps were infeasible, 100% of the run's time, so the fallback \
                (relax) acted on most";
    assert!(r.stderr.contains(want), "{}", r.stderr);
    // its noise is not what blocks it: with no data, the conditions fail
    // without the noise as well
    assert!(!r.stderr.contains("noise_sigma too large"), "{}", r.stderr);
    // p' = v declared known under a zero prior: 0 where the system has v
    let r = run_set(&["gp.known_rows=[0]"], "b");
    let want = "gp.known_rows: row 0 of F is taken from gp.prior_mean, which gives \
                [0.000, 0.000] at x = [-0.500, 1.000] where the system has [1.000, 0.000]";
    assert!(r.stderr.contains(want), "{}", r.stderr);
    // without input bounds the default fallback is max-margin, and relax
    // is warned of (p* can take an unbounded control)
    let unbounded = BARE_CART.replace("[controller]\nu_min = [-5.0]\nu_max = [5.0]\n", "");
    assert_ne!(unbounded, BARE_CART);
    std::fs::write(dir.join("free.toml"), unbounded).unwrap();
    let free =
        |sets: &[&str], out| run_with(&dir, "free.toml", &[&["steps=20"], sets].concat(), out);
    let r = free(&[], "f");
    assert!(r.status.success(), "{}", r.stderr);
    let summary = summary_in(&dir, "f");
    assert!(
        summary.contains("\"fallback\": \"max_margin\""),
        "{summary}"
    );
    assert!(
        !r.stderr.contains("relax without input bounds"),
        "{}",
        r.stderr
    );
    let r = free(&["controller.fallback=\"relax\""], "g");
    assert!(
        r.stderr
            .contains("fallback relax without input bounds (u_min, u_max)"),
        "{}",
        r.stderr
    );
    let prior = r#"gp.prior_mean={"type":"expression","f":["v","0"],"g":[["0"],["1"]]}"#;
    let r = run_set(
        &[prior, "gp.known_rows=[0]", "gp.B=[[1.0,0.0],[0.0,0.01]]"],
        "c",
    );
    assert!(r.status.success(), "{}", r.stderr);
    for unwanted in ["prior_mean is zero", "gp.known_rows: row", "acted on most"] {
        assert!(!r.stderr.contains(unwanted), "{unwanted}: {}", r.stderr);
    }
}

/// An arm joint against two limits whose kinematic row is known and right
/// (`q' = w`), with gravity and friction its prior gets wrong.
const ARM: &str = include_str!("data/arm-joint.toml");

/// A known row that the labels contradict only because gains beyond 1/dt
/// move the state faster than the labels' step (without process noise):
/// the warning names the labels, not only the prior. At the file's gains
/// it says nothing, nor with the fast gains under the file's process
/// noise, whose σ_w/√dt = 0.1 on the labels is the misfit (rms 0.097).
#[test]
fn a_known_row_misfit_under_fast_gains_names_the_labels() {
    let dir = scratch_dir("outputs-known-row-labels");
    std::fs::write(dir.join("arm.toml"), ARM).unwrap();
    let fast = "barriers.0.k_alpha=[15000.0,250.0]";
    for sets in [&[][..], &["--set", fast]] {
        let mut args = vec!["run", "arm.toml", "--out", "quiet"];
        args.extend(sets);
        let r = run_in(&dir, &args);
        assert!(r.status.success(), "{}", r.stderr);
        assert!(
            !r.stderr.contains("gp.known_rows"),
            "{sets:?}: {}",
            r.stderr
        );
    }
    let quiet = "sim.process_noise=0.0";
    let args = [
        "run", "arm.toml", "--out", "fast", "--set", fast, "--set", quiet,
    ];
    let r = run_in(&dir, &args);
    assert!(r.status.success(), "{}", r.stderr);
    assert!(
        r.stderr.contains("row 0 of F is declared known")
            && r.stderr.contains("unless the labels are what is off")
            && r.stderr.contains("a pole of 150.000 /s"),
        "{}",
        r.stderr
    );
}

/// Two barriers that cross in steps that met their conditions (fast gains
/// against the process noise on the known row): the warning names each
/// barrier's first crossing, the velocity limit's (t = 1.24) as well as
/// the position limit's (t = 3.76).
#[test]
fn every_barrier_that_crossed_in_a_met_step_is_named() {
    let dir = scratch_dir("outputs-two-crossings");
    std::fs::write(dir.join("msd.toml"), include_str!("data/msd.toml")).unwrap();
    let args = "run msd.toml --seed 960007 --set barriers.1.alpha=50.0 \
                --set barriers.0.k_alpha=[100.0,20.0] --out r";
    let r = run_in(&dir, &args.split_whitespace().collect::<Vec<_>>());
    succeeded_with(
        &r,
        &[
            "barriers[1] (seed 960007): h crossed zero at t = 1.240",
            "barriers[0] (seed 960007): h crossed zero at t = 3.760",
        ],
    );
}

/// A sweep shows each kind of warning once, for the first seed to issue
/// it, then counts the seeds that issued each kind; `sweep.csv`, the
/// sweep summary and each run's `summary.json` record them, and shards
/// merge to the same record. The bare cart without learning warns of its
/// zero prior, of an input it cannot see and of falling back on every step,
/// at every seed; with learning and a prior it warns of nothing.
#[test]
fn a_sweep_counts_the_seeds_that_issued_each_warning() {
    let dir = scratch_dir("outputs-warned-seeds");
    std::fs::write(dir.join("cart.toml"), BARE_CART).unwrap();
    let sweep = |extra: &[&str], out: &str| {
        let mut args = vec!["run", "cart.toml", "--seeds", "0..3", "--set", "steps=60"];
        for set in extra {
            args.extend(["--set", *set]);
        }
        args.extend(["--out", out]);
        run_in(&dir, &args)
    };
    let r = sweep(&["learning.update_every=0"], "s");
    succeeded_with(
        &r,
        &[
            "warnings by seed: mostly_infeasible on 3 of 3 (0, 1, 2); no_input_effect on 3 of \
           3 (0, 1, 2); unmodelled_lgh on 3 of 3 (0, 1, 2); zero_prior on 3 of 3 (0, 1, 2); \
           each kind was shown once, above, for the first seed to issue it",
        ],
    );
    for shown in ["steps were infeasible", "gp.prior_mean is zero", "≈ 0 at x"] {
        assert_eq!(r.stderr.matches(shown).count(), 1, "{shown}: {}", r.stderr);
    }
    let csv = std::fs::read_to_string(dir.join("s/sweep.csv")).unwrap();
    assert!(csv.starts_with("seed,safe,collided,min_barrier,infeasible_steps,goal_distance,control_step_us,wall_time_s,warnings,error\n"), "{csv}");
    let kinds = [
        "mostly_infeasible",
        "no_input_effect",
        "unmodelled_lgh",
        "zero_prior",
    ];
    for line in csv.lines().skip(1) {
        let mut row: Vec<&str> = line.split(',').nth(8).unwrap().split(';').collect();
        row.sort_unstable();
        assert_eq!(row, kinds, "{csv}");
    }
    let summary = std::fs::read_to_string(dir.join("s/sweep_summary.json")).unwrap();
    let json: serde_json::Value = serde_json::from_str(&summary).unwrap();
    assert_eq!(
        json["warnings"],
        serde_json::json!(kinds
            .map(|k| (k, [0, 1, 2]))
            .into_iter()
            .collect::<std::collections::BTreeMap<_, _>>()),
        "{summary}"
    );
    // the shards' records merge to the unsharded one
    for i in 0..2 {
        let shard = format!("{i}/2");
        let mut args = vec!["run", "cart.toml", "--seeds", "0..3", "--shard", &shard];
        args.extend(["--set", "steps=60", "--set", "learning.update_every=0"]);
        let out = format!("p{i}");
        args.extend(["--out", &out]);
        let r = run_in(&dir, &args);
        assert!(r.status.success(), "{}", r.stderr);
    }
    let r = run_in(&dir, &["merge", "p0", "p1", "--out", "m"]);
    assert!(r.status.success(), "{}", r.stderr);
    let merged = std::fs::read_to_string(dir.join("m/sweep_summary.json")).unwrap();
    let merged: serde_json::Value = serde_json::from_str(&merged).unwrap();
    assert_eq!(merged["warnings"], json["warnings"]);
    // one run records its warning, with the text it showed
    let r = run_with(
        &dir,
        "cart.toml",
        &["steps=60", "learning.update_every=0"],
        "one",
    );
    assert!(r.status.success(), "{}", r.stderr);
    let one: serde_json::Value = serde_json::from_str(&summary_in(&dir, "one")).unwrap();
    let last = &one["warnings"][3];
    assert_eq!(last["kind"], "mostly_infeasible", "{one}");
    let message = last["message"].as_str().unwrap();
    assert!(
        message.starts_with("seed 0: 60 of 60 steps were infeasible") && r.stderr.contains(message),
        "{message}: {}",
        r.stderr
    );
    // learning, with the prior's kinematic row and gain: nothing to count
    let prior = r#"gp.prior_mean={"type":"expression","f":["v","0"],"g":[["0"],["1"]]}"#;
    let r = sweep(&[prior, "gp.known_rows=[0]"], "q");
    succeeded_without(&r, "warnings by seed");
    let summary = std::fs::read_to_string(dir.join("q/sweep_summary.json")).unwrap();
    assert!(summary.contains("\"warnings\": {}"), "{summary}");
}

/// The pendulum of docs/interfaces.md hangs still at its defaults, and
/// every step is infeasible: after the first, the spread that blocks the
/// steps is the model's noise (`noise_sigma = 0.1`), which the predictive
/// conditions carry while the simulated pendulum puts no noise on the
/// labels. The warning says so; at `noise_sigma = 0.01` only the first,
/// data-less step is infeasible. A model that learns nothing (the bare
/// cart without updates) is not told of its noise: the test above.
#[test]
fn infeasible_steps_blocked_by_the_model_noise_name_it() {
    let dir = scratch_dir("outputs-noise-blocks");
    let toml = include_str!("data/pendulum-expression.toml");
    std::fs::write(dir.join("pendulum.toml"), toml).unwrap();
    let r = run_with(&dir, "pendulum.toml", &["steps=200"], "a");
    succeeded_with(
        &r,
        &[
            "200 of 200 steps were infeasible",
            "or gp.noise_sigma too large for controller.predictive, whose conditions carry \
             the model's noise: σ·√A_ii = 0.100 on row 1, where the labels carry no process \
             noise; with the run's final model, 20 of 20 infeasible steps are feasible \
             without it",
        ],
    );
    let r = run_with(
        &dir,
        "pendulum.toml",
        &["steps=200", "gp.noise_sigma=0.01"],
        "b",
    );
    succeeded_without(&r, "steps were infeasible");
    summary_has(&dir, "b", "\"infeasible_steps\": 1,");
}

/// The self-triggered double integrator under max-margin drives into its
/// wall through a stretch of infeasible steps whose `p*` is about 0.95:
/// the warning says that max-margin applied the control of least spread
/// where relax would have met the conditions at `p*`; under the
/// built-in's own `relax` the same seed stays clear.
#[test]
fn a_crossing_under_max_margin_names_relax() {
    let dir = scratch_dir("outputs-max-margin-crossing");
    let args = "run double-integrator --seed 52009 --set trigger.self_triggered=true \
                --set trigger.cuboid=[0.2,0.2] --set trigger.delta_l=1e-4 --set trigger.grid=10 \
                --set trigger.samples=10 --set trigger.tau_min=0.01 --set trigger.tau_max=0.1 \
                --set trigger.tau_from=analytic --set controller.zeta=0.01";
    let args: Vec<&str> = args.split_whitespace().collect();
    let mm = [
        &args[..],
        &["--set", "controller.fallback=max_margin", "--out", "mm"],
    ]
    .concat();
    succeeded_with(
        &run_in(&dir, &mm),
        &[
            "(p* = 0.953; fallback max_margin), 264 of 499 steps were infeasible",
            "max_margin, at the c(p) of controller.probability, applies the control of least \
             spread, which can brake too little: relax would have met the conditions at p*",
        ],
    );
    let r = run_in(&dir, &[&args[..], &["--out", "relax"]].concat());
    succeeded_without(&r, "crossed zero");
    summary_has(&dir, "relax", "\"safe\": true");
}

/// The double integrator under an eighth of its input bound with a window
/// of 300 observations in place of its budget crosses its wall once the
/// window drops the few observations at other controls (docs/robots.md);
/// the warning says so and names the budget. With the file's budget the
/// same seed stays clear.
#[test]
fn a_crossing_after_the_window_forgot_names_the_budget() {
    let dir = scratch_dir("outputs-window-forgot");
    let run = "run double-integrator --seed 67118 --set controller.u_min=[-0.5] \
               --set controller.u_max=[0.5]";
    let window = format!("{run} --set learning.budget=0 --set learning.window=300 --out w");
    succeeded_with(
        &run_in(&dir, &words(&window)),
        &[
            "the data window was full (learning.window = 300) and the model's spread rose",
            "learning.budget = 300 keeps the most informative instead",
        ],
    );
    let r = run_in(&dir, &words(&format!("{run} --out b")));
    succeeded_without(&r, "crossed zero");
    summary_has(&dir, "b", "\"safe\": true");
}

/// Objective weights 10³ apart run, with a warning of how roughly the
/// solver resolves the lightly weighted control; 10⁷ apart are refused.
#[test]
fn weights_far_apart_are_warned_of_or_refused() {
    let dir = scratch_dir("outputs-weights-apart");
    let r = run_with(
        &dir,
        "unicycle-obstacles",
        &["steps=5", "controller.r=[1.0,1000.0]"],
        "a",
    );
    succeeded_with(&r, &["warning: R: its weights are 1.0e3 apart"]);
    let r = run_with(
        &dir,
        "unicycle-obstacles",
        &["steps=5", "controller.r=[1.0,1e7]"],
        "b",
    );
    assert!(!r.status.success());
    let want = "error: controller: invalid R = weights 1.0e7 apart";
    assert!(r.stderr.contains(want), "{}", r.stderr);
    let r = run_with(&dir, "unicycle-obstacles", &["steps=5"], "c");
    assert!(!r.stderr.contains("apart"), "{}", r.stderr);
}

/// Starts `args` in `dir`, waits until a run's staging directory appears,
/// sends SIGINT and returns the exit code and stderr.
#[cfg(unix)]
fn interrupted(dir: &std::path::Path, args: &[&str]) -> (Option<i32>, String) {
    let child = Command::new(env!("CARGO_BIN_EXE_bayes-cbf"))
        .args(args)
        .current_dir(dir)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let staged = || {
        std::fs::read_dir(dir)
            .unwrap()
            .any(|e| e.unwrap().file_name().to_string_lossy().contains(".tmp-"))
    };
    let start = std::time::Instant::now();
    while !staged() && start.elapsed().as_secs() < 60 {
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    assert!(staged(), "no staging directory appeared");
    std::thread::sleep(std::time::Duration::from_millis(300));
    let pid = child.id().to_string();
    let kill = Command::new("kill").args(["-INT", &pid]).status().unwrap();
    assert!(kill.success());
    let out = child.wait_with_output().unwrap();
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// Ctrl-C stops a run and a sweep before their next step: exit status 130,
/// a message, and neither their output nor a staging directory is left.
#[cfg(unix)]
#[test]
fn ctrl_c_leaves_nothing_behind() {
    for (name, args) in [
        (
            "run",
            vec![
                "run",
                "ackermann-learning",
                "--set",
                "steps=20000",
                "--out",
                "d",
            ],
        ),
        (
            "sweep",
            vec![
                "run",
                "ackermann-learning",
                "--seeds",
                "0..1000",
                "--out",
                "d",
            ],
        ),
    ] {
        let dir = scratch_dir(&format!("outputs-ctrl-c-{name}"));
        let (code, stderr) = interrupted(&dir, &args);
        assert_eq!(code, Some(130), "{name}: {stderr}");
        assert!(
            stderr.contains("interrupted: nothing was written"),
            "{name}: {stderr}"
        );
        let left: Vec<_> = std::fs::read_dir(&*dir)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert!(left.is_empty(), "{name}: left {left:?}");
    }
}
