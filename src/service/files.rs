//! The embedded file store: blobs as files under one folder, each written
//! to a temporary name, synced, renamed into place, and its folder synced.

use std::fs::{self, File};
use std::io::{self, Write};
use std::path::{Path, PathBuf};

use super::store::{FileStore, StoreError};

pub struct LocalFileStore {
    root: PathBuf,
}

/// Temporary files end with this; whatever a crash leaves is swept at open.
const TMP_SUFFIX: &str = ".partial";

fn io_err(what: &str, path: &Path, e: io::Error) -> StoreError {
    let message = format!("{what} {}: {e}", path.display());
    if super::store::is_full(&e) {
        StoreError::Full(message)
    } else if e.raw_os_error() == Some(libc::EIO) {
        // The disk failed the read or write, not the request.
        StoreError::files_unavailable(message)
    } else {
        StoreError::Files(message)
    }
}

impl LocalFileStore {
    pub fn open(root: &Path) -> Result<Self, StoreError> {
        fs::create_dir_all(root).map_err(|e| io_err("cannot create", root, e))?;
        let store = LocalFileStore {
            root: root.to_path_buf(),
        };
        store.sweep(root)?;
        Ok(store)
    }

    fn sweep(&self, dir: &Path) -> Result<(), StoreError> {
        let entries = match fs::read_dir(dir) {
            Ok(e) => e,
            Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(()),
            Err(e) => return Err(io_err("cannot list", dir, e)),
        };
        for entry in entries {
            let entry = entry.map_err(|e| io_err("cannot list", dir, e))?;
            let path = entry.path();
            let ty = entry
                .file_type()
                .map_err(|e| io_err("cannot inspect", &path, e))?;
            if ty.is_dir() {
                self.sweep(&path)?;
            } else if path
                .file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.ends_with(TMP_SUFFIX))
            {
                let _ = fs::remove_file(&path);
            }
        }
        Ok(())
    }

    fn path(&self, key: &str) -> Result<PathBuf, StoreError> {
        let mut p = self.root.clone();
        for part in key.split('/') {
            if part.is_empty()
                || part == "."
                || part == ".."
                || part.contains(['\\', '\0'])
                || part.ends_with(TMP_SUFFIX)
            {
                return Err(StoreError::Files(format!("invalid key {key:?}")));
            }
            p.push(part);
        }
        Ok(p)
    }
}

fn sync_dir(dir: &Path) -> Result<(), StoreError> {
    File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(|e| io_err("cannot sync", dir, e))
}

impl FileStore for LocalFileStore {
    fn put(&self, key: &str, bytes: &[u8]) -> Result<(), StoreError> {
        let path = self.path(key)?;
        let dir = path.parent().unwrap_or(&self.root).to_path_buf();
        fs::create_dir_all(&dir).map_err(|e| io_err("cannot create", &dir, e))?;
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let suffix = super::job::random_id().map_err(|e| io_err("cannot name", &path, e))?;
        let tmp = dir.join(format!(".{name}.{}{TMP_SUFFIX}", &suffix[..8]));
        let written = File::create(&tmp).and_then(|mut f| {
            f.write_all(bytes)?;
            f.sync_all()
        });
        if let Err(e) = written {
            let _ = fs::remove_file(&tmp);
            return Err(io_err("cannot write", &tmp, e));
        }
        fs::rename(&tmp, &path).map_err(|e| {
            let _ = fs::remove_file(&tmp);
            io_err("cannot rename into", &path, e)
        })?;
        sync_dir(&dir)
    }

    fn get(&self, key: &str) -> Result<Option<Vec<u8>>, StoreError> {
        let path = self.path(key)?;
        match fs::read(&path) {
            Ok(b) => Ok(Some(b)),
            Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(io_err("cannot read", &path, e)),
        }
    }

