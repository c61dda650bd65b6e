//! The embedded job store: one SQLite file, written through the WAL with a
//! full sync on every commit, so an accepted job survives `kill -9` and
//! power loss alike.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Mutex;

use rusqlite::{params, Connection, OptionalExtension, Transaction};

use super::job::{Callback, Job, JobState};
use super::store::{decode, encode, JobStore, Lease, Reclaimed, StoreError, Submitted};

pub struct SqliteJobStore {
    conn: Mutex<Connection>,
}

const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS jobs (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    id TEXT NOT NULL UNIQUE,
    owner TEXT NOT NULL,
    state TEXT NOT NULL,
    input_key TEXT NOT NULL,
    idem_key TEXT,
    finished_ms INTEGER,
    data TEXT NOT NULL
);
CREATE UNIQUE INDEX IF NOT EXISTS jobs_idem ON jobs(owner, idem_key) WHERE idem_key IS NOT NULL;
CREATE INDEX IF NOT EXISTS jobs_state ON jobs(state, seq);
CREATE INDEX IF NOT EXISTS jobs_owner ON jobs(owner, seq);
CREATE INDEX IF NOT EXISTS jobs_key ON jobs(owner, input_key, state);
CREATE INDEX IF NOT EXISTS jobs_finished ON jobs(finished_ms);
-- Jobs with a callback to deliver once they are finished, and when next.
CREATE TABLE IF NOT EXISTS callbacks (
    id TEXT PRIMARY KEY,
    due_ms INTEGER NOT NULL
);
";

/// Columns added since the first schema, for stores made before them.
const ADDED_COLUMNS: [(&str, &str); 2] = [
    // The worker holding a running job, and until when (see `store::Lease`).
    ("lease_owner", "TEXT"),
    ("lease_until", "INTEGER"),
];

fn db_err(e: rusqlite::Error) -> StoreError {
    match e.sqlite_error_code() {
        Some(rusqlite::ErrorCode::DiskFull) => StoreError::Full(e.to_string()),
        // Another process holding the file past the busy timeout, or the
        // disk under it failing a read or write: the file is fine, the
        // moment is not.
        Some(
            rusqlite::ErrorCode::DatabaseBusy
            | rusqlite::ErrorCode::DatabaseLocked
            | rusqlite::ErrorCode::SystemIoFailure,
        ) => StoreError::jobs_unavailable(e.to_string()),
        _ => StoreError::Jobs(e.to_string()),
    }
}

impl SqliteJobStore {
    pub fn open(path: &Path) -> Result<Self, StoreError> {
        let conn = Connection::open(path).map_err(db_err)?;
        conn.pragma_update(None, "journal_mode", "WAL")
            .map_err(db_err)?;
        conn.pragma_update(None, "synchronous", "FULL")
            .map_err(db_err)?;
        conn.busy_timeout(std::time::Duration::from_secs(10))
            .map_err(db_err)?;
        conn.execute_batch(SCHEMA).map_err(db_err)?;
        add_columns(&conn)?;
        Ok(SqliteJobStore {
            conn: Mutex::new(conn),
        })
    }

