//! Small shared helpers: atomic file output, user-facing error kinds, seeded RNG.

use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

/// An error caused by the user's data or environment (bad file, missing adapter...),
/// as opposed to a usage error (bad flags) or a bug. Maps to exit code 2 at the CLI.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {problem}")]
pub struct DataError {
    pub path: PathBuf,
    pub problem: String,
}

impl DataError {
    pub fn new(path: impl Into<PathBuf>, problem: impl Into<String>) -> Self {
        Self { path: path.into(), problem: problem.into() }
    }
}

/// The temporary name an output is written under before it is renamed into place.
pub fn temp_name(path: &Path) -> PathBuf {
    let file = path.file_name().map(|f| f.to_string_lossy().into_owned()).unwrap_or_default();
    path.with_file_name(format!(".{file}.{}.tmp", std::process::id()))
}

/// Write `bytes` to `path` atomically: a temporary file in the same folder, synced, then renamed.
/// A crash never leaves a half-written file under the final name.
pub fn atomic_write(path: &Path, bytes: &[u8]) -> Result<(), DataError> {
    atomic_write_with(path, |f| f.write_all(bytes))
}

/// Like [`atomic_write`], but the content is produced by `write` into the temporary file.
pub fn atomic_write_with(
    path: &Path,
    write: impl FnOnce(&mut fs::File) -> std::io::Result<()>,
) -> Result<(), DataError> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        fs::create_dir_all(dir)
            .map_err(|e| DataError::new(dir, format!("cannot create output folder: {e}")))?;
    }
    let tmp = temp_name(path);
    let result = (|| {
        let mut f = fs::File::create(&tmp)?;
        write(&mut f)?;
        f.sync_all()?;
        fs::rename(&tmp, path)
    })();
    result.map_err(|e| {
        let _ = fs::remove_file(&tmp);
        DataError::new(path, format!("cannot write: {e}"))
    })
}

/// Seeded, portable RNG used everywhere randomness is needed (initialisation, ray sampling, tests).
pub fn rng(seed: u64) -> rand::rngs::StdRng {
    use rand::SeedableRng;
    rand::rngs::StdRng::seed_from_u64(seed)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn atomic_write_leaves_no_temp_and_reports_unwritable_folder() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.bin");
        atomic_write(&p, b"hello").unwrap();
        assert_eq!(fs::read(&p).unwrap(), b"hello");
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1, "temporary file left behind");
        // A file where a folder should be: the error names the path.
        let blocker = dir.path().join("file");
        fs::write(&blocker, b"x").unwrap();
        let err = atomic_write(&blocker.join("out.glb"), b"x").unwrap_err();
        assert!(err.to_string().contains("file"), "{err}");
    }
}
