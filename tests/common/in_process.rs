//! The daemon's server (`rigbridge::server::run`) in the test's own process, shared
//! by tests/executor.rs, tests/serve_jobs.rs and benches/cells.rs: on a tokio runtime of its
//! own, listening on a free port of 127.0.0.1, stopped when the caller asks. Owns no request
//! and no judgement: the callers send requests and check the answers and the result.
#![allow(dead_code)]

use rigbridge::daemon::config::RunSettings;
use rigbridge::server::ServeError;
use rigbridge::server::{ServeOptions, run};
use std::net::SocketAddr;
use std::path::PathBuf;

/// A server's options in a test or a bench: jobs' logs in `runs_dir`, the wall clock, no
/// token, no host names beyond the default, no hook, no Zenoh, no Foxglove server
/// (several run side by side, and its default port is one; a bench measures the cycles
/// alone), and an executor on no CPU of its own (the test's other threads would have to
/// keep off it).
pub fn options(runs_dir: PathBuf) -> ServeOptions {
    ServeOptions {
        runs_dir,
        virtual_clock: false,
        token: None,
        allowed_hosts: Vec::new(),
        before_job: None,
        foxglove_port: 0,
        foxglove_allow_remote: false,
        zenoh_connect: None,
        executor_cpus: Vec::new(),
    }
}

/// A started server: where it listens, and what stops it.
pub struct Running {
    runtime: tokio::runtime::Runtime,
    pub address: SocketAddr,
    stop: tokio::sync::oneshot::Sender<()>,
    server: tokio::task::JoinHandle<Result<(), ServeError>>,
}

/// Serves `cells` with `options` on a free port of 127.0.0.1.
pub fn start(cells: Vec<RunSettings>, options: ServeOptions) -> Running {
    let runtime = tokio::runtime::Runtime::new().expect("runtime");
    let listener = runtime
        .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
        .expect("listener");
    let address = listener.local_addr().expect("address");
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let server = runtime.spawn(run(listener, cells, options, async {
        let _ = stopped.await;
    }));
    Running {
        runtime,
        address,
        stop,
        server,
    }
}

impl Running {
    /// Asks the server to stop and waits for it: what it returned, or its task's panic.
    pub fn stop(self) -> Result<Result<(), ServeError>, tokio::task::JoinError> {
        let _ = self.stop.send(());
        self.runtime.block_on(self.server)
    }
}
