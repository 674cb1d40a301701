//! Online recalibration of the barrier conditions' variances: a
//! per-barrier inflation `κ_i ≥ 1` of the posterior standard deviation of
//! each condition, adapted after every model update so that the one-sided
//! bound the SOCP certifies is missed at the promised rate `1 − p` even
//! when the prior is wrong.
//!
//! ## The monitored event
//! At step `k` the controller certifies `C_i(x_k, u_k) ≥ E_i − c(p) κ_i σ_i`
//! from the moments `(E_i, σ_i²)` of the model that holds the data up to
//! `k − 1`. Once the step's observation is added, the same condition under
//! the updated model has moments `(E_i⁺, σ_i⁺²)`. For a model whose
//! posterior is right, the innovation `E_i⁺ − E_i` is distributed with
//! mean 0 and variance `s_i² = σ_i² − σ_i⁺²` (the variance the new
//! observation explains; for a condition linear in `F`, relative degree 1,
//! it is the standardised one-step prediction residual projected on the
//! condition, and Gaussian). A *miss* is
//! `E_i⁺ − E_i < −c(p) κ_i s_i`: its probability is `1 − p` under the
//! Gaussian factor of relative degree 1, and at most `1 − p` under
//! Cantelli's factor (relative degree 2), when the model is right and
//! `κ_i = 1`. A biased or over-confident model misses more often. The
//! comparison holds for added observations only: the closed loop drops a
//! sliding window's oldest points, or a budget's least informative ones,
//! after it (forgetting moves the posterior by more than `s_i` allows, and
//! counted as misses it drove `κ` to its ceiling while a robot stood
//! still).
//!
//! ## The update (adaptive conformal inference)
//! `log κ_i ← max(0, log κ_i + η (miss − (1 − p)))`: the online quantile
//! tracking of Gibbs and Candès (2021), in the scale of the standard
//! deviation rather than the level. For any sequence of observations the
//! long-run miss rate of the unfloored iteration is within
//! `(max log κ + η) / (η T)` of `1 − p` over `T` updates (Gibbs & Candès,
//! Prop. 4.1); the floor at `κ = 1` only inflates, so a model that is right
//! keeps its promise and a wrong one is widened until its misses are as
//! rare as promised. `κ` rises by a factor `e^{η p}` at a miss and decays
//! by `e^{−η (1−p)}` at a hit.
//!
//! ## Reference
//! I. Gibbs and E. Candès, "Adaptive conformal inference under distribution
//! shift", NeurIPS 2021; A. Angelopoulos, E. Candès and R. Tibshirani,
//! "Conformal PID control for time series prediction", NeurIPS 2023
//! (quantile tracking).

use crate::error::{check_positive, InputError};

/// Settings of the online recalibration.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct RecalibrationSettings {
    /// Step size `η > 0` of `log κ` (default 0.3).
    pub rate: f64,
    /// Largest inflation `κ_max ≥ 1` (default 100).
    pub max_inflation: f64,
}

impl Default for RecalibrationSettings {
    fn default() -> Self {
        Self {
            rate: 0.3,
            max_inflation: 100.0,
        }
    }
}

impl RecalibrationSettings {
    /// Checks the ranges.
    pub fn validate(&self) -> Result<(), InputError> {
        check_positive("recalibration.rate", self.rate)?;
        if !(self.max_inflation.is_finite() && self.max_inflation >= 1.0) {
            return Err(InputError::invalid(
                "recalibration.max_inflation",
                self.max_inflation,
                "must be finite and ≥ 1",
            ));
        }
        Ok(())
    }
}

/// The per-barrier inflations `κ_i` and their miss counts.
#[derive(Debug, Clone, PartialEq)]
pub struct Recalibrator {
    settings: RecalibrationSettings,
    log_kappa: Vec<f64>,
    misses: Vec<usize>,
    updates: Vec<usize>,
}

impl Recalibrator {
    /// `κ_i = 1` for `barriers` barriers.
    pub fn new(barriers: usize, settings: RecalibrationSettings) -> Result<Self, InputError> {
        settings.validate()?;
        Ok(Self {
            settings,
            log_kappa: vec![0.0; barriers],
            misses: vec![0; barriers],
            updates: vec![0; barriers],
        })
    }

    /// The settings.
    pub fn settings(&self) -> &RecalibrationSettings {
        &self.settings
    }

