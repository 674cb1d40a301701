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
                /// A number (infinite and NaN ones too: the expression's
                /// names refuse them, naming the entry), or anything else.
                #[derive(Deserialize)]
                #[serde(untagged)]
                enum Entry {
                    Number(f64),
                    Other(serde_json::Value),
                }
                while let Some(key) = map.next_key::<String>()? {
                    match map.next_value::<Entry>()? {
                        Entry::Number(v) => {
                            out.insert(key, v);
                        }
                        // a TOML inf or nan reaches here as null when the
                        // table went through JSON (prior means)
                        Entry::Other(serde_json::Value::Null) => {
                            return Err(serde::de::Error::custom(format!(
                                "params.{key}: expected a finite number (got null, \
                                 an infinite or a NaN value)"
                            )))
                        }
                        Entry::Other(value) => {
                            return Err(serde::de::Error::custom(format!(
                                "params.{key} = {value}: expected a number"
                            )))
                        }
                    }
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
