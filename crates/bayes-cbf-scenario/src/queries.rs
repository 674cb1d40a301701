//! One-shot queries of a model: the moments of a barrier condition at
//! `(x, u)` and one safety-filter step, with typed, serialisable reports.
//! `bayes-cbf moments`, `bayes-cbf control` and the Python package share
//! them (interfaces.md).

use crate::bail;
use crate::error::{check_vector, Context, Result};
use bayes_cbf::barrier::{
    cbc_moments, mc_cbc_moments, ConditionMoments, DynBarrier, McSettings, MomentWorkspace,
};
use bayes_cbf::control::{ControlOutput, ControlStatus, SafetyController, SafetySettings};
use bayes_cbf::gp::Mvgp;
use serde::Serialize;
use std::sync::Arc;

/// The moments of a barrier condition `CBC⁽ʳ⁾(x, u)` under the posterior
/// (paper, Lemma 2 and Thm. 2; Monte Carlo beyond relative degree 2).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MomentsReport {
    /// Relative degree `r` of the barrier.
    pub relative_degree: usize,
    /// `E[CBC]` at `u`.
    pub mean: f64,
    /// `Var[CBC]` at `u`.
    pub variance: f64,
    /// `h(x)`.
    pub h: f64,
    /// `e` with `E[CBC] = eᵀ u̲`, `u̲ = (1, u)`.
    pub e: Vec<f64>,
    /// `Cov(z)` with `Var[CBC] = u̲ᵀ Cov(z) u̲`, rows of `1 + m`.
    pub cov: Vec<Vec<f64>>,
    /// `"exact"` (relative degree 1 and 2) or `"monte_carlo"`.
    pub method: &'static str,
    /// Monte Carlo draws.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub samples: Option<usize>,
    /// Monte Carlo standard error of the mean.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mean_se: Option<f64>,
    /// Monte Carlo standard error of the variance.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub variance_se: Option<f64>,
}

/// Checks that `barrier` is for the model's state dimension; `label` names it.
pub fn check_barrier(model: &Mvgp, barrier: &dyn DynBarrier, label: &str) -> Result<()> {
    let n = model.state_dim();
    if barrier.state_dim() != n {
        bail!(
            "{label} is for state dimension {}, but the model's state_dim is {n}",
            barrier.state_dim()
        );
    }
    Ok(())
}

/// The moments of `barrier`'s condition at state `x` and control `u`:
/// exact for relative degree 1 and 2, Monte Carlo (`mc`) beyond.
pub fn condition_moments(
    model: &Mvgp,
    barrier: &dyn DynBarrier,
    label: &str,
    x: &[f64],
    u: &[f64],
    mc: &McSettings,
) -> Result<MomentsReport> {
    check_barrier(model, barrier, label)?;
    // the Monte Carlo settings are checked whether or not this barrier
    // needs them: a bad value is a bad value
    mc.validate()?;
    check_vector("x", x, model.state_dim(), "the model's state_dim")?;
    check_vector("u", u, model.control_dim(), "the model's control_dim")?;
    let m = model.control_dim();
    let (mom, method, samples, mean_se, variance_se) = if barrier.relative_degree() <= 2 {
        let mut ws = MomentWorkspace::new(model);
        ws.update(model, x, barrier.relative_degree())
            .context("x")?;
        let mut mom = ConditionMoments::zeros(m);
        cbc_moments(&mut ws, barrier, &mut mom).with_context(|| label.to_string())?;
        (mom, "exact", None, None, None)
    } else {
        let est = mc_cbc_moments(model, barrier, x, mc).with_context(|| label.to_string())?;
        let (se_m, se_v) = est.standard_errors(u);
        (
            est.moments,
            "monte_carlo",
            Some(est.samples),
            Some(se_m),
            Some(se_v),
        )
    };
    mom.check_finite(label, x)?;
    let mean = mom.mean(u);
    let variance = mom
        .variance_resolved(u)
        .map_err(bayes_cbf::Error::from)
        .with_context(|| label.to_string())?;
    if !(mean.is_finite() && variance.is_finite()) {
        bail!(
            "{label}: the condition at u = {u:?} overflows (mean {mean:e}, variance {variance:e})"
        );
    }
    let cov = (0..m + 1)
        .map(|i| mom.cov.row(i).iter().copied().collect())
        .collect();
    Ok(MomentsReport {
        relative_degree: mom.relative_degree,
        mean,
        variance,
        h: mom.value,
        e: mom.e.clone(),
        cov,
        method,
        samples,
        mean_se,
        variance_se,
    })
}

