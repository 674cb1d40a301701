//! Warnings issued once per scope, and recorded for each run.
//!
//! A warning that a run would repeat at every step, or a sweep at every
//! seed, is issued once: by the first [`WarnOnce::issue`] of its site in the
//! current scope. The process is one scope until a [`Scope`] is entered: the
//! scenario crate enters one for each run, sweep and experiment it is asked
//! for, and the Python package for each filter it builds, so that a second
//! run with the same mistake is warned of too. A scope entered while another
//! is open (a sweep's runs, on any thread) is part of it. A scope that closes
//! leaves its sites as they are until the next one opens: the steps of a
//! filter after its constructor returned warn in the scope it opened, or in
//! a later one (a program that builds a filter at every step is warned at
//! every step).
//!
//! A [`Record`] open on a thread keeps, besides, the first warning of each
//! site issued on that thread while it is open, whether or not the scope had
//! already shown it: a sweep shows a warning once, for its first seed, and
//! the record of each run says which of them warned. A thread working for
//! another (a refit in the background) keeps a record of its own and hands
//! it over ([`adopt`]) when its work is taken up.

use std::cell::RefCell;
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
pub struct WarnOnce {
    /// The scope the site last warned in.
    scope: AtomicU64,
    /// Its name in [`Record`]s.
    name: &'static str,
}

impl WarnOnce {
    /// A site that has not warned yet, named `name` in [`Record`]s (one
    /// word in snake case, unique among the sites).
    pub const fn new(name: &'static str) -> Self {
        Self {
            scope: AtomicU64::new(0),
            name,
        }
    }

    /// The site's name.
    pub fn name(&self) -> &'static str {
        self.name
    }

    /// Issues the warning `message()`: shown (`log::warn!`) if this is the
    /// site's first in the current scope, and kept by the [`Record`] open
    /// on this thread if it has none of the site yet. `message` is called
    /// only then, so a warning checked at every step costs no allocation
    /// after its first.
    pub fn issue(&self, message: impl FnOnce() -> String) {
        let show = self.first();
        let record = self.unrecorded();
        if show || record {
            let message = message();
            if record {
                hold(Issued {
                    site: self.name,
                    message: message.clone(),
                });
            }
            if show {
                log::warn!("{message}");
            }
        }
    }

    /// Keeps the warning `message()` in the [`Record`] open on this thread,
    /// if it has none of the site yet, without showing it: for a site that
    /// shows its warnings by a rule of its own. `message` is called only
    /// then.
    pub fn keep(&self, message: impl FnOnce() -> String) {
        if self.unrecorded() {
            hold(Issued {
                site: self.name,
                message: message(),
            });
        }
    }

    /// Whether [`issue`](Self::issue) would show or record a warning now:
    /// checks that only feed a warning can be skipped when not.
    pub fn pending(&self) -> bool {
        !self.warned() || self.unrecorded()
    }

    /// Whether this is the site's first warning in the current scope (the
    /// site counts as having warned from now on).
    fn first(&self) -> bool {
        let scope = SCOPE.load(Ordering::Relaxed);
        self.scope.swap(scope, Ordering::Relaxed) != scope
    }

    /// Whether the site has warned in the current scope.
    fn warned(&self) -> bool {
        self.scope.load(Ordering::Relaxed) == SCOPE.load(Ordering::Relaxed)
    }

    /// A record is open on this thread and holds nothing of this site.
    fn unrecorded(&self) -> bool {
        RECORD.with_borrow(|r| {
            r.as_ref()
                .is_some_and(|r| r.iter().all(|i| i.site != self.name))
        })
    }
}

/// A warning kept by a [`Record`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Issued {
    /// The site's [name](WarnOnce::name).
    pub site: &'static str,
    /// The warning.
    pub message: String,
}

thread_local! {
    /// The warnings of the record open on this thread, if one is.
    static RECORD: RefCell<Option<Vec<Issued>>> = const { RefCell::new(None) };
}

/// Adds to the [`Record`] open on this thread the warnings `issued`
/// elsewhere (a [`Record`] finished on another thread), those of sites it
/// holds none of, in order; they are not shown again. Nothing happens when
/// no record is open.
pub fn adopt(issued: Vec<Issued>) {
    issued.into_iter().for_each(hold);
}

/// Adds `issued` to the record open on this thread, if one is and it holds
/// none of its site.
fn hold(issued: Issued) {
    RECORD.with_borrow_mut(|r| {
        if let Some(r) = r {
            if r.iter().all(|held| held.site != issued.site) {
                r.push(issued);
            }
        }
    });
}

