//! Damaged inputs never take the process down.
//!
//! A small seed corpus per format the tool reads (scene files, images, masks, latlong maps, SG
//! JSON, checkpoints), deterministic seeded mutations (byte flips, truncation, insertion, numeric
//! fields replaced by nan / inf / 1e308 / -0 / huge counts, structure-aware edits of PNG chunks,
//! EXR header attributes, npy headers inside npz archives, safetensors headers), each case run as
//! a subprocess (an abort is only visible from outside) with a time limit. Every case must:
//! exit with 0, 1 or 2; print no panic or allocation failure; on failure name the damaged file;
//! leave no temporary or partial output behind.
//!
//! The test command runs [`DEFAULT_CASES`] cases on two threads. `scripts/fuzz.sh` (the ignored
//! `fuzz_large` test, `PII_FUZZ_CASES`, `PII_FUZZ_SEED`) runs thousands and prints the summary
//! table. Checkpoints have no CLI reader yet: their cases run `ParamStore::load` in a child
//! process of this test binary (`checkpoint_child`), the same subprocess contract.

use std::collections::BTreeMap;
use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use glam::{DMat3, DQuat, DVec3};
use pii_bake::image_io::write_exr_rgb;

/// Cases in the normal test command.
const DEFAULT_CASES: usize = 600;
/// Per-case wall-clock limit (debug build; a case normally takes well under a second).
const CASE_TIMEOUT: Duration = Duration::from_secs(60);

// ---------------------------------------------------------------------------------------------
// Deterministic randomness (splitmix64).

struct Rng(u64);

impl Rng {
    fn new(seed: u64) -> Self {
        Rng(seed ^ 0x9E37_79B9_7F4A_7C15)
    }
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: usize) -> usize {
        if n == 0 {
            0
        } else {
            (self.next() % n as u64) as usize
        }
    }
    fn pick<'a, T>(&mut self, v: &'a [T]) -> &'a T {
        &v[self.below(v.len())]
    }
}

// ---------------------------------------------------------------------------------------------
// Mutations.

const TEXT_NUMBERS: &[&str] = &[
    "nan", "NaN", "inf", "-inf", "Infinity", "1e308", "-1e308", "1e309", "-0", "0", "-1", "1e-320", "0.5",
    "18446744073709551616", "99999999999", "4294967295", "2147483648", "65537", "1e30", "3",
];
const F64S: &[f64] = &[f64::NAN, f64::INFINITY, f64::NEG_INFINITY, 1e308, -1e308, -0.0, 0.0, 1e-310, 1e30];
const U64S: &[u64] = &[u64::MAX, 1 << 62, 1 << 40, 1 << 32, 0x7fff_ffff, 0, 1 << 20];
const U32S: &[u32] = &[u32::MAX, i32::MAX as u32, i32::MIN as u32, 0x4000_0000, 65536, 65535, 0, 1 << 20];

fn flip(b: &mut [u8], rng: &mut Rng) {
    if b.is_empty() {
        return;
    }
    for _ in 0..1 + rng.below(8) {
        let i = rng.below(b.len());
        b[i] ^= 1 + rng.below(255) as u8;
    }
}

fn truncate(b: &mut Vec<u8>, rng: &mut Rng) {
    let n = rng.below(b.len().max(1));
    b.truncate(n);
}

fn insert(b: &mut Vec<u8>, rng: &mut Rng) {
    let at = rng.below(b.len() + 1);
    let n = 1 + rng.below(64);
    let bytes: Vec<u8> = (0..n).map(|_| rng.next() as u8).collect();
    b.splice(at..at, bytes);
}

/// Positions (start, end) of numeric tokens in text.
fn number_spans(b: &[u8]) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    let mut i = 0;
    while i < b.len() {
        let c = b[i];
        let starts = c.is_ascii_digit() || (c == b'-' && b.get(i + 1).is_some_and(u8::is_ascii_digit));
        let prev_ok = i == 0 || !(b[i - 1].is_ascii_alphanumeric() || b[i - 1] == b'_');
        if starts && prev_ok {
            let s = i;
            i += 1;
            while i < b.len() && (b[i].is_ascii_digit() || matches!(b[i], b'.' | b'e' | b'E' | b'+' | b'-')) {
                i += 1;
            }
            out.push((s, i));
        } else {
            i += 1;
        }
    }
    out
}

/// Replace 1-3 numeric tokens of a text with special values.
fn replace_numbers(b: &mut Vec<u8>, rng: &mut Rng) -> bool {
    let spans = number_spans(b);
    if spans.is_empty() {
        return false;
    }
    let mut chosen: Vec<(usize, usize)> = (0..1 + rng.below(3)).map(|_| *rng.pick(&spans)).collect();
    chosen.sort();
    chosen.dedup();
    for (s, e) in chosen.into_iter().rev() {
        let v = rng.pick(TEXT_NUMBERS).as_bytes().to_vec();
        b.splice(s..e, v);
    }
    true
}

/// Overwrite a little-endian word at a random offset within `range` with a special value.
fn replace_word(b: &mut [u8], range: std::ops::Range<usize>, rng: &mut Rng) {
    let range = range.start.min(b.len())..range.end.min(b.len());
    match rng.below(3) {
        0 if range.len() >= 8 => {
            let at = range.start + rng.below(range.len() - 7);
            b[at..at + 8].copy_from_slice(&rng.pick(F64S).to_le_bytes());
        }
        1 if range.len() >= 8 => {
            let at = range.start + rng.below(range.len() - 7);
            b[at..at + 8].copy_from_slice(&rng.pick(U64S).to_le_bytes());
        }
        _ if range.len() >= 4 => {
            let at = range.start + rng.below(range.len() - 3);
            b[at..at + 4].copy_from_slice(&rng.pick(U32S).to_le_bytes());
        }
        _ => {}
    }
}

/// Overwrite an aligned f64 slot in `range` (numeric arrays) with a special value.
fn replace_f64_slot(b: &mut [u8], range: std::ops::Range<usize>, rng: &mut Rng) {
    let slots = range.len() / 8;
    if slots == 0 || range.end > b.len() {
        return;
    }
    let at = range.start + 8 * rng.below(slots);
    b[at..at + 8].copy_from_slice(&rng.pick(F64S).to_le_bytes());
}

fn crc32(bytes: &[u8]) -> u32 {
    let mut h = crc32fast::Hasher::new();
    h.update(bytes);
    h.finalize()
}

/// Recompute every PNG chunk CRC (so a mutation reaches the decoder, not only the CRC check).
fn fix_png_crcs(b: &mut [u8]) {
    let mut p = 8;
    while p + 12 <= b.len() {
        let len = u32::from_be_bytes(b[p..p + 4].try_into().unwrap()) as usize;
        let Some(end) = (p + 8).checked_add(len).filter(|e| e + 4 <= b.len()) else { break };
        let c = crc32(&b[p + 4..end]);
        b[end..end + 4].copy_from_slice(&c.to_be_bytes());
        p = end + 4;
    }
}

