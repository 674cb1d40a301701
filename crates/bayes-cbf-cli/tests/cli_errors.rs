//! The `bayes-cbf` binary on bad input: every case must exit non-zero with
//! one `error: ...` line on stderr that names the bad field or value, never
//! panic, and never leave a partial output file behind.

mod common;

use common::{assert_fails, read_json, run, scratch_dir, words};
use std::path::Path;

/// The model file of `interfaces.md`, valid; bad cases edit one thing.
const GOOD_MODEL: &str = r#"{
  "state_dim": 2,
  "control_dim": 1,
  "kernel": {"type": "rbf", "lengthscales": [0.7, 1.3], "variance": 1.5},
  "A": [[1.0, 0.1], [0.1, 0.8]],
  "B": [[1.0, 0.2], [0.2, 0.5]],
  "noise_sigma": 0.1,
  "prior_mean": "zero",
  "data": {"x": [[0.1, 0.2]], "u": [[0.5]], "xdot": [[0.2, -0.4]]}
}"#;

const GOOD_CSV: &str = "x1,x2,u1,xdot1,xdot2\n0.1,0.2,0.5,0.2,-0.4\n0.3,-0.1,1.0,-0.1,-1.9\n";

const A: &str = "[[1.0, 0.1], [0.1, 0.8]]";
const B: &str = "[[1.0, 0.2], [0.2, 0.5]]";
const SIGMA: &str = "\"noise_sigma\": 0.1";
const PRIOR: &str = "\"prior_mean\": \"zero\"";

