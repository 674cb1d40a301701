//! Warnings issued once per scope.
//!
//! A warning that a run would repeat at every step, or a sweep at every
//! seed, is issued once: by the first [`WarnOnce::first`] of its site in the
//! current scope. The process is one scope until a [`Scope`] is entered: the
//! scenario crate enters one for each run, sweep and experiment it is asked
//! for, and the Python package for each filter it builds, so that a second
//! run with the same mistake is warned of too. A scope entered while another
//! is open (a sweep's runs, on any thread) is part of it. A scope that closes
//! leaves its sites as they are until the next one opens: the steps of a
//! filter after its constructor returned warn in the scope it opened, or in
//! a later one (a program that builds a filter at every step is warned at
//! every step).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

/// The current scope; sites remember the scope they last warned in.
static SCOPE: AtomicU64 = AtomicU64::new(1);
/// Scopes open now (nested or on other threads); entering the first one
/// and advancing [`SCOPE`] happen under the lock, as one step.
static OPEN: Mutex<usize> = Mutex::new(0);

/// Opens a new scope now, whatever is open: every [`WarnOnce`] site may
/// warn again.
pub fn new_scope() {
    SCOPE.fetch_add(1, Ordering::Relaxed);
}

/// An open scope: a new one if none was open, else part of the open one;
/// closed when dropped.
#[derive(Debug)]
#[must_use = "the scope closes when this is dropped"]
pub struct Scope(());

impl Scope {
    /// Enters a scope ([module docs](self)).
    pub fn enter() -> Self {
        let mut open = OPEN.lock().unwrap_or_else(|e| e.into_inner());
        if *open == 0 {
            new_scope();
        }
        *open += 1;
        Scope(())
    }
}

impl Drop for Scope {
    fn drop(&mut self) {
        let mut open = OPEN.lock().unwrap_or_else(|e| e.into_inner());
        *open = open.saturating_sub(1);
    }
}

/// A warning site that warns once per scope ([module docs](self)).
#[derive(Debug)]
pub struct WarnOnce(AtomicU64);

impl WarnOnce {
    /// A site that has not warned yet.
    pub const fn new() -> Self {
        Self(AtomicU64::new(0))
    }

    /// Whether this is the site's first warning in the current scope (the
    /// site counts as having warned from now on).
    pub fn first(&self) -> bool {
        let scope = SCOPE.load(Ordering::Relaxed);
        self.0.swap(scope, Ordering::Relaxed) != scope
    }

    /// Whether the site has warned in the current scope.
    pub fn warned(&self) -> bool {
        self.0.load(Ordering::Relaxed) == SCOPE.load(Ordering::Relaxed)
    }
}

impl Default for WarnOnce {
    fn default() -> Self {
        Self::new()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_site_warns_once_per_scope_and_a_nested_scope_is_the_outer_one() {
        static SITE: WarnOnce = WarnOnce::new();
        new_scope();
        assert!(!SITE.warned());
        assert!(SITE.first());
        assert!(SITE.warned());
        assert!(!SITE.first());
        new_scope();
        assert!(SITE.first());
        assert!(!SITE.first());
        // (one test: scopes are global, and tests run at once)
        {
            let _outer = Scope::enter();
            assert!(SITE.first());
            let _inner = Scope::enter();
            assert!(!SITE.first(), "the inner scope is the outer one");
        }
        let _next = Scope::enter();
        assert!(SITE.first(), "a scope entered after is new");
    }
}
