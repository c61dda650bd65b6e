//! The cluster's job store: PostgreSQL, shared by any number of API servers
//! and workers.
//!
//! The tables come from the versioned migrations in `migrations/postgres`
//! (applied at start under PostgreSQL's advisory lock, so processes that
//! start together apply them once). Workers claim with
//! `FOR UPDATE SKIP LOCKED`: concurrent claims skip each other's rows
//! instead of waiting, and no job is claimed twice. A claim is a lease
//! (see [`super::store::Lease`]); whoever finds a lease run out puts the job
//! back. Every change that queues or finishes a job is announced with
//! `NOTIFY`, which PostgreSQL delivers at commit to every process that
//! listens ([`JobStore::listen`]).

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use sqlx::postgres::{PgListener, PgPool, PgPoolOptions};
use sqlx::{PgConnection, Row};
use tokio::runtime::Handle;

use super::job::{Callback, Job, JobState};
use super::store::{decode, encode, JobStore, Lease, Reclaimed, StoreError, StoreEvent, Submitted};

static MIGRATOR: sqlx::migrate::Migrator = sqlx::migrate!("migrations/postgres");

/// The channel `NOTIFY` announces queue changes on.
const CHANNEL: &str = "seamstress_jobs";

/// Serialises submissions across servers, so that the queue bound holds
/// exactly: counting the queued jobs and inserting one is one step. (A key
/// of the application's own in PostgreSQL's advisory lock space.)
const SUBMIT_LOCK: i64 = 0x5ea3_5715;

/// Connections per process: a worker's job thread, the claim loop, the
/// lease renewals and a few API requests at once; more only queue inside
/// PostgreSQL.
const POOL_SIZE: u32 = 8;

/// How long a connection may take to come from the pool, connecting
/// included. The pool's own default (30 s) held every caller that long
/// while the server was away; past this the store counts as unavailable.
const ACQUIRE_WITHIN: Duration = Duration::from_secs(2);

/// How long one call (a transaction, or a query) may take. A server that
/// stops answering mid-call (frozen, or cut off without a reset) would
/// otherwise hold the caller until TCP gives up, many minutes later.
const CALL_WITHIN: Duration = Duration::from_secs(5);

/// How long `/readyz`'s probe may take: it must say within a second.
const CHECK_WITHIN: Duration = Duration::from_millis(800);

/// How long a callback a process has taken for delivery stays its own
/// before another process may deliver it (one try takes at most 10 s).
const CALLBACK_CLAIM_MS: u64 = 60_000;

pub struct PgJobStore {
    pool: PgPool,
    rt: Handle,
}

fn db_err(e: sqlx::Error) -> StoreError {
    if let Some(db) = e.as_database_error() {
        let code = db.code();
        let code = code.as_deref().unwrap_or("");
        // 53100 disk_full; 53200 out_of_memory is not the client's to retry.
        if code == "53100" {
            return StoreError::Full(db.to_string());
        }
        // Connection exceptions (class 08), the server shutting down or
        // starting up (57P01-57P03), too many connections (53300): the
        // server is away, not refusing what was asked.
        if code.starts_with("08") || code.starts_with("57P") || code == "53300" {
            return StoreError::jobs_unavailable(db.to_string());
        }
        return StoreError::Jobs(e.to_string());
    }
    match e {
        sqlx::Error::Io(_)
        | sqlx::Error::Tls(_)
        | sqlx::Error::Protocol(_)
        | sqlx::Error::PoolTimedOut
        | sqlx::Error::PoolClosed
        | sqlx::Error::WorkerCrashed => StoreError::jobs_unavailable(e.to_string()),
        _ => StoreError::Jobs(e.to_string()),
    }
}

fn decode_rows(rows: Vec<sqlx::postgres::PgRow>) -> Result<Vec<Job>, StoreError> {
    rows.iter()
        .map(|r| {
            let seq: i64 = r.try_get(0).map_err(db_err)?;
            let id: String = r.try_get(1).map_err(db_err)?;
            let data: String = r.try_get(2).map_err(db_err)?;
            decode(seq, &id, &data)
        })
        .collect()
}

fn ms(v: u64) -> i64 {
    v.min(i64::MAX as u64) as i64
}

async fn load(tx: &mut PgConnection, id: &str) -> Result<Option<Job>, StoreError> {
    let rows = sqlx::query("SELECT seq, id, data FROM jobs WHERE id = $1 FOR UPDATE")
        .bind(id)
        .fetch_all(tx)
        .await
        .map_err(db_err)?;
    Ok(decode_rows(rows)?.into_iter().next())
}