/// Find `needle` in `hay`.
fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}

/// End of an EXR header (the byte after the empty attribute name ending the last header),
/// approximated as the first offset table start: the first "\0\0" after "lineOrder".
fn exr_header_end(b: &[u8]) -> usize {
    find(b, b"lineOrder").map(|p| p + 40).unwrap_or(64).min(b.len())
}

/// Set an EXR's data window to (0, 0)-(`xmax`, `ymax`) and keep a `chunkCount` attribute (the exr
/// crate writes one; OpenEXR and Blender do not) consistent with it, as a damaged header that
/// still parses would be.
fn patch_exr_window(b: &mut [u8], xmax: i32, ymax: i32) {
    let attr = b"dataWindow\0box2i\0";
    let Some(p) = find(b, attr).map(|p| p + attr.len() + 4).filter(|p| p + 16 <= b.len()) else { return };
    for (i, v) in [0i32, 0, xmax, ymax].iter().enumerate() {
        b[p + 4 * i..p + 4 * i + 4].copy_from_slice(&v.to_le_bytes());
    }
    let lines = find(b, b"compression\0compression\0")
        .and_then(|c| b.get(c + 28).copied())
        .map(|c| match c {
            3 | 5 => 16i64,
            4 | 6 | 7 | 8 => 32,
            9 => 256,
            _ => 1,
        })
        .unwrap_or(1);
    let chunks = (ymax as i64 + 1 + lines - 1) / lines;
    let attr = b"chunkCount\0int\0";
    if let Some(c) = find(b, attr).map(|c| c + attr.len() + 4).filter(|c| c + 4 <= b.len()) {
        b[c..c + 4].copy_from_slice(&(chunks.min(i32::MAX as i64) as i32).to_le_bytes());
    }
}

/// What a file is, for structure-aware mutations.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Kind {
    Json,
    Text,
    Png,
    Jpeg,
    Exr,
    Npy,
    Npz,
    ColmapBin,
    Safetensors,
}

/// Mutate `seed` (the bytes of a file of `kind`); returns the bytes and the mutation's name.
fn mutate(kind: Kind, seed: &[u8], rng: &mut Rng) -> (Vec<u8>, &'static str) {
    let mut b = seed.to_vec();
    let generic = |b: &mut Vec<u8>, rng: &mut Rng| -> &'static str {
        match rng.below(3) {
            0 => {
                flip(b, rng);
                "flip"
            }
            1 => {
                truncate(b, rng);
                "truncate"
            }
            _ => {
                insert(b, rng);
                "insert"
            }
        }
    };
    // About half the cases are structure-aware, the rest generic.
    if rng.below(2) == 0 {
        let name = generic(&mut b, rng);
        return (b, name);
    }
    let name = match kind {
        Kind::Json | Kind::Text => {
            if replace_numbers(&mut b, rng) {
                "number"
            } else {
                generic(&mut b, rng)
            }
        }
        Kind::Png => {
            // IHDR width/height (bytes 16..24) or any chunk field, CRCs fixed afterwards.
            if rng.below(2) == 0 && b.len() >= 24 {
                let at = 16 + 4 * rng.below(2);
                b[at..at + 4].copy_from_slice(&rng.pick(U32S).to_be_bytes());
            } else {
                flip(&mut b, rng);
            }
            fix_png_crcs(&mut b);
            "png-field"
        }
        Kind::Jpeg => {
            // SOF0 height/width (after FFC0, length, precision).
            if let Some(p) = find(&b, &[0xFF, 0xC0]).filter(|p| p + 9 <= b.len()) {
                let at = p + 5 + 2 * rng.below(2);
                let v = *rng.pick(&[0u16, 1, 65535, 40000, 16384]);
                b[at..at + 2].copy_from_slice(&v.to_be_bytes());
                "jpeg-sof"
            } else {
                generic(&mut b, rng)
            }
        }
        Kind::Exr => {
            let end = exr_header_end(&b);
            match rng.below(3) {
                0 => {
                    if rng.below(2) == 0 {
                        // a consistent-looking but huge (or merely large) data window
                        let big = [16i32, 4000, 65535, 100_000, 1_000_000, i32::MAX / 2 - 1];
                        patch_exr_window(&mut b, *rng.pick(&big), *rng.pick(&big));
                        "exr-window"
                    } else {
                        // one dataWindow / displayWindow coordinate
                        let attr: &[u8] = if rng.below(2) == 0 { b"dataWindow\0box2i\0" } else { b"displayWindow\0box2i\0" };
                        if let Some(p) = find(&b, attr) {
                            let at = p + attr.len() + 4 + 4 * rng.below(4);
                            if at + 4 <= b.len() {
                                b[at..at + 4].copy_from_slice(&rng.pick(U32S).to_le_bytes());
                            }
                        }
                        "exr-window-word"
                    }
                }
                1 => {
                    replace_word(&mut b, 8..end, rng);
                    "exr-header-word"
                }
                _ => {
                    // the offset table and the chunks (sizes, pixel values of an uncompressed map)
                    let len = b.len();
                    replace_word(&mut b, end..len, rng);
                    "exr-body-word"
                }
            }
        }
        Kind::Npy => {
            let hdr_end = find(&b, b"\n").map(|p| p + 1).unwrap_or(b.len());
            if rng.below(2) == 0 {
                // the header dict: shape, descr
                let mut h = b[..hdr_end].to_vec();
                replace_numbers(&mut h, rng);
                h.extend_from_slice(&b[hdr_end..]);
                b = h;
                "npy-header"
            } else {
                let len = b.len();
                replace_f64_slot(&mut b, hdr_end..len, rng);
                "npy-value"
            }
        }
        Kind::Npz => {
            // Mutate one array inside and re-zip, so the npy reader sees the damage.
            let mut entries = unzip_stored(&b);
            if entries.is_empty() {
                generic(&mut b, rng)
            } else {
                let i = rng.below(entries.len());
                let (inner, _) = mutate(Kind::Npy, &entries[i].1, rng);
                entries[i].1 = inner;
                b = zip_stored(&entries);
                "npz-array"
            }
        }
        Kind::ColmapBin => {
            match rng.below(2) {
                0 => {
                    // the record count
                    b[..8.min(seed.len())].copy_from_slice(&rng.pick(U64S).to_le_bytes()[..8.min(seed.len())]);
                    "colmap-count"
                }
                _ => {
                    let len = b.len();
                    replace_word(&mut b, 8..len, rng);
                    "colmap-field"
                }
            }
        }
        Kind::Safetensors => {
            if b.len() < 8 {
                return (b, "tiny");
            }
            let n = u64::from_le_bytes(b[..8].try_into().unwrap()) as usize;
            match rng.below(3) {
                0 => {
                    b[..8].copy_from_slice(&rng.pick(U64S).to_le_bytes());
                    "st-header-len"
                }
                1 if 8 + n <= b.len() => {
                    // shapes, offsets or metadata numbers in the JSON header, length prefix fixed
                    let mut h = b[8..8 + n].to_vec();
                    replace_numbers(&mut h, rng);
                    let mut out = (h.len() as u64).to_le_bytes().to_vec();
                    out.extend_from_slice(&h);
                    out.extend_from_slice(&b[8 + n..]);
                    b = out;
                    "st-header-number"
                }
                _ => {
                    let len = b.len();
                    replace_f64_slot(&mut b, (8 + n).min(len)..len, rng);
                    "st-value"
                }
            }
        }
    };
    (b, name)
}

