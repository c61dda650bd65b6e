//! Whether what the service depends on answers, as this process last saw
//! it: the job store, the file store and the data folder's disk.
//!
//! A prober asks each of them every second, one question at a time and
//! each within a bound, and everyone else reads the answer without asking
//! again. While one is down the API answers 503 at once instead of waiting
//! on it, `/readyz` says which and why, and workers stop claiming jobs; the
//! prober asks four times as often then, so that work resumes soon after
//! the dependency does.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tokio::sync::watch;

use super::app::Shared;
use super::store::StoreError;

/// How often the prober asks while everything answers.
const PROBE_EVERY: Duration = Duration::from_secs(1);

/// How often it asks while something is down.
const PROBE_DOWN_EVERY: Duration = Duration::from_millis(250);

/// A probe that has not answered by then counts as a failure: `/readyz`
/// must say within a second. The stores bound their own checks below this
/// (`CHECK_WITHIN`); this catches whatever they miss.
const PROBE_WITHIN: Duration = Duration::from_millis(900);

/// What the service depends on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dependency {
    Jobs,
    Files,
    Disk,
}

impl Dependency {
    pub const ALL: [Dependency; 3] = [Dependency::Jobs, Dependency::Files, Dependency::Disk];

    pub fn name(self) -> &'static str {
        match self {
            Dependency::Jobs => "job store",
            Dependency::Files => "file store",
            Dependency::Disk => "disk",
        }
    }

    fn index(self) -> usize {
        self as usize
    }
}

/// A dependency that does not answer, since when, and why.
#[derive(Clone, Debug)]
pub struct Down {
    pub what: Dependency,
    pub since: Instant,
    pub reason: String,
}

impl Down {
    /// One line for a client or a log.
    pub fn message(&self) -> String {
        format!(
            "the {} has not answered for {} s: {}",
            self.what.name(),
            self.since.elapsed().as_secs(),
            self.reason
        )
    }
}

/// The last answer of every dependency.
pub struct Health {
    down: Mutex<[Option<Down>; 3]>,
    /// When each dependency last came back (or the process started).
    back: Mutex<[Instant; 3]>,
    in_flight: [AtomicBool; 3],
    /// Bumped on every change, so that waiters wake.
    changed: watch::Sender<u64>,
}

impl Default for Health {
    fn default() -> Self {
        Health {
            down: Mutex::new([None, None, None]),
            back: Mutex::new([Instant::now(); 3]),
            in_flight: Default::default(),
            changed: watch::channel(0).0,
        }
    }
}

impl Health {
    fn state(&self) -> std::sync::MutexGuard<'_, [Option<Down>; 3]> {
        self.down.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The first of `of` that is down.
    pub fn down_among(&self, of: &[Dependency]) -> Option<Down> {
        let state = self.state();
        of.iter().find_map(|d| state[d.index()].clone())
    }

    /// The first dependency that is down.
    pub fn down(&self) -> Option<Down> {
        self.down_among(&Dependency::ALL)
    }

    /// How long `what` has answered since it last came back; `None` while
    /// it is down.
    pub fn up_for(&self, what: Dependency) -> Option<Duration> {
        if self.state()[what.index()].is_some() {
            return None;
        }
        let back = self.back.lock().unwrap_or_else(|p| p.into_inner());
        Some(back[what.index()].elapsed())
    }

    /// Records an answer, and logs when it changes the picture.
    pub fn record(&self, what: Dependency, answer: Result<(), String>) {
        let mut state = self.state();
        let slot = &mut state[what.index()];
        match (answer, slot.as_ref()) {
            (Ok(()), None) => return,
            (Ok(()), Some(down)) => {
                tracing::warn!(
                    dependency = what.name(),
                    down_ms = down.since.elapsed().as_millis() as u64,
                    "dependency answers again"
                );
                *slot = None;
                self.back.lock().unwrap_or_else(|p| p.into_inner())[what.index()] = Instant::now();
            }
            (Err(reason), None) => {
                tracing::error!(dependency = what.name(), reason = %reason, "dependency down");
                *slot = Some(Down {
                    what,
                    since: Instant::now(),
                    reason,
                });
            }
            (Err(reason), Some(_)) => {
                if let Some(down) = slot.as_mut() {
                    down.reason = reason;
                }
                return;
            }
        }
        drop(state);
        self.changed.send_modify(|n| *n = n.wrapping_add(1));
    }

