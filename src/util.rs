//! Small shared helpers: atomic file output, user-facing error kinds, seeded RNG, a parallel
//! reduction whose rounding does not depend on the thread count.

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

/// Check that `dir` can take output files before any heavy work: create it (and its parents) if
/// missing, write a small probe file and remove it. The error names the folder.
pub fn ensure_writable_dir(dir: &Path) -> Result<(), DataError> {
    let dir = if dir.as_os_str().is_empty() { Path::new(".") } else { dir };
    if dir.exists() && !dir.is_dir() {
        return Err(DataError::new(dir, "output folder is not a folder (a file has that name)"));
    }
    fs::create_dir_all(dir).map_err(|e| DataError::new(dir, format!("cannot create output folder: {e}")))?;
    let probe = dir.join(format!(".pii-bake-write-probe.{}.tmp", std::process::id()));
    let result = fs::OpenOptions::new().write(true).create_new(true).open(&probe).and_then(|mut f| {
        f.write_all(b"probe")?;
        f.sync_all()
    });
    let removed = fs::remove_file(&probe);
    result.map_err(|e| DataError::new(dir, format!("output folder is not writable: {e}")))?;
    removed.map_err(|e| DataError::new(dir, format!("output folder: cannot remove the write probe: {e}")))
}

/// [`ensure_writable_dir`] for the folder an output file goes into.
pub fn ensure_writable_parent(file: &Path) -> Result<(), DataError> {
    ensure_writable_dir(file.parent().unwrap_or(Path::new("")))
}

/// Largest JSON (or other text) input the readers accept, in bytes.
pub const MAX_TEXT_BYTES: u64 = 256 << 20;

/// Read a whole file, refusing one larger than `max_bytes` (checked from its size before reading,
/// and again while reading, for files that grow or lie about their size).
pub fn read_bounded(path: &Path, max_bytes: u64) -> Result<Vec<u8>, DataError> {
    use std::io::Read;
    let f = fs::File::open(path).map_err(|e| DataError::new(path, format!("cannot read: {e}")))?;
    let len = f.metadata().map_err(|e| DataError::new(path, format!("cannot read: {e}")))?.len();
    let too_big = |n: u64| DataError::new(path, format!("file is {n} bytes, more than the {max_bytes} bytes this reader accepts"));
    if len > max_bytes {
        return Err(too_big(len));
    }
    let mut out = Vec::with_capacity(len as usize);
    f.take(max_bytes + 1).read_to_end(&mut out).map_err(|e| DataError::new(path, format!("cannot read: {e}")))?;
    if out.len() as u64 > max_bytes {
        return Err(too_big(out.len() as u64));
    }
    Ok(out)
}

/// Read a UTF-8 text file of at most `max_bytes`.
pub fn read_text_bounded(path: &Path, max_bytes: u64) -> Result<String, DataError> {
    String::from_utf8(read_bounded(path, max_bytes)?).map_err(|e| DataError::new(path, format!("not UTF-8 text: {e}")))
}

/// Read and parse a JSON file of at most [`MAX_TEXT_BYTES`] (serde_json bounds nesting depth).
pub fn read_json_value(path: &Path) -> Result<serde_json::Value, DataError> {
    let text = read_text_bounded(path, MAX_TEXT_BYTES)?;
    serde_json::from_str(&text).map_err(|e| DataError::new(path, format!("malformed JSON: {e}")))
}

/// Seeded, portable RNG used everywhere randomness is needed (initialisation, ray sampling, tests).
pub fn rng(seed: u64) -> rand::rngs::StdRng {
    use rand::SeedableRng;
    rand::rngs::StdRng::seed_from_u64(seed)
}

/// Whether two slices hold the same bits (a parallel compare: parameter vectors are megabytes).
pub fn same_bits(a: &[f32], b: &[f32]) -> bool {
    use rayon::prelude::*;
    let (a, b): (&[u32], &[u32]) = (bytemuck::cast_slice(a), bytemuck::cast_slice(b));
    a.len() == b.len() && a.par_chunks(1 << 16).zip(b.par_chunks(1 << 16)).all(|(x, y)| x == y)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fold_ordered_gives_the_same_bits_on_any_thread_count() {
        // Values over 12 orders of magnitude: any change in the order of the additions shows in
        // the f32 sum's last bits.
        let v: Vec<f32> =
            (0..100_000u32).map(|i| (i as f32 * 0.37).sin() * 10f32.powi((i % 13) as i32 - 6)).collect();
        let sum = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| fold_ordered(v.len(), 777, || 0.0f32, |a, i| *a += v[i], |a, b| *a += b))
        };
        // The same additions written out: each group from zero in order, the groups in order.
        let mut want = 0.0f32;
        for g in v.chunks(777) {
            want += g.iter().fold(0.0f32, |a, &x| a + x);
        }
        for t in [1, 2, 3, 7, 16] {
            assert_eq!(sum(t).to_bits(), want.to_bits(), "{t} threads");
        }
        assert_eq!(fold_ordered(0, 8, || 5.0f32, |a, _| *a += 1.0, |a, b| *a += b), 5.0, "no items: init()");
    }

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

    #[test]
    fn ensure_writable_dir_creates_probes_and_names_the_folder() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("a").join("b");
        ensure_writable_dir(&out).unwrap();
        assert!(out.is_dir());
        assert_eq!(fs::read_dir(&out).unwrap().count(), 0, "probe left behind");
        let blocker = dir.path().join("file");
        fs::write(&blocker, b"x").unwrap();
        let err = ensure_writable_dir(&blocker).unwrap_err().to_string();
        assert!(err.contains("file") && err.contains("not a folder"), "{err}");
        let err = ensure_writable_dir(&blocker.join("sub")).unwrap_err().to_string();
        assert!(err.contains("file"), "{err}");
        ensure_writable_parent(&out.join("x.json")).unwrap();
    }

    #[test]
    fn bounded_reads_refuse_large_files() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("big.json");
        fs::write(&p, vec![b' '; 100]).unwrap();
        let err = read_bounded(&p, 10).unwrap_err().to_string();
        assert!(err.contains("big.json") && err.contains("100 bytes"), "{err}");
        assert_eq!(read_bounded(&p, 100).unwrap().len(), 100);
    }
}