/// `(replace, with, stderr must contain)` applied to `GOOD_MODEL`.
const MODEL_EDITS: &[(&str, &str, &[&str])] = &[
    (
        A,
        "[[1.0, 0.1, 0], [0.1, 0.8, 0], [0, 0, 1]]",
        &["A has 3 rows"],
    ),
    (A, "[[1.0, 0.1], [0.1]]", &["A[1] has 1 entries"]),
    (
        A,
        "[[1.0, 2.0], [2.0, 1.0]]",
        &["A is not symmetric positive definite"],
    ),
    (
        B,
        "[[1.0, 0.2], [0.3, 0.5]]",
        &["B is not symmetric positive definite", "not symmetric"],
    ),
    (
        B,
        "[[1.0, 0.2, 0.0], [0.2, 0.5, 0.0]]",
        &["B[0] has 3 entries"],
    ),
    (B, "[[1.0, 0.2], [0.2, 0.5], [0.0, 0.0]]", &["B has 3 rows"]),
    (
        B,
        "[[-1.0, 0.0], [0.0, 0.5]]",
        &["B is not symmetric positive definite", "eigenvalue"],
    ),
    (SIGMA, "\"noise_sigma\": -0.1", &["noise_sigma", "-0.1"]),
    (SIGMA, "\"noise_sigma\": 0", &["noise_sigma"]),
    (
        SIGMA,
        "\"noise_sigma\": \"small\"",
        &["noise_sigma", "invalid type"],
    ),
    (SIGMA, "\"noise_sigma\": 1e999", &["number out of range"]),
    (
        SIGMA,
        "\"noise_sigma\": 0.1, \"noise\": 2",
        &["unknown key \"noise\""],
    ),
    ("[0.7, 1.3]", "[0.0, 1.3]", &["kernel.lengthscales[0]"]),
    (
        "[0.7, 1.3]",
        "[0.7, 1.3, 2.0]",
        &["kernel.lengthscales has 3 entries"],
    ),
    (
        "\"variance\": 1.5",
        "\"variance\": -1.5",
        &["kernel.variance"],
    ),
    (
        "\"variance\": 1.5",
        "\"variance\": 1.5, \"period\": 2",
        &["kernel", "unknown field `period`"],
    ),
    ("\"rbf\"", "\"matern\"", &["kernel", "matern"]),
    (
        PRIOR,
        "\"prior_mean\": {\"type\": \"cartpole\"}",
        &["prior_mean", "cartpole"],
    ),
    (
        PRIOR,
        "\"prior_mean\": {\"type\": \"pendulum\", \"mass\": -1}",
        &["field prior_mean", "invalid mass = -1"],
    ),
    (
        PRIOR,
        "\"prior_mean\": {\"type\": \"pendulum\", \"mas\": 1}",
        &["prior_mean", "`mas`"],
    ),
    (
        PRIOR,
        "\"prior_mean\": {\"type\": \"ackermann\", \"wheelbase\": 2}",
        &["prior_mean", "n = 3"],
    ),
    (
        PRIOR,
        r#""prior_mean": {"type": "expression", "state": ["a", "b"], "control": ["u"], "f": ["b", "sin(a"], "g": [["0"], ["1"]]}"#,
        &["prior_mean", "f[1], column 6", "expected ')'"],
    ),
    (
        PRIOR,
        r#""prior_mean": {"type": "expression", "state": ["a", "b"], "control": ["u"], "f": ["b", "sin(c)"], "g": [["0"], ["1"]]}"#,
        &[
            "prior_mean",
            "f[1], column 5",
            "unknown name 'c' (known: a, b, pi)",
        ],
    ),
    (
        PRIOR,
        r#""prior_mean": {"type": "expression", "state": ["a", "b"], "control": ["u"], "f": ["b"], "g": [["0"], ["1"]]}"#,
        &["prior_mean", "wrong shape of f"],
    ),
    (
        PRIOR,
        r#""prior_mean": {"type": "expression", "control": ["u"], "f": ["b", "a"], "g": [["0"], ["1"]]}"#,
        &["prior_mean", "needs \"state\""],
    ),
    (
        PRIOR,
        r#""prior_mean": {"type": "expression", "state": ["a", "b"], "control": ["u"], "f": ["b", "log(a - 5)"], "g": [["0"], ["1"]]}"#,
        &["prior mean: f[1] = NaN at state [0.1, 0.2]"],
    ),
    (
        PRIOR,
        r#""prior_mean": {"type": "expression", "state": ["a", "b"], "control": ["u"], "params": {"k": "x"}, "f": ["b", "a"], "g": [["0"], ["1"]]}"#,
        &["params.k = \"x\": expected a number"],
    ),
    (PRIOR, "\"input_map\": [4]", &["input_map[0]"]),
    (
        PRIOR,
        "\"input_map\": [{\"tan\": 0}]",
        &["input_map", "tan"],
    ),
    (
        "\"u\": [[0.5]]",
        "\"u\": [[0.5, 1.0]]",
        &["data.u[0] has 2 entries"],
    ),
    (
        "\"x\": [[0.1, 0.2]]",
        "\"x\": [[0.1, 0.2, 0.3]]",
        &["data.x[0] has 3 entries"],
    ),
    (
        "\"xdot\": [[0.2, -0.4]]",
        "\"xdot\": []",
        &["data.xdot has 0 rows"],
    ),
    (
        "\"data\": {",
        "\"data\": {\"t\": [], ",
        &["data", "unknown field `t`"],
    ),
    ("\"state_dim\": 2,", "", &["missing field `state_dim`"]),
    (
        "\"control_dim\": 1,",
        "\"control_dim\": 0,",
        &["control_dim"],
    ),
];

/// Whole model files that are not models at all.
const MODEL_TEXTS: &[(&str, &[&str])] = &[
    ("", &["is empty"]),
    (
        "{\"state_dim\": 2, \"control_dim\": 1, \"kernel\": {\"type\"",
        &["truncated"],
    ),
    ("{\"state_dim\": 2,, }", &["not valid JSON"]),
    ("[1, 2]", &["JSON object"]),
    // as Python's json.dump writes them: the field is named
    (
        "{\"state_dim\": 2, \"noise_sigma\": NaN}",
        &["field 'noise_sigma' holds NaN", "not a JSON number"],
    ),
    (
        "{\"state_dim\": 2, \"A\": [[1.0, 0.0], [0.0, -Infinity]]}",
        &["field 'A' holds -Infinity", "line 1 column"],
    ),
];

