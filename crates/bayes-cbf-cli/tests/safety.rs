#![allow(clippy::approx_constant)] // the literal values of interfaces.md
//! `bayes-cbf moments` and `bayes-cbf control` through the real binary:
//! the JSON of interfaces.md, agreement with the library, and bad input.

mod common;

use bayes_cbf::barrier::{cbc_moments, ConditionMoments, MomentWorkspace, PendulumSector};
use bayes_cbf::gp::{InputMap, Mvgp, MvgpHyper, PriorMean, Rbf};
use common::{assert_fails, run_in, scratch_dir, words, Scratch};
use nalgebra::DMatrix;
use serde_json::Value;
use std::path::Path;

const MODEL: &str = r#"{
  "state_dim": 2, "control_dim": 1,
  "kernel": {"type": "rbf", "lengthscales": [0.7, 1.3], "variance": 1.5},
  "A": [[1.0, 0.1], [0.1, 0.8]], "B": [[1.0, 0.2], [0.2, 0.5]],
  "noise_sigma": 0.1, "prior_mean": "zero",
  "data": {"x": [[0.1, 0.2], [1.0, -0.5], [0.9, 0.3]], "u": [[0.5], [-1.0], [2.0]], "xdot": [[0.2, -0.4], [-0.5, -9.0], [0.3, -5.0]]}
}"#;

const SECTOR: &str = r#"{"type": "pendulum_sector", "theta_c": 0.7854, "delta": 0.3927, "relative_degree": 2, "k_alpha": [1.0, 3.0]}"#;
const SECTOR_RD1: &str = r#"{"type": "pendulum_sector", "theta_c": 0.7854, "delta": 0.3927, "relative_degree": 1, "alpha": 2.0}"#;

/// A scratch directory holding `model.json` (`MODEL`) and `files`.
fn setup(name: &str, files: &[(&str, &str)]) -> Scratch {
    let dir = scratch_dir(name);
    for (file, text) in [("model.json", MODEL)].iter().chain(files) {
        std::fs::write(dir.join(file), text).unwrap();
    }
    dir
}

/// Runs `bayes-cbf ARGS` in `dir` and returns the JSON it prints.
fn json_out(dir: &Path, args: &str) -> Value {
    let r = run_in(dir, &words(args));
    assert!(r.status.success(), "{args}: {}", r.stderr);
    serde_json::from_str(&r.stdout).unwrap()
}

fn library_model() -> Mvgp {
    let hyper = MvgpHyper {
        kernel: Rbf::new(vec![0.7, 1.3], 1.5).unwrap(),
        A: DMatrix::from_row_slice(2, 2, &[1.0, 0.1, 0.1, 0.8]),
        B: DMatrix::from_row_slice(2, 2, &[1.0, 0.2, 0.2, 0.5]),
        sigma: 0.1,
    };
    let mut m = Mvgp::new(2, 1, hyper, PriorMean::Zero, InputMap::Identity).unwrap();
    m.set_data(
        &[0.1, 0.2, 1.0, -0.5, 0.9, 0.3],
        &[0.5, -1.0, 2.0],
        &[0.2, -0.4, -0.5, -9.0, 0.3, -5.0],
    )
    .unwrap();
    m
}

#[test]
fn moments_match_the_library() {
    let dir = setup("moments", &[("barrier.json", SECTOR)]);
    let v = json_out(
        &dir,
        "moments --model model.json --barrier barrier.json --x 1.2,-0.4 --u=-0.7",
    );
    assert_eq!(v["relative_degree"], 2);
    let model = library_model();
    let b = PendulumSector::new(0.7854, 0.3927, 2, vec![1.0, 3.0]).unwrap();
    let mut ws = MomentWorkspace::new(&model);
    ws.update(&model, &[1.2, -0.4], 2).unwrap();
    let mut mom = ConditionMoments::zeros(1);
    cbc_moments(&mut ws, &b, &mut mom).unwrap();
    assert!((v["mean"].as_f64().unwrap() - mom.mean(&[-0.7])).abs() < 1e-12);
    assert!((v["variance"].as_f64().unwrap() - mom.variance(&[-0.7])).abs() < 1e-12);
    assert!(v["variance"].as_f64().unwrap() > 0.0);
}

