//! Accepts connections and serves the routes on them over HTTP/1.1,
//! bounding what a client can hold.
//!
//! A client that connects and sends nothing, or half a request, holds one
//! of the process's file descriptors; enough of them take every
//! descriptor, and then the server can accept nothing, not even
//! `/healthz`, and its stores and job processes cannot open files either.
//! So a connection has a deadline whenever the server waits for it (a
//! request's header, or the next request of a kept-alive connection);
//! connections are bounded below the descriptor limit; and past the bound
//! the connection that has waited longest for a request is closed to make
//! room, so a client that sends its request at once always gets in. Only
//! when every connection is busy with a request is a new one answered
//! `503`.

use std::collections::HashMap;
use std::convert::Infallible;
use std::future::Future;
use std::io;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicU8, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::task::{Context, Poll};
use std::time::Duration;

use axum::body::Body;
use axum::Router;
use http_body_util::BodyExt;
use hyper::body::Incoming;
use hyper::server::conn::http1;
use hyper::service::Service as _;
use hyper_util::rt::TokioIo;
use hyper_util::service::TowerToHyperService;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt, ReadBuf};
use tokio::net::{TcpListener, TcpSocket, TcpStream};
use tokio::sync::{watch, Notify, Semaphore};
use tokio::time::Instant;

use super::config::Config;

/// Descriptors kept for everything but connections: the standard streams,
/// the listener and the runtime's own, the job store's files or pool, the
/// object store's and callbacks' connections, and the connections being
/// closed past the bound (`EVICTING`, `LINGERING`).
const RESERVE_BASE: u64 = 64;
/// And for each worker: its job process's pipes (twice over while it
/// starts) and the files it reads and writes.
const RESERVE_PER_WORKER: u64 = 8;
/// Above this many connections it is memory and the cores, not the
/// descriptor limit, that bound a server.
const MAX_DEFAULT: u64 = 4096;
/// However tight the descriptor limit, a server must take some clients.
const MIN_DEFAULT: u64 = 8;

/// Connections told to go that may still hold their descriptors: past
/// it, accepting waits for them, so that a flood of clients cannot outrun
/// the closing and take the descriptors the bound keeps free.
const EVICTING: usize = 8;
/// The longest such wait: a connection told to go while it started a
/// request goes only once it is answered.
const SETTLE: Duration = Duration::from_millis(100);
/// Connections the kernel holds for the listener before it accepts them.
/// The standard library's 128 overflows when a burst of clients outruns
/// the accept loop, and the client whose handshake is dropped waits a
/// second or more to retry it.
const BACKLOG: u32 = 1024;
/// Refused connections closed gently at once, at most (the rest are
/// dropped): each holds a descriptor past the bound.
const LINGERING: usize = 16;
/// How long a refused connection is read from so that its client gets
/// the answer before the close.
const LINGER: Duration = Duration::from_secs(1);
/// Longest pause between accepts that fail for want of descriptors or
/// memory.
const MAX_BACKOFF: Duration = Duration::from_secs(1);
/// How often the closings are logged, at most, as one line per reason.
const REPORT_EVERY: Duration = Duration::from_secs(1);

/// What clients may hold, and what is kept from them.
#[derive(Clone, Copy, Debug)]
pub struct Limits {
    /// A request's whole header must arrive within it: counted from the
    /// connection's start for the first request, from the first byte for
    /// the next ones.
    pub header_timeout: Duration,
    /// A kept-alive connection that starts no new request within it of
    /// the previous response is closed.
    pub idle_timeout: Duration,
    pub max_connections: usize,
    /// Descriptors the rest of the server needs (logged beside the limit).
    pub reserve: u64,
}

impl Limits {
    pub fn of(cfg: &Config) -> Limits {
        Limits {
            header_timeout: cfg.header_timeout,
            idle_timeout: cfg.idle_timeout,
            max_connections: cfg.max_connections,
            reserve: reserve(cfg.workers),
        }
    }
}

fn reserve(workers: usize) -> u64 {
    RESERVE_BASE.saturating_add(RESERVE_PER_WORKER.saturating_mul(workers as u64))
}

/// The default bound on connections: half of what the descriptor limit
/// leaves beside the reserve, as a connection that uploads or downloads
/// holds a file besides its socket; between 8 and 4096.
pub fn default_max_connections(workers: usize) -> usize {
    let spare = descriptor_limit().saturating_sub(reserve(workers)) / 2;
    spare.clamp(MIN_DEFAULT, MAX_DEFAULT) as usize
}

