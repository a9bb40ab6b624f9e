//! `rigbridge serve`: loads one run settings file per cell (`--config`, repeatable), binds
//! 127.0.0.1 (or `--bind` / the first file's `[serve] bind`) and hands the listener to the
//! daemon's server. A non-loopback address requires a token (`RIGBRIDGE_TOKEN` or the first
//! file's `[serve] token`), and `[serve] foxglove_allow_remote` for the live Foxglove server
//! (or `foxglove_port = 0` / `--foxglove-port 0`).

use super::run::ClockChoice;
use anyhow::Context;
use clap::Args;
use rigbridge::daemon::config::RunSettings;
use rigbridge::daemon::config::{foxglove_bind_problem, load_run_settings, token_problem};
use rigbridge::device::LinkSpec;
use rigbridge::server::{ServeOptions, check_cells, run};
use std::net::IpAddr;
use std::path::PathBuf;
use std::process::ExitCode;

/// The environment variable holding the API token; it wins over `[serve] token`.
const TOKEN_VAR: &str = "RIGBRIDGE_TOKEN";

#[derive(Args)]
pub struct ServeArgs {
    /// Run settings of a cell: rig, stream rate, twin, plan and the default job. Repeat it
    /// to serve several rigs at once, one cell each, named by its rig; the first file's
    /// `[serve]` sets the bind address and token, and its cell answers the routes without a
    /// cell name.
    #[arg(long, env = "RIGBRIDGE_CONFIG", default_value = rigbridge::rig::shipped::DEFAULT_RUN_SETTINGS)]
    config: Vec<PathBuf>,
    /// Address to listen on [default: `[serve] bind`, else 127.0.0.1]. Anything but a
    /// loopback address requires a token (RIGBRIDGE_TOKEN or `[serve] token`).
    #[arg(long, value_name = "ADDRESS")]
    bind: Option<IpAddr>,
    /// Port on the bind address (0 picks a free one).
    #[arg(long, default_value_t = 0)]
    port: u16,
    /// Where each job's MCAP log goes.
    #[arg(long, default_value = "runs")]
    runs_dir: PathBuf,
    /// Whose time the cycles run on: wall (real time) or virtual (the same cycles without
    /// waiting).
    #[arg(long, value_enum, default_value = "wall")]
    clock: ClockChoice,
    /// Port of the live Foxglove WebSocket server on the bind address [default: `[serve]
    /// foxglove_port`, else 8765]; 0 turns it off. Off loopback it needs `[serve]
    /// foxglove_allow_remote = true`: it has no authentication.
    #[arg(long, value_name = "PORT")]
    foxglove_port: Option<u16>,
    /// Join ROS 2 over Zenoh through this router or peer (`tcp/HOST:PORT`), every cell as
    /// a node in its rig's namespace; overrides each file's `[ros2] zenoh_connect`.
    #[arg(long, value_name = "ENDPOINT", value_parser = super::run::parse_zenoh_endpoint)]
    zenoh_connect: Option<String>,
}

async fn shutdown_signal() {
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut signal) => {
                signal.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    tokio::select! {
        _ = tokio::signal::ctrl_c() => {}
        _ = terminate => {}
    }
    eprintln!("stopping: bringing any job to rest, closing its log");
}

/// The token: `RIGBRIDGE_TOKEN` when set, else `[serve] token`.
fn token(config_token: Option<&str>) -> anyhow::Result<Option<String>> {
    match std::env::var(TOKEN_VAR) {
        Ok(token) => {
            if let Some(reason) = token_problem(&token) {
                anyhow::bail!("{TOKEN_VAR} is set but not usable: it {reason}");
            }
            Ok(Some(token))
        }
        Err(std::env::VarError::NotPresent) => Ok(config_token.map(String::from)),
        Err(std::env::VarError::NotUnicode(_)) => {
            anyhow::bail!("{TOKEN_VAR} is set but not usable: it is not valid Unicode")
        }
    }
}

