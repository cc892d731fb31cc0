//! The `bench nn` command.

use crate::cli::Context;

#[derive(Debug, clap::Args)]
pub struct BenchNnArgs {}

pub fn run(_args: &BenchNnArgs, _ctx: &Context) -> anyhow::Result<()> {
    anyhow::bail!("`bench nn` is not implemented yet")
}