    /// The number of barriers.
    pub fn barriers(&self) -> usize {
        self.log_kappa.len()
    }

    /// `κ_i`.
    pub fn inflation(&self, i: usize) -> f64 {
        self.log_kappa[i].exp()
    }

    /// Misses and updates of barrier `i` so far.
    pub fn counts(&self, i: usize) -> (usize, usize) {
        (self.misses[i], self.updates[i])
    }

    /// One update of barrier `i` from the condition's mean and variance
    /// before (`mean`, `var`, uninflated) and after (`mean_post`,
    /// `var_post`) the model learned the step's observation, at the
    /// promised factor `c = c(p)` and miss rate `alpha = 1 − p`. Returns
    /// whether it was a miss; `None` (no update) when the observation
    /// explained no variance of this condition.
    pub fn update(
        &mut self,
        i: usize,
        (mean, var): (f64, f64),
        (mean_post, var_post): (f64, f64),
        c: f64,
        alpha: f64,
    ) -> Option<bool> {
        let explained = var - var_post;
        let finite = [mean, var, mean_post, var_post, c, alpha]
            .iter()
            .all(|v| v.is_finite());
        // rounding: an observation far from x explains nothing here
        if !finite || explained <= 1e-12 * var.abs().max(f64::MIN_POSITIVE) {
            return None;
        }
        let s = explained.sqrt();
        let miss = mean_post - mean < -c * self.inflation(i) * s;
        let step = self.settings.rate * (if miss { 1.0 } else { 0.0 } - alpha);
        self.log_kappa[i] = (self.log_kappa[i] + step).clamp(0.0, self.settings.max_inflation.ln());
        self.updates[i] += 1;
        self.misses[i] += usize::from(miss);
        Some(miss)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, StandardNormal};

    /// Innovations `E⁺ − E = scale · s · z` with `z` standard normal:
    /// the miss rate and the geometric mean of `κ` over the second half.
    fn track(scale: f64, p: f64, steps: usize) -> (f64, f64) {
        let c = crate::barrier::quantile_factor(p, 1).unwrap();
        let mut r = Recalibrator::new(1, RecalibrationSettings::default()).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let (var, var_post) = (2.0, 0.5);
        let s: f64 = var - var_post;
        let mut log_sum = 0.0;
        for k in 0..steps {
            let z: f64 = StandardNormal.sample(&mut rng);
            r.update(
                0,
                (1.0, var),
                (1.0 + scale * s.sqrt() * z, var_post),
                c,
                1.0 - p,
            );
            if k >= steps / 2 {
                log_sum += r.inflation(0).ln();
            }
        }
        let (m, n) = r.counts(0);
        (
            m as f64 / n as f64,
            (log_sum / (steps - steps / 2) as f64).exp(),
        )
    }

    #[test]
    fn a_right_model_keeps_its_variance_and_a_wrong_one_is_widened_to_its_promise() {
        for p in [0.9, 0.99] {
            // right: κ stays near 1; the floor at 1 keeps the misses at
            // most 1 − p (fewer: κ rises after each miss)
            let (rate, kappa) = track(1.0, p, 100_000);
            assert!(rate <= 1.0 - p && rate > 0.5 * (1.0 - p), "{p}: {rate}");
            assert!(kappa < 2.0, "{p}: {kappa}");
            // four times over-confident: widened to about 4, misses at 1 − p
            let (rate, kappa) = track(4.0, p, 100_000);
            assert!((rate - (1.0 - p)).abs() < 0.2 * (1.0 - p), "{p}: {rate}");
            assert!((3.0..5.5).contains(&kappa), "{p}: {kappa}");
        }
        // nothing explained: no update
        let mut r = Recalibrator::new(1, RecalibrationSettings::default()).unwrap();
        assert_eq!(r.update(0, (0.0, 1.0), (5.0, 1.0), 2.0, 0.01), None);
        assert_eq!(r.counts(0), (0, 0));
        // a miss raises κ by e^{η(1−α)}
        assert_eq!(r.update(0, (0.0, 1.0), (-5.0, 0.0), 2.0, 0.01), Some(true));
        assert!((r.inflation(0) - (0.3f64 * 0.99).exp()).abs() < 1e-12);
        assert!(Recalibrator::new(
            1,
            RecalibrationSettings {
                rate: 0.0,
                ..Default::default()
            }
        )
        .is_err());
    }
}