/// The soft `RLIMIT_NOFILE`: the descriptors this process may open.
pub fn descriptor_limit() -> u64 {
    let mut rl = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit writes into the struct we own and reads nothing else.
    let ok = unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut rl) } == 0;
    match (ok, rl.rlim_cur) {
        (true, libc::RLIM_INFINITY) => u64::MAX,
        (true, n) => n,
        // The usual soft limit, so that the bound errs small.
        (false, _) => 1024,
    }
}

/// Listens on the first of `addrs` that can be bound, as
/// `TcpListener::bind` does, with a longer queue of pending connections.
pub fn bind(addrs: &[SocketAddr]) -> io::Result<TcpListener> {
    let mut last = io::Error::new(io::ErrorKind::InvalidInput, "no address to listen on");
    for addr in addrs {
        let socket = if addr.is_ipv4() {
            TcpSocket::new_v4()
        } else {
            TcpSocket::new_v6()
        };
        let listener = socket.and_then(|socket| {
            // As the standard library does: a restarted server can take
            // its port back while the old connections linger in TIME_WAIT.
            socket.set_reuseaddr(true)?;
            socket.bind(*addr)?;
            socket.listen(BACKLOG)
        });
        match listener {
            Ok(listener) => return Ok(listener),
            Err(e) => last = e,
        }
    }
    Err(last)
}

/// Serves `router` on `listener` until `shutdown` resolves; then stops
/// accepting, lets the requests in progress finish, and returns once every
/// connection is closed.
pub async fn serve(
    listener: TcpListener,
    router: Router,
    limits: Limits,
    shutdown: impl Future<Output = ()> + Send + 'static,
) {
    log_limits(&limits);
    let table = Arc::new(Table::new());
    let tally = Arc::new(Tally::default());
    let reporter = tokio::spawn(report(tally.clone(), table.clone(), limits));
    let (stop, stopping) = watch::channel(false);
    let lingering = Arc::new(Semaphore::new(LINGERING));
    let mut backoff = Duration::from_millis(10);
    tokio::pin!(shutdown);
    loop {
        table.settle().await;
        let accepted = tokio::select! {
            accepted = listener.accept() => accepted,
            () = &mut shutdown => break,
        };
        let stream = match accepted {
            Ok((stream, _)) => stream,
            Err(e) => {
                accept_failed(e, &table, &tally, &mut backoff).await;
                continue;
            }
        };
        backoff = Duration::from_millis(10);
        match table.make_room(limits.max_connections) {
            Room::Free => {}
            Room::Evicted => tally.count(Reason::Evicted),
            Room::Full => {
                tally.count(Reason::Refused);
                refuse(stream, &lingering);
                continue;
            }
        }
        let entry = table.insert();
        let (router, stopping, tally) = (router.clone(), stopping.clone(), tally.clone());
        tokio::spawn(connection(stream, entry, router, limits, stopping, tally));
    }
    drop(listener);
    let _ = stop.send(true);
    table.wait_empty().await;
    reporter.abort();
    tally.flush(&table, &limits);
}

fn log_limits(limits: &Limits) {
    let nofile = descriptor_limit();
    tracing::info!(
        max_connections = limits.max_connections,
        header_timeout_s = limits.header_timeout.as_secs_f64(),
        idle_timeout_s = limits.idle_timeout.as_secs_f64(),
        nofile,
        reserve = limits.reserve,
        "connection limits"
    );
    if (limits.max_connections as u64).saturating_add(limits.reserve) > nofile {
        tracing::warn!(
            max_connections = limits.max_connections,
            nofile,
            reserve = limits.reserve,
            "max_connections leaves the rest of the server too few file descriptors: \
             raise the limit (ulimit -n) or lower max_connections"
        );
    }
}

/// An accept that failed. A connection that went away before it was
/// accepted is no matter; otherwise (out of descriptors or memory) the
/// listener stays readable, so retrying at once would spin: wait, longer
/// each time, and free a descriptor if a connection waits idle.
async fn accept_failed(e: io::Error, table: &Table, tally: &Tally, backoff: &mut Duration) {
    use io::ErrorKind::{ConnectionAborted, ConnectionRefused, ConnectionReset, Interrupted};
    if matches!(
        e.kind(),
        ConnectionAborted | ConnectionRefused | ConnectionReset | Interrupted
    ) {
        return;
    }
    if matches!(e.raw_os_error(), Some(libc::EMFILE | libc::ENFILE)) && table.evict_oldest() {
        tally.count(Reason::Evicted);
    }
    tally.accept_failed(&e);
    tokio::time::sleep(*backoff).await;
    *backoff = (*backoff * 2).min(MAX_BACKOFF);
}

