//! End-to-end tests of the `bayes-cbf` binary in scratch directories:
//! fit → predict on pendulum data, time series with angle wrap, the demos,
//! the bench and help output. Bad input of every kind is tested in
//! `cli_errors.rs`.

use bayes_cbf::sim::{sample_uniform, simulate_trajectory, SimSettings};
use bayes_cbf::systems::{DynSystem, Pendulum};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::Value;
use std::path::Path;

mod common;

use common::{read_json, run, run_in, scratch_dir, words};

/// Writes `k` noise-free pendulum samples `x1,x2,u1,xdot1,xdot2`, states
/// uniform on `[-π, π) × [-4, 4]`, torques uniform on `[-5, 5]`.
fn write_pendulum_csv(path: &Path, k: usize, seed: u64) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let pi = std::f64::consts::PI;
    let (lo, hi) = ([-pi, -4.0], [pi, 4.0]);
    let ds = sample_uniform(
        &Pendulum::default(),
        &lo,
        &hi,
        &[-5.0],
        &[5.0],
        k,
        0.0,
        &mut rng,
    );
    let ds = ds.unwrap();
    let mut s = String::from("x1,x2,u1,xdot1,xdot2\n");
    for j in 0..k {
        let (x, xd) = (&ds.xs[2 * j..2 * j + 2], &ds.xdot[2 * j..2 * j + 2]);
        s.push_str(&format!(
            "{},{},{},{},{}\n",
            x[0], x[1], ds.us[j], xd[0], xd[1]
        ));
    }
    std::fs::write(path, s).unwrap();
}

fn matrix(v: &Value) -> Vec<Vec<f64>> {
    let row = |r: &Value| {
        r.as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect()
    };
    v.as_array().unwrap().iter().map(row).collect()
}

/// Runs `bayes-cbf fit --data DATA --state-dim 2 --control-dim 1 --out OUT
/// EXTRA`; returns its stderr.
fn fit(data: &Path, out: &Path, extra: &[&str]) -> String {
    let (data, out) = (data.to_str().unwrap(), out.to_str().unwrap());
    let fit = words("fit --state-dim 2 --control-dim 1 --data");
    let r = run(&[&fit[..], &[data, "--out", out], extra].concat());
    assert!(r.status.success(), "{extra:?}: {}", r.stderr);
    assert!(
        r.stderr.contains("fit: k = ") && r.stderr.contains("log-likelihood"),
        "{}",
        r.stderr
    );
    r.stderr
}

/// Runs `bayes-cbf predict --model MODEL ARGS` and returns its JSON.
fn predict(model: &Path, args: &[&str]) -> Value {
    let r = run(&[&["predict", "--model", model.to_str().unwrap()], args].concat());
    assert!(r.status.success(), "predict failed: {}", r.stderr);
    if r.stdout.is_empty() {
        return Value::Null;
    }
    serde_json::from_str(&r.stdout).unwrap()
}

