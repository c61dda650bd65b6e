//! Configuration: flags, `SEAMSTRESS_*` environment variables and an
//! optional TOML file, in that order of precedence, over built-in defaults.

use std::net::{SocketAddr, ToSocketAddrs};
use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::Deserialize;
use sha2::{Digest, Sha256};

/// `seamstress serve`: every option is also an environment variable and a
/// key of the `--config` file (same name, `_` for `-`).
#[derive(clap::Args, Clone, Debug, Default)]
pub struct ServeArgs {
    /// Address to listen on; port 0 picks a free one [default: 127.0.0.1:8080].
    #[arg(long, env = "SEAMSTRESS_LISTEN")]
    pub listen: Option<String>,
    /// Folder for the job database and the files [default: ./data]; with
    /// --store and --files elsewhere, only the jobs' scratch space.
    #[arg(long, env = "SEAMSTRESS_DATA")]
    pub data: Option<PathBuf>,
    /// The job store shared by a cluster's processes:
    /// postgres://USER@HOST:PORT/DB [default: SQLite in the data folder].
    #[arg(long, env = "SEAMSTRESS_STORE", hide_env_values = true)]
    pub store: Option<String>,
    /// Where job files live: s3://BUCKET/PREFIX (endpoint and credentials
    /// from the AWS_* environment variables) or a folder [default: the data
    /// folder's files/].
    #[arg(long, env = "SEAMSTRESS_FILES")]
    pub files: Option<String>,
    /// How long a worker's claim on a job holds without renewal; a job
    /// whose worker died goes back to the queue after it [default: 30s].
    #[arg(long, env = "SEAMSTRESS_LEASE")]
    pub lease: Option<String>,
    /// TOML file with any of these options.
    #[arg(long, env = "SEAMSTRESS_CONFIG")]
    pub config: Option<PathBuf>,
    /// Jobs processed at once; 0 for an API server that runs none
    /// [default: the number of cores].
    #[arg(long, env = "SEAMSTRESS_WORKERS")]
    pub workers: Option<usize>,
    /// Most jobs waiting for a worker; beyond it, submissions get 503 [default: 64].
    #[arg(long, env = "SEAMSTRESS_QUEUE_SIZE")]
    pub queue_size: Option<usize>,
    /// Time limit of one job, e.g. 600s, 10m [default: 10m].
    #[arg(long, env = "SEAMSTRESS_JOB_TIMEOUT")]
    pub job_timeout: Option<String>,
    /// How long finished jobs and their files are kept, e.g. 7d [default: 7d].
    #[arg(long, env = "SEAMSTRESS_RETENTION")]
    pub retention: Option<String>,
    /// On SIGTERM, how long running jobs may take to finish before they are
    /// re-queued [default: 30s].
    #[arg(long, env = "SEAMSTRESS_GRACE")]
    pub grace: Option<String>,
    /// A client must send a request's whole header within this time of
    /// connecting (of the request's first byte, on a kept-alive
    /// connection), or the connection is closed [default: 10s].
    #[arg(long, env = "SEAMSTRESS_HEADER_TIMEOUT")]
    pub header_timeout: Option<String>,
    /// A kept-alive connection that starts no new request within this time
    /// of its last response is closed [default: 75s].
    #[arg(long, env = "SEAMSTRESS_IDLE_TIMEOUT")]
    pub idle_timeout: Option<String>,
    /// Most connections open at once; past it, the connection that has
    /// waited longest for a request is closed to make room, or, when every
    /// connection is busy with a request, the new one is answered 503
    /// [default: half of what the file descriptor limit (ulimit -n) leaves
    /// after 64 + 8 per worker, between 8 and 4096].
    #[arg(long, env = "SEAMSTRESS_MAX_CONNECTIONS")]
    pub max_connections: Option<usize>,
    /// Largest request body, e.g. 512MiB [default: 512MiB].
    #[arg(long, env = "SEAMSTRESS_MAX_BODY")]
    pub max_body: Option<String>,
    /// Largest texture width or height, checked before decoding [default: 16384].
    #[arg(long, env = "SEAMSTRESS_MAX_TEXTURE_SIZE")]
    pub max_texture_size: Option<u32>,
    /// Peak memory one job may use, e.g. 2GiB; uploads estimated above it
    /// are refused with 422 too_large [default: the memory available at
    /// start (MemAvailable, or less under a cgroup limit or `ulimit -v`)
    /// divided among the workers].
    #[arg(long, env = "SEAMSTRESS_MAX_MEMORY")]
    pub max_memory: Option<String>,
    /// Longest `Prefer: wait=N` honoured [default: 10m].
    #[arg(long, env = "SEAMSTRESS_MAX_WAIT")]
    pub max_wait: Option<String>,
    /// Bearer token as NAME:SECRET or SECRET; repeat for more (environment:
    /// comma-separated). Each token sees only its own jobs.
    #[arg(long = "token", env = "SEAMSTRESS_TOKENS", value_delimiter = ',')]
    pub tokens: Vec<String>,
    /// Allow listening beyond loopback without tokens.
    #[arg(long, env = "SEAMSTRESS_INSECURE_OPEN")]
    pub insecure_open: bool,
    /// Address space each job's process may map, e.g. 8GiB; a job that
    /// needs more fails with too_large [default: twice --max-memory, at
    /// least 2GiB more than it].
    #[arg(long, env = "SEAMSTRESS_JOB_ADDRESS_SPACE")]
    pub job_address_space: Option<String>,
    /// Free space on the data folder's disk below which /readyz answers 503
    /// and uploads get 507, e.g. 256MiB [default: 256MiB].
    #[arg(long, env = "SEAMSTRESS_MIN_FREE")]
    pub min_free: Option<String>,
    /// Start even though the job store is missing, empty or unreadable
    /// while job folders exist beside it: those jobs and their files are
    /// dropped. Without it such a server refuses to start.
    #[arg(long)]
    pub rebuild_store: bool,
    /// A host (HOST or HOST:PORT) that job callbacks may be sent to; repeat
    /// for more (environment: comma-separated). Without any, callbacks are
    /// refused, so that a job cannot make the server call into a private
    /// network.
    #[arg(
        long = "callback-allow",
        env = "SEAMSTRESS_CALLBACK_ALLOW",
        value_delimiter = ','
    )]
    pub callback_allow: Vec<String>,
    /// The secret that signs callbacks of a server without tokens (with
    /// tokens, each token's own secret signs its jobs' callbacks).
    #[arg(long, env = "SEAMSTRESS_CALLBACK_SECRET", hide_env_values = true)]
    pub callback_secret: Option<String>,
    /// The callback of a token's jobs that name none, as NAME=URL (or URL
    /// alone on a server without tokens); repeat for more (environment:
    /// comma-separated).
    #[arg(
        long = "callback-default",
        env = "SEAMSTRESS_CALLBACK_DEFAULTS",
        value_delimiter = ','
    )]
    pub callback_defaults: Vec<String>,
}

