//! The `eval` command.

use crate::cli::Context;

#[derive(Debug, clap::Args)]
pub struct EvalArgs {}

pub fn run(_args: &EvalArgs, _ctx: &Context) -> anyhow::Result<()> {
    anyhow::bail!("`eval` is not implemented yet")
}