#[test]
fn fit_then_predict_pendulum_matches_truth() {
    let dir = scratch_dir("fit_predict");
    let (csv, model) = (dir.join("data.csv"), dir.join("sub").join("model.json"));
    write_pendulum_csv(&csv, 150, 1);
    assert!(fit(&csv, &model, &[]).contains("fit: k = 150"));
    let file = read_json(&model);
    assert_eq!(
        (&file["state_dim"], &file["control_dim"]),
        (&2.into(), &1.into())
    );
    assert_eq!(
        (&file["kernel"]["type"], &file["prior_mean"]),
        (&"rbf".into(), &"zero".into())
    );
    assert_eq!(file["kernel"]["lengthscales"].as_array().unwrap().len(), 2);
    assert!(file["noise_sigma"].as_f64().unwrap() > 0.0);
    assert_eq!((matrix(&file["A"]).len(), matrix(&file["B"]).len()), (2, 2));
    assert_eq!(file["data"]["x"].as_array().unwrap().len(), 150);
    assert!(file.get("input_map").is_none());

    // both spellings of a negative vector, two query points
    let points = [([0.5, -1.0], 2.0), ([-2.0, 1.5], -3.0)];
    let json = predict(&model, &["--x", "0.5,-1", "--x=-2.0,1.5"]);
    let obj = json.as_object().unwrap();
    assert_eq!(obj.keys().collect::<Vec<_>>(), vec!["predictions"]);
    let preds = json["predictions"].as_array().unwrap();
    assert_eq!(preds.len(), 2);
    for (p, (x, u)) in preds.iter().zip(points) {
        assert_eq!(p.as_object().unwrap().len(), 4, "{p}");
        assert_eq!(p["x"], serde_json::json!(x));
        let (mean, b, a) = (matrix(&p["mean"]), matrix(&p["B"]), matrix(&p["A"]));
        for m in [&mean, &b, &a] {
            assert_eq!((m.len(), m[0].len()), (2, 2));
        }
        assert_eq!(a, matrix(&file["A"]), "A is the model's row covariance");
        // B_k(x, x) is symmetric and, up to round-off relative to the prior
        // scale B k0(x, x), positive semi-definite and below the prior
        let prior_b = matrix(&file["B"]);
        let variance = file["kernel"]["variance"].as_f64().unwrap();
        assert_eq!(b[0][1], b[1][0]);
        for i in 0..2 {
            let scale = prior_b[i][i] * variance;
            assert!(b[i][i] >= -1e-12 * scale && b[i][i] <= scale, "B_k = {b:?}");
        }
        // mean of F(x)u̲ against the true pendulum
        let (mut f, mut truth) = ([0.0; 4], [0.0; 2]);
        Pendulum::default().xdot(&x, &[u], &mut f, &mut truth);
        let pred: Vec<f64> = (0..2).map(|r| mean[r][0] + mean[r][1] * u).collect();
        let err = ((pred[0] - truth[0]).powi(2) + (pred[1] - truth[1]).powi(2)).sqrt();
        let norm = (truth[0].powi(2) + truth[1].powi(2)).sqrt();
        assert!(
            err < 0.03 * norm,
            "x={x:?} u={u}: predicted {pred:?}, truth {truth:?}"
        );
    }

    // --out writes the same JSON to a file
    let pred_file = dir.join("pred.json");
    let out = predict(
        &model,
        &["--x", "0.5,-1", "--out", pred_file.to_str().unwrap()],
    );
    assert_eq!(out, Value::Null, "nothing on stdout");
    assert_eq!(read_json(&pred_file)["predictions"][0], preds[0]);

    // --out - is stdout, for predict and for fit's model file: no file
    // named '-'
    let m = model.to_str().unwrap();
    let r = run_in(
        &dir,
        &["predict", "--model", m, "--x", "0.5,-1", "--out", "-"],
    );
    assert!(r.status.success(), "{}", r.stderr);
    let v: Value = serde_json::from_str(&r.stdout).unwrap();
    assert_eq!(v["predictions"][0], preds[0]);
    let fit_args = "fit --state-dim 2 --control-dim 1 --max-iters 2 --out - --data";
    let r = run_in(
        &dir,
        &[&words(fit_args)[..], &[csv.to_str().unwrap()]].concat(),
    );
    assert!(r.status.success(), "{}", r.stderr);
    let v: Value = serde_json::from_str(&r.stdout).unwrap();
    assert_eq!(v["state_dim"], 2);
    assert!(!dir.join("-").exists());
}

#[test]
fn fit_with_prior_mean_file_input_map_and_ranks() {
    let dir = scratch_dir("fit_prior");
    let (csv, model, prior) = (
        dir.join("data.csv"),
        dir.join("model.json"),
        dir.join("p.json"),
    );
    write_pendulum_csv(&csv, 60, 2);
    // a wrong-gravity pendulum as the prior, from a file
    let text = r#"{"type": "pendulum", "mass": 1.0, "length": 1.0, "gravity": 8.0}"#;
    std::fs::write(&prior, text).unwrap();
    let opts = "--input-map 0 --rank-a diag --rank-b 1 --restarts 1 --seed 7 --prior-mean";
    fit(
        &csv,
        &model,
        &[&words(opts)[..], &[prior.to_str().unwrap()]].concat(),
    );
    let file = read_json(&model);
    assert_eq!(file["prior_mean"]["type"], "pendulum");
    assert_eq!(file["prior_mean"]["gravity"], 8.0);
    assert_eq!(file["input_map"], serde_json::json!([0]));
    assert_eq!(file["kernel"]["lengthscales"].as_array().unwrap().len(), 1);
    let a = matrix(&file["A"]);
    assert_eq!(a[0][1], 0.0, "diagonal A has no off-diagonal entries");
    // the kernel sees θ only, so predictions differ from the prior mean by a
    // function of θ: f1 = ω is carried by the prior, exactly
    let mean = matrix(&predict(&model, &["--x", "0.3,2.5"])["predictions"][0]["mean"]);
    assert!((mean[1][1] - 1.0).abs() < 0.05, "g2 = {}", mean[1][1]);
    // inline JSON prior and bare name work too
    for p in [r#"{"type":"pendulum"}"#, "pendulum"] {
        fit(&csv, &model, &["--prior-mean", p]);
    }
}