/// Every `--config` file, loaded and checked to run side by side.
fn load_cells(files: &[PathBuf]) -> anyhow::Result<Vec<RunSettings>> {
    let cells = files
        .iter()
        .map(|file| load_run_settings(file).context("cannot load run settings"))
        .collect::<anyhow::Result<Vec<_>>>()?;
    check_cells(&cells).context("cannot serve these run settings together")?;
    for cell in cells.iter().skip(1) {
        let serve = &cell.config.serve;
        if serve.bind != "127.0.0.1" || serve.token.is_some() {
            eprintln!(
                "note: [serve] in {} is ignored: the first --config file's [serve] applies",
                cell.file.display()
            );
        }
    }
    Ok(cells)
}

/// A real controller keeps real time: a virtual clock would stream faster than it runs.
fn refuse_virtual_clock_with_real_links(cells: &[RunSettings]) -> anyhow::Result<()> {
    for cell in cells {
        let link = &cell.config.stream.link;
        let spec: LinkSpec = link
            .parse()
            .with_context(|| format!("[stream] link in {}", cell.file.display()))?;
        anyhow::ensure!(
            spec == LinkSpec::Loopback,
            "--clock virtual needs the loopback twin: the cell of {} streams to {link}, a \
             controller that runs in real time",
            cell.file.display()
        );
    }
    Ok(())
}

/// Keeps this thread, and so every thread the daemon starts from it (the runtime, the jobs,
/// their log writers), off the CPUs the shared executor will keep to; returns them, or none
/// (unpinned executor) when that is refused.
fn keep_off_executor_cpus(cpus: Vec<usize>) -> Vec<usize> {
    if cpus.is_empty() {
        return cpus;
    }
    match rigbridge::realtime::keep_off_all(&cpus) {
        Ok(()) => cpus,
        Err(e) => {
            eprintln!(
                "note: the shared executor gets no CPU of its own (cannot keep the daemon's \
                 other threads off it: {e}); its cycles may wake later"
            );
            Vec::new()
        }
    }
}

pub fn serve(args: ServeArgs) -> anyhow::Result<ExitCode> {
    let cells = load_cells(&args.config)?;
    let settings = &cells[0];
    let bind = match args.bind {
        Some(bind) => bind,
        // Validated on load.
        None => settings
            .config
            .serve
            .bind
            .parse()
            .context("cannot parse [serve] bind")?,
    };
    let token = token(settings.config.serve.token.as_deref())?;
    if !bind.is_loopback() && token.is_none() {
        anyhow::bail!(
            "refusing to serve on {bind} without a token: anyone who can reach a non-loopback \
             address could move the arm. Set one in the environment ({TOKEN_VAR}=<secret>) \
             or as `token` under [serve] in {}, or bind 127.0.0.1",
            settings.file.display()
        );
    }
    let serve = &settings.config.serve;
    let foxglove_port = args.foxglove_port.unwrap_or(serve.foxglove_port);
    if let Some(problem) = foxglove_bind_problem(bind, foxglove_port, serve.foxglove_allow_remote) {
        anyhow::bail!(
            "refusing to serve: {problem} (in {})",
            settings.file.display()
        );
    }
    let virtual_clock = matches!(args.clock, ClockChoice::Virtual);
    if virtual_clock {
        refuse_virtual_clock_with_real_links(&cells)?;
    }
    let executor_cpus = if virtual_clock {
        Vec::new()
    } else {
        keep_off_executor_cpus(serve.executor_cpus())
    };
    let options = ServeOptions {
        runs_dir: args.runs_dir,
        virtual_clock,
        token,
        allowed_hosts: settings.config.serve.hosts.clone(),
        before_job: None,
        foxglove_port,
        foxglove_allow_remote: serve.foxglove_allow_remote,
        zenoh_connect: args.zenoh_connect,
        executor_cpus,
    };
    tokio::runtime::Runtime::new()?.block_on(async move {
        let address = std::net::SocketAddr::new(bind, args.port);
        let listener =
            rigbridge::server::bind(address).with_context(|| format!("cannot bind {address}"))?;
        say!("http://{}/", listener.local_addr()?);
        run(listener, cells, options, shutdown_signal()).await?;
        anyhow::Ok(())
    })?;
    Ok(ExitCode::SUCCESS)
}
