//! The starting point and the settings of a marginal-likelihood fit as the
//! `fit` command and the learning demo set them up (the fit itself is
//! [`bayes_cbf::gp::fit`]).

use crate::error::{Context, Result};
use crate::parse::parse_rank;
use crate::prior_spec::PriorSpec;
use bayes_cbf::gp::{FitSettings, InputMap, Mvgp, MvgpHyper, Rbf};
use nalgebra::DMatrix;

/// The MVGP a fit starts from: unit lengthscales and signal variance on
/// `input_map(x)`, `A = I`, `B = I`, `σ = 0.1`, prior mean `prior`, no data.
pub fn initial_model(n: usize, m: usize, prior: &PriorSpec, input_map: InputMap) -> Result<Mvgp> {
    let d = input_map.output_dim(n);
    let hyper = MvgpHyper {
        kernel: Rbf::new(vec![1.0; d], 1.0)?,
        A: DMatrix::identity(n, n),
        B: DMatrix::identity(m + 1, m + 1),
        sigma: 0.1,
    };
    Ok(Mvgp::new(n, m, hyper, prior.to_prior()?, input_map)?)
}

/// Validated fit settings from options as a user writes them: `ranks` are
/// the `(field, text)` of the structures of `A` and `B` (`full`, `diag` or
/// an integer rank; errors name the field), the rest as in [`FitSettings`].
pub fn fit_settings(
    ranks: [(&str, &str); 2],
    max_iters: u64,
    restarts: usize,
    seed: u64,
    sigma_min: f64,
) -> Result<FitSettings> {
    let [(field_a, text_a), (field_b, text_b)] = ranks;
    let settings = FitSettings {
        rank_a: parse_rank(field_a, text_a)?,
        rank_b: parse_rank(field_b, text_b)?,
        max_iters,
        restarts,
        seed,
        sigma_min,
        ..FitSettings::default()
    };
    settings.validate().context("fit settings")?;
    Ok(settings)
}

#[cfg(test)]
mod tests {
    use super::*;
    use bayes_cbf::gp::Rank;

    #[test]
    fn settings_and_start() {
        let s = fit_settings([("--rank-a", "diag"), ("--rank-b", "1")], 30, 2, 7, 0.0).unwrap();
        assert_eq!((s.rank_a, s.rank_b), (Rank::Diagonal, Rank::Low(1)));
        assert_eq!((s.max_iters, s.restarts, s.seed), (30, 2, 7));
        let e = fit_settings([("--rank-a", "full"), ("--rank-b", "x")], 30, 0, 0, 0.0);
        assert!(e.unwrap_err().to_string().contains("--rank-b"));
        let e = fit_settings([("a", "full"), ("b", "full")], 0, 0, 0, 0.0);
        assert!(e.unwrap_err().to_string().contains("max_iters"));
        let model = initial_model(2, 1, &PriorSpec::Zero, InputMap::periodic(2, &[0])).unwrap();
        assert_eq!(model.hyper().kernel.lengthscales().len(), 3);
        assert_eq!((model.len(), model.hyper().sigma), (0, 0.1));
    }
}
