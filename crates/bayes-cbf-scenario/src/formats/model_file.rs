//! The model file (`model.json`, see `interfaces.md`): parsing with unknown
//! keys rejected, validation with errors that name the field, and
//! conversion to and from [`Mvgp`].

use crate::error::{check_vector, Context, Result};
use crate::input_map_spec::{from_input_map, to_input_map, FeatureSpec};
use crate::prior_spec::PriorSpec;
use crate::{bail, err};
use bayes_cbf::gp::{InputMap, Kernel, Mvgp, MvgpHyper, Rbf};
use nalgebra::DMatrix;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use std::path::Path;

/// Scalar kernel `k0` of the model file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "lowercase", deny_unknown_fields)]
pub enum KernelSpec {
    /// `k0(x, x') = variance · exp(−½ Σ_i (x_i − x'_i)² / lengthscales_i²)`.
    Rbf {
        /// ARD lengthscales `ℓ_i > 0`, one per kernel input.
        lengthscales: Vec<f64>,
        /// Output scale `s > 0`.
        variance: f64,
    },
}

/// Training data `(x_j, u_j, ẋ_j)` as arrays of rows.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DataSpec {
    /// States, `k` rows of `n`.
    #[serde(default)]
    pub x: Vec<Vec<f64>>,
    /// Controls, `k` rows of `m`.
    #[serde(default)]
    pub u: Vec<Vec<f64>>,
    /// State derivatives, `k` rows of `n`.
    #[serde(default)]
    pub xdot: Vec<Vec<f64>>,
}

/// A whole model file: `vec F(x) ~ GP(vec M0(x), B k0(x,x') ⊗ A)` with noise
/// `noise_sigma² A` and its training data (paper, Sec. IV).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[allow(non_snake_case)]
pub struct ModelFile {
    /// State dimension `n`.
    #[serde(deserialize_with = "crate::parse::whole_number")]
    pub state_dim: usize,
    /// Control dimension `m`.
    #[serde(deserialize_with = "crate::parse::whole_number")]
    pub control_dim: usize,
    /// Scalar kernel `k0`.
    pub kernel: KernelSpec,
    /// Row covariance `A` (`n × n`, symmetric positive definite).
    pub A: Vec<Vec<f64>>,
    /// Column covariance `B` (`(1+m) × (1+m)`, symmetric positive definite).
    pub B: Vec<Vec<f64>>,
    /// Noise scale `σ > 0`.
    pub noise_sigma: f64,
    /// Prior mean `M0`.
    #[serde(default)]
    pub prior_mean: PriorSpec,
    /// What the kernel sees: state indices or `{"cos": i}` / `{"sin": i}`
    /// features (identity when absent).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub input_map: Option<Vec<FeatureSpec>>,
    /// Rows of `F` known exactly from the prior mean (only the others are
    /// learned; `Mvgp::with_known_rows`).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub known_rows: Vec<usize>,
    /// Training data (may be empty: the prior only).
    #[serde(default)]
    pub data: DataSpec,
}

/// Checks one top-level field on its own, so that a type error can be
/// reported with the name of the field it is in.
fn check_field(key: &str, v: &Value) -> Result<(), String> {
    use crate::parse::type_error as de;
    match key {
        "state_dim" | "control_dim" => crate::parse::whole_number_error(v),
        "kernel" => de::<KernelSpec>(v),
        "A" | "B" => de::<Vec<Vec<f64>>>(v),
        "noise_sigma" => de::<f64>(v),
        "prior_mean" => de::<PriorSpec>(v),
        "input_map" => de::<Option<Vec<FeatureSpec>>>(v),
        "data" => de::<DataSpec>(v),
        "known_rows" => de::<Vec<usize>>(v),
        _ => Err(format!(
            "unknown key \"{key}\" (expected state_dim, control_dim, kernel, A, B, noise_sigma, prior_mean, input_map, known_rows, data)"
        )),
    }
}

/// Converts an array of rows into a `rows × cols` matrix, naming `field`.
fn to_matrix(
    field: &str,
    m: &[Vec<f64>],
    rows: usize,
    cols: usize,
    what: &str,
) -> Result<DMatrix<f64>> {
    if m.len() != rows {
        bail!("{field} has {} rows, expected {rows} ({what})", m.len());
    }
    check_rows(field, m, cols, what)?;
    Ok(DMatrix::from_fn(rows, cols, |i, j| m[i][j]))
}

/// Checks that every row of `field` has `width` finite entries (`what`
/// names the width).
fn check_rows(field: &str, rows: &[Vec<f64>], width: usize, what: &str) -> Result<()> {
    for (i, r) in rows.iter().enumerate() {
        check_vector(&format!("{field}[{i}]"), r, width, what)?;
    }
    Ok(())
}