/// Writes `job`'s record; announces it when it has just finished.
async fn store(tx: &mut PgConnection, job: &Job) -> Result<(), StoreError> {
    sqlx::query(
        "UPDATE jobs SET state = $2, finished_ms = $3, attempts = $4, data = $5 WHERE id = $1",
    )
    .bind(&job.id)
    .bind(job.state.as_str())
    .bind(job.finished_ms.map(ms))
    .bind(job.attempts as i32)
    .bind(encode(job)?)
    .execute(&mut *tx)
    .await
    .map_err(db_err)?;
    if job.state.is_terminal() {
        notify(tx, StoreEvent::Finished).await?;
    }
    Ok(())
}

async fn notify(tx: &mut PgConnection, event: StoreEvent) -> Result<(), StoreError> {
    let payload = match event {
        StoreEvent::Queued => "queued",
        StoreEvent::Finished => "finished",
    };
    sqlx::query("SELECT pg_notify($1, $2)")
        .bind(CHANNEL)
        .bind(payload)
        .execute(tx)
        .await
        .map_err(db_err)?;
    Ok(())
}

/// Whether job `id` is running under `worker`'s lease; locks its row.
async fn holds(tx: &mut PgConnection, id: &str, worker: Option<&str>) -> Result<bool, StoreError> {
    let row = sqlx::query("SELECT state, lease_owner FROM jobs WHERE id = $1 FOR UPDATE")
        .bind(id)
        .fetch_optional(tx)
        .await
        .map_err(db_err)?;
    let Some(row) = row else {
        return Ok(false);
    };
    let state: String = row.try_get(0).map_err(db_err)?;
    let owner: Option<String> = row.try_get(1).map_err(db_err)?;
    Ok(state == "running" && owner.as_deref() == worker)
}

impl PgJobStore {
    /// Connects to `url` and brings its tables up to date. `rt` runs the
    /// connections; calls then block on it from threads outside it.
    pub fn open(url: &str, rt: Handle) -> Result<Self, StoreError> {
        let pool = rt.block_on(async {
            let pool = PgPoolOptions::new()
                .max_connections(POOL_SIZE)
                .acquire_timeout(ACQUIRE_WITHIN)
                .connect(url)
                .await
                .map_err(|e| StoreError::Jobs(format!("cannot connect to the job store: {e}")))?;
            MIGRATOR
                .run(&pool)
                .await
                .map_err(|e| StoreError::Jobs(format!("cannot migrate the job store: {e}")))?;
            Ok::<_, StoreError>(pool)
        })?;
        Ok(PgJobStore { pool, rt })
    }

    /// Runs `call` on the store's runtime, for at most `within`.
    fn run<T>(
        &self,
        within: Duration,
        call: impl std::future::Future<Output = Result<T, StoreError>>,
    ) -> Result<T, StoreError> {
        self.rt.block_on(async {
            tokio::time::timeout(within, call)
                .await
                .unwrap_or_else(|_| {
                    Err(StoreError::jobs_unavailable(format!(
                        "no answer within {} ms",
                        within.as_millis()
                    )))
                })
        })
    }

    /// Runs `f` in one transaction, committed if it returns `Ok`.
    fn with<T, F>(&self, f: F) -> Result<T, StoreError>
    where
        F: for<'c> FnOnce(
            &'c mut PgConnection,
        ) -> std::pin::Pin<
            Box<dyn std::future::Future<Output = Result<T, StoreError>> + Send + 'c>,
        >,
    {
        self.run(CALL_WITHIN, async {
            let mut tx = self.pool.begin().await.map_err(db_err)?;
            let out = f(&mut tx).await?;
            tx.commit().await.map_err(db_err)?;
            Ok(out)
        })
    }
}

