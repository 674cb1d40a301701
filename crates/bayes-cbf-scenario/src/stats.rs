//! The statistics every report uses, from statrs: quantiles of a sample and
//! the standard normal distribution.
//!
//! One definition of a quantile for every summary, table and bench row:
//! statrs' [`OrderStatistics::quantile`] (Hyndman and Fan's type 8, the
//! approximately median-unbiased estimator; the median is the usual middle
//! value or midpoint), on the finite values of the sample.

use statrs::distribution::{ContinuousCDF, Normal};
use statrs::statistics::{Data, OrderStatistics};

/// Quantile `q ∈ [0, 1]` of the finite values of `values`; NaN when there
/// are none.
pub fn quantile(values: &[f64], q: f64) -> f64 {
    let finite: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    if finite.is_empty() {
        return f64::NAN;
    }
    Data::new(finite).quantile(q.clamp(0.0, 1.0))
}

/// The median of the finite values of `values`; NaN when there are none.
pub fn median(values: &[f64]) -> f64 {
    quantile(values, 0.5)
}

/// The standard normal distribution function `Φ(x)`.
pub fn normal_cdf(x: f64) -> f64 {
    standard_normal().cdf(x)
}

/// The standard normal quantile `Φ⁻¹(p)`.
pub fn normal_quantile(p: f64) -> f64 {
    standard_normal().inverse_cdf(p)
}

fn standard_normal() -> Normal {
    Normal::standard()
}

/// The Wilson score interval for `k` successes in `n` trials at 95 %:
/// `(p̂ + z²/2n ± z √(p̂(1 − p̂)/n + z²/4n²)) / (1 + z²/n)`.
///
/// Chosen over the Wald interval because it stays inside `[0, 1]` and has
/// close to nominal coverage for the small rates measured here, including
/// `k = 0` (upper end `z²/(n + z²)`, about `3.8/n`). `n = 0` gives `[0, 1]`.
pub fn wilson(k: usize, n: usize) -> (f64, f64) {
    if n == 0 {
        return (0.0, 1.0);
    }
    let (kf, nf) = (k as f64, n as f64);
    let p = kf / nf;
    let z = normal_quantile(0.975);
    let z2 = z * z;
    let denom = 1.0 + z2 / nf;
    let centre = (p + z2 / (2.0 * nf)) / denom;
    let half = z * (p * (1.0 - p) / nf + z2 / (4.0 * nf * nf)).sqrt() / denom;
    // exact ends at k = 0 and k = n (the formula leaves roundoff there)
    let lo = if k == 0 {
        0.0
    } else {
        (centre - half).max(0.0)
    };
    let hi = if k == n {
        1.0
    } else {
        (centre + half).min(1.0)
    };
    (lo, hi)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_and_normal_against_reference_values() {
        // type 8 on 1..=10: h = (n + 1/3) q + 1/3
        let v: Vec<f64> = (1..=10).map(f64::from).collect();
        assert!((median(&v) - 5.5).abs() < 1e-12);
        assert!((quantile(&v, 0.2) - (2.0 + 0.4)).abs() < 1e-12);
        assert!((quantile(&v, 0.9) - (9.0 + 0.6333333333333329)).abs() < 1e-12);
        assert!((median(&[3.0, f64::NAN, 1.0, 2.0]) - 2.0).abs() < 1e-15);
        assert!(median(&[]).is_nan());
        let c = normal_cdf(1.959_963_984_540_054);
        assert!((c - 0.975).abs() < 1e-10, "{c}");
        assert!((normal_cdf(-1.0) - 0.158_655_253_931_457_05).abs() < 1e-10);
        assert!((normal_quantile(0.975) - 1.959_963_984_540_054).abs() < 1e-9);
    }
}
