//! Input maps: the kernel sees `z = φ(x)` rather than `x`.

use crate::error::{check_index, InputError};

/// Checks that `entries` (of a map's `kind`: index or feature) are
/// distinct, at least one, and read coordinates below `n`; `index` gives
/// an entry's coordinate and the key it stands under (`.cos` of
/// `{"cos": 2}`, empty for a bare index).
fn check_entries<T: PartialEq>(
    entries: &[T],
    index: impl Fn(&T) -> (usize, &'static str),
    n: usize,
    kind: &str,
) -> Result<(), InputError> {
    if entries.is_empty() {
        return Err(InputError::shape(
            "input_map",
            format!("at least one {kind}"),
            0,
        ));
    }
    for (j, e) in entries.iter().enumerate() {
        let (i, key) = index(e);
        let field = format!("input_map[{j}]{key}");
        check_index(&field, i, n)?;
        if entries[..j].contains(e) {
            return Err(InputError::invalid_shown(
                &field,
                i,
                &format!("duplicate {kind}"),
            ));
        }
    }
    Ok(())
}

/// One kernel input computed from one state coordinate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub enum Feature {
    /// `x_i`.
    Coord(usize),
    /// `cos x_i` (with [`Feature::Sin`]: a periodic embedding of an angle).
    Cos(usize),
    /// `sin x_i`.
    Sin(usize),
}

impl Feature {
    fn index(self) -> usize {
        match self {
            Feature::Coord(i) | Feature::Cos(i) | Feature::Sin(i) => i,
        }
    }
}

/// A map from the state `x ∈ R^n` to the kernel input `z ∈ R^d`, applied
/// identically in training, prediction and control.
///
/// `Select(vec![2])` for the Ackermann vehicle makes the kernel depend on the
/// heading θ only: the dynamics are invariant to translations (paper,
/// Sec. VII-B). [`InputMap::periodic`] embeds angles as `(cos θ, sin θ)` so
/// the kernel is continuous across the `±π` wrap.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub enum InputMap {
    /// `z = x`.
    #[default]
    Identity,
    /// `z = (x_{i_1}, …, x_{i_d})`.
    Select(Vec<usize>),
    /// Each `z_j` is a [`Feature`] of one coordinate.
    Features(Vec<Feature>),
}

impl InputMap {
    /// The map seeing every coordinate of an `n`-dimensional state, with the
    /// coordinates in `angles` embedded as `(cos, sin)`.
    pub fn periodic(n: usize, angles: &[usize]) -> Self {
        let mut f = Vec::new();
        for i in 0..n {
            if angles.contains(&i) {
                f.push(Feature::Cos(i));
                f.push(Feature::Sin(i));
            } else {
                f.push(Feature::Coord(i));
            }
        }
        InputMap::Features(f)
    }

    /// Checks the map against the state dimension `n`.
    pub fn validate(&self, n: usize) -> Result<(), InputError> {
        match self {
            InputMap::Identity => Ok(()),
            InputMap::Select(idx) => check_entries(idx, |&i| (i, ""), n, "index"),
            InputMap::Features(f) => check_entries(
                f,
                |f| {
                    let key = match f {
                        Feature::Coord(_) => "",
                        Feature::Cos(_) => ".cos",
                        Feature::Sin(_) => ".sin",
                    };
                    (f.index(), key)
                },
                n,
                "feature",
            ),
        }
    }

    /// Kernel input dimension `d` for state dimension `n`.
    pub fn output_dim(&self, n: usize) -> usize {
        match self {
            InputMap::Identity => n,
            InputMap::Select(i) => i.len(),
            InputMap::Features(f) => f.len(),
        }
    }

    /// Writes `φ(x)` into `z`.
    #[inline]
    pub fn apply(&self, x: &[f64], z: &mut [f64]) {
        match self {
            InputMap::Identity => z.copy_from_slice(x),
            InputMap::Select(idx) => {
                for (zj, &i) in z.iter_mut().zip(idx) {
                    *zj = x[i];
                }
            }
            InputMap::Features(f) => {
                for (zj, feat) in z.iter_mut().zip(f) {
                    *zj = match *feat {
                        Feature::Coord(i) => x[i],
                        Feature::Cos(i) => x[i].cos(),
                        Feature::Sin(i) => x[i].sin(),
                    };
                }
            }
        }
    }

    /// State index feeding kernel input `j`: each `z_j` depends on one
    /// coordinate only, so `∂z_j/∂x_i = [i == source(j)] · derivative(j, x)`.
    #[inline]
    pub fn source(&self, j: usize) -> usize {
        match self {
            InputMap::Identity => j,
            InputMap::Select(idx) => idx[j],
            InputMap::Features(f) => f[j].index(),
        }
    }

    /// `∂z_j/∂x_{source(j)}` at `x`.
    #[inline]
    pub fn derivative(&self, j: usize, x: &[f64]) -> f64 {
        match self {
            InputMap::Identity | InputMap::Select(_) => 1.0,
            InputMap::Features(f) => match f[j] {
                Feature::Coord(_) => 1.0,
                Feature::Cos(i) => -x[i].sin(),
                Feature::Sin(i) => x[i].cos(),
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The error of `map.validate(n)`, as its field and message.
    fn refusal(map: InputMap, n: usize) -> (String, String) {
        let e = map.validate(n).unwrap_err();
        let field = match &e {
            InputError::Invalid { field, .. } | InputError::Shape { field, .. } => field.clone(),
            other => panic!("unexpected error {other:?}"),
        };
        (field, e.to_string())
    }

    #[test]
    fn validation_names_the_entry_at_fault() {
        assert!(InputMap::Identity.validate(3).is_ok());
        assert!(InputMap::Select(vec![2, 0]).validate(3).is_ok());
        assert!(InputMap::periodic(3, &[1]).validate(3).is_ok());
        let cases = [
            (InputMap::Select(vec![]), "input_map", "at least one index"),
            (
                InputMap::Features(vec![]),
                "input_map",
                "at least one feature",
            ),
            (
                InputMap::Select(vec![0, 3]),
                "input_map[1]",
                "index must be < state dimension 3",
            ),
            (
                InputMap::Features(vec![Feature::Coord(0), Feature::Sin(5)]),
                "input_map[1].sin",
                "index must be < state dimension 3",
            ),
            (
                InputMap::Select(vec![1, 2, 1]),
                "input_map[2]",
                "duplicate index",
            ),
            (
                InputMap::Features(vec![Feature::Cos(1), Feature::Sin(1), Feature::Cos(1)]),
                "input_map[2].cos",
                "duplicate feature",
            ),
        ];
        for (map, field, message) in cases {
            let (f, text) = refusal(map.clone(), 3);
            assert_eq!(f, field, "{map:?}");
            assert!(text.contains(message), "{map:?}: {text}");
        }
        // the same coordinate under two features is no duplicate
        assert!(InputMap::Features(vec![Feature::Cos(1), Feature::Sin(1)])
            .validate(3)
            .is_ok());
    }
}
