//! End-to-end tests of the `bayes-cbf` binary in scratch directories:
//! fit → predict on pendulum data, time series with angle wrap, the demo and
//! help output. Bad input of every kind is tested in `cli_errors.rs`.

use bayes_cbf::sim::{sample_uniform, simulate_trajectory, SimSettings};
use bayes_cbf::systems::{DynSystem, Pendulum};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::Value;
use std::path::Path;

mod common;

use common::{run, run_in, scratch_dir};

/// Writes `k` noise-free pendulum samples `x1,x2,u1,xdot1,xdot2`, states
/// uniform on `[-π, π) × [-4, 4]`, torques uniform on `[-5, 5]`.
fn write_pendulum_csv(path: &Path, k: usize, seed: u64) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let pi = std::f64::consts::PI;
    let ds = sample_uniform(
        &Pendulum::default(),
        &[-pi, -4.0],
        &[pi, 4.0],
        &[-5.0],
        &[5.0],
        k,
        0.0,
        &mut rng,
    )
    .unwrap();
    let mut s = String::from("x1,x2,u1,xdot1,xdot2\n");
    for j in 0..k {
        let r = [
            ds.xs[2 * j],
            ds.xs[2 * j + 1],
            ds.us[j],
            ds.xdot[2 * j],
            ds.xdot[2 * j + 1],
        ];
        s.push_str(
            &r.iter()
                .map(|v| v.to_string())
                .collect::<Vec<_>>()
                .join(","),
        );
        s.push('\n');
    }
    std::fs::write(path, s).unwrap();
}

fn matrix(v: &Value) -> Vec<Vec<f64>> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|r| {
            r.as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap())
                .collect()
        })
        .collect()
}

fn true_xdot(x: &[f64], u: f64) -> Vec<f64> {
    let mut f = [0.0; 4];
    let mut out = vec![0.0; 2];
    Pendulum::default().xdot(x, &[u], &mut f, &mut out);
    out
}

