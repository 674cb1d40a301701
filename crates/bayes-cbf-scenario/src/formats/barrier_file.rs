//! Barrier files (`barrier.json`, interfaces.md): parsing and validation.

use super::params::Params;
use crate::bail;
use crate::error::{Context, Result};
use bayes_cbf::barrier::{
    CircleHeading, Disc, DynBarrier, ExpressionBarrier, HalfSpace, PendulumSector,
    PendulumSectorEdge, SectorEdge,
};
use bayes_cbf::warnings::WarnOnce;
use serde::Deserialize;
use std::path::Path;
use std::sync::Arc;

/// Declares [`BarrierSpec`] with the fields every barrier has,
/// `relative_degree`, `alpha` and `k_alpha`, after each variant's own, and
/// `BarrierSpec::order`, which reads them.
macro_rules! barrier_spec {
    ($($(#[$meta:meta])* $variant:ident { $($field:tt)* },)*) => {
        /// One barrier as written in a file.
        #[derive(Debug, Clone, PartialEq, Deserialize, serde::Serialize)]
        #[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
        pub enum BarrierSpec {
            $($(#[$meta])* $variant {
                $($field)*
                /// Relative degree (≥ 1).
                #[serde(deserialize_with = "crate::parse::whole_number")]
                relative_degree: usize,
                /// Gain for relative degree 1.
                #[serde(default, skip_serializing_if = "Option::is_none")]
                alpha: Option<f64>,
                /// Gains for relative degree ≥ 2, one per derivative order.
                #[serde(default, skip_serializing_if = "Option::is_none")]
                k_alpha: Option<Vec<f64>>,
            },)*
        }

        impl BarrierSpec {
            /// `(relative_degree, alpha, k_alpha)`, the fields every variant has.
            fn order(&self) -> (usize, &Option<f64>, &Option<Vec<f64>>) {
                match self {
                    $(BarrierSpec::$variant {
                        relative_degree,
                        alpha,
                        k_alpha,
                        ..
                    })|* => (*relative_degree, alpha, k_alpha),
                }
            }
        }
    };
}

barrier_spec! {
    /// `h = cos(delta) − cos(θ − theta_c)`.
    PendulumSector {
        /// Sector centre (rad).
        theta_c: f64,
        /// Sector half-width (rad).
        delta: f64,
    },
    /// One edge of the sector `theta_c ± delta` as a linear barrier in
    /// `φ = (θ − theta_c) mod 2π`: `h = φ − delta` (`edge = "upper"`) or
    /// `h = 2π − delta − φ` (`edge = "lower"`).
    PendulumSectorEdge {
        /// Sector centre (rad).
        theta_c: f64,
        /// Sector half-width (rad).
        delta: f64,
        /// `"upper"` (`theta_c + delta`) or `"lower"` (`theta_c − delta`).
        edge: EdgeSpec,
    },
    /// Ackermann obstacle with heading term.
    CircleHeading {
        /// Obstacle centre.
        center: [f64; 2],
        /// Obstacle radius.
        radius: f64,
        /// Distance weight.
        q1: f64,
        /// Heading weight.
        q2: f64,
    },
    /// `h = ‖x[indices] − center‖² − radius²`.
    Disc {
        /// State dimension.
        #[serde(deserialize_with = "crate::parse::whole_number")]
        state_dim: usize,
        /// The two plane coordinates.
        indices: [usize; 2],
        /// Centre.
        center: [f64; 2],
        /// Radius.
        radius: f64,
    },
    /// `h = normalᵀx − offset`.
    HalfSpace {
        /// Normal vector.
        normal: Vec<f64>,
        /// Offset.
        offset: f64,
    },
    /// `h` written as an expression over named states (interfaces.md,
    /// "Expressions").
    Expression {
        /// State names; in a scenario, the system's when absent.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        state: Option<Vec<String>>,
        /// Named constants.
        #[serde(default, skip_serializing_if = "Params::is_empty")]
        params: Params,
        /// `h(x)`.
        h: String,
    },
}

/// Whether `v` reads as the barrier field `key`; unknown keys pass (the
/// typed parse lists the known ones).
fn check_field(key: &str, v: &serde_json::Value) -> std::result::Result<(), String> {
    use crate::parse::type_error as de;
    match key {
        "type" | "h" => de::<String>(v),
        "edge" => de::<EdgeSpec>(v),
        "theta_c" | "delta" | "radius" | "q1" | "q2" | "offset" => de::<f64>(v),
        "alpha" => de::<Option<f64>>(v),
        "relative_degree" | "state_dim" => crate::parse::whole_number_error(v),
        "center" => de::<[f64; 2]>(v),
        "indices" => de::<[usize; 2]>(v),
        "normal" => de::<Vec<f64>>(v),
        "k_alpha" => de::<Option<Vec<f64>>>(v),
        "state" => de::<Option<Vec<String>>>(v),
        "params" => de::<Params>(v),
        _ => Ok(()),
    }
}

/// The `edge` of a `pendulum_sector_edge` barrier.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum EdgeSpec {
    /// `theta_c + delta`.
    Upper,
    /// `theta_c − delta`.
    Lower,
}

impl std::str::FromStr for EdgeSpec {
    type Err = crate::Error;
    /// `"upper"` or `"lower"`, as in barrier files.
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "upper" => Ok(EdgeSpec::Upper),
            "lower" => Ok(EdgeSpec::Lower),
            other => bail!("edge: '{other}' is neither 'upper' nor 'lower'"),
        }
    }
}