/// The configuration file: the same options as [`ServeArgs`].
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "snake_case")]
struct FileConfig {
    listen: Option<String>,
    data: Option<PathBuf>,
    store: Option<String>,
    files: Option<String>,
    lease: Option<Quantity>,
    workers: Option<usize>,
    queue_size: Option<usize>,
    job_timeout: Option<Quantity>,
    retention: Option<Quantity>,
    grace: Option<Quantity>,
    header_timeout: Option<Quantity>,
    idle_timeout: Option<Quantity>,
    max_connections: Option<usize>,
    max_body: Option<Quantity>,
    max_texture_size: Option<u32>,
    max_memory: Option<Quantity>,
    job_address_space: Option<Quantity>,
    min_free: Option<Quantity>,
    max_wait: Option<Quantity>,
    tokens: Option<Vec<String>>,
    insecure_open: Option<bool>,
    callback_allow: Option<Vec<String>>,
    callback_secret: Option<String>,
    callback_defaults: Option<Vec<String>>,
}

/// A duration or size written as a bare number or with a unit.
#[derive(Debug, Deserialize)]
#[serde(untagged)]
enum Quantity {
    Number(u64),
    Text(String),
}

impl Quantity {
    fn text(&self) -> String {
        match self {
            Quantity::Number(n) => n.to_string(),
            Quantity::Text(s) => s.clone(),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read {path}: {source}")]
    Read {
        path: String,
        source: std::io::Error,
    },
    #[error("{path}: {message}")]
    File { path: String, message: String },
    #[error("{option}: {message}")]
    Invalid {
        option: &'static str,
        message: String,
    },
}

/// Where job files live.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum FilesAt {
    /// An S3-compatible bucket: `s3://BUCKET/PREFIX`.
    Bucket(String),
    Folder(PathBuf),
}

impl FilesAt {
    fn parse(text: &str) -> FilesAt {
        if text.starts_with("s3://") {
            FilesAt::Bucket(text.to_string())
        } else {
            FilesAt::Folder(PathBuf::from(text.strip_prefix("file://").unwrap_or(text)))
        }
    }
}

/// A bearer token: the secret is kept only as its digest.
#[derive(Clone, Debug)]
pub struct Token {
    /// Who owns the jobs submitted with it.
    pub owner: String,
    pub digest: [u8; 32],
}

/// Every setting resolved.
#[derive(Clone, Debug)]
pub struct Config {
    pub listen: String,
    pub data: PathBuf,
    /// The shared job store's URL; `None` for the embedded one.
    pub store: Option<String>,
    /// Where job files live; `None` for the data folder's `files/`.
    pub files: Option<FilesAt>,
    pub lease: Duration,
    pub workers: usize,
    pub queue_size: usize,
    pub job_timeout: Duration,
    pub retention: Duration,
    pub grace: Duration,
    /// How long a request's header may take to arrive.
    pub header_timeout: Duration,
    /// How long a kept-alive connection may wait for its next request.
    pub idle_timeout: Duration,
    /// Most connections open at once.
    pub max_connections: usize,
    pub max_body: usize,
    pub max_texture_size: u32,
    /// Peak memory one job may use, bytes (the budget's limit).
    pub max_memory: u64,
    /// Address space of one job's process, bytes.
    pub job_address_space: u64,
    /// Free bytes the data folder's disk must keep (readiness, uploads).
    pub min_free: u64,
    pub max_wait: Duration,
    pub tokens: Vec<Token>,
    pub insecure_open: bool,
    /// Start afresh over a damaged job store (`--rebuild-store`).
    pub rebuild_store: bool,
    /// Hosts (`HOST` or `HOST:PORT`, lower case) callbacks may reach.
    pub callback_allow: Vec<String>,
    /// SHA-256 of the secret signing an open server's callbacks.
    pub callback_key: Option<[u8; 32]>,
    /// Each owner's callback for jobs that name none (owner `""` on a
    /// server without tokens).
    pub callback_defaults: std::collections::BTreeMap<String, String>,
}

impl Default for Config {
    fn default() -> Self {
        let workers = std::thread::available_parallelism().map_or(1, |n| n.get());
        Config {
            listen: "127.0.0.1:8080".into(),
            data: PathBuf::from("data"),
            store: None,
            files: None,
            lease: Duration::from_secs(30),
            workers,
            queue_size: 64,
            job_timeout: Duration::from_secs(600),
            retention: Duration::from_secs(7 * 24 * 3600),
            grace: Duration::from_secs(30),
            header_timeout: Duration::from_secs(10),
            // Longer than the 60 s that load balancers commonly keep an
            // idle connection, so that they, not the server, close it.
            idle_timeout: Duration::from_secs(75),
            max_connections: super::listen::default_max_connections(workers),
            max_body: 512 << 20,
            max_texture_size: 16384,
            max_memory: crate::budget::memory_per_job(workers),
            job_address_space: address_space_for(crate::budget::memory_per_job(workers)),
            min_free: 256 << 20,
            max_wait: Duration::from_secs(600),
            tokens: Vec::new(),
            insecure_open: false,
            rebuild_store: false,
            callback_allow: Vec::new(),
            callback_key: None,
            callback_defaults: Default::default(),
        }
    }
}

impl Config {
    /// Merges flags and environment (already in `args`, flags first) over
    /// the file named by `--config`, over the defaults.
    pub fn resolve(args: &ServeArgs) -> Result<Config, ConfigError> {
        let file = match &args.config {
            Some(path) => read_file(path)?,
            None => FileConfig::default(),
        };
        let d = Config::default();
        let duration =
            |option: &'static str, flag: &Option<String>, file: &Option<Quantity>| match flag
                .clone()
                .or_else(|| file.as_ref().map(Quantity::text))
            {
                Some(text) => parse_duration(&text)
                    .map(Some)
                    .map_err(|message| ConfigError::Invalid { option, message }),
                None => Ok(None),
            };
        let size = |option: &'static str, flag: &Option<String>, file: &Option<Quantity>| match flag
            .clone()
            .or_else(|| file.as_ref().map(Quantity::text))
        {
            Some(text) => crate::budget::parse_bytes(&text)
                .map(Some)
                .map_err(|message| ConfigError::Invalid { option, message }),
            None => Ok(None),
        };
        let max_body = match size("max_body", &args.max_body, &file.max_body)? {
            Some(n) => usize::try_from(n).map_err(|_| ConfigError::Invalid {
                option: "max_body",
                message: format!("{n} bytes is too large"),
            })?,
            None => d.max_body,
        };
        let max_memory = size("max_memory", &args.max_memory, &file.max_memory)?;
        let job_address_space = size(
            "job_address_space",
            &args.job_address_space,
            &file.job_address_space,
        )?;
        let min_free = size("min_free", &args.min_free, &file.min_free)?.unwrap_or(d.min_free);
        let token_specs = if args.tokens.is_empty() {
            file.tokens.clone().unwrap_or_default()
        } else {
            args.tokens.clone()
        };
        let workers = args.workers.or(file.workers).unwrap_or(d.workers);
        let cfg = Config {
            listen: args.listen.clone().or(file.listen).unwrap_or(d.listen),
            data: args.data.clone().or(file.data).unwrap_or(d.data),
            store: args.store.clone().or(file.store),
            files: args
                .files
                .clone()
                .or(file.files)
                .map(|f| FilesAt::parse(&f)),
            lease: duration("lease", &args.lease, &file.lease)?.unwrap_or(d.lease),
            workers,
            // Every worker may run a job at its peak at once.
            max_memory: max_memory.unwrap_or_else(|| crate::budget::memory_per_job(workers)),
            job_address_space: 0,
            queue_size: args.queue_size.or(file.queue_size).unwrap_or(d.queue_size),
            job_timeout: duration("job_timeout", &args.job_timeout, &file.job_timeout)?
                .unwrap_or(d.job_timeout),
            retention: duration("retention", &args.retention, &file.retention)?
                .unwrap_or(d.retention),
            grace: duration("grace", &args.grace, &file.grace)?.unwrap_or(d.grace),
            header_timeout: duration("header_timeout", &args.header_timeout, &file.header_timeout)?
                .unwrap_or(d.header_timeout),
            idle_timeout: duration("idle_timeout", &args.idle_timeout, &file.idle_timeout)?
                .unwrap_or(d.idle_timeout),
            // The reserve grows with the workers this server runs.
            max_connections: args
                .max_connections
                .or(file.max_connections)
                .unwrap_or_else(|| super::listen::default_max_connections(workers)),
            max_body,
            min_free,
            max_texture_size: args
                .max_texture_size
                .or(file.max_texture_size)
                .unwrap_or(d.max_texture_size),
            max_wait: duration("max_wait", &args.max_wait, &file.max_wait)?.unwrap_or(d.max_wait),
            tokens: parse_tokens(&token_specs)?,
            insecure_open: args.insecure_open || file.insecure_open.unwrap_or(false),
            rebuild_store: args.rebuild_store,
            callback_allow: if args.callback_allow.is_empty() {
                file.callback_allow.clone().unwrap_or_default()
            } else {
                args.callback_allow.clone()
            }
            .iter()
            .map(|h| h.trim().to_ascii_lowercase())
            .filter(|h| !h.is_empty())
            .collect(),
            callback_key: args
                .callback_secret
                .clone()
                .or(file.callback_secret.clone())
                .map(|s| Sha256::digest(s.as_bytes()).into()),
            callback_defaults: Default::default(),
        };
        let default_specs = if args.callback_defaults.is_empty() {
            file.callback_defaults.clone().unwrap_or_default()
        } else {
            args.callback_defaults.clone()
        };
        let mut cfg = cfg;
        cfg.callback_defaults = parse_callback_defaults(&cfg, &default_specs)?;
        cfg.job_address_space =
            job_address_space.unwrap_or_else(|| address_space_for(cfg.max_memory));
        cfg.check()?;
        Ok(cfg)
    }

