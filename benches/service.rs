//! The service under load: 16 concurrent clients on loopback submit
//! BoxTextured and blub (each upload unique, so the result cache never
//! answers), wait for each result and download its DDS. Compared with
//! `seamstress process` run back to back on the same models.
//!
//!     cargo bench --bench service
//!
//! `SEAMSTRESS_BENCH_ROUNDS` (default 2): jobs per client per model, so
//! 16 × 2 × ROUNDS jobs in all. Every phase stops after 10 minutes.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde_json::{json, Value};

#[path = "../tests/common/mod.rs"]
mod common;
use common::server::Server;

const CLIENTS: usize = 16;
const PHASE_LIMIT: Duration = Duration::from_secs(600);

fn assets() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/assets")
}

/// The same GLB with a different JSON chunk: equal work, different bytes.
fn variant(glb: &[u8], n: u64) -> Vec<u8> {
    let parts = seamstress::model::rewrite::split_glb(glb).expect("a GLB");
    let mut root: Value = serde_json::from_slice(parts.json).expect("glTF JSON");
    root["extras"] = json!({ "bench": n });
    seamstress::model::rewrite::pack_glb(&serde_json::to_vec(&root).expect("JSON"), parts.bin)
}

/// Peak resident memory of a process, in MiB, while it lives.
fn peak_rss_mib(pid: u32) -> Option<f64> {
    status_mib(pid, "VmHWM:")
}

/// A memory figure of `/proc/PID/status` (`VmHWM:`, `VmRSS:`) in MiB.
fn status_mib(pid: u32, field: &str) -> Option<f64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status.lines().find(|l| l.starts_with(field))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

/// Runs a child to its end, sampling its peak memory.
fn run_sampled(mut child: Child) -> (bool, f64) {
    let pid = child.id();
    let mut peak: f64 = 0.0;
    loop {
        if let Some(m) = peak_rss_mib(pid) {
            peak = peak.max(m);
        }
        match child.try_wait() {
            Ok(Some(status)) => return (status.success(), peak),
            Ok(None) => std::thread::sleep(Duration::from_millis(5)),
            Err(_) => return (false, peak),
        }
    }
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let rank = (p / 100.0 * (sorted.len() - 1) as f64).round() as usize;
    sorted[rank.min(sorted.len() - 1)]
}

struct Workload {
    /// (file name, bytes) for every job, in submission order.
    jobs: Vec<(String, Vec<u8>)>,
}

fn workload(rounds: usize) -> Workload {
    let boxtex =
        std::fs::read(assets().join("BoxTextured/BoxTextured-glTF-Binary/BoxTextured.glb"))
            .expect("BoxTextured.glb");
    let blub = std::fs::read(assets().join("blub/blub.glb")).expect("blub.glb");
    let mut jobs = Vec::new();
    let mut n = 0;
    for _ in 0..CLIENTS * rounds {
        jobs.push(("BoxTextured.glb".to_string(), variant(&boxtex, n)));
        jobs.push(("blub.glb".to_string(), variant(&blub, n + 1)));
        n += 2;
    }
    Workload { jobs }
}

/// `seamstress process` on each job, one after the other.
fn back_to_back(w: &Workload, dir: &Path) -> (usize, Duration, f64) {
    let started = Instant::now();
    let mut done = 0;
    let mut peak: f64 = 0.0;
    for (i, (name, bytes)) in w.jobs.iter().enumerate() {
        if started.elapsed() > PHASE_LIMIT {
            break;
        }
        let input = dir.join(format!("in-{i}-{name}"));
        std::fs::write(&input, bytes).expect("write input");
        let child = Command::new(env!("CARGO_BIN_EXE_seamstress"))
            .arg("process")
            .arg(&input)
            .arg("--out")
            .arg(dir.join(format!("out-{i}")))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("seamstress process");
        let (ok, p) = run_sampled(child);
        assert!(ok, "seamstress process failed on {name}");
        peak = peak.max(p);
        done += 1;
    }
    (done, started.elapsed(), peak)
}

struct ServiceRun {
    done: usize,
    elapsed: Duration,
    submit_ms: Vec<f64>,
    peak_mib: f64,
    idle_mib: f64,
    bytes_out: u64,
}