// ---------------------------------------------------------------------------------------------
// Seed writers.

/// An npy v1 array of little-endian f64.
fn npy_f64(shape: &[usize], values: &[f64]) -> Vec<u8> {
    let shape_s = match shape {
        [n] => format!("({n},)"),
        s => format!("({})", s.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", ")),
    };
    let mut header = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': {shape_s}, }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for v in values {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

/// A zip archive with stored (uncompressed) entries, as numpy's `savez` writes.
fn zip_stored(entries: &[(String, Vec<u8>)]) -> Vec<u8> {
    let mut out = Vec::new();
    let mut central = Vec::new();
    for (name, data) in entries {
        let offset = out.len() as u32;
        let crc = crc32(data);
        let local = |v: &mut Vec<u8>, sig: u32| {
            v.extend_from_slice(&sig.to_le_bytes());
        };
        local(&mut out, 0x0403_4b50);
        for x in [20u16, 0, 0, 0, 0] {
            out.extend_from_slice(&x.to_le_bytes());
        }
        for x in [crc, data.len() as u32, data.len() as u32] {
            out.extend_from_slice(&x.to_le_bytes());
        }
        out.extend_from_slice(&(name.len() as u16).to_le_bytes());
        out.extend_from_slice(&0u16.to_le_bytes());
        out.extend_from_slice(name.as_bytes());
        out.extend_from_slice(data);

        central.extend_from_slice(&0x0201_4b50u32.to_le_bytes());
        for x in [20u16, 20, 0, 0, 0, 0] {
            central.extend_from_slice(&x.to_le_bytes());
        }
        for x in [crc, data.len() as u32, data.len() as u32] {
            central.extend_from_slice(&x.to_le_bytes());
        }
        for x in [name.len() as u16, 0, 0, 0, 0] {
            central.extend_from_slice(&x.to_le_bytes());
        }
        central.extend_from_slice(&0u32.to_le_bytes());
        central.extend_from_slice(&offset.to_le_bytes());
        central.extend_from_slice(name.as_bytes());
    }
    let cd_offset = out.len() as u32;
    out.extend_from_slice(&central);
    out.extend_from_slice(&0x0605_4b50u32.to_le_bytes());
    for x in [0u16, 0, entries.len() as u16, entries.len() as u16] {
        out.extend_from_slice(&x.to_le_bytes());
    }
    out.extend_from_slice(&(central.len() as u32).to_le_bytes());
    out.extend_from_slice(&cd_offset.to_le_bytes());
    out.extend_from_slice(&0u16.to_le_bytes());
    out
}

/// The entries of an archive written by [`zip_stored`] (local headers walked; empty if damaged).
fn unzip_stored(b: &[u8]) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    let mut p = 0;
    while p + 30 <= b.len() && b[p..p + 4] == 0x0403_4b50u32.to_le_bytes() {
        let size = u32::from_le_bytes(b[p + 18..p + 22].try_into().unwrap()) as usize;
        let nlen = u16::from_le_bytes(b[p + 26..p + 28].try_into().unwrap()) as usize;
        let elen = u16::from_le_bytes(b[p + 28..p + 30].try_into().unwrap()) as usize;
        let start = p + 30 + nlen + elen;
        if start + size > b.len() {
            return Vec::new();
        }
        out.push((String::from_utf8_lossy(&b[p + 30..p + 30 + nlen]).into_owned(), b[start..start + size].to_vec()));
        p = start + size;
    }
    out
}

/// An object-centred test image: a bright disc on black, `w`×`h`, RGB (or RGBA with the disc opaque).
fn disc(w: usize, h: usize, channels: usize) -> Vec<f32> {
    let mut px = vec![0.0f32; w * h * channels];
    for y in 0..h {
        for x in 0..w {
            let (dx, dy) = (x as f32 + 0.5 - w as f32 / 2.0, y as f32 + 0.5 - h as f32 / 2.0);
            if dx * dx + dy * dy < (w.min(h) as f32 * 0.3).powi(2) {
                let p = &mut px[(y * w + x) * channels..(y * w + x + 1) * channels];
                p.fill(0.7);
            }
        }
    }
    px
}

fn png_bytes(w: usize, h: usize, channels: usize, data: &[f32]) -> Vec<u8> {
    pii_bake::image_io::encode_png8(w, h, channels, data, true).unwrap()
}

fn jpeg_bytes(w: usize, h: usize) -> Vec<u8> {
    let px: Vec<u8> = disc(w, h, 3).iter().map(|v| (v * 255.0) as u8).collect();
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 90)
        .encode(&px, w as u32, h as u32, image::ExtendedColorType::Rgb8)
        .unwrap();
    out
}

fn exr_zip_bytes(w: usize, h: usize, rgb: &[f32]) -> Vec<u8> {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("a.exr");
    write_exr_rgb(&p, w, h, rgb).unwrap();
    std::fs::read(p).unwrap()
}

/// An uncompressed scanline RGB EXR (pixel values reachable by byte-level mutations).
fn exr_raw_bytes(w: usize, h: usize, rgb: &[f32]) -> Vec<u8> {
    use exr::prelude::*;
    let channels = SpecificChannels::rgb(|p: Vec2<usize>| {
        let i = (p.y() * w + p.x()) * 3;
        (rgb[i], rgb[i + 1], rgb[i + 2])
    });
    let encoding = Encoding { compression: Compression::Uncompressed, blocks: Blocks::ScanLines, line_order: LineOrder::Increasing };
    let layer = Layer::new((w, h), LayerAttributes::named("rgb"), encoding, channels);
    let mut out = std::io::Cursor::new(Vec::new());
    Image::from_layer(layer).write().to_buffered(&mut out).unwrap();
    out.into_inner()
}

/// A latlong test map: a warm sky lobe plus a dim floor.
fn latlong(w: usize, h: usize) -> Vec<f32> {
    let mut rgb = vec![0.0f32; w * h * 3];
    for y in 0..h {
        for x in 0..w {
            let sky = (1.0 - y as f32 / h as f32).powi(2);
            let sun = if (x * 4 / w, y * 4 / h) == (1, 0) { 20.0 } else { 0.0 };
            rgb[(y * w + x) * 3..(y * w + x) * 3 + 3].copy_from_slice(&[0.1 + sky + sun, 0.1 + sky * 0.9 + sun, 0.1 + sky * 0.7]);
        }
    }
    rgb
}