#[test]
fn control_returns_a_safe_optimal_input() {
    // b2: ω ≥ −10
    let b2 = r#"{"type": "half_space", "normal": [0.0, 1.0], "offset": -10.0, "relative_degree": 1, "alpha": 1.0}"#;
    let dir = setup("control", &[("b1.json", SECTOR_RD1), ("b2.json", b2)]);
    let args = "control --model model.json --barrier b1.json --barrier b2.json --x 2.5,0.0 \
                --probability 0.9 --u-ref=-3 --zeta 0.01";
    let v = json_out(&dir, args);
    assert_eq!(v["status"], "optimal");
    assert_eq!(v["u"].as_array().unwrap().len(), 1);
    let cons = v["constraints"].as_array().unwrap();
    assert_eq!(cons.len(), 2);
    let c_gauss = 1.2815515655446004; // √2 erf⁻¹(0.8)
    assert!((cons[0]["c"].as_f64().unwrap() - c_gauss).abs() < 1e-9);
    assert!((cons[1]["c"].as_f64().unwrap() - c_gauss).abs() < 1e-9);
    // the reference −3 is unsafe for the sector barrier: u moved up from it
    assert!(v["u"][0].as_f64().unwrap() > -3.0);
    for c in cons {
        let (mean, std, cc) = (
            c["mean"].as_f64().unwrap(),
            c["std"].as_f64().unwrap(),
            c["c"].as_f64().unwrap(),
        );
        assert!(mean - 0.01 - cc * std >= -1e-6, "{c}");
        assert!((c["slack"].as_f64().unwrap() - (mean - 0.01 - cc * std)).abs() < 1e-9);
    }
}

#[test]
fn predictive_control_widens_each_condition_by_the_observation_noise() {
    let dir = setup("control-predictive", &[("b1.json", SECTOR_RD1)]);
    let args = "control --model model.json --barrier b1.json --x 2.5,0.0 \
                --probability 0.9 --u-ref=-3";
    // the paper's latent condition by default (interfaces.md), --latent
    // naming it; --predictive for the condition as realised
    let latent = json_out(&dir, args);
    assert_eq!(latent, json_out(&dir, &format!("{args} --latent")));
    let pred = json_out(&dir, &format!("{args} --predictive"));
    let std = |v: &serde_json::Value| v["constraints"][0]["std"].as_f64().unwrap();
    // the default's std is the square root of the variance `moments` prints
    // at its control
    let u = latent["u"][0].as_f64().unwrap();
    let m = json_out(
        &dir,
        &format!("moments --model model.json --barrier b1.json --x 2.5,0.0 --u={u}"),
    );
    let var = m["variance"].as_f64().unwrap();
    assert!(
        (std(&latent) - var.sqrt()).abs() <= 1e-9 * var.sqrt(),
        "{latent} {m}"
    );
    // more variance at least at its own control, and the control moved
    // further from the unsafe reference
    assert!(std(&pred) > std(&latent), "{pred} {latent}");
    assert!(pred["u"][0].as_f64().unwrap() > latent["u"][0].as_f64().unwrap());
    let c = &pred["constraints"][0];
    let (mean, cc) = (c["mean"].as_f64().unwrap(), c["c"].as_f64().unwrap());
    assert!(mean - cc * std(&pred) >= -1e-6, "{c}");
}

#[test]
fn control_reports_infeasibility_and_fallback() {
    let dir = setup("control_infeasible", &[("b.json", SECTOR)]);
    // deep inside the unsafe sector with tight bounds: no input satisfies the condition
    let args = "control --model model.json --barrier b.json --x 0.7854,-3.0 --probability 0.999 \
                --u-min=-0.1 --u-max 0.1 --fallback brake";
    let v = json_out(&dir, args);
    assert_eq!(v["status"], "infeasible");
    assert_eq!(v["fallback"], "brake");
    assert_eq!(v["u"][0].as_f64().unwrap(), 0.0);
    assert_eq!(v["violated"][0], 0);
    // Cantelli factor for relative degree 2: √(p/(1−p))
    let c = v["constraints"][0]["c"].as_f64().unwrap();
    assert!((c - (0.999f64 / 0.001).sqrt()).abs() < 1e-6, "{c}");
}

/// A scratch directory holding `model.json`, the model at kernel variance
/// `variance` as `huge.json` and the relative-degree-1 sector as `b.json`.
fn huge_variance(name: &str, variance: &str) -> Scratch {
    let huge = MODEL.replace("\"variance\": 1.5", &format!("\"variance\": {variance}"));
    setup(name, &[("huge.json", &huge), ("b.json", SECTOR_RD1)])
}

/// A kernel variance of 10¹⁶ puts the condition's covariance at ~10¹⁵, whose
/// rounding hides the standard deviation at the control: the solver's
/// control misses the condition by 1.7, and the command fails with a
/// numerical error instead of reporting it as optimal.
#[test]
fn an_unresolvable_covariance_is_an_error_not_an_optimum() {
    let dir = huge_variance("control_unresolved", "1e16");
    let args = "control --model huge.json --barrier b.json --x 0.1,0.2 --probability 0.9 \
                --u-min=-5 --u-max 5";
    assert_fails(
        &run_in(&dir, &words(args)),
        &["barrier 0", "beyond what double precision resolves"],
        args,
    );
}

/// At a kernel variance of 10¹⁴ the condition's variance at u = 0.5 (0.004
/// at unit variance) is below the rounding of its terms: `moments` says so
/// and names the barrier, where it printed 0. At the file's variance the
/// same query gives the number.
#[test]
fn an_unresolved_variance_is_an_error_not_zero() {
    let dir = huge_variance("moments_unresolved", "1e14");
    let args = "moments --model huge.json --barrier b.json --x 0.1,0.2 --u 0.5";
    assert_fails(
        &run_in(&dir, &words(args)),
        &["barrier 'b.json'", "variance at u", "not resolved"],
        args,
    );
    let fine = run_in(
        &dir,
        &words("moments --model model.json --barrier b.json --x 0.1,0.2 --u 0.5"),
    );
    assert!(fine.status.success(), "{}", fine.stderr);
}

