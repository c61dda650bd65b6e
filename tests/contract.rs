//! The HTTP service against its own OpenAPI document: schemathesis generates
//! requests for every operation (bounded in count and time, loopback only),
//! and no answer may be a server error.

use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

mod common;
use common::server::Server;
use needs::needs;

/// Far above the run's own bound (`--max-time`), for a hung request.
const DEADLINE: Duration = Duration::from_secs(900);

#[needs(schemathesis)]
#[test]
fn no_generated_request_gets_a_server_error() {
    if !common::SCHEMATHESIS.available() {
        return;
    }
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let scratch = std::env::temp_dir().join(format!("seamstress-contract-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&scratch);
    std::fs::create_dir_all(&scratch).unwrap();

    let mut server = Server::start(&scratch.join("data"), &[]);

    // Run from the scratch folder: schemathesis keeps its example database
    // in the working directory.
    let mut run = Command::new("schemathesis")
        .arg("run")
        .arg(root.join("openapi.yaml"))
        .args(["--url", &server.base])
        .args(["--checks", "not_a_server_error"])
        .args([
            "--max-examples",
            "25",
            "--max-time",
            "60",
            "--request-timeout",
            "60",
        ])
        .current_dir(&scratch)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("schemathesis starts");
    // Its output can exceed a pipe's buffer: read it while it runs.
    let (stdout, stderr) = (run.stdout.take().unwrap(), run.stderr.take().unwrap());
    let out = std::thread::spawn(move || std::io::read_to_string(stdout).unwrap_or_default());
    let err = std::thread::spawn(move || std::io::read_to_string(stderr).unwrap_or_default());
    let start = Instant::now();
    let status = loop {
        if let Some(status) = run.try_wait().unwrap() {
            break Some(status);
        }
        if start.elapsed() > DEADLINE {
            let _ = run.kill();
            let _ = run.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(200));
    };
    server.kill();
    let (out, err) = (out.join().unwrap(), err.join().unwrap());
    let _ = std::fs::remove_dir_all(&scratch);
    assert!(
        status.is_some_and(|s| s.success()),
        "schemathesis {}:\n{out}\n{err}",
        match status {
            Some(s) => format!("failed ({s})"),
            None => format!("ran past {DEADLINE:?}"),
        }
    );
}
