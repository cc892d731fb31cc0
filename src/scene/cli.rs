//! The `info` command.

use crate::cli::Context;

#[derive(Debug, clap::Args)]
pub struct InfoArgs {}

pub fn run(_args: &InfoArgs, _ctx: &Context) -> anyhow::Result<()> {
    anyhow::bail!("`info` is not implemented yet")
}
