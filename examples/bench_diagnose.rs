//! The diagnosis benchmark: renders the proof suite and prints the table
//! (`scripts/bench-diagnose.sh` runs this). Arguments are those of `lensrig diagnose`, e.g.
//! `--bench-seeds 3 [--bench-effect vignetting]`.

use clap::Parser;
use lensrig::diagnose::cli::{run, DiagnoseArgs};

#[derive(Parser)]
struct Cli {
    #[command(flatten)]
    args: DiagnoseArgs,
}

fn main() -> anyhow::Result<()> {
    run(&Cli::parse().args)
}
