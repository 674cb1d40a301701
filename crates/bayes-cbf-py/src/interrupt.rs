//! Long library calls that Ctrl-C stops. Python runs its signal handlers
//! only on the main thread and only when asked (`PyErr_CheckSignals`), which
//! a call in Rust with the GIL released never does: the work runs on a
//! worker thread while the calling thread checks for signals, and a
//! signal's exception (`KeyboardInterrupt`) sets the work's stop flag and
//! is raised once the work has stopped.

use pyo3::prelude::*;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// How often the calling thread checks for signals.
const POLL: Duration = Duration::from_millis(50);

/// `work(stop)` on a worker thread, the GIL released, and the exception of
/// a Python signal handler that raised meanwhile (Ctrl-C's
/// `KeyboardInterrupt`), which set `stop`: the caller raises it after
/// keeping what `work` did, since `work` may have finished as the handler
/// ran. Outside the main thread, where Python handles no signals, this is
/// `work` with a flag that stays clear.
pub fn interruptible<T: Send>(
    py: Python<'_>,
    work: impl FnOnce(&Arc<AtomicBool>) -> T + Send,
) -> (T, PyResult<()>) {
    let stop = Arc::new(AtomicBool::new(false));
    let mut signal: Option<PyErr> = None;
    let caller = std::thread::current();
    let out = py.detach(|| {
        std::thread::scope(|s| {
            let worker = s.spawn(|| {
                let out = work(&stop);
                caller.unpark();
                out
            });
            while !worker.is_finished() {
                std::thread::park_timeout(POLL);
                if signal.is_none() && !worker.is_finished() {
                    if let Err(e) = Python::attach(|py| py.check_signals()) {
                        signal = Some(e);
                        stop.store(true, Ordering::Relaxed);
                    }
                }
            }
            worker
                .join()
                .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
        })
    });
    (out, signal.map_or(Ok(()), Err))
}
