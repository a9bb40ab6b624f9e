//! `rigbridge config dump DIR`: the built-in configuration files written out for editing;
//! `rigbridge config urdf`: the rig in its cell as one URDF (and its SRDF). Owns only the
//! commands; the files and the writing are `rigbridge::rig::shipped`'s and
//! `rigbridge::cell::urdf`'s.

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
    /// Write the rig's URDF with its collision geometry, the cell's tool (a fixed link at its
    /// TCP) and objects (fixed links on the base): the world the checks see (docs/cell.md).
    Urdf(UrdfArgs),
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
        ConfigCommand::Urdf(args) => urdf(args),
    }
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