impl JobStore for PgJobStore {
    fn submit(&self, job: &Job, queue_limit: usize) -> Result<Submitted, StoreError> {
        let job = job.clone();
        self.with(move |tx| {
            Box::pin(async move {
                sqlx::query("SELECT pg_advisory_xact_lock($1)")
                    .bind(SUBMIT_LOCK)
                    .execute(&mut *tx)
                    .await
                    .map_err(db_err)?;
                if let Some(key) = &job.idempotency_key {
                    let rows =
                        sqlx::query("SELECT seq, id, data FROM jobs WHERE owner = $1 AND idem_key = $2")
                            .bind(&job.owner)
                            .bind(key)
                            .fetch_all(&mut *tx)
                            .await
                            .map_err(db_err)?;
                    if let Some(e) = decode_rows(rows)?.into_iter().next() {
                        return Ok(Submitted::Existing(Box::new(e)));
                    }
                }
                if job.state == JobState::Queued {
                    let queued: i64 =
                        sqlx::query_scalar("SELECT COUNT(*) FROM jobs WHERE state = 'queued'")
                            .fetch_one(&mut *tx)
                            .await
                            .map_err(db_err)?;
                    if queued as usize >= queue_limit {
                        return Ok(Submitted::QueueFull);
                    }
                }
                sqlx::query(
                    "INSERT INTO jobs (id, owner, state, input_key, idem_key, attempts, finished_ms, data)
                     VALUES ($1, $2, $3, $4, $5, $6, $7, $8)",
                )
                .bind(&job.id)
                .bind(&job.owner)
                .bind(job.state.as_str())
                .bind(&job.input_key)
                .bind(&job.idempotency_key)
                .bind(job.attempts as i32)
                .bind(job.finished_ms.map(ms))
                .bind(encode(&job)?)
                .execute(&mut *tx)
                .await
                .map_err(db_err)?;
                if job.callback.is_some() {
                    sqlx::query("INSERT INTO callbacks (id, due_ms) VALUES ($1, 0)")
                        .bind(&job.id)
                        .execute(&mut *tx)
                        .await
                        .map_err(db_err)?;
                }
                let event = match job.state {
                    JobState::Queued => StoreEvent::Queued,
                    _ => StoreEvent::Finished,
                };
                notify(tx, event).await?;
                Ok(Submitted::Created)
            })
        })
    }

    fn get(&self, id: &str) -> Result<Option<Job>, StoreError> {
        self.run(CALL_WITHIN, async {
            let rows = sqlx::query("SELECT seq, id, data FROM jobs WHERE id = $1")
                .bind(id)
                .fetch_all(&self.pool)
                .await
                .map_err(db_err)?;
            Ok(decode_rows(rows)?.into_iter().next())
        })
    }

    fn list(&self, owner: &str, before: Option<i64>, limit: usize) -> Result<Vec<Job>, StoreError> {
        self.run(CALL_WITHIN, async {
            let rows = sqlx::query(
                "SELECT seq, id, data FROM jobs WHERE owner = $1 AND seq < $2
                 ORDER BY seq DESC LIMIT $3",
            )
            .bind(owner)
            .bind(before.unwrap_or(i64::MAX))
            .bind(limit as i64)
            .fetch_all(&self.pool)
            .await
            .map_err(db_err)?;
            decode_rows(rows)
        })
    }

    fn find_succeeded(&self, owner: &str, input_key: &str) -> Result<Option<Job>, StoreError> {
        self.run(CALL_WITHIN, async {
            let rows = sqlx::query(
                "SELECT seq, id, data FROM jobs
                 WHERE owner = $1 AND input_key = $2 AND state = 'succeeded'
                 ORDER BY seq DESC LIMIT 1",
            )
            .bind(owner)
            .bind(input_key)
            .fetch_all(&self.pool)
            .await
            .map_err(db_err)?;
            Ok(decode_rows(rows)?.into_iter().next())
        })
    }

    fn claim(&self, lease: &Lease<'_>, now_ms: u64) -> Result<Option<Job>, StoreError> {
        let (worker, until) = (lease.worker.to_string(), lease.until_ms);
        self.with(move |tx| {
            Box::pin(async move {
                let rows = sqlx::query(
                    "SELECT seq, id, data FROM jobs WHERE state = 'queued'
                     ORDER BY seq LIMIT 1 FOR UPDATE SKIP LOCKED",
                )
                .fetch_all(&mut *tx)
                .await
                .map_err(db_err)?;
                let Some(mut job) = decode_rows(rows)?.into_iter().next() else {
                    return Ok(None);
                };
                job.start(&worker, now_ms);
                sqlx::query(
                    "UPDATE jobs SET state = 'running', attempts = $2, data = $3,
                         lease_owner = $4, lease_until = $5
                     WHERE id = $1",
                )
                .bind(&job.id)
                .bind(job.attempts as i32)
                .bind(encode(&job)?)
                .bind(&worker)
                .bind(ms(until))
                .execute(&mut *tx)
                .await
                .map_err(db_err)?;
                Ok(Some(job))
            })
        })
    }

    fn renew(&self, id: &str, lease: &Lease<'_>) -> Result<bool, StoreError> {
        self.run(CALL_WITHIN, async {
            let done = sqlx::query(
                "UPDATE jobs SET lease_until = $3
                 WHERE id = $1 AND state = 'running' AND lease_owner = $2",
            )
            .bind(id)
            .bind(lease.worker)
            .bind(ms(lease.until_ms))
            .execute(&self.pool)
            .await
            .map_err(db_err)?;
            Ok(done.rows_affected() == 1)
        })
    }