/// The answer past the bound, written on the socket as it is accepted:
/// the HTTP stack is never started for it.
fn overloaded() -> String {
    let body = r#"{"code":"overloaded","message":"the server has too many connections; retry after Retry-After seconds"}"#;
    format!(
        "HTTP/1.1 503 Service Unavailable\r\nRetry-After: 1\r\nConnection: close\r\n\
         Content-Type: application/json\r\nContent-Length: {}\r\n\r\n{body}",
        body.len()
    )
}

fn refuse(stream: TcpStream, lingering: &Arc<Semaphore>) {
    // A fresh socket's send buffer is empty: the answer fits at once.
    let _ = stream.try_write(overloaded().as_bytes());
    // Closing a socket with unread request bytes resets it, and a reset
    // can discard the answer before the client reads it: read until the
    // client closes, briefly, while few connections do so.
    if let Ok(permit) = lingering.clone().try_acquire_owned() {
        tokio::spawn(async move {
            let _permit = permit;
            let mut stream = stream;
            let _ = stream.shutdown().await;
            let mut buf = [0u8; 4096];
            let _ = tokio::time::timeout(LINGER, async {
                while matches!(stream.read(&mut buf).await, Ok(n) if n > 0) {}
            })
            .await;
        });
    }
}

/// One connection's life: HTTP/1.1 until the client closes, a deadline
/// passes, it is evicted, or the server stops.
async fn connection(
    stream: TcpStream,
    entry: Entry,
    router: Router,
    limits: Limits,
    mut stopping: watch::Receiver<bool>,
    tally: Arc<Tally>,
) {
    let conn = entry.conn.clone();
    let epoch = entry.table.epoch;
    let io = TokioIo::new(Watched {
        stream,
        conn: conn.clone(),
        epoch,
    });
    let service = {
        let (conn, router) = (conn.clone(), TowerToHyperService::new(router));
        hyper::service::service_fn(move |request: hyper::Request<Incoming>| {
            let busy = Busy::new(conn.clone(), epoch);
            let response = router.call(request);
            async move {
                let response = response.await?;
                // The guard lives as long as the body, which hyper drops
                // once it is sent: the connection is busy until then.
                Ok::<_, Infallible>(response.map(|body| {
                    Body::new(body.map_frame(move |frame| {
                        let _busy = &busy;
                        frame
                    }))
                }))
            }
        })
    };
    // The deadlines are this module's: hyper's header timeout would also
    // run while a kept-alive connection waits, cutting its idle time short.
    let mut builder = http1::Builder::new();
    builder.header_read_timeout(None);
    let http = builder.serve_connection(io, service);
    tokio::pin!(http);
    let mut stopped = false;
    loop {
        if !stopped && *stopping.borrow_and_update() {
            stopped = true;
            http.as_mut().graceful_shutdown();
        }
        let deadline = conn.deadline(epoch, &limits);
        tokio::select! {
            ended = http.as_mut() => {
                if let Err(e) = ended {
                    tracing::debug!(error = %e, "connection ended");
                }
                return;
            }
            () = sleep_until(deadline) => {
                if let Some(reason) = conn.expired(epoch, &limits) {
                    tally.count(reason);
                    return;
                }
            }
            () = conn.wake.notified() => {
                if conn.evicted.load(Ordering::Acquire) && conn.idle() {
                    return;
                }
            }
            changed = stopping.changed(), if !stopped => {
                if changed.is_err() {
                    stopped = true;
                    http.as_mut().graceful_shutdown();
                }
            }
        }
    }
}

async fn sleep_until(deadline: Option<Instant>) {
    match deadline {
        Some(at) => tokio::time::sleep_until(at).await,
        None => std::future::pending().await,
    }
}

/// What a connection waits for while no request is in progress.
const FRESH: u8 = 0;
/// A kept-alive connection, nothing of its next request yet.
const IDLE: u8 = 1;
/// The next request has begun.
const HEADER: u8 = 2;

/// One connection as the listener sees it.
struct Conn {
    /// FRESH, IDLE or HEADER.
    phase: AtomicU8,
    /// When the phase began, in milliseconds since the table's epoch.
    since_ms: AtomicU64,
    /// Requests in progress: their responses are not yet sent.
    busy: AtomicUsize,
    /// Told to close as soon as no request is in progress.
    evicted: AtomicBool,
    wake: Notify,
}

impl Conn {
    fn idle(&self) -> bool {
        self.busy.load(Ordering::Acquire) == 0
    }

    fn enter(&self, phase: u8, epoch: Instant) {
        self.since_ms.store(millis_since(epoch), Ordering::Release);
        self.phase.store(phase, Ordering::Release);
    }

