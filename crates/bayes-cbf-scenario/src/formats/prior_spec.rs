//! The `prior_mean` field of a model file and the `--prior-mean` option:
//! `"zero"`, `{"type": "pendulum", "mass": .., "length": .., "gravity": ..}`
//! or `{"type": "ackermann", "wheelbase": ..}` (see `interfaces.md`).

use crate::bail;
use crate::error::{Context, Result};
use bayes_cbf::gp::PriorMean;
use bayes_cbf::systems::{Ackermann, Pendulum};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use std::sync::Arc;

/// Prior mean `M0(x)` of `F(x)` as written in files.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(try_from = "Value", into = "Value")]
pub enum PriorSpec {
    /// `M0(x) = 0`.
    #[default]
    Zero,
    /// The pendulum of Eq. (31): `f = [ω, −(g/l) sin θ]`, `g = [0, 1/(m l)]`.
    Pendulum {
        /// Mass `m` (kg), > 0.
        mass: f64,
        /// Length `l` (m), > 0.
        length: f64,
        /// Gravity `g` (m/s²), finite.
        gravity: f64,
    },
    /// The Ackermann vehicle of Eq. (32) with wheelbase `L` > 0.
    Ackermann {
        /// Wheelbase `L` (m).
        wheelbase: f64,
    },
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PendulumFields {
    #[serde(rename = "type")]
    _type: String,
    #[serde(default = "one")]
    mass: f64,
    #[serde(default = "one")]
    length: f64,
    #[serde(default = "ten")]
    gravity: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct AckermannFields {
    #[serde(rename = "type")]
    _type: String,
    #[serde(default = "one")]
    wheelbase: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ZeroFields {
    #[serde(rename = "type")]
    _type: String,
}

fn one() -> f64 {
    1.0
}

fn ten() -> f64 {
    10.0
}

fn positive(field: &str, v: f64) -> Result<(), String> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(format!(
            "invalid prior_mean.{field} = {v}: must be finite and > 0"
        ))
    }
}

impl TryFrom<Value> for PriorSpec {
    type Error = String;

    fn try_from(v: Value) -> Result<Self, String> {
        let ty = match &v {
            Value::String(s) => s.clone(),
            Value::Object(o) => match o.get("type") {
                Some(Value::String(s)) => s.clone(),
                Some(other) => {
                    return Err(format!("prior_mean.type must be a string, got {other}"))
                }
                None => {
                    return Err(
                        "prior_mean object needs a \"type\" key (pendulum or ackermann)".into(),
                    )
                }
            },
            other => {
                return Err(format!(
                    "prior_mean must be \"zero\" or an object with a \"type\", got {other}"
                ))
            }
        };
        let is_obj = v.is_object();
        let spec = match ty.as_str() {
            "zero" => {
                if is_obj {
                    ZeroFields::deserialize(&v).map_err(|e| format!("prior_mean: {e}"))?;
                }
                PriorSpec::Zero
            }
            "pendulum" if is_obj => {
                let p = PendulumFields::deserialize(&v).map_err(|e| format!("prior_mean: {e}"))?;
                positive("mass", p.mass)?;
                positive("length", p.length)?;
                if !p.gravity.is_finite() {
                    return Err(format!("invalid prior_mean.gravity = {}: must be finite", p.gravity));
                }
                PriorSpec::Pendulum { mass: p.mass, length: p.length, gravity: p.gravity }
            }
            "ackermann" if is_obj => {
                let a = AckermannFields::deserialize(&v).map_err(|e| format!("prior_mean: {e}"))?;
                positive("wheelbase", a.wheelbase)?;
                PriorSpec::Ackermann { wheelbase: a.wheelbase }
            }
            "pendulum" => PriorSpec::Pendulum { mass: 1.0, length: 1.0, gravity: 10.0 },
            "ackermann" => PriorSpec::Ackermann { wheelbase: 1.0 },
            other => {
                return Err(format!(
                    "unknown prior_mean type \"{other}\": expected \"zero\", \"pendulum\" or \"ackermann\""
                ))
            }
        };
        Ok(spec)
    }
}

impl From<PriorSpec> for Value {
    fn from(p: PriorSpec) -> Value {
        match p {
            PriorSpec::Zero => json!("zero"),
            PriorSpec::Pendulum {
                mass,
                length,
                gravity,
            } => {
                json!({"type": "pendulum", "mass": mass, "length": length, "gravity": gravity})
            }
            PriorSpec::Ackermann { wheelbase } => {
                json!({"type": "ackermann", "wheelbase": wheelbase})
            }
        }
    }
}

impl PriorSpec {
    /// The library's prior mean for this specification.
    pub fn to_prior(&self) -> PriorMean {
        match *self {
            PriorSpec::Zero => PriorMean::Zero,
            PriorSpec::Pendulum {
                mass,
                length,
                gravity,
            } => PriorMean::System(Arc::new(Pendulum {
                mass,
                length,
                gravity,
            })),
            PriorSpec::Ackermann { wheelbase } => {
                PriorMean::System(Arc::new(Ackermann { wheelbase }))
            }
        }
    }