/// Simulates a spinning pendulum that crosses θ = ±π and writes `t,x1,x2,u1`.
fn write_spinning_time_series(path: &Path) -> Vec<f64> {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let policy = |_: &[f64], r: &mut ChaCha8Rng| vec![r.random_range(-2.0..2.0)];
    let sim = SimSettings::default();
    let ds = simulate_trajectory(
        &Pendulum::default(),
        &[2.9, 7.0],
        policy,
        0.01,
        120,
        sim,
        &mut rng,
    );
    let ds = ds.unwrap();
    let mut s = String::from("t,x1,x2,u1\n");
    for j in 0..ds.len() {
        let (t, x) = (j as f64 * 0.01, &ds.xs[2 * j..2 * j + 2]);
        s.push_str(&format!("{t},{},{},{}\n", x[0], x[1], ds.us[j]));
    }
    std::fs::write(path, s).unwrap();
    let thetas: Vec<f64> = (0..ds.len()).map(|j| ds.xs[2 * j]).collect();
    assert!(
        thetas.windows(2).any(|w| (w[1] - w[0]).abs() > 6.0),
        "the trajectory must wrap around ±π"
    );
    (0..ds.len()).map(|j| ds.xs[2 * j + 1]).collect()
}

#[test]
fn time_series_estimates_derivatives_across_the_wrap() {
    let dir = scratch_dir("time_series");
    let csv = dir.join("series.csv");
    let omegas = write_spinning_time_series(&csv);
    // the pendulum prior makes x1 an angle by default; explicit
    // --angle-index with a zero prior gives the same derivatives; without
    // wrapping, the crossing shows up as a 2π/Δt spike
    let cases = [
        ("wrapped", "--prior-mean pendulum --max-iters 30"),
        ("explicit", "--angle-index 0 --max-iters 30"),
        ("raw", "--angle-index none --max-iters 5"),
    ];
    let xdot: Vec<Vec<Vec<f64>>> = cases
        .iter()
        .map(|(name, opts)| {
            let model = dir.join(format!("{name}.json"));
            fit(
                &csv,
                &model,
                &[&["--time-series"], &words(opts)[..]].concat(),
            );
            matrix(&read_json(&model)["data"]["xdot"])
        })
        .collect();
    assert_eq!(xdot[0].len(), omegas.len());
    for (j, (row, w)) in xdot[0].iter().zip(&omegas).enumerate() {
        assert!(
            (row[0] - w).abs() < 0.2,
            "row {j}: dθ/dt = {} but ω = {w}",
            row[0]
        );
    }
    assert_eq!(xdot[1], xdot[0]);
    assert!(xdot[2].iter().any(|r| r[0].abs() > 100.0));
}

/// The learning demo writes its files into `runs/learning-demo` and says
/// so; its numbers are checked in `bayes-cbf-scenario/tests/learning_demo.rs`.
#[test]
fn learning_demo_writes_its_files() {
    let dir = scratch_dir("demo");
    let out = run_in(
        &dir,
        &words("demo --seed 3 --steps 80 --heldout 30 --grid 6"),
    );
    assert!(out.status.success(), "{}", out.stderr);
    let out_dir = Path::new("runs/learning-demo");
    for f in ["model.json", "grid.csv", "summary.json"] {
        let path = out_dir.join(f).display().to_string();
        assert!(out.stdout.contains(&path), "{}", out.stdout);
    }
    assert!(out.stdout.contains("relative RMSE"), "{}", out.stdout);
    let out_dir = dir.join(out_dir);
    let grid = std::fs::read_to_string(out_dir.join("grid.csv")).unwrap();
    assert_eq!(grid.lines().count(), 1 + 36);
    let summary = read_json(&out_dir.join("summary.json"));
    assert_eq!(
        (&summary["seed"], &summary["training_samples"]),
        (&3.into(), &80.into())
    );
    assert!(summary["rel_rmse"]["f_grid"].as_f64().unwrap() < 0.5);
    assert_eq!(summary["files"]["grid"], "runs/learning-demo/grid.csv");
    // the model file is a valid input of predict
    predict(&out_dir.join("model.json"), &["--x", "0.1,0.2"]);
}

