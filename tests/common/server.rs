//! `seamstress serve` as a child process on a free loopback port. (The
//! service tests and the service bench each use part of it.)
#![allow(dead_code)]

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

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
        let mut child = Command::new(env!("CARGO_BIN_EXE_seamstress"))
            .args(["serve", "--listen", "127.0.0.1:0", "--data"])
            .arg(data)
            .args(&args)
            .env_remove("SEAMSTRESS_TOKENS")
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("the server starts");
        let mut line = String::new();
        BufReader::new(child.stdout.take().expect("a piped stdout"))
            .read_line(&mut line)
            .expect("the server prints its address");
        let addr = line
            .trim()
            .strip_prefix("listening on ")
            .unwrap_or_else(|| panic!("unexpected first line {line:?}"))
            .to_string();
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