impl From<EdgeSpec> for SectorEdge {
    fn from(e: EdgeSpec) -> Self {
        match e {
            EdgeSpec::Upper => SectorEdge::Upper,
            EdgeSpec::Lower => SectorEdge::Lower,
        }
    }
}

/// Gains from `alpha` (relative degree 1) or `k_alpha` (≥ 2); either, not
/// both, and as many as the relative degree.
pub fn gains(r: usize, alpha: &Option<f64>, k_alpha: &Option<Vec<f64>>) -> Result<Vec<f64>> {
    match (r, alpha, k_alpha) {
        (0, _, _) => bail!("relative_degree = 0: must be ≥ 1"),
        (1, Some(a), None) => Ok(vec![*a]),
        (1, None, Some(k)) if k.len() == 1 => Ok(k.clone()),
        (1, None, None) => bail!("alpha is required for relative_degree 1"),
        (1, _, _) => bail!("give either alpha or a one-element k_alpha for relative_degree 1"),
        (r, None, Some(k)) => {
            if k.len() != r {
                bail!(
                    "k_alpha has {} entries, expected {r} (one per derivative order of h)",
                    k.len()
                );
            }
            Ok(k.clone())
        }
        (r, Some(_), _) => bail!("alpha is for relative_degree 1; use k_alpha with {r} entries"),
        (r, None, None) => bail!("k_alpha with {r} entries is required for relative_degree {r}"),
    }
}

impl BarrierSpec {
    /// Builds the library barrier, validating every field (an expression
    /// must name its states).
    pub fn build(&self) -> Result<Arc<dyn DynBarrier>> {
        self.build_in(None)
    }

    /// Builds the barrier of a system whose states are named `state` (an
    /// expression without its own names uses them).
    pub fn build_in(&self, state: Option<&[String]>) -> Result<Arc<dyn DynBarrier>> {
        let (r, alpha, k_alpha) = self.order();
        let gains = gains(r, alpha, k_alpha)?;
        Ok(match self {
            BarrierSpec::PendulumSector { theta_c, delta, .. } => {
                Arc::new(PendulumSector::new(*theta_c, *delta, r, gains)?)
            }
            BarrierSpec::PendulumSectorEdge {
                theta_c,
                delta,
                edge,
                ..
            } => Arc::new(PendulumSectorEdge::new(
                *theta_c,
                *delta,
                (*edge).into(),
                r,
                gains,
            )?),
            BarrierSpec::CircleHeading {
                center,
                radius,
                q1,
                q2,
                ..
            } => Arc::new(CircleHeading::new(*center, *radius, *q1, *q2, r, gains)?),
            BarrierSpec::Disc {
                state_dim,
                indices,
                center,
                radius,
                ..
            } => Arc::new(Disc::new(*state_dim, *indices, *center, *radius, r, gains)?),
            BarrierSpec::HalfSpace { normal, offset, .. } => {
                Arc::new(HalfSpace::new(normal.clone(), *offset, r, gains)?)
            }
            BarrierSpec::Expression {
                state: own,
                params,
                h,
                ..
            } => {
                let names: &[String] = match (own, state) {
                    (Some(own), Some(sys)) if own.len() != sys.len() => bail!(
                        "state has {} names, the system {} states",
                        own.len(),
                        sys.len()
                    ),
                    (Some(own), _) => own,
                    (None, Some(sys)) => sys,
                    (None, None) => {
                        bail!("an expression barrier needs \"state\" (the state names)")
                    }
                };
                let barrier = ExpressionBarrier::new(names, &params.pairs(), h, r, gains)?;
                warn_kinks(&barrier);
                Arc::new(barrier)
            }
        })
    }