/// Asserts a failed run with one `error:` line containing every `expect`.
fn check(args: &[&str], expect: &[&str], case: &str) {
    assert_fails(&run(args), expect, case);
}

/// Writes `text` to `dir/name` and returns the path.
fn written(dir: &Path, name: &str, text: &str) -> String {
    let path = path_str(dir, name);
    std::fs::write(&path, text).unwrap();
    path
}

fn path_str(dir: &Path, name: &str) -> String {
    dir.join(name).to_str().unwrap().to_string()
}

#[test]
fn bad_model_files_are_rejected_naming_the_field() {
    let dir = scratch_dir("bad_models");
    let good = path_str(&dir, "good.json");
    std::fs::write(&good, GOOD_MODEL).unwrap();
    let out = run(&["predict", "--model", &good, "--x", "0.1,0.2"]);
    assert!(
        out.status.success(),
        "the base model is valid: {}",
        out.stderr
    );

    let mut texts: Vec<(String, &[&str])> = MODEL_EDITS
        .iter()
        .map(|(from, to, expect)| {
            assert!(GOOD_MODEL.contains(from), "{from}");
            (GOOD_MODEL.replacen(from, to, 1), *expect)
        })
        .collect();
    texts.extend(MODEL_TEXTS.iter().map(|(t, e)| (t.to_string(), *e)));
    for (i, (text, expect)) in texts.iter().enumerate() {
        let path = path_str(&dir, &format!("model{i}.json"));
        std::fs::write(&path, text).unwrap();
        check(
            &["predict", "--model", &path, "--x", "0.1,0.2"],
            expect,
            &format!("model {i}: {text}"),
        );
    }
    let missing = path_str(&dir, "missing.json");
    check(
        &["predict", "--model", &missing, "--x", "0.1,0.2"],
        &["cannot read model file", "missing.json"],
        "missing",
    );
    assert!(texts.len() >= 30);
}

#[test]
fn bad_query_vectors_are_rejected() {
    let dir = scratch_dir("bad_queries");
    let good = path_str(&dir, "good.json");
    std::fs::write(&good, GOOD_MODEL).unwrap();
    let cases: &[(&[&str], &[&str])] = &[
        (&["--x", "0.1,abc"], &["--x[1]", "abc", "not a number"]),
        (
            &["--x", "0.1,0.2,0.3"],
            &["--x", "3 values", "state_dim is 2"],
        ),
        (&["--x=-0.1"], &["--x", "1 values"]),
        (&["--x", "0.1,nan"], &["--x[1]", "not finite"]),
        (&["--x", "0.1,-inf"], &["--x[1]", "not finite"]),
        (&["--x", ""], &["--x", "empty"]),
        (&["--x", "0.1;0.2"], &["--x[0]", "not a number"]),
        (&["--x", "0.1,0.2", "--x", "1"], &["--x (#2)", "1 values"]),
        (&[], &["--x"]),
    ];
    for (extra, expect) in cases {
        let mut args = vec!["predict", "--model", good.as_str()];
        args.extend_from_slice(extra);
        check(&args, expect, &format!("{extra:?}"));
    }
}

/// A barrier whose `h` is not a number at the queried state is named by
/// its file, among several.
#[test]
fn control_names_the_barrier_file_that_fails() {
    let dir = scratch_dir("bad_control_barrier");
    let model = written(&dir, "model.json", GOOD_MODEL);
    let barrier = |h: &str| {
        format!(
            r#"{{"type": "expression", "state": ["t", "w"], "h": "{h}", "relative_degree": 1, "alpha": 1.0}}"#
        )
    };
    let fine = written(&dir, "fine.json", &barrier("1 - t"));
    let root = written(&dir, "root.json", &barrier("t^0.5"));
    let args = [
        "control",
        "--model",
        &model,
        "--barrier",
        &fine,
        "--barrier",
        &root,
        "--x=-1.2,-0.4",
        "--probability",
        "0.9",
    ];
    check(
        &args,
        &[&format!("barrier '{root}'"), "NaN"],
        "t^0.5 at t < 0",
    );
}

