//! `rigbridge config dump DIR`: the built-in configuration files written out for editing;
//! `rigbridge config allowed-pairs`: a rig's allowed pairs found by sampling. Owns only the
//! commands; the files, the writing and the sampling are the library's.

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
    /// Find the rig's allowed pairs by sampling (adjacent links, pairs always or never in
    /// collision, as MoveIt's setup assistant) and print them as the rig file's
    /// `allowed_pairs`, or write them into the file (--write).
    AllowedPairs(AllowedPairsArgs),
}

#[derive(Args)]
pub struct AllowedPairsArgs {
    /// The rig file (TOML); default the built-in IRB 120.
    #[arg(long, default_value = shipped::DEFAULT_RIG)]
    rig: PathBuf,
    /// Configurations to sample, uniform within the joint limits.
    #[arg(long, default_value_t = rigbridge::cell::DEFAULT_SAMPLES)]
    samples: usize,
    /// The sampler's seed (the same seed gives the same pairs).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Rewrite the rig file's `allowed_pairs` instead of printing it.
    #[arg(long)]
    write: bool,
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
    match command {
        ConfigCommand::Dump(args) => dump(args),
        ConfigCommand::AllowedPairs(args) => allowed_pairs(args),
    }
}

fn allowed_pairs(args: AllowedPairsArgs) -> anyhow::Result<ExitCode> {
    let rig = rigbridge::rig::load_rig(&args.rig)?;
    let pairs = rigbridge::cell::find_allowed_pairs(&rig, args.samples, args.seed)?;
    let key = rigbridge::cell::allowed_pairs_toml(&pairs);
    if !args.write {
        say!("{key}");
        return Ok(ExitCode::SUCCESS);
    }
    if shipped::is_shipped(&args.rig) {
        anyhow::bail!(super::Usage(format!(
            "{} is built in and cannot be rewritten: `rigbridge config dump DIR` writes it out",
            args.rig.display()
        )));
    }
    let text = std::fs::read_to_string(&args.rig)
        .with_context(|| format!("cannot read {}", args.rig.display()))?;
    std::fs::write(
        &args.rig,
        rigbridge::cell::replace_allowed_pairs(&text, &key),
    )
    .with_context(|| format!("cannot write {}", args.rig.display()))?;
    say!(
        "wrote {} allowed pairs into {}",
        pairs.len(),
        args.rig.display()
    );
    Ok(ExitCode::SUCCESS)
}

fn dump(args: DumpArgs) -> anyhow::Result<ExitCode> {
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
