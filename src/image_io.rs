//! Image files in and out, shared by every module: PNG/JPEG (sRGB-decoded to linear) and EXR
//! (linear float) reading; sRGB/linear 8-bit PNG and ZIP-compressed float EXR writing, always
//! through a temporary name and a rename.

use std::path::Path;

use crate::util::{atomic_write, temp_name, DataError};

/// A float image, row-major from the top row, `channels` (3 = RGB, 4 = RGBA) per pixel, linear.
#[derive(Clone, Debug, PartialEq)]
pub struct ImageF32 {
    pub width: usize,
    pub height: usize,
    pub channels: usize,
    pub data: Vec<f32>,
}

impl ImageF32 {
    pub fn new(width: usize, height: usize, channels: usize) -> Self {
        Self { width, height, channels, data: vec![0.0; width * height * channels] }
    }
    pub fn pixel(&self, x: usize, y: usize) -> &[f32] {
        let i = (y * self.width + x) * self.channels;
        &self.data[i..i + self.channels]
    }
    /// RGB only (drops alpha if present).
    pub fn rgb(&self) -> Vec<f32> {
        if self.channels == 3 {
            return self.data.clone();
        }
        self.data.chunks_exact(self.channels).flat_map(|p| [p[0], p[1], p[2]]).collect()
    }
    /// The alpha channel, if any.
    pub fn alpha(&self) -> Option<Vec<f32>> {
        (self.channels == 4).then(|| self.data.chunks_exact(4).map(|p| p[3]).collect())
    }
}

/// sRGB transfer function, decode (IEC 61966-2-1).
pub fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// sRGB transfer function, encode.
pub fn linear_to_srgb(c: f32) -> f32 {
    let c = c.clamp(0.0, 1.0);
    if c <= 0.003_130_8 {
        c * 12.92
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    }
}

fn is_exr(path: &Path) -> bool {
    path.extension().is_some_and(|e| e.eq_ignore_ascii_case("exr"))
}

/// Largest width or height an image file may declare.
pub const MAX_IMAGE_SIDE: usize = 1 << 16;
/// Largest pixel count an image file may declare (16384 × 8192, a 16k latlong map; 134 MP photos).
pub const MAX_IMAGE_PIXELS: usize = 16384 * 8192;

/// Check a size an image file declares against [`MAX_IMAGE_SIDE`] and [`MAX_IMAGE_PIXELS`].
pub fn check_declared_size(path: &Path, width: usize, height: usize) -> Result<(), DataError> {
    if width == 0 || height == 0 {
        return Err(DataError::new(path, format!("image declares an empty size {width}x{height}")));
    }
    let pixels = width.checked_mul(height);
    if width > MAX_IMAGE_SIDE || height > MAX_IMAGE_SIDE || pixels.is_none_or(|p| p > MAX_IMAGE_PIXELS) {
        return Err(DataError::new(
            path,
            format!(
                "image declares a size of {width}x{height}, past the limit ({MAX_IMAGE_SIDE} per side, {MAX_IMAGE_PIXELS} pixels): damaged header?"
            ),
        ));
    }
    Ok(())
}

/// The image crate's decoding limits matching [`MAX_IMAGE_SIDE`] / [`MAX_IMAGE_PIXELS`]
/// (16-bit RGBA is the largest layout PNG decodes to).
fn decode_limits() -> image::Limits {
    let mut l = image::Limits::default();
    l.max_image_width = Some(MAX_IMAGE_SIDE as u32);
    l.max_image_height = Some(MAX_IMAGE_SIDE as u32);
    l.max_alloc = Some(MAX_IMAGE_PIXELS as u64 * 8 + (64 << 20));
    l
}

fn open_reader(path: &Path) -> Result<image::ImageReader<std::io::BufReader<std::fs::File>>, DataError> {
    image::ImageReader::open(path)
        .map_err(|e| DataError::new(path, format!("cannot open: {e}")))?
        .with_guessed_format()
        .map_err(|e| DataError::new(path, format!("cannot read: {e}")))
}