    fn check(&self) -> Result<(), ConfigError> {
        let invalid = |option, message: &str| ConfigError::Invalid {
            option,
            message: message.to_string(),
        };
        if let Some(url) = &self.store {
            if !(url.starts_with("postgres://") || url.starts_with("postgresql://")) {
                return Err(invalid("store", "expected postgres://USER@HOST:PORT/DB"));
            }
        }
        if self.lease < Duration::from_secs(1) {
            return Err(invalid("lease", "must be at least 1s"));
        }
        if self.queue_size == 0 {
            return Err(invalid("queue_size", "must be at least 1"));
        }
        if self.max_texture_size == 0 {
            return Err(invalid("max_texture_size", "must be at least 1"));
        }
        if self.job_timeout.is_zero() {
            return Err(invalid("job_timeout", "must be positive"));
        }
        if self.header_timeout.is_zero() {
            return Err(invalid("header_timeout", "must be positive"));
        }
        if self.idle_timeout.is_zero() {
            return Err(invalid("idle_timeout", "must be positive"));
        }
        if self.max_connections == 0 {
            return Err(invalid("max_connections", "must be at least 1"));
        }
        Ok(())
    }

    /// The addresses `listen` names, refusing to expose a server without
    /// tokens beyond loopback unless `insecure_open` says so.
    pub fn listen_addrs(&self) -> Result<Vec<SocketAddr>, ConfigError> {
        let addrs = self.listen_addrs_unchecked()?;
        if self.tokens.is_empty() && !self.insecure_open {
            if let Some(open) = addrs.iter().find(|a| !a.ip().is_loopback()) {
                return Err(ConfigError::Invalid {
                    option: "listen",
                    message: format!(
                        "{open} is not a loopback address: configure tokens, or pass \
                         --insecure-open to serve anyone who can reach it"
                    ),
                });
            }
        }
        Ok(addrs)
    }

