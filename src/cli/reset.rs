//! `rigbridge reset`: opens a link as `run` does, sends Reset when the controller reports a
//! latched fault, and says what it answered. Exit 0 when the controller reports no fault
//! afterwards (cleared, or none was latched), 3 when it keeps its fault.

use anyhow::Context;
use clap::Args;
use rigbridge::daemon::config::load_run_settings;
use rigbridge::daemon::open_link;
use rigbridge::daemon::reset::{RESET_TIMEOUT, reset_controller};
use rigbridge::device::LinkSpec;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Args)]
pub struct ResetArgs {
    /// The controller (default: the config's `[stream] link`); `--help` lists every form.
    #[arg(long, long_help = format!("The controller whose latched fault or e-stop to clear (default: the config's `[stream] link`): {}", rigbridge::device::link_forms()))]
    link: Option<String>,
    /// Run settings: the rig and stream rate the bridge's Hello announces.
    #[arg(long, env = "RIGBRIDGE_CONFIG", default_value = rigbridge::rig::shipped::DEFAULT_RUN_SETTINGS)]
    config: PathBuf,
}

/// Exit code when the controller keeps its fault, as for a run that did not complete.
const KEPT_EXIT: u8 = 3;

pub fn reset(args: ResetArgs) -> anyhow::Result<ExitCode> {
    let settings =
        load_run_settings(&args.config).with_context(|| super::settings_context(&args.config))?;
    let spec: LinkSpec = args
        .link
        .as_deref()
        .unwrap_or(&settings.config.stream.link)
        .parse()?;
    let mut link = open_link(&spec, &settings).context("cannot open the link")?;
    let outcome = reset_controller(link.as_mut(), RESET_TIMEOUT)
        .with_context(|| format!("reset over {}", link.describe()))?;
    say!("reset over {}: {outcome}", link.describe());
    Ok(if outcome.is_clear() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(KEPT_EXIT)
    })
}
