//! pii-bake: posed photos → relightable production asset.
//!
//! The library holds all the work; `src/main.rs` is a thin CLI over [`cli::main`].
//! See `ARCHITECTURE.md` for the code map and the invariants.

pub mod backend;
pub mod bake;
pub mod cli;
pub mod context;
pub mod eval;
pub mod image_io;
pub mod export;
pub mod mesh;
pub mod nn;
pub mod render;
pub mod scene;
pub mod sg;
pub mod testing;
pub mod train;
pub mod util;
