//! Each job in a process of its own, so that its crash or its running out
//! of memory cannot take the server, or any other job, with it.
//!
//! The worker writes the upload and the options into a scratch folder and
//! starts `seamstress run-job` on it under an address-space limit
//! (`setrlimit(RLIMIT_AS)`, so an allocation past it fails in the child
//! instead of the kernel killing whatever process it likes). The child runs
//! [`engine::run`] and reports on standard output, one JSON event a line:
//! progress, then the outcome, whose files it has written beside the input.
//! The worker relays progress to the job store, and stops the child
//! (SIGKILL) on a cancel, the time limit or shutdown. A child that ends
//! without an outcome has crashed: the worker's caller retries it once.

use std::io::{BufRead, BufReader, Read};
use std::os::unix::ffi::OsStrExt;
use std::os::unix::process::{CommandExt, ExitStatusExt};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use serde::{Deserialize, Serialize};
use serde_json::value::RawValue;

use crate::budget::Limits;

use super::engine::{self, EngineError, Produced, Stop};
use super::job::{Progress, StageTimings};
use super::upload::Bundle;
use crate::pipeline::ProcessOptions;

/// How often a waiting worker looks for a cancel or the time limit.
const POLL: Duration = Duration::from_millis(50);

/// The most of a crashed child's standard error kept for its message.
const STDERR_TAIL: usize = 2048;

/// What the child tells the worker, a line each.
// Externally tagged: an internally tagged enum buffers its fields, which a
// `RawValue` cannot pass through.
#[derive(Debug, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
enum Event {
    Progress(Progress),
    /// The job's files are `out/0`, `out/1`, … in the order of `names`.
    Done {
        names: Vec<String>,
        report: Box<RawValue>,
        timings: StageTimings,
        warnings: Vec<String>,
    },
    Failed {
        kind: FailureKind,
        message: String,
    },
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
enum FailureKind {
    BadInput,
    TooLarge,
    StorageFull,
    Failed,
}

/// What the child is given besides the upload.
#[derive(Debug, Serialize, Deserialize)]
struct Task {
    options: ProcessOptions,
    max_texture_size: u32,
    max_memory: u64,
}

/// How a job process is started and held.
#[derive(Clone, Debug)]
pub struct Isolation {
    /// The `seamstress` binary (the server's own).
    pub exe: PathBuf,
    /// Address space a job process may map, bytes.
    pub address_space: u64,
    /// Where scratch folders go (inside the data folder).
    pub scratch: PathBuf,
}

/// Runs one job in a child process. `checkpoint` receives the child's
/// progress (an `Err` stops the child); `stopped` is polled meanwhile.
#[allow(clippy::too_many_arguments)]
pub fn run(
    iso: &Isolation,
    tag: &str,
    bundle: &[u8],
    options: &ProcessOptions,
    max_texture_size: u32,
    limits: &Limits,
    checkpoint: &mut dyn FnMut(&Progress) -> Result<(), Stop>,
    stopped: &dyn Fn() -> Option<Stop>,
) -> Result<Produced, EngineError> {
    let dir = iso.scratch.join(tag);
    let _ = std::fs::remove_dir_all(&dir);
    let failed = |what: &str, e: std::io::Error| {
        let message = format!("cannot {what} the job's scratch folder: {e}");
        if super::store::is_full(&e) {
            EngineError::StorageFull(message)
        } else {
            EngineError::Failed(message)
        }
    };
    std::fs::create_dir_all(dir.join("out")).map_err(|e| failed("create", e))?;
    let _cleanup = RemoveOnDrop(dir.clone());
    let task = Task {
        options: *options,
        max_texture_size,
        max_memory: limits.max_memory,
    };
    std::fs::write(dir.join("input.bundle"), bundle).map_err(|e| failed("write", e))?;
    std::fs::write(
        dir.join("task.json"),
        serde_json::to_vec(&task).map_err(|e| EngineError::Failed(e.to_string()))?,
    )
    .map_err(|e| failed("write", e))?;

    let mut cmd = Command::new(&iso.exe);
    cmd.arg("run-job")
        .arg(&dir)
        .env("RUST_BACKTRACE", "0")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    let limit = iso.address_space;
    let parent = std::process::id();
    // SAFETY: setrlimit, prctl, getppid and _exit are async-signal-safe and
    // touch only the child.
    unsafe {
        cmd.pre_exec(move || {
            let lim = libc::rlimit {
                rlim_cur: limit,
                rlim_max: limit,
            };
            if libc::setrlimit(libc::RLIMIT_AS, &lim) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            // A server killed outright takes its jobs' processes with it
            // (the worker thread that started them lives as long as it);
            // the restarted server runs those jobs again.
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            // The server died between the fork and the line above: no
            // signal will come, so the child must not run at all.
            if libc::getppid() as u32 != parent {
                libc::_exit(1);
            }
            Ok(())
        });
    }
    let mut child = cmd
        .spawn()
        .map_err(|e| EngineError::Failed(format!("cannot start the job process: {e}")))?;
    // For the next server on this data folder, should this one die: see
    // `stop_leftovers`.
    let _ = std::fs::write(dir.join(PID_FILE), child.id().to_string());
    let stdout = child.stdout.take().expect("piped stdout");
    let mut stderr = child.stderr.take().expect("piped stderr");
    let (events, received) = mpsc::channel();
    let reader = std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines() {
            let Ok(line) = line else { break };
            match serde_json::from_str::<Event>(&line) {
                Ok(e) => {
                    if events.send(e).is_err() {
                        break;
                    }
                }
                Err(e) => tracing::warn!(error = %e, "unreadable event from a job process"),
            }
        }
    });
    let errors = std::thread::spawn(move || {
        let mut text = Vec::new();
        let _ = stderr.read_to_end(&mut text);
        let from = text.len().saturating_sub(STDERR_TAIL);
        String::from_utf8_lossy(&text[from..]).into_owned()
    });

    let mut outcome = None;
    let stop = loop {
        match received.recv_timeout(POLL) {
            Ok(Event::Progress(at)) => {
                if let Err(stop) = checkpoint(&at) {
                    break Some(stop);
                }
            }
            Ok(end) => outcome = Some(end),
            Err(mpsc::RecvTimeoutError::Timeout) => {}
            Err(mpsc::RecvTimeoutError::Disconnected) => break None,
        }
        if let Some(stop) = stopped() {
            break Some(stop);
        }
    };
    if stop.is_some() {
        let _ = child.kill();
    }
    let status = child.wait();
    let _ = reader.join();
    let stderr_tail = errors.join().unwrap_or_default();
    if let Some(stop) = stop {
        return Err(EngineError::Stopped(stop));
    }
    match outcome {
        Some(Event::Done {
            names,
            report,
            timings,
            warnings,
        }) => {
            let mut files = Vec::with_capacity(names.len());
            for (k, name) in names.into_iter().enumerate() {
                let bytes = std::fs::read(dir.join("out").join(k.to_string()))
                    .map_err(|e| failed("read", e))?;
                files.push((name, bytes));
            }
            Ok(Produced {
                files,
                report,
                timings,
                warnings,
            })
        }
        Some(Event::Failed { kind, message }) => Err(match kind {
            FailureKind::BadInput => EngineError::BadInput(message),
            FailureKind::TooLarge => EngineError::TooLarge(message),
            FailureKind::StorageFull => EngineError::StorageFull(message),
            FailureKind::Failed => EngineError::Failed(message),
        }),
        _ => Err(crashed(status, &stderr_tail, limit)),
    }
}