fn rows_of(m: &DMatrix<f64>) -> Vec<Vec<f64>> {
    (0..m.nrows())
        .map(|i| m.row(i).iter().copied().collect())
        .collect()
}

impl ModelFile {
    /// Parses model-file text; `name` labels errors (usually the path).
    pub fn parse(text: &str, name: &str) -> Result<Self> {
        if text.trim().is_empty() {
            bail!("model file '{name}' is empty");
        }
        let value: Value = crate::parse::json_value(text).map_err(|e| {
            if e.is_eof() {
                err!("model file '{name}' is truncated or incomplete JSON: {e}")
            } else {
                err!(
                    "model file '{name}' is not valid JSON: {}",
                    crate::parse::json_error_message(text, &e)
                )
            }
        })?;
        let obj = value.as_object().ok_or_else(|| {
            err!(
                "model file '{name}' must hold a JSON object, not {}",
                kind(&value)
            )
        })?;
        match ModelFile::deserialize(&value) {
            Ok(m) => Ok(m),
            Err(e) => {
                for (key, v) in obj {
                    if let Err(fe) = check_field(key, v) {
                        // messages that already name the field need no prefix
                        if key.len() > 1 && fe.contains(key.as_str()) {
                            bail!("model file '{name}': {fe}");
                        }
                        bail!("model file '{name}': field {key}: {fe}");
                    }
                }
                bail!("model file '{name}': {e}")
            }
        }
    }

    /// Reads and parses a model file.
    pub fn load(path: &Path) -> Result<Self> {
        let text = crate::io::read_input_text(path)
            .with_context(|| format!("cannot read model file '{}'", path.display()))?;
        Self::parse(&text, &path.display().to_string())
    }

    /// The kernel input map.
    pub fn input_map(&self) -> InputMap {
        to_input_map(self.input_map.as_deref())
    }

    /// Validates every field and builds the model with its data factorised.
    #[allow(non_snake_case)]
    pub fn to_model(&self) -> Result<Mvgp> {
        let (n, m) = (self.state_dim, self.control_dim);
        if n == 0 {
            bail!("invalid state_dim = 0: must be ≥ 1");
        }
        if m == 0 {
            bail!("invalid control_dim = 0: must be ≥ 1");
        }
        bayes_cbf::gp::check_dims(n, m)?;
        let input_map = self.input_map();
        input_map.validate(n)?;
        let d = input_map.output_dim(n);
        let KernelSpec::Rbf {
            lengthscales,
            variance,
        } = &self.kernel;
        if lengthscales.len() != d {
            bail!(
                "kernel.lengthscales has {} entries, expected {d} (the kernel input dimension{})",
                lengthscales.len(),
                if self.input_map.is_some() {
                    ", the length of input_map"
                } else {
                    ", state_dim"
                }
            );
        }
        let kernel = Rbf::new(lengthscales.clone(), *variance)?;
        let A = to_matrix("A", &self.A, n, n, "A is n × n with n = state_dim")?;
        let B = to_matrix(
            "B",
            &self.B,
            m + 1,
            m + 1,
            "B is (1+m) × (1+m) with m = control_dim",
        )?;
        let hyper = MvgpHyper {
            kernel,
            A,
            B,
            sigma: self.noise_sigma,
        };
        let mut model = Mvgp::new(n, m, hyper, self.prior_mean.to_prior()?, input_map)?;
        if !self.known_rows.is_empty() {
            model = model.with_known_rows(&self.known_rows)?;
            if self.prior_mean == PriorSpec::Zero {
                log::warn!(
                    "known_rows: rows {:?} of F are taken from prior_mean, which is zero: \
                     they are declared exactly 0 and never learned; give a prior_mean that \
                     has those rows (as p' = v)",
                    self.known_rows
                );
            }
        }
        let (xs, us, xdot) = self.flat_data()?;
        if !xs.is_empty() {
            model.set_data(&xs, &us, &xdot)?;
        }
        Ok(model)
    }

    /// The data as row-major flat arrays, checking every row's length.
    pub fn flat_data(&self) -> Result<(Vec<f64>, Vec<f64>, Vec<f64>)> {
        let (n, m) = (self.state_dim, self.control_dim);
        let k = self.data.x.len();
        for (field, rows, width, dim) in [
            ("data.x", &self.data.x, n, "state_dim"),
            ("data.u", &self.data.u, m, "control_dim"),
            ("data.xdot", &self.data.xdot, n, "state_dim"),
        ] {
            if rows.len() != k {
                bail!(
                    "{field} has {} rows but data.x has {k}: x, u and xdot need one row per sample",
                    rows.len()
                );
            }
            check_rows(field, rows, width, dim)?;
        }
        let flat = |rows: &Vec<Vec<f64>>| rows.iter().flatten().copied().collect::<Vec<f64>>();
        Ok((
            flat(&self.data.x),
            flat(&self.data.u),
            flat(&self.data.xdot),
        ))
    }