#[test]
fn bad_data_files_are_rejected_with_line_and_column() {
    let dir = scratch_dir("bad_csv");
    let edit = |from: &str, to: &str| {
        assert!(GOOD_CSV.contains(from), "{from}");
        GOOD_CSV.replacen(from, to, 1)
    };
    let cases: Vec<(String, &[&str])> = vec![
        (
            edit("0.2,-0.4\n", "nan,-0.4\n"),
            &["line 2", "column xdot1", "not finite"],
        ),
        (
            edit("0.3,-0.1", "0.3,inf"),
            &["line 3", "column x2", "not finite"],
        ),
        (edit("u1", "u"), &["header column 3", "\"u\"", "\"u1\""]),
        (
            edit(",xdot2\n", "\n"),
            &["header has 4 columns", "x1,x2,u1,xdot1,xdot2"],
        ),
        (
            edit("1.0,-0.1,-1.9", "1.0,-0.1"),
            &["line 3: expected 5 columns, got 4"],
        ),
        (
            edit("-1.9\n", "-1.9,7\n"),
            &["line 3: expected 5 columns, got 6"],
        ),
        (
            edit("0.5,0.2", "0.5,zero"),
            &["line 2", "column xdot1", "\"zero\" is not a number"],
        ),
        (String::new(), &["is empty"]),
        ("x1,x2,u1,xdot1,xdot2\n".to_string(), &["no data rows"]),
    ];
    for (i, (text, expect)) in cases.iter().enumerate() {
        let (data, out) = (
            path_str(&dir, &format!("data{i}.csv")),
            path_str(&dir, &format!("out{i}.json")),
        );
        std::fs::write(&data, text).unwrap();
        let args = [
            &words("fit --state-dim 2 --control-dim 1 --data")[..],
            &[&data, "--out", &out],
        ];
        check(&args.concat(), expect, &format!("csv {i}: {text}"));
        assert!(!Path::new(&out).exists(), "csv {i}: no output on failure");
    }
}

#[test]
fn bad_fit_options_are_rejected() {
    let dir = scratch_dir("bad_fit_options");
    let (data, out) = (path_str(&dir, "good.csv"), path_str(&dir, "never.json"));
    std::fs::write(&data, GOOD_CSV).unwrap();
    let series = path_str(&dir, "series.csv");
    let text = "t,x1,x2,u1\n0.0,0.1,0.2,0.5\n0.01,0.1,0.2,0.5\n0.01,0.1,0.2,0.5\n";
    std::fs::write(&series, text).unwrap();
    let missing = path_str(&dir, "missing.csv");
    // (data file, options after `--state-dim 2 --control-dim 1` unless they
    // give a dimension, stderr must contain)
    let cases: &[(&str, &str, &[&str])] = &[
        (
            &data,
            "--state-dim 1 --control-dim 1",
            &["header has 5 columns", "need 3", "x1,u1,xdot1"],
        ),
        (&data, "--state-dim 0 --control-dim 1", &["--state-dim"]),
        (
            &data,
            "--state-dim -1 --control-dim 1",
            &["'-1' for '--state-dim"],
        ),
        (&data, "--max-iters -5", &["'-5' for '--max-iters"]),
        (
            &data,
            "--state-dim two --control-dim 1",
            &["--state-dim", "two"],
        ),
        (&data, "--control-dim 1", &["--state-dim"]),
        (
            &data,
            r#"--prior-mean {"type":"quadrotor"}"#,
            &["--prior-mean", "quadrotor"],
        ),
        (
            &data,
            r#"--prior-mean {"type":"pendulum""#,
            &["--prior-mean", "not valid JSON"],
        ),
        (
            &data,
            "--prior-mean nope.json",
            &["--prior-mean", "nope.json"],
        ),
        (&data, "--rank-a 0", &["--rank-a"]),
        // a negative rank reaches the rule, not clap's "unexpected argument"
        (
            &data,
            "--rank-a -1",
            &["--rank-a = '-1'", "positive integer rank"],
        ),
        (&data, "--rank-b lots", &["--rank-b", "lots"]),
        (&data, "--input-map 5", &["--input-map[0]", "out of range"]),
        (&data, "--input-map tan:0", &["--input-map[0]", "tan"]),
        (
            &data,
            "--angle-index 0",
            &["--angle-index", "--time-series"],
        ),
        (&data, "--max-iters 0", &["max_iters"]),
        (&data, "--sigma-min -1", &["sigma_min"]),
        (&data, "--colour red", &["--colour"]),
        (&series, "--time-series", &["t[2]", "strictly increasing"]),
        (
            &series,
            "--time-series --angle-index 2",
            &["--angle-index[0]", "out of range"],
        ),
        (&missing, "", &["cannot read data file"]),
    ];
    for (data, opts, expect) in cases {
        let mut args = vec!["fit", "--data", data, "--out", &out];
        if !opts.contains("-dim ") {
            args.extend(["--state-dim", "2", "--control-dim", "1"]);
        }
        args.extend(words(opts));
        check(&args, expect, opts);
        assert!(!Path::new(&out).exists(), "{opts}: no output on failure");
    }
    check(&["frobnicate"], &["frobnicate"], "unknown subcommand");
    check(&["demo", "--grid", "1"], &["grid = 1"], "demo grid");
}

