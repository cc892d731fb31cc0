//! Training stages, losses, schedules, progress, checkpoint/resume.

pub mod hull;
pub mod photo;
pub mod preview;
