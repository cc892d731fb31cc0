//! COLMAP sparse model: `sparse/0/{cameras,images}.{bin,txt}` + `images/` (+ optional `masks/`).
//!
//! `images` hold world-to-camera rotation as a quaternion (qw, qx, qy, qz) and translation t, OpenCV
//! axes; the camera centre is −Rᵀt. COLMAP's pixel convention is ours (pixel centre at i + 0.5), so cx, cy
//! are used as stored. Camera models: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV; others are
//! refused. Masks: `masks/<image name>`, `masks/<image name>.png` or `masks/<stem>.png`. All views `train`.
//! The binary format is read with bounds checks (a truncated file is an error, not a panic).

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use glam::{DMat3, DQuat, DVec3};

use super::normalise::BoundHint;
use super::{declared_side, world_from_camera, Camera, Distortion, RawView, Split};
use crate::util::{read_text_bounded, DataError};

/// Largest COLMAP text file accepted (images.txt holds every 2-D point of every image).
const MAX_COLMAP_TEXT_BYTES: u64 = 2 << 30;

fn bad(path: &Path, what: impl Into<String>) -> DataError {
    DataError::new(path, what.into())
}

/// The model folder: `<path>/sparse/0`, `<path>/sparse`, or `<path>` itself.
pub(crate) fn find_model(path: &Path) -> Option<PathBuf> {
    [path.join("sparse").join("0"), path.join("sparse"), path.to_path_buf()]
        .into_iter()
        .find(|d| ["cameras.bin", "cameras.txt"].iter().any(|f| d.join(f).is_file()))
}

#[derive(Clone, Debug)]
struct ColmapCamera {
    model: String,
    width: usize,
    height: usize,
    params: Vec<f64>,
}

#[derive(Clone, Debug)]
struct ColmapImage {
    q: [f64; 4],
    t: [f64; 3],
    camera_id: u32,
    name: String,
}

fn model_name(id: i32) -> Option<(&'static str, usize)> {
    Some(match id {
        0 => ("SIMPLE_PINHOLE", 3),
        1 => ("PINHOLE", 4),
        2 => ("SIMPLE_RADIAL", 4),
        3 => ("RADIAL", 5),
        4 => ("OPENCV", 8),
        5 => ("OPENCV_FISHEYE", 8),
        6 => ("FULL_OPENCV", 12),
        7 => ("FOV", 5),
        8 => ("SIMPLE_RADIAL_FISHEYE", 4),
        9 => ("RADIAL_FISHEYE", 5),
        10 => ("THIN_PRISM_FISHEYE", 12),
        _ => return None,
    })
}

struct Cursor<'a> {
    path: &'a Path,
    data: &'a [u8],
    pos: usize,
}

impl<'a> Cursor<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], DataError> {
        if self.pos + n > self.data.len() {
            return Err(bad(self.path, format!("truncated binary file at byte {}", self.pos)));
        }
        let s = &self.data[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }
    fn u64(&mut self) -> Result<u64, DataError> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().expect("8 bytes")))
    }
    fn i32(&mut self) -> Result<i32, DataError> {
        Ok(i32::from_le_bytes(self.take(4)?.try_into().expect("4 bytes")))
    }
    fn f64(&mut self) -> Result<f64, DataError> {
        Ok(f64::from_le_bytes(self.take(8)?.try_into().expect("8 bytes")))
    }
    /// A record count: each record needs at least `min_record` bytes, so a count the rest of the
    /// file cannot hold is an error (naming the count), not a loop or an allocation.
    fn count(&mut self, what: &str, min_record: usize) -> Result<usize, DataError> {
        let n = self.u64()?;
        let left = (self.data.len() - self.pos) as u64;
        if n > left / min_record as u64 {
            return Err(bad(
                self.path,
                format!("declares {n} {what} but the {left} bytes that follow hold at most {}", left / min_record as u64),
            ));
        }
        Ok(n as usize)
    }
}

fn read_cameras_bin(path: &Path) -> Result<HashMap<u32, ColmapCamera>, DataError> {
    let data = std::fs::read(path).map_err(|e| bad(path, format!("cannot read: {e}")))?;
    let mut c = Cursor { path, data: &data, pos: 0 };
    // id, model, width, height, at least 3 parameters
    let n = c.count("cameras", 4 + 4 + 8 + 8 + 3 * 8)?;
    let mut out = HashMap::new();
    for _ in 0..n {
        let id = c.i32()? as u32;
        let model_id = c.i32()?;
        let (model, np) = model_name(model_id).ok_or_else(|| bad(path, format!("unknown camera model id {model_id}")))?;
        let (w, h) = (c.u64()?, c.u64()?);
        let max = crate::image_io::MAX_IMAGE_SIDE as u64;
        if w == 0 || h == 0 || w > max || h > max {
            return Err(bad(path, format!("camera {id} declares an image size {w}x{h} out of range (1..={max})")));
        }
        let (width, height) = (w as usize, h as usize);
        let params = (0..np).map(|_| c.f64()).collect::<Result<Vec<_>, _>>()?;
        out.insert(id, ColmapCamera { model: model.into(), width, height, params });
    }
    Ok(out)
}

