//! One owner per data folder, and a job store never mistaken for empty.
//!
//! Two servers on one `--data` would each take the other's running jobs
//! for interrupted ones and run them again; so the first holds an exclusive
//! `flock` on `data/lock` for its whole life (released by the kernel when
//! the process dies, however it dies) and a second refuses to start,
//! touching nothing. And a job store that is missing, empty or unreadable
//! while job folders exist beside it is a damaged store, not a new one:
//! starting on it would delete every job's files as belonging to no job.

use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, Write};
use std::os::unix::io::AsRawFd;
use std::path::{Path, PathBuf};

/// Why a data folder cannot be used. Each is one line, and the server exits
/// with status 2: the operator, not the program, must act.
#[derive(Debug, thiserror::Error)]
pub enum DataDirError {
    #[error("{dir}: in use by another seamstress server{pid}; stop it first, or give this one another --data")]
    Locked { dir: String, pid: String },
    #[error(
        "{store}: {what}, but {jobs} job folders exist beside it; refusing to start \
         (nothing was deleted). Restore the store, or start with --rebuild-store to drop those jobs"
    )]
    Damaged {
        store: String,
        what: &'static str,
        jobs: usize,
    },
    #[error("{path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
}

impl DataDirError {
    fn io(path: &Path, source: std::io::Error) -> Self {
        DataDirError::Io {
            path: path.display().to_string(),
            source,
        }
    }
}

/// The exclusive hold on a data folder; released when dropped or when the
/// process ends.
#[derive(Debug)]
pub struct DataLock {
    _file: File,
}

/// Takes the folder's lock, writing this process's id into it for the
/// message another server would print.
pub fn lock(dir: &Path) -> Result<DataLock, DataDirError> {
    let path = dir.join("lock");
    let mut file = OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(&path)
        .map_err(|e| DataDirError::io(&path, e))?;
    // SAFETY: flock on a descriptor this function owns.
    let held = unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } != 0;
    if held {
        let mut text = String::new();
        let _ = file.read_to_string(&mut text);
        let pid = match text.trim() {
            "" => String::new(),
            p => format!(" (pid {p})"),
        };
        return Err(DataDirError::Locked {
            dir: dir.display().to_string(),
            pid,
        });
    }
    let _ = file.set_len(0);
    let _ = file.rewind();
    let _ = writeln!(file, "{}", std::process::id());
    Ok(DataLock { _file: file })
}

/// Refuses a job store that is missing, empty or not a database while job
/// folders exist under `jobs_dir`, unless `rebuild` says to start afresh.
pub fn check_store(store: &Path, jobs_dir: &Path, rebuild: bool) -> Result<(), DataDirError> {
    let jobs = match std::fs::read_dir(jobs_dir) {
        Ok(entries) => entries.count(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => 0,
        Err(e) => return Err(DataDirError::io(jobs_dir, e)),
    };
    if jobs == 0 || rebuild {
        return Ok(());
    }
    let what = match std::fs::metadata(store) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Some("missing"),
        Err(e) => return Err(DataDirError::io(store, e)),
        Ok(m) if m.len() == 0 => Some("empty"),
        Ok(_) if !is_sqlite(store) => Some("not a SQLite database"),
        Ok(_) => None,
    };
    match what {
        None => Ok(()),
        Some(what) => Err(DataDirError::Damaged {
            store: store.display().to_string(),
            what,
            jobs,
        }),
    }
}

fn is_sqlite(path: &Path) -> bool {
    let mut head = [0u8; 16];
    File::open(path)
        .and_then(|mut f| f.read_exact(&mut head))
        .is_ok_and(|()| &head == b"SQLite format 3\0")
}

/// Bytes free for an unprivileged writer on the disk holding `dir`.
pub fn free_space(dir: &Path) -> Option<u64> {
    use std::os::unix::ffi::OsStrExt;
    let c = std::ffi::CString::new(dir.as_os_str().as_bytes()).ok()?;
    // SAFETY: statvfs fills the zeroed struct we own from a valid C string.
    let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
    if unsafe { libc::statvfs(c.as_ptr(), &mut st) } != 0 {
        return None;
    }
    Some((st.f_bavail as u64).saturating_mul(st.f_frsize as u64))
}

/// Where the job store lives in a data folder.
pub fn store_path(dir: &Path) -> PathBuf {
    dir.join("jobs.sqlite3")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn folder(name: &str) -> PathBuf {
        let d =
            std::env::temp_dir().join(format!("seamstress-datadir-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn free_space_is_known_for_a_folder_and_not_for_nothing() {
        assert!(free_space(&std::env::temp_dir()).is_some_and(|b| b > 0));
        assert!(free_space(Path::new("/no/such/folder")).is_none());
    }

    #[test]
    fn a_second_lock_is_refused_until_the_first_is_dropped() {
        let d = folder("lock");
        let first = lock(&d).unwrap();
        match lock(&d) {
            Err(DataDirError::Locked { pid, .. }) => {
                assert!(pid.contains(&std::process::id().to_string()))
            }
            other => panic!("{other:?}"),
        }
        drop(first);
        lock(&d).unwrap();
    }

    #[test]
    fn a_damaged_store_beside_jobs_is_refused() {
        let d = folder("store");
        let store = store_path(&d);
        let jobs = d.join("files/jobs");
        // No jobs: any store (or none) is fine.
        check_store(&store, &jobs, false).unwrap();
        std::fs::create_dir_all(jobs.join("abc")).unwrap();
        for (contents, what) in [
            (None, "missing"),
            (Some(&b""[..]), "empty"),
            (Some(&b"not a database at all"[..]), "not a SQLite database"),
        ] {
            if let Some(c) = contents {
                std::fs::write(&store, c).unwrap();
            }
            match check_store(&store, &jobs, false) {
                Err(e @ DataDirError::Damaged { .. }) => {
                    assert!(e.to_string().contains(what), "{e}");
                    assert!(e.to_string().contains("1 job folders"), "{e}");
                }
                other => panic!("{what}: {other:?}"),
            }
            check_store(&store, &jobs, true).unwrap();
        }
        assert!(jobs.join("abc").exists());
    }
}
