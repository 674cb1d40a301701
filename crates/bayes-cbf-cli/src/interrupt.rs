//! Ctrl-C (SIGINT) and SIGTERM during a scenario run or a sweep: the first
//! stops it before its next step, so that its staged outputs are removed
//! and nothing of it is left; a second ends the process at once. Commands
//! that do not ask for [`stop_flag`] keep the default: the signal ends them.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, OnceLock};

static STOP: OnceLock<Arc<AtomicBool>> = OnceLock::new();

/// The exit status of a command stopped by a signal (128 + SIGINT).
pub const INTERRUPTED: u8 = 130;

#[cfg(unix)]
extern "C" fn on_signal(_: libc::c_int) {
    // async-signal-safe: an atomic load and swap, or _exit
    if let Some(stop) = STOP.get() {
        if stop.swap(true, Ordering::SeqCst) {
            // SAFETY: _exit is async-signal-safe and ends the process
            unsafe { libc::_exit(i32::from(INTERRUPTED)) }
        }
    }
}

/// The flag that SIGINT and SIGTERM set, the handler installed on the
/// first call.
pub fn stop_flag() -> Arc<AtomicBool> {
    let flag = STOP.get_or_init(|| Arc::new(AtomicBool::new(false)));
    #[cfg(unix)]
    {
        static INSTALLED: std::sync::Once = std::sync::Once::new();
        INSTALLED.call_once(|| {
            let handler = on_signal as extern "C" fn(libc::c_int) as libc::sighandler_t;
            // SAFETY: the handler only touches an atomic (above)
            unsafe {
                libc::signal(libc::SIGINT, handler);
                libc::signal(libc::SIGTERM, handler);
            }
        });
    }
    Arc::clone(flag)
}

/// Whether `e` is a run stopped by [`stop_flag`].
pub fn is_interrupted(e: &anyhow::Error) -> bool {
    e.chain().any(|c| {
        c.downcast_ref::<bayes_cbf::Error>()
            .is_some_and(|e| matches!(e, bayes_cbf::Error::Interrupted))
            || c.downcast_ref::<bayes_cbf_scenario::Error>()
                .is_some_and(|e| {
                    matches!(
                        e.root(),
                        bayes_cbf_scenario::Error::Core(bayes_cbf::Error::Interrupted)
                    )
                })
    })
}