    /// Marks a dependency down on an error that says so, without waiting
    /// for the next probe: the worker that met it stops claiming now.
    pub fn saw(&self, e: &StoreError) {
        let what = match e {
            StoreError::Unavailable { which, .. } if *which == Dependency::Jobs.name() => {
                Dependency::Jobs
            }
            StoreError::Unavailable { .. } => Dependency::Files,
            StoreError::Full(_) => Dependency::Disk,
            _ => return,
        };
        self.record(what, Err(e.to_string()));
    }

    /// Waits until nothing is down, or `limit` has passed.
    pub async fn until_up(&self, limit: Duration) {
        let mut changes = self.changed.subscribe();
        let _ = tokio::time::timeout(limit, async {
            while self.down().is_some() {
                if changes.changed().await.is_err() {
                    return;
                }
            }
        })
        .await;
    }
}

/// Asks every dependency in turn, for the life of the process.
pub async fn probe(app: Shared) {
    let mut stopping = app.stopping.subscribe();
    loop {
        for what in Dependency::ALL {
            probe_one(&app, what).await;
        }
        let every = if app.health.down().is_some() {
            PROBE_DOWN_EVERY
        } else {
            PROBE_EVERY
        };
        tokio::select! {
            _ = tokio::time::sleep(every) => {}
            _ = stopping.changed() => return,
        }
    }
}

/// One bounded question. A probe still running from before (a store that
/// holds calls past their bound) is not asked again: the answer is "down".
async fn probe_one(app: &Shared, what: Dependency) {
    let flag = &app.health.in_flight[what.index()];
    if flag.swap(true, Ordering::AcqRel) {
        app.health
            .record(what, Err("the previous check has not returned".into()));
        return;
    }
    let task_app = Arc::clone(app);
    let asked = tokio::task::spawn_blocking(move || {
        let answer = ask(&task_app, what);
        task_app.health.in_flight[what.index()].store(false, Ordering::Release);
        answer
    });
    let answer = match tokio::time::timeout(PROBE_WITHIN, asked).await {
        Ok(Ok(answer)) => answer,
        Ok(Err(e)) => Err(format!("the check failed: {e}")),
        Err(_) => Err(format!("no answer within {} ms", PROBE_WITHIN.as_millis())),
    };
    app.health.record(what, answer);
}

fn ask(app: &Shared, what: Dependency) -> Result<(), String> {
    match what {
        Dependency::Jobs => app.jobs.check().map_err(|e| e.to_string()),
        Dependency::Files => app.files.check().map_err(|e| e.to_string()),
        Dependency::Disk => match super::data_dir::free_space(&app.cfg.data) {
            Some(free) if free < app.cfg.min_free => Err(format!(
                "{} bytes free under {}, below --min-free ({} bytes)",
                free,
                app.cfg.data.display(),
                app.cfg.min_free
            )),
            _ => Ok(()),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_answer_clears_what_an_error_set() {
        let h = Health::default();
        assert!(h.down().is_none());
        h.saw(&StoreError::files_unavailable("refused"));
        let down = h.down().expect("the file store is down");
        assert_eq!(down.what, Dependency::Files);
        assert!(h.down_among(&[Dependency::Jobs]).is_none());
        h.saw(&StoreError::jobs_unavailable("timed out"));
        assert_eq!(h.down().unwrap().what, Dependency::Jobs);
        h.record(Dependency::Jobs, Ok(()));
        h.record(Dependency::Files, Ok(()));
        assert!(h.down().is_none());
        // Not outages: nothing is marked.
        h.saw(&StoreError::Jobs("syntax error".into()));
        assert!(h.down().is_none());
    }
}