fn owned(args: Vec<&str>) -> Vec<String> {
    args.into_iter().map(String::from).collect()
}

/// Inputs that once panicked, aborted on an allocation, hung or wrote
/// non-finite numbers: each is now one error naming the field.
#[test]
fn extreme_values_are_errors_not_crashes() {
    let dir = scratch_dir("extremes");
    let model = written(&dir, "model.json", GOOD_MODEL);
    let sector = written(
        &dir,
        "sector.json",
        r#"{"type": "pendulum_sector", "theta_c": 0.7854, "delta": 0.3927,
            "relative_degree": 2, "k_alpha": [1.0, 3.0]}"#,
    );
    // θ' = ω known: the sector's L_g h is 0, and the run says nothing else
    let known = path_str(&dir, "known.json");
    std::fs::write(
        &known,
        GOOD_MODEL.replace(PRIOR, "\"prior_mean\": {\"type\": \"pendulum\", \"mass\": 1.0, \"length\": 1.0, \"gravity\": 10.0}, \"known_rows\": [0]"),
    )
    .unwrap();
    let steep = path_str(&dir, "steep.json");
    std::fs::write(
        &steep,
        r#"{"type": "expression", "state": ["x", "y"], "h": "1e200*x + 1",
            "relative_degree": 1, "alpha": 1}"#,
    )
    .unwrap();
    let deep = path_str(&dir, "deep.json");
    std::fs::write(
        &deep,
        r#"{"type": "pendulum_sector", "theta_c": 0.7854, "delta": 0.3927,
            "relative_degree": 3, "k_alpha": [1.0, 3.0, 3.0]}"#,
    )
    .unwrap();
    let out = path_str(&dir, "out");
    let run_di = |sets: &[&str]| -> Vec<String> {
        let mut a = vec!["run", "double-integrator", "--out", out.as_str()];
        for s in sets {
            a.push("--set");
            a.push(s);
        }
        a.iter().map(|s| s.to_string()).collect()
    };
    let moments = |model: &str, barrier: &str, x: &str, u: &str| -> Vec<String> {
        [
            "moments",
            "--model",
            model,
            "--barrier",
            barrier,
            "--x",
            x,
            "--u",
            u,
        ]
        .iter()
        .map(|s| s.to_string())
        .collect()
    };
    let cases: Vec<(Vec<String>, &[&str])> = vec![
        (
            run_di(&["start_spread=[1e308,0]"]),
            &["start_spread[0]", "too large"],
        ),
        (run_di(&["dt=1e10", "steps=3"]), &["dt", "sub-steps"]),
        (run_di(&["steps=1000000000000"]), &["steps", "too large"]),
        (
            owned(words(
                "run double-integrator --set steps=10 --seeds 0..1000000000000000",
            )),
            &["seeds", "too large"],
        ),
        (
            owned(words("run soak --steps 1000000000000000000")),
            &["steps = ", "too large"],
        ),
        (
            owned(words("run double-integrator --seed 9223372036854775808")),
            &["--seed", "not in 0..=9223372036854775807"],
        ),
        (
            moments(&known, &sector, "1e308,0.1", "0.7"),
            &["not finite at x = [1e308, 0.1]"],
        ),
        (
            moments(&known, &sector, "0.1,0.1", "1e200"),
            &["u = [1e200]", "overflows"],
        ),
        (
            moments(&model, &steep, "0,0.5", "0.7"),
            &["cov[0][0] = inf"],
        ),
        (
            {
                let mut a = moments(&known, &deep, "0,0.5", "0.7");
                a.extend(["--samples".to_string(), "99999999999999".to_string()]);
                a
            },
            &["samples", "too large"],
        ),
    ];
    for (args, expect) in cases {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        check(&args, expect, &args.join(" "));
        assert!(!Path::new(&out).join("summary.json").exists(), "{args:?}");
    }
    // an observation beyond the magnitude the regression squares
    let big = GOOD_MODEL.replace("\"xdot\": [[0.2, -0.4]]", "\"xdot\": [[1e200, -0.4]]");
    std::fs::write(&model, big).unwrap();
    check(
        &["predict", "--model", &model, "--x", "0.1,0.2"],
        &["xdot[0][0]", "1e200", "too large"],
        "observation 1e200",
    );
}

