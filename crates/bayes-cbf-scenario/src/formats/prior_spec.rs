//! The `prior_mean` field of a model file, the `--prior-mean` option and a
//! scenario's `[system]`: `"zero"`,
//! `{"type": "pendulum", "mass": .., "length": .., "gravity": ..}`,
//! `{"type": "ackermann", "wheelbase": ..}` or
//! `{"type": "expression", "state": [..], "control": [..], "params": {..},
//! "f": [..], "g": [[..], ..], "angles": [..]}` (see `interfaces.md`). A
//! pendulum's keys left out take `mass` 1, `length` 1 and `gravity` 10, an
//! Ackermann vehicle's `wheelbase` 1, as the bare names `"pendulum"` and
//! `"ackermann"` do. Errors name the key, not the field holding the
//! description (the caller adds that: `gp.prior_mean`, `[system]`, ...).

use super::params::Params;
use crate::bail;
use crate::error::{Context, Result};
use bayes_cbf::gp::PriorMean;
use bayes_cbf::systems::{Ackermann, DynSystem, ExpressionSystem, Pendulum};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use std::sync::Arc;

/// A system written as expressions (interfaces.md, "Expressions").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SystemExpression {
    /// State names; taken from the scenario's system when absent (a prior
    /// mean inside a scenario).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub state: Option<Vec<String>>,
    /// Control names, likewise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub control: Option<Vec<String>>,
    /// Named constants.
    #[serde(default, skip_serializing_if = "Params::is_empty")]
    pub params: Params,
    /// `f(x)`, one expression per state.
    pub f: Vec<String>,
    /// `g(x)`, one row per state of one expression per control.
    pub g: Vec<Vec<String>>,
    /// States wrapped to `[-π, π)`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub angles: Vec<String>,
}

/// State and control names of a system.
pub type SystemNames = (Vec<String>, Vec<String>);

fn strings(v: &[&str]) -> Vec<String> {
    v.iter().map(|s| s.to_string()).collect()
}

impl SystemExpression {
    /// Builds the system; `names` supplies the state and control names the
    /// expression leaves out.
    pub fn build(&self, names: Option<&SystemNames>) -> Result<ExpressionSystem> {
        let (state, control) = match (&self.state, &self.control, names) {
            (Some(s), Some(c), _) => (s.clone(), c.clone()),
            (s, c, Some((ns, nc))) => (
                s.clone().unwrap_or_else(|| ns.clone()),
                c.clone().unwrap_or_else(|| nc.clone()),
            ),
            (None, _, None) => bail!("an expression system needs \"state\" (the state names)"),
            (_, None, None) => {
                bail!("an expression system needs \"control\" (the control names)")
            }
        };
        if let Some((ns, nc)) = names {
            if (state.len(), control.len()) != (ns.len(), nc.len()) {
                bail!(
                    "{} states and {} controls, the system has {} and {}",
                    state.len(),
                    control.len(),
                    ns.len(),
                    nc.len()
                );
            }
        }
        let params = self.params.pairs();
        Ok(ExpressionSystem::new(
            &state,
            &control,
            &params,
            &self.f,
            &self.g,
            &self.angles,
        )?)
    }
}

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
    /// `f` and `g` written as expressions.
    Expression(SystemExpression),
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
        Err(format!("invalid {field} = {v}: must be finite and > 0"))
    }
}

impl TryFrom<Value> for PriorSpec {
    type Error = String;