    /// One guarded statement: progress is most of a job's writes, and
    /// needs no transaction; a final state adds its `NOTIFY`.
    fn update_running(&self, job: &Job) -> Result<bool, StoreError> {
        let data = encode(job)?;
        self.run(CALL_WITHIN, async {
            let sql = "UPDATE jobs SET state = $2, finished_ms = $3, attempts = $4, data = $5
                 WHERE id = $1 AND state = 'running' AND lease_owner IS NOT DISTINCT FROM $6";
            let update = sqlx::query(sql)
                .bind(&job.id)
                .bind(job.state.as_str())
                .bind(job.finished_ms.map(ms))
                .bind(job.attempts as i32)
                .bind(&data)
                .bind(job.worker.as_deref());
            if !job.state.is_terminal() {
                let done = update.execute(&self.pool).await.map_err(db_err)?;
                return Ok(done.rows_affected() == 1);
            }
            let mut tx = self.pool.begin().await.map_err(db_err)?;
            let done = update.execute(&mut *tx).await.map_err(db_err)?;
            if done.rows_affected() != 1 {
                return Ok(false);
            }
            notify(&mut tx, StoreEvent::Finished).await?;
            tx.commit().await.map_err(db_err)?;
            Ok(true)
        })
    }

    fn cancel(&self, id: &str, now_ms: u64) -> Result<Option<Job>, StoreError> {
        let id = id.to_string();
        self.with(move |tx| {
            Box::pin(async move {
                let Some(mut job) = load(tx, &id).await? else {
                    return Ok(None);
                };
                if job.state.is_terminal() {
                    return Ok(None);
                }
                job.cancel(now_ms);
                store(tx, &job).await?;
                Ok(Some(job))
            })
        })
    }

    fn requeue(&self, id: &str, worker: &str) -> Result<bool, StoreError> {
        let (id, worker) = (id.to_string(), worker.to_string());
        self.with(move |tx| {
            Box::pin(async move {
                if !holds(tx, &id, Some(&worker)).await? {
                    return Ok(false);
                }
                let Some(mut job) = load(tx, &id).await? else {
                    return Ok(false);
                };
                job.requeue_uncounted();
                store(tx, &job).await?;
                notify(tx, StoreEvent::Queued).await?;
                Ok(true)
            })
        })
    }

    fn reclaim(
        &self,
        expired_before_ms: u64,
        max_lost: u32,
        now_ms: u64,
    ) -> Result<Reclaimed, StoreError> {
        self.with(move |tx| {
            Box::pin(async move {
                let rows = sqlx::query(
                    "SELECT seq, id, data FROM jobs
                     WHERE state = 'running' AND COALESCE(lease_until, 0) < $1
                     ORDER BY seq FOR UPDATE SKIP LOCKED",
                )
                .bind(ms(expired_before_ms))
                .fetch_all(&mut *tx)
                .await
                .map_err(db_err)?;
                let mut out = Reclaimed::default();
                for mut job in decode_rows(rows)? {
                    if job.reclaim(max_lost, now_ms) {
                        out.requeued.push(job.clone());
                    } else {
                        out.failed.push(job.clone());
                    }
                    store(tx, &job).await?;
                }
                if !out.requeued.is_empty() {
                    notify(tx, StoreEvent::Queued).await?;
                }
                Ok(out)
            })
        })
    }

    fn delete(&self, id: &str) -> Result<(), StoreError> {
        self.run(CALL_WITHIN, async {
            // The callback row goes with it (ON DELETE CASCADE).
            sqlx::query("DELETE FROM jobs WHERE id = $1")
                .bind(id)
                .execute(&self.pool)
                .await
                .map_err(db_err)?;
            Ok(())
        })
    }

