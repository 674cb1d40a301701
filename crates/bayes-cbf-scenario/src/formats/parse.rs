//! Parsing of vectors, index lists and covariance structures given as text
//! (command-line options, `--set` values, Python arguments).

use crate::error::Result;
use crate::{bail, err};
use bayes_cbf::gp::Rank;

/// Parses a comma-separated vector of finite numbers given to option `name`,
/// e.g. `--x -0.3,0.2`.
pub fn parse_vector(name: &str, s: &str) -> Result<Vec<f64>> {
    if s.trim().is_empty() {
        bail!("{name}: empty vector; expected comma-separated numbers such as 0.3,-0.2");
    }
    s.split(',')
        .enumerate()
        .map(|(i, tok)| {
            let tok = tok.trim();
            let v: f64 = tok
                .parse()
                .map_err(|_| err!("{name}[{i}] = '{tok}' is not a number (in '{s}')"))?;
            if !v.is_finite() {
                bail!("{name}[{i}] = {v} is not finite (in '{s}')");
            }
            Ok(v)
        })
        .collect()
}

/// Parses a comma-separated list of indices, each `< n`, for option `name`.
/// `none` (or an empty string) gives an empty list.
pub fn parse_indices(name: &str, s: &str, n: usize) -> Result<Vec<usize>> {
    let t = s.trim();
    if t.is_empty() || t.eq_ignore_ascii_case("none") {
        return Ok(Vec::new());
    }
    let mut out: Vec<usize> = Vec::new();
    for (j, tok) in t.split(',').enumerate() {
        let tok = tok.trim();
        let i: usize = tok
            .parse()
            .map_err(|_| err!("{name}[{j}] = '{tok}' is not a non-negative integer index"))?;
        if i >= n {
            bail!("{name}[{j}] = {i} is out of range: state indices are 0..{n}");
        }
        if out.contains(&i) {
            bail!("{name}[{j}] = {i} is listed twice");
        }
        out.push(i);
    }
    Ok(out)
}

/// Parses the structure of a learned covariance for option `name`:
/// `full`, `diag` (or `diagonal`), or a positive integer rank.
pub fn parse_rank(name: &str, s: &str) -> Result<Rank> {
    match s.trim().to_ascii_lowercase().as_str() {
        "full" => Ok(Rank::Full),
        "diag" | "diagonal" => Ok(Rank::Diagonal),
        t => match t.parse::<usize>() {
            Ok(0) => bail!("{name} = 0: a rank must be ≥ 1 (use 'diag' for a diagonal matrix)"),
            Ok(r) => Ok(Rank::Low(r)),
            Err(_) => bail!("{name} = '{s}': expected full, diag or a positive integer rank"),
        },
    }
}

/// Formats a rank back into the form [`parse_rank`] accepts.
pub fn rank_name(r: Rank) -> String {
    match r {
        Rank::Full => "full".into(),
        Rank::Diagonal => "diag".into(),
        Rank::Low(k) => k.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vectors_and_lists() {
        assert_eq!(parse_vector("--x", "-0.3, 0.2").unwrap(), vec![-0.3, 0.2]);
        assert!(parse_vector("--x", "1,,2").is_err());
        assert!(parse_vector("--x", "1,nan")
            .unwrap_err()
            .to_string()
            .contains("--x[1]"));
        assert!(parse_vector("--x", "").is_err());
        assert_eq!(
            parse_indices("--angle-index", "0,2", 3).unwrap(),
            vec![0, 2]
        );
        assert!(parse_indices("--angle-index", "none", 3)
            .unwrap()
            .is_empty());
        assert!(parse_indices("--angle-index", "3", 3).is_err());
        assert!(parse_indices("--angle-index", "1,1", 3).is_err());
        assert_eq!(parse_rank("--rank-a", "2").unwrap(), Rank::Low(2));
        assert_eq!(parse_rank("--rank-a", "Diag").unwrap(), Rank::Diagonal);
        assert!(parse_rank("--rank-a", "0").is_err());
        assert!(parse_rank("--rank-a", "lots").is_err());
        assert_eq!(rank_name(Rank::Low(3)), "3");
    }
}

/// Deserializes a count (a dimension, a relative degree): a non-negative
/// integer, or a number with no fractional part (`2.0`), as JSON writers
/// of floats (Python's `json.dumps(2.0)`, Julia) give it.
pub fn whole_number<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> std::result::Result<usize, D::Error> {
    use serde::de::{Error, Unexpected, Visitor};
    struct Whole;
    impl Visitor<'_> for Whole {
        type Value = usize;
        fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            f.write_str("a non-negative whole number")
        }
        fn visit_u64<E: Error>(self, v: u64) -> std::result::Result<usize, E> {
            usize::try_from(v).map_err(|_| E::invalid_value(Unexpected::Unsigned(v), &self))
        }
        fn visit_i64<E: Error>(self, v: i64) -> std::result::Result<usize, E> {
            usize::try_from(v).map_err(|_| E::invalid_value(Unexpected::Signed(v), &self))
        }
        fn visit_f64<E: Error>(self, v: f64) -> std::result::Result<usize, E> {
            // below 2⁵³ every whole float is exact
            if v.fract() == 0.0 && (0.0..9_007_199_254_740_992.0).contains(&v) {
                Ok(v as usize)
            } else {
                Err(E::invalid_value(Unexpected::Float(v), &self))
            }
        }
    }
    d.deserialize_any(Whole)
}