/// Decode a PNG/JPEG with the size it declares checked first (against the limits and against
/// the file's own size: deflate shrinks at most ~1032:1, JPEG gets a wide bound) and the
/// decoder's allocations bounded.
fn decode_limited(path: &Path) -> Result<image::DynamicImage, DataError> {
    use image::ImageDecoder;
    let file_len = std::fs::metadata(path).map_err(|e| DataError::new(path, format!("cannot read: {e}")))?.len();
    let mut reader = open_reader(path)?;
    let limits = decode_limits();
    reader.limits(limits.clone());
    let ratio: u64 = if reader.format() == Some(image::ImageFormat::Png) { 2048 } else { 1 << 16 };
    let decoder = reader.into_decoder().map_err(|e| DataError::new(path, format!("not a readable image: {e}")))?;
    let (w, h) = decoder.dimensions();
    check_declared_size(path, w as usize, h as usize)?;
    let total = decoder.total_bytes();
    if total > limits.max_alloc.unwrap_or(u64::MAX) || total / ratio > file_len {
        return Err(DataError::new(
            path,
            format!("image declares {w}x{h} pixels ({total} bytes decoded) but the file holds only {file_len} bytes: damaged header or truncated file"),
        ));
    }
    image::DynamicImage::from_decoder(decoder).map_err(|e| DataError::new(path, format!("not a readable image: {e}")))
}

/// The size a PNG/JPEG declares (header only).
fn png_jpeg_size(path: &Path) -> Result<(usize, usize), DataError> {
    let mut reader = open_reader(path)?;
    // The header only: the size is checked by the caller, with a message naming it.
    reader.no_limits();
    let (w, h) = reader
        .into_dimensions()
        .map_err(|e| DataError::new(path, format!("not a readable image: {e}")))?;
    Ok((w as usize, h as usize))
}

/// The size of an image file from its header (no pixel decoding), checked against the limits.
pub fn image_dimensions(path: &Path) -> Result<(usize, usize), DataError> {
    if !path.exists() {
        return Err(DataError::new(path, "file not found"));
    }
    let (w, h) = if is_exr(path) { exr_rgba_size(path)? } else { png_jpeg_size(path)? };
    check_declared_size(path, w, h)?;
    Ok((w, h))
}

/// Read an image as linear float. PNG/JPEG colour is sRGB-decoded (alpha stays linear);
/// EXR is read as stored (linear). Keeps alpha when the file has it. The size the file declares
/// is checked against [`MAX_IMAGE_SIDE`] / [`MAX_IMAGE_PIXELS`] (and, for EXR, against the file's
/// own size) before anything is allocated.
pub fn read_image_linear(path: &Path) -> Result<ImageF32, DataError> {
    if !path.exists() {
        return Err(DataError::new(path, "file not found"));
    }
    if is_exr(path) {
        return read_exr(path);
    }
    let img = decode_limited(path)?;
    let has_alpha = img.color().has_alpha();
    let (w, h) = (img.width() as usize, img.height() as usize);
    let rgba = img.to_rgba32f();
    let channels = if has_alpha { 4 } else { 3 };
    let mut data = Vec::with_capacity(w * h * channels);
    for p in rgba.pixels() {
        data.extend_from_slice(&[srgb_to_linear(p[0]), srgb_to_linear(p[1]), srgb_to_linear(p[2])]);
        if has_alpha {
            data.push(p[3]);
        }
    }
    Ok(ImageF32 { width: w, height: h, channels, data })
}

