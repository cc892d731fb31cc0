//! What every command receives: the resolved global options (backend choice, output mode), and
//! the ways a command talks to the user (lines, JSON Lines records, progress bars). It lives
//! outside `cli` so the modules that own the work depend on it, not on the command line that
//! dispatches to them (`cli` depends on them, never the reverse).

use std::io::Write;

use crate::backend::{Backend, BackendChoice};

/// What every command receives: the resolved global options. Holds no clap types.
#[derive(Debug, Clone)]
pub struct Context {
    pub backend_choice: BackendChoice,
    pub adapter: Option<String>,
    pub json: bool,
    pub quiet: bool,
    /// `--profile-kernels`: the wgpu backend times every kernel (`GpuContext::set_kernel_profile`).
    pub profile_kernels: bool,
}

impl Context {
    /// Create the compute backend the user asked for.
    pub fn backend(&self) -> anyhow::Result<Backend> {
        let b = Backend::select(self.backend_choice, self.adapter.as_deref())?;
        tracing::info!("backend: {}", b.describe());
        if self.profile_kernels {
            match b.gpu() {
                Some(g) => g.set_kernel_profile(true)?,
                None => tracing::warn!("--profile-kernels times wgpu kernels; the cpu backend has none to time"),
            }
        }
        Ok(b)
    }

    /// Emit one JSON Lines record (only with `--json`). `kind` becomes the `type` field.
    pub fn emit(&self, kind: &str, value: serde_json::Value) {
        if !self.json {
            return;
        }
        let mut obj = match value {
            serde_json::Value::Object(m) => m,
            other => {
                let mut m = serde_json::Map::new();
                m.insert("value".into(), other);
                m
            }
        };
        obj.insert("type".into(), serde_json::Value::String(kind.into()));
        let mut out = std::io::stdout().lock();
        let _ = writeln!(out, "{}", serde_json::Value::Object(obj));
    }

    /// Print a human-readable line on stdout unless `--json` or `--quiet`.
    pub fn say(&self, line: impl AsRef<str>) {
        if !self.json && !self.quiet {
            println!("{}", line.as_ref());
        }
    }

    /// Whether progress is drawn: on a terminal, never with `--json`/`--quiet`.
    fn draws_progress(&self) -> bool {
        use std::io::IsTerminal;
        !self.json && !self.quiet && std::io::stderr().is_terminal()
    }

    /// A progress bar drawn only on a terminal and never with `--json`/`--quiet`.
    pub fn progress(&self, len: u64, what: &str) -> indicatif::ProgressBar {
        if !self.draws_progress() {
            return indicatif::ProgressBar::hidden();
        }
        let pb = indicatif::ProgressBar::new(len);
        pb.set_style(
            indicatif::ProgressStyle::with_template("{msg:>12} [{bar:40}] {pos}/{len} {elapsed_precise} eta {eta}")
                .expect("static template")
                .progress_chars("=> "),
        );
        pb.set_message(what.to_string());
        pb
    }

    /// A spinner for work of unknown length (its message says what is happening; it ticks on
    /// its own through long single calls); drawn only where [`Context::progress`] draws.
    pub fn spinner(&self, what: &str) -> indicatif::ProgressBar {
        if !self.draws_progress() {
            return indicatif::ProgressBar::hidden();
        }
        let pb = indicatif::ProgressBar::new_spinner();
        if let Ok(style) = indicatif::ProgressStyle::with_template("{spinner} {msg} [{elapsed}]") {
            pb.set_style(style);
        }
        pb.set_message(what.to_string());
        pb.enable_steady_tick(std::time::Duration::from_millis(120));
        pb
    }
}

