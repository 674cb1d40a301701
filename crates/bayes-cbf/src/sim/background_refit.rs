//! Hyperparameter refits on a background thread, swapped into the closed
//! loop at a fixed step so that runs stay deterministic.
//!
//! ## Semantics
//!
//! A refit due after step `k` (the schedule of
//! [`LoopSettings::refit_every`](super::LoopSettings::refit_every) and
//! `refit_geometric`) launches [`fit`](crate::gp::fit) on a copy of the model as it is at
//! that moment: the same data, factor and hyperparameters, and the same fit
//! settings and seed as the synchronous refit. The loop goes on with the
//! previous hyperparameters, learning as usual, and after step `k + d`
//! (`d` = [`LoopSettings::refit_background`](super::LoopSettings::refit_background))
//! it joins the thread and swaps in the refitted model, brought up to date
//! by replaying the observations added and removed since the launch (O(k²)
//! each, in the same order, so the data are exactly the loop's). So:
//!
//! - the hyperparameters are bit-for-bit those of the synchronous refit at
//!   step `k`; they take effect `d` steps later instead of immediately;
//! - the result depends on the step count only, never on thread timing: if
//!   the fit has not finished after step `k + d` the loop waits for it
//!   (choose `d` from the fit's measured duration and the control period);
//! - a refit that falls due while another is running is skipped (logged);
//! - a refit still running when the run ends is joined and discarded.
//!
//! Cost in the loop: the copy at launch (a memory copy of the factor,
//! O(k²)), and at the swap the replay of the `≈ d` updates since the launch
//! (O(d k²)); the O(k³) refactorisations and the optimiser run on the other
//! thread. Should a replayed observation be rejected under the new
//! hyperparameters (a factorisation that needs more than the bounded
//! jitter), the swap falls back to refactorising the loop's data with the
//! new hyperparameters (O(k³), on the loop's thread).
//!
//! The fit's warnings are shown when issued, on its thread, and join the
//! [record](crate::warnings::Record) of the loop's thread at the swap, as a
//! synchronous refit's would; those of a discarded refit are not kept.

use crate::error::Error;
use crate::gp::{fit_until, FitReport, FitSettings, Mvgp};
use crate::warnings::{self, Issued, Record, WarnOnce};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::thread::JoinHandle;

/// One change of the model's data since the launch.
#[derive(Debug)]
enum DataOp {
    Add(Vec<f64>, Vec<f64>, Vec<f64>),
    Remove(usize),
}

/// A refit that failed, in the loop or in the background: the model keeps
/// its hyperparameters.
pub(crate) static REFIT_FAILED: WarnOnce = WarnOnce::new("refit_failed");
/// The data added and removed since a background refit's launch could not
/// be replayed on the refitted model.
static REFIT_REPLAY_FAILED: WarnOnce = WarnOnce::new("refit_replay_failed");

/// What the fit's thread hands back: the refitted model, or why not, and
/// the warnings it issued.
type Fitted = (Result<(Mvgp, FitReport), Error>, Vec<Issued>);

/// A refit running on another thread.
#[derive(Debug)]
pub(crate) struct BackgroundRefit {
    handle: JoinHandle<Fitted>,
    launched: usize,
    apply_after: usize,
    log: Vec<DataOp>,
}

impl BackgroundRefit {
    /// Starts `fit(copy of model, settings)` after step `step`, stopped
    /// once the loop's `stop` flag is set; the result is applied after step
    /// `step + lag`.
    pub(crate) fn launch(
        model: &Mvgp,
        settings: FitSettings,
        step: usize,
        lag: usize,
        stop: Arc<AtomicBool>,
    ) -> Self {
        let mut copy = model.clone();
        let handle = std::thread::spawn(move || {
            let record = Record::start();
            let fitted = fit_until(&mut copy, &settings, &stop).map(|report| (copy, report));
            (fitted, record.finish())
        });
        Self {
            handle,
            launched: step,
            apply_after: step + lag,
            log: Vec::new(),
        }
    }