    /// The addresses `listen` names.
    pub fn listen_addrs_unchecked(&self) -> Result<Vec<SocketAddr>, ConfigError> {
        let addrs: Vec<SocketAddr> = self
            .listen
            .to_socket_addrs()
            .map_err(|e| ConfigError::Invalid {
                option: "listen",
                message: format!("{:?}: {e}", self.listen),
            })?
            .collect();
        if addrs.is_empty() {
            return Err(ConfigError::Invalid {
                option: "listen",
                message: format!("{:?} names no address", self.listen),
            });
        }
        Ok(addrs)
    }
}

fn read_file(path: &Path) -> Result<FileConfig, ConfigError> {
    let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
        path: path.display().to_string(),
        source,
    })?;
    toml::from_str(&text).map_err(|e| ConfigError::File {
        path: path.display().to_string(),
        message: e.message().to_string(),
    })
}

/// `NAME=URL` (or a bare URL for a server without tokens), each URL on
/// the allow-list and each name a token's.
fn parse_callback_defaults(
    cfg: &Config,
    specs: &[String],
) -> Result<std::collections::BTreeMap<String, String>, ConfigError> {
    let invalid = |message: String| ConfigError::Invalid {
        option: "callback_defaults",
        message,
    };
    let mut out = std::collections::BTreeMap::new();
    for spec in specs.iter().map(|s| s.trim()).filter(|s| !s.is_empty()) {
        let (owner, url) = if spec.starts_with("http://") || spec.starts_with("https://") {
            ("", spec)
        } else {
            spec.split_once('=')
                .ok_or_else(|| invalid(format!("{spec:?} is not NAME=URL")))?
        };
        let known = if cfg.tokens.is_empty() {
            owner.is_empty()
        } else {
            cfg.tokens.iter().any(|t| t.owner == owner)
        };
        if !known {
            return Err(invalid(format!("{owner:?} is not a token's name")));
        }
        let url = super::callback::check_url(cfg, url).map_err(invalid)?;
        out.insert(owner.to_string(), url);
    }
    Ok(out)
}