    /// Takes the due callbacks for this process: each is pushed
    /// `CALLBACK_CLAIM_MS` into the future, so that another server does
    /// not deliver it at the same time.
    fn callbacks_due(&self, now_ms: u64, limit: usize) -> Result<Vec<Job>, StoreError> {
        self.with(move |tx| {
            Box::pin(async move {
                let rows = sqlx::query(
                    "SELECT j.seq, j.id, j.data FROM callbacks c JOIN jobs j ON j.id = c.id
                     WHERE c.due_ms <= $1 AND j.state IN ('succeeded', 'failed', 'canceled')
                     ORDER BY c.due_ms LIMIT $2 FOR UPDATE OF c SKIP LOCKED",
                )
                .bind(ms(now_ms))
                .bind(limit as i64)
                .fetch_all(&mut *tx)
                .await
                .map_err(db_err)?;
                let jobs = decode_rows(rows)?;
                let ids: Vec<String> = jobs.iter().map(|j| j.id.clone()).collect();
                sqlx::query("UPDATE callbacks SET due_ms = $2 WHERE id = ANY($1)")
                    .bind(&ids)
                    .bind(ms(now_ms + CALLBACK_CLAIM_MS))
                    .execute(&mut *tx)
                    .await
                    .map_err(db_err)?;
                Ok(jobs)
            })
        })
    }

    fn callback_tried(
        &self,
        id: &str,
        status: &Callback,
        next_ms: Option<u64>,
    ) -> Result<(), StoreError> {
        let (id, status) = (id.to_string(), status.clone());
        self.with(move |tx| {
            Box::pin(async move {
                let Some(mut job) = load(tx, &id).await? else {
                    return Ok(());
                };
                job.callback = Some(status);
                sqlx::query("UPDATE jobs SET data = $2 WHERE id = $1")
                    .bind(&id)
                    .bind(encode(&job)?)
                    .execute(&mut *tx)
                    .await
                    .map_err(db_err)?;
                match next_ms {
                    Some(next) => {
                        sqlx::query("UPDATE callbacks SET due_ms = $2 WHERE id = $1")
                            .bind(&id)
                            .bind(ms(next))
                            .execute(&mut *tx)
                            .await
                    }
                    None => {
                        sqlx::query("DELETE FROM callbacks WHERE id = $1")
                            .bind(&id)
                            .execute(&mut *tx)
                            .await
                    }
                }
                .map_err(db_err)?;
                Ok(())
            })
        })
    }

    fn expired(&self, before_ms: u64, limit: usize) -> Result<Vec<Job>, StoreError> {
        self.run(CALL_WITHIN, async {
            let rows = sqlx::query(
                "SELECT seq, id, data FROM jobs
                 WHERE finished_ms IS NOT NULL AND finished_ms < $1
                   AND state IN ('succeeded', 'failed', 'canceled')
                 ORDER BY finished_ms LIMIT $2",
            )
            .bind(ms(before_ms))
            .bind(limit as i64)
            .fetch_all(&self.pool)
            .await
            .map_err(db_err)?;
            decode_rows(rows)
        })
    }

    fn counts(&self) -> Result<BTreeMap<JobState, u64>, StoreError> {
        self.run(CALL_WITHIN, async {
            let rows = sqlx::query("SELECT state, COUNT(*) FROM jobs GROUP BY state")
                .fetch_all(&self.pool)
                .await
                .map_err(db_err)?;
            let mut counts: BTreeMap<JobState, u64> =
                JobState::ALL.iter().map(|&s| (s, 0)).collect();
            for row in rows {
                let state: String = row.try_get(0).map_err(db_err)?;
                let n: i64 = row.try_get(1).map_err(db_err)?;
                if let Some(s) = JobState::parse(&state) {
                    counts.insert(s, n as u64);
                }
            }
            Ok(counts)
        })
    }

    fn check(&self) -> Result<(), StoreError> {
        self.run(CHECK_WITHIN, async {
            sqlx::query("SELECT 1")
                .execute(&self.pool)
                .await
                .map_err(db_err)?;
            Ok(())
        })
    }

    fn listen(&self, on: Arc<dyn Fn(StoreEvent) + Send + Sync>) {
        let pool = self.pool.clone();
        self.rt.spawn(async move {
            loop {
                if let Err(e) = relay(&pool, on.as_ref()).await {
                    tracing::warn!(error = %e, "job store notifications lost; reconnecting");
                    // What was announced meanwhile is found by polling.
                    on(StoreEvent::Queued);
                    on(StoreEvent::Finished);
                }
                tokio::time::sleep(Duration::from_secs(1)).await;
            }
        });
    }
}

/// Hands every notification on the channel to `on` until the connection
/// fails.
async fn relay(pool: &PgPool, on: &(dyn Fn(StoreEvent) + Send + Sync)) -> Result<(), sqlx::Error> {
    let mut listener = PgListener::connect_with(pool).await?;
    listener.listen(CHANNEL).await?;
    loop {
        let n = listener.recv().await?;
        match n.payload() {
            "queued" => on(StoreEvent::Queued),
            "finished" => on(StoreEvent::Finished),
            _ => {}
        }
    }
}
