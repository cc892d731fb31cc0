//! The `bench env` command.

use crate::cli::Context;

#[derive(Debug, clap::Args)]
pub struct BenchEnvArgs {}

pub fn run(_args: &BenchEnvArgs, _ctx: &Context) -> anyhow::Result<()> {
    anyhow::bail!("`bench env` is not implemented yet")
}