/// The warnings issued on this thread from [`start`](Self::start) to
/// [`finish`](Self::finish), the first of each site ([module
/// docs](self)). A record started while another is open on the thread
/// replaces it until finished or dropped; the outer one then goes on.
#[derive(Debug)]
#[must_use = "finish the record to read it"]
pub struct Record {
    /// The record this one replaced.
    outer: Option<Vec<Issued>>,
}

impl Record {
    /// Starts recording on this thread.
    pub fn start() -> Self {
        Record {
            outer: RECORD.replace(Some(Vec::new())),
        }
    }

    /// The warnings recorded, in the order they were issued.
    pub fn finish(mut self) -> Vec<Issued> {
        let outer = self.outer.take();
        let issued = RECORD.replace(outer).unwrap_or_default();
        std::mem::forget(self);
        issued
    }
}

impl Drop for Record {
    fn drop(&mut self) {
        RECORD.set(self.outer.take());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_site_warns_once_per_scope_and_a_nested_scope_is_the_outer_one() {
        static SITE: WarnOnce = WarnOnce::new("test_scope_site");
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
        a_record_keeps_the_first_warning_of_each_site_whether_or_not_it_was_shown();
    }

    fn a_record_keeps_the_first_warning_of_each_site_whether_or_not_it_was_shown() {
        static A: WarnOnce = WarnOnce::new("test_record_a");
        static B: WarnOnce = WarnOnce::new("test_record_b");
        let calls = std::cell::Cell::new(0);
        let message = |text: &str| {
            calls.set(calls.get() + 1);
            text.to_string()
        };
        // shown in the scope before the record starts
        A.issue(|| message("a0"));
        assert!(A.warned());
        assert!(!A.pending(), "shown, and no record open");
        let record = Record::start();
        assert!(A.pending(), "the record has nothing of A yet");
        A.issue(|| message("a1"));
        A.issue(|| message("a2"));
        B.issue(|| message("b1"));
        assert!(!A.pending() && !B.pending());
        let inner = Record::start();
        B.issue(|| message("b2"));
        assert_eq!(
            inner.finish(),
            vec![Issued {
                site: "test_record_b",
                message: "b2".into()
            }]
        );
        B.issue(|| message("b3"));
        // a dropped record leaves the outer one as it was
        drop(Record::start());
        assert!(!A.pending());
        let got = record.finish();
        let want = [("test_record_a", "a1"), ("test_record_b", "b1")];
        assert_eq!(got.len(), 2, "{got:?}");
        for (g, (site, message)) in got.iter().zip(want) {
            assert_eq!((g.site, g.message.as_str()), (site, message));
        }
        // a message is built only when shown or recorded: a0, a1, b1, b2
        assert_eq!(calls.get(), 4);
        A.issue(|| message("a3"));
        assert_eq!(calls.get(), 4, "shown in this scope, and no record open");
        assert!(RECORD.with_borrow(Option::is_none));
        a_record_adopts_another_thread_s_and_keeps_without_showing();
    }

    fn a_record_adopts_another_thread_s_and_keeps_without_showing() {
        static C: WarnOnce = WarnOnce::new("test_record_c");
        static D: WarnOnce = WarnOnce::new("test_record_d");
        let record = Record::start();
        C.issue(|| "c1".into());
        let elsewhere = std::thread::spawn(|| {
            let record = Record::start();
            C.issue(|| "c2".into());
            D.issue(|| "d1".into());
            record.finish()
        })
        .join()
        .unwrap();
        assert_eq!(elsewhere.len(), 2);
        adopt(elsewhere);
        D.keep(|| unreachable!("D is held already"));
        let got: Vec<_> = record.finish().into_iter().map(|i| i.message).collect();
        assert_eq!(got, ["c1", "d1"], "the first of each site, in order");
        // kept, not shown: the new scope's first showing is still to come
        new_scope();
        let record = Record::start();
        D.keep(|| "d2".into());
        assert!(!D.warned());
        assert_eq!(record.finish()[0].message, "d2");
        // with no record open, nothing is kept or adopted
        D.keep(|| unreachable!("no record is open"));
        adopt(vec![Issued {
            site: "test_record_d",
            message: "d3".into(),
        }]);
        assert!(RECORD.with_borrow(Option::is_none));
    }
}