fn read_images_bin(path: &Path) -> Result<Vec<ColmapImage>, DataError> {
    let data = std::fs::read(path).map_err(|e| bad(path, format!("cannot read: {e}")))?;
    let mut c = Cursor { path, data: &data, pos: 0 };
    // id, quaternion, translation, camera id, name terminator, point count
    let n = c.count("images", 4 + 32 + 24 + 4 + 1 + 8)?;
    let mut out = Vec::new();
    for _ in 0..n {
        let _id = c.i32()?;
        let q = [c.f64()?, c.f64()?, c.f64()?, c.f64()?];
        let t = [c.f64()?, c.f64()?, c.f64()?];
        let camera_id = c.i32()? as u32;
        let mut name = Vec::new();
        loop {
            let b = c.take(1)?[0];
            if b == 0 {
                break;
            }
            name.push(b);
        }
        let np = c.count("2-D points", 24)?;
        c.take(np * 24)?;
        out.push(ColmapImage { q, t, camera_id, name: String::from_utf8_lossy(&name).into_owned() });
    }
    Ok(out)
}

fn parse_nums(path: &Path, line_no: usize, toks: &[&str]) -> Result<Vec<f64>, DataError> {
    toks.iter()
        .map(|t| t.parse::<f64>().map_err(|_| bad(path, format!("line {line_no}: {t:?} is not a number"))))
        .collect()
}

fn read_cameras_txt(path: &Path) -> Result<HashMap<u32, ColmapCamera>, DataError> {
    let text = read_text_bounded(path, MAX_COLMAP_TEXT_BYTES)?;
    let mut out = HashMap::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let toks: Vec<&str> = line.split_whitespace().collect();
        if toks.len() < 5 {
            return Err(bad(path, format!("line {}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS", i + 1)));
        }
        let id = toks[0].parse::<u32>().map_err(|_| bad(path, format!("line {}: bad camera id", i + 1)))?;
        let wh = parse_nums(path, i + 1, &toks[2..4])?;
        let (width, height) =
            (declared_side(path, &format!("line {}: width", i + 1), wh[0])?, declared_side(path, &format!("line {}: height", i + 1), wh[1])?);
        let params = parse_nums(path, i + 1, &toks[4..])?;
        out.insert(id, ColmapCamera { model: toks[1].to_string(), width, height, params });
    }
    Ok(out)
}

fn read_images_txt(path: &Path) -> Result<Vec<ColmapImage>, DataError> {
    let text = read_text_bounded(path, MAX_COLMAP_TEXT_BYTES)?;
    // Two lines per image; the second (2D points) may be empty, so only comment lines are skipped.
    let lines: Vec<(usize, &str)> = text.lines().enumerate().filter(|(_, l)| !l.trim_start().starts_with('#')).collect();
    let mut out = Vec::new();
    let mut k = 0;
    while k < lines.len() {
        let (no, line) = lines[k];
        k += 2;
        if line.trim().is_empty() {
            k -= 1; // a stray blank line at the end
            continue;
        }
        let toks: Vec<&str> = line.split_whitespace().collect();
        if toks.len() < 10 {
            return Err(bad(path, format!("line {}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME", no + 1)));
        }
        let v = parse_nums(path, no + 1, &toks[1..8])?;
        let camera_id = toks[8].parse::<u32>().map_err(|_| bad(path, format!("line {}: bad camera id", no + 1)))?;
        out.push(ColmapImage { q: [v[0], v[1], v[2], v[3]], t: [v[4], v[5], v[6]], camera_id, name: toks[9..].join(" ") });
    }
    Ok(out)
}

