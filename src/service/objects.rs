//! The cluster's file store: any S3-compatible object store, through the
//! `object_store` crate.
//!
//! `s3://BUCKET/PREFIX` names the place; the endpoint, region and
//! credentials come from the usual `AWS_*` environment variables
//! (`AWS_ENDPOINT_URL`, `AWS_REGION`, `AWS_ACCESS_KEY_ID`,
//! `AWS_SECRET_ACCESS_KEY`, `AWS_ALLOW_HTTP=true` for a plain HTTP endpoint).
//! An object store writes an object whole or not at all, which is the
//! [`FileStore::put`] contract; copies are made server-side.

use std::sync::Arc;
use std::time::Duration;

use axum::body::Bytes;
use futures_util::TryStreamExt;
use object_store::aws::{AmazonS3, AmazonS3Builder, AmazonS3ConfigKey};
use object_store::buffered::BufWriter;
use object_store::path::Path;
use object_store::signer::Signer;
use object_store::{BackoffConfig, ClientConfigKey, ObjectStore, RetryConfig};
use tokio::io::AsyncWriteExt;
use tokio::runtime::Handle;

use super::store::{FileStore, StoreError};

/// Parts of a multipart upload. Blobs below this go up in one request;
/// S3 wants parts of at least 5 MiB.
const PART_BYTES: usize = 8 << 20;

/// Parts of one blob in flight at once.
const PARTS_IN_FLIGHT: usize = 4;

pub struct ObjectFileStore {
    s3: Arc<AmazonS3>,
    prefix: String,
    rt: Handle,
}

/// How long a connection to the object store may take to open.
const CONNECT_WITHIN: &str = "2s";

/// How long one request may take, its body included. Bounds a store that
/// accepts connections but does not answer (frozen, or cut off without a
/// reset); parts of a multipart upload are 8 MiB, which leaves a slow link
/// about 300 KB/s.
const REQUEST_WITHIN: &str = "30s";

/// Retries of a failed request inside one call: a few, quickly. A store
/// that is away for longer is an outage, which the callers wait out (see
/// `worker.rs`); the crate's default (ten retries over three minutes) held
/// every caller, API requests included, for minutes.
const RETRIES: usize = 3;
const RETRY_WITHIN: Duration = Duration::from_secs(10);

/// How long `/readyz`'s probe may take: it must say within a second.
const CHECK_WITHIN: Duration = Duration::from_millis(800);

fn obj_err(e: object_store::Error) -> StoreError {
    match e {
        // What the HTTP client reports itself: refused, reset, timed out,
        // or a 5xx after the retries. Everything the server answered in
        // words (not found, refused, precondition) has a variant of its own.
        object_store::Error::Generic { .. } | object_store::Error::JoinError { .. } => {
            StoreError::files_unavailable(e.to_string())
        }
        _ => StoreError::Files(e.to_string()),
    }
}

impl ObjectFileStore {
    /// Opens `s3://BUCKET/PREFIX`; calls then block on `rt` from threads
    /// outside it.
    pub fn open(url: &str, rt: Handle) -> Result<Self, StoreError> {
        let rest = url
            .strip_prefix("s3://")
            .ok_or_else(|| StoreError::Files(format!("{url}: expected s3://BUCKET/PREFIX")))?;
        let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
        if bucket.is_empty() {
            return Err(StoreError::Files(format!("{url}: no bucket")));
        }
        let mut builder = AmazonS3Builder::from_env().with_bucket_name(bucket);
        // The operator's `AWS_*` settings win over these defaults.
        for (key, value) in [
            (ClientConfigKey::ConnectTimeout, CONNECT_WITHIN),
            (ClientConfigKey::Timeout, REQUEST_WITHIN),
        ] {
            let key = AmazonS3ConfigKey::Client(key);
            if builder.get_config_value(&key).is_none() {
                builder = builder.with_config(key, value);
            }
        }
        let s3 = builder
            .with_retry(RetryConfig {
                backoff: BackoffConfig::default(),
                max_retries: RETRIES,
                retry_timeout: RETRY_WITHIN,
            })
            .build()
            .map_err(|e| StoreError::Files(format!("{url}: {e}")))?;
        Ok(ObjectFileStore {
            s3: Arc::new(s3),
            prefix: prefix.trim_matches('/').to_string(),
            rt,
        })
    }

    /// One PUT below a part's size, a multipart upload above it; an
    /// upload that fails is aborted, leaving nothing behind.
    async fn upload(&self, path: Path, bytes: Bytes) -> Result<(), StoreError> {
        let store: Arc<dyn ObjectStore> = self.s3.clone();
        let mut writer =
            BufWriter::with_capacity(store, path, PART_BYTES).with_max_concurrency(PARTS_IN_FLIGHT);
        let written = async {
            writer.put(bytes).await.map_err(obj_err)?;
            writer
                .shutdown()
                .await
                .map_err(|e| StoreError::Files(e.to_string()))
        }
        .await;
        if written.is_err() {
            let _ = writer.abort().await;
        }
        written
    }

