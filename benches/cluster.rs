//! The cluster against the embedded default, on this machine: one
//! `serve --workers 1` on SQLite and a folder, then one API server
//! (`serve --workers 0`) with 1, 2 and 3 `worker` processes (`--workers 1`
//! each) on one PostgreSQL and one S3 store (SeaweedFS), all started here
//! on 127.0.0.1. The embedded setup and the one with 1 worker run side by
//! side, their batches alternating over a few rounds: on a 2-core machine
//! the noise between two runs is of the order of the difference between
//! them. It prints:
//!
//! - throughput: a batch of distinct small jobs (cube_gradient_128 and
//!   BoxTextured, alternately), all submitted at once, timed from the first
//!   submission to the last job's `finished_at`;
//! - claim latency: `timings_ms.queued` (submitted → claimed, as the store
//!   records it at the claim) of jobs submitted one at a time into the idle
//!   setup, each waited for before the next;
//! - `Prefer: wait` latency: for those same jobs, submitted with
//!   `Prefer: wait=60`, the time from the job's `finished_at` to the
//!   response's arrival (one machine, one clock).
//!
//!     PATH=/tmp/seamstress-ci-venv/bin:$PATH cargo bench --bench cluster
//!
//! `SEAMSTRESS_BENCH_JOBS` (default 200): jobs in each batch;
//! `SEAMSTRESS_BENCH_ROUNDS` (default 3): batches each of the embedded and
//! the 1-worker setup (2 and 3 workers: one);
//! `SEAMSTRESS_BENCH_IDLE` (default 30): jobs one at a time. Without
//! PostgreSQL or `weed` (see `tests/common/cluster.rs`) only the embedded
//! setup runs.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use reqwest::blocking::Client;
use serde_json::Value;

#[path = "../tests/common/mod.rs"]
mod common;
use common::cluster::{Postgres, Seaweed};
use common::shared_assets;

/// Client threads submitting a batch.
const SUBMITTERS: usize = 8;

