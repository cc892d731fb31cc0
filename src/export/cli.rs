//! The `export` command.

use crate::cli::Context;

#[derive(Debug, clap::Args)]
pub struct ExportArgs {}

pub fn run(_args: &ExportArgs, _ctx: &Context) -> anyhow::Result<()> {
    anyhow::bail!("`export` is not implemented yet")
}