    /// The object path of `key`, refusing keys that would leave the prefix.
    fn path(&self, key: &str) -> Result<Path, StoreError> {
        if key
            .split('/')
            .any(|p| p.is_empty() || p == "." || p == ".." || p.contains(['\\', '\0']))
        {
            return Err(StoreError::Files(format!("invalid key {key:?}")));
        }
        let full = if self.prefix.is_empty() {
            key.to_string()
        } else {
            format!("{}/{key}", self.prefix)
        };
        Path::parse(&full).map_err(|e| StoreError::Files(format!("invalid key {key:?}: {e}")))
    }
}

impl FileStore for ObjectFileStore {
    fn put(&self, key: &str, bytes: &[u8]) -> Result<(), StoreError> {
        let path = self.path(key)?;
        self.rt
            .block_on(self.upload(path, Bytes::copy_from_slice(bytes)))
    }

    fn put_all(&self, blobs: &[(String, &[u8])]) -> Result<(), StoreError> {
        let uploads = blobs
            .iter()
            .map(|(key, bytes)| Ok(self.upload(self.path(key)?, Bytes::copy_from_slice(bytes))))
            .collect::<Result<Vec<_>, StoreError>>()?;
        self.rt
            .block_on(futures_util::future::try_join_all(uploads))
            .map(drop)
    }

    fn remove(&self, key: &str) -> Result<(), StoreError> {
        let path = self.path(key)?;
        self.rt.block_on(async {
            match self.s3.delete(&path).await {
                Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
                Err(e) => Err(obj_err(e)),
            }
        })
    }

    fn get(&self, key: &str) -> Result<Option<Vec<u8>>, StoreError> {
        let path = self.path(key)?;
        self.rt.block_on(async {
            match self.s3.get(&path).await {
                Ok(r) => Ok(Some(r.bytes().await.map_err(obj_err)?.to_vec())),
                Err(object_store::Error::NotFound { .. }) => Ok(None),
                Err(e) => Err(obj_err(e)),
            }
        })
    }

    fn read_range(&self, key: &str, range: std::ops::Range<u64>) -> Result<Vec<u8>, StoreError> {
        let path = self.path(key)?;
        if range.is_empty() {
            return Ok(Vec::new());
        }
        self.rt.block_on(async {
            // No HEAD first: a range running past the end comes back short,
            // and only one starting past it is refused, which the size then
            // tells apart from a real failure.
            match self.s3.get_range(&path, range.clone()).await {
                Ok(bytes) => Ok(bytes.to_vec()),
                Err(e) => match self.s3.head(&path).await {
                    Ok(meta) if range.start >= meta.size => Ok(Vec::new()),
                    _ => Err(obj_err(e)),
                },
            }
        })
    }

    fn copy(&self, from: &str, to: &str) -> Result<(), StoreError> {
        let (from, to) = (self.path(from)?, self.path(to)?);
        self.rt
            .block_on(async { self.s3.copy(&from, &to).await.map_err(obj_err) })
    }

    fn delete_prefix(&self, prefix: &str) -> Result<(), StoreError> {
        let path = self.path(prefix)?;
        self.rt.block_on(async {
            // The blob itself, and everything under it as a folder.
            let mut paths: Vec<Path> = self
                .s3
                .list(Some(&path))
                .map_ok(|m| m.location)
                .try_collect()
                .await
                .map_err(obj_err)?;
            paths.push(path);
            for p in paths {
                match self.s3.delete(&p).await {
                    Ok(()) | Err(object_store::Error::NotFound { .. }) => {}
                    Err(e) => return Err(obj_err(e)),
                }
            }
            Ok(())
        })
    }

    fn list(&self, prefix: &str) -> Result<Vec<String>, StoreError> {
        let path = self.path(prefix)?;
        self.rt.block_on(async {
            let listing = self
                .s3
                .list_with_delimiter(Some(&path))
                .await
                .map_err(obj_err)?;
            let mut names: Vec<String> = listing
                .common_prefixes
                .iter()
                .chain(listing.objects.iter().map(|o| &o.location))
                .filter_map(|p| p.filename().map(str::to_string))
                .collect();
            names.sort();
            names.dedup();
            Ok(names)
        })
    }

    fn check(&self) -> Result<(), StoreError> {
        let path = self.path("jobs")?;
        self.rt.block_on(async {
            let listed =
                tokio::time::timeout(CHECK_WITHIN, self.s3.list_with_delimiter(Some(&path)));
            match listed.await {
                Ok(r) => r.map(drop).map_err(obj_err),
                Err(_) => Err(StoreError::files_unavailable(format!(
                    "no answer within {} ms",
                    CHECK_WITHIN.as_millis()
                ))),
            }
        })
    }

    fn presign(&self, key: &str, ttl: Duration) -> Result<Option<String>, StoreError> {
        let path = self.path(key)?;
        self.rt.block_on(async {
            let url = self
                .s3
                .signed_url(axum::http::Method::GET, &path, ttl)
                .await
                .map_err(obj_err)?;
            Ok(Some(url.to_string()))
        })
    }
}