/// Read a single-channel mask (PNG/JPEG/EXR) as values in [0, 1], no sRGB decoding:
/// the mean of the colour channels, or alpha when the image has alpha and no colour content.
pub fn read_mask(path: &Path) -> Result<(usize, usize, Vec<f32>), DataError> {
    if !path.exists() {
        return Err(DataError::new(path, "file not found"));
    }
    if is_exr(path) {
        let img = read_exr(path)?;
        let m = img.data.chunks_exact(img.channels).map(|p| ((p[0] + p[1] + p[2]) / 3.0).clamp(0.0, 1.0)).collect();
        return Ok((img.width, img.height, m));
    }
    let img = decode_limited(path)?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let m = if img.color().has_color() || !img.color().has_alpha() {
        img.to_rgb32f().pixels().map(|p| (p[0] + p[1] + p[2]) / 3.0).collect()
    } else {
        img.to_luma_alpha32f().pixels().map(|p| p[1]).collect()
    };
    Ok((w, h, m))
}

/// The most a codec can shrink pixel data: a declared image needs at least
/// `pixel bytes / ratio` bytes of file. Generous (a bound, not an estimate): RLE stores at most
/// 128 copies in 2 bytes; deflate (ZIP, PXR24 after its 24-bit packing) at most ~1032:1; PIZ,
/// DWA and the codecs the exr crate cannot decode get a wide bound.
fn max_compression_ratio(c: exr::compression::Compression) -> u64 {
    use exr::compression::Compression as C;
    match c {
        C::Uncompressed => 1,
        C::RLE => 64,
        C::B44 | C::B44A => 16,
        C::ZIP1 | C::ZIP16 | C::PXR24 => 2048,
        _ => 1 << 16,
    }
}

/// Read an EXR's headers and check every layer's declared data window × channels against the
/// pixel limits and against the file's own size, before any pixel memory is allocated.
/// Returns the headers.
fn check_exr_header(path: &Path) -> Result<Vec<exr::meta::header::Header>, DataError> {
    let file_len = std::fs::metadata(path).map_err(|e| DataError::new(path, format!("cannot read: {e}")))?.len();
    let meta = exr::meta::MetaData::read_from_file(path, false)
        .map_err(|e| DataError::new(path, format!("not a readable EXR header: {e}")))?;
    if meta.headers.is_empty() {
        return Err(DataError::new(path, "EXR file has no layers"));
    }
    for (i, h) in meta.headers.iter().enumerate() {
        let layer = if meta.headers.len() > 1 { format!("layer {i}: ") } else { String::new() };
        if h.deep {
            return Err(DataError::new(path, format!("{layer}deep EXR data is not supported")));
        }
        let (w, hh) = (h.layer_size.width(), h.layer_size.height());
        check_declared_size(path, w, hh).map_err(|e| DataError::new(path, format!("{layer}data window: {}", e.problem)))?;
        if h.channels.list.is_empty() || h.channels.list.len() > 1024 {
            return Err(DataError::new(path, format!("{layer}{} channels declared", h.channels.list.len())));
        }
        // Pixel bytes of the full-resolution level (a lower bound on what the file stores).
        let mut pixel_bytes: u64 = 0;
        for c in &h.channels.list {
            let (sx, sy) = (c.sampling.x().max(1) as u64, c.sampling.y().max(1) as u64);
            let samples = (w as u64 / sx) * (hh as u64 / sy);
            pixel_bytes = pixel_bytes.saturating_add(samples.saturating_mul(c.sample_type.bytes_per_sample() as u64));
        }
        let min_len = (h.chunk_count as u64).saturating_mul(8).saturating_add(pixel_bytes / max_compression_ratio(h.compression));
        if min_len > file_len {
            return Err(DataError::new(
                path,
                format!(
                    "{layer}declares a {w}x{hh} data window with {} channels ({pixel_bytes} bytes of pixels in {} chunks, {}) but the file holds only {file_len} bytes: damaged header or truncated file",
                    h.channels.list.len(),
                    h.chunk_count,
                    h.compression
                ),
            ));
        }
    }
    Ok(meta.headers.into_vec())
}

