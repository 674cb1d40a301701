//! The library's `log` warnings as Python `UserWarning`s. A logger keeps
//! the warnings of a call (from any thread, a sweep's workers included)
//! until the call returns to Python, where [`emit`] hands them to
//! `warnings.warn`; without it they would be lost, since Python shows no
//! Rust log.

use pyo3::prelude::*;
use std::ffi::CString;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;

/// Whether warnings wait for [`emit`] (read without a lock in the filter's
/// step).
static PENDING: AtomicBool = AtomicBool::new(false);
/// The waiting warnings, each once.
static HELD: Mutex<Vec<String>> = Mutex::new(Vec::new());
/// Warnings kept per call; a run that warns at every step repeats itself.
const MAX_HELD: usize = 20;

struct Collector;

static COLLECTOR: Collector = Collector;

impl log::Log for Collector {
    fn enabled(&self, metadata: &log::Metadata) -> bool {
        metadata.level() <= log::Level::Warn
    }

    fn log(&self, record: &log::Record) {
        if !self.enabled(record.metadata()) {
            return;
        }
        if let Ok(mut held) = HELD.lock() {
            let message = record.args().to_string();
            if held.len() < MAX_HELD && !held.contains(&message) {
                held.push(message);
            }
            PENDING.store(true, Ordering::Release);
        }
    }

    fn flush(&self) {}
}

/// Installs the collector as the process's logger (once; a logger another
/// extension installed first is left alone).
pub fn install() {
    if log::set_logger(&COLLECTOR).is_ok() {
        log::set_max_level(log::LevelFilter::Warn);
    }
}

/// Issues the held warnings as `UserWarning`s (an exception if the
/// warnings filter turns them into errors). One atomic load when there
/// are none.
pub fn emit(py: Python<'_>) -> PyResult<()> {
    if !PENDING.swap(false, Ordering::AcqRel) {
        return Ok(());
    }
    let held = HELD
        .lock()
        .map(|mut h| std::mem::take(&mut *h))
        .unwrap_or_default();
    let category = py.get_type::<pyo3::exceptions::PyUserWarning>();
    for message in held {
        let text = CString::new(message.replace('\0', " ")).unwrap_or_default();
        PyErr::warn(py, &category, &text, 1)?;
    }
    Ok(())
}

/// `result` of a call into the library, after issuing the warnings the call
/// raised: each call issues its own, not the next call that emits. An
/// error of the call comes first; a warning the filter turns into an
/// exception comes after a result.
pub fn after<T>(py: Python<'_>, result: PyResult<T>) -> PyResult<T> {
    let warned = emit(py);
    let value = result?;
    warned?;
    Ok(value)
}