fn knob(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// One `seamstress` process, its address as it printed it; its stderr goes
/// to `log`.
struct Node {
    child: Child,
    base: String,
    log: PathBuf,
}

impl Node {
    fn start(args: &[String], env: &[(&'static str, String)], log: &Path) -> Node {
        let mut child = Command::new(env!("CARGO_BIN_EXE_seamstress"))
            .args(args)
            .envs(env.iter().map(|(k, v)| (*k, v.as_str())))
            .env_remove("SEAMSTRESS_TOKENS")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(File::create(log).expect("a log file"))
            .spawn()
            .expect("seamstress starts");
        let mut line = String::new();
        BufReader::new(child.stdout.take().expect("a piped stdout"))
            .read_line(&mut line)
            .expect("seamstress prints its address");
        let Some(addr) = line.trim().strip_prefix("listening on ") else {
            let _ = child.kill();
            let _ = child.wait();
            panic!(
                "{args:?}: first line {line:?}; its log:\n{}",
                std::fs::read_to_string(log).unwrap_or_default()
            );
        };
        Node {
            base: format!("http://{addr}"),
            child,
            log: log.to_path_buf(),
        }
    }
}

impl Drop for Node {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A running setup: the API server and any worker processes.
struct Setup {
    name: String,
    /// Worker processes; 0 for the embedded setup.
    workers: usize,
    api: Node,
    worker_nodes: Vec<Node>,
}

impl Setup {
    fn embedded(dir: &Path, queue: usize) -> Setup {
        let data = dir.join("embedded");
        let args = strings(&["serve", "--workers", "1", "--listen", "127.0.0.1:0"])
            .into_iter()
            .chain(["--data".into(), path(&data)])
            .chain(["--queue-size".into(), queue.to_string()])
            .collect::<Vec<_>>();
        Setup {
            name: "embedded: serve --workers 1".into(),
            workers: 0,
            api: Node::start(&args, &[], &dir.join("embedded.log")),
            worker_nodes: Vec::new(),
        }
    }

    /// One API server and `n` workers, on a database and a prefix of their
    /// own.
    fn distributed(dir: &Path, queue: usize, (pg, s3): &(Postgres, Seaweed), n: usize) -> Setup {
        let tag = format!("w{n}");
        let stores = [
            "--store".to_string(),
            pg.new_database(&format!("bench_{tag}")),
            "--files".into(),
            s3.url(&tag),
        ];
        let env = s3.env();
        let api_args = strings(&["serve", "--workers", "0", "--listen", "127.0.0.1:0"])
            .into_iter()
            .chain(["--data".into(), path(&dir.join(format!("{tag}-api")))])
            .chain(["--queue-size".into(), queue.to_string()])
            .chain(stores.iter().cloned())
            .collect::<Vec<_>>();
        let api = Node::start(&api_args, &env, &dir.join(format!("{tag}-api.log")));
        let worker_nodes = (0..n)
            .map(|i| {
                let args = strings(&["worker", "--workers", "1"])
                    .into_iter()
                    .chain(["--metrics-listen".into(), "127.0.0.1:0".into()])
                    .chain(["--data".into(), path(&dir.join(format!("{tag}-{i}")))])
                    .chain(stores.iter().cloned())
                    .collect::<Vec<_>>();
                Node::start(&args, &env, &dir.join(format!("{tag}-{i}.log")))
            })
            .collect();
        Setup {
            name: format!("distributed: {n} worker{}", if n == 1 { "" } else { "s" }),
            workers: n,
            api,
            worker_nodes,
        }
    }

    fn logs(&self) -> String {
        std::iter::once(&self.api)
            .chain(&self.worker_nodes)
            .map(|n| {
                let text = std::fs::read_to_string(&n.log).unwrap_or_default();
                let lines: Vec<&str> = text.lines().collect();
                format!(
                    "--- {}:\n{}",
                    n.log.display(),
                    lines[lines.len().saturating_sub(20)..].join("\n")
                )
            })
            .collect::<Vec<_>>()
            .join("\n")
    }
}

fn strings(s: &[&str]) -> Vec<String> {
    s.iter().map(|s| s.to_string()).collect()
}

fn path(p: &Path) -> String {
    p.to_str().expect("a UTF-8 path").to_string()
}

/// A job to submit: the model's name and bytes, and its `seam_weight`:
/// `48.SNNNNN` for series S and index N, near the default 48 (the same
/// work), and a distinct job for the result cache.
struct Spec {
    name: &'static str,
    bytes: &'static [u8],
    seam_weight: String,
}

fn specs(models: &[(&'static str, &'static [u8])], n: usize, series: usize) -> Vec<Spec> {
    (0..n)
        .map(|i| {
            let (name, bytes) = models[i % models.len()];
            Spec {
                name,
                bytes,
                seam_weight: format!("48.{series}{i:05}"),
            }
        })
        .collect()
}

fn submit(c: &Client, base: &str, s: &Spec, wait: Option<u64>) -> Value {
    let mut req = c
        .post(format!(
            "{base}/v1/jobs?name={}&seam_weight={}",
            s.name, s.seam_weight
        ))
        .header("content-type", "model/gltf-binary")
        .body(s.bytes);
    if let Some(w) = wait {
        req = req.header("prefer", format!("wait={w}"));
    }
    let r = req.send().expect("the API server answers");
    let status = r.status();
    let body: Value = r.json().expect("a JSON answer");
    assert!(status.is_success(), "submission refused: {status} {body}");
    body
}

/// The job once final (or after 120 s).
fn final_job(c: &Client, base: &str, id: &str) -> Value {
    c.get(format!("{base}/v1/jobs/{id}"))
        .header("prefer", "wait=120")
        .send()
        .expect("the API server answers")
        .json()
        .expect("a JSON answer")
}

fn state(job: &Value) -> &str {
    job["state"].as_str().unwrap_or("?")
}

/// Milliseconds since 1970 of `YYYY-MM-DDTHH:MM:SS[.mmm]Z`.
fn rfc3339_ms(s: &str) -> Option<i64> {
    let s = s.strip_suffix('Z')?;
    let (date, time) = s.split_once('T')?;
    let mut d = date.splitn(3, '-').map(|p| p.parse::<i64>().ok());
    let (y, m, day) = (d.next()??, d.next()??, d.next()??);
    let (hms, frac) = time.split_once('.').unwrap_or((time, "0"));
    let mut t = hms.splitn(3, ':').map(|p| p.parse::<i64>().ok());
    let (hh, mm, ss) = (t.next()??, t.next()??, t.next()??);
    // Milliseconds from the first three digits of the fraction.
    let ms = format!("{frac:0<3}")[..3].parse::<i64>().ok()?;
    // Days from a civil date (H. Hinnant's algorithm).
    let y = if m <= 2 { y - 1 } else { y };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let doy = (153 * (m + if m > 2 { -3 } else { 9 }) + 2) / 5 + day - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    let days = era * 146_097 + doe - 719_468;
    Some(((days * 86_400 + hh * 3600 + mm * 60 + ss) * 1000) + ms)
}

fn field_ms(job: &Value, field: &str) -> i64 {
    job[field]
        .as_str()
        .and_then(rfc3339_ms)
        .unwrap_or_else(|| panic!("job without a valid {field}: {job}"))
}

fn now_ms() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .expect("after 1970")
        .as_millis() as i64
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let rank = (p / 100.0 * (sorted.len() - 1) as f64).round() as usize;
    sorted[rank.min(sorted.len() - 1)]
}

fn sorted(mut v: Vec<f64>) -> Vec<f64> {
    v.sort_by(f64::total_cmp);
    v
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

/// What a setup's jobs submitted one at a time showed.
struct Latency {
    setup: String,
    /// Sorted `timings_ms.queued`: submitted → claimed.
    claim_ms: Vec<f64>,
    /// Sorted response received − `finished_at`.
    wait_ms: Vec<f64>,
    /// Mean submit → response.
    round_trip_ms: f64,
}

/// What one batch showed.
struct Batch {
    setup: String,
    workers: usize,
    round: usize,
    jobs: usize,
    /// First submission to the last `finished_at`.
    seconds: f64,
    /// Mean `finished_at − started_at`: a worker's time on each job, the
    /// stores' included.
    busy_ms: f64,
    /// Mean `timings_ms.store`: writing a job's results to the file store.
    store_ms: f64,
    /// Mean time a worker spent between finishing a job and starting its
    /// next, with work queued: the final write, the claim, the hand-over.
    gap_ms: f64,
}

impl Batch {
    fn per_minute(&self) -> f64 {
        self.jobs as f64 / self.seconds * 60.0
    }
}

fn check(setup: &Setup, job: &Value) {
    assert!(
        state(job) == "succeeded",
        "{}: a job ended {}: {job}\n{}",
        setup.name,
        state(job),
        setup.logs()
    );
}

/// Submits the jobs one at a time into the idle setup, each with
/// `Prefer: wait=60`, so answered when final.
fn idle_series(setup: &Setup, c: &Client, specs: &[Spec]) -> Latency {
    let base = setup.api.base.as_str();
    let (mut claim, mut wait, mut trips) = (Vec::new(), Vec::new(), Vec::new());
    for s in specs {
        // Let idle workers settle into their wait for work.
        std::thread::sleep(Duration::from_millis(100));
        let sent = Instant::now();
        let mut job = submit(c, base, s, Some(60));
        let answered = now_ms();
        trips.push(sent.elapsed().as_secs_f64() * 1000.0);
        if state(&job) != "succeeded" {
            // Not final within the wait (should not happen): no figure.
            job = final_job(c, base, job["id"].as_str().expect("an id"));
            check(setup, &job);
            continue;
        }
        check(setup, &job);
        claim.push(
            job["timings_ms"]["queued"]
                .as_f64()
                .expect("timings_ms.queued"),
        );
        wait.push((answered - field_ms(&job, "finished_at")) as f64);
    }
    Latency {
        setup: setup.name.clone(),
        claim_ms: sorted(claim),
        wait_ms: sorted(wait),
        round_trip_ms: mean(&trips),
    }
}

/// Submits the jobs all at once, from a few client threads, and waits for
/// them all.
fn batch(setup: &Setup, c: &Client, specs: &[Spec], round: usize) -> Batch {
    let base = setup.api.base.as_str();
    // Whatever ran before settles.
    std::thread::sleep(Duration::from_millis(500));
    let first = now_ms();
    let ids: Vec<String> = std::thread::scope(|scope| {
        let handles: Vec<_> = (0..SUBMITTERS)
            .map(|t| {
                scope.spawn(move || {
                    specs
                        .iter()
                        .skip(t)
                        .step_by(SUBMITTERS)
                        .map(|s| {
                            submit(c, base, s, None)["id"]
                                .as_str()
                                .expect("an id")
                                .to_string()
                        })
                        .collect::<Vec<_>>()
                })
            })
            .collect();
        handles
            .into_iter()
            .flat_map(|h| h.join().expect("a submitting thread"))
            .collect()
    });
    let jobs: Vec<Value> = ids.iter().map(|id| final_job(c, base, id)).collect();
    for j in &jobs {
        check(setup, j);
    }
    let last = jobs
        .iter()
        .map(|j| field_ms(j, "finished_at"))
        .max()
        .expect("a batch");
    let busy: Vec<f64> = jobs
        .iter()
        .map(|j| (field_ms(j, "finished_at") - field_ms(j, "started_at")) as f64)
        .collect();
    let store: Vec<f64> = jobs
        .iter()
        .map(|j| j["timings_ms"]["store"].as_f64().unwrap_or(f64::NAN))
        .collect();
    // Each worker's jobs in the order it ran them.
    let mut by_worker: BTreeMap<String, Vec<(i64, i64)>> = BTreeMap::new();
    for j in &jobs {
        by_worker
            .entry(j["worker"].as_str().unwrap_or("").to_string())
            .or_default()
            .push((field_ms(j, "started_at"), field_ms(j, "finished_at")));
    }
    let mut gaps = Vec::new();
    for runs in by_worker.values_mut() {
        runs.sort();
        gaps.extend(runs.windows(2).map(|w| (w[1].0 - w[0].1) as f64));
    }
    Batch {
        setup: setup.name.clone(),
        workers: setup.workers,
        round,
        jobs: jobs.len(),
        seconds: (last - first) as f64 / 1000.0,
        busy_ms: mean(&busy),
        store_ms: mean(&store),
        gap_ms: mean(&gaps),
    }
}

fn main() {
    let n = knob("SEAMSTRESS_BENCH_JOBS", 200);
    let n_idle = knob("SEAMSTRESS_BENCH_IDLE", 30);
    let rounds = knob("SEAMSTRESS_BENCH_ROUNDS", 3).clamp(1, 8);
    let dir = std::env::temp_dir().join(format!("seamstress-bench-cluster-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("scratch folder");

    let read = |p: &str| -> &'static [u8] {
        let bytes = std::fs::read(shared_assets().join(p)).unwrap_or_else(|e| panic!("{p}: {e}"));
        Box::leak(bytes.into_boxed_slice())
    };
    let models = [
        ("cube_gradient_128.glb", read("cube/cube_gradient_128.glb")),
        (
            "BoxTextured.glb",
            read("BoxTextured/BoxTextured-glTF-Binary/BoxTextured.glb"),
        ),
    ];
    // Series 1 one at a time, then one series per round: distinct jobs in
    // one store, the same jobs for every setup.
    let idle = specs(&models, n_idle, 1);
    let batches: Vec<Vec<Spec>> = (0..rounds).map(|r| specs(&models, n, 2 + r)).collect();
    let queue = n + n_idle + 16;
    let c = Client::builder()
        .no_proxy()
        .timeout(Duration::from_secs(180))
        .build()
        .expect("an HTTP client");

    println!(
        "{} cores; batches of {n} distinct jobs (cube_gradient_128, BoxTextured \
         alternately), {n_idle} jobs one at a time",
        std::thread::available_parallelism().map_or(1, |c| c.get())
    );
    let began = Instant::now();
    // Started first, so that they idle through the embedded runs too.
    let servers = Postgres::start().zip(Seaweed::start());
    let (mut latencies, mut runs) = (Vec::new(), Vec::new());
    {
        let embedded = Setup::embedded(&dir, queue);
        latencies.push(idle_series(&embedded, &c, &idle));
        let pair = match &servers {
            Some(servers) => {
                let d1 = Setup::distributed(&dir, queue, servers, 1);
                // The LISTEN connections come up after the address.
                std::thread::sleep(Duration::from_secs(1));
                latencies.push(idle_series(&d1, &c, &idle));
                vec![embedded, d1]
            }
            None => {
                println!("(no PostgreSQL or SeaweedFS here: the embedded setup only)");
                vec![embedded]
            }
        };
        // The two the ratio compares, both up, their batches alternating
        // (A B, B A, A B, ...) so that the machine's drift falls on both.
        for (r, jobs) in batches.iter().enumerate() {
            let mut order: Vec<&Setup> = pair.iter().collect();
            if r % 2 == 1 {
                order.reverse();
            }
            for setup in order {
                eprintln!("{}, round {}", setup.name, r + 1);
                runs.push(batch(setup, &c, jobs, r + 1));
            }
        }
    }
    if let Some(servers) = &servers {
        for workers in [2, 3] {
            let setup = Setup::distributed(&dir, queue, servers, workers);
            std::thread::sleep(Duration::from_secs(1));
            latencies.push(idle_series(&setup, &c, &idle));
            eprintln!("{}, round 1", setup.name);
            runs.push(batch(&setup, &c, &batches[0], 1));
        }
    }
    drop(servers);

    println!();
    println!(
        "{:<28} {:>5} {:>8} {:>8} {:>8} {:>8} {:>7}",
        "throughput", "round", "batch s", "jobs/min", "busy ms", "store ms", "gap ms"
    );
    for b in &runs {
        println!(
            "{:<28} {:>5} {:>8.2} {:>8.1} {:>8.1} {:>8.1} {:>7.1}",
            b.setup,
            b.round,
            b.seconds,
            b.per_minute(),
            b.busy_ms,
            b.store_ms,
            b.gap_ms
        );
    }
    // Jobs per minute over every batch of a setup.
    let pooled = |workers: usize| -> (f64, Vec<&Batch>) {
        let of: Vec<&Batch> = runs.iter().filter(|b| b.workers == workers).collect();
        let jobs: usize = of.iter().map(|b| b.jobs).sum();
        let secs: f64 = of.iter().map(|b| b.seconds).sum();
        (jobs as f64 / secs * 60.0, of)
    };
    println!();
    for workers in 0..=3 {
        let (per_minute, of) = pooled(workers);
        if let Some(b) = of.first() {
            println!(
                "{:<28} {:>8.1} jobs/min over {} batch{}",
                b.setup,
                per_minute,
                of.len(),
                if of.len() == 1 { "" } else { "es" }
            );
        }
    }
    let ((embedded, e_runs), (distributed, d_runs)) = (pooled(0), pooled(1));
    if !d_runs.is_empty() {
        let each: Vec<String> = e_runs
            .iter()
            .zip(&d_runs)
            .map(|(e, d)| format!("{:.1}%", d.per_minute() / e.per_minute() * 100.0))
            .collect();
        println!(
            "distributed (1 worker) / embedded: {:.1}% (rounds: {}); target >= 90%",
            distributed / embedded * 100.0,
            each.join(", ")
        );
    }

    println!();
    println!(
        "{:<28} {:>15} {:>18} {:>8}",
        "one at a time, idle (ms)", "claim p50/p99", "wait-lag p50/p99", "rtt mean"
    );
    for l in &latencies {
        println!(
            "{:<28} {:>7.0}/{:<7.0} {:>9.0}/{:<8.0} {:>8.0}",
            l.setup,
            percentile(&l.claim_ms, 50.0),
            percentile(&l.claim_ms, 99.0),
            percentile(&l.wait_ms, 50.0),
            percentile(&l.wait_ms, 99.0),
            l.round_trip_ms
        );
    }
    println!();
    println!(
        "batch s: first submission to the last finished_at of the batch\n\
         busy ms: mean finished_at - started_at of the batch's jobs (claim to final state)\n\
         store ms: mean timings_ms.store of the batch's jobs (results into the file store)\n\
         gap ms: mean time a worker spent between one job's finished_at and its next started_at\n\
         claim: timings_ms.queued; wait-lag: response received - finished_at; rtt: submit to\n\
         answer; of {n_idle} jobs submitted one at a time with Prefer: wait=60 into the idle setup"
    );
    println!("took {:.0} s", began.elapsed().as_secs_f64());
    let _ = std::fs::remove_dir_all(&dir);
}
