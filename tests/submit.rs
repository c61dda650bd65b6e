//! `submit`: the farm folder through a server that is killed with SIGKILL
//! halfway and restarted; run again, the batch completes with no model run
//! twice, and every output is what `process` writes.
//!
//! The farm here leaves out the two blub atlases: GLBs of one texture like
//! blub's, which the farm keeps, they go through the same upload, job and
//! download as it and are the two costliest models to process (`batch`
//! and `harm` process them).

use std::path::Path;
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

mod common;
use common::server::Server;
use common::{farm_folder_without, report_without_timings};

fn scratch(tag: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("seamstress-submit-{}-{tag}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn seamstress(verb: &str, input: &Path, out: &Path, extra: &[&str]) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_seamstress"));
    c.arg(verb)
        .arg(input)
        .arg("--out")
        .arg(out)
        .args(["--keep-going", "--jobs", "2"])
        .args(extra)
        .env_remove("SEAMSTRESS_TOKEN");
    c
}

fn run(mut c: Command) -> (Output, Value, String) {
    let sum = std::env::temp_dir().join(format!("seamstress-submit-{}.json", std::process::id()));
    let o = c
        .arg("--summary")
        .arg(&sum)
        .output()
        .expect("seamstress runs");
    let s = serde_json::from_slice(&std::fs::read(&sum).unwrap_or_default()).unwrap_or(Value::Null);
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    (o, s, err)
}

/// Every file below `dir`, relative, but the staging folders.
fn tree(dir: &Path) -> Vec<String> {
    let mut out = Vec::new();
    let mut dirs = vec![dir.to_path_buf()];
    while let Some(d) = dirs.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                dirs.push(p);
            } else {
                out.push(p.strip_prefix(dir).unwrap().display().to_string());
            }
        }
    }
    out.sort();
    out
}

fn stamps(dir: &Path) -> usize {
    if !dir.exists() {
        return 0;
    }
    tree(dir)
        .iter()
        .filter(|f| f.ends_with("seamstress.stamp.json"))
        .count()
}

fn jobs_on(s: &Server) -> Vec<Value> {
    let body = reqwest::blocking::get(s.url("/v1/jobs?limit=100"))
        .and_then(|r| r.json::<Value>())
        .expect("the job list");
    body["jobs"].as_array().cloned().unwrap_or_default()
}

fn kill(child: &mut Child) {
    let _ = child.kill();
    let _ = child.wait();
}