/// Camera-to-world rotation (OpenCV axes) of a camera at `c` looking at the origin, world +Z up.
fn look_at(c: DVec3) -> DMat3 {
    let z = (-c).normalize();
    let x = z.cross(DVec3::Z).normalize();
    let y = z.cross(x);
    DMat3::from_cols(x, y, z)
}

/// Camera centres on a ring around the origin.
fn ring(n: usize) -> Vec<DVec3> {
    (0..n)
        .map(|i| {
            let a = i as f64 * std::f64::consts::TAU / n as f64;
            DVec3::new(3.0 * a.cos(), 3.0 * a.sin(), 0.8)
        })
        .collect()
}

/// Small scene images: `n` 16×16 PNGs of a disc (the object at the origin, seen by `ring`).
const SIDE: usize = 16;
const FOCAL: f64 = 20.0;

fn example_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/example")
}

/// A seed: the files of a case folder, which of them is mutated, its kind, and how to run the tool.
#[derive(Clone)]
struct Seed {
    format: &'static str,
    files: Vec<(PathBuf, Vec<u8>)>,
    target: PathBuf,
    kind: Kind,
    run: Run,
}

#[derive(Clone, Copy, Debug)]
enum Run {
    /// `pii-bake info <case>`
    Info,
    /// `pii-bake fit-env <target> --out <case>/out ...`
    FitEnv,
    /// `pii-bake eval --gt <case>/gt --pred <case>/pred --out <case>/out/metrics.json ...`
    Eval,
    /// `pii-bake export --analytic sphere --env-json <target> --out <case>/out ...`
    ExportEnvJson,
    /// this test binary's `checkpoint_child` (ParamStore::load + config)
    Checkpoint,
    /// this test binary's `checkpoint_child` reading a config JSON file
    ConfigJson,
}

/// A transforms frame: image path, camera-to-world rows, optional mask path.
type Frame = (String, [[f64; 4]; 4], Option<String>);

fn transforms_json(frames: &[Frame], extra_top: &str) -> Vec<u8> {
    let fr: Vec<String> = frames
        .iter()
        .map(|(fp, m, mask)| {
            let rows: Vec<String> = m.iter().map(|r| format!("[{}, {}, {}, {}]", r[0], r[1], r[2], r[3])).collect();
            let mask = mask.as_ref().map(|m| format!(", \"mask_path\": \"{m}\"")).unwrap_or_default();
            format!("    {{\"file_path\": \"{fp}\"{mask}, \"transform_matrix\": [{}]}}", rows.join(", "))
        })
        .collect();
    format!("{{\n  \"camera_angle_x\": 0.7{extra_top},\n  \"frames\": [\n{}\n  ]\n}}\n", fr.join(",\n")).into_bytes()
}

/// OpenGL camera-to-world rows for a ring camera.
fn gl_matrix(c: DVec3) -> [[f64; 4]; 4] {
    let r = look_at(c);
    let (x, y, z) = (r.x_axis, -r.y_axis, -r.z_axis);
    [[x.x, y.x, z.x, c.x], [x.y, y.y, z.y, c.y], [x.z, y.z, z.z, c.z], [0.0, 0.0, 0.0, 1.0]]
}

