//! Training stages, losses, schedules, progress, checkpoint/resume.

pub mod bench;
pub mod cli;
pub mod hull;
pub mod photo;
pub mod preview;
pub mod stage1;