    /// The model file describing `model` (hyperparameters and data).
    pub fn from_model(model: &Mvgp, prior: &PriorSpec) -> Self {
        let (n, m) = (model.state_dim(), model.control_dim());
        let h = model.hyper();
        let rows = |v: &[f64], w: usize| v.chunks(w).map(<[f64]>::to_vec).collect::<Vec<_>>();
        let controls = model.controls();
        let input_map = from_input_map(model.input_map());
        debug_assert_eq!(h.kernel.input_dim(), model.input_map().output_dim(n));
        ModelFile {
            state_dim: n,
            control_dim: m,
            kernel: KernelSpec::Rbf {
                lengthscales: h.kernel.lengthscales().to_vec(),
                variance: h.kernel.variance(),
            },
            A: rows_of(&h.A),
            B: rows_of(&h.B),
            noise_sigma: h.sigma,
            prior_mean: prior.clone(),
            input_map,
            known_rows: model.known_rows().to_vec(),
            data: DataSpec {
                x: rows(model.xs(), n),
                u: rows(&controls, m),
                xdot: rows(model.xdot(), n),
            },
        }
    }

    /// Serialises to pretty JSON with a trailing newline.
    pub fn to_json(&self) -> Result<String> {
        let mut s = serde_json::to_string_pretty(self).context("cannot serialise the model")?;
        s.push('\n');
        Ok(s)
    }
}

fn kind(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const GOOD: &str = r#"{
      "state_dim": 2, "control_dim": 1,
      "kernel": {"type": "rbf", "lengthscales": [0.7, 1.3], "variance": 1.5},
      "A": [[1.0, 0.1], [0.1, 0.8]], "B": [[1.0, 0.2], [0.2, 0.5]],
      "noise_sigma": 0.1, "prior_mean": "zero",
      "data": {"x": [[0.1, 0.2]], "u": [[0.5]], "xdot": [[0.2, -0.4]]}
    }"#;

    fn err(text: &str) -> String {
        match ModelFile::parse(text, "m.json").and_then(|m| m.to_model().map(|_| ())) {
            Ok(()) => panic!("accepted: {text}"),
            Err(e) => format!("{e:#}"),
        }
    }

    #[test]
    fn interface_example_round_trips() {
        let mf = ModelFile::parse(GOOD, "m.json").unwrap();
        let model = mf.to_model().unwrap();
        assert_eq!(model.len(), 1);
        let back = ModelFile::from_model(&model, &mf.prior_mean);
        assert_eq!(back, mf);
        let again = ModelFile::parse(&back.to_json().unwrap(), "m.json").unwrap();
        assert_eq!(again, mf);
    }

    #[test]
    fn errors_name_the_field() {
        let with = |from: &str, to: &str| GOOD.replacen(from, to, 1);
        assert!(err(&with(
            "\"noise_sigma\": 0.1",
            "\"noise_sigma\": 0.1, \"extra\": 1"
        ))
        .contains("extra"));
        assert!(err(&with("[0.7, 1.3]", "[0.7]")).contains("kernel.lengthscales"));
        assert!(err(&with("[0.7, 1.3]", "[0.7, \"a\"]")).contains("field kernel"));
        assert!(err(&with("\"rbf\"", "\"matern\"")).contains("matern"));
        assert!(err(&with("[0.1, 0.8]]", "[0.1, 0.8], [0.0, 0.0]]")).contains("A has 3 rows"));
        assert!(err(&with("[0.2, 0.5]]", "[0.3, 0.5]]")).contains("B is not symmetric"));
        assert!(err(&with("\"u\": [[0.5]]", "\"u\": [[0.5, 1.0]]")).contains("data.u[0]"));
        assert!(err(&GOOD[..GOOD.len() / 2]).contains("truncated"));
        assert!(err("  ").contains("empty"));
        assert!(err("[1, 2]").contains("JSON object"));
        assert!(err(&with("\"state_dim\": 2", "\"state_dim\": 2.5")).contains("field state_dim"));
        // a whole float is a dimension
        let m = ModelFile::parse(&with("\"state_dim\": 2", "\"state_dim\": 2.0"), "m").unwrap();
        assert_eq!(m.state_dim, 2);
    }
}