fn seeds() -> Vec<Seed> {
    let ex = example_dir();
    let read = |p: &str| std::fs::read(ex.join(p)).unwrap_or_else(|e| panic!("{p}: {e}"));
    let mut out = Vec::new();
    let small_png = png_bytes(SIDE, SIDE, 4, &disc(SIDE, SIDE, 4));
    let small_rgb_png = png_bytes(SIDE, SIDE, 3, &disc(SIDE, SIDE, 3));
    let mask_png = png_bytes(SIDE, SIDE, 1, &disc(SIDE, SIDE, 1).iter().map(|v| if *v > 0.0 { 1.0 } else { 0.0 }).collect::<Vec<_>>());
    let cams = ring(3);

    // transforms.json from the example: its first two frames and their images, with scene.json.
    let full: serde_json::Value = serde_json::from_slice(&read("transforms_train.json")).unwrap();
    let mut two = full.clone();
    two["frames"] = serde_json::Value::Array(full["frames"].as_array().unwrap()[..2].to_vec());
    let example_files = vec![
        (PathBuf::from("transforms_train.json"), serde_json::to_vec_pretty(&two).unwrap()),
        (PathBuf::from("scene.json"), read("scene.json")),
        (PathBuf::from("train/r_000.png"), read("train/r_000.png")),
        (PathBuf::from("train/r_001.png"), read("train/r_001.png")),
    ];
    for (format, target, kind) in [
        ("transforms.json", "transforms_train.json", Kind::Json),
        ("scene.json", "scene.json", Kind::Json),
        ("png image", "train/r_000.png", Kind::Png),
    ] {
        out.push(Seed { format, files: example_files.clone(), target: target.into(), kind, run: Run::Info });
    }

    // nerfstudio transforms.json with intrinsics, distortion, masks (PNG) and a JPEG / EXR image.
    let frames: Vec<Frame> = cams
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let img = match i {
                0 => "img_0.jpg".to_string(),
                1 => "img_1.exr".to_string(),
                _ => format!("img_{i}.png"),
            };
            (img, gl_matrix(*c), Some(format!("mask_{i}.{}", if i == 1 { "exr" } else { "png" })))
        })
        .collect();
    let ns = transforms_json(
        &frames,
        &format!(", \"fl_x\": {FOCAL}, \"fl_y\": {FOCAL}, \"cx\": 8.0, \"cy\": 8.0, \"w\": {SIDE}, \"h\": {SIDE}, \"k1\": 0.01, \"p1\": 0.001"),
    );
    let mask_exr = exr_zip_bytes(SIDE, SIDE, &disc(SIDE, SIDE, 3).iter().map(|v| if *v > 0.0 { 1.0 } else { 0.0 }).collect::<Vec<_>>());
    let ns_files = vec![
        (PathBuf::from("transforms.json"), ns),
        (PathBuf::from("img_0.jpg"), jpeg_bytes(SIDE, SIDE)),
        (PathBuf::from("img_1.exr"), exr_raw_bytes(SIDE, SIDE, &disc(SIDE, SIDE, 3))),
        (PathBuf::from("img_2.png"), small_rgb_png.clone()),
        (PathBuf::from("mask_0.png"), mask_png.clone()),
        (PathBuf::from("mask_1.exr"), mask_exr),
        (PathBuf::from("mask_2.png"), mask_png.clone()),
    ];
    for (format, target, kind) in [
        ("nerfstudio transforms.json", "transforms.json", Kind::Json),
        ("jpeg image", "img_0.jpg", Kind::Jpeg),
        ("exr image", "img_1.exr", Kind::Exr),
        ("png mask", "mask_0.png", Kind::Png),
        ("exr mask", "mask_1.exr", Kind::Exr),
    ] {
        out.push(Seed { format, files: ns_files.clone(), target: target.into(), kind, run: Run::Info });
    }

    // IDR cameras_sphere.npz + image/ + mask/.
    let k = DMat3::from_cols(DVec3::new(FOCAL, 0.0, 0.0), DVec3::new(0.0, FOCAL, 0.0), DVec3::new(7.5, 7.5, 1.0));
    let mut entries = Vec::new();
    let mut idr_files = Vec::new();
    for (i, c) in cams.iter().enumerate() {
        let r_cw = look_at(*c).transpose();
        let t = -(r_cw * *c);
        let p = k * r_cw;
        let kt = k * t;
        let mut m = [0.0f64; 16];
        for row in 0..3 {
            for col in 0..3 {
                m[row * 4 + col] = p.col(col)[row];
            }
            m[row * 4 + 3] = kt[row];
        }
        m[15] = 1.0;
        entries.push((format!("world_mat_{i}.npy"), npy_f64(&[4, 4], &m)));
        entries.push((format!("scale_mat_{i}.npy"), npy_f64(&[4, 4], &[1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0])));
        idr_files.push((PathBuf::from(format!("image/{i:03}.png")), small_rgb_png.clone()));
        idr_files.push((PathBuf::from(format!("mask/{i:03}.png")), mask_png.clone()));
    }
    idr_files.push((PathBuf::from("cameras_sphere.npz"), zip_stored(&entries)));
    out.push(Seed { format: "cameras_sphere.npz", files: idr_files, target: "cameras_sphere.npz".into(), kind: Kind::Npz, run: Run::Info });

    // LLFF poses_bounds.npy + images/.
    let mut rows = Vec::new();
    let mut llff_files = Vec::new();
    for (i, c) in cams.iter().enumerate() {
        let r = look_at(*c);
        let (right, down, fwd) = (r.x_axis, r.y_axis, r.z_axis);
        let back = -fwd;
        for row in 0..3 {
            rows.extend_from_slice(&[down[row], right[row], back[row], c[row], [SIDE as f64, SIDE as f64, FOCAL][row]]);
        }
        rows.extend_from_slice(&[1.0, 6.0]);
        llff_files.push((PathBuf::from(format!("images/{i:03}.png")), small_rgb_png.clone()));
    }
    llff_files.push((PathBuf::from("poses_bounds.npy"), npy_f64(&[cams.len(), 17], &rows)));
    out.push(Seed { format: "poses_bounds.npy", files: llff_files, target: "poses_bounds.npy".into(), kind: Kind::Npy, run: Run::Info });

    // COLMAP sparse/0, binary and text.
    let mut cams_bin = 1u64.to_le_bytes().to_vec();
    cams_bin.extend_from_slice(&1i32.to_le_bytes());
    cams_bin.extend_from_slice(&1i32.to_le_bytes()); // PINHOLE
    cams_bin.extend_from_slice(&(SIDE as u64).to_le_bytes());
    cams_bin.extend_from_slice(&(SIDE as u64).to_le_bytes());
    for v in [FOCAL, FOCAL, 8.0, 8.0] {
        cams_bin.extend_from_slice(&v.to_le_bytes());
    }
    let mut imgs_bin = (cams.len() as u64).to_le_bytes().to_vec();
    let mut imgs_txt = String::from("# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME\n");
    let mut colmap_images = Vec::new();
    for (i, c) in cams.iter().enumerate() {
        let r_cw = look_at(*c).transpose();
        let q = DQuat::from_mat3(&r_cw);
        let t = -(r_cw * *c);
        imgs_bin.extend_from_slice(&(i as i32 + 1).to_le_bytes());
        for v in [q.w, q.x, q.y, q.z, t.x, t.y, t.z] {
            imgs_bin.extend_from_slice(&v.to_le_bytes());
        }
        imgs_bin.extend_from_slice(&1i32.to_le_bytes());
        imgs_bin.extend_from_slice(format!("{i:03}.png\0").as_bytes());
        imgs_bin.extend_from_slice(&1u64.to_le_bytes());
        for v in [4.0f64, 5.0] {
            imgs_bin.extend_from_slice(&v.to_le_bytes());
        }
        imgs_bin.extend_from_slice(&(-1i64).to_le_bytes());
        imgs_txt.push_str(&format!("{} {} {} {} {} {} {} {} 1 {i:03}.png\n4.0 5.0 -1\n", i + 1, q.w, q.x, q.y, q.z, t.x, t.y, t.z));
        colmap_images.push((PathBuf::from(format!("images/{i:03}.png")), small_rgb_png.clone()));
        colmap_images.push((PathBuf::from(format!("masks/{i:03}.png")), mask_png.clone()));
    }
    let cams_txt = format!("# CAMERA_ID MODEL WIDTH HEIGHT PARAMS\n1 PINHOLE {SIDE} {SIDE} {FOCAL} {FOCAL} 8 8\n");
    let mut bin_files = colmap_images.clone();
    bin_files.push(("sparse/0/cameras.bin".into(), cams_bin));
    bin_files.push(("sparse/0/images.bin".into(), imgs_bin));
    let mut txt_files = colmap_images;
    txt_files.push(("sparse/0/cameras.txt".into(), cams_txt.into_bytes()));
    txt_files.push(("sparse/0/images.txt".into(), imgs_txt.into_bytes()));
    for (format, files, target, kind) in [
        ("colmap cameras.bin", &bin_files, "sparse/0/cameras.bin", Kind::ColmapBin),
        ("colmap images.bin", &bin_files, "sparse/0/images.bin", Kind::ColmapBin),
        ("colmap cameras.txt", &txt_files, "sparse/0/cameras.txt", Kind::Text),
        ("colmap images.txt", &txt_files, "sparse/0/images.txt", Kind::Text),
    ] {
        out.push(Seed { format, files: files.clone(), target: target.into(), kind, run: Run::Info });
    }

    // Latlong EXRs for fit-env: a small uncompressed one, a small ZIP one, the example's map.
    let ll = latlong(16, 8);
    out.push(Seed { format: "latlong exr (raw)", files: vec![("map.exr".into(), exr_raw_bytes(16, 8, &ll))], target: "map.exr".into(), kind: Kind::Exr, run: Run::FitEnv });
    out.push(Seed { format: "latlong exr (zip)", files: vec![("map.exr".into(), exr_zip_bytes(16, 8, &ll))], target: "map.exr".into(), kind: Kind::Exr, run: Run::FitEnv });
    out.push(Seed { format: "latlong exr (example)", files: vec![("map.exr".into(), read("env/train.exr"))], target: "map.exr".into(), kind: Kind::Exr, run: Run::FitEnv });

    // eval: a ground truth and a prediction folder.
    let octa = "v 1 0 0\nv -1 0 0\nv 0 1 0\nv 0 -1 0\nv 0 0 1\nv 0 0 -1\nf 1 3 5\nf 3 2 5\nf 2 4 5\nf 4 1 5\nf 3 1 6\nf 2 3 6\nf 4 2 6\nf 1 4 6\n";
    let mut ply = b"ply\nformat binary_little_endian 1.0\nelement vertex 6\nproperty float x\nproperty float y\nproperty float z\nelement face 8\nproperty list uchar int vertex_indices\nend_header\n".to_vec();
    for v in [[1.0f32, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]] {
        for c in v {
            ply.extend_from_slice(&c.to_le_bytes());
        }
    }
    for f in [[0i32, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]] {
        ply.push(3);
        for i in f {
            ply.extend_from_slice(&i.to_le_bytes());
        }
    }
    let eval_files = |pred_mesh: (&str, Vec<u8>)| {
        vec![
            (PathBuf::from("gt/transforms_test.json"), transforms_json(&[("./test/r_000".into(), gl_matrix(cams[0]), None)], "")),
            (PathBuf::from("gt/test/r_000.png"), small_png.clone()),
            (PathBuf::from("gt/test/r_000_albedo.png"), small_png.clone()),
            (PathBuf::from("gt/test/r_000_roughness.png"), small_png.clone()),
            (PathBuf::from("gt/env/train.exr"), exr_zip_bytes(16, 8, &ll)),
            (PathBuf::from("gt/gt/mesh.obj"), octa.as_bytes().to_vec()),
            (PathBuf::from("pred/test/r_000.png"), small_png.clone()),
            (PathBuf::from("pred/test/r_000_albedo.png"), small_png.clone()),
            (PathBuf::from("pred/test/r_000_roughness.png"), small_png.clone()),
            (PathBuf::from("pred/env.exr"), exr_raw_bytes(16, 8, &ll)),
            (PathBuf::from(format!("pred/{}", pred_mesh.0)), pred_mesh.1),
        ]
    };
    let obj_eval = eval_files(("mesh.obj", octa.as_bytes().to_vec()));
    let ply_eval = eval_files(("mesh.ply", ply));
    for (format, files, target, kind) in [
        ("eval transforms_test.json", &obj_eval, "gt/transforms_test.json", Kind::Json),
        ("eval png prediction", &obj_eval, "pred/test/r_000.png", Kind::Png),
        ("eval exr environment", &obj_eval, "pred/env.exr", Kind::Exr),
        ("eval obj mesh", &obj_eval, "pred/mesh.obj", Kind::Text),
        ("eval ply mesh", &ply_eval, "pred/mesh.ply", Kind::Text),
    ] {
        out.push(Seed { format, files: files.clone(), target: target.into(), kind, run: Run::Eval });
    }

    // SG environment JSON (export --env-json).
    let env = pii_bake::sg::env::EnvSgs {
        lobes: vec![
            pii_bake::sg::env::SgLobe { axis: [0.0, 1.0, 0.0], sharpness: 2.0, amplitude: [1.0, 0.9, 0.8] },
            pii_bake::sg::env::SgLobe { axis: [0.6, 0.0, 0.8], sharpness: 30.0, amplitude: [5.0, 4.0, 3.0] },
        ],
    };
    let env_json = {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("env_sg.json");
        env.write_json(&p).unwrap();
        std::fs::read(p).unwrap()
    };
    out.push(Seed { format: "sg env json", files: vec![("env_sg.json".into(), env_json)], target: "env_sg.json".into(), kind: Kind::Json, run: Run::ExportEnvJson });

    // A checkpoint (safetensors, written by ParamStore::save) and a config JSON.
    let mut store = pii_bake::nn::params::ParamStore::new();
    store.insert("field/layer0/w", &[4, 3], (0..12).map(|i| i as f32 * 0.25 - 1.0).collect()).unwrap();
    store.insert("field/layer0/b", &[4], vec![0.5; 4]).unwrap();
    store.insert("optim/field/layer0/b/m", &[4], vec![0.01; 4]).unwrap();
    let config = serde_json::json!({"preset": "fast", "lr": 0.001, "hash_levels": 16, "batch": 4096, "steps": [1000, 2000]});
    store.set_config(&config).unwrap();
    store.set_step(1234);
    let (ckpt, cfg) = {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("ckpt.safetensors");
        store.save(&p).unwrap();
        (std::fs::read(p).unwrap(), serde_json::to_vec_pretty(&config).unwrap())
    };
    out.push(Seed { format: "checkpoint safetensors", files: vec![("ckpt.safetensors".into(), ckpt)], target: "ckpt.safetensors".into(), kind: Kind::Safetensors, run: Run::Checkpoint });
    out.push(Seed { format: "checkpoint config json", files: vec![("config.json".into(), cfg)], target: "config.json".into(), kind: Kind::Json, run: Run::ConfigJson });
    out
}

