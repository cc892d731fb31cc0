//! NeRF/Blender and nerfstudio `transforms*.json`.
//!
//! - A folder with `transforms_{train,val,test}.json` (NeRF/Blender: one file per split), or a single
//!   `transforms.json` (nerfstudio: every frame is `train` unless listed in `val_filenames`/`test_filenames`).
//! - Intrinsics: `fl_x, fl_y, cx, cy, w, h` (nerfstudio, top level or per frame; `cx, cy` in the pixel-corner
//!   convention, as nerfstudio generates rays through pixel + 0.5), else `camera_angle_x` (horizontal FOV;
//!   `camera_angle_y` if present) with the principal point at the image centre and the size from the image.
//! - Distortion `k1, k2, k3, p1, p2` (camera_model OPENCV/PINHOLE) is applied in ray generation; `k4` or the
//!   OPENCV_FISHEYE / EQUIRECTANGULAR models are refused.
//! - `transform_matrix`: camera-to-world with OpenGL camera axes (−Z forward, +Y up); converted to OpenCV axes.
//! - Mask: per-frame `mask_path`, else the image's alpha channel.
//! - A `scene.json` beside it written by `scripts/make_scene.py` supplies the known object bound.

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use glam::{DMat3, DVec3};
use serde_json::Value;

use super::normalise::BoundHint;
use super::{check_rotation, declared_side, image_size, resolve_image, world_from_camera, Camera, Distortion, RawView, Split};
use crate::util::{read_json_value, DataError};

/// The transforms files of a folder (or the file itself), with their split.
pub(crate) fn find_files(path: &Path) -> Result<Vec<(PathBuf, Option<Split>)>, DataError> {
    if path.is_file() {
        let name = path.file_name().map(|f| f.to_string_lossy().to_lowercase()).unwrap_or_default();
        let split = if name.contains("train") {
            Some(Split::Train)
        } else if name.contains("val") {
            Some(Split::Val)
        } else if name.contains("test") {
            Some(Split::Test)
        } else {
            None
        };
        return Ok(vec![(path.to_path_buf(), split)]);
    }
    let mut out = Vec::new();
    for (name, split) in
        [("transforms_train.json", Split::Train), ("transforms_val.json", Split::Val), ("transforms_test.json", Split::Test)]
    {
        let p = path.join(name);
        if p.is_file() {
            out.push((p, Some(split)));
        }
    }
    if out.is_empty() {
        let p = path.join("transforms.json");
        if p.is_file() {
            out.push((p, None));
        }
    }
    if out.is_empty() {
        return Err(DataError::new(path, "no transforms*.json"));
    }
    Ok(out)
}

fn num(v: &Value, key: &str) -> Option<f64> {
    v.get(key).and_then(Value::as_f64)
}

/// Look a key up in the frame first, then the file's top level.
fn field(frame: &Value, top: &Value, key: &str) -> Option<f64> {
    num(frame, key).or_else(|| num(top, key))
}

fn bad(path: &Path, what: impl Into<String>) -> DataError {
    DataError::new(path, what.into())
}

pub(crate) fn read(path: &Path) -> Result<(Vec<RawView>, BoundHint), DataError> {
    let files = find_files(path)?;
    let mut views = Vec::new();
    for (file, split) in &files {
        read_file(file, *split, &mut views)?;
    }
    let dir = if path.is_file() { path.parent().unwrap_or(Path::new(".")).to_path_buf() } else { path.to_path_buf() };
    let hint = generated_scene_bound(&dir)?;
    Ok((views, hint))
}