    fn with<T>(
        &self,
        f: impl FnOnce(&Transaction<'_>) -> Result<T, StoreError>,
    ) -> Result<T, StoreError> {
        // A poisoned lock only means another thread panicked mid-call; the
        // transaction it held was rolled back when it unwound.
        let mut conn = self.conn.lock().unwrap_or_else(|p| p.into_inner());
        let tx = conn
            .transaction_with_behavior(rusqlite::TransactionBehavior::Immediate)
            .map_err(db_err)?;
        let out = f(&tx)?;
        tx.commit().map_err(db_err)?;
        Ok(out)
    }
}

fn add_columns(conn: &Connection) -> Result<(), StoreError> {
    let mut stmt = conn
        .prepare("SELECT name FROM pragma_table_info('jobs')")
        .map_err(db_err)?;
    let have: Vec<String> = stmt
        .query_map([], |r| r.get(0))
        .map_err(db_err)?
        .collect::<Result<_, _>>()
        .map_err(db_err)?;
    for (name, ty) in ADDED_COLUMNS {
        if !have.iter().any(|h| h == name) {
            conn.execute_batch(&format!("ALTER TABLE jobs ADD COLUMN {name} {ty}"))
                .map_err(db_err)?;
        }
    }
    Ok(())
}

fn query_jobs(
    tx: &Transaction<'_>,
    sql: &str,
    params: impl rusqlite::Params,
) -> Result<Vec<Job>, StoreError> {
    let mut stmt = tx.prepare_cached(sql).map_err(db_err)?;
    let rows = stmt
        .query_map(params, |r| {
            Ok((
                r.get::<_, i64>(0)?,
                r.get::<_, String>(1)?,
                r.get::<_, String>(2)?,
            ))
        })
        .map_err(db_err)?;
    let mut jobs = Vec::new();
    for row in rows {
        let (seq, id, data) = row.map_err(db_err)?;
        jobs.push(decode(seq, &id, &data)?);
    }
    Ok(jobs)
}

fn load(tx: &Transaction<'_>, id: &str) -> Result<Option<Job>, StoreError> {
    Ok(
        query_jobs(tx, "SELECT seq, id, data FROM jobs WHERE id = ?1", [id])?
            .into_iter()
            .next(),
    )
}

/// Whether job `id` is running under `worker`'s lease.
fn holds(tx: &Transaction<'_>, id: &str, worker: Option<&str>) -> Result<bool, StoreError> {
    let row: Option<(String, Option<String>)> = tx
        .query_row(
            "SELECT state, lease_owner FROM jobs WHERE id = ?1",
            [id],
            |r| Ok((r.get(0)?, r.get(1)?)),
        )
        .optional()
        .map_err(db_err)?;
    Ok(matches!(row, Some((state, owner)) if state == "running" && owner.as_deref() == worker))
}

fn store(tx: &Transaction<'_>, job: &Job) -> Result<(), StoreError> {
    tx.execute(
        "UPDATE jobs SET state = ?2, finished_ms = ?3, data = ?4 WHERE id = ?1",
        params![
            job.id,
            job.state.as_str(),
            job.finished_ms.map(|v| v as i64),
            encode(job)?
        ],
    )
    .map_err(db_err)?;
    Ok(())
}

impl JobStore for SqliteJobStore {
    fn submit(&self, job: &Job, queue_limit: usize) -> Result<Submitted, StoreError> {
        self.with(|tx| {
            if let Some(key) = &job.idempotency_key {
                let existing = query_jobs(
                    tx,
                    "SELECT seq, id, data FROM jobs WHERE owner = ?1 AND idem_key = ?2",
                    params![job.owner, key],
                )?;
                if let Some(e) = existing.into_iter().next() {
                    return Ok(Submitted::Existing(Box::new(e)));
                }
            }
            if job.state == JobState::Queued {
                let queued: i64 = tx
                    .query_row(
                        "SELECT COUNT(*) FROM jobs WHERE state = 'queued'",
                        [],
                        |r| r.get(0),
                    )
                    .map_err(db_err)?;
                if queued as usize >= queue_limit {
                    return Ok(Submitted::QueueFull);
                }
            }
            tx.execute(
                "INSERT INTO jobs (id, owner, state, input_key, idem_key, finished_ms, data)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7)",
                params![
                    job.id,
                    job.owner,
                    job.state.as_str(),
                    job.input_key,
                    job.idempotency_key,
                    job.finished_ms.map(|v| v as i64),
                    encode(job)?
                ],
            )
            .map_err(db_err)?;
            if job.callback.is_some() {
                tx.execute(
                    "INSERT INTO callbacks (id, due_ms) VALUES (?1, 0)",
                    [&job.id],
                )
                .map_err(db_err)?;
            }
            Ok(Submitted::Created)
        })
    }

    fn get(&self, id: &str) -> Result<Option<Job>, StoreError> {
        self.with(|tx| load(tx, id))
    }

    fn list(&self, owner: &str, before: Option<i64>, limit: usize) -> Result<Vec<Job>, StoreError> {
        self.with(|tx| {
            query_jobs(
                tx,
                "SELECT seq, id, data FROM jobs WHERE owner = ?1 AND seq < ?2
                 ORDER BY seq DESC LIMIT ?3",
                params![owner, before.unwrap_or(i64::MAX), limit as i64],
            )
        })
    }

    fn find_succeeded(&self, owner: &str, input_key: &str) -> Result<Option<Job>, StoreError> {
        self.with(|tx| {
            Ok(query_jobs(
                tx,
                "SELECT seq, id, data FROM jobs
                 WHERE owner = ?1 AND input_key = ?2 AND state = 'succeeded'
                 ORDER BY seq DESC LIMIT 1",
                params![owner, input_key],
            )?
            .into_iter()
            .next())
        })
    }

    fn claim(&self, lease: &Lease<'_>, now_ms: u64) -> Result<Option<Job>, StoreError> {
        self.with(|tx| {
            let next = query_jobs(
                tx,
                "SELECT seq, id, data FROM jobs WHERE state = 'queued' ORDER BY seq LIMIT 1",
                [],
            )?;
            let Some(mut job) = next.into_iter().next() else {
                return Ok(None);
            };
            job.start(lease.worker, now_ms);
            store(tx, &job)?;
            tx.execute(
                "UPDATE jobs SET lease_owner = ?2, lease_until = ?3 WHERE id = ?1",
                params![job.id, lease.worker, lease.until_ms as i64],
            )
            .map_err(db_err)?;
            Ok(Some(job))
        })
    }

