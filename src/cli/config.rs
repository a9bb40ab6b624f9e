//! `rigbridge config dump DIR`: the built-in configuration files written out for editing;
//! `rigbridge config allowed-pairs`: a rig's allowed pairs found by sampling;
//! `rigbridge config urdf`: the rig in its cell as one URDF (and its SRDF). Owns only the
//! commands; the files, the writing and the sampling are the library's
//! (`rigbridge::rig::shipped`, `rigbridge::cell`).

use anyhow::Context;
use clap::{Args, Subcommand};
use rigbridge::cell::urdf::{cell_to_srdf, cell_to_urdf};
use rigbridge::rig::shipped::{self, Dumped};
use std::path::{Path, PathBuf};
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
    /// Write the rig's URDF with its collision geometry, the cell's tool (a fixed link at its
    /// TCP) and objects (fixed links on the base): the world the checks see (docs/cell.md).
    Urdf(UrdfArgs),
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

#[derive(Args)]
pub struct UrdfArgs {
    /// Run settings naming the rig and its cell [default: the built-in IRB 120 on its
    /// floor].
    #[arg(long, env = super::CONFIG_VAR)]
    config: Option<PathBuf>,
    /// Where the URDF goes; `-` writes stdout. Convex hulls are written beside it as OBJ
    /// files, so a cell with hulls needs a file here.
    #[arg(long, default_value = "-")]
    output: PathBuf,
    /// Also write the pairs never checked (the rig's and the cell's allowed pairs) as an
    /// SRDF (MoveIt's `disable_collisions`) to this file.
    #[arg(long, value_name = "FILE")]
    srdf: Option<PathBuf>,
}

pub fn config_command(command: ConfigCommand) -> anyhow::Result<ExitCode> {
    match command {
        ConfigCommand::Dump(args) => dump(args),
        ConfigCommand::AllowedPairs(args) => allowed_pairs(args),
        ConfigCommand::Urdf(args) => urdf(args),
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

fn write(path: &Path, text: &str) -> anyhow::Result<()> {
    std::fs::write(path, text).with_context(|| format!("cannot write {}", path.display()))
}

fn urdf(args: UrdfArgs) -> anyhow::Result<ExitCode> {
    let (rig, cell) = super::batch::rig_and_cell(args.config.as_deref())?;
    let export = cell_to_urdf(&rig, &cell);
    if args.output == Path::new("-") {
        if let Some(mesh) = export.meshes.first() {
            anyhow::bail!(super::Usage(format!(
                "the cell holds convex hulls (the first: {}) written as mesh files beside the \
                 URDF: give --output FILE",
                mesh.file
            )));
        }
        use std::io::Write as _;
        super::stdout().write_all(export.text.as_bytes())?;
    } else {
        write(&args.output, &export.text)?;
        let dir = args.output.parent().unwrap_or(Path::new("."));
        for mesh in &export.meshes {
            write(&dir.join(&mesh.file), &mesh.obj_text())?;
        }
    }
    if let Some(path) = &args.srdf {
        write(path, &cell_to_srdf(&rig, &cell))?;
    }
    Ok(ExitCode::SUCCESS)
}
