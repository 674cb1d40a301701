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

use crate::error::Error;
use crate::gp::{fit_until, FitReport, FitSettings, Mvgp};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::thread::JoinHandle;

/// One change of the model's data since the launch.
#[derive(Debug)]
enum DataOp {
    Add(Vec<f64>, Vec<f64>, Vec<f64>),
    Remove(usize),
}

/// A refit running on another thread.
#[derive(Debug)]
pub(crate) struct BackgroundRefit {
    handle: JoinHandle<Result<(Mvgp, FitReport), Error>>,
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
            let report = fit_until(&mut copy, &settings, &stop)?;
            Ok((copy, report))
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
    /// (module docs). A failed fit keeps the previous hyperparameters, as
    /// the synchronous refit does; a panic in the fit is re-raised.
    pub(crate) fn finish(self, model: &mut Mvgp) {
        let launched = self.launched;
        let (mut fitted, _report) = match self.handle.join() {
            Ok(Ok(r)) => r,
            // the loop's stop flag is set: it ends at its next step
            Ok(Err(Error::Interrupted)) => return,
            Ok(Err(e)) => {
                log::warn!("refit launched at step {launched} failed ({e}); keeping the previous hyperparameters");
                return;
            }
            Err(panic) => std::panic::resume_unwind(panic),
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
                log::warn!("refit launched at step {launched}: replaying the data since the launch failed ({e}); refactorising with the new hyperparameters");
                if let Err(e) = model.set_hyper(fitted.hyper().clone()) {
                    log::warn!("refit launched at step {launched}: the new hyperparameters do not factorise the current data ({e}); keeping the previous ones");
                }
                return;
            }
        }
        *model = fitted;
    }

    /// Joins the thread and drops its result (the run ended first).
    pub(crate) fn abandon(self) {
        if let Err(panic) = self.handle.join() {
            std::panic::resume_unwind(panic);
        }
    }
}