async fn service(w: Workload, data: &Path) -> ServiceRun {
    let mut server = Server::start(data, &["--queue-size", "256"]);
    let (pid, base) = (server.child.id(), server.base.clone());
    let peak = Arc::new(AtomicU64::new(0));
    let sampling = Arc::new(AtomicBool::new(true));
    let sampler = {
        let (peak, sampling) = (peak.clone(), sampling.clone());
        std::thread::spawn(move || {
            while sampling.load(Ordering::Relaxed) {
                if let Some(m) = peak_rss_mib(pid) {
                    peak.fetch_max((m * 1024.0) as u64, Ordering::Relaxed);
                }
                std::thread::sleep(Duration::from_millis(20));
            }
        })
    };
    let client = reqwest::Client::builder()
        .timeout(Duration::from_secs(600))
        .build()
        .expect("client");
    let jobs = Arc::new(w.jobs);
    let started = Instant::now();
    let mut tasks = Vec::new();
    for c in 0..CLIENTS {
        let (client, base, jobs) = (client.clone(), base.clone(), jobs.clone());
        tasks.push(tokio::spawn(async move {
            let mut latencies = Vec::new();
            let mut done = 0usize;
            let mut bytes_out = 0u64;
            for (name, bytes) in jobs.iter().skip(c).step_by(CLIENTS) {
                if started.elapsed() > PHASE_LIMIT {
                    break;
                }
                let t = Instant::now();
                let r = client
                    .post(format!("{base}/v1/jobs?name={name}"))
                    .header("content-type", "model/gltf-binary")
                    .body(bytes.clone())
                    .send()
                    .await
                    .expect("submit");
                let status = r.status();
                let job: Value = r.json().await.expect("job JSON");
                latencies.push(t.elapsed().as_secs_f64() * 1000.0);
                assert_eq!(status.as_u16(), 202, "{job}");
                let id = job["id"].as_str().expect("id").to_string();
                let job = loop {
                    let j: Value = client
                        .get(format!("{base}/v1/jobs/{id}"))
                        .header("prefer", "wait=60")
                        .send()
                        .await
                        .expect("poll")
                        .json()
                        .await
                        .expect("job JSON");
                    if j["state"] != "queued" && j["state"] != "running" {
                        break j;
                    }
                };
                assert_eq!(job["state"], "succeeded", "{job}");
                let dds = job["report"]["textures"][0]["files"]["dds"]
                    .as_str()
                    .expect("a DDS")
                    .to_string();
                let body = client
                    .get(format!("{base}/v1/jobs/{id}/files/{dds}"))
                    .send()
                    .await
                    .expect("download")
                    .bytes()
                    .await
                    .expect("DDS bytes");
                bytes_out += body.len() as u64;
                done += 1;
            }
            (latencies, done, bytes_out)
        }));
    }
    let mut submit_ms = Vec::new();
    let (mut done, mut bytes_out) = (0, 0);
    for t in tasks {
        let (l, d, b) = t.await.expect("client task");
        submit_ms.extend(l);
        done += d;
        bytes_out += b;
    }
    let elapsed = started.elapsed();
    sampling.store(false, Ordering::Relaxed);
    let _ = sampler.join();
    // An idle worker hands freed memory back; give it a moment to notice.
    std::thread::sleep(Duration::from_secs(3));
    let idle_mib = status_mib(pid, "VmRSS:").unwrap_or(f64::NAN);
    server.kill();
    submit_ms.sort_by(|a, b| a.total_cmp(b));
    ServiceRun {
        done,
        elapsed,
        submit_ms,
        peak_mib: peak.load(Ordering::Relaxed) as f64 / 1024.0,
        idle_mib,
        bytes_out,
    }
}

fn main() {
    let rounds: usize = std::env::var("SEAMSTRESS_BENCH_ROUNDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .filter(|&r| (1..=8).contains(&r))
        .unwrap_or(2);
    let dir = std::env::temp_dir().join(format!("seamstress-bench-service-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(dir.join("cli")).expect("scratch folder");
    let w = workload(rounds);
    let total = w.jobs.len();
    println!(
        "workload: {total} jobs (BoxTextured and blub alternating), {CLIENTS} clients, {} cores",
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );

    let (cli_done, cli_time, cli_peak) = back_to_back(&w, &dir.join("cli"));
    let cli_rate = cli_done as f64 / cli_time.as_secs_f64() * 60.0;
    println!(
        "seamstress process back to back: {cli_done} jobs in {:.1} s = {cli_rate:.1} jobs/min, peak {cli_peak:.0} MiB per process",
        cli_time.as_secs_f64()
    );

    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    let run = rt.block_on(service(w, &dir.join("data")));
    let rate = run.done as f64 / run.elapsed.as_secs_f64() * 60.0;
    let p50 = percentile(&run.submit_ms, 50.0);
    let p99 = percentile(&run.submit_ms, 99.0);
    println!(
        "seamstress serve, {CLIENTS} clients: {} jobs in {:.1} s = {rate:.1} jobs/min",
        run.done,
        run.elapsed.as_secs_f64()
    );
    println!(
        "submission latency: p50 {p50:.1} ms, p99 {p99:.1} ms, max {:.1} ms ({} submissions)",
        run.submit_ms.last().copied().unwrap_or(f64::NAN),
        run.submit_ms.len()
    );
    println!(
        "server memory: peak {:.0} MiB, {:.0} MiB once idle; DDS downloaded: {:.1} MiB",
        run.peak_mib,
        run.idle_mib,
        run.bytes_out as f64 / (1 << 20) as f64
    );
    let ratio = rate / cli_rate;
    println!(
        "goals: p99 submission < 50 ms: {} ({p99:.1} ms); throughput >= 90% of back-to-back: {} ({:.0}%)",
        if p99 < 50.0 { "met" } else { "missed" },
        if ratio >= 0.9 { "met" } else { "missed" },
        ratio * 100.0
    );
    let _ = std::fs::remove_dir_all(&dir);
}