fn parse_tokens(specs: &[String]) -> Result<Vec<Token>, ConfigError> {
    let mut tokens: Vec<Token> = Vec::new();
    for spec in specs.iter().map(|s| s.trim()).filter(|s| !s.is_empty()) {
        let (owner, secret) = match spec.split_once(':') {
            Some((name, secret)) if !name.is_empty() => (name.to_string(), secret),
            _ => {
                let digest = Sha256::digest(spec.as_bytes());
                (format!("token-{}", &hex(&digest)[..12]), spec)
            }
        };
        if secret.is_empty() {
            return Err(ConfigError::Invalid {
                option: "tokens",
                message: format!("token {owner:?} has an empty secret"),
            });
        }
        if !secret.bytes().all(|b| b.is_ascii_graphic()) {
            return Err(ConfigError::Invalid {
                option: "tokens",
                message: format!("token {owner:?}: secrets are printable ASCII without spaces"),
            });
        }
        let digest: [u8; 32] = Sha256::digest(secret.as_bytes()).into();
        if tokens
            .iter()
            .any(|t| t.digest == digest || t.owner == owner)
        {
            return Err(ConfigError::Invalid {
                option: "tokens",
                message: format!("token {owner:?} is given twice"),
            });
        }
        tokens.push(Token { owner, digest });
    }
    Ok(tokens)
}