    /// The same barrier written as an expression over the state names
    /// `state` (the built-ins restated in the expression language; an
    /// expression is returned as it is).
    pub fn to_expression(&self, state: &[String]) -> Result<Self> {
        let name = |i: usize| -> Result<&str> {
            state.get(i).map(String::as_str).ok_or_else(|| {
                crate::err!("state index {i} out of range ({} state names)", state.len())
            })
        };
        let (params, h) = match self {
            BarrierSpec::PendulumSector { theta_c, delta, .. } => (
                Params::of(&[("theta_c", *theta_c), ("delta", *delta)]),
                format!("cos(delta) - cos({} - theta_c)", name(0)?),
            ),
            BarrierSpec::PendulumSectorEdge {
                theta_c,
                delta,
                edge,
                ..
            } => {
                // (θ − θ_c) mod 2π, with its jump at θ_c as the built-in's
                let phi = format!(
                    "(pi + atan2(-sin({0} - theta_c), -cos({0} - theta_c)))",
                    name(0)?
                );
                let h = match edge {
                    EdgeSpec::Upper => format!("{phi} - delta"),
                    EdgeSpec::Lower => format!("2*pi - delta - {phi}"),
                };
                (Params::of(&[("theta_c", *theta_c), ("delta", *delta)]), h)
            }
            BarrierSpec::CircleHeading {
                center,
                radius,
                q1,
                q2,
                ..
            } => {
                let (x, y, th) = (name(0)?, name(1)?, name(2)?);
                (
                    Params::of(&[("cx", center[0]), ("cy", center[1]), ("r", *radius), ("q1", *q1), ("q2", *q2)]),
                    format!("q1*(({x} - cx)^2 + ({y} - cy)^2 - r^2) + q2*cos({th} - atan2({y} - cy, {x} - cx))"),
                )
            }
            BarrierSpec::Disc {
                indices,
                center,
                radius,
                ..
            } => (
                Params::of(&[("cx", center[0]), ("cy", center[1]), ("r", *radius)]),
                format!(
                    "({} - cx)^2 + ({} - cy)^2 - r^2",
                    name(indices[0])?,
                    name(indices[1])?
                ),
            ),
            BarrierSpec::HalfSpace { normal, offset, .. } => {
                let mut terms = Vec::new();
                let mut params = vec![("offset".to_string(), *offset)];
                for (i, w) in normal.iter().enumerate() {
                    terms.push(format!("n{i}*{}", name(i)?));
                    params.push((format!("n{i}"), *w));
                }
                (
                    Params(params.into_iter().collect()),
                    format!("{} - offset", terms.join(" + ")),
                )
            }
            BarrierSpec::Expression { .. } => return Ok(self.clone()),
        };
        let (relative_degree, alpha, k_alpha) = self.order();
        Ok(BarrierSpec::Expression {
            state: None,
            params,
            h,
            relative_degree,
            alpha: *alpha,
            k_alpha: k_alpha.clone(),
        })
    }

    /// Parses a barrier from JSON text; `name` is used in errors.
    pub fn parse(text: &str, name: &str) -> Result<Self> {
        if text.trim().is_empty() {
            bail!("barrier file '{name}' is empty");
        }
        serde_json::from_str(crate::parse::strip_bom(text)).map_err(|e| {
            // a field of the wrong type, named (the tagged enum's error
            // names none)
            let field = crate::parse::json_value(text)
                .ok()
                .and_then(|v| v.as_object().cloned())
                .and_then(|obj| {
                    obj.iter()
                        .find_map(|(k, v)| check_field(k, v).err().map(|fe| (k.clone(), fe)))
                });
            match field {
                Some((key, fe)) => crate::err!("barrier file '{name}': field {key}: {fe}"),
                None => crate::err!(
                    "barrier file '{name}': {}",
                    crate::parse::json_error_message(text, &e)
                ),
            }
        })
    }

