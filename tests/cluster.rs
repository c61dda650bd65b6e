//! A cluster on one machine: two API servers and three worker processes on
//! one PostgreSQL and one S3 object store (SeaweedFS), all started here on
//! 127.0.0.1. Fifty jobs go round-robin to both API servers while one
//! worker is killed with SIGKILL mid-job and one API server is restarted;
//! every job succeeds, none runs to completion twice, and the files are
//! byte for byte what `seamstress process` writes.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use reqwest::blocking::Client;
use serde_json::Value;

mod common;
use common::cluster::{Postgres, Seaweed};
use common::{report_without_timings, shared_assets};
use needs::needs;

/// Short leases, so that a killed worker's job comes back within seconds.
const LEASE: &str = "2s";

fn scratch(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("seamstress-cluster-{}-{tag}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// One process of the cluster: `serve` or `worker`, on the shared stores.
struct Node {
    child: Child,
    base: String,
    argv: Vec<String>,
    env: Vec<(&'static str, String)>,
    alive: bool,
}

impl Node {
    fn start(argv: Vec<String>, env: Vec<(&'static str, String)>) -> Node {
        let mut child = Command::new(env!("CARGO_BIN_EXE_seamstress"))
            .args(&argv)
            .envs(env.iter().map(|(k, v)| (*k, v.as_str())))
            .env_remove("SEAMSTRESS_TOKENS")
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("seamstress starts");
        let addr = common::server::address_of(&mut child);
        Node {
            child,
            base: format!("http://{addr}"),
            argv,
            env,
            alive: true,
        }
    }

    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        self.alive = false;
    }

    fn restart(&mut self) {
        self.kill();
        *self = Node::start(self.argv.clone(), self.env.clone());
    }

    /// `seamstress_jobs_claimed_total` and `seamstress_leases_expired_total`
    /// of this process, summed over its workers.
    fn counters(&self, c: &Client) -> (u64, u64) {
        let text = c.get(self.url("/metrics")).send().unwrap().text().unwrap();
        let sum = |name: &str| -> u64 {
            text.lines()
                .filter(|l| l.starts_with(name))
                .filter_map(|l| l.rsplit(' ').next()?.parse::<u64>().ok())
                .sum()
        };
        (
            sum("seamstress_jobs_claimed_total{"),
            sum("seamstress_leases_expired_total{"),
        )
    }

    fn busy(&self, c: &Client) -> u64 {
        let text = c.get(self.url("/metrics")).send().unwrap().text().unwrap();
        text.lines()
            .find_map(|l| l.strip_prefix("seamstress_workers_busy "))
            .and_then(|v| v.trim().parse().ok())
            .unwrap_or(0)
    }
}

impl Drop for Node {
    fn drop(&mut self) {
        self.kill();
    }
}

/// The jobs: every small shared GLB under each decoder target, with and
/// without the seam-aware encoder, so that most jobs are work of their own;
/// the last ones repeat earlier ones (the store's cache answers them).
fn plan() -> Vec<(PathBuf, String)> {
    let a = shared_assets();
    let models = [
        a.join("BoxTextured/BoxTextured-glTF-Binary/BoxTextured.glb"),
        a.join("cube/cube_gradient_128.glb"),
        a.join("cube/cube_bad_background_100.glb"),
        a.join("blub/blub.glb"),
    ];
    let mut jobs = Vec::new();
    for seam_aware in ["true", "false"] {
        for decoder in ["ideal", "nvidia", "amd", "robust"] {
            for m in &models {
                jobs.push((
                    m.clone(),
                    format!("&decoder={decoder}&seam_aware={seam_aware}&pictures=false"),
                ));
            }
        }
    }
    let distinct = jobs.len();
    for i in 0..50 - distinct {
        jobs.push(jobs[i * 3 % distinct].clone());
    }
    jobs
}

fn submit(c: &Client, api: &Node, model: &Path, query: &str, key: &str) -> (u16, Value) {
    let name = model.file_name().unwrap().to_string_lossy();
    let r = c
        .post(api.url(&format!("/v1/jobs?name={name}{query}")))
        .header("content-type", "model/gltf-binary")
        .header("idempotency-key", key)
        .body(std::fs::read(model).unwrap())
        .send()
        .unwrap();
    let status = r.status().as_u16();
    (status, r.json().unwrap())
}

fn job(c: &Client, api: &Node, id: &str) -> Value {
    c.get(api.url(&format!("/v1/jobs/{id}")))
        .send()
        .unwrap()
        .json()
        .unwrap()
}

/// Waits until `pred` holds of job `id`, or panics after `secs`.
fn wait_job(c: &Client, api: &Node, id: &str, secs: u64, pred: impl Fn(&Value) -> bool) -> Value {
    let deadline = Instant::now() + Duration::from_secs(secs);
    loop {
        let j = job(c, api, id);
        if pred(&j) {
            return j;
        }
        assert!(Instant::now() < deadline, "job {id} stuck: {j}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// What `seamstress process` writes for `model` with the options of
/// `query`, by file name (the report without its timings).
fn processed(model: &Path, query: &str, out: &Path) -> BTreeMap<String, Vec<u8>> {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_seamstress"));
    cmd.arg("process").arg(model).arg("--out").arg(out);
    // The CLI's flags for the options the jobs set (its defaults: the
    // seam-aware encoder on, no pictures).
    for pair in query.split('&').filter(|p| !p.is_empty()) {
        match pair.split_once('=').unwrap() {
            ("seam_aware", "false") => {
                cmd.arg("--no-seam-aware");
            }
            ("seam_aware", "true") | ("pictures", "false") => {}
            ("decoder", v) => {
                cmd.arg(format!("--decoder={v}"));
            }
            other => panic!("no flag for {other:?}"),
        }
    }
    let o = cmd.output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let mut files = BTreeMap::new();
    for e in std::fs::read_dir(out).unwrap() {
        let p = e.unwrap().path();
        if p.is_file() {
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            files.insert(name, std::fs::read(&p).unwrap());
        }
    }
    files
}

fn same_files(got: &BTreeMap<String, Vec<u8>>, want: &BTreeMap<String, Vec<u8>>, what: &str) {
    assert_eq!(
        got.keys().collect::<Vec<_>>(),
        want.keys().collect::<Vec<_>>(),
        "{what}"
    );
    for (name, bytes) in want {
        if name == "report.json" {
            assert_eq!(
                report_without_timings(&got[name]),
                report_without_timings(bytes),
                "{what}: {name}"
            );
        } else {
            assert!(got[name] == *bytes, "{what}: {name} differs");
        }
    }
}

#[needs(postgres, seaweedfs)]
#[test]
fn two_api_servers_and_three_workers_lose_nothing() {
    let (Some(pg), Some(s3)) = (Postgres::start(), Seaweed::start()) else {
        return;
    };
    let root = scratch("main");
    let env = s3.env();
    let stores = |dir: &str| -> Vec<String> {
        vec![
            "--data".into(),
            root.join(dir).display().to_string(),
            "--store".into(),
            pg.url.clone(),
            "--files".into(),
            s3.url("jobs-of-the-cluster"),
            "--lease".into(),
            LEASE.into(),
        ]
    };
    let api_node = |dir: &str| {
        let mut argv: Vec<String> = ["serve", "--listen", "127.0.0.1:0", "--workers", "0"]
            .map(String::from)
            .to_vec();
        argv.extend(stores(dir));
        Node::start(argv, env.clone())
    };
    let worker_node = |dir: &str| {
        let mut argv: Vec<String> = [
            "worker",
            "--metrics-listen",
            "127.0.0.1:0",
            "--workers",
            "1",
        ]
        .map(String::from)
        .to_vec();
        argv.extend(stores(dir));
        Node::start(argv, env.clone())
    };
    let mut apis = [api_node("api0"), api_node("api1")];
    let mut workers = [worker_node("w0"), worker_node("w1"), worker_node("w2")];
    let c = Client::builder()
        .timeout(Duration::from_secs(120))
        .build()
        .unwrap();

    // A cancel sent to one API server stops the job a worker runs for the
    // other: the worker is free again long before the job would end.
    let slow = shared_assets().join("cube/cube_gradient_1024.glb");
    let (status, j) = submit(&c, &apis[1], &slow, "&decoder=robust&mips=true", "slow");
    assert_eq!(status, 202, "{j}");
    let id = j["id"].as_str().unwrap().to_string();
    wait_job(&c, &apis[0], &id, 30, |j| j["state"] == "running");
    let r = c
        .delete(apis[0].url(&format!("/v1/jobs/{id}")))
        .send()
        .unwrap();
    assert!(r.status().is_success(), "{}", r.status());
    let canceled_at = Instant::now();
    wait_job(&c, &apis[1], &id, 10, |j| j["state"] == "canceled");
    while workers.iter().map(|w| w.busy(&c)).sum::<u64>() > 0 {
        assert!(
            canceled_at.elapsed() < Duration::from_secs(10),
            "a worker still runs the canceled job"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let cancel_ms = canceled_at.elapsed().as_millis();

    // Fifty jobs, round-robin; each key sent again to the other server
    // names the same job.
    let plan = plan();
    let mut ids = Vec::new();
    // The worker killed, and the job it was running.
    let mut killed: Option<(String, String)> = None;
    let mut expired_before_restart = 0;
    for (i, (model, query)) in plan.iter().enumerate() {
        let key = format!("job-{i}");
        let (status, j) = submit(&c, &apis[i % 2], model, query, &key);
        assert!(status == 202 || status == 200, "{status}: {j}");
        let id = j["id"].as_str().unwrap().to_string();
        if i % 10 == 0 {
            let (_, again) = submit(&c, &apis[(i + 1) % 2], model, query, &key);
            assert_eq!(again["id"].as_str(), Some(id.as_str()), "key {key}");
        }
        ids.push(id);
        if i == 20 {
            // SIGKILL a worker in the middle of a job.
            let (running, victim_job) = loop {
                let found = ids.iter().find_map(|id| {
                    let j = job(&c, &apis[0], id);
                    (j["state"] == "running")
                        .then(|| (j["worker"].as_str().unwrap().to_string(), id.clone()))
                });
                if let Some(w) = found {
                    break w;
                }
                std::thread::sleep(Duration::from_millis(20));
            };
            let victim = workers
                .iter_mut()
                .find(|w| running.contains(&format!("-{}-", w.child.id())))
                .expect("the worker running the job is one of ours");
            victim.kill();
            killed = Some((running, victim_job));
        }
        if i == 30 {
            // Its counters start again from zero: what it counted so far
            // (the killed worker's lease may be among it) is kept.
            expired_before_restart += apis[0].counters(&c).1;
            apis[0].restart();
        }
    }

    // Every job succeeds; only the killed worker's job ran twice.
    let mut attempts = BTreeMap::new();
    // Whether the kill caught its job mid-run: a job can finish between
    // being seen running and the SIGKILL, and then no lease is left to expire.
    let mut caught = false;
    for id in &ids {
        let j = wait_job(&c, &apis[1], id, 600, |j| {
            !matches!(j["state"].as_str(), Some("queued" | "running"))
        });
        assert_eq!(j["state"], "succeeded", "{j}");
        if let Some((worker, victim)) = &killed {
            if victim == id {
                // Run again elsewhere, the killed run not charged, unless
                // it had just finished when the worker died.
                assert!(
                    j["worker"].as_str() != Some(worker.as_str()) || j["interruptions"] == 0,
                    "{j}"
                );
                caught = j["worker"].as_str() != Some(worker.as_str());
            }
        }
        *attempts
            .entry(j["attempts"].as_u64().unwrap())
            .or_insert(0usize) += 1;
    }
    // A worker killed by the operator is no fault of its job's (jobs the
    // cache answered at submission never ran: 0).
    assert!(attempts.keys().all(|&a| a <= 1), "attempts {attempts:?}");
    let expired: u64 = expired_before_restart
        + apis
            .iter()
            .chain(workers.iter().filter(|w| w.alive))
            .map(|n| n.counters(&c).1)
            .sum::<u64>();
    assert!(
        expired >= 1 || !caught,
        "the killed worker's lease was never taken back"
    );

    // Byte for byte what `process` writes, for every distinct job. The
    // runs of `process` go two at a time (small models leave a core idle).
    let mut seen = BTreeSet::new();
    let mut compared = Vec::new();
    for (n, ((model, query), id)) in plan.iter().zip(&ids).enumerate() {
        if !seen.insert((model.clone(), query.clone())) {
            continue;
        }
        let j = job(&c, &apis[n % 2], id);
        let mut got = BTreeMap::new();
        for f in j["files"].as_array().unwrap() {
            let name = f["name"].as_str().unwrap().to_string();
            let bytes = c
                .get(apis[n % 2].url(f["url"].as_str().unwrap()))
                .send()
                .unwrap()
                .bytes()
                .unwrap();
            got.insert(name, bytes.to_vec());
        }
        compared.push((n, model, query, got));
    }
    let next = std::sync::atomic::AtomicUsize::new(0);
    std::thread::scope(|scope| {
        for _ in 0..2 {
            scope.spawn(|| loop {
                let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let Some((n, model, query, got)) = compared.get(i) else {
                    break;
                };
                let want = processed(model, query, &root.join(format!("process-{n}")));
                same_files(got, &want, &format!("{} {query}", model.display()));
            });
        }
    });
    eprintln!(
        "cluster: 50 jobs, attempts {attempts:?}, leases taken back {expired}, \
         a cancel stopped its worker in {cancel_ms} ms"
    );
}
