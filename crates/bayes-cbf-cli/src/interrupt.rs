//! Ctrl-C (SIGINT) and SIGTERM during a scenario run, the default demo or a
//! sweep: the first
//! stops it before its next step, or before it publishes its files
//! ([`check`]), so that its staged outputs are removed and nothing of it is
//! left; a second ends the process at once (which can leave the hidden
//! staging directory, removed by the next run into the same place).
//! Commands that do not ask for [`stop_flag`] keep the default: the signal
//! ends them. A signal the process inherited as ignored stays ignored.

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
            for signal in [libc::SIGINT, libc::SIGTERM] {
                // SAFETY: the handler only touches an atomic (above); a
                // signal ignored by the parent (a background job) is put
                // back to ignored
                unsafe {
                    if libc::signal(signal, handler) == libc::SIG_IGN {
                        libc::signal(signal, libc::SIG_IGN);
                    }
                }
            }
        });
    }
    Arc::clone(flag)
}

/// [`bayes_cbf::Error::Interrupted`] if a signal came since [`stop_flag`]
/// was first asked for: called before a run publishes what it computed.
pub fn check() -> anyhow::Result<()> {
    match STOP.get() {
        Some(stop) if stop.load(Ordering::SeqCst) => Err(bayes_cbf::Error::Interrupted.into()),
        _ => Ok(()),
    }
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
