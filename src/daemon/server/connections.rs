//! The listener's connections: accepting them, the connection cap, and the timeouts that
//! close idle and slow ones. Owns only connection bookkeeping; routing and access control
//! stay in `server.rs`.
//!
//! Why not `axum::serve`: it never closes an idle or slow connection and keeps accepting
//! until the process runs out of descriptors, after which nobody (an e-stop included) gets
//! in. Here every connection is registered; at the cap, or when `accept` fails for lack of
//! descriptors, the oldest connection that is not in the middle of a request is closed (the
//! oldest of all if every one is), so a new client always gets in: an e-stop is answered
//! however many clients hold connections open.

use axum::Router;
use hyper::body::Incoming;
use hyper_util::rt::{TokioIo, TokioTimer};
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};
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
/// How long to wait after `accept` failed for a reason other than the descriptor limit.
const ACCEPT_BACKOFF: Duration = Duration::from_millis(10);

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

/// One open connection: whether a request is being served on it, and its task.
struct Entry {
    busy: Arc<AtomicBool>,
    abort: AbortHandle,
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

    /// Closes the oldest connection not serving a request, or the oldest of all.
    fn evict_one(&self) {
        let mut open = self.open();
        let victim = open
            .iter()
            .find(|(_, e)| !e.busy.load(Ordering::Relaxed))
            .or_else(|| open.iter().next())
            .map(|(id, _)| *id);
        if let Some(entry) = victim.and_then(|id| open.remove(&id)) {
            entry.abort.abort();
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
                    while registry.open().len() >= cap {
                        registry.evict_one();
                    }
                    spawn_connection(stream, app.clone(), &registry);
                }
                Err(e) if is_out_of_descriptors(&e) => registry.evict_one(),
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

fn spawn_connection(stream: tokio::net::TcpStream, app: Router, registry: &Arc<Registry>) {
    let id = registry.next.fetch_add(1, Ordering::Relaxed);
    let busy = Arc::new(AtomicBool::new(false));
    let last_done = Arc::new(Mutex::new(Instant::now()));
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
                *last_done.lock().unwrap_or_else(PoisonError::into_inner) = Instant::now();
                busy.store(false, Ordering::Relaxed);
                response
            }
        })
    };
    let watched = busy.clone();
    // Registered before the task runs, so the cap counts it at once.
    let mut open = registry.open();
    let task = tokio::spawn(async move {
        let _guard = guard;
        let mut builder = hyper::server::conn::http1::Builder::new();
        builder
            .timer(TokioTimer::new())
            .header_read_timeout(HEADER_TIMEOUT);
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
            busy,
            abort: task.abort_handle(),
        },
    );
}

/// Completes once the connection has served no request for [`IDLE_TIMEOUT`].
async fn idle(busy: &AtomicBool, last_done: &Mutex<Instant>) {
    loop {
        tokio::time::sleep(IDLE_CHECK).await;
        let since = last_done
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .elapsed();
        if !busy.load(Ordering::Relaxed) && since >= IDLE_TIMEOUT {
            return;
        }
    }
}
