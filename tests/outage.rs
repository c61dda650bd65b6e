//! Outages are weather: a server on PostgreSQL and an S3 object store
//! (SeaweedFS), both started here on 127.0.0.1, keeps its jobs through 20 s
//! in which one of them is frozen (SIGSTOP: connections open, nothing
//! answers, as with a host that has gone away). Jobs run and wait in the
//! queue when it goes; during the outage the API answers 503
//! `store_unavailable` with `Retry-After` in under a second, and `/readyz`
//! says which store; afterwards every job succeeds, none charged an
//! attempt.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use reqwest::blocking::Client;
use serde_json::{json, Value};

mod common;
use common::cluster::{Postgres, Seaweed};
use common::shared_assets;
use needs::needs;

/// How long the store stays away: the figure.
const OUTAGE: Duration = Duration::from_secs(20);

/// Jobs submitted before the outage: two workers busy, the rest queued.
const JOBS: u64 = 6;

/// What a client may wait, during the outage, for any answer.
const PROMPT: Duration = Duration::from_secs(1);

#[derive(Clone, Copy, Debug)]
enum Away {
    ObjectStore,
    JobStore,
}

fn scratch(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("seamstress-outage-{}-{tag}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// `seamstress serve` on the two stores, its log in `data/serve.log`.
struct Serve {
    child: Child,
    base: String,
    log: PathBuf,
}

impl Serve {
    fn start(data: &Path, pg: &Postgres, s3: &Seaweed, name: &str) -> Serve {
        let log = data.join("serve.log");
        let mut child = Command::new(env!("CARGO_BIN_EXE_seamstress"))
            .args(["serve", "--listen", "127.0.0.1:0", "--workers", "2"])
            .args(["--lease", "2s", "--data"])
            .arg(data.join("data"))
            .arg("--store")
            .arg(pg.new_database(name))
            .arg("--files")
            .arg(s3.url(name))
            .envs(s3.env())
            .env_remove("SEAMSTRESS_TOKENS")
            .env("SEAMSTRESS_LOG", "seamstress=info")
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .expect("seamstress starts");
        let addr = common::server::address_of(&mut child);
        Serve {
            child,
            base: format!("http://{addr}"),
            log,
        }
    }

    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    fn log(&self) -> String {
        let bytes = std::fs::read(&self.log).unwrap_or_default();
        let from = bytes.len().saturating_sub(6000);
        String::from_utf8_lossy(&bytes[from..]).into_owned()
    }
}

impl Drop for Serve {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A model of its own for job `n`: the same cube, told apart by an extra,
/// so that no job reuses another's result.
fn variant(n: u64) -> Vec<u8> {
    let glb = std::fs::read(shared_assets().join("cube/cube_gradient_1024.glb")).unwrap();
    let parts = seamstress::model::rewrite::split_glb(&glb).unwrap();
    let mut root: Value = serde_json::from_slice(parts.json).unwrap();
    root["extras"] = json!({ "variant": n });
    seamstress::model::rewrite::pack_glb(&serde_json::to_vec(&root).unwrap(), parts.bin)
}

fn submit(c: &Client, s: &Serve, n: u64) -> reqwest::blocking::Response {
    c.post(s.url(&format!("/v1/jobs?name=cube{n}.glb")))
        .header("content-type", "model/gltf-binary")
        .body(variant(n))
        .send()
        .unwrap()
}

fn job(c: &Client, s: &Serve, id: &str) -> Option<Value> {
    let r = c.get(s.url(&format!("/v1/jobs/{id}"))).send().ok()?;
    r.status().is_success().then(|| r.json().ok()).flatten()
}

/// Times one request; the status, `Retry-After`, body and time it took.
fn timed(req: reqwest::blocking::RequestBuilder) -> (u16, Option<String>, Value, Duration) {
    let (status, headers, body, took) = timed_with_headers(req);
    let retry = headers
        .get("retry-after")
        .and_then(|v| v.to_str().ok())
        .map(str::to_string);
    (status, retry, body, took)
}

/// [`timed`], with every header of the answer.
fn timed_with_headers(
    req: reqwest::blocking::RequestBuilder,
) -> (u16, reqwest::header::HeaderMap, Value, Duration) {
    let t = Instant::now();
    let r = req.send().expect("an answer");
    let took = t.elapsed();
    let status = r.status().as_u16();
    let headers = r.headers().clone();
    let body = r.json().unwrap_or(Value::Null);
    (status, headers, body, took)
}

fn ride_out(pg: &Postgres, s3: &Seaweed, away: Away) {
    let tag = match away {
        Away::ObjectStore => "s3",
        Away::JobStore => "pg",
    };
    let dir = scratch(tag);
    let s = Serve::start(&dir, pg, s3, &format!("outage_{tag}"));
    let c = Client::builder()
        .timeout(Duration::from_secs(30))
        .build()
        .unwrap();

    let mut ids = Vec::new();
    for n in 0..JOBS {
        let r = submit(&c, &s, n);
        assert_eq!(r.status().as_u16(), 202, "{}", s.log());
        let j: Value = r.json().unwrap();
        ids.push(j["id"].as_str().unwrap().to_string());
    }
    // Away while the first jobs run and the rest wait.
    let deadline = Instant::now() + Duration::from_secs(60);
    while !job(&c, &s, &ids[0]).is_some_and(|j| j["state"] != "queued") {
        assert!(Instant::now() < deadline, "no job started\n{}", s.log());
        std::thread::sleep(Duration::from_millis(20));
    }
    let gone = Instant::now();
    match away {
        Away::ObjectStore => s3.pause(),
        Away::JobStore => pg.pause(),
    }
    // The prober looks every second; give it two looks.
    std::thread::sleep(Duration::from_secs(3));

    let which = match away {
        Away::ObjectStore => "file store",
        Away::JobStore => "job store",
    };
    let (status, headers, body, took) = timed_with_headers(
        c.post(s.url("/v1/jobs?name=late.glb"))
            .header("content-type", "model/gltf-binary")
            .body(variant(100)),
    );
    assert_eq!(status, 503, "{body}\n{}", s.log());
    assert_eq!(body["code"], "store_unavailable", "{body}");
    assert!(headers.contains_key("retry-after"), "no Retry-After");
    // Its upload left unread, the connection closes after the answer: the
    // answer says so, and the client's next request takes a new one.
    assert_eq!(
        headers.get("connection").and_then(|v| v.to_str().ok()),
        Some("close"),
        "{headers:?}"
    );
    assert!(took < PROMPT, "submission answered in {took:?}");
    eprintln!("{tag}: submission answered {status} in {took:?}");
    let (status, _, body, took) = timed(c.get(s.url("/readyz")));
    assert_eq!(status, 503, "{body}");
    assert!(
        body["message"].as_str().unwrap_or("").contains(which),
        "{body}"
    );
    assert!(took < PROMPT, "/readyz answered in {took:?}");
    eprintln!(
        "{tag}: /readyz answered {status} in {took:?}: {}",
        body["message"]
    );
    let (status, _, _, took) = timed(c.get(s.url("/healthz")));
    assert_eq!(status, 200);
    assert!(took < PROMPT, "/healthz answered in {took:?}");
    let (status, _, _, _) = timed(c.get(s.url("/metrics")));
    assert_eq!(status, 200, "metrics are served during an outage");
    if let Away::ObjectStore = away {
        // The job store answers: the jobs can be read.
        let (status, _, body, took) = timed(c.get(s.url(&format!("/v1/jobs/{}", ids[0]))));
        assert_eq!(status, 200, "{body}");
        assert!(took < PROMPT, "a job read in {took:?}");
    }

    std::thread::sleep(OUTAGE.saturating_sub(gone.elapsed()));
    match away {
        Away::ObjectStore => s3.resume(),
        Away::JobStore => pg.resume(),
    }
    eprintln!("{tag}: back after {:?}", gone.elapsed());

    let deadline = Instant::now() + Duration::from_secs(300);
    for id in &ids {
        let j = loop {
            if let Some(j) = job(&c, &s, id) {
                if !matches!(j["state"].as_str(), Some("queued" | "running")) {
                    break j;
                }
            }
            assert!(
                Instant::now() < deadline,
                "job {id} did not end\n{}",
                s.log()
            );
            std::thread::sleep(Duration::from_millis(100));
        };
        assert_eq!(j["state"], "succeeded", "{j}\n{}", s.log());
        assert_eq!(j["attempts"], 1, "charged for an outage: {j}");
        let report = c
            .get(s.url(&format!("/v1/jobs/{id}/files/report.json")))
            .send()
            .unwrap();
        assert_eq!(report.status().as_u16(), 200);
    }
    let (status, _, body, _) = timed(c.get(s.url("/readyz")));
    assert_eq!(status, 200, "{body}");
    let log = std::fs::read_to_string(&s.log).unwrap();
    for said in ["dependency down", "dependency answers again"] {
        assert!(
            log.contains(said),
            "the log never says {said:?}\n{}",
            s.log()
        );
    }
    let outage_lines: Vec<&str> = log
        .lines()
        .filter(|l| l.contains("outage") || l.contains("dependency"))
        .collect();
    eprintln!("{tag}: {}", outage_lines.join("\n"));
    drop(s);
    let _ = std::fs::remove_dir_all(&dir);
}

/// One after the other, on one pair of servers: each outage must be the
/// only thing going on.
#[needs(postgres, seaweedfs)]
#[test]
fn jobs_ride_out_either_store_going_away() {
    let (Some(pg), Some(s3)) = (Postgres::start(), Seaweed::start()) else {
        return;
    };
    ride_out(&pg, &s3, Away::ObjectStore);
    ride_out(&pg, &s3, Away::JobStore);
}
