//! Training stages, losses, schedules, progress, checkpoint/resume.
