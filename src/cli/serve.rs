//! `rigbridge serve`: binds 127.0.0.1 and hands the listener to the daemon's server.

use super::run::ClockChoice;
use anyhow::Context;
use clap::Args;
use rigbridge::daemon::config::load_run_settings;
use rigbridge::daemon::server::{ServeOptions, run};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Args)]
pub struct ServeArgs {
    /// Run settings: rig, stream rate, twin, plan and the default job.
    #[arg(long, default_value = "config/rigbridge.toml")]
    config: PathBuf,
    /// Port on 127.0.0.1 (0 picks a free one).
    #[arg(long, default_value_t = 0)]
    port: u16,
    /// Where each job's MCAP log goes.
    #[arg(long, default_value = "runs")]
    runs_dir: PathBuf,
    #[arg(long, value_enum, default_value = "wall")]
    clock: ClockChoice,
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

pub fn serve(args: ServeArgs) -> anyhow::Result<ExitCode> {
    let settings = load_run_settings(&args.config).context("cannot load run settings")?;
    let options = ServeOptions {
        runs_dir: args.runs_dir,
        virtual_clock: matches!(args.clock, ClockChoice::Virtual),
    };
    tokio::runtime::Runtime::new()?.block_on(async move {
        let listener = tokio::net::TcpListener::bind(("127.0.0.1", args.port))
            .await
            .with_context(|| format!("cannot bind 127.0.0.1:{}", args.port))?;
        println!("http://{}/", listener.local_addr()?);
        run(listener, settings, options, shutdown_signal()).await?;
        anyhow::Ok(())
    })?;
    Ok(ExitCode::SUCCESS)
}
