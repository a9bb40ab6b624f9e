//! `rigbridge config dump DIR`: the built-in configuration files written out for editing.
//! Owns only the command; the files and the writing are `rigbridge::rig::shipped`'s.

use anyhow::Context;
use clap::{Args, Subcommand};
use rigbridge::rig::shipped::{self, Dumped};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Subcommand)]
pub enum ConfigCommand {
    /// Write the built-in files (the IRB 120 rig, the demo run settings and the files they
    /// name) into DIR, then run with `--config DIR/rigbridge.toml`. Existing files are kept
    /// unless --force.
    Dump(DumpArgs),
}

#[derive(Args)]
pub struct DumpArgs {
    /// The directory to write into (created if needed).
    dir: PathBuf,
    /// Overwrite files that already exist.
    #[arg(long)]
    force: bool,
}

pub fn config_command(command: ConfigCommand) -> anyhow::Result<ExitCode> {
    let ConfigCommand::Dump(args) = command;
    let done = shipped::dump(&args.dir, args.force)
        .with_context(|| format!("cannot write the built-in files to {}", args.dir.display()))?;
    let mut kept = 0;
    for entry in &done {
        match entry {
            Dumped::Written(file) => say!("wrote {}", file.display()),
            Dumped::Kept(file) => {
                kept += 1;
                eprintln!("kept {} (exists; --force overwrites it)", file.display());
            }
        }
    }
    if kept > 0 {
        anyhow::bail!(super::Usage(format!(
            "{kept} of {} files already exist in {} and were not overwritten (--force overwrites them)",
            done.len(),
            args.dir.display()
        )));
    }
    Ok(ExitCode::SUCCESS)
}