    /// When the server stops waiting for this connection; none while a
    /// request is in progress.
    fn deadline(&self, epoch: Instant, limits: &Limits) -> Option<Instant> {
        if !self.idle() {
            return None;
        }
        let since = epoch + Duration::from_millis(self.since_ms.load(Ordering::Acquire));
        Some(match self.phase.load(Ordering::Acquire) {
            IDLE => since + limits.idle_timeout,
            _ => since + limits.header_timeout,
        })
    }

    fn expired(&self, epoch: Instant, limits: &Limits) -> Option<Reason> {
        let deadline = self.deadline(epoch, limits)?;
        (Instant::now() >= deadline).then(|| match self.phase.load(Ordering::Acquire) {
            IDLE => Reason::IdleTimeout,
            _ => Reason::HeaderTimeout,
        })
    }
}

fn millis_since(epoch: Instant) -> u64 {
    u64::try_from(epoch.elapsed().as_millis()).unwrap_or(u64::MAX)
}

/// A request in progress on a connection, until its response is sent.
struct Busy {
    conn: Arc<Conn>,
    epoch: Instant,
}

impl Busy {
    fn new(conn: Arc<Conn>, epoch: Instant) -> Busy {
        conn.busy.fetch_add(1, Ordering::AcqRel);
        Busy { conn, epoch }
    }
}

impl Drop for Busy {
    fn drop(&mut self) {
        // The idle time starts before the connection counts as idle, so
        // that an eviction never sees it idle since an older instant.
        self.conn.enter(IDLE, self.epoch);
        if self.conn.busy.fetch_sub(1, Ordering::AcqRel) == 1 {
            self.conn.wake.notify_one();
        }
    }
}

/// The socket, noting when the next request of a kept-alive connection
/// begins: from then on its header has a deadline of its own.
struct Watched {
    stream: TcpStream,
    conn: Arc<Conn>,
    epoch: Instant,
}

impl AsyncRead for Watched {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let before = buf.filled().len();
        let polled = Pin::new(&mut self.stream).poll_read(cx, buf);
        if buf.filled().len() > before && self.conn.phase.load(Ordering::Acquire) == IDLE {
            self.conn.enter(HEADER, self.epoch);
        }
        polled
    }
}

impl AsyncWrite for Watched {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.stream).poll_write(cx, buf)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.stream).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.stream.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_shutdown(cx)
    }
}

/// Whether a new connection fits.
enum Room {
    Free,
    /// The connection that waited longest for a request was told to go.
    Evicted,
    /// Every connection is busy with a request.
    Full,
}

/// The open connections.
struct Table {
    conns: Mutex<HashMap<u64, Arc<Conn>>>,
    next_id: AtomicU64,
    /// Connections told to go that have not yet gone: they no longer
    /// count against the bound.
    evicting: AtomicUsize,
    epoch: Instant,
    /// Told whenever a connection leaves.
    left: Notify,
}