    fn read_range(&self, key: &str, range: std::ops::Range<u64>) -> Result<Vec<u8>, StoreError> {
        use std::io::{Read, Seek, SeekFrom};
        let path = self.path(key)?;
        let mut file = File::open(&path).map_err(|e| io_err("cannot read", &path, e))?;
        file.seek(SeekFrom::Start(range.start))
            .map_err(|e| io_err("cannot read", &path, e))?;
        let mut bytes = Vec::new();
        file.take(range.end.saturating_sub(range.start))
            .read_to_end(&mut bytes)
            .map_err(|e| io_err("cannot read", &path, e))?;
        Ok(bytes)
    }

    fn copy(&self, from: &str, to: &str) -> Result<(), StoreError> {
        let src = self.path(from)?;
        let dst = self.path(to)?;
        let dir = dst.parent().unwrap_or(&self.root).to_path_buf();
        fs::create_dir_all(&dir).map_err(|e| io_err("cannot create", &dir, e))?;
        let _ = fs::remove_file(&dst);
        // Files are never modified in place, so a hard link is a copy.
        if fs::hard_link(&src, &dst).is_err() {
            let bytes = fs::read(&src).map_err(|e| io_err("cannot read", &src, e))?;
            return self.put(to, &bytes);
        }
        sync_dir(&dir)
    }

    fn delete_prefix(&self, prefix: &str) -> Result<(), StoreError> {
        let path = self.path(prefix)?;
        let result = match fs::symlink_metadata(&path) {
            Ok(m) if m.is_dir() => fs::remove_dir_all(&path),
            Ok(_) => fs::remove_file(&path),
            Err(e) => Err(e),
        };
        match result {
            Ok(()) => Ok(()),
            Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(()),
            Err(e) => Err(io_err("cannot delete", &path, e)),
        }
    }

    fn list(&self, prefix: &str) -> Result<Vec<String>, StoreError> {
        let path = self.path(prefix)?;
        let entries = match fs::read_dir(&path) {
            Ok(e) => e,
            Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(io_err("cannot list", &path, e)),
        };
        let mut names = Vec::new();
        for entry in entries {
            let entry = entry.map_err(|e| io_err("cannot list", &path, e))?;
            if let Some(name) = entry.file_name().to_str() {
                if !name.ends_with(TMP_SUFFIX) {
                    names.push(name.to_string());
                }
            }
        }
        names.sort();
        Ok(names)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn put_get_copy_delete() {
        let root = std::env::temp_dir().join(format!("seamstress-files-{}", std::process::id()));
        let _ = fs::remove_dir_all(&root);
        fs::create_dir_all(root.join("jobs/x")).unwrap();
        fs::write(root.join("jobs/x/.a.1234abcd.partial"), b"junk").unwrap();
        let s = LocalFileStore::open(&root).unwrap();
        assert!(!root.join("jobs/x/.a.1234abcd.partial").exists());
        s.put("jobs/x/out/a.dds", b"hello").unwrap();
        assert_eq!(s.get("jobs/x/out/a.dds").unwrap().unwrap(), b"hello");
        assert_eq!(s.read_range("jobs/x/out/a.dds", 1..3).unwrap(), b"el");
        assert_eq!(s.read_range("jobs/x/out/a.dds", 3..99).unwrap(), b"lo");
        s.copy("jobs/x/out/a.dds", "jobs/y/out/a.dds").unwrap();
        assert_eq!(s.list("jobs").unwrap(), vec!["x", "y"]);
        s.delete_prefix("jobs/x").unwrap();
        assert!(s.get("jobs/x/out/a.dds").unwrap().is_none());
        assert_eq!(s.get("jobs/y/out/a.dds").unwrap().unwrap(), b"hello");
        assert!(s.put("jobs/../../etc", b"").is_err());
        assert!(s.get("/abs").is_err());
        s.delete_prefix("jobs/none").unwrap();
        fs::remove_dir_all(&root).unwrap();
    }
}
