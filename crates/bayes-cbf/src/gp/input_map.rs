//! Input maps: the kernel sees `z = φ(x)` rather than `x`.

use crate::error::InputError;

/// A map from the state `x ∈ R^n` to the kernel input `z ∈ R^d`, applied
/// identically in training, prediction and control.
///
/// `Select(vec![2])` for the Ackermann vehicle makes the kernel depend on the
/// heading θ only: the dynamics are invariant to translations (paper,
/// Sec. VII-B).
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum InputMap {
    /// `z = x`.
    #[default]
    Identity,
    /// `z = (x_{i_1}, …, x_{i_d})`.
    Select(Vec<usize>),
}

impl InputMap {
    /// Checks the map against the state dimension `n`.
    pub fn validate(&self, n: usize) -> Result<(), InputError> {
        if let InputMap::Select(idx) = self {
            if idx.is_empty() {
                return Err(InputError::shape("input_map", "at least one index", 0));
            }
            for (j, &i) in idx.iter().enumerate() {
                if i >= n {
                    return Err(InputError::invalid(
                        &format!("input_map[{j}]"),
                        i as f64,
                        &format!("index must be < state dimension {n}"),
                    ));
                }
                if idx[..j].contains(&i) {
                    return Err(InputError::invalid(
                        &format!("input_map[{j}]"),
                        i as f64,
                        "duplicate index",
                    ));
                }
            }
        }
        Ok(())
    }

    /// Kernel input dimension `d` for state dimension `n`.
    pub fn output_dim(&self, n: usize) -> usize {
        match self {
            InputMap::Identity => n,
            InputMap::Select(i) => i.len(),
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
        }
    }

    /// State index feeding kernel input `j`: the map is a coordinate
    /// selection, so its Jacobian is `∂z_j/∂x_i = [i == source(j)]`.
    #[inline]
    pub fn source(&self, j: usize) -> usize {
        match self {
            InputMap::Identity => j,
            InputMap::Select(idx) => idx[j],
        }
    }
}