// ---------------------------------------------------------------------------------------------
// Running one case.

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum Outcome {
    /// Exit 1/2, no panic, the error names the damaged file, no partial output.
    CleanError,
    /// Exit 0, no temporary files left.
    Accepted,
    /// Anything else: signal/abort, timeout, other exit code, panic text, unnamed file, leftovers.
    Crash,
}

struct CaseResult {
    format: &'static str,
    mutation: &'static str,
    outcome: Outcome,
    why: String,
    secs: f64,
    /// The last line the tool printed on stderr (the error, for failures).
    last_line: String,
}

fn bin() -> assert_cmd::Command {
    let mut c = assert_cmd::Command::cargo_bin("pii-bake").unwrap();
    c.env("XDG_RUNTIME_DIR", std::env::temp_dir()).env_remove("RUST_LOG").env_remove("PII_BACKEND").env_remove("RUST_BACKTRACE");
    c
}

fn command(seed: &Seed, case: &Path) -> assert_cmd::Command {
    let out = case.join("out");
    let target = case.join(&seed.target);
    let os = |v: &[&str]| v.iter().map(OsString::from).collect::<Vec<_>>();
    match seed.run {
        Run::Info => {
            let mut c = bin();
            c.args(["--backend", "cpu", "info"]).arg(case);
            c
        }
        Run::FitEnv => {
            let mut c = bin();
            c.args(os(&["--backend", "cpu", "fit-env"])).arg(&target).arg("--out").arg(&out);
            c.args(["--lobes", "1", "--iterations", "2", "--fit-width", "8"]);
            c
        }
        Run::Eval => {
            let mut c = bin();
            c.args(["--backend", "cpu", "eval", "--gt"]).arg(case.join("gt")).arg("--pred").arg(case.join("pred"));
            c.arg("--out").arg(out.join("metrics.json")).args(["--mesh-samples", "64"]);
            c
        }
        Run::ExportEnvJson => {
            let mut c = bin();
            c.args(["--backend", "cpu", "export", "--analytic", "sphere", "--resolution", "12", "--texture", "64"]);
            c.arg("--env-json").arg(&target).arg("--out").arg(&out);
            c
        }
        Run::Checkpoint | Run::ConfigJson => {
            let mut c = assert_cmd::Command::new(std::env::current_exe().unwrap());
            c.args(["checkpoint_child", "--exact", "--nocapture", "--test-threads=1", "--quiet"]);
            let var = if matches!(seed.run, Run::Checkpoint) { "PII_FUZZ_CHILD_CHECKPOINT" } else { "PII_FUZZ_CHILD_CONFIG" };
            c.env(var, &target);
            c
        }
    }
}