    fn renew(&self, id: &str, lease: &Lease<'_>) -> Result<bool, StoreError> {
        self.with(|tx| {
            let n = tx
                .execute(
                    "UPDATE jobs SET lease_until = ?3
                     WHERE id = ?1 AND state = 'running' AND lease_owner = ?2",
                    params![id, lease.worker, lease.until_ms as i64],
                )
                .map_err(db_err)?;
            Ok(n == 1)
        })
    }

    fn update_running(&self, job: &Job) -> Result<bool, StoreError> {
        self.with(|tx| {
            if !holds(tx, &job.id, job.worker.as_deref())? {
                return Ok(false);
            }
            store(tx, job)?;
            Ok(true)
        })
    }

    fn cancel(&self, id: &str, now_ms: u64) -> Result<Option<Job>, StoreError> {
        self.with(|tx| {
            let Some(mut job) = load(tx, id)? else {
                return Ok(None);
            };
            if job.state.is_terminal() {
                return Ok(None);
            }
            job.cancel(now_ms);
            store(tx, &job)?;
            Ok(Some(job))
        })
    }

    fn requeue(&self, id: &str, worker: &str) -> Result<bool, StoreError> {
        self.with(|tx| {
            if !holds(tx, id, Some(worker))? {
                return Ok(false);
            }
            let Some(mut job) = load(tx, id)? else {
                return Ok(false);
            };
            job.requeue_uncounted();
            store(tx, &job)?;
            Ok(true)
        })
    }

    fn reclaim(
        &self,
        expired_before_ms: u64,
        max_lost: u32,
        now_ms: u64,
    ) -> Result<Reclaimed, StoreError> {
        self.with(|tx| {
            let expired = query_jobs(
                tx,
                "SELECT seq, id, data FROM jobs
                 WHERE state = 'running' AND COALESCE(lease_until, 0) < ?1 ORDER BY seq",
                [expired_before_ms.min(i64::MAX as u64) as i64],
            )?;
            let mut out = Reclaimed::default();
            for mut job in expired {
                if job.reclaim(max_lost, now_ms) {
                    out.requeued.push(job.clone());
                } else {
                    out.failed.push(job.clone());
                }
                store(tx, &job)?;
            }
            Ok(out)
        })
    }

    fn delete(&self, id: &str) -> Result<(), StoreError> {
        self.with(|tx| {
            tx.execute("DELETE FROM jobs WHERE id = ?1", [id])
                .map_err(db_err)?;
            tx.execute("DELETE FROM callbacks WHERE id = ?1", [id])
                .map_err(db_err)?;
            Ok(())
        })
    }

    fn callbacks_due(&self, now_ms: u64, limit: usize) -> Result<Vec<Job>, StoreError> {
        self.with(|tx| {
            query_jobs(
                tx,
                "SELECT j.seq, j.id, j.data FROM callbacks c JOIN jobs j ON j.id = c.id
                 WHERE c.due_ms <= ?1 AND j.state IN ('succeeded', 'failed', 'canceled')
                 ORDER BY c.due_ms LIMIT ?2",
                params![now_ms as i64, limit as i64],
            )
        })
    }

    fn callback_tried(
        &self,
        id: &str,
        status: &Callback,
        next_ms: Option<u64>,
    ) -> Result<(), StoreError> {
        self.with(|tx| {
            let Some(mut job) = load(tx, id)? else {
                return Ok(());
            };
            job.callback = Some(status.clone());
            store(tx, &job)?;
            match next_ms {
                Some(ms) => tx.execute(
                    "UPDATE callbacks SET due_ms = ?2 WHERE id = ?1",
                    params![id, ms as i64],
                ),
                None => tx.execute("DELETE FROM callbacks WHERE id = ?1", [id]),
            }
            .map_err(db_err)?;
            Ok(())
        })
    }

    fn expired(&self, before_ms: u64, limit: usize) -> Result<Vec<Job>, StoreError> {
        self.with(|tx| {
            query_jobs(
                tx,
                "SELECT seq, id, data FROM jobs
                 WHERE finished_ms IS NOT NULL AND finished_ms < ?1
                   AND state IN ('succeeded', 'failed', 'canceled')
                 ORDER BY finished_ms LIMIT ?2",
                params![before_ms as i64, limit as i64],
            )
        })
    }

    fn counts(&self) -> Result<BTreeMap<JobState, u64>, StoreError> {
        self.with(|tx| {
            let mut stmt = tx
                .prepare_cached("SELECT state, COUNT(*) FROM jobs GROUP BY state")
                .map_err(db_err)?;
            let rows = stmt
                .query_map([], |r| Ok((r.get::<_, String>(0)?, r.get::<_, i64>(1)?)))
                .map_err(db_err)?;
            let mut counts: BTreeMap<JobState, u64> =
                JobState::ALL.iter().map(|&s| (s, 0)).collect();
            for row in rows {
                let (state, n) = row.map_err(db_err)?;
                if let Some(s) = JobState::parse(&state) {
                    counts.insert(s, n as u64);
                }
            }
            Ok(counts)
        })
    }
}