    fn try_from(v: Value) -> Result<Self, String> {
        let ty =
            match &v {
                Value::String(s) => s.clone(),
                Value::Object(o) => match o.get("type") {
                    Some(Value::String(s)) => s.clone(),
                    Some(other) => return Err(format!("type must be a string, got {other}")),
                    None => return Err(
                        "an object needs a \"type\" key (zero, pendulum, ackermann or expression)"
                            .into(),
                    ),
                },
                other => {
                    return Err(format!(
                        "expected \"zero\" or an object with a \"type\", got {other}"
                    ))
                }
            };
        let is_obj = v.is_object();
        let spec = match ty.as_str() {
            "zero" => {
                if is_obj {
                    ZeroFields::deserialize(&v).map_err(|e| e.to_string())?;
                }
                PriorSpec::Zero
            }
            "pendulum" if is_obj => {
                let p = PendulumFields::deserialize(&v).map_err(|e| format!("pendulum: {e}"))?;
                positive("mass", p.mass)?;
                positive("length", p.length)?;
                if !p.gravity.is_finite() {
                    return Err(format!("invalid gravity = {}: must be finite", p.gravity));
                }
                PriorSpec::Pendulum { mass: p.mass, length: p.length, gravity: p.gravity }
            }
            "ackermann" if is_obj => {
                let a = AckermannFields::deserialize(&v).map_err(|e| format!("ackermann: {e}"))?;
                positive("wheelbase", a.wheelbase)?;
                PriorSpec::Ackermann { wheelbase: a.wheelbase }
            }
            "expression" if is_obj => {
                let mut o = v.as_object().cloned().unwrap_or_default();
                o.remove("type");
                let e = SystemExpression::deserialize(Value::Object(o))
                    .map_err(|e| format!("expression: {e}"))?;
                PriorSpec::Expression(e)
            }
            "pendulum" => PriorSpec::Pendulum { mass: 1.0, length: 1.0, gravity: 10.0 },
            "ackermann" => PriorSpec::Ackermann { wheelbase: 1.0 },
            other => {
                return Err(format!(
                    "unknown type \"{other}\": expected \"zero\", \"pendulum\", \"ackermann\" or \"expression\" (an object with f and g)"
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
            PriorSpec::Expression(e) => {
                let mut v = serde_json::to_value(e).unwrap_or(Value::Null);
                if let Value::Object(o) = &mut v {
                    o.insert("type".into(), json!("expression"));
                }
                v
            }
        }
    }
}

impl PriorSpec {
    /// The system, `None` for the zero mean; `names` supplies the state and
    /// control names an expression leaves out (the scenario's system).
    pub fn to_system(&self, names: Option<&SystemNames>) -> Result<Option<Arc<dyn DynSystem>>> {
        Ok(match self {
            PriorSpec::Zero => None,
            PriorSpec::Pendulum {
                mass,
                length,
                gravity,
            } => Some(Arc::new(Pendulum {
                mass: *mass,
                length: *length,
                gravity: *gravity,
            })),
            PriorSpec::Ackermann { wheelbase } => Some(Arc::new(Ackermann {
                wheelbase: *wheelbase,
            })),
            PriorSpec::Expression(e) => Some(Arc::new(e.build(names)?)),
        })
    }

    /// The library's prior mean for this specification (an expression
    /// must name its states and controls).
    pub fn to_prior(&self) -> Result<PriorMean> {
        self.to_prior_in(None)
    }

    /// The prior mean, with the state and control names of the system it
    /// belongs to.
    pub fn to_prior_in(&self, names: Option<&SystemNames>) -> Result<PriorMean> {
        Ok(match self.to_system(names).context("prior_mean")? {
            None => PriorMean::Zero,
            Some(s) => PriorMean::System(s),
        })
    }

    /// The same system written as an expression (the built-ins restated in
    /// the expression language; an expression is returned as it is, the
    /// zero mean as `None`).
    pub fn to_expression(&self) -> Option<SystemExpression> {
        let (state, control) = self.names()?;
        Some(match self {
            PriorSpec::Zero => return None,
            PriorSpec::Pendulum {
                mass,
                length,
                gravity,
            } => SystemExpression {
                state: Some(state),
                control: Some(control),
                params: Params::of(&[("m", *mass), ("l", *length), ("g", *gravity)]),
                f: strings(&["omega", "-g/l*sin(theta)"]),
                g: vec![strings(&["0"]), strings(&["1/(m*l)"])],
                angles: strings(&["theta"]),
            },
            PriorSpec::Ackermann { wheelbase } => SystemExpression {
                state: Some(state),
                control: Some(control),
                params: Params::of(&[("L", *wheelbase)]),
                f: strings(&["0", "0", "0"]),
                g: vec![
                    strings(&["cos(theta)", "0"]),
                    strings(&["sin(theta)", "0"]),
                    strings(&["0", "1/L"]),
                ],
                angles: strings(&["theta"]),
            },
            PriorSpec::Expression(e) => e.clone(),
        })
    }

    /// State and control names: an expression's own, and for the built-in
    /// systems `theta, omega; u` (pendulum) and `x, y, theta; v, z`
    /// (Ackermann). `None` for the zero mean or an expression without
    /// names.
    pub fn names(&self) -> Option<SystemNames> {
        match self {
            PriorSpec::Zero => None,
            PriorSpec::Pendulum { .. } => Some((strings(&["theta", "omega"]), strings(&["u"]))),
            PriorSpec::Ackermann { .. } => {
                Some((strings(&["x", "y", "theta"]), strings(&["v", "z"])))
            }
            PriorSpec::Expression(e) => Some((e.state.clone()?, e.control.clone()?)),
        }
    }

    /// State components that are angles in the prior's system (pendulum
    /// `[0]`, Ackermann `[2]`, an expression's `angles`, none for the zero
    /// mean).
    pub fn angle_indices(&self) -> Vec<usize> {
        match self {
            PriorSpec::Zero => Vec::new(),
            PriorSpec::Pendulum { .. } => vec![0],
            PriorSpec::Ackermann { .. } => vec![2],
            PriorSpec::Expression(e) => match &e.state {
                Some(state) => {
                    let mut v: Vec<usize> = e
                        .angles
                        .iter()
                        .filter_map(|a| state.iter().position(|s| s == a))
                        .collect();
                    v.sort_unstable();
                    v.dedup();
                    v
                }
                None => Vec::new(),
            },
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
            if let Ok(v) = serde_json::from_str::<Value>(t) {
                let kind = match v {
                    Value::Array(_) => "an array",
                    Value::Number(_) => "a number",
                    Value::Bool(_) => "a boolean",
                    _ => "null",
                };
                bail!("--prior-mean '{arg}' is JSON of another kind ({kind}): expected a prior name (zero, pendulum, ackermann) or an object such as {{\"type\": \"pendulum\", \"mass\": 1, \"length\": 1, \"gravity\": 10}}");
            }
            bail!("--prior-mean '{arg}' is neither JSON, a known prior name (zero, pendulum, ackermann) nor an existing file");
        }
        let text = crate::io::read_input_text(path)
            .with_context(|| format!("--prior-mean: cannot read '{}'", path.display()))?;
        Self::from_json_text(&text)
            .with_context(|| format!("--prior-mean file '{}'", path.display()))
    }

    fn from_json_text(text: &str) -> Result<Self> {
        let v: Value = crate::parse::json_value(text).map_err(|e| {
            crate::err!(
                "not valid JSON: {}",
                crate::parse::json_error_message(text, &e)
            )
        })?;
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
        assert!(e.to_string().contains("unknown type \"cartpole\""));
        let e = serde_json::from_str::<PriorSpec>(r#"{"type": "pendulum", "mas": 1}"#).unwrap_err();
        assert!(e.to_string().contains("unknown field `mas`"), "{e}");
        let e = serde_json::from_str::<PriorSpec>(r#"{"type": "ackermann", "wheelbase": -1}"#)
            .unwrap_err();
        assert!(e.to_string().contains("invalid wheelbase = -1"), "{e}");
        // keys left out take the documented values
        assert_eq!(
            serde_json::from_str::<PriorSpec>(r#"{"type": "pendulum", "mass": 2}"#).unwrap(),
            PriorSpec::Pendulum {
                mass: 2.0,
                length: 1.0,
                gravity: 10.0
            }
        );
        assert_eq!(PriorSpec::from_arg("zero").unwrap(), PriorSpec::Zero);
        assert_eq!(
            PriorSpec::from_arg(r#"{"type":"ackermann","wheelbase":8}"#).unwrap(),
            PriorSpec::Ackermann { wheelbase: 8.0 }
        );
        assert!(PriorSpec::from_arg("/no/such/file.json").is_err());
        let e = PriorSpec::from_arg("[1,2]").unwrap_err().to_string();
        assert!(e.contains("JSON of another kind (an array)"), "{e}");
    }
}