/// Every file under `dir`, recursively.
fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
    if let Ok(rd) = std::fs::read_dir(dir) {
        for e in rd.flatten() {
            let p = e.path();
            if p.is_dir() {
                walk(&p, out);
            } else {
                out.push(p);
            }
        }
    }
}

fn run_case(seed: &Seed, index: u64, base_seed: u64) -> CaseResult {
    let mut rng = Rng::new(base_seed.wrapping_mul(0x1000_0000_01B3) ^ index.wrapping_mul(0x9E37_79B9));
    let original = &seed.files.iter().find(|(p, _)| *p == seed.target).expect("target in files").1;
    let (bytes, mutation) = mutate(seed.kind, original, &mut rng);
    let dir = tempfile::tempdir().unwrap();
    let case = dir.path().join("case");
    for (rel, data) in &seed.files {
        let p = case.join(rel);
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(&p, if *rel == seed.target { &bytes } else { data }).unwrap();
    }
    let t = Instant::now();
    let result = command(seed, &case).timeout(CASE_TIMEOUT).output();
    let secs = t.elapsed().as_secs_f64();
    let out = match result {
        Ok(o) => o,
        Err(e) => {
            return CaseResult { format: seed.format, mutation, outcome: Outcome::Crash, why: format!("could not run: {e}"), secs, last_line: String::new() }
        }
    };
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    let last_line = stderr.lines().last().unwrap_or("").to_string();
    let res = |outcome, why: String| CaseResult { format: seed.format, mutation, outcome, why, secs, last_line: last_line.clone() };
    let tail = || stderr.lines().rev().take(6).collect::<Vec<_>>().into_iter().rev().collect::<Vec<_>>().join(" | ");
    let Some(code) = out.status.code() else {
        let why = if secs >= CASE_TIMEOUT.as_secs_f64() { "timed out" } else { "killed by a signal (abort?)" };
        return res(Outcome::Crash, format!("{why}: {}", tail()));
    };
    for bad in ["panicked", "memory allocation of", "RUST_BACKTRACE", "stack overflow"] {
        if stderr.contains(bad) {
            return res(Outcome::Crash, format!("exit {code} with {bad:?}: {}", tail()));
        }
    }
    if code > 2 {
        return res(Outcome::Crash, format!("exit {code}: {}", tail()));
    }
    let mut files = Vec::new();
    walk(&case, &mut files);
    if let Some(tmp) = files.iter().find(|p| p.to_string_lossy().ends_with(".tmp")) {
        return res(Outcome::Crash, format!("exit {code} left a temporary file {}", tmp.display()));
    }
    if code == 0 {
        return res(Outcome::Accepted, String::new());
    }
    if let Some(f) = files.iter().find(|p| p.starts_with(case.join("out"))) {
        return res(Outcome::Crash, format!("exit {code} left output {}", f.display()));
    }
    let name = seed.target.file_name().unwrap().to_string_lossy().into_owned();
    if !stderr.contains(&name) {
        return res(Outcome::Crash, format!("exit {code}, the error does not name {name}: {}", tail()));
    }
    res(Outcome::CleanError, String::new())
}

#[derive(Default, Clone)]
struct Row {
    cases: usize,
    clean: usize,
    accepted: usize,
    crashes: usize,
    secs: f64,
}

/// Run `cases` cases (round-robin over the seeds) on `threads` threads; returns the table rows
/// (per format) and the failures.
fn campaign(cases: usize, base_seed: u64, threads: usize) -> (BTreeMap<&'static str, Row>, Vec<String>) {
    let seeds = seeds();
    let next = AtomicUsize::new(0);
    let results = Mutex::new(Vec::new());
    std::thread::scope(|s| {
        for _ in 0..threads {
            s.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                if i >= cases {
                    break;
                }
                let seed = &seeds[i % seeds.len()];
                let r = run_case(seed, i as u64, base_seed);
                if std::env::var_os("PII_FUZZ_VERBOSE").is_some() {
                    println!("case {i:5} {:<28} {:<18} {:?} {:.3}s {}", r.format, r.mutation, r.outcome, r.secs, r.last_line);
                }
                results.lock().unwrap().push((i, r));
            });
        }
    });
    let mut results = results.into_inner().unwrap();
    results.sort_by_key(|(i, _)| *i);
    let mut table: BTreeMap<&'static str, Row> = seeds.iter().map(|s| (s.format, Row::default())).collect();
    let mut failures = Vec::new();
    for (i, r) in &results {
        let row = table.get_mut(r.format).unwrap();
        row.cases += 1;
        row.secs += r.secs;
        match r.outcome {
            Outcome::CleanError => row.clean += 1,
            Outcome::Accepted => row.accepted += 1,
            Outcome::Crash => {
                row.crashes += 1;
                failures.push(format!("case {i} ({}, {}, seed {base_seed}): {}", r.format, r.mutation, r.why));
            }
        }
    }
    (table, failures)
}

fn print_table(table: &BTreeMap<&'static str, Row>, wall: f64) {
    println!("| format | cases | clean errors | accepted | crashes | mean s/case |");
    println!("| --- | ---: | ---: | ---: | ---: | ---: |");
    let mut total = Row::default();
    for (f, r) in table {
        println!("| {f} | {} | {} | {} | {} | {:.3} |", r.cases, r.clean, r.accepted, r.crashes, r.secs / r.cases.max(1) as f64);
        total.cases += r.cases;
        total.clean += r.clean;
        total.accepted += r.accepted;
        total.crashes += r.crashes;
        total.secs += r.secs;
    }
    println!(
        "| **total** | {} | {} | {} | {} | {:.3} |",
        total.cases,
        total.clean,
        total.accepted,
        total.crashes,
        total.secs / total.cases.max(1) as f64
    );
    println!("{} cases in {wall:.1} s wall", total.cases);
}

fn env_usize(name: &str) -> Option<usize> {
    std::env::var(name).ok().and_then(|v| v.parse().ok())
}

fn run_and_check(cases: usize) {
    let seed = env_usize("PII_FUZZ_SEED").unwrap_or(1) as u64;
    let threads = env_usize("PII_FUZZ_THREADS").unwrap_or(2);
    let t = Instant::now();
    let (table, failures) = campaign(cases, seed, threads);
    print_table(&table, t.elapsed().as_secs_f64());
    assert!(failures.is_empty(), "{} of {cases} cases failed:\n{}", failures.len(), failures.join("\n"));
    for (f, r) in &table {
        assert!(r.cases > 0 && r.clean > 0, "format {f}: no case gave a clean error ({} cases): mutations too weak", r.cases);
    }
}

/// The test command's fuzz run: a few hundred cases.
#[test]
fn damaged_inputs_give_clean_errors() {
    run_and_check(env_usize("PII_FUZZ_CASES_QUICK").unwrap_or(DEFAULT_CASES));
}

