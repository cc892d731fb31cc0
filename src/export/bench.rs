//! The `bench export` command.

use crate::cli::Context;

#[derive(Debug, clap::Args)]
pub struct BenchExportArgs {}

pub fn run(_args: &BenchExportArgs, _ctx: &Context) -> anyhow::Result<()> {
    anyhow::bail!("`bench export` is not implemented yet")
}