/// An override may set a field the file leaves out (the seed, the goal);
/// an unknown one is refused with the list of the known ones.
/// Negative or out-of-range numbers given after a space name their option.
#[test]
fn run_numbers_name_their_option() {
    for (args, expect) in [
        ("run double-integrator --seed -3", &["'-3' for '--seed"][..]),
        ("run double-integrator --seeds -1..2", &["seeds '-1..2'"]),
        (
            "run double-integrator --seeds 0..2 --shard -1/2",
            &["shard '-1/2'"],
        ),
        (
            "run calibration --episodes 18446744073709551615",
            &["episodes = ", "too large"],
        ),
        (
            "run double-integrator --seeds 18446744073709551615..=18446744073709551615",
            &["seeds are at most 9223372036854775807"],
        ),
        // the printed scenario is one that runs
        (
            "run double-integrator --print-config --set dt=-1",
            &["dt = -1: must be finite and > 0"],
        ),
    ] {
        check(&words(args), expect, args);
    }
}

#[test]
fn overrides_reach_fields_the_file_leaves_out() {
    let dir = scratch_dir("overrides");
    let printed = run(&["run", "double-integrator", "--print-config"]);
    assert!(printed.status.success(), "{}", printed.stderr);
    let text: String = printed
        .stdout
        .lines()
        .filter(|l| !l.starts_with("seed ="))
        .map(|l| format!("{l}\n"))
        .collect();
    let file = path_str(&dir, "noseed.toml");
    std::fs::write(&file, text).unwrap();
    let out = path_str(&dir, "out");
    let ok = run(&[
        "run",
        &file,
        "--seed",
        "5",
        "--set",
        "steps=20",
        "--set",
        "goal=[1,0]",
        "--out",
        &out,
    ]);
    assert!(ok.status.success(), "{}", ok.stderr);
    let summary = read_json(&Path::new(&out).join("summary.json"));
    assert_eq!(summary["seed"], 5);
    assert!(summary["final_goal_distance"].is_number(), "{summary}");
    check(
        &["run", &file, "--set", "bogus=1", "--out", &out],
        &["unknown field `bogus`", "expected one of"],
        "unknown top-level key",
    );
}