#[test]
fn fit_then_predict_pendulum_matches_truth() {
    let dir = scratch_dir("fit_predict");
    let csv = dir.join("data.csv");
    let model = dir.join("sub").join("model.json");
    write_pendulum_csv(&csv, 150, 1);
    let out = run(&[
        "fit",
        "--data",
        csv.to_str().unwrap(),
        "--state-dim",
        "2",
        "--control-dim",
        "1",
        "--out",
        model.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "fit failed: {}", out.stderr);
    assert!(
        out.stderr.contains("fit: k = 150") && out.stderr.contains("log-likelihood"),
        "{}",
        out.stderr
    );

    let file: Value = serde_json::from_str(&std::fs::read_to_string(&model).unwrap()).unwrap();
    assert_eq!(file["state_dim"], 2);
    assert_eq!(file["control_dim"], 1);
    assert_eq!(file["kernel"]["type"], "rbf");
    assert_eq!(file["kernel"]["lengthscales"].as_array().unwrap().len(), 2);
    assert_eq!(file["prior_mean"], "zero");
    assert!(file["noise_sigma"].as_f64().unwrap() > 0.0);
    assert_eq!(matrix(&file["A"]).len(), 2);
    assert_eq!(matrix(&file["B"]).len(), 2);
    assert_eq!(file["data"]["x"].as_array().unwrap().len(), 150);
    assert!(file.get("input_map").is_none());

    // both spellings of a negative vector, two query points
    let points = [([0.5, -1.0], 2.0), ([-2.0, 1.5], -3.0)];
    let out = run(&[
        "predict",
        "--model",
        model.to_str().unwrap(),
        "--x",
        "0.5,-1",
        "--x=-2.0,1.5",
    ]);
    assert!(out.status.success(), "predict failed: {}", out.stderr);
    let json: Value = serde_json::from_str(&out.stdout).unwrap();
    let obj = json.as_object().unwrap();
    assert_eq!(obj.keys().collect::<Vec<_>>(), vec!["predictions"]);
    let preds = json["predictions"].as_array().unwrap();
    assert_eq!(preds.len(), 2);
    for (p, (x, u)) in preds.iter().zip(points) {
        let keys: Vec<&String> = p.as_object().unwrap().keys().collect();
        assert_eq!(keys.len(), 4, "{keys:?}");
        assert_eq!(
            p["x"]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap())
                .collect::<Vec<_>>(),
            x.to_vec()
        );
        let mean = matrix(&p["mean"]);
        let b = matrix(&p["B"]);
        let a = matrix(&p["A"]);
        assert_eq!((mean.len(), mean[0].len()), (2, 2));
        assert_eq!((b.len(), b[0].len()), (2, 2));
        assert_eq!((a.len(), a[0].len()), (2, 2));
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
        let truth = true_xdot(&x, u);
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
    let out = run(&[
        "predict",
        "--model",
        model.to_str().unwrap(),
        "--x",
        "0.5,-1",
        "--out",
        pred_file.to_str().unwrap(),
    ]);
    assert!(
        out.status.success() && out.stdout.is_empty(),
        "{}",
        out.stderr
    );
    let saved: Value = serde_json::from_str(&std::fs::read_to_string(&pred_file).unwrap()).unwrap();
    assert_eq!(saved["predictions"][0], preds[0]);
}

#[test]
fn fit_with_prior_mean_file_input_map_and_ranks() {
    let dir = scratch_dir("fit_prior");
    let csv = dir.join("data.csv");
    let model = dir.join("model.json");
    let prior = dir.join("prior.json");
    write_pendulum_csv(&csv, 60, 2);
    // a wrong-gravity pendulum as the prior, from a file
    std::fs::write(
        &prior,
        r#"{"type": "pendulum", "mass": 1.0, "length": 1.0, "gravity": 8.0}"#,
    )
    .unwrap();
    let out = run(&[
        "fit",
        "--data",
        csv.to_str().unwrap(),
        "--state-dim",
        "2",
        "--control-dim",
        "1",
        "--prior-mean",
        prior.to_str().unwrap(),
        "--input-map",
        "0",
        "--rank-a",
        "diag",
        "--rank-b",
        "1",
        "--restarts",
        "1",
        "--seed",
        "7",
        "--out",
        model.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", out.stderr);
    let file: Value = serde_json::from_str(&std::fs::read_to_string(&model).unwrap()).unwrap();
    assert_eq!(file["prior_mean"]["type"], "pendulum");
    assert_eq!(file["prior_mean"]["gravity"], 8.0);
    assert_eq!(file["input_map"], serde_json::json!([0]));
    assert_eq!(file["kernel"]["lengthscales"].as_array().unwrap().len(), 1);
    let a = matrix(&file["A"]);
    assert_eq!(a[0][1], 0.0, "diagonal A has no off-diagonal entries");
    // the kernel sees θ only, so predictions differ from the prior mean by a
    // function of θ: f1 = ω is carried by the prior, exactly
    let out = run(&[
        "predict",
        "--model",
        model.to_str().unwrap(),
        "--x",
        "0.3,2.5",
    ]);
    assert!(out.status.success(), "{}", out.stderr);
    let json: Value = serde_json::from_str(&out.stdout).unwrap();
    let mean = matrix(&json["predictions"][0]["mean"]);
    assert!((mean[1][1] - 1.0).abs() < 0.05, "g2 = {}", mean[1][1]);
    // inline JSON prior and bare name work too
    for p in [r#"{"type":"pendulum"}"#, "pendulum"] {
        let out = run(&[
            "fit",
            "--data",
            csv.to_str().unwrap(),
            "--state-dim",
            "2",
            "--control-dim",
            "1",
            "--prior-mean",
            p,
            "--out",
            model.to_str().unwrap(),
        ]);
        assert!(out.status.success(), "{p}: {}", out.stderr);
    }
}

/// Simulates a spinning pendulum that crosses θ = ±π and writes `t,x1,x2,u1`.
fn write_spinning_time_series(path: &Path) -> Vec<f64> {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let sys = Pendulum::default();
    let policy = |_: &[f64], r: &mut ChaCha8Rng| vec![r.random_range(-2.0..2.0)];
    let ds = simulate_trajectory(
        &sys,
        &[2.9, 7.0],
        policy,
        0.01,
        120,
        SimSettings::default(),
        &mut rng,
    )
    .unwrap();
    let mut s = String::from("t,x1,x2,u1\n");
    for j in 0..ds.len() {
        s.push_str(&format!(
            "{},{},{},{}\n",
            j as f64 * 0.01,
            ds.xs[2 * j],
            ds.xs[2 * j + 1],
            ds.us[j]
        ));
    }
    std::fs::write(path, s).unwrap();
    let thetas: Vec<f64> = (0..ds.len()).map(|j| ds.xs[2 * j]).collect();
    assert!(
        thetas.windows(2).any(|w| (w[1] - w[0]).abs() > 6.0),
        "the trajectory must wrap around ±π"
    );
    (0..ds.len()).map(|j| ds.xs[2 * j + 1]).collect()
}

fn fitted_xdot(model: &Path) -> Vec<Vec<f64>> {
    let file: Value = serde_json::from_str(&std::fs::read_to_string(model).unwrap()).unwrap();
    matrix(&file["data"]["xdot"])
}

#[test]
fn time_series_estimates_derivatives_across_the_wrap() {
    let dir = scratch_dir("time_series");
    let csv = dir.join("series.csv");
    let omegas = write_spinning_time_series(&csv);
    let base = [
        "fit",
        "--data",
        csv.to_str().unwrap(),
        "--state-dim",
        "2",
        "--control-dim",
        "1",
        "--time-series",
    ];

    // the pendulum prior makes x1 an angle by default
    let wrapped = dir.join("wrapped.json");
    let mut args = base.to_vec();
    args.extend([
        "--prior-mean",
        "pendulum",
        "--max-iters",
        "30",
        "--out",
        wrapped.to_str().unwrap(),
    ]);
    let out = run(&args);
    assert!(out.status.success(), "{}", out.stderr);
    let xd = fitted_xdot(&wrapped);
    assert_eq!(xd.len(), omegas.len());
    for (j, (row, w)) in xd.iter().zip(&omegas).enumerate() {
        assert!(
            (row[0] - w).abs() < 0.2,
            "row {j}: dθ/dt = {} but ω = {w}",
            row[0]
        );
    }

    // explicit --angle-index with a zero prior gives the same derivatives
    let explicit = dir.join("explicit.json");
    let mut args = base.to_vec();
    args.extend([
        "--angle-index",
        "0",
        "--max-iters",
        "30",
        "--out",
        explicit.to_str().unwrap(),
    ]);
    let out = run(&args);
    assert!(out.status.success(), "{}", out.stderr);
    assert_eq!(fitted_xdot(&explicit), xd);

    // without wrapping, the crossing shows up as a 2π/Δt spike
    let raw = dir.join("raw.json");
    let mut args = base.to_vec();
    args.extend([
        "--angle-index",
        "none",
        "--max-iters",
        "5",
        "--out",
        raw.to_str().unwrap(),
    ]);
    let out = run(&args);
    assert!(out.status.success(), "{}", out.stderr);
    assert!(fitted_xdot(&raw).iter().any(|r| r[0].abs() > 100.0));
}

#[test]
fn demo_writes_its_files_deterministically() {
    let dir = scratch_dir("demo");
    let mut grids = Vec::new();
    for run_no in 0..2 {
        let out_dir = dir.join(format!("run{run_no}"));
        let out = run(&[
            "demo",
            "--out",
            out_dir.to_str().unwrap(),
            "--seed",
            "3",
            "--steps",
            "80",
            "--heldout",
            "30",
            "--grid",
            "6",
        ]);
        assert!(out.status.success(), "{}", out.stderr);
        for f in ["model.json", "grid.csv", "summary.json"] {
            assert!(
                out.stdout.contains(&out_dir.join(f).display().to_string()),
                "{}",
                out.stdout
            );
        }
        assert!(out.stdout.contains("relative RMSE"), "{}", out.stdout);
        let grid = std::fs::read_to_string(out_dir.join("grid.csv")).unwrap();
        let lines: Vec<&str> = grid.lines().collect();
        assert_eq!(lines.len(), 1 + 36);
        assert!(lines[0].starts_with("theta,omega,f1_true,f2_true,g1_true,g2_true,f1_mean"));
        assert!(lines.iter().all(|l| l.split(',').count() == 14));
        let summary: Value =
            serde_json::from_str(&std::fs::read_to_string(out_dir.join("summary.json")).unwrap())
                .unwrap();
        assert_eq!(summary["seed"], 3);
        assert_eq!(summary["training_samples"], 80);
        let rel = &summary["rel_rmse"];
        for key in ["f_grid", "g_grid", "Fu_heldout"] {
            let v = rel[key].as_f64().unwrap();
            assert!(v.is_finite() && v < 0.5, "{key} = {v}");
        }
        assert!(
            summary["log_likelihood"].as_f64().unwrap()
                > summary["log_likelihood_initial"].as_f64().unwrap()
        );
        // the model file is a valid input of predict
        let out = run(&[
            "predict",
            "--model",
            out_dir.join("model.json").to_str().unwrap(),
            "--x",
            "0.1,0.2",
        ]);
        assert!(out.status.success(), "{}", out.stderr);
        grids.push(grid);
    }
    assert_eq!(grids[0], grids[1], "same seed, same results");
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
    for f in [
        "comparison.png",
        "mean-cbf/summary.json",
        "mean-cbf/animation.gif",
        "bayes-cbf/trajectory.png",
        "bayes-cbf/timeseries.png",
    ] {
        assert!(dir.join("runs/demo").join(f).is_file(), "{f} missing");
    }
    let read = |d: &str| -> Value {
        serde_json::from_str(
            &std::fs::read_to_string(dir.join("runs/demo").join(d).join("summary.json")).unwrap(),
        )
        .unwrap()
    };
    assert_eq!(read("mean-cbf")["collided"], true);
    assert_eq!(read("bayes-cbf")["collided"], false);
}

#[test]
fn learning_demo_fits_the_pendulum() {
    let dir = scratch_dir("learning_demo");
    let out = run_in(&dir, &["demo"]);
    assert!(out.status.success(), "{}", out.stderr);
    let summary: Value = serde_json::from_str(
        &std::fs::read_to_string(dir.join("runs/learning-demo/summary.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(summary["training_samples"], 200);
    assert_eq!(summary["grid"], 20);
    assert_eq!(
        std::fs::read_to_string(dir.join("runs/learning-demo/grid.csv"))
            .unwrap()
            .lines()
            .count(),
        401
    );
    // the fit is good: a few percent on the whole grid
    assert!(
        summary["rel_rmse"]["f_grid"].as_f64().unwrap() < 0.05,
        "{summary}"
    );
    assert!(
        summary["rel_rmse"]["g_grid"].as_f64().unwrap() < 0.05,
        "{summary}"
    );
    assert!(
        summary["rel_rmse"]["Fu_heldout"].as_f64().unwrap() < 0.05,
        "{summary}"
    );
}

#[test]
fn help_is_available_everywhere() {
    for args in [
        vec!["--help"],
        vec!["fit", "--help"],
        vec!["predict", "--help"],
        vec!["demo", "--help"],
    ] {
        let out = run(&args);
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
    let v: Value = serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
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
        q.iter()
            .find(|r| !r[key].is_null())
            .unwrap_or_else(|| panic!("no {key} quality row"))["rmse_fu"]
            .as_f64()
            .unwrap()
    };
    // a budget remembers the headings a window of the same size forgot
    assert!(err("budget") < err("window") / 5.0, "{q:?}");
    assert!(err("full") <= err("budget"), "{q:?}");
}