/// A parallel fold over `0..n` whose result is bit-identical on any thread count.
///
/// rayon's `fold`/`reduce` split the work where threads steal it, so a float sum's order (and
/// its last bits) changes from run to run and from machine to machine; a seeded training run
/// would then not repeat itself. Here the items are cut into fixed groups of `group`, each group
/// is folded in index order (groups run in parallel), and the group results are merged in index
/// order: the same sequence of additions whatever the pool.
pub fn fold_ordered<A: Send>(
    n: usize,
    group: usize,
    init: impl Fn() -> A + Sync + Send,
    step: impl Fn(&mut A, usize) + Sync + Send,
    mut merge: impl FnMut(&mut A, A),
) -> A {
    use rayon::prelude::*;
    let group = group.max(1);
    let parts: Vec<A> = (0..n.div_ceil(group))
        .into_par_iter()
        .map(|g| {
            let mut a = init();
            for i in g * group..((g + 1) * group).min(n) {
                step(&mut a, i);
            }
            a
        })
        .collect();
    let mut parts = parts.into_iter();
    let mut acc = parts.next().unwrap_or_else(&init);
    for p in parts {
        merge(&mut acc, p);
    }
    acc
}

/// Keep freed heap memory in the process instead of returning it to the kernel.
///
/// Training allocates and frees tens of MB every step (a hash grid's dense parameter gradient is
/// `levels · 2^log2_table · F` values). glibc serves blocks that large with a fresh `mmap` and
/// unmaps them on `free`, so every step page-faults each page again (the scatter reads a page
/// before writing it: two faults and a cross-core TLB flush per page). Serving every block from
/// the heap (no mmap) and never trimming it lets the blocks be reused; peak memory is unchanged.
/// Measured on the 2-core CPU box, stage 1 on the Ethiopian head (2^19 tables): 2.5 -> 4.0 it/s,
/// identical results.
/// Returns whether both settings were accepted (always false off glibc, where it does nothing).
pub fn keep_freed_memory() -> bool {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: mallopt only changes allocator parameters; called before heavy allocation.
        unsafe {
            // The largest threshold glibc accepts is half its maximum heap size (32 MiB on 64-bit);
            // M_MMAP_MAX = 0 then keeps every block on the heap, whatever its size.
            let a = libc::mallopt(libc::M_MMAP_MAX, 0);
            let b = libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX);
            a == 1 && b == 1
        }
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    {
        false
    }
}

#[cfg(all(test, target_os = "linux", target_env = "gnu"))]
mod alloc_tests {
    #[test]
    fn glibc_accepts_the_allocator_settings() {
        assert!(super::keep_freed_memory());
        // Large blocks still allocate, zeroed, and free.
        let v = vec![0f32; 50 << 20];
        assert!(v.iter().step_by(4096).all(|&x| x == 0.0));
    }
}

/// The calling thread's CPU time in seconds (None where the platform has no per-thread clock),
/// for host costs that other threads (a software adapter's, rayon's) would blur in wall time.
/// `CLOCK_THREAD_CPUTIME_ID` counts up to the moment it is read; `/proc/thread-self/schedstat`
/// (the fallback) only advances at scheduler ticks, so a millisecond of work could read as none.
pub fn thread_cpu_seconds() -> Option<f64> {
    #[cfg(unix)]
    {
        let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
        // SAFETY: clock_gettime writes one timespec into the valid, exclusively borrowed `ts`.
        if unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) } == 0 {
            return Some(ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9);
        }
    }
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    Some(s.split_whitespace().next()?.parse::<f64>().ok()? * 1e-9)
}

#[cfg(all(test, target_os = "linux"))]
mod clock_tests {
    #[test]
    fn the_thread_cpu_clock_advances_within_a_millisecond_of_work() {
        // The per-launch benchmark times about a millisecond of host work; a clock that advances
        // only at scheduler ticks (4 ms) read it as none. Over the first millisecond of CPU time
        // (by the clock itself, so a loaded machine does not matter) a fine clock takes many values.
        let a = super::thread_cpu_seconds().expect("Linux has a per-thread clock");
        let (t, mut last, mut values) = (std::time::Instant::now(), a, 0);
        while last - a < 1e-3 && t.elapsed() < std::time::Duration::from_secs(5) {
            let now = super::thread_cpu_seconds().unwrap();
            if now != last {
                values += 1;
                last = now;
            }
        }
        assert!(values >= 20, "the thread clock took {values} values over {} s of CPU time", last - a);
    }
}
