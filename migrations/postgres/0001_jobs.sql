-- The job queue: one row per job. `data` is the job's record as JSON (the
-- same document the embedded store keeps); the columns beside it are what
-- the queue searches and locks on.
CREATE TABLE jobs (
    seq BIGSERIAL PRIMARY KEY,
    id TEXT NOT NULL UNIQUE,
    owner TEXT NOT NULL,
    state TEXT NOT NULL,
    input_key TEXT NOT NULL,
    idem_key TEXT,
    attempts INTEGER NOT NULL DEFAULT 0,
    finished_ms BIGINT,
    -- The worker holding a running job, and until when.
    lease_owner TEXT,
    lease_until BIGINT,
    data TEXT NOT NULL
);
-- An owner's idempotency key names one job, whichever API server took it.
CREATE UNIQUE INDEX jobs_idem ON jobs (owner, idem_key) WHERE idem_key IS NOT NULL;
CREATE INDEX jobs_queued ON jobs (seq) WHERE state = 'queued';
CREATE INDEX jobs_leases ON jobs (lease_until) WHERE state = 'running';
CREATE INDEX jobs_owner ON jobs (owner, seq);
CREATE INDEX jobs_key ON jobs (owner, input_key, state);
CREATE INDEX jobs_finished ON jobs (finished_ms);

-- Jobs with a callback to deliver once they are finished, and when next.
CREATE TABLE callbacks (
    id TEXT PRIMARY KEY REFERENCES jobs (id) ON DELETE CASCADE,
    due_ms BIGINT NOT NULL
);
