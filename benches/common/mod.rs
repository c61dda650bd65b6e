//! What more than one bench needs.

// Each bench includes this module and reads what it needs of it.
#![allow(dead_code)]

use std::process::{Command, Stdio};
use std::time::Instant;

/// One finished run of a command: wall and CPU seconds, peak MiB.
pub struct Run {
    pub wall: f64,
    pub cpu: f64,
    pub peak_mb: f64,
}

/// Runs `cmd` to its end and reads its own rusage (wait4).
pub fn measure(mut cmd: Command) -> Result<Run, String> {
    let t = Instant::now();
    let child = cmd
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| e.to_string())?;
    let mut status = 0;
    // SAFETY: rusage is plain data the kernel fills in.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: the pid is our own child's, not yet waited for.
    let pid = unsafe { libc::wait4(child.id() as i32, &mut status, 0, &mut usage) };
    let wall = t.elapsed().as_secs_f64();
    if pid < 0 || !libc::WIFEXITED(status) || libc::WEXITSTATUS(status) != 0 {
        let mut err = String::new();
        if let Some(mut e) = child.stderr {
            let _ = std::io::Read::read_to_string(&mut e, &mut err);
        }
        return Err(format!("status {status}: {}", err.trim()));
    }
    let secs = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    Ok(Run {
        wall,
        cpu: secs(usage.ru_utime) + secs(usage.ru_stime),
        peak_mb: usage.ru_maxrss as f64 / 1024.0,
    })
}