#[test]
fn a_batch_survives_a_killed_server_runs_each_model_once_and_matches_process() {
    let dir = scratch("farm");
    let (input, models) = farm_folder_without(&dir, &["blub_atlas"]);
    let local = dir.join("local");
    let (o, s, err) = run(seamstress("process", &input, &local, &[]));
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert_eq!(s["processed"], models - 1, "{s}");

    let data = dir.join("data");
    let mut server = Server::start(&data, &["--workers", "1"]);
    let remote = dir.join("remote");
    let mut first = seamstress("submit", &input, &remote, &["--server", &server.base])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    // Halfway: some models downloaded, others uploaded or waiting.
    let deadline = Instant::now() + Duration::from_secs(300);
    while stamps(&remote) < 3 {
        assert!(Instant::now() < deadline, "no model came back");
        assert!(first.try_wait().unwrap().is_none(), "submit ended early");
        std::thread::sleep(Duration::from_millis(50));
    }
    server.kill();
    kill(&mut first);
    let done_before = stamps(&remote);
    assert!(
        done_before < models - 1,
        "the batch was done before the kill"
    );
    server.restart();

    let (o, s, err) = run(seamstress(
        "submit",
        &input,
        &remote,
        &["--server", &server.base],
    ));
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert_eq!(s["models"], models, "{s}");
    assert_eq!(s["bad_input"], 1, "{s}");
    assert_eq!(s["cached"], done_before, "{s}");
    assert_eq!(s["processed"], models - 1 - done_before, "{s}");
    assert!(err.contains("KHR_draco_mesh_compression"), "{err}");

    // One job per good model, however often it was uploaded: the bad one
    // was refused at the door.
    let jobs = jobs_on(&server);
    assert_eq!(jobs.len(), models - 1, "{jobs:?}");
    assert!(jobs.iter().all(|j| j["state"] == "succeeded"), "{jobs:?}");
    let third = run(seamstress(
        "submit",
        &input,
        &remote,
        &["--server", &server.base],
    ))
    .1;
    assert_eq!(third["cached"], models - 1, "{third}");
    assert_eq!(jobs_on(&server).len(), models - 1);

    // The same tree as `process`, the same bytes (a report's timings aside).
    let files = tree(&local);
    assert_eq!(tree(&remote), files);
    for f in &files {
        let a = std::fs::read(local.join(f)).unwrap();
        let b = std::fs::read(remote.join(f)).unwrap();
        if f.ends_with("report.json") {
            assert_eq!(
                report_without_timings(&a),
                report_without_timings(&b),
                "{f}"
            );
        } else if !f.ends_with("seamstress.stamp.json") {
            assert_eq!(a, b, "{f}");
        }
    }
    drop(server);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_wrong_token_fails_with_status_2_and_the_right_one_succeeds() {
    let dir = scratch("refused");
    let model = common::shared_assets().join("cube/cube_gradient_128.glb");
    let data = dir.join("data");
    let server = Server::start(&data, &["--token", "right"]);
    let out = dir.join("out");
    let mut c = seamstress("submit", &model, &out, &["--server", &server.base]);
    c.env("SEAMSTRESS_TOKEN", "wrong");
    let o = c.output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("401") && err.contains("SEAMSTRESS_TOKEN"),
        "{err}"
    );
    let mut c = seamstress("submit", &model, &out, &["--server", &server.base]);
    c.env("SEAMSTRESS_TOKEN", "right");
    let o = c.output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.join("cube_gradient_128.dds").is_file());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn an_address_the_client_cannot_speak_to_fails_at_once_with_status_2() {
    let dir = scratch("address");
    let model = common::shared_assets().join("cube/cube_gradient_128.glb");
    let out = dir.join("out");
    for (server, says) in [
        (
            "ftp://127.0.0.1:8080",
            "ftp:// is not a scheme this client speaks",
        ),
        ("https://127.0.0.1:8080", "plain HTTP only"),
        ("http://127.0.0.1:99999", "not a URL: invalid port number"),
        ("http://", "not a URL: empty host"),
        ("http://127.0.0.1:8080/?x=1", "no query or fragment"),
        ("127.0.0.1:8080", "no scheme; give http://127.0.0.1:8080"),
    ] {
        let started = Instant::now();
        let o = seamstress("submit", &model, &out, &["--server", server])
            .output()
            .unwrap();
        let took = started.elapsed();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{server}: {err}");
        assert!(took < Duration::from_secs(1), "{server}: {took:?}");
        let lines: Vec<&str> = err.lines().collect();
        assert_eq!(lines.len(), 1, "{server}: {err}");
        assert!(
            lines[0].starts_with(&format!("error: --server {server}: ")),
            "{err}"
        );
        assert!(lines[0].contains(says), "{server}: {err}");
    }
    assert!(
        !out.exists(),
        "nothing is written before the address is checked"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn against_a_closed_port_each_retry_is_said_and_the_batch_gives_up() {
    let dir = scratch("closed");
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let server = format!("http://127.0.0.1:{port}");
    let started = Instant::now();
    // Three models, two at once: the third starts after the first two
    // gave up.
    let (o, s, err) = run(seamstress(
        "submit",
        &common::shared_assets().join("cube"),
        &dir.join("out"),
        &["--server", &server, "--give-up-after", "2s"],
    ));
    let took = started.elapsed();
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("server unreachable, retry 1 in 250 ms, giving up in 2 s"),
        "{err}"
    );
    let retries = err.matches("server unreachable, retry ").count();
    assert!(retries >= 4, "two models, each retried: {err}");
    assert!(err.contains("gave up after 3 retries"), "{err}");
    assert!(
        err.contains("stayed unreachable for an earlier model"),
        "{err}"
    );
    assert_eq!(s["failed"], 3, "{s}");
    assert!(took < Duration::from_secs(20), "{took:?}");
    let _ = std::fs::remove_dir_all(&dir);
}
