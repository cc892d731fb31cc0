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

/// Read an image as linear float. PNG/JPEG colour is sRGB-decoded (alpha stays linear);
/// EXR is read as stored (linear). Keeps alpha when the file has it.
pub fn read_image_linear(path: &Path) -> Result<ImageF32, DataError> {
    if !path.exists() {
        return Err(DataError::new(path, "file not found"));
    }
    if is_exr(path) {
        return read_exr(path);
    }
    let img = image::ImageReader::open(path)
        .map_err(|e| DataError::new(path, format!("cannot open: {e}")))?
        .with_guessed_format()
        .map_err(|e| DataError::new(path, format!("cannot read: {e}")))?
        .decode()
        .map_err(|e| DataError::new(path, format!("not a readable image: {e}")))?;
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
    let img = image::ImageReader::open(path)
        .map_err(|e| DataError::new(path, format!("cannot open: {e}")))?
        .with_guessed_format()
        .map_err(|e| DataError::new(path, format!("cannot read: {e}")))?
        .decode()
        .map_err(|e| DataError::new(path, format!("not a readable image: {e}")))?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let m = if img.color().has_color() || !img.color().has_alpha() {
        img.to_rgb32f().pixels().map(|p| (p[0] + p[1] + p[2]) / 3.0).collect()
    } else {
        img.to_luma_alpha32f().pixels().map(|p| p[1]).collect()
    };
    Ok((w, h, m))
}

fn read_exr(path: &Path) -> Result<ImageF32, DataError> {
    use exr::prelude::*;
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
}