/// Size of the layer [`read_exr`] reads (the first one with R, G and B channels), from the header.
fn exr_rgba_size(path: &Path) -> Result<(usize, usize), DataError> {
    let headers = check_exr_header(path)?;
    let has = |h: &exr::meta::header::Header, n: &str| h.channels.list.iter().any(|c| c.name.eq(n));
    let h = headers
        .iter()
        .find(|h| has(h, "R") && has(h, "G") && has(h, "B"))
        .ok_or_else(|| DataError::new(path, "EXR has no layer with R, G, B channels"))?;
    Ok((h.layer_size.width(), h.layer_size.height()))
}

fn read_exr(path: &Path) -> Result<ImageF32, DataError> {
    use exr::prelude::*;
    check_exr_header(path)?;
    let image = read_first_rgba_layer_from_file(
        path,
        |resolution, channels: &RgbaChannels| {
            let has_alpha = channels.3.is_some();
            let c = if has_alpha { 4 } else { 3 };
            ImageF32 { width: resolution.width(), height: resolution.height(), channels: c, data: vec![0.0; resolution.area() * c] }
        },
        |img: &mut ImageF32, pos: Vec2<usize>, (r, g, b, a): (f32, f32, f32, f32)| {
            let i = (pos.y() * img.width + pos.x()) * img.channels;
            img.data[i] = r;
            img.data[i + 1] = g;
            img.data[i + 2] = b;
            if img.channels == 4 {
                img.data[i + 3] = a;
            }
        },
    )
    .map_err(|e| DataError::new(path, format!("cannot read EXR (needs R, G, B channels): {e}")))?;
    Ok(image.layer_data.channel_data.pixels)
}

/// Write a linear float RGB image (3 floats per pixel) as a ZIP-compressed scanline EXR.
pub fn write_exr_rgb(path: &Path, width: usize, height: usize, rgb: &[f32]) -> Result<(), DataError> {
    use exr::prelude::*;
    if rgb.len() != width * height * 3 {
        return Err(DataError::new(path, format!("{} floats for a {width}x{height} RGB image", rgb.len())));
    }
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| DataError::new(dir, format!("cannot create output folder: {e}")))?;
    }
    let channels = SpecificChannels::rgb(|p: Vec2<usize>| {
        let i = (p.y() * width + p.x()) * 3;
        (rgb[i], rgb[i + 1], rgb[i + 2])
    });
    let encoding = Encoding { compression: Compression::ZIP16, blocks: Blocks::ScanLines, line_order: LineOrder::Increasing };
    let layer = Layer::new((width, height), LayerAttributes::named("rgb"), encoding, channels);
    let tmp = temp_name(path);
    Image::from_layer(layer)
        .write()
        .to_file(&tmp)
        .map_err(|e| {
            let _ = std::fs::remove_file(&tmp);
            DataError::new(path, format!("cannot write EXR: {e}"))
        })?;
    std::fs::rename(&tmp, path).map_err(|e| DataError::new(path, format!("cannot write: {e}")))
}

/// Encode 8-bit PNG bytes from float pixels (`channels` 1, 3 or 4). `srgb` applies the sRGB
/// transfer to colour channels (not alpha); otherwise values are stored linearly.
/// The PNG carries no iCCP/gAMA chunks.
pub fn encode_png8(width: usize, height: usize, channels: usize, data: &[f32], srgb: bool) -> Result<Vec<u8>, String> {
    if data.len() != width * height * channels {
        return Err(format!("{} values for a {width}x{height}x{channels} image", data.len()));
    }
    let bytes: Vec<u8> = data
        .iter()
        .enumerate()
        .map(|(i, &v)| {
            let is_alpha = channels == 4 && i % 4 == 3;
            let v = if srgb && !is_alpha { linear_to_srgb(v) } else { v.clamp(0.0, 1.0) };
            (v * 255.0 + 0.5) as u8
        })
        .collect();
    let color = match channels {
        1 => image::ExtendedColorType::L8,
        3 => image::ExtendedColorType::Rgb8,
        4 => image::ExtendedColorType::Rgba8,
        c => return Err(format!("unsupported channel count {c}")),
    };
    let mut out = Vec::new();
    use image::ImageEncoder;
    image::codecs::png::PngEncoder::new(&mut out)
        .write_image(&bytes, width as u32, height as u32, color)
        .map_err(|e| e.to_string())?;
    Ok(out)
}

