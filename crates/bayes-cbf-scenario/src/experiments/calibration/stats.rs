//! Binomial confidence intervals and the exact sign test used by the
//! calibration report.

use statrs::distribution::{Binomial, DiscreteCDF};

/// `z` of a two-sided 95 % interval, `Φ⁻¹(0.975)`.
fn z95() -> f64 {
    crate::stats::normal_quantile(0.975)
}

pub(crate) use crate::stats::wilson;

/// A 95 % interval for a pooled rate `Σ k_e / Σ n_e` over episodes whose
/// steps are correlated, by the cluster-robust (ratio-estimator) variance
/// `E/(E − 1) Σ_e (k_e − r n_e)² / (Σ n_e)²` and a normal approximation,
/// clipped to `[0, 1]`. `None` with fewer than 2 episodes with steps.
pub(crate) fn cluster_interval(counts: &[(usize, usize)]) -> Option<(f64, f64)> {
    let used: Vec<(f64, f64)> = counts
        .iter()
        .filter(|(_, n)| *n > 0)
        .map(|&(k, n)| (k as f64, n as f64))
        .collect();
    let e = used.len() as f64;
    let total: f64 = used.iter().map(|(_, n)| n).sum();
    if used.len() < 2 || total == 0.0 {
        return None;
    }
    let r = used.iter().map(|(k, _)| k).sum::<f64>() / total;
    let ss: f64 = used.iter().map(|(k, n)| (k - r * n).powi(2)).sum();
    let se = (e / (e - 1.0) * ss).sqrt() / total;
    Some(((r - z95() * se).max(0.0), (r + z95() * se).min(1.0)))
}

/// `P(X ≥ k)` for `X ~ Binomial(n, ½)`: the one-sided exact sign
/// (McNemar) test of `k` discordant pairs favouring one side out of `n`.
pub(crate) fn sign_test_p(k: usize, n: usize) -> f64 {
    if k == 0 {
        return 1.0;
    }
    if k > n {
        return 0.0;
    }
    match Binomial::new(0.5, n as u64) {
        Ok(b) => b.sf(k as u64 - 1),
        Err(_) => f64::NAN,
    }
}

/// A binomial proportion with its 95 % Wilson interval.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Proportion {
    /// Successes.
    pub count: usize,
    /// Trials.
    pub of: usize,
    /// `count / of`; `None` without trials.
    pub rate: Option<f64>,
    /// 95 % Wilson score interval.
    pub ci95: [f64; 2],
}

/// A rate pooled over episodes: the [`Proportion`] of all their steps, and
/// a cluster-robust interval by episode (`None` with fewer than 2).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Pooled {
    /// The proportion of all steps.
    #[serde(flatten)]
    pub all: Proportion,
    /// 95 % cluster-robust interval.
    pub ci95_clustered: Option<[f64; 2]>,
}

/// The proportion `k / n` with its Wilson interval.
pub(crate) fn proportion(k: usize, n: usize) -> Proportion {
    let (lo, hi) = wilson(k, n);
    Proportion {
        count: k,
        of: n,
        rate: (n > 0).then(|| k as f64 / n as f64),
        ci95: [lo, hi],
    }
}

/// [`proportion`] of pooled per-episode counts `(k_e, n_e)`, with the
/// cluster-robust interval as well.
pub(crate) fn pooled(counts: &[(usize, usize)]) -> Pooled {
    let k: usize = counts.iter().map(|c| c.0).sum();
    let n: usize = counts.iter().map(|c| c.1).sum();
    Pooled {
        all: proportion(k, n),
        ci95_clustered: cluster_interval(counts).map(|(lo, hi)| [lo, hi]),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wilson_matches_reference_values() {
        // reference: statsmodels proportion_confint(method="wilson")
        let (lo, hi) = wilson(0, 200);
        assert!(lo == 0.0 && (hi - 0.018_845).abs() < 1e-5, "{lo} {hi}");
        let (lo, hi) = wilson(10, 100);
        assert!(
            (lo - 0.055_2).abs() < 1e-4 && (hi - 0.174_4).abs() < 1e-4,
            "{lo} {hi}"
        );
        let (lo, hi) = wilson(50, 50);
        assert!((lo - 0.928_6).abs() < 1e-4 && hi == 1.0, "{lo}");
        assert_eq!(wilson(0, 0), (0.0, 1.0));
    }

    #[test]
    fn sign_test_tails() {
        assert!((sign_test_p(10, 10) - 0.5f64.powi(10)).abs() < 1e-15);
        assert!((sign_test_p(5, 10) - 0.623_046_875).abs() < 1e-12);
        assert_eq!(sign_test_p(0, 4), 1.0);
        // large n does not underflow
        let p = sign_test_p(600, 1000);
        assert!(p > 0.0 && p < 1e-9, "{p}");
    }

    #[test]
    fn clustered_interval_widens_with_correlated_episodes() {
        // the same pooled rate 0.1: spread evenly vs concentrated in one episode
        let even = vec![(10, 100); 10];
        let lumpy: Vec<(usize, usize)> = (0..10)
            .map(|i| (if i == 0 { 100 } else { 0 }, 100))
            .collect();
        let (a, b) = cluster_interval(&even).unwrap();
        let (c, d) = cluster_interval(&lumpy).unwrap();
        assert!(a == 0.1 && b == 0.1, "no between-episode spread: {a} {b}");
        assert!(c < 0.05 && d > 0.25, "{c} {d}");
        assert!(cluster_interval(&[(1, 10)]).is_none());
    }
}