    /// Loads and validates a barrier file.
    pub fn load(path: &Path) -> Result<(Self, Arc<dyn DynBarrier>)> {
        let name = path.display().to_string();
        let text = crate::io::read_input_text(path)
            .with_context(|| format!("cannot read barrier file '{name}'"))?;
        let spec = Self::parse(&text, &name)?;
        let b = spec
            .build()
            .with_context(|| format!("barrier file '{name}'"))?;
        Ok((spec, b))
    }
}

static KINKS: WarnOnce = WarnOnce::new("barrier_kinks");

/// Warns, once per scope, of an expression barrier with a kink
/// ([`ExpressionBarrier::kinks`]).
fn warn_kinks(barrier: &ExpressionBarrier) {
    let kinks = barrier.kinks();
    if !kinks.is_empty() {
        crate::warn_once(
            &KINKS,
            format!(
                "barrier '{}' uses {}: h has no derivative where it switches, so the \
                 condition there constrains one side only and the other can cross zero \
                 although every step meets it (a min of two walls escapes their corner); \
                 write each side as its own barrier (docs/robots.md, \"Smooth barriers\")",
                barrier.expression(),
                kinks.join(", ")
            ),
        );
    }
}

#[cfg(test)]
#[allow(clippy::approx_constant)] // the literal values of interfaces.md
mod tests {
    use super::*;

    #[test]
    fn interface_examples_parse() {
        let a = r#"{"type": "pendulum_sector", "theta_c": 0.7854, "delta": 0.3927, "relative_degree": 2, "k_alpha": [1.0, 3.0]}"#;
        let b = r#"{"type": "circle_heading", "center": [-1.1667, -1.5], "radius": 0.7906, "q1": 0.7, "q2": 0.3, "relative_degree": 1, "alpha": 5.0}"#;
        let ba = BarrierSpec::parse(a, "a").unwrap().build().unwrap();
        assert_eq!(ba.relative_degree(), 2);
        assert!((ba.value(&[0.0, 0.0]) - (0.3927f64.cos() - 0.7854f64.cos())).abs() < 1e-12);
        let bb = BarrierSpec::parse(b, "b").unwrap().build().unwrap();
        assert_eq!(bb.gains(), &[5.0]);
    }