/// Write an 8-bit PNG atomically (see [`encode_png8`]).
pub fn write_png8(path: &Path, width: usize, height: usize, channels: usize, data: &[f32], srgb: bool) -> Result<(), DataError> {
    let bytes = encode_png8(width, height, channels, data, srgb).map_err(|e| DataError::new(path, e))?;
    atomic_write(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn srgb_round_trip() {
        for i in 0..=255 {
            let c = i as f32 / 255.0;
            assert!((linear_to_srgb(srgb_to_linear(c)) - c).abs() < 1e-5);
        }
    }

    #[test]
    fn exr_and_png_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let (w, h) = (5, 3);
        let rgb: Vec<f32> = (0..w * h * 3).map(|i| i as f32 * 0.37).collect();
        let p = dir.path().join("a.exr");
        write_exr_rgb(&p, w, h, &rgb).unwrap();
        let back = read_image_linear(&p).unwrap();
        assert_eq!((back.width, back.height, back.channels), (w, h, 3));
        assert_eq!(back.data, rgb);
        let lin: Vec<f32> = (0..w * h * 3).map(|i| (i % 11) as f32 / 10.0).collect();
        let q = dir.path().join("a.png");
        write_png8(&q, w, h, 3, &lin, true).unwrap();
        let back = read_image_linear(&q).unwrap();
        for (a, b) in back.data.iter().zip(&lin) {
            assert!((a - b).abs() < 0.01, "{a} vs {b}");
        }
        let err = read_image_linear(&dir.path().join("missing.png")).unwrap_err();
        assert!(err.to_string().contains("missing.png"));
        std::fs::write(dir.path().join("bad.png"), b"not a png").unwrap();
        assert!(read_image_linear(&dir.path().join("bad.png")).is_err());
    }

    /// An EXR header whose data window is past the pixel limit, or larger than the file could
    /// hold, is refused before any pixel memory is allocated.
    #[test]
    fn exr_declared_window_is_checked_against_limits_and_file_size() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("w.exr");
        write_exr_rgb(&p, 16, 8, &vec![0.5; 16 * 8 * 3]).unwrap();
        let good = std::fs::read(&p).unwrap();
        let attr = b"dataWindow\0box2i\0";
        let at = good.windows(attr.len()).position(|w| w == attr).unwrap() + attr.len() + 4;
        for (max, want) in [((1_000_000, 500_000), "1000001x500001"), ((3999, 1999), "4000x2000")] {
            let mut b = good.clone();
            b[at + 8..at + 12].copy_from_slice(&(max.0 as i32).to_le_bytes());
            b[at + 12..at + 16].copy_from_slice(&(max.1 as i32).to_le_bytes());
            std::fs::write(&p, &b).unwrap();
            let e = read_image_linear(&p).unwrap_err().to_string();
            assert!(e.contains("w.exr") && e.contains(want), "{e}");
            let e = image_dimensions(&p).unwrap_err().to_string();
            assert!(e.contains("w.exr") && e.contains(want), "{e}");
        }
        assert_eq!(check_declared_size(Path::new("x.png"), 65537, 1).unwrap_err().path, Path::new("x.png"));
        assert!(check_declared_size(Path::new("x.png"), 16384, 8192).is_ok());
        assert!(check_declared_size(Path::new("x.png"), 16384, 8193).is_err());
    }
}