#[test]
fn default_job_runs_the_closed_loop_comparison() {
    let dir = scratch_dir("default_job");
    let out = run_in(&dir, &[]);
    assert!(out.status.success(), "{}", out.stderr);
    assert!(
        out.stderr.contains("runs/demo/comparison.png"),
        "{}",
        out.stderr
    );
    let root = dir.join("runs/demo");
    for f in [
        "comparison.png",
        "mean-cbf/summary.json",
        "mean-cbf/animation.gif",
        "bayes-cbf/trajectory.png",
        "bayes-cbf/timeseries.png",
    ] {
        assert!(root.join(f).is_file(), "{f} missing");
    }
    assert_eq!(
        read_json(&root.join("mean-cbf/summary.json"))["collided"],
        true
    );
    assert_eq!(
        read_json(&root.join("bayes-cbf/summary.json"))["collided"],
        false
    );
}

#[test]
fn help_is_available_everywhere() {
    for args in ["--help", "fit --help", "predict --help", "demo --help"] {
        let out = run(&words(args));
        assert!(out.status.success(), "{args:?}");
        assert!(out.stdout.contains("Usage"), "{args:?}: {}", out.stdout);
    }
}

/// `bench --quick --out FILE` writes every case of the JSON, with the
/// bounded streams and the window / budget / full-data quality comparison.
#[test]
fn quick_bench_writes_every_case() {
    let dir = scratch_dir("bench");
    let out = dir.join("bench.json");
    let r = run_in(&dir, &["bench", "--quick", "--out", &out.to_string_lossy()]);
    assert!(r.status.success(), "{}", r.stderr);
    let v = read_json(&out);
    assert_eq!(v["threads"], 1);
    let rows = v["rows"].as_array().unwrap();
    let cases = |c: &str| rows.iter().filter(|r| r["case"] == c).collect::<Vec<_>>();
    for c in [
        "control_step",
        "add_observation",
        "remove_oldest",
        "predict",
        "floor",
        "fit",
    ] {
        assert!(!cases(c).is_empty(), "no {c} row");
    }
    let streams = cases("stream");
    assert!(streams.iter().any(|r| r["window"] == 200));
    assert!(streams.iter().any(|r| r["budget"] == 200));
    for s in &streams {
        assert_eq!(s["steps"], 2000);
        assert!(s["p50_us"].as_f64().unwrap() > 0.0, "{s}");
    }
    let q = cases("stream_quality");
    let err = |key: &str| {
        let row = q.iter().find(|r| !r[key].is_null());
        row.unwrap_or_else(|| panic!("no {key} quality row"))["rmse_fu"]
            .as_f64()
            .unwrap()
    };
    // a budget remembers the headings a window of the same size forgot
    assert!(err("budget") < err("window") / 5.0, "{q:?}");
    assert!(err("full") <= err("budget"), "{q:?}");
}

/// `--known-rows 0` on pendulum data: with the pendulum prior mean, whose
/// row 0 (`θ̇ = ω`) is right, `predict` gives row 0 the prior's value and
/// zero variance (its `A` has row and column 0 zeroed, so that
/// `Cov(vec F) = B ⊗ A` holds); under the zero prior mean the row is not
/// known at all, and `fit` warns that the data say otherwise.
#[test]
fn known_rows_are_zeroed_in_a_and_checked_against_the_data() {
    let dir = scratch_dir("fit_known_rows");
    let (csv, prior) = (dir.join("data.csv"), dir.join("p.json"));
    write_pendulum_csv(&csv, 60, 3);
    std::fs::write(
        &prior,
        r#"{"type": "pendulum", "mass": 1.0, "length": 1.0, "gravity": 9.81}"#,
    )
    .unwrap();
    let known = dir.join("known.json");
    let args = ["--known-rows", "0", "--prior-mean", prior.to_str().unwrap()];
    let stderr = fit(&csv, &known, &args);
    assert!(!stderr.contains("declared known"), "{stderr}");
    let json = predict(&known, &["--x", "0.5,-1"]);
    let p = &json["predictions"][0];
    let (mean, b, a) = (matrix(&p["mean"]), matrix(&p["B"]), matrix(&p["A"]));
    assert_eq!((a[0][0], a[0][1], a[1][0]), (0.0, 0.0, 0.0), "{a:?}");
    assert!(a[1][1] > 0.0, "{a:?}");
    // row 0 is the prior's θ̇ = ω exactly, and B ⊗ A gives it no variance
    assert_eq!((mean[0][0], mean[0][1]), (-1.0, 0.0));
    assert!(b[0][0] > 0.0 && a[0][0] * b[0][0] == 0.0);

    let zero = dir.join("zero.json");
    let stderr = fit(&csv, &zero, &["--known-rows", "0"]);
    assert!(
        stderr.contains("row 0 of F is declared known") && stderr.contains("prior mean"),
        "{stderr}"
    );
}