    /// State components that are angles in the prior's system (pendulum
    /// `[0]`, Ackermann `[2]`, none for the zero mean).
    pub fn angle_indices(&self) -> Vec<usize> {
        match self {
            PriorSpec::Zero => Vec::new(),
            PriorSpec::Pendulum { .. } => vec![0],
            PriorSpec::Ackermann { .. } => vec![2],
        }
    }

    /// Parses the `--prior-mean` argument: inline JSON (`'"zero"'`,
    /// `'{"type": "pendulum", ...}'`), a bare name (`zero`, `pendulum`,
    /// `ackermann`), or the path of a file holding the JSON.
    pub fn from_arg(arg: &str) -> Result<Self> {
        let t = arg.trim();
        if t.starts_with('{') || t.starts_with('"') {
            return Self::from_json_text(t).context("--prior-mean");
        }
        if matches!(t, "zero" | "pendulum" | "ackermann") {
            return Self::try_from(Value::String(t.to_string()))
                .map_err(crate::error::Error::Input);
        }
        let path = std::path::Path::new(t);
        if !path.is_file() {
            bail!("--prior-mean '{arg}' is neither JSON, a known prior name (zero, pendulum, ackermann) nor an existing file");
        }
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("--prior-mean: cannot read '{}'", path.display()))?;
        Self::from_json_text(&text)
            .with_context(|| format!("--prior-mean file '{}'", path.display()))
    }

    fn from_json_text(text: &str) -> Result<Self> {
        let v: Value =
            serde_json::from_str(text).map_err(|e| crate::err!("not valid JSON: {e}"))?;
        Self::try_from(v).map_err(crate::error::Error::Input)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_errors() {
        for p in [
            PriorSpec::Zero,
            PriorSpec::Pendulum {
                mass: 2.0,
                length: 0.5,
                gravity: 9.81,
            },
            PriorSpec::Ackermann { wheelbase: 12.0 },
        ] {
            let s = serde_json::to_string(&p).unwrap();
            assert_eq!(serde_json::from_str::<PriorSpec>(&s).unwrap(), p);
        }
        let e = serde_json::from_str::<PriorSpec>(r#"{"type": "cartpole"}"#).unwrap_err();
        assert!(e
            .to_string()
            .contains("unknown prior_mean type \"cartpole\""));
        let e = serde_json::from_str::<PriorSpec>(r#"{"type": "pendulum", "mas": 1}"#).unwrap_err();
        assert!(e.to_string().contains("unknown field `mas`"), "{e}");
        let e = serde_json::from_str::<PriorSpec>(r#"{"type": "ackermann", "wheelbase": -1}"#)
            .unwrap_err();
        assert!(e.to_string().contains("prior_mean.wheelbase"));
        assert_eq!(PriorSpec::from_arg("zero").unwrap(), PriorSpec::Zero);
        assert_eq!(
            PriorSpec::from_arg(r#"{"type":"ackermann","wheelbase":8}"#).unwrap(),
            PriorSpec::Ackermann { wheelbase: 8.0 }
        );
        assert!(PriorSpec::from_arg("/no/such/file.json").is_err());
    }
}