/// Whether `v` reads as a `T`: the error message if not. Used to name the
/// field of a file whose typed parse failed (internally tagged enums and
/// flattened structs lose the path).
pub fn type_error<T: serde::de::DeserializeOwned>(
    v: &serde_json::Value,
) -> std::result::Result<(), String> {
    T::deserialize(v).map(|_| ()).map_err(|e| e.to_string())
}

/// [`whole_number`] as a [`type_error`] check.
pub fn whole_number_error(v: &serde_json::Value) -> std::result::Result<(), String> {
    whole_number(v).map(|_| ()).map_err(|e| e.to_string())
}

/// A serde message with the Rust types it names in words: `expected usize`
/// becomes "expected a non-negative whole number", `expected struct
/// ControllerSpec` "expected a table (a JSON object)", and so on: the user
/// wrote a file or an argument, not the library's types.
pub fn in_words(msg: &str) -> String {
    let mut out = msg.to_string();
    for (rust, words) in [
        ("expected usize", "expected a non-negative whole number"),
        ("expected u64", "expected a non-negative whole number"),
        ("expected u32", "expected a non-negative whole number"),
        ("expected i64", "expected a whole number"),
        ("expected f64", "expected a number"),
        ("expected bool", "expected true or false"),
    ] {
        out = out.replace(rust, words);
    }
    // serde names a type the library defines (CamelCase) after these
    for (prefix, words) in [
        (
            "internally tagged enum ",
            "a table (a JSON object) with its \"type\"",
        ),
        ("struct ", "a table (a JSON object)"),
        ("enum ", "one of the documented values"),
    ] {
        let mut from = 0;
        while let Some(i) = out[from..].find(prefix).map(|i| i + from) {
            let rest = &out[i + prefix.len()..];
            let len = rest
                .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
                .unwrap_or(rest.len());
            if rest.starts_with(|c: char| c.is_ascii_uppercase()) {
                out.replace_range(i..i + prefix.len() + len, words);
                from = i + words.len();
            } else {
                from = i + prefix.len();
            }
        }
    }
    out
}

/// `text` without a leading UTF-8 byte-order mark, which some editors
/// write and JSON and TOML parsers refuse.
pub fn strip_bom(text: &str) -> &str {
    text.strip_prefix('\u{feff}').unwrap_or(text)
}

