//! Property-based fuzzing of every file reader: arbitrary text, and valid
//! files with random characters replaced, inserted or removed, must give
//! `Ok` or an error with a message, never a panic. (Messages may quote the
//! offending text, newlines included; `main` folds them onto one line.)

use crate::barrier_file::BarrierSpec;
use crate::csv_data::{expected_header, parse_table, Layout};
use crate::model_file::ModelFile;
use crate::scenario::{apply_set, load, Scenario, BUILTIN};
use proptest::prelude::*;

const MODEL: &str = r#"{"state_dim": 2, "control_dim": 1, "kernel": {"type": "rbf", "lengthscales": [0.7, 1.3], "variance": 1.5},
 "A": [[1.0, 0.1], [0.1, 0.8]], "B": [[1.0, 0.2], [0.2, 0.5]], "noise_sigma": 0.1, "prior_mean": "zero",
 "data": {"x": [[0.1, 0.2], [0.3, 0.1]], "u": [[0.5], [0.1]], "xdot": [[0.2, -0.4], [0.1, 0.0]]}}"#;
const BARRIER: &str = r#"{"type": "circle_heading", "center": [-1.1667, -1.5], "radius": 0.7906, "q1": 0.7, "q2": 0.3, "relative_degree": 1, "alpha": 5.0}"#;
const EXPR_BARRIER: &str = r#"{"type": "expression", "state": ["x", "y", "theta"], "params": {"r": 0.5, "c": 1.0},
 "h": "(x - c)^2 + (y + 1)^2 - r^2 + 0.1*cos(theta - atan2(y + 1, x - c)) - sqrt(abs(x*y)) / max(exp(y), 1)", "relative_degree": 2, "k_alpha": [1.0, 3.0]}"#;
const EXPR_MODEL: &str = r#"{"state_dim": 2, "control_dim": 1, "kernel": {"type": "rbf", "lengthscales": [0.7, 1.3], "variance": 1.5},
 "A": [[1.0, 0.1], [0.1, 0.8]], "B": [[1.0, 0.2], [0.2, 0.5]], "noise_sigma": 0.1,
 "prior_mean": {"type": "expression", "state": ["theta", "omega"], "control": ["u"], "params": {"l": 2.0},
                "f": ["omega", "-10/l*sin(theta)"], "g": [["0"], ["1/l^2"]], "angles": ["theta"]},
 "data": {"x": [[0.1, 0.2], [0.3, 0.1]], "u": [[0.5], [0.1]], "xdot": [[0.2, -0.4], [0.1, 0.0]]}}"#;
const EXPR_SCENARIO: &str = include_str!("../tests/data/pendulum-safe-expression.toml");
const CSV: &str = "x1,x2,u1,xdot1,xdot2\n0.1,0.2,0.5,0.2,-0.4\n0.3,0.1,0.1,0.1,0.0\n";

/// A mutation of `base`: byte-level edits at random positions.
fn mutated(base: &'static str) -> impl Strategy<Value = String> {
    prop::collection::vec((any::<prop::sample::Index>(), 0u8..3, any::<char>()), 1..6).prop_map(
        move |edits| {
            let mut chars: Vec<char> = base.chars().collect();
            for (idx, op, c) in edits {
                if chars.is_empty() {
                    chars.push(c);
                    continue;
                }
                let i = idx.index(chars.len());
                match op {
                    0 => chars[i] = c,
                    1 => chars.insert(i, c),
                    _ => {
                        chars.remove(i);
                    }
                }
            }
            chars.into_iter().collect()
        },
    )
}

fn one_line<T>(r: crate::error::Result<T>) -> bool {
    match r {
        Ok(_) => true,
        Err(e) => !format!("{e:#}").trim().is_empty(),
    }
}

fn model(text: &str) -> crate::error::Result<()> {
    let f = ModelFile::parse(text, "m.json")?;
    f.to_model()?;
    Ok(())
}

fn barrier(text: &str) -> crate::error::Result<()> {
    let b = BarrierSpec::parse(text, "b.json")?.build()?;
    // evaluate what parsed: values, gradients and Hessians at a few points
    let n = b.state_dim();
    let (mut g, mut h) = (vec![0.0; n], vec![0.0; n * n]);
    let mut d = vec![num_dual::Dual64::from(0.0); n];
    let mut hd = vec![num_dual::HyperDual64::from(0.0); n];
    for x in [vec![0.0; n], vec![1.0; n], vec![-2.5; n]] {
        b.value(&x);
        b.gradient(&x, &mut g, &mut d);
        b.hessian(&x, &mut g, &mut h, &mut hd);
    }
    let _ = b.take_error();
    Ok(())
}

fn csv(text: &str) -> crate::error::Result<()> {
    let header = expected_header(Layout::Derivatives, 2, 1)?;
    parse_table(text, "d.csv", &header)?;
    Ok(())
}

fn scenario(text: &str) -> crate::error::Result<()> {
    let s: Scenario = toml::from_str(text).map_err(|e| crate::err!("{e}"))?;
    crate::scenario::validate(&s)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2000, ..ProptestConfig::default() })]

    #[test]
    fn model_reader_never_panics(t in mutated(MODEL)) {
        prop_assert!(one_line(model(&t)));
    }

    #[test]
    fn barrier_reader_never_panics(t in mutated(BARRIER)) {
        prop_assert!(one_line(barrier(&t)));
    }

    #[test]
    fn expression_barrier_reader_never_panics(t in mutated(EXPR_BARRIER)) {
        prop_assert!(one_line(barrier(&t)));
    }

    #[test]
    fn expression_model_reader_never_panics(t in mutated(EXPR_MODEL)) {
        prop_assert!(one_line(model(&t)));
    }

    #[test]
    fn expression_scenario_reader_never_panics(t in mutated(EXPR_SCENARIO)) {
        prop_assert!(one_line(scenario(&t)));
    }

    #[test]
    fn csv_reader_never_panics(t in mutated(CSV)) {
        prop_assert!(one_line(csv(&t)));
    }

    #[test]
    fn scenario_reader_never_panics(
        (i, t) in (0..BUILTIN.len()).prop_flat_map(|i| (Just(i), mutated(BUILTIN[i].1)))
    ) {
        // the mutated text of built-in `i`, parsed and validated
        prop_assert!(one_line(scenario(&t)), "{}", BUILTIN[i].0);
    }

    #[test]
    fn arbitrary_text_never_panics(t in "\\PC{0,200}") {
        prop_assert!(one_line(model(&t)));
        prop_assert!(one_line(barrier(&t)));
        prop_assert!(one_line(csv(&t)));
        let _ = scenario(&t);
    }

    #[test]
    fn overrides_never_panic(key in "[a-z_.0-9]{0,30}", value in "\\PC{0,20}") {
        for (name, _) in BUILTIN {
            let _ = load(name, &[format!("{key}={value}")]);
        }
        let mut table: toml::Table = BUILTIN[0].1.parse().unwrap();
        let _ = apply_set(&mut table, &format!("{key}={value}"));
    }
}
