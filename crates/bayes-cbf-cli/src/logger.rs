//! A tiny [`log`] backend writing to stderr.
//!
//! The library reports the jitter escalation of ill-conditioned Gram
//! matrices with `log::warn!`. During hyperparameter fitting that can happen
//! at many trial hyperparameters the optimiser then leaves behind, so
//! [`hold_warnings`] collects the warnings of a fit into one summary line
//! (all are shown with `-v`).

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Mutex;

struct StderrLogger;

static LOGGER: StderrLogger = StderrLogger;
static VERBOSE: AtomicU64 = AtomicU64::new(0);
static HOLDING: AtomicBool = AtomicBool::new(false);
static HELD: AtomicU64 = AtomicU64::new(0);
static FIRST_HELD: Mutex<Option<String>> = Mutex::new(None);

fn label(level: log::Level) -> &'static str {
    match level {
        log::Level::Error => "error",
        log::Level::Warn => "warning",
        log::Level::Info => "info",
        log::Level::Debug => "debug",
        log::Level::Trace => "trace",
    }
}

impl log::Log for StderrLogger {
    fn enabled(&self, metadata: &log::Metadata<'_>) -> bool {
        metadata.level() <= log::max_level()
    }

    fn log(&self, record: &log::Record<'_>) {
        if !self.enabled(record.metadata()) {
            return;
        }
        let held = record.level() == log::Level::Warn
            && HOLDING.load(Ordering::Relaxed)
            && VERBOSE.load(Ordering::Relaxed) == 0;
        if held {
            if HELD.fetch_add(1, Ordering::Relaxed) == 0 {
                let mut first = FIRST_HELD.lock().unwrap_or_else(|e| e.into_inner());
                *first = Some(record.args().to_string());
            }
            return;
        }
        note!("{}: {}", label(record.level()), record.args());
    }

    fn flush(&self) {}
}

/// Installs the stderr logger; `verbosity` 0 shows warnings, 1 info, 2+ debug.
pub fn init_logger(verbosity: u8) {
    let level = match verbosity {
        0 => log::LevelFilter::Warn,
        1 => log::LevelFilter::Info,
        _ => log::LevelFilter::Debug,
    };
    VERBOSE.store(u64::from(verbosity), Ordering::Relaxed);
    // A second installation (impossible in the binary) is harmless.
    if log::set_logger(&LOGGER).is_ok() {
        log::set_max_level(level);
    }
}

/// Runs `f` holding back its warnings (unless `-v`), then prints one line
/// saying how many there were during `what`, quoting the first.
pub fn hold_warnings<T>(what: &str, f: impl FnOnce() -> T) -> T {
    let (out, held, first) = collect_warnings(f);
    if held > 0 {
        let first = first.unwrap_or_default();
        note!("warning: {held} warning(s) during {what}, the first: {first} (-v shows all)");
    }
    out
}

/// Runs `f` with warnings held back; returns its result, the number of
/// warnings held and the first of them.
fn collect_warnings<T>(f: impl FnOnce() -> T) -> (T, u64, Option<String>) {
    HELD.store(0, Ordering::Relaxed);
    *FIRST_HELD.lock().unwrap_or_else(|e| e.into_inner()) = None;
    HOLDING.store(true, Ordering::Relaxed);
    let out = f();
    HOLDING.store(false, Ordering::Relaxed);
    let first = FIRST_HELD.lock().unwrap_or_else(|e| e.into_inner()).take();
    (out, HELD.swap(0, Ordering::Relaxed), first)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn warnings_are_held_and_counted() {
        init_logger(0);
        let (v, held, first) = collect_warnings(|| {
            log::warn!("jitter 1");
            log::warn!("jitter 2");
            log::info!("not a warning");
            7
        });
        assert_eq!((v, held), (7, 2));
        assert_eq!(first.as_deref(), Some("jitter 1"));
        let (_, held, first) = collect_warnings(|| ());
        assert_eq!((held, first), (0, None));
        assert_eq!(hold_warnings("a test", || 3), 3);
    }
}
