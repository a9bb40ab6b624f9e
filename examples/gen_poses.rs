//! Writes the tool poses of seeded random in-limit configurations in the `rigbridge ik`
//! input contract (`x,y,z,qw,qx,qy,qz`, metres and a unit quaternion, 12 decimals): the
//! input of `scripts/bench-ik-cli.sh`.
//!
//! ```text
//! cargo run --release --example gen_poses -- --count 100000 --seed 7 --output poses.csv
//! ```

use clap::Parser;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rigbridge::rig::load_rig;
use std::io::Write;
use std::path::PathBuf;

#[derive(Parser)]
#[command(about = "FK poses of seeded random in-limit configurations, as a pose CSV")]
struct Args {
    #[arg(long, default_value = "config/irb120.toml")]
    rig: PathBuf,
    #[arg(long, default_value_t = 100_000)]
    count: usize,
    #[arg(long, default_value_t = 7)]
    seed: u64,
    #[arg(long)]
    output: PathBuf,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let rig = load_rig(&args.rig)?;
    let mut rng = ChaCha8Rng::seed_from_u64(args.seed);
    let mut out = std::io::BufWriter::new(std::fs::File::create(&args.output)?);
    writeln!(out, "x,y,z,qw,qx,qy,qz")?;
    for _ in 0..args.count {
        let joints: Vec<f64> = rig
            .joints
            .iter()
            .map(|j| rng.random_range(j.limits.lower..j.limits.upper))
            .collect();
        let pose = rig.tool_pose(&joints)?;
        let (p, q) = (pose.position, pose.orientation);
        writeln!(
            out,
            "{:.12},{:.12},{:.12},{:.12},{:.12},{:.12},{:.12}",
            p.x, p.y, p.z, q.w, q.x, q.y, q.z
        )?;
    }
    out.flush()?;
    Ok(())
}