/// One barrier constraint at the returned control.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ConstraintReport {
    /// The barrier's label.
    pub barrier: String,
    /// Its relative degree.
    pub relative_degree: usize,
    /// `E[CBC]`.
    pub mean: f64,
    /// `√Var[CBC]`.
    pub std: f64,
    /// Safety factor `c(p)`.
    pub c: f64,
    /// `mean − ζ − c·std` (≥ 0 when met).
    pub slack: f64,
}

/// One safety-filter step (`bayes-cbf control`, `SafetyFilter.filter`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ControlReport {
    /// `"optimal"` or `"infeasible"`.
    pub status: &'static str,
    /// The control.
    pub u: Vec<f64>,
    /// One report per barrier.
    pub constraints: Vec<ConstraintReport>,
    /// The fallback that produced `u` when infeasible.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fallback: Option<&'static str>,
    /// Largest feasible probability when infeasible.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub p_star: Option<f64>,
    /// Barriers violated at the fallback control.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub violated: Option<Vec<usize>>,
}

impl ControlReport {
    /// The report of a step's `out`, with barrier `labels` and relative
    /// `degrees` in the controller's order.
    pub fn from_output(out: &ControlOutput, labels: &[String], degrees: &[usize]) -> Self {
        let constraints = out
            .constraints
            .iter()
            .zip(labels.iter().zip(degrees))
            .map(|(c, (l, r))| ConstraintReport {
                barrier: l.clone(),
                relative_degree: *r,
                mean: c.mean,
                std: c.std,
                c: c.c,
                slack: c.slack,
            })
            .collect();
        let (status, fallback, p_star, violated) = status_parts(out);
        ControlReport {
            status,
            u: out.u.clone(),
            constraints,
            fallback,
            p_star,
            violated,
        }
    }
}

/// The outcome of a step as reported: status name, fallback name, `p*` and
/// the violated barriers (the last three only when infeasible).
#[allow(clippy::type_complexity)]
pub fn status_parts(
    out: &ControlOutput,
) -> (
    &'static str,
    Option<&'static str>,
    Option<f64>,
    Option<Vec<usize>>,
) {
    match &out.status {
        ControlStatus::Optimal | ControlStatus::AlmostOptimal => ("optimal", None, None, None),
        ControlStatus::Infeasible(info) => (
            "infeasible",
            Some(info.fallback.name()),
            info.p_star,
            Some(info.violated.clone()),
        ),
    }
}

/// One step of a safety filter built for `barriers` (labelled) at state `x`
/// around `u_ref`.
pub fn control_step(
    model: &Mvgp,
    barriers: Vec<(String, Arc<dyn DynBarrier>)>,
    settings: SafetySettings,
    mc: &McSettings,
    x: &[f64],
    u_ref: &[f64],
) -> Result<ControlReport> {
    let (n, m) = (model.state_dim(), model.control_dim());
    for (label, b) in &barriers {
        check_barrier(model, b.as_ref(), label)?;
    }
    check_vector("x", x, n, "the model's state_dim")?;
    check_vector("u_ref", u_ref, m, "the model's control_dim")?;
    let labels: Vec<String> = barriers.iter().map(|(l, _)| l.clone()).collect();
    let degrees: Vec<usize> = barriers.iter().map(|(_, b)| b.relative_degree()).collect();
    // the barrier an evaluation error is of: the only one, or one whose h
    // is not finite at x
    let culprit = match &barriers[..] {
        [(label, _)] => Some(label.clone()),
        bs => bs
            .iter()
            .find(|(_, b)| !b.value(x).is_finite())
            .map(|(l, _)| l.clone()),
    };
    let bs = barriers.into_iter().map(|(_, b)| b).collect();
    let mut ctrl = SafetyController::new(n, m, bs, None, settings)?;
    ctrl.set_monte_carlo(*mc);
    let mut out = ControlOutput::new(m, labels.len());
    ctrl.step(model, x, u_ref, None, &mut out)
        .map_err(|e| match (&e, culprit) {
            (bayes_cbf::Error::Input(_), Some(label)) => {
                crate::Error::from(e).context(format!("barrier '{label}'"))
            }
            _ => e.into(),
        })?;
    Ok(ControlReport::from_output(&out, &labels, &degrees))
}