pub(crate) fn hex(bytes: &[u8]) -> String {
    use std::fmt::Write;
    bytes.iter().fold(String::new(), |mut s, b| {
        let _ = write!(s, "{b:02x}");
        s
    })
}

/// `90`, `90s`, `15m`, `2h`, `7d`; a bare number is seconds.
pub fn parse_duration(text: &str) -> Result<Duration, String> {
    let t = text.trim();
    let split = t.find(|c: char| !c.is_ascii_digit()).unwrap_or(t.len());
    let (num, unit) = t.split_at(split);
    let n: u64 = num
        .parse()
        .map_err(|_| format!("{text:?} is not a duration like 30s, 10m, 2h or 7d"))?;
    let scale = match unit.trim() {
        "" | "s" => 1,
        "m" => 60,
        "h" => 3600,
        "d" => 86400,
        _ => return Err(format!("{text:?}: unknown unit (s, m, h or d)")),
    };
    n.checked_mul(scale)
        .map(Duration::from_secs)
        .ok_or_else(|| format!("{text:?} is too long"))
}

/// The address space a job process gets by default: its memory budget
/// twice over, and at least 2 GiB more (code, thread stacks and allocator
/// reservations are mapped but mostly never touched).
fn address_space_for(max_memory: u64) -> u64 {
    max_memory
        .saturating_mul(2)
        .max(max_memory.saturating_add(2 << 30))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::budget::parse_bytes;

    #[test]
    fn durations_and_sizes() {
        assert_eq!(parse_duration("90").unwrap(), Duration::from_secs(90));
        assert_eq!(parse_duration("15m").unwrap(), Duration::from_secs(900));
        assert_eq!(parse_duration("7d").unwrap(), Duration::from_secs(604800));
        assert!(parse_duration("7w").is_err());
        assert!(parse_duration("m").is_err());
        assert_eq!(parse_bytes("512MiB").unwrap(), 512 << 20);
        assert_eq!(parse_bytes("10").unwrap(), 10);
        assert!(parse_bytes("1XB").is_err());
    }

    #[test]
    fn flags_win_over_the_file() {
        let dir = std::env::temp_dir().join(format!("seamstress-config-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("seamstress.toml");
        std::fs::write(
            &path,
            "workers = 3\nqueue_size = 5\nretention = \"2h\"\nmax_body = 1024\ntokens = [\"ci:abc\"]\n",
        )
        .unwrap();
        let args = ServeArgs {
            config: Some(path),
            workers: Some(1),
            ..ServeArgs::default()
        };
        let cfg = Config::resolve(&args).unwrap();
        assert_eq!(cfg.workers, 1);
        assert_eq!(cfg.queue_size, 5);
        assert_eq!(cfg.retention, Duration::from_secs(7200));
        assert_eq!(cfg.max_body, 1024);
        assert_eq!(cfg.tokens[0].owner, "ci");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn connection_limits_from_the_file_and_flags() {
        let dir = std::env::temp_dir().join(format!("seamstress-conn-cfg-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("seamstress.toml");
        std::fs::write(
            &path,
            "header_timeout = \"5s\"\nidle_timeout = 30\nmax_connections = 100\n",
        )
        .unwrap();
        let args = ServeArgs {
            config: Some(path),
            max_connections: Some(7),
            ..ServeArgs::default()
        };
        let cfg = Config::resolve(&args).unwrap();
        assert_eq!(cfg.header_timeout, Duration::from_secs(5));
        assert_eq!(cfg.idle_timeout, Duration::from_secs(30));
        assert_eq!(cfg.max_connections, 7);
        let zero = ServeArgs {
            header_timeout: Some("0s".into()),
            ..ServeArgs::default()
        };
        assert!(Config::resolve(&zero).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn open_listening_needs_tokens_or_consent() {
        let mut cfg = Config {
            listen: "0.0.0.0:0".into(),
            ..Config::default()
        };
        assert!(cfg.listen_addrs().is_err());
        cfg.insecure_open = true;
        assert!(cfg.listen_addrs().is_ok());
        cfg.insecure_open = false;
        cfg.tokens = parse_tokens(&["a:secret".into()]).unwrap();
        assert!(cfg.listen_addrs().is_ok());
        cfg.listen = "127.0.0.1:0".into();
        cfg.tokens.clear();
        assert!(cfg.listen_addrs().is_ok());
    }
}