/// The release check (`scripts/fuzz.sh`): `PII_FUZZ_CASES` cases (default 5000).
#[test]
#[ignore]
fn fuzz_large() {
    run_and_check(env_usize("PII_FUZZ_CASES").unwrap_or(5000));
}

/// Child process for checkpoint cases (no CLI command reads checkpoints yet): load the file named
/// by `PII_FUZZ_CHILD_CHECKPOINT` (or the JSON named by `PII_FUZZ_CHILD_CONFIG`) and exit 0 / 1
/// like the CLI. Without the variables it does nothing.
#[test]
fn checkpoint_child() {
    let finish = |r: Result<(), pii_bake::util::DataError>| -> ! {
        match r {
            Ok(()) => std::process::exit(0),
            Err(e) => {
                eprintln!("error: {e}");
                std::process::exit(1)
            }
        }
    };
    if let Some(p) = std::env::var_os("PII_FUZZ_CHILD_CHECKPOINT") {
        let p = PathBuf::from(p);
        finish(pii_bake::nn::params::ParamStore::load(&p).and_then(|s| s.config_value(&p).map(|_| ())));
    }
    if let Some(p) = std::env::var_os("PII_FUZZ_CHILD_CONFIG") {
        finish(pii_bake::util::read_json_value(Path::new(&p)).map(|_| ()));
    }
}

/// Every seed is accepted as it is (the mutations start from valid inputs).
#[test]
fn seeds_are_valid_inputs() {
    let seeds = seeds();
    std::thread::scope(|s| {
        let handles: Vec<_> = seeds
            .chunks(seeds.len().div_ceil(2))
            .map(|chunk| {
                s.spawn(move || {
                    for seed in chunk {
                        let dir = tempfile::tempdir().unwrap();
                        let case = dir.path().join("case");
                        for (rel, data) in &seed.files {
                            let p = case.join(rel);
                            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
                            std::fs::write(&p, data).unwrap();
                        }
                        let out = command(seed, &case).timeout(CASE_TIMEOUT).output().unwrap();
                        assert!(
                            out.status.success(),
                            "seed {} is not accepted: {}",
                            seed.format,
                            String::from_utf8_lossy(&out.stderr)
                        );
                    }
                })
            })
            .collect();
        for h in handles {
            h.join().unwrap();
        }
    });
}

/// Regression (issue 11): a latlong EXR whose header declares a huge data window made `fit-env`
/// abort with "memory allocation of 2216201558016 bytes failed". It must be a clean error that
/// names the file, with nothing written.
#[test]
fn damaged_exr_data_window_is_a_clean_error() {
    let dir = tempfile::tempdir().unwrap();
    let map = dir.path().join("sky.exr");
    let mut bytes = exr_zip_bytes(16, 8, &latlong(16, 8));
    // (xMin, yMin, xMax, yMax) = (0, 0, 1_000_000, 500_000): a 1M x 500k window, ~6 TB as RGB f32;
    // chunkCount kept consistent, as in a file without that attribute (Blender's, OpenEXR's).
    patch_exr_window(&mut bytes, 1_000_000, 500_000);
    std::fs::write(&map, &bytes).unwrap();
    let out_dir = dir.path().join("out");
    let out = bin()
        .args(["--backend", "cpu", "fit-env"])
        .arg(&map)
        .arg("--out")
        .arg(&out_dir)
        .args(["--lobes", "1", "--iterations", "2", "--fit-width", "8"])
        .timeout(CASE_TIMEOUT)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(!stderr.contains("memory allocation") && !stderr.contains("panicked"), "{stderr}");
    assert!(stderr.contains("sky.exr") && stderr.contains("1000001x500001"), "{stderr}");
    let mut left = Vec::new();
    walk(&out_dir, &mut left);
    assert!(left.is_empty(), "output left behind: {left:?}");

    // The same file read as a scene image or by eval is the same clean error.
    let e = pii_bake::image_io::read_image_linear(&map).unwrap_err().to_string();
    assert!(e.contains("sky.exr") && e.contains("data window"), "{e}");
}

/// The mutation helpers themselves: deterministic, and each changes its input.
#[test]
fn mutations_are_deterministic() {
    let seed = br#"{"a": [1, 2.5, -3e2], "b": "x"}"#;
    let a = mutate(Kind::Json, seed, &mut Rng::new(7));
    let b = mutate(Kind::Json, seed, &mut Rng::new(7));
    assert_eq!(a, b);
    assert_eq!(number_spans(seed).len(), 3);
    let zip = zip_stored(&[("a.npy".into(), npy_f64(&[2], &[1.0, 2.0]))]);
    assert_eq!(unzip_stored(&zip).len(), 1);
}

/// Commands that write check their output folder first: a file where the folder should be is a
/// clean error naming it, before the input is even read.
#[test]
fn unwritable_output_is_refused_before_work() {
    let dir = tempfile::tempdir().unwrap();
    let blocker = dir.path().join("blocker");
    std::fs::write(&blocker, b"not a folder").unwrap();
    let maps = dir.path().join("maps");
    std::fs::create_dir(&maps).unwrap();
    std::fs::write(maps.join("sky.exr"), exr_zip_bytes(16, 8, &latlong(16, 8))).unwrap();
    let missing = dir.path().join("missing.exr");
    let runs: Vec<Vec<OsString>> = vec![
        // the map does not exist: the output folder is what fails first
        vec!["fit-env".into(), missing.clone().into(), "--out".into(), blocker.join("out").into()],
        vec!["fit-env".into(), missing.into(), "--out".into(), blocker.clone().into()],
        vec!["bench".into(), "env".into(), "--maps".into(), maps.clone().into(), "--lobes".into(), "1".into(), "--out".into(), blocker.join("b").into()],
        vec!["bench".into(), "nn".into(), "--batches".into(), "64".into(), "--out".into(), blocker.join("nn.json").into()],
        vec!["bench".into(), "export".into(), "--resolutions".into(), "8".into(), "--out".into(), blocker.join("ex.json").into()],
        vec!["eval".into(), "--gt".into(), dir.path().join("nogt").into(), "--pred".into(), dir.path().join("nopred").into(), "--out".into(), blocker.join("m.json").into()],
    ];
    for args in runs {
        let out = bin().args(["--backend", "cpu"]).args(&args).timeout(CASE_TIMEOUT).output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{args:?}: {stderr}");
        assert!(stderr.contains("blocker") && !stderr.contains("missing.exr") && !stderr.contains("nogt"), "{args:?}: {stderr}");
        assert_eq!(stderr.trim().lines().count(), 1, "{args:?}: {stderr}");
    }
    assert_eq!(std::fs::read(&blocker).unwrap(), b"not a folder");
    let mut left = Vec::new();
    walk(dir.path(), &mut left);
    assert!(left.iter().all(|p| !p.to_string_lossy().ends_with(".tmp")), "{left:?}");
}