/// The message of a JSON error in `text`, naming a `NaN` or `Infinity`
/// where the parser stopped and the field it stands in: JSON has neither
/// (Python's `json.dump` writes them unless `allow_nan=False`), and the
/// parser's own message gives only a column.
pub fn json_error_message(text: &str, e: &serde_json::Error) -> String {
    let text = strip_bom(text);
    let at = text
        .split_inclusive('\n')
        .take(e.line().saturating_sub(1))
        .map(str::len)
        .sum::<usize>()
        + e.column().saturating_sub(1);
    // the parser stops at the word, or one past its sign
    let found = [at.saturating_sub(1), at].into_iter().find_map(|start| {
        let here = text.get(start..)?;
        ["-Infinity", "Infinity", "-NaN", "NaN", "-inf", "inf", "nan"]
            .into_iter()
            .find(|w| here.starts_with(w))
            .map(|w| (start, w))
    });
    let Some((start, word)) = found else {
        return in_words(&e.to_string());
    };
    let field = enclosing_key(&text[..start]);
    let place = format!("line {} column {}", e.line(), e.column() - (at - start));
    match field {
        Some(f) => format!(
            "field '{f}' holds {word} ({place}), which is not a JSON number: give finite numbers (Python: json.dump(..., allow_nan=False) finds them)"
        ),
        None => format!(
            "{word} ({place}) is not a JSON number: give finite numbers (Python: json.dump(..., allow_nan=False) finds them)"
        ),
    }
}

/// The key of the innermost object member that the end of the JSON
/// prefix `before` stands in (through arrays and past closed objects).
fn enclosing_key(before: &str) -> Option<String> {
    // one entry per open container: the current key of an object, None
    // for an array
    let mut open: Vec<Option<String>> = Vec::new();
    let mut chars = before.chars();
    let mut last_string = None;
    while let Some(c) = chars.next() {
        match c {
            '"' => {
                let mut s = String::new();
                while let Some(c) = chars.next() {
                    match c {
                        '\\' => {
                            chars.next();
                        }
                        '"' => break,
                        c => s.push(c),
                    }
                }
                last_string = Some(s);
            }
            ':' => {
                if let Some(top @ Some(_)) = open.last_mut() {
                    *top = last_string.take();
                }
            }
            '{' => open.push(Some(String::new())),
            '[' => open.push(None),
            '}' | ']' => {
                open.pop();
            }
            _ => {}
        }
    }
    open.into_iter().rev().flatten().find(|k| !k.is_empty())
}

/// JSON text as a value (after a byte-order mark, if any), refusing an
/// object that gives a key twice (`serde_json` would keep the last one
/// silently).
pub fn json_value(text: &str) -> serde_json::Result<serde_json::Value> {
    let text = strip_bom(text);
    use serde::de::{Deserialize, Deserializer, Error, MapAccess, SeqAccess, Visitor};
    use serde_json::{Map, Value};

    struct Strict(Value);
    struct V;
    impl<'de> Visitor<'de> for V {
        type Value = Strict;
        fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            f.write_str("a JSON value")
        }
        fn visit_bool<E: Error>(self, v: bool) -> Result<Strict, E> {
            Ok(Strict(Value::Bool(v)))
        }
        fn visit_i64<E: Error>(self, v: i64) -> Result<Strict, E> {
            Ok(Strict(Value::from(v)))
        }
        fn visit_u64<E: Error>(self, v: u64) -> Result<Strict, E> {
            Ok(Strict(Value::from(v)))
        }
        fn visit_f64<E: Error>(self, v: f64) -> Result<Strict, E> {
            Ok(Strict(Value::from(v)))
        }
        fn visit_str<E: Error>(self, v: &str) -> Result<Strict, E> {
            Ok(Strict(Value::String(v.to_string())))
        }
        fn visit_unit<E: Error>(self) -> Result<Strict, E> {
            Ok(Strict(Value::Null))
        }
        fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Strict, A::Error> {
            let mut out = Vec::new();
            while let Some(Strict(v)) = seq.next_element()? {
                out.push(v);
            }
            Ok(Strict(Value::Array(out)))
        }
        fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Strict, A::Error> {
            let mut out = Map::new();
            while let Some(key) = map.next_key::<String>()? {
                if out.contains_key(&key) {
                    return Err(A::Error::custom(format!("key \"{key}\" is given twice")));
                }
                let Strict(v) = map.next_value()?;
                out.insert(key, v);
            }
            Ok(Strict(Value::Object(out)))
        }
    }
    impl<'de> Deserialize<'de> for Strict {
        fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
            d.deserialize_any(V)
        }
    }
    serde_json::from_str::<Strict>(text).map(|s| s.0)
}

