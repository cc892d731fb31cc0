//! `pii-bake devices`: what wgpu sees and which backend `auto` picks.

use super::Context;
use crate::backend::gpu::list_adapters;
use crate::backend::{Backend, BackendChoice, NO_ADAPTER_HINT};

pub fn run(ctx: &Context) -> anyhow::Result<()> {
    let adapters = list_adapters();
    if adapters.is_empty() {
        ctx.say(format!("no GPU adapters: {NO_ADAPTER_HINT}"));
    }
    for a in &adapters {
        ctx.say(format!(
            "{}: {} ({}, {}{}) driver {}",
            a.index,
            a.name,
            a.backend,
            a.device_type,
            if a.software { ", software" } else { "" },
            a.driver.trim()
        ));
        ctx.emit("adapter", serde_json::to_value(a)?);
    }
    let auto = Backend::select(BackendChoice::Auto, ctx.adapter.as_deref())?;
    ctx.say(format!("auto backend: {}", auto.describe()));
    ctx.emit("backend", serde_json::json!({ "auto": auto.name(), "describe": auto.describe() }));
    Ok(())
}
