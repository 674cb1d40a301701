//! The optional `input_map` of a model file and the `--input-map` option:
//! which functions of the state the kernel sees.
//!
//! In JSON an entry is a state index `i` (the kernel sees `x_i`) or
//! `{"cos": i}` / `{"sin": i}` (a periodic embedding of an angle). On the
//! command line the same entries are written `i`, `cos:i` and `sin:i`,
//! comma-separated. A list of plain indices is a coordinate selection, e.g.
//! `[2]` for the translation-invariant Ackermann model (paper, Sec. VII-B).

use crate::error::Result;
use crate::{bail, err};
use bayes_cbf::gp::{Feature, InputMap};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

/// One kernel input.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "Value", into = "Value")]
pub enum FeatureSpec {
    /// `x_i`.
    Coord(usize),
    /// `cos x_i`.
    Cos(usize),
    /// `sin x_i`.
    Sin(usize),
}

impl TryFrom<Value> for FeatureSpec {
    type Error = String;

    fn try_from(v: Value) -> Result<Self, String> {
        let index = |v: &Value| v.as_u64().and_then(|i| usize::try_from(i).ok());
        let bad = || {
            format!("input_map entries are state indices (0, 1, ...) or {{\"cos\": i}} / {{\"sin\": i}}, got {v}")
        };
        if let Some(i) = index(&v) {
            return Ok(FeatureSpec::Coord(i));
        }
        match v.as_object() {
            Some(o) if o.len() == 1 => {
                let (k, iv) = o.iter().next().ok_or_else(bad)?;
                let i = index(iv).ok_or_else(bad)?;
                match k.as_str() {
                    "cos" => Ok(FeatureSpec::Cos(i)),
                    "sin" => Ok(FeatureSpec::Sin(i)),
                    _ => Err(bad()),
                }
            }
            _ => Err(bad()),
        }
    }
}

impl From<FeatureSpec> for Value {
    fn from(f: FeatureSpec) -> Value {
        match f {
            FeatureSpec::Coord(i) => json!(i),
            FeatureSpec::Cos(i) => json!({"cos": i}),
            FeatureSpec::Sin(i) => json!({"sin": i}),
        }
    }
}

impl FeatureSpec {
    fn index(self) -> usize {
        match self {
            FeatureSpec::Coord(i) | FeatureSpec::Cos(i) | FeatureSpec::Sin(i) => i,
        }
    }
}

/// The library's input map for a list of entries: a plain selection when
/// every entry is a coordinate, trigonometric features otherwise.
pub fn to_input_map(spec: Option<&[FeatureSpec]>) -> InputMap {
    match spec {
        None => InputMap::Identity,
        Some(s) if s.iter().all(|f| matches!(f, FeatureSpec::Coord(_))) => {
            InputMap::Select(s.iter().map(|f| f.index()).collect())
        }
        Some(s) => InputMap::Features(
            s.iter()
                .map(|f| match *f {
                    FeatureSpec::Coord(i) => Feature::Coord(i),
                    FeatureSpec::Cos(i) => Feature::Cos(i),
                    FeatureSpec::Sin(i) => Feature::Sin(i),
                })
                .collect(),
        ),
    }
}

/// The entries describing `map` (`None` for the identity).
pub fn from_input_map(map: &InputMap) -> Option<Vec<FeatureSpec>> {
    match map {
        InputMap::Identity => None,
        InputMap::Select(idx) => Some(idx.iter().map(|&i| FeatureSpec::Coord(i)).collect()),
        InputMap::Features(f) => Some(
            f.iter()
                .map(|f| match *f {
                    Feature::Coord(i) => FeatureSpec::Coord(i),
                    Feature::Cos(i) => FeatureSpec::Cos(i),
                    Feature::Sin(i) => FeatureSpec::Sin(i),
                })
                .collect(),
        ),
    }
}

/// Parses `--input-map` (`i`, `cos:i`, `sin:i`, comma-separated) for state
/// dimension `n`, checking ranges and duplicates.
pub fn parse_input_map(arg: &str, n: usize) -> Result<Vec<FeatureSpec>> {
    let mut out: Vec<FeatureSpec> = Vec::new();
    for (j, tok) in arg.split(',').enumerate() {
        let tok = tok.trim();
        let (kind, idx) = match tok.split_once(':') {
            Some((k, i)) => (k.trim(), i.trim()),
            None => ("", tok),
        };
        let i: usize = idx.parse().map_err(|_| {
            err!("--input-map[{j}] = '{tok}': expected a state index i, cos:i or sin:i")
        })?;
        let f = match kind {
            "" => FeatureSpec::Coord(i),
            "cos" => FeatureSpec::Cos(i),
            "sin" => FeatureSpec::Sin(i),
            _ => {
                bail!("--input-map[{j}] = '{tok}': unknown feature '{kind}' (expected cos or sin)")
            }
        };
        if i >= n {
            bail!(
                "--input-map[{j}] = '{tok}': index {i} is out of range, state indices are 0..{n}"
            );
        }
        if out.contains(&f) {
            bail!("--input-map[{j}] = '{tok}' is listed twice");
        }
        out.push(f);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_cli_and_library_forms_agree() {
        let spec: Vec<FeatureSpec> =
            serde_json::from_str(r#"[1, {"cos": 0}, {"sin": 0}]"#).unwrap();
        assert_eq!(spec, parse_input_map("1, cos:0, sin:0", 2).unwrap());
        let map = to_input_map(Some(&spec));
        assert_eq!(
            map,
            InputMap::Features(vec![Feature::Coord(1), Feature::Cos(0), Feature::Sin(0)])
        );
        assert_eq!(from_input_map(&map).as_deref(), Some(spec.as_slice()));
        assert_eq!(
            serde_json::to_string(&spec).unwrap(),
            r#"[1,{"cos":0},{"sin":0}]"#
        );
        assert_eq!(
            to_input_map(Some(&[FeatureSpec::Coord(2)])),
            InputMap::Select(vec![2])
        );
        assert_eq!(to_input_map(None), InputMap::Identity);
        assert!(serde_json::from_str::<Vec<FeatureSpec>>(r#"[{"tan": 0}]"#).is_err());
        assert!(serde_json::from_str::<Vec<FeatureSpec>>("[-1]").is_err());
        assert!(parse_input_map("2", 2)
            .unwrap_err()
            .to_string()
            .contains("--input-map[0]"));
        assert!(parse_input_map("0,0", 2).is_err());
        assert!(parse_input_map("tan:0", 2).is_err());
        assert!(parse_input_map("", 2).is_err());
    }
}