impl Table {
    fn new() -> Table {
        Table {
            conns: Mutex::new(HashMap::new()),
            next_id: AtomicU64::new(0),
            evicting: AtomicUsize::new(0),
            epoch: Instant::now(),
            left: Notify::new(),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<u64, Arc<Conn>>> {
        // The map stays whole whatever panicked while holding it.
        self.conns.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn open(&self) -> usize {
        self.lock().len()
    }

    fn insert(self: &Arc<Self>) -> Entry {
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        let conn = Arc::new(Conn {
            phase: AtomicU8::new(FRESH),
            since_ms: AtomicU64::new(millis_since(self.epoch)),
            busy: AtomicUsize::new(0),
            evicted: AtomicBool::new(false),
            wake: Notify::new(),
        });
        self.lock().insert(id, conn.clone());
        Entry {
            table: self.clone(),
            id,
            conn,
        }
    }

    fn make_room(&self, max: usize) -> Room {
        let open = self.open();
        if open.saturating_sub(self.evicting.load(Ordering::Acquire)) < max {
            Room::Free
        } else if self.evict_oldest() {
            Room::Evicted
        } else {
            Room::Full
        }
    }

    /// Tells the connection that has waited longest for a request to go.
    fn evict_oldest(&self) -> bool {
        let conns = self.lock();
        let oldest = conns
            .values()
            .filter(|c| c.idle() && !c.evicted.load(Ordering::Acquire))
            .min_by_key(|c| c.since_ms.load(Ordering::Acquire));
        let Some(conn) = oldest else {
            return false;
        };
        conn.evicted.store(true, Ordering::Release);
        self.evicting.fetch_add(1, Ordering::AcqRel);
        conn.wake.notify_one();
        true
    }

    /// Waits, briefly, for the connections told to go to be gone.
    async fn settle(&self) {
        let _ = tokio::time::timeout(SETTLE, async {
            loop {
                let left = self.left.notified();
                if self.evicting.load(Ordering::Acquire) < EVICTING {
                    return;
                }
                left.await;
            }
        })
        .await;
    }

    async fn wait_empty(&self) {
        loop {
            let left = self.left.notified();
            if self.open() == 0 {
                return;
            }
            left.await;
        }
    }
}

/// A connection's place in the table, given up when its task ends.
struct Entry {
    table: Arc<Table>,
    id: u64,
    conn: Arc<Conn>,
}

impl Drop for Entry {
    fn drop(&mut self) {
        let mut conns = self.table.lock();
        conns.remove(&self.id);
        if self.conn.evicted.load(Ordering::Acquire) {
            self.table.evicting.fetch_sub(1, Ordering::AcqRel);
        }
        drop(conns);
        self.table.left.notify_waiters();
    }
}

/// Why a connection was closed or refused by the server.
#[derive(Clone, Copy)]
enum Reason {
    HeaderTimeout,
    IdleTimeout,
    Evicted,
    Refused,
}

/// Closings since the last report: a flood of clients gives one line a
/// second per reason, not one per client.
#[derive(Default)]
struct Tally {
    header_timeout: AtomicU64,
    idle_timeout: AtomicU64,
    evicted: AtomicU64,
    refused: AtomicU64,
    accept_errors: AtomicU64,
    last_accept_error: Mutex<Option<String>>,
}

impl Tally {
    fn count(&self, reason: Reason) {
        let counter = match reason {
            Reason::HeaderTimeout => &self.header_timeout,
            Reason::IdleTimeout => &self.idle_timeout,
            Reason::Evicted => &self.evicted,
            Reason::Refused => &self.refused,
        };
        counter.fetch_add(1, Ordering::Relaxed);
    }

    fn accept_failed(&self, e: &io::Error) {
        self.accept_errors.fetch_add(1, Ordering::Relaxed);
        *self
            .last_accept_error
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = Some(e.to_string());
    }

    /// Logs what happened since the last report.
    fn flush(&self, table: &Table, limits: &Limits) {
        let open = table.open();
        let max_connections = limits.max_connections;
        let take = |counter: &AtomicU64| counter.swap(0, Ordering::Relaxed);
        let idle = take(&self.idle_timeout);
        if idle > 0 {
            // Kept-alive clients going quiet is the normal course.
            tracing::debug!(
                reason = "idle_timeout",
                connections = idle,
                open,
                "connections closed"
            );
        }
        for (reason, counter) in [
            ("header_timeout", &self.header_timeout),
            ("evicted", &self.evicted),
        ] {
            let connections = take(counter);
            if connections > 0 {
                tracing::warn!(
                    reason,
                    connections,
                    open,
                    max_connections,
                    "connections closed"
                );
            }
        }
        let refused = take(&self.refused);
        if refused > 0 {
            // Every connection was busy with a request: nothing to evict.
            tracing::warn!(
                connections = refused,
                open,
                max_connections,
                "connections refused with 503"
            );
        }
        let errors = take(&self.accept_errors);
        if errors > 0 {
            let last = self
                .last_accept_error
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .take()
                .unwrap_or_default();
            tracing::error!(errors, error = %last, open, "cannot accept connections");
        }
    }
}

async fn report(tally: Arc<Tally>, table: Arc<Table>, limits: Limits) {
    loop {
        tokio::time::sleep(REPORT_EVERY).await;
        tally.flush(&table, &limits);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_overload_answer_is_whole() {
        let answer = overloaded();
        let (head, body) = answer.split_once("\r\n\r\n").unwrap();
        assert!(head.starts_with("HTTP/1.1 503 "));
        assert!(head.contains("\r\nRetry-After: 1\r\n"));
        assert!(head.contains("\r\nConnection: close\r\n"));
        assert!(head.contains(&format!("\r\nContent-Length: {}", body.len())));
        let json: serde_json::Value = serde_json::from_str(body).unwrap();
        assert_eq!(json["code"], "overloaded");
    }

    #[test]
    fn the_default_bound_leaves_the_reserve() {
        let max = default_max_connections(2) as u64;
        assert!((MIN_DEFAULT..=MAX_DEFAULT).contains(&max));
        let nofile = descriptor_limit();
        if nofile > reserve(2) + 2 * MIN_DEFAULT {
            assert!(max + reserve(2) <= nofile);
        }
    }
}