fn intrinsics(path: &Path, c: &ColmapCamera) -> Result<(f64, f64, f64, f64, Option<Distortion>), DataError> {
    let p = &c.params;
    let need = match c.model.as_str() {
        "SIMPLE_PINHOLE" => 3,
        "PINHOLE" | "SIMPLE_RADIAL" => 4,
        "RADIAL" => 5,
        "OPENCV" => 8,
        m => return Err(bad(path, format!("camera model {m} is not supported (pinhole, radial or OPENCV only)"))),
    };
    if p.len() != need {
        return Err(bad(path, format!("camera model {} needs {need} parameters, got {}", c.model, p.len())));
    }
    if p.iter().any(|v| !v.is_finite()) {
        return Err(bad(path, format!("camera model {}: parameters {p:?} are not all finite", c.model)));
    }
    let d = |k1, k2, p1, p2| Some(Distortion { k1, k2, k3: 0.0, p1, p2 });
    Ok(match c.model.as_str() {
        "SIMPLE_PINHOLE" => (p[0], p[0], p[1], p[2], None),
        "PINHOLE" => (p[0], p[1], p[2], p[3], None),
        "SIMPLE_RADIAL" => (p[0], p[0], p[1], p[2], d(p[3], 0.0, 0.0, 0.0)),
        "RADIAL" => (p[0], p[0], p[1], p[2], d(p[3], p[4], 0.0, 0.0)),
        _ => (p[0], p[1], p[2], p[3], d(p[4], p[5], p[6], p[7])),
    })
}

pub(crate) fn read(path: &Path) -> Result<(Vec<RawView>, BoundHint), DataError> {
    let model = find_model(path).ok_or_else(|| bad(path, "no COLMAP model (sparse/0/cameras.bin or .txt)"))?;
    let (cams, cam_file, imgs, img_file) = if model.join("cameras.bin").is_file() {
        let (cf, imf) = (model.join("cameras.bin"), model.join("images.bin"));
        (read_cameras_bin(&cf)?, cf, read_images_bin(&imf)?, imf)
    } else {
        let (cf, imf) = (model.join("cameras.txt"), model.join("images.txt"));
        (read_cameras_txt(&cf)?, cf, read_images_txt(&imf)?, imf)
    };
    // The scene root holds images/ (the model may be <root>/sparse/0 or <root>/sparse).
    let root = [path.to_path_buf(), model.clone(), model.join(".."), model.join("..").join("..")]
        .into_iter()
        .find(|d| d.join("images").is_dir())
        .ok_or_else(|| bad(path, "no images/ folder next to the COLMAP model"))?;
    if imgs.is_empty() {
        return Err(bad(&img_file, "the model lists no images"));
    }
    if cams.is_empty() {
        return Err(bad(&cam_file, "the model lists no cameras"));
    }
    let mask_dir = root.join("masks");
    let mut imgs = imgs;
    imgs.sort_by(|a, b| a.name.cmp(&b.name));
    let mut views = Vec::new();
    for im in imgs {
        let c = cams
            .get(&im.camera_id)
            .ok_or_else(|| bad(&img_file, format!("image {} uses camera {} not in {}", im.name, im.camera_id, cam_file.display())))?;
        let (fx, fy, cx, cy, dist) = intrinsics(&cam_file, c)?;
        let qn = (im.q.iter().map(|x| x * x).sum::<f64>()).sqrt();
        if !(qn.is_finite() && (qn - 1.0).abs() < 1e-3) {
            return Err(bad(&img_file, format!("image {}: quaternion norm {qn:.4} is not a rotation", im.name)));
        }
        if im.t.iter().any(|v| !v.is_finite()) {
            return Err(bad(&img_file, format!("image {}: translation {:?} is not finite", im.name, im.t)));
        }
        let q = DQuat::from_xyzw(im.q[1], im.q[2], im.q[3], im.q[0]).normalize();
        let r_cw = DMat3::from_quat(q);
        let t = DVec3::from_array(im.t);
        let r_wc = r_cw.transpose();
        let camera = Camera {
            width: c.width,
            height: c.height,
            fx,
            fy,
            cx,
            cy,
            distortion: dist.filter(|d| !d.is_zero()),
            world_from_camera: world_from_camera(r_wc, -(r_wc * t)),
        };
        let image_path = root.join("images").join(&im.name);
        if !image_path.is_file() {
            return Err(bad(&image_path, format!("image listed in {} not found", img_file.display())));
        }
        let stem = Path::new(&im.name).file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        let mask_path = if mask_dir.is_dir() {
            let cands = [mask_dir.join(&im.name), mask_dir.join(format!("{}.png", im.name)), mask_dir.join(format!("{stem}.png"))];
            Some(cands.iter().find(|p| p.is_file()).cloned().ok_or_else(|| bad(&mask_dir, format!("no mask for image {}", im.name)))?)
        } else {
            None
        };
        views.push(RawView { name: stem, split: Split::Train, camera, image_path, mask_path, alpha_mask: false, sources: vec![cam_file.clone(), img_file.clone()] });
    }
    Ok((views, BoundHint::default()))
}
