//! `seamstress serve` as a child process on a free loopback port. (The
//! service tests and the service bench each use part of it.)
//!
//! In the test binary `service_cluster` (the service suite again), every
//! server runs on the cluster's stores instead of the embedded ones: one
//! PostgreSQL database and one S3 prefix per data folder, on servers the
//! binary starts once (`common::cluster`).
#![allow(dead_code)]

use std::collections::HashSet;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Mutex, OnceLock};

use super::cluster::{Postgres, Seaweed};

/// Whether this test binary runs its servers on PostgreSQL and S3.
pub fn on_cluster() -> bool {
    env!("CARGO_CRATE_NAME") == "service_cluster"
}

/// The cluster's servers, started by the first server of the binary.
struct Shared {
    pg: Postgres,
    s3: Seaweed,
    databases: Mutex<HashSet<String>>,
}

fn shared() -> &'static Shared {
    static SHARED: OnceLock<Shared> = OnceLock::new();
    SHARED.get_or_init(|| match (Postgres::start(), Seaweed::start()) {
        (Some(pg), Some(s3)) => Shared {
            pg,
            s3,
            databases: Mutex::new(HashSet::new()),
        },
        _ => {
            // The servers are missing and not required (`start` said so):
            // the suite has already run on the embedded stores.
            eprintln!("skipped: the service suite on PostgreSQL and S3");
            std::process::exit(0);
        }
    })
}

/// The options and environment that put a server with data folder `data`
/// on the cluster's stores: its own database and prefix, named after the
/// folder so that a restart finds its jobs again. Leases are short so that
/// a killed server's jobs come back quickly.
pub fn cluster_stores(data: &Path) -> (Vec<String>, Vec<(&'static str, String)>) {
    let shared = shared();
    let digest = super::crc32(data.to_string_lossy().as_bytes());
    let name = format!("t{digest:08x}");
    let url = {
        let mut made = shared.databases.lock().unwrap();
        if made.insert(name.clone()) {
            shared.pg.new_database(&name)
        } else {
            format!(
                "postgres://{}@127.0.0.1:{}/{name}",
                super::cluster::PG_USER,
                shared.pg.port
            )
        }
    };
    let args = vec![
        "--store".to_string(),
        url,
        "--files".to_string(),
        shared.s3.url(&name),
        "--lease".to_string(),
        "3s".to_string(),
    ];
    (args, shared.s3.env())
}

/// The address a `serve` or `worker` child prints on its first line
/// (`listening on ADDR`); its standard output must be piped.
pub fn address_of(child: &mut Child) -> String {
    let mut line = String::new();
    BufReader::new(child.stdout.take().expect("a piped stdout"))
        .read_line(&mut line)
        .expect("the server prints its address");
    line.trim()
        .strip_prefix("listening on ")
        .unwrap_or_else(|| panic!("unexpected first line {line:?}"))
        .to_string()
}

pub struct Server {
    pub child: Child,
    /// `http://ADDR`, as the server printed it.
    pub base: String,
    data: PathBuf,
    args: Vec<String>,
}

impl Server {
    /// Starts the binary under test on `127.0.0.1:0` with its data in
    /// `data`, open to loopback without tokens, and waits for its address.
    pub fn start(data: &Path, args: &[&str]) -> Server {
        let args: Vec<String> = args.iter().map(|s| s.to_string()).collect();
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_seamstress"));
        cmd.args(["serve", "--listen", "127.0.0.1:0", "--data"])
            .arg(data)
            .args(&args);
        if on_cluster() {
            let (stores, env) = cluster_stores(data);
            cmd.args(stores).envs(env);
        }
        let mut child = cmd
            .env_remove("SEAMSTRESS_TOKENS")
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("the server starts");
        let addr = address_of(&mut child);
        Server {
            child,
            base: format!("http://{addr}"),
            data: data.to_path_buf(),
            args,
        }
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// Starts a new server on the same data folder with the same options.
    pub fn restart(&mut self) {
        self.kill();
        let args: Vec<&str> = self.args.iter().map(String::as_str).collect();
        *self = Server::start(&self.data, &args);
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        self.kill();
    }
}
