//! The listener's connections: accepting them, the connection cap, and the timeouts that
//! close idle and slow ones. Owns only connection bookkeeping; routing and access control
//! stay in `server.rs`.
//!
//! Why not `axum::serve`: it never closes an idle or slow connection and keeps accepting
//! until the process runs out of descriptors, after which nobody (an e-stop included) gets
//! in. Here every connection is registered; at the cap, or when `accept` fails for lack of
//! descriptors, one connection is closed so a new client always gets in: an e-stop is
//! answered however many clients hold connections open. Which one: the oldest of those that
//! have sent nothing yet (idle), else the oldest of those in the middle of a request's
//! headers (slow), else the oldest of all. A client that sends its request as it connects,
//! as an operator's e-stop does, is never closed for an idle newcomer, even when a flood
//! of them turns the whole table over before its task first runs: before an idle-looking
//! connection is closed, the kernel is asked whether bytes wait on it.

use crate::clock::{self, Clock};
use axum::Router;
use hyper::body::Incoming;
use hyper_util::rt::{TokioIo, TokioTimer};
use std::collections::BTreeMap;
use std::os::fd::AsRawFd;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::task::{Context, Poll};
use std::time::Duration;
use tokio::net::TcpListener;
use tokio::sync::watch;
use tokio::task::AbortHandle;
use tower::Service;

/// How long a client may take to send a request's headers: generous for any real client
/// on a slow link, short enough that a slowloris client holds its connection for seconds.
pub const HEADER_TIMEOUT: Duration = Duration::from_secs(5);
/// How long a connection may sit without a request before it is closed.
pub const IDLE_TIMEOUT: Duration = Duration::from_secs(10);
/// How often each connection checks its idle time.
const IDLE_CHECK: Duration = Duration::from_millis(500);
/// Descriptors kept free of connections for the rest of the daemon (log files, links,
/// the live view's sockets, a serial port): the cap is the descriptor limit minus these.
const RESERVED_DESCRIPTORS: u64 = 64;
/// The connection cap's bounds, whatever the descriptor limit says.
const MIN_CONNECTIONS: u64 = 16;
const MAX_CONNECTIONS: u64 = 1024;
/// How long to wait for descriptors when every connection holding one has spoken: long
/// enough for closed connections' tasks to run and let theirs go.
const DESCRIPTOR_WAIT: Duration = Duration::from_millis(1);
/// How long to wait after `accept` failed for a reason other than the descriptor limit.
const ACCEPT_BACKOFF: Duration = Duration::from_millis(10);

/// Connections the kernel may hold complete but not yet accepted (the kernel caps it at
/// `net.core.somaxconn`). The standard library's 128 overflows under a few hundred
/// clients reconnecting at once: the kernel then drops handshakes, and a client that lost
/// one (an e-stop) retries only after a second.
pub const LISTEN_BACKLOG: u32 = 4096;

/// A listener on `address` with [`LISTEN_BACKLOG`].
pub fn bind(address: std::net::SocketAddr) -> std::io::Result<TcpListener> {
    let socket = if address.is_ipv4() {
        tokio::net::TcpSocket::new_v4()?
    } else {
        tokio::net::TcpSocket::new_v6()?
    };
    // As std's bind does: a restarted daemon gets its port back at once.
    socket.set_reuseaddr(true)?;
    socket.bind(address)?;
    socket.listen(LISTEN_BACKLOG)
}

/// The connection cap for this process: its descriptor limit less a reserve.
pub fn connection_cap() -> usize {
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit only writes the struct it is given.
    let soft = if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) } == 0 {
        limit.rlim_cur
    } else {
        MAX_CONNECTIONS
    };
    let cap = soft
        .saturating_sub(RESERVED_DESCRIPTORS)
        .clamp(MIN_CONNECTIONS, MAX_CONNECTIONS);
    usize::try_from(cap).unwrap_or(usize::MAX)
}

/// One open connection: whether it has sent anything, whether a request is being served
/// on it, and its task.
struct Entry {
    /// The socket, to ask the kernel about (never to close: the task owns it).
    fd: std::os::fd::RawFd,
    spoke: Arc<AtomicBool>,
    busy: Arc<AtomicBool>,
    abort: AbortHandle,
}

impl Entry {
    /// Which connections go first when one must: 0 idle, 1 in a request's headers, 2
    /// serving one.
    fn keep_rank(&self) -> u8 {
        if self.busy.load(Ordering::Relaxed) {
            2
        } else if self.spoke.load(Ordering::Relaxed) {
            1
        } else {
            0
        }
    }

    /// Idle as far as the server has read, and nothing waiting in the kernel either; a
    /// connection found with bytes waiting counts as having spoken from then on.
    fn is_silent(&self) -> bool {
        if self.keep_rank() != 0 {
            return false;
        }
        if bytes_waiting(self.fd) {
            self.spoke.store(true, Ordering::Relaxed);
            return false;
        }
        true
    }
}

#[derive(Default)]
struct Registry {
    next: AtomicU64,
    open: Mutex<BTreeMap<u64, Entry>>,
}

impl Registry {
    fn open(&self) -> std::sync::MutexGuard<'_, BTreeMap<u64, Entry>> {
        self.open.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Closes the oldest silent connection, or with `any`, failing that, the oldest of the
    /// lowest [`Entry::keep_rank`]; whether it closed one.
    fn evict_one(&self, any: bool) -> bool {
        let mut open = self.open();
        // Ids grow with age: the first found is the oldest. The kernel is asked only until
        // a silent one turns up, usually the first.
        let silent = open.iter().find(|(_, e)| e.is_silent()).map(|(id, _)| *id);
        let victim = silent.or_else(|| {
            any.then(|| open.iter().min_by_key(|(id, e)| (e.keep_rank(), **id)))
                .flatten()
                .map(|(id, _)| *id)
        });
        match victim.and_then(|id| open.remove(&id)) {
            Some(entry) => {
                entry.abort.abort();
                true
            }
            None => false,
        }
    }
}