fn read_file(file: &Path, split: Option<Split>, views: &mut Vec<RawView>) -> Result<(), DataError> {
    let top = read_json_value(file)?;
    let dir = file.parent().unwrap_or(Path::new("."));
    let frames = top.get("frames").and_then(Value::as_array).ok_or_else(|| bad(file, "no \"frames\" array"))?;
    if frames.is_empty() {
        return Err(bad(file, "\"frames\" is empty"));
    }
    let listed = |key: &str| -> HashSet<String> {
        top.get(key)
            .and_then(Value::as_array)
            .map(|a| a.iter().filter_map(Value::as_str).map(|s| s.trim_start_matches("./").to_string()).collect())
            .unwrap_or_default()
    };
    let (val_names, test_names) = (listed("val_filenames"), listed("test_filenames"));
    for (i, frame) in frames.iter().enumerate() {
        let what = format!("frame {i}");
        let fp = frame
            .get("file_path")
            .and_then(Value::as_str)
            .ok_or_else(|| bad(file, format!("{what}: no \"file_path\"")))?;
        let base = dir.join(fp);
        let image_path = resolve_image(&base).ok_or_else(|| bad(&base, format!("image of {what} in {} not found", file.display())))?;
        let model = frame.get("camera_model").or_else(|| top.get("camera_model")).and_then(Value::as_str).unwrap_or("OPENCV");
        if !matches!(model, "OPENCV" | "PINHOLE" | "SIMPLE_PINHOLE") {
            return Err(bad(file, format!("{what}: camera_model {model} is not supported (only pinhole / OPENCV)")));
        }
        if field(frame, &top, "k4").is_some_and(|k| k != 0.0) {
            return Err(bad(file, format!("{what}: distortion k4 (fisheye) is not supported")));
        }
        let (w, h) = match (field(frame, &top, "w"), field(frame, &top, "h")) {
            (Some(w), Some(h)) => (declared_side(file, &format!("{what}: w"), w)?, declared_side(file, &format!("{what}: h"), h)?),
            _ => image_size(&image_path)?,
        };
        let (fx, fy, cx, cy) = if let Some(fx) = field(frame, &top, "fl_x") {
            let fy = field(frame, &top, "fl_y").unwrap_or(fx);
            (fx, fy, field(frame, &top, "cx").unwrap_or(w as f64 / 2.0), field(frame, &top, "cy").unwrap_or(h as f64 / 2.0))
        } else if let Some(ax) = field(frame, &top, "camera_angle_x") {
            if !(ax > 0.0 && ax < std::f64::consts::PI) {
                return Err(bad(file, format!("camera_angle_x = {ax} is not a field of view in radians")));
            }
            let fx = 0.5 * w as f64 / (0.5 * ax).tan();
            let fy = match field(frame, &top, "camera_angle_y") {
                Some(ay) if !(ay > 0.0 && ay < std::f64::consts::PI) => {
                    return Err(bad(file, format!("camera_angle_y = {ay} is not a field of view in radians")));
                }
                Some(ay) => 0.5 * h as f64 / (0.5 * ay).tan(),
                None => fx,
            };
            (fx, fy, w as f64 / 2.0, h as f64 / 2.0)
        } else {
            return Err(bad(file, format!("{what}: no intrinsics (camera_angle_x or fl_x)")));
        };
        if !(fx > 0.0 && fy > 0.0 && fx.is_finite() && fy.is_finite()) {
            return Err(bad(file, format!("{what}: focal length must be positive")));
        }
        if !(cx.is_finite() && cy.is_finite()) {
            return Err(bad(file, format!("{what}: principal point ({cx}, {cy}) is not finite")));
        }
        let d = Distortion {
            k1: field(frame, &top, "k1").unwrap_or(0.0),
            k2: field(frame, &top, "k2").unwrap_or(0.0),
            k3: field(frame, &top, "k3").unwrap_or(0.0),
            p1: field(frame, &top, "p1").unwrap_or(0.0),
            p2: field(frame, &top, "p2").unwrap_or(0.0),
        };
        if [d.k1, d.k2, d.k3, d.p1, d.p2].iter().any(|v| !v.is_finite()) {
            return Err(bad(file, format!("{what}: distortion coefficients are not finite")));
        }
        let m = parse_matrix(file, &what, frame.get("transform_matrix"))?;
        // OpenGL camera axes (x right, y up, z back) -> OpenCV (x right, y down, z forward).
        let r_gl = DMat3::from_cols(m[0], m[1], m[2]);
        check_rotation(file, &what, r_gl, 1e-3)?;
        let r_cv = DMat3::from_cols(m[0], -m[1], -m[2]);
        let camera = Camera {
            width: w,
            height: h,
            fx,
            fy,
            cx,
            cy,
            distortion: (!d.is_zero()).then_some(d),
            world_from_camera: world_from_camera(r_cv, m[3]),
        };
        let key = fp.trim_start_matches("./").to_string();
        let split = split.unwrap_or(if test_names.contains(&key) {
            Split::Test
        } else if val_names.contains(&key) {
            Split::Val
        } else {
            Split::Train
        });
        let mask_path = match frame.get("mask_path").and_then(Value::as_str) {
            Some(mp) => {
                let p = dir.join(mp);
                Some(resolve_image(&p).ok_or_else(|| bad(&p, format!("mask of {what} in {} not found", file.display())))?)
            }
            None => None,
        };
        let name = Path::new(fp).file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| format!("{i}"));
        views.push(RawView { name, split, camera, image_path, mask_path, alpha_mask: true, sources: vec![file.to_path_buf()] });
    }
    Ok(())
}

/// A 4×4 row-major JSON matrix → its first three columns and the translation (as world vectors).
fn parse_matrix(file: &Path, what: &str, v: Option<&Value>) -> Result<[DVec3; 4], DataError> {
    let rows = v.and_then(Value::as_array).ok_or_else(|| bad(file, format!("{what}: no \"transform_matrix\"")))?;
    let mut m = [[0.0f64; 4]; 4];
    if rows.len() < 3 {
        return Err(bad(file, format!("{what}: transform_matrix must be 4x4")));
    }
    for (r, row) in rows.iter().take(4).enumerate() {
        let row = row.as_array().filter(|a| a.len() == 4).ok_or_else(|| bad(file, format!("{what}: transform_matrix must be 4x4")))?;
        for (c, x) in row.iter().enumerate() {
            m[r][c] = x.as_f64().filter(|x| x.is_finite()).ok_or_else(|| bad(file, format!("{what}: transform_matrix has a non-number")))?;
        }
    }
    let col = |c: usize| DVec3::new(m[0][c], m[1][c], m[2][c]);
    Ok([col(0), col(1), col(2), col(3)])
}

/// The object bound recorded by `scripts/make_scene.py` (`scene.json` → `bound`), if present.
fn generated_scene_bound(dir: &Path) -> Result<BoundHint, DataError> {
    let p = dir.join("scene.json");
    if !p.is_file() {
        return Ok(BoundHint::default());
    }
    let v = read_json_value(&p)?;
    let Some(b) = v.get("bound") else { return Ok(BoundHint::default()) };
    let c = b.get("center").and_then(Value::as_array).filter(|a| a.len() == 3);
    let r = b.get("radius").and_then(Value::as_f64);
    match (c, r) {
        (Some(c), Some(r)) if r > 0.0 && r.is_finite() && (1.0 / r).is_finite() => {
            let c: Vec<f64> = c.iter().filter_map(Value::as_f64).filter(|x| x.is_finite()).collect();
            if c.len() != 3 {
                return Err(bad(&p, "bound.center must be 3 finite numbers"));
            }
            Ok(BoundHint {
                sphere: Some((DVec3::new(c[0], c[1], c[2]), r)),
                exact_unit_sphere: false,
                source: "scene.json bound (generated scene)".into(),
            })
        }
        _ => Err(bad(&p, "bound needs center [x, y, z] and radius > 0")),
    }
}
