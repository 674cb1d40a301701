//! Exact serde of `f64` for partial results that are merged later: finite
//! numbers as JSON numbers (serde_json's `float_roundtrip` parses them back
//! to the same bits), non-finite ones as the strings `"inf"`, `"-inf"` and
//! `"NaN"` (JSON has no such numbers).
//!
//! Use as `#[serde(with = "crate::exact")]`, or `crate::exact::option` for
//! `Option<f64>`.

use serde::{Deserialize, Deserializer, Serializer};

#[derive(Deserialize)]
#[serde(untagged)]
enum Repr {
    Num(f64),
    Text(String),
}

fn to_f64<E: serde::de::Error>(r: Repr) -> Result<f64, E> {
    match r {
        Repr::Num(v) => Ok(v),
        Repr::Text(s) => s
            .parse::<f64>()
            .map_err(|_| E::custom(format!("'{s}' is not a number"))),
    }
}

/// Serialises `v` exactly.
pub fn serialize<S: Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
    if v.is_finite() {
        s.serialize_f64(*v)
    } else {
        s.serialize_str(&v.to_string())
    }
}

/// Deserialises a number or `"inf"`, `"-inf"`, `"NaN"`.
pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    to_f64(Repr::deserialize(d)?)
}

/// The same for `Option<f64>` (`null` is `None`).
pub mod option {
    use super::*;

    /// Serialises `v` exactly.
    pub fn serialize<S: Serializer>(v: &Option<f64>, s: S) -> Result<S::Ok, S::Error> {
        match v {
            Some(v) => super::serialize(v, s),
            None => s.serialize_none(),
        }
    }

    /// Deserialises `null`, a number or `"inf"`, `"-inf"`, `"NaN"`.
    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Option<f64>, D::Error> {
        Option::<Repr>::deserialize(d)?.map(to_f64).transpose()
    }
}

#[cfg(test)]
mod tests {
    #[derive(serde::Serialize, serde::Deserialize, PartialEq, Debug)]
    struct T {
        #[serde(with = "crate::exact")]
        a: f64,
        #[serde(with = "crate::exact::option")]
        b: Option<f64>,
    }

    #[test]
    fn round_trip_keeps_every_bit() {
        let mut x = 0.1f64;
        for i in 0..2000 {
            x = (x * 1.618_033_988_749 + 1e-7 * i as f64).fract() * 10f64.powi(i % 40 - 20);
            for v in [
                x,
                -x,
                f64::INFINITY,
                f64::NEG_INFINITY,
                f64::MIN_POSITIVE,
                5e-324,
            ] {
                let t = T { a: v, b: Some(v) };
                let back: T = serde_json::from_str(&serde_json::to_string(&t).unwrap()).unwrap();
                assert_eq!(back.a.to_bits(), v.to_bits());
                assert_eq!(back.b.unwrap().to_bits(), v.to_bits());
            }
        }
        let t = T {
            a: f64::NAN,
            b: None,
        };
        let back: T = serde_json::from_str(&serde_json::to_string(&t).unwrap()).unwrap();
        assert!(back.a.is_nan() && back.b.is_none());
    }
}