/// Removes its connection from the registry when the connection's task ends.
struct Registered {
    id: u64,
    registry: Arc<Registry>,
}

impl Drop for Registered {
    fn drop(&mut self) {
        self.registry.open().remove(&self.id);
    }
}

/// Serves `app` on `listener` until `stopping` turns true, at most `cap` connections at once.
pub async fn serve(
    listener: TcpListener,
    app: Router,
    cap: usize,
    mut stopping: watch::Receiver<bool>,
) {
    let registry = Arc::new(Registry::default());
    loop {
        tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok((stream, _)) => {
                    while registry.open().len() >= cap && registry.evict_one(true) {}
                    spawn_connection(stream, app.clone(), &registry);
                }
                // Descriptors run out below the cap while closed connections' tasks have yet
                // to let go of theirs: close a silent one, never one that spoke (an e-stop)
                // for a newcomer nobody has heard yet; else wait for them.
                Err(e) if is_out_of_descriptors(&e) => {
                    if !registry.evict_one(false) {
                        tokio::time::sleep(DESCRIPTOR_WAIT).await;
                    }
                }
                Err(_) => tokio::time::sleep(ACCEPT_BACKOFF).await,
            },
            _ = stopping.changed() => break,
        }
    }
    let open: Vec<Entry> = std::mem::take(&mut *registry.open())
        .into_values()
        .collect();
    for entry in open {
        entry.abort.abort();
    }
}

fn is_out_of_descriptors(e: &std::io::Error) -> bool {
    matches!(e.raw_os_error(), Some(libc::EMFILE | libc::ENFILE))
}

/// Whether bytes wait to be read on socket `fd` (FIONREAD). Should the connection have
/// closed and its number gone to another socket meanwhile, the answer is about that one:
/// at worst a wrong choice of whom to close, never a wrong close.
fn bytes_waiting(fd: std::os::fd::RawFd) -> bool {
    let mut pending: libc::c_int = 0;
    // SAFETY: FIONREAD writes one int to the pointer it is given; on a descriptor that is
    // not a socket (or not open) it fails, which reads as "nothing waiting".
    let asked = unsafe { libc::ioctl(fd, libc::FIONREAD, &mut pending) };
    asked == 0 && pending > 0
}

fn spawn_connection(stream: tokio::net::TcpStream, app: Router, registry: &Arc<Registry>) {
    let id = registry.next.fetch_add(1, Ordering::Relaxed);
    let fd = stream.as_raw_fd();
    let spoke = Arc::new(AtomicBool::new(bytes_waiting(fd)));
    let busy = Arc::new(AtomicBool::new(false));
    let last_done = Arc::new(Mutex::new(clock::real().now()));
    let guard = Registered {
        id,
        registry: registry.clone(),
    };
    let service = {
        let (busy, last_done) = (busy.clone(), last_done.clone());
        hyper::service::service_fn(move |request: hyper::Request<Incoming>| {
            let mut app = app.clone();
            let (busy, last_done) = (busy.clone(), last_done.clone());
            busy.store(true, Ordering::Relaxed);
            async move {
                let response = app.call(request).await;
                *last_done.lock().unwrap_or_else(PoisonError::into_inner) = clock::real().now();
                busy.store(false, Ordering::Relaxed);
                response
            }
        })
    };
    let watched = busy.clone();
    let heard = spoke.clone();
    // Registered before the task runs, so the cap counts it at once.
    let mut open = registry.open();
    let task = tokio::spawn(async move {
        let _guard = guard;
        let mut builder = hyper::server::conn::http1::Builder::new();
        builder
            .timer(TokioTimer::new())
            .header_read_timeout(HEADER_TIMEOUT);
        let stream = Heard {
            inner: stream,
            spoke: heard,
        };
        let connection = builder
            .serve_connection(TokioIo::new(stream), service)
            .with_upgrades();
        tokio::select! {
            _ = connection => {}
            _ = idle(&watched, &last_done) => {}
        }
    });
    open.insert(
        id,
        Entry {
            fd,
            spoke,
            busy,
            abort: task.abort_handle(),
        },
    );
}

/// Completes once the connection has served no request for [`IDLE_TIMEOUT`].
async fn idle(busy: &AtomicBool, last_done: &Mutex<Duration>) {
    loop {
        tokio::time::sleep(IDLE_CHECK).await;
        let done = *last_done.lock().unwrap_or_else(PoisonError::into_inner);
        let since = clock::real().now().saturating_sub(done);
        if !busy.load(Ordering::Relaxed) && since >= IDLE_TIMEOUT {
            return;
        }
    }
}

/// A connection's stream that notes when the client first sends a byte.
struct Heard {
    inner: tokio::net::TcpStream,
    spoke: Arc<AtomicBool>,
}

impl tokio::io::AsyncRead for Heard {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut tokio::io::ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        let before = buf.filled().len();
        let polled = Pin::new(&mut self.inner).poll_read(cx, buf);
        if buf.filled().len() > before {
            self.spoke.store(true, Ordering::Relaxed);
        }
        polled
    }
}

impl tokio::io::AsyncWrite for Heard {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }
}