    /// Whether the swap is due after step `step`.
    pub(crate) fn due(&self, step: usize) -> bool {
        step >= self.apply_after
    }

    /// Records an observation added to the loop's model since the launch.
    pub(crate) fn record_add(&mut self, x: Vec<f64>, u: Vec<f64>, xdot: Vec<f64>) {
        self.log.push(DataOp::Add(x, u, xdot));
    }

    /// Records the removal of observation `j` from the loop's model.
    pub(crate) fn record_remove(&mut self, j: usize) {
        self.log.push(DataOp::Remove(j));
    }

    /// Joins the thread and swaps the refitted hyperparameters into `model`
    /// (module docs); the fit's warnings join this thread's record. A
    /// failed fit keeps the previous hyperparameters, as the synchronous
    /// refit does; a panic in the fit is re-raised.
    pub(crate) fn finish(self, model: &mut Mvgp) {
        let launched = self.launched;
        let (fitted, issued) = self
            .handle
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
        warnings::adopt(issued);
        let mut fitted = match fitted {
            Ok((fitted, _report)) => fitted,
            // the loop's stop flag is set: it ends at its next step
            Err(Error::Interrupted) => return,
            Err(e) => {
                REFIT_FAILED.issue(|| {
                    format!("refit launched at step {launched} failed ({e}); keeping the previous hyperparameters")
                });
                return;
            }
        };
        for op in &self.log {
            let replayed = match op {
                DataOp::Add(x, u, xd) => fitted.add_observation(x, u, xd),
                DataOp::Remove(j) => {
                    fitted.remove_observation(*j);
                    Ok(())
                }
            };
            if let Err(e) = replayed {
                let outcome = match model.set_hyper(fitted.hyper().clone()) {
                    Ok(()) => "refactorised the current data with the new hyperparameters".into(),
                    Err(e) => format!(
                        "the new hyperparameters do not factorise the current data ({e}); keeping the previous ones"
                    ),
                };
                REFIT_REPLAY_FAILED.issue(|| {
                    format!("refit launched at step {launched}: replaying the data since the launch failed ({e}); {outcome}")
                });
                return;
            }
        }
        *model = fitted;
    }

    /// Joins the thread and drops its result and warnings (the run ended
    /// first).
    pub(crate) fn abandon(self) {
        if let Err(panic) = self.handle.join() {
            std::panic::resume_unwind(panic);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A model of `ẋ = (x₀ + u, 0)` on data whose second state is 0.5 in
    /// every row: a fit cannot learn that input's lengthscale and warns.
    fn model() -> Mvgp {
        let mut m = crate::gp::plain_model(2, 1, 1.0, 1.0, 0.1);
        for j in 0..20 {
            let (x0, u) = ((j as f64 * 0.7).sin(), (j as f64 * 1.3).cos());
            m.add_observation(&[x0, 0.5], &[u], &[x0 + u, 0.0]).unwrap();
        }
        m
    }

    /// The warnings of a background refit join the loop thread's record at
    /// the swap, the same as the synchronous refit's; a discarded refit's
    /// do not.
    #[test]
    fn a_background_refit_s_warnings_join_the_loop_s_record_at_the_swap() {
        let settings = FitSettings {
            max_iters: 20,
            ..FitSettings::default()
        };
        let stop = Arc::new(AtomicBool::new(false));
        let sites = |issued: Vec<Issued>| issued.into_iter().map(|i| i.site).collect::<Vec<_>>();
        let record = Record::start();
        fit_until(&mut model(), &settings, &stop).unwrap();
        let sync = sites(record.finish());
        assert_eq!(sync, ["lengthscale_unfit"]);

        let mut m = model();
        let record = Record::start();
        let bg = BackgroundRefit::launch(&m, settings.clone(), 0, 1, Arc::clone(&stop));
        bg.finish(&mut m);
        assert_eq!(sites(record.finish()), sync);

        let record = Record::start();
        BackgroundRefit::launch(&m, settings, 0, 1, stop).abandon();
        assert!(record.finish().is_empty());
    }
}