    #[test]
    fn bad_barriers_name_the_field() {
        let cases = [
            (
                r#"{"type": "pendulum_sector", "theta_c": 0.7, "delta": 0.3, "relative_degree": 2, "k_alpha": [1.0]}"#,
                "k_alpha",
            ),
            (
                r#"{"type": "pendulum_sector", "theta_c": 0.7, "delta": 0.3, "relative_degree": 1}"#,
                "alpha",
            ),
            (
                r#"{"type": "pendulum_sector", "theta_c": 0.7, "delta": -0.3, "relative_degree": 1, "alpha": 1}"#,
                "delta",
            ),
            (
                r#"{"type": "circle_heading", "center": [0, 0], "radius": 0, "q1": 1, "q2": 1, "relative_degree": 1, "alpha": 1}"#,
                "radius",
            ),
            (
                r#"{"type": "circle_heading", "center": [0, 0], "radius": 1, "q1": 1, "q2": 1, "relative_degree": 1, "alpha": 1, "extra": 2}"#,
                "extra",
            ),
            (r#"{"type": "triangle"}"#, "triangle"),
            (
                r#"{"type": "pendulum_sector_edge", "theta_c": 0.7, "delta": 0.3, "edge": "middle", "relative_degree": 1, "alpha": 1}"#,
                "middle",
            ),
            (
                r#"{"type": "pendulum_sector_edge", "theta_c": 0.7, "delta": 0.3, "relative_degree": 1, "alpha": 1}"#,
                "edge",
            ),
            (
                r#"{"type": "half_space", "normal": [0, 0], "offset": 1, "relative_degree": 1, "alpha": 1}"#,
                "normal",
            ),
            // fields of the wrong type, named (the tagged enum's own error
            // names none)
            (
                r#"{"type": "circle_heading", "center": [1.0], "radius": 1, "q1": 1, "q2": 1, "relative_degree": 1, "alpha": 1}"#,
                "field center: invalid length 1",
            ),
            (
                r#"{"type": "pendulum_sector", "theta_c": "0.7", "delta": 0.3, "relative_degree": 1, "alpha": 1}"#,
                "field theta_c: invalid type",
            ),
            (
                r#"{"type": "expression", "state": ["x"], "h": 3, "relative_degree": 1, "alpha": 1}"#,
                "field h: invalid type",
            ),
            (
                r#"{"type": "disc", "state_dim": 2.5, "indices": [0, 1], "center": [0, 0], "radius": 1, "relative_degree": 1, "alpha": 1}"#,
                "field state_dim: invalid value: floating point `2.5`",
            ),
        ];
        for (text, field) in cases {
            let err = BarrierSpec::parse(text, "f")
                .and_then(|s| s.build().map(|_| ()))
                .unwrap_err();
            let msg = format!("{err:#}");
            assert!(msg.contains(field), "{msg} should name {field}");
        }
    }

    /// A count written as a whole float (`2.0`, as float writers give it)
    /// reads as the integer.
    #[test]
    fn whole_floats_are_counts() {
        let text = r#"{"type": "disc", "state_dim": 3.0, "indices": [0, 1], "center": [0, 0], "radius": 1, "relative_degree": 2.0, "k_alpha": [1, 2]}"#;
        let spec = BarrierSpec::parse(text, "f").unwrap();
        assert_eq!(spec.build().unwrap().state_dim(), 3);
        assert_eq!(spec.order().0, 2);
    }

    #[test]
    fn every_built_in_barrier_restated_as_an_expression_is_the_same_function() {
        let names: Vec<String> = ["a", "b", "c"].iter().map(|s| s.to_string()).collect();
        let specs = [
            r#"{"type": "pendulum_sector", "theta_c": 0.7854, "delta": 0.3927, "relative_degree": 2, "k_alpha": [1.0, 3.0]}"#,
            r#"{"type": "pendulum_sector_edge", "theta_c": 0.7854, "delta": 0.3927, "edge": "upper", "relative_degree": 2, "k_alpha": [1.0, 3.0]}"#,
            r#"{"type": "pendulum_sector_edge", "theta_c": -2.5, "delta": 0.2, "edge": "lower", "relative_degree": 1, "alpha": 2.0}"#,
            r#"{"type": "circle_heading", "center": [-1.1667, -1.5], "radius": 0.7906, "q1": 0.7, "q2": 0.3, "relative_degree": 1, "alpha": 5.0}"#,
            r#"{"type": "disc", "state_dim": 3, "indices": [2, 0], "center": [0.5, -0.2], "radius": 0.4, "relative_degree": 1, "alpha": 2.0}"#,
            r#"{"type": "half_space", "normal": [0.3, -1.2, 2.0], "offset": 0.7, "relative_degree": 2, "k_alpha": [2.0, 3.0]}"#,
        ];
        for text in specs {
            let spec = BarrierSpec::parse(text, "b").unwrap();
            let a = spec.build().unwrap();
            let n = a.state_dim();
            let expr = spec.to_expression(&names[..n]).unwrap();
            assert!(matches!(expr, BarrierSpec::Expression { .. }), "{expr:?}");
            let b = expr.build_in(Some(&names[..n])).unwrap();
            assert_eq!(
                (a.relative_degree(), a.gains()),
                (b.relative_degree(), b.gains())
            );
            let (mut ga, mut gb) = (vec![0.0; n], vec![0.0; n]);
            let (mut ha, mut hb) = (vec![0.0; n * n], vec![0.0; n * n]);
            let mut hd = vec![num_dual::HyperDual64::from(0.0); n];
            for k in 0..50 {
                let x: Vec<f64> = (0..n)
                    .map(|i| ((k * 7 + i * 13) % 23) as f64 / 23.0 * 6.0 - 3.0)
                    .collect();
                let va = a.hessian(&x, &mut ga, &mut ha, &mut hd);
                let vb = b.hessian(&x, &mut gb, &mut hb, &mut hd);
                let close = |p: f64, q: f64| (p - q).abs() <= 1e-12 * q.abs().max(1.0);
                assert!(close(va, vb), "{text} at {x:?}: h {va} vs {vb}");
                for (p, q) in ga.iter().chain(&ha).zip(gb.iter().chain(&hb)) {
                    assert!(
                        close(*p, *q),
                        "{text} at {x:?}: {ga:?} {ha:?} vs {gb:?} {hb:?}"
                    );
                }
            }
        }
    }
}