#[cfg(test)]
mod json_tests {
    use super::{in_words, json_error_message, json_value};

    #[test]
    fn json_values_refuse_a_key_given_twice_at_any_depth() {
        let same = r#"{"a": [1, 2.5, {"b": null, "c": "x"}], "d": true}"#;
        assert_eq!(
            json_value(same).unwrap(),
            serde_json::from_str::<serde_json::Value>(same).unwrap()
        );
        for text in [
            r#"{"noise_sigma": 0.1, "noise_sigma": 0.2}"#,
            r#"{"a": [{"b": 1, "b": 1}]}"#,
        ] {
            let e = json_value(text).unwrap_err().to_string();
            assert!(e.contains("given twice"), "{text}: {e}");
        }
    }

    /// NaN and Infinity, which JSON does not have and Python writes, are
    /// named with the field they stand in; other errors keep the parser's
    /// message.
    #[test]
    fn json_errors_name_a_nan_and_its_field() {
        for (text, want) in [
            (
                r#"{"a": 1, "noise_sigma": NaN}"#,
                "field 'noise_sigma' holds NaN",
            ),
            (
                "{\n  \"data\": {\"xdot\": [[0.5, 1.0],\n [Infinity, 2]]}\n}",
                "field 'xdot' holds Infinity (line 3 column 3)",
            ),
            (
                r#"[1, -Infinity]"#,
                "-Infinity (line 1 column 5) is not a JSON number",
            ),
            // past a closed object inside the array, the array's own key
            (
                r#"{"type": "half_space", "normal": [{"k": 1}, NaN], "offset": 0}"#,
                "field 'normal' holds NaN",
            ),
            // a key with an escaped quote, and a colon inside a string
            (r#"{"a\"b": "x:y", "c": [NaN]}"#, "field 'c' holds NaN"),
        ] {
            let e = json_value(text).unwrap_err();
            let m = json_error_message(text, &e);
            assert!(m.contains(want), "{text}: {m}");
        }
        let text = r#"{"a": 1,, }"#;
        let e = json_value(text).unwrap_err();
        assert_eq!(json_error_message(text, &e), e.to_string());
    }

    /// A byte-order mark, as some editors write it, is skipped by every
    /// reader: JSON values, barrier files and scenario files.
    /// The library's type names and Rust's number types are told in words;
    /// other text, and a lower-case word after "struct", stay.
    #[test]
    fn serde_messages_name_no_rust_types() {
        for (msg, want) in [
            (
                "invalid type: integer `5`, expected internally tagged enum BarrierSpec",
                "invalid type: integer `5`, expected a table (a JSON object) with its \"type\"",
            ),
            (
                "invalid type: null, expected struct DataSpec at line 1 column 9",
                "invalid type: null, expected a table (a JSON object) at line 1 column 9",
            ),
            (
                "invalid type: floating point `1.0`, expected usize",
                "invalid type: floating point `1.0`, expected a non-negative whole number",
            ),
            ("a struct field", "a struct field"),
            (
                "expected enum Rank or struct X",
                "expected one of the documented values or a table (a JSON object)",
            ),
        ] {
            assert_eq!(in_words(msg), want);
        }
    }

    #[test]
    fn a_byte_order_mark_is_skipped() {
        assert_eq!(json_value("\u{feff}{\"a\": 1}").unwrap()["a"], 1);
        let barrier = "\u{feff}{\"type\": \"half_space\", \"normal\": [1], \"offset\": 0, \"relative_degree\": 1, \"alpha\": 1}";
        assert!(crate::barrier_file::BarrierSpec::parse(barrier, "b.json").is_ok());
        let dir = std::env::temp_dir().join(format!("bayes-cbf-bom-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("s.toml");
        let (_, text) = crate::scenario::scenario_text("double-integrator").unwrap();
        std::fs::write(&path, format!("\u{feff}{text}")).unwrap();
        assert!(crate::scenario::load(path.to_str().unwrap(), &[]).is_ok());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
