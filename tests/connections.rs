//! What a client can hold of `seamstress serve`: connections that send half
//! a request, kept-alive connections that go quiet, and more connections
//! than the server takes. The real binary, over raw TCP.

use std::io::{self, Read, Write};
use std::net::TcpStream;
use std::os::unix::process::CommandExt;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

mod common;

/// The server's file descriptor limit in these tests.
const NOFILE: u64 = 256;

struct Server {
    child: Child,
    addr: String,
    log: PathBuf,
    data: PathBuf,
}

impl Server {
    /// `serve` on a free loopback port under a limit of `NOFILE` file
    /// descriptors, its log in a file.
    fn start(name: &str, args: &[&str]) -> Server {
        let data =
            std::env::temp_dir().join(format!("seamstress-conn-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&data);
        std::fs::create_dir_all(&data).unwrap();
        let log = data.join("stderr.log");
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_seamstress"));
        cmd.args([
            "serve",
            "--listen",
            "127.0.0.1:0",
            "--workers",
            "1",
            "--data",
        ])
        .arg(data.join("data"))
        .args(args)
        .env_remove("SEAMSTRESS_TOKENS")
        .env("SEAMSTRESS_LOG", "info")
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(&log).unwrap());
        // SAFETY: setrlimit is async-signal-safe and touches only the child.
        unsafe {
            cmd.pre_exec(|| {
                let lim = libc::rlimit {
                    rlim_cur: NOFILE as libc::rlim_t,
                    rlim_max: NOFILE as libc::rlim_t,
                };
                if libc::setrlimit(libc::RLIMIT_NOFILE, &lim) != 0 {
                    return Err(io::Error::last_os_error());
                }
                Ok(())
            });
        }
        let mut child = cmd.spawn().expect("the server starts");
        let addr = common::server::address_of(&mut child);
        Server {
            child,
            addr,
            log,
            data,
        }
    }

    fn connect(&self) -> TcpStream {
        let stream = TcpStream::connect(&self.addr).unwrap();
        stream
            .set_read_timeout(Some(Duration::from_secs(10)))
            .unwrap();
        stream
    }

    fn descriptors(&self) -> usize {
        std::fs::read_dir(format!("/proc/{}/fd", self.child.id()))
            .map(|d| d.count())
            .unwrap_or(0)
    }

    fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// Waits up to 5 s for the log to contain every one of `needles`.
    fn wait_for_log(&self, needles: &[&str]) -> String {
        let deadline = Instant::now() + Duration::from_secs(5);
        loop {
            let log = self.log();
            if needles.iter().all(|n| log.contains(n)) || Instant::now() > deadline {
                return log;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_dir_all(&self.data);
    }
}

/// Reads one response (status line, headers, a Content-Length body).
fn read_response(stream: &mut TcpStream) -> io::Result<String> {
    let mut head = Vec::new();
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") {
        if stream.read(&mut byte)? == 0 {
            return Err(io::ErrorKind::UnexpectedEof.into());
        }
        head.push(byte[0]);
    }
    let head = String::from_utf8_lossy(&head).into_owned();
    let length = head
        .lines()
        .find_map(|l| {
            l.to_ascii_lowercase()
                .strip_prefix("content-length:")
                .map(|v| v.trim().to_string())
        })
        .and_then(|v| v.parse::<usize>().ok())
        .unwrap_or(0);
    let mut body = vec![0u8; length];
    stream.read_exact(&mut body)?;
    Ok(head + &String::from_utf8_lossy(&body))
}

/// `GET /healthz` on a new connection: the answer and how long it took.
fn healthz(server: &Server) -> (io::Result<String>, Duration) {
    let start = Instant::now();
    let mut stream = server.connect();
    let answer = stream
        .write_all(b"GET /healthz HTTP/1.1\r\nHost: test\r\nConnection: close\r\n\r\n")
        .and_then(|()| read_response(&mut stream));
    (answer, start.elapsed())
}

/// Whether the server closed `stream` (end of file or a reset) within
/// `limit`.
fn closed_within(stream: &mut TcpStream, limit: Duration) -> bool {
    stream.set_read_timeout(Some(limit)).unwrap();
    let mut buf = [0u8; 64];
    loop {
        match stream.read(&mut buf) {
            Ok(0) => return true,
            Ok(_) => continue,
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                ) =>
            {
                return false
            }
            Err(_) => return true,
        }
    }
}

#[test]
fn half_sent_requests_leave_healthz_answering() {
    let header_timeout = Duration::from_secs(2);
    let server = Server::start("half-sent", &["--header-timeout", "2s"]);
    let mut held: Vec<(TcpStream, Instant)> = (0..300)
        .map(|_| {
            let mut s = server.connect();
            s.write_all(b"GET /healthz HTTP/1.1\r\nHost: test\r\n")
                .unwrap();
            (s, Instant::now())
        })
        .collect();
    let (answer, took) = healthz(&server);
    let answer = answer.expect("/healthz answers while 300 half-sent requests are held");
    assert!(answer.starts_with("HTTP/1.1 200"), "{answer}");
    assert!(took < Duration::from_secs(1), "/healthz took {took:?}");
    let fds = server.descriptors();
    assert!(
        fds < NOFILE as usize - 32,
        "the server holds {fds} descriptors"
    );

    // Every held connection is closed by the header timeout, if not before
    // to make room (a second of slack for a loaded machine).
    for (i, (stream, opened)) in held.iter_mut().enumerate() {
        let left = (header_timeout + Duration::from_secs(1)).saturating_sub(opened.elapsed());
        assert!(
            closed_within(stream, left.max(Duration::from_millis(1))),
            "held connection {i} still open after {:?}; the log:\n{}",
            opened.elapsed(),
            server.log()
        );
    }
    let log = server.wait_for_log(&["reason=\"header_timeout\"", "reason=\"evicted\""]);
    assert!(log.contains("reason=\"header_timeout\""), "{log}");
    assert!(log.contains("reason=\"evicted\""), "{log}");
    let (answer, _) = healthz(&server);
    assert!(answer.unwrap().starts_with("HTTP/1.1 200"));
}

#[test]
fn a_quiet_kept_alive_connection_is_closed_after_the_idle_timeout() {
    let server = Server::start("idle", &["--idle-timeout", "1s", "--header-timeout", "5s"]);
    let mut stream = server.connect();
    let request = b"GET /healthz HTTP/1.1\r\nHost: test\r\n\r\n";
    stream.write_all(request).unwrap();
    assert!(read_response(&mut stream)
        .unwrap()
        .starts_with("HTTP/1.1 200"));
    // Within the idle time the connection serves the next request.
    std::thread::sleep(Duration::from_millis(600));
    stream.write_all(request).unwrap();
    assert!(read_response(&mut stream)
        .unwrap()
        .starts_with("HTTP/1.1 200"));
    let answered = Instant::now();
    assert!(
        closed_within(&mut stream, Duration::from_millis(2500)),
        "an idle connection still open after {:?}",
        answered.elapsed()
    );
    let idle = answered.elapsed();
    assert!(
        idle >= Duration::from_millis(800),
        "closed after {idle:?}, before the idle timeout"
    );
}

#[test]
fn past_the_bound_with_every_connection_busy_the_answer_is_503() {
    let server = Server::start("bound", &["--max-connections", "2"]);
    // Two uploads in progress: their bodies never finish arriving.
    let busy: Vec<TcpStream> = (0..2)
        .map(|_| {
            let mut s = server.connect();
            s.write_all(
                b"POST /v1/jobs HTTP/1.1\r\nHost: test\r\nContent-Type: model/gltf-binary\r\n\
                  Content-Length: 100000\r\n\r\nglTF",
            )
            .unwrap();
            s
        })
        .collect();
    std::thread::sleep(Duration::from_millis(300));
    let mut third = server.connect();
    let _ = third.write_all(b"GET /healthz HTTP/1.1\r\nHost: test\r\n\r\n");
    let answer = read_response(&mut third).expect("an answer past the bound");
    assert!(answer.starts_with("HTTP/1.1 503"), "{answer}");
    assert!(answer.contains("Retry-After: 1"), "{answer}");
    assert!(answer.contains("\"code\":\"overloaded\""), "{answer}");
    assert!(closed_within(&mut third, Duration::from_secs(2)));
    let log = server.wait_for_log(&["connections refused with 503"]);
    assert!(log.contains("connections refused with 503"), "{log}");

    // Once the uploads go, there is room again.
    drop(busy);
    let deadline = Instant::now() + Duration::from_secs(5);
    loop {
        let (answer, _) = healthz(&server);
        match answer {
            Ok(a) if a.starts_with("HTTP/1.1 200") => break,
            other => assert!(Instant::now() < deadline, "{other:?}"),
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn out_of_descriptors_the_server_backs_off_and_sheds() {
    // A bound above what the descriptor limit allows: accepting runs out
    // of descriptors, and the server must neither spin nor stay stuck.
    let server = Server::start(
        "nofile",
        &["--max-connections", "1000", "--header-timeout", "2s"],
    );
    let held: Vec<TcpStream> = (0..300)
        .map(|_| {
            let mut s = server.connect();
            s.write_all(b"GET /healthz HTTP/1.1\r\nHost: test\r\n")
                .unwrap();
            s
        })
        .collect();
    let (answer, took) = healthz(&server);
    let answer = answer.expect("/healthz answers once idle connections are shed");
    assert!(answer.starts_with("HTTP/1.1 200"), "{answer}");
    assert!(took < Duration::from_secs(3), "/healthz took {took:?}");
    let needles = [
        "cannot accept connections",
        "os error 24",
        "reason=\"evicted\"",
    ];
    let log = server.wait_for_log(&needles);
    for needle in needles {
        assert!(log.contains(needle), "no {needle:?} in\n{log}");
    }
    // One line a second, not one per failed accept.
    let lines = log.matches("cannot accept connections").count();
    assert!(lines <= 5, "{lines} lines of accept errors:\n{log}");
    drop(held);
}
