//! Training stages, losses, schedules, progress, checkpoint/resume.

pub mod bench;
pub mod bench_material;
pub mod blender_check;
pub mod cli;
pub mod coverage;
pub mod hull;
pub mod material;
pub mod multiview;
pub mod photo;
pub mod pose;
pub mod preview;
pub mod relight;
pub mod stage1;
pub mod stage2;
