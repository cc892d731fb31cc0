//! The `fit-env` command.

use crate::cli::Context;

#[derive(Debug, clap::Args)]
pub struct FitEnvArgs {}

pub fn run(_args: &FitEnvArgs, _ctx: &Context) -> anyhow::Result<()> {
    anyhow::bail!("`fit-env` is not implemented yet")
}
