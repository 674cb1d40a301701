//! The `params` table of an expression: named numbers.

use serde::de::{Deserializer, MapAccess, Visitor};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Named constants of an expression (`params = { m = 1.0, l = 2.0 }`); an
/// entry that is not a number is an error naming it.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
#[serde(transparent)]
pub struct Params(pub BTreeMap<String, f64>);

impl Params {
    /// Whether there are no parameters.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// Parameters from (name, value) pairs.
    pub fn of(pairs: &[(&str, f64)]) -> Self {
        Params(pairs.iter().map(|(k, v)| (k.to_string(), *v)).collect())
    }

    /// The parameters as (name, value) pairs, for the core constructors.
    pub fn pairs(&self) -> Vec<(String, f64)> {
        self.0.iter().map(|(k, v)| (k.clone(), *v)).collect()
    }
}

impl<'de> Deserialize<'de> for Params {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = Params;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a table of named numbers")
            }
            fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Params, A::Error> {
                let mut out = BTreeMap::new();
                while let Some(key) = map.next_key::<String>()? {
                    let value: serde_json::Value = map.next_value()?;
                    let v = value.as_f64().ok_or_else(|| {
                        serde::de::Error::custom(format!(
                            "params.{key} = {value}: expected a number"
                        ))
                    })?;
                    out.insert(key, v);
                }
                Ok(Params(out))
            }
        }
        d.deserialize_map(V)
    }
}

impl From<BTreeMap<String, f64>> for Params {
    fn from(m: BTreeMap<String, f64>) -> Self {
        Params(m)
    }
}