#[test]
fn bad_safety_input_names_the_field() {
    let dir = setup(
        "safety_errors",
        &[
            ("b.json", SECTOR),
            (
                "bad_k.json",
                r#"{"type": "pendulum_sector", "theta_c": 0.7854, "delta": 0.3927, "relative_degree": 2, "k_alpha": [1.0]}"#,
            ),
            (
                "ackermann.json",
                r#"{"type": "circle_heading", "center": [0, 0], "radius": 1, "q1": 0.7, "q2": 0.3, "relative_degree": 1, "alpha": 5}"#,
            ),
            (
                "unknown.json",
                r#"{"type": "pendulum_sector", "theta_c": 0.7854, "delta": 0.3927, "relative_degree": 1, "alpha": 1, "gamma": 2}"#,
            ),
            ("empty.json", ""),
            (
                "sqrt.json",
                r#"{"type": "expression", "state": ["t", "w"], "h": "sqrt(t - 0.3)", "relative_degree": 1, "alpha": 1}"#,
            ),
        ],
    );
    let fails = |args: &str, field: &str| {
        assert_fails(&run_in(&dir, &words(args)), &[field], args);
    };
    for (barrier_and_options, field) in [
        ("b.json --probability 1.5", "probability"),
        ("b.json --probability 0.9 --zeta=-1", "zeta"),
        // a negative value after a space is the value, not a flag
        ("b.json --probability 0.9 --zeta -1", "invalid --zeta = -1"),
        ("b.json --probability -0.5", "probability"),
        ("b.json --probability 0.9 --zeta -1e-3", "invalid --zeta"),
        ("b.json --probability 0.9 --zeta -inf", "zeta"),
        ("b.json --probability 0.9 --u-min 1 --u-max 0", "u-min"),
        ("b.json --probability 0.9 --u-min 1", "u_min"),
        ("b.json --probability 0.9 --u-ref 1,2", "--u-ref"),
        ("b.json --probability 0.9 --fallback panic", "fallback"),
        ("bad_k.json --probability 0.9", "k_alpha"),
        ("ackermann.json --probability 0.9", "state dimension"),
        ("unknown.json --probability 0.9", "gamma"),
        ("empty.json --probability 0.9", "empty"),
        ("missing.json --probability 0.9", "missing.json"),
    ] {
        let control = "control --model model.json --x 1.4,0.0 --barrier";
        fails(&format!("{control} {barrier_and_options}"), field);
    }
    let moments = "moments --model model.json --barrier b.json";
    fails(&format!("{moments} --x 1,nan --u 0"), "--x");
    // ∇h infinite where h is not: the state is named
    fails(
        "moments --model model.json --barrier sqrt.json --x 0.3,0 --u 0",
        "∇h of barrier 'sqrt(t - 0.3)' is NaN at x = [0.3, 0.0]",
    );
    fails(&format!("{moments} --x 1,0 --u 0,1"), "--u");
}

#[test]
fn moments_beyond_relative_degree_two_use_monte_carlo() {
    let b3 = r#"{"type": "half_space", "normal": [1.0, 0.0], "offset": -2.0, "relative_degree": 3, "k_alpha": [1.0, 3.0, 3.0]}"#;
    let dir = setup("moments_mc", &[("b3.json", b3)]);
    let args = "moments --model model.json --barrier b3.json --x 0.5,0.1 --u 0.3 --samples";
    let v = json_out(&dir, &format!("{args} 3000 --seed 4"));
    assert_eq!(v["method"], "monte_carlo");
    assert_eq!(v["samples"], 3000);
    assert!(v["mean_se"].as_f64().unwrap() > 0.0 && v["variance_se"].as_f64().unwrap() > 0.0);
    // deterministic given the seed
    assert_eq!(json_out(&dir, &format!("{args} 3000 --seed 4")), v);
    let exact = run_in(&dir, &words(&format!("{args} 1")));
    assert!(
        !exact.status.success() && exact.stderr.contains("--samples"),
        "{}",
        exact.stderr
    );
    // `control` takes the same options, and names them in its errors
    let control = "control --model model.json --barrier b3.json --x 0.5,0.1 --probability 0.9";
    let v = json_out(
        &dir,
        &format!("{control} --samples 3000 --seed 4 --step 0.02"),
    );
    assert_eq!(v["constraints"][0]["relative_degree"], 3);
    assert_eq!(
        json_out(
            &dir,
            &format!("{control} --samples 3000 --seed 4 --step 0.02")
        ),
        v
    );
    let bad = run_in(&dir, &words(&format!("{control} --samples 1")));
    assert!(
        !bad.status.success() && bad.stderr.contains("invalid --samples = 1"),
        "{}",
        bad.stderr
    );
}