/// Why a child ended without an outcome, as the job's error.
fn crashed(
    status: std::io::Result<std::process::ExitStatus>,
    stderr: &str,
    limit: u64,
) -> EngineError {
    let how = match status {
        Ok(s) => match (s.code(), s.signal()) {
            (Some(c), _) => format!("exit status {c}"),
            (None, Some(sig)) => format!("signal {sig}"),
            _ => "an unknown status".to_string(),
        },
        Err(e) => format!("an unreadable status ({e})"),
    };
    // The panic's or the allocator's own words: the first lines it wrote.
    let said: Vec<&str> = stderr
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .take(2)
        .collect();
    let said = said.join(" ");
    let out_of_memory = stderr.contains("memory allocation of")
        || stderr.contains("capacity overflow")
        || stderr.contains("out of memory");
    if out_of_memory {
        return EngineError::TooLarge(format!(
            "the job ran out of its {} of address space ({said})",
            crate::budget::Bytes(limit)
        ));
    }
    EngineError::Crashed(format!("the job process ended with {how}: {said}"))
}

/// The job process's id, in its scratch folder.
const PID_FILE: &str = "pid";

/// Stops the job processes a dead server left running on `scratch`, before
/// their jobs run again. The kernel sends them SIGKILL when their server
/// dies (`PR_SET_PDEATHSIG`), but only once the server's own exit is done,
/// which takes a while for a server holding gigabytes; meanwhile a new
/// server may already have started. A process is stopped only if it still
/// runs `run-job` on that very folder: a pid alone may have been reused.
pub fn stop_leftovers(scratch: &Path) {
    let Ok(entries) = std::fs::read_dir(scratch) else {
        return;
    };
    for dir in entries.flatten().map(|e| e.path()) {
        let Some(pid) = std::fs::read_to_string(dir.join(PID_FILE))
            .ok()
            .and_then(|s| s.trim().parse::<i32>().ok())
            .filter(|&p| p > 1)
        else {
            continue;
        };
        if !runs_job_in(pid, &dir) {
            continue;
        }
        tracing::warn!(pid, dir = %dir.display(), "stopping a job process left by a dead server");
        // SAFETY: a plain signal to a process checked just above.
        unsafe { libc::kill(pid, libc::SIGKILL) };
        let deadline = std::time::Instant::now() + Duration::from_secs(5);
        while runs_job_in(pid, &dir) && std::time::Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

/// Whether process `pid` is alive (not a zombie) and runs `run-job` on
/// `dir`.
fn runs_job_in(pid: i32, dir: &Path) -> bool {
    let proc = PathBuf::from(format!("/proc/{pid}"));
    let alive = std::fs::read_to_string(proc.join("stat"))
        .ok()
        .and_then(|s| {
            s.rsplit_once(')')
                .map(|(_, rest)| rest.trim_start().to_string())
        })
        .is_some_and(|rest| !rest.starts_with('Z') && !rest.starts_with('X'));
    let args = std::fs::read(proc.join("cmdline")).unwrap_or_default();
    let mut args = args.split(|&b| b == 0);
    let runs = args.any(|a| a == b"run-job")
        && args
            .next()
            .is_some_and(|a| Path::new(std::ffi::OsStr::from_bytes(a)) == dir);
    alive && runs
}

struct RemoveOnDrop(PathBuf);

impl Drop for RemoveOnDrop {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// `seamstress run-job DIR`: the child's side. Always exits 0 once it has
/// written an outcome; anything else is a crash for the worker to handle.
pub fn child(dir: &Path) -> std::io::Result<()> {
    use std::io::Write;
    let stdout = std::io::stdout();
    let emit = |e: &Event| -> std::io::Result<()> {
        let mut line = serde_json::to_vec(e).map_err(std::io::Error::other)?;
        line.push(b'\n');
        let mut out = stdout.lock();
        out.write_all(&line)?;
        out.flush()
    };
    let task: Task = serde_json::from_slice(&std::fs::read(dir.join("task.json"))?)
        .map_err(std::io::Error::other)?;
    let bundle =
        Bundle::decode(&std::fs::read(dir.join("input.bundle"))?).map_err(std::io::Error::other)?;
    let limits = Limits {
        max_memory: task.max_memory,
    };
    let mut checkpoint = |at: &Progress| -> Result<(), Stop> {
        let _ = emit(&Event::Progress(at.clone()));
        Ok(())
    };
    let event = match engine::run(
        &bundle,
        &task.options,
        task.max_texture_size,
        &limits,
        &mut checkpoint,
    ) {
        Ok(produced) => {
            let mut names = Vec::with_capacity(produced.files.len());
            let mut written = Ok(());
            for (k, (name, bytes)) in produced.files.into_iter().enumerate() {
                written = std::fs::write(dir.join("out").join(k.to_string()), bytes);
                if written.is_err() {
                    break;
                }
                names.push(name);
            }
            match written {
                Ok(()) => Event::Done {
                    names,
                    report: produced.report,
                    timings: produced.timings,
                    warnings: produced.warnings,
                },
                Err(e) => Event::Failed {
                    kind: if super::store::is_full(&e) {
                        FailureKind::StorageFull
                    } else {
                        FailureKind::Failed
                    },
                    message: format!("cannot write the results: {e}"),
                },
            }
        }
        Err(e) => {
            let (kind, message) = match e {
                EngineError::BadInput(m) => (FailureKind::BadInput, m),
                EngineError::TooLarge(m) => (FailureKind::TooLarge, m),
                EngineError::StorageFull(m) => (FailureKind::StorageFull, m),
                EngineError::Failed(m) | EngineError::Crashed(m) => (FailureKind::Failed, m),
                EngineError::Stopped(_) => (FailureKind::Failed, "stopped".to_string()),
            };
            Event::Failed { kind, message }
        }
    };
    emit(&event)
}
