//! Scenes in: dataset readers, images, masks, normalisation into the unit sphere, rays.
//!
//! # The internal scene (the contract for training, baking and export)
//!
//! Every reader produces one [`Scene`]: a list of [`View`]s (name, split, linear-RGB image, optional mask
//! in [0, 1]) each with a [`Camera`], plus the [`Normalisation`] that was applied.
//!
//! **Frames.** Cameras are stored in the *normalised* frame: `x_norm = (x_world − center) · scale`, so the
//! object lies inside the unit sphere (IDR convention). The normalisation is a translation and a uniform
//! scale only (no rotation): directions are the same in both frames. [`Normalisation::to_world`] undoes it
//! (exports do). The detected up axis (mean camera up, world frame) is reported, not applied.
//!
//! **Camera axes.** `world_from_camera` maps camera coordinates to the normalised world with OpenCV axes:
//! x right, y down, z forward (the camera looks along +z).
//!
//! **Pixel coordinates.** Continuous, with (0, 0) at the *top-left corner* of the top-left pixel: pixel
//! (i, j) (column i, row j) covers [i, i+1] × [j, j+1] and its centre is (i + 0.5, j + 0.5). `cx, cy` are
//! in this convention (NeRF/Blender and COLMAP use it; OpenCV/IDR, whose integer coordinates are pixel
//! centres, are converted by +0.5 on reading). Downscaling by N divides fx, fy, cx, cy by N exactly.
//!
//! **Distortion.** Optional OpenCV radial-tangential (k1, k2, k3, p1, p2), applied in [`Camera::project`]
//! and inverted (fixed-point iteration) in [`Camera::ray`].
//!
//! **Images.** Linear RGB (sRGB PNG/JPEG decoded, EXR as stored), row-major from the top row.

pub mod cli;
pub mod colmap;
pub mod consistency;
pub mod idr;
pub mod llff;
pub mod normalise;
pub mod texture;
pub mod transforms;

use std::path::{Path, PathBuf};

use glam::{DMat3, DMat4, DVec2, DVec3};
use serde::Serialize;

use crate::image_io::{read_image_linear, read_mask, ImageF32};
use crate::util::DataError;

pub use normalise::Normalisation;

/// OpenCV radial-tangential distortion on normalised image coordinates.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Distortion {
    pub k1: f64,
    pub k2: f64,
    pub k3: f64,
    pub p1: f64,
    pub p2: f64,
}

impl Distortion {
    pub fn is_zero(&self) -> bool {
        [self.k1, self.k2, self.k3, self.p1, self.p2].iter().all(|v| *v == 0.0)
    }
    /// Undistorted normalised coordinates → distorted.
    pub fn apply(&self, p: DVec2) -> DVec2 {
        let (x, y) = (p.x, p.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        DVec2::new(
            x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        )
    }
    /// Distorted → undistorted by fixed-point iteration (as OpenCV's `undistortPoints`).
    pub fn remove(&self, d: DVec2) -> DVec2 {
        let mut p = d;
        for _ in 0..30 {
            let err = self.apply(p) - d;
            p -= err;
            if err.length_squared() < 1e-24 {
                break;
            }
        }
        p
    }
}

/// A pinhole camera (optionally distorted). See the module docs for axes and pixel conventions.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Camera {
    pub width: usize,
    pub height: usize,
    pub fx: f64,
    pub fy: f64,
    /// Principal point, pixel-corner convention (image centre = (width/2, height/2)).
    pub cx: f64,
    pub cy: f64,
    pub distortion: Option<Distortion>,
    /// Camera (OpenCV axes) → normalised world.
    pub world_from_camera: DMat4,
}

impl Camera {
    /// The same camera with `s`× the pixels per axis (each pixel split into s×s sub-pixels).
    pub fn supersampled(&self, s: usize) -> Camera {
        let f = s.max(1) as f64;
        Camera { width: self.width * s.max(1), height: self.height * s.max(1), fx: self.fx * f, fy: self.fy * f, cx: self.cx * f, cy: self.cy * f, ..self.clone() }
    }

    /// Camera centre in the normalised world.
    pub fn center(&self) -> DVec3 {
        self.world_from_camera.w_axis.truncate()
    }
    /// The 3×3 rotation camera → world.
    pub fn rotation(&self) -> DMat3 {
        DMat3::from_mat4(self.world_from_camera)
    }
    /// Viewing direction (camera +z) in the world.
    pub fn forward(&self) -> DVec3 {
        self.world_from_camera.z_axis.truncate().normalize()
    }
    /// Camera "up" (−y) in the world.
    pub fn up(&self) -> DVec3 {
        -self.world_from_camera.y_axis.truncate().normalize()
    }

    /// Ray through the continuous pixel coordinate (px, py) (pixel centre of (i, j) = (i+0.5, j+0.5)):
    /// origin (camera centre) and unit direction, both in the normalised world.
    pub fn ray(&self, px: f64, py: f64) -> (DVec3, DVec3) {
        let mut n = DVec2::new((px - self.cx) / self.fx, (py - self.cy) / self.fy);
        if let Some(d) = &self.distortion {
            n = d.remove(n);
        }
        let dir_cam = DVec3::new(n.x, n.y, 1.0);
        let dir = self.rotation() * dir_cam;
        (self.center(), dir.normalize())
    }

    /// Project a normalised-world point to continuous pixel coordinates; `None` if it is behind the camera.
    pub fn project(&self, p: DVec3) -> Option<DVec2> {
        self.project_camera_point(self.world_from_camera.inverse().transform_point3(p))
    }

    /// Project a point given in this camera's frame (OpenCV axes) to continuous pixel coordinates;
    /// `None` if it is behind the camera.
    pub fn project_camera_point(&self, q: DVec3) -> Option<DVec2> {
        if q.z <= 1e-9 {
            return None;
        }
        let mut n = DVec2::new(q.x / q.z, q.y / q.z);
        if let Some(d) = &self.distortion {
            n = d.apply(n);
        }
        Some(DVec2::new(self.fx * n.x + self.cx, self.fy * n.y + self.cy))
    }

    /// Horizontal field of view in radians (ignoring distortion).
    pub fn fov_x(&self) -> f64 {
        2.0 * (self.width as f64 / (2.0 * self.fx)).atan()
    }

    /// The camera after downscaling its image by an integer factor (image cropped to a multiple of n).
    pub fn downscaled(&self, n: usize) -> Camera {
        let f = n as f64;
        Camera {
            width: self.width / n,
            height: self.height / n,
            fx: self.fx / f,
            fy: self.fy / f,
            cx: self.cx / f,
            cy: self.cy / f,
            ..self.clone()
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, PartialOrd, Ord, Hash)]
#[serde(rename_all = "lowercase")]
pub enum Split {
    Train,
    Val,
    Test,
}

impl Split {
    pub fn name(&self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Val => "val",
            Split::Test => "test",
        }
    }
}

/// One posed image.
#[derive(Clone, Debug)]
pub struct View {
    pub name: String,
    pub split: Split,
    pub camera: Camera,
    /// Linear RGB, 3 channels, `camera.width × camera.height`.
    pub image: ImageF32,
    /// Per-pixel mask in [0, 1] (soft masks kept as weights), same size as the image.
    pub mask: Option<Vec<f32>>,
    /// The image file it came from.
    pub image_path: PathBuf,
}

impl View {
    /// Fraction of mask pixels ≥ 0.5, if there is a mask.
    pub fn mask_coverage(&self) -> Option<f64> {
        self.mask.as_ref().map(|m| m.iter().filter(|v| **v >= 0.5).count() as f64 / m.len().max(1) as f64)
    }
    /// Mask value at the pixel containing (px, py) (1.0 if no mask, 0.0 outside the image).
    pub fn mask_at(&self, px: f64, py: f64) -> f32 {
        if px < 0.0 || py < 0.0 || px >= self.camera.width as f64 || py >= self.camera.height as f64 {
            return 0.0;
        }
        match &self.mask {
            None => 1.0,
            Some(m) => m[py as usize * self.camera.width + px as usize],
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Format {
    /// NeRF/Blender or nerfstudio `transforms*.json`.
    Transforms,
    /// IDR/DTU/NeuS `cameras_sphere.npz` + `image/` + `mask/`.
    Idr,
    /// LLFF `poses_bounds.npy` + `images/` (+ `masks/`).
    Llff,
    /// COLMAP `sparse/0` (.bin or .txt) + `images/` (+ `masks/`).
    Colmap,
}

impl Format {
    pub fn name(&self) -> &'static str {
        match self {
            Format::Transforms => "transforms.json (NeRF/Blender, nerfstudio)",
            Format::Idr => "IDR/DTU/NeuS cameras_sphere.npz",
            Format::Llff => "LLFF poses_bounds.npy",
            Format::Colmap => "COLMAP sparse model",
        }
    }
}

/// Everything a reader found.
#[derive(Clone, Debug)]
pub struct Scene {
    pub format: Format,
    /// The folder (or file) the scene was read from.
    pub source: PathBuf,
    pub views: Vec<View>,
    pub normalisation: Normalisation,
    /// Silhouette agreement between the views; views it excluded are not in `views`.
    pub silhouettes: consistency::SilhouetteCheck,
    /// The views the silhouette check left out, in the same normalised frame: nothing trains on
    /// them, but a command asked to render a camera (`relight` of a test view) still can.
    pub excluded: Vec<View>,
    /// The integer factor the images were read at (1 = full size), as [`ReadOptions::downscale`]
    /// resolved it.
    pub downscale: usize,
    /// Why `Downscale::Auto` read the photos below full size (None at full size or a given factor).
    pub downscale_note: Option<String>,
}

impl Scene {
    pub fn views_in(&self, split: Split) -> impl Iterator<Item = &View> {
        self.views.iter().filter(move |v| v.split == split)
    }
}

/// The image scale a scene is read at.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Downscale {
    /// Full size unless the photos are larger than the model can use or memory should hold: see
    /// [`auto_downscale`].
    #[default]
    Auto,
    /// This integer factor (1 = full size).
    By(usize),
}

impl std::str::FromStr for Downscale {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if s.eq_ignore_ascii_case("auto") {
            return Ok(Self::Auto);
        }
        match s.parse::<usize>() {
            Ok(n) if n >= 1 => Ok(Self::By(n)),
            _ => Err(format!("expected `auto` or an integer factor >= 1, got {s:?}")),
        }
    }
}

impl std::fmt::Display for Downscale {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Auto => f.write_str("auto"),
            Self::By(n) => write!(f, "{n}"),
        }
    }
}

/// The longest image side `Downscale::Auto` reads. The SDF's finest hash-grid level is capped at
/// 1024 cells across the bounding sphere's diameter (`SceneSizes::grid_finest`); where that sphere
/// spans a frame's shorter side, a 3:2 frame of 1536 × 1024 pixels already has one pixel per finest
/// cell, and larger photos add pixels that no level of the model resolves.
pub const AUTO_MAX_SIDE: usize = 1536;
/// The most pixels `Downscale::Auto` reads over all views: about 3.7 GB in memory while training
/// (55 bytes a pixel, measured), and 32 times the pixels a default stage-1 run draws rays through
/// (4096 rays × 500 iterations), so a larger pool adds memory, not information.
pub const AUTO_MAX_PIXELS: usize = 1 << 26;

/// The factor `Downscale::Auto` reads images of these sizes at: the smallest that brings every
/// longer side to at most [`AUTO_MAX_SIDE`] and all views together to at most
/// [`AUTO_MAX_PIXELS`] (1 for photos within both, which the bundled scenes are).
pub fn auto_downscale(sizes: &[(usize, usize)]) -> usize {
    let side = sizes.iter().map(|&(w, h)| w.max(h)).max().unwrap_or(0);
    let mut n = side.div_ceil(AUTO_MAX_SIDE).max(1);
    let pixels = |n: usize| sizes.iter().map(|&(w, h)| (w / n) * (h / n)).sum::<usize>();
    while pixels(n) > AUTO_MAX_PIXELS && n < side.max(1) {
        n += 1;
    }
    n
}

impl Downscale {
    /// The factor for images of these sizes.
    pub fn resolve(self, sizes: &[(usize, usize)]) -> usize {
        match self {
            Self::Auto => auto_downscale(sizes),
            Self::By(n) => n,
        }
    }
}

/// How to read a scene.
#[derive(Clone, Debug)]
pub struct ReadOptions {
    /// Image downscale (intrinsics follow exactly); `Auto` by default.
    pub downscale: Downscale,
    /// Keep the views whose silhouette contradicts the others (see [`consistency`]); they are
    /// still measured and named in the report.
    pub keep_all_views: bool,
}

impl Default for ReadOptions {
    fn default() -> Self {
        Self { downscale: Downscale::Auto, keep_all_views: false }
    }
}

/// A view as a reader produces it: camera in the reader's world frame, image not yet loaded.
#[derive(Clone, Debug)]
pub(crate) struct RawView {
    pub name: String,
    pub split: Split,
    pub camera: Camera,
    pub image_path: PathBuf,
    pub mask_path: Option<PathBuf>,
    /// Use the image's alpha channel as the mask (when there is no mask file).
    pub alpha_mask: bool,
    /// The files the camera came from (named in errors about the camera), main one first.
    pub sources: Vec<PathBuf>,
}

impl RawView {
    fn sources_text(&self) -> String {
        self.sources.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(" and ")
    }
}

/// Detect the format of `path` (a folder or a transforms/npz file).
pub fn detect(path: &Path) -> Result<Format, DataError> {
    if !path.exists() {
        return Err(DataError::new(path, "scene not found"));
    }
    if path.is_file() {
        let name = path.file_name().map(|f| f.to_string_lossy().to_lowercase()).unwrap_or_default();
        return if name.ends_with(".json") {
            Ok(Format::Transforms)
        } else if name.ends_with(".npz") {
            Ok(Format::Idr)
        } else if name == "poses_bounds.npy" {
            Ok(Format::Llff)
        } else {
            Err(DataError::new(path, "not a scene file (expected transforms*.json, cameras*.npz, poses_bounds.npy)"))
        };
    }
    if transforms::find_files(path).is_ok() {
        return Ok(Format::Transforms);
    }
    if path.join("cameras_sphere.npz").exists() || path.join("cameras.npz").exists() {
        return Ok(Format::Idr);
    }
    if path.join("poses_bounds.npy").exists() {
        return Ok(Format::Llff);
    }
    if colmap::find_model(path).is_some() {
        return Ok(Format::Colmap);
    }
    Err(DataError::new(
        path,
        "no scene found: expected transforms*.json, cameras_sphere.npz, poses_bounds.npy or sparse/0 (COLMAP)",
    ))
}

/// Read a scene in any supported format, load images and masks, and normalise it into the unit sphere.
pub fn load(path: &Path, opts: &ReadOptions) -> Result<Scene, DataError> {
    if opts.downscale == Downscale::By(0) {
        return Err(DataError::new(path, "--downscale must be >= 1"));
    }
    let format = detect(path)?;
    let (raw, hint) = match format {
        Format::Transforms => transforms::read(path)?,
        Format::Idr => idr::read(path)?,
        Format::Llff => llff::read(path)?,
        Format::Colmap => colmap::read(path)?,
    };
    if raw.is_empty() {
        return Err(DataError::new(path, "the scene has no views"));
    }
    // Named when the scene cannot be normalised: the problem lies between these files.
    let mut files: Vec<String> = raw.iter().map(RawView::sources_text).collect();
    files.extend(raw.iter().filter_map(|r| r.mask_path.as_ref()?.parent().map(|d| format!("masks in {}", d.display()))));
    files.sort();
    files.dedup();
    let sizes: Vec<(usize, usize)> = raw.iter().map(|r| (r.camera.width, r.camera.height)).collect();
    let downscale = opts.downscale.resolve(&sizes);
    let downscale_note = (opts.downscale == Downscale::Auto && downscale > 1).then(|| {
        let side = sizes.iter().map(|&(w, h)| w.max(h)).max().unwrap_or(0);
        let pixels: usize = sizes.iter().map(|&(w, h)| w * h).sum();
        format!(
            "photos read at 1/{downscale} size (--downscale auto): their longest side is {side} pixels and they hold {:.0} megapixels in all, beyond what training uses ({AUTO_MAX_SIDE} pixels a side, {:.0} megapixels in all); `--downscale 1` reads them at full size",
            pixels as f64 / 1e6,
            AUTO_MAX_PIXELS as f64 / 1e6
        )
    });
    if let Some(note) = &downscale_note {
        tracing::debug!("{note}");
    }
    let views = load_views(raw, downscale)?;
    // Views whose mask contradicts all the others (a failed pose or a wrong mask) would cut the
    // hull, the bound and the mask loss: they are taken out here and reported.
    let (start, half) = normalise::search_cube(&views, &hint);
    let (drop, silhouettes) = consistency::check(&views, start, half, !opts.keep_all_views);
    for e in &silhouettes.excluded {
        tracing::warn!(
            "excluded view {} ({}): its silhouette disagrees with the other views (it alone carves {:.1}% of their hull): a wrong pose or a wrong mask",
            e.name,
            e.image,
            100.0 * e.solo_carve
        );
    }
    if let Some(note) = &silhouettes.note {
        tracing::warn!("{note}");
    }
    let (excluded, views): (Vec<_>, Vec<_>) = views.into_iter().enumerate().partition(|(i, _)| drop.contains(i));
    let views: Vec<View> = views.into_iter().map(|(_, v)| v).collect();
    let normalisation = normalise::compute(path, &views, &hint)
        .map_err(|e| DataError::new(e.path, format!("{} (cameras from {})", e.problem, files.join(", "))))?;
    let to_normalised = |mut v: View| {
        v.camera.world_from_camera = normalisation.camera_to_normalised(v.camera.world_from_camera);
        v
    };
    let views = views.into_iter().map(to_normalised).collect();
    let excluded = excluded.into_iter().map(|(_, v)| to_normalised(v)).collect();
    Ok(Scene { format, source: path.to_path_buf(), views, normalisation, silhouettes, excluded, downscale, downscale_note })
}

fn load_views(raw: Vec<RawView>, n: usize) -> Result<Vec<View>, DataError> {
    use rayon::prelude::*;
    raw.into_par_iter().map(|r| load_view(r, n)).collect()
}

fn load_view(r: RawView, n: usize) -> Result<View, DataError> {
    let source = r.sources.first().cloned().unwrap_or_default();
    check_camera(&source, &format!("{} (camera from {})", r.name, r.sources_text()), &r.camera)?;
    let img = read_image_linear(&r.image_path)?;
    if img.width != r.camera.width || img.height != r.camera.height {
        return Err(DataError::new(
            &r.image_path,
            format!(
                "image is {}x{} but its camera in {} says {}x{}",
                img.width,
                img.height,
                r.sources_text(),
                r.camera.width,
                r.camera.height
            ),
        ));
    }
    let mut mask = None;
    if let Some(mp) = &r.mask_path {
        let (w, h, m) = read_mask(mp)?;
        if (w, h) != (img.width, img.height) {
            return Err(DataError::new(
                mp,
                format!("mask is {w}x{h} but its image {} is {}x{}", r.image_path.display(), img.width, img.height),
            ));
        }
        if !m.iter().any(|v| *v >= 0.5) {
            return Err(DataError::new(mp, "mask is empty (no pixel >= 0.5)"));
        }
        mask = Some(m);
    } else if r.alpha_mask {
        if let Some(a) = img.alpha() {
            if !a.iter().any(|v| *v >= 0.5) {
                return Err(DataError::new(&r.image_path, "alpha mask is empty (no pixel with alpha >= 0.5)"));
            }
            mask = Some(a);
        }
    }
    let rgb = ImageF32 { width: img.width, height: img.height, channels: 3, data: img.rgb() };
    let (image, mask, camera) = if n > 1 {
        if img.width < n || img.height < n {
            return Err(DataError::new(&r.image_path, format!("image too small for --downscale {n}")));
        }
        let image = downscale(&rgb, n);
        let mask = mask.map(|m| {
            let mi = ImageF32 { width: img.width, height: img.height, channels: 1, data: m };
            downscale(&mi, n).data
        });
        (image, mask, r.camera.downscaled(n))
    } else {
        (rgb, mask, r.camera)
    };
    Ok(View { name: r.name, split: r.split, camera, image, mask, image_path: r.image_path })
}

/// Box-filter downscale by an integer factor; the image is cropped to a multiple of `n` on the right and
/// bottom first, so the pixel-corner intrinsics divide exactly.
pub fn downscale(img: &ImageF32, n: usize) -> ImageF32 {
    let (w, h, c) = (img.width / n, img.height / n, img.channels);
    let mut out = ImageF32::new(w, h, c);
    let inv = 1.0 / (n * n) as f32;
    for y in 0..h {
        for x in 0..w {
            for ch in 0..c {
                let mut s = 0.0;
                for dy in 0..n {
                    for dx in 0..n {
                        s += img.data[((y * n + dy) * img.width + x * n + dx) * c + ch];
                    }
                }
                out.data[(y * w + x) * c + ch] = s * inv;
            }
        }
    }
    out
}

/// Check that a 3×3 matrix is a rotation (orthonormal, det +1) within `tol`.
pub(crate) fn check_rotation(path: &Path, what: &str, r: DMat3, tol: f64) -> Result<(), DataError> {
    let rtr = r.transpose() * r;
    let mut err: f64 = 0.0;
    for (i, col) in [rtr.x_axis, rtr.y_axis, rtr.z_axis].iter().enumerate() {
        for j in 0..3 {
            let e = if i == j { 1.0 } else { 0.0 };
            err = err.max((col[j] - e).abs());
        }
    }
    let det = r.determinant();
    if !err.is_finite() || err > tol || (det - 1.0).abs() > tol * 3.0 {
        return Err(DataError::new(
            path,
            format!("{what}: camera rotation is not a rotation matrix (|R^T R - I| = {err:.3e}, det = {det:.4})"),
        ));
    }
    Ok(())
}

/// Find an image file for `stem` (a path with or without an extension).
pub(crate) fn resolve_image(base: &Path) -> Option<PathBuf> {
    if base.is_file() {
        return Some(base.to_path_buf());
    }
    for ext in ["png", "PNG", "jpg", "JPG", "jpeg", "JPEG", "exr", "EXR"] {
        let mut s = base.as_os_str().to_owned();
        s.push(".");
        s.push(ext);
        let p = PathBuf::from(s);
        if p.is_file() {
            return Some(p);
        }
    }
    None
}

/// Image files (png/jpg/jpeg/exr) in a folder, sorted by name.
pub(crate) fn list_images(dir: &Path) -> Result<Vec<PathBuf>, DataError> {
    let rd = std::fs::read_dir(dir).map_err(|e| DataError::new(dir, format!("cannot list folder: {e}")))?;
    let mut out: Vec<PathBuf> = rd
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.is_file()
                && p.extension().is_some_and(|e| {
                    let e = e.to_string_lossy().to_lowercase();
                    matches!(e.as_str(), "png" | "jpg" | "jpeg" | "exr")
                })
        })
        .collect();
    out.sort();
    Ok(out)
}

/// Image size without decoding the pixels (from the header, checked against the image limits).
pub(crate) fn image_size(path: &Path) -> Result<(usize, usize), DataError> {
    crate::image_io::image_dimensions(path)
}

/// Check camera values a file declares: a size within the image limits, finite positive focal
/// lengths, a finite principal point and finite distortion. The error names `source` (the file
/// the camera came from).
pub(crate) fn check_camera(source: &Path, what: &str, c: &Camera) -> Result<(), DataError> {
    let max = crate::image_io::MAX_IMAGE_SIDE;
    if c.width == 0 || c.height == 0 || c.width > max || c.height > max {
        return Err(DataError::new(source, format!("{what}: image size {}x{} is out of range (1..={max})", c.width, c.height)));
    }
    if !(c.fx.is_finite() && c.fy.is_finite() && c.fx > 0.0 && c.fy > 0.0) {
        return Err(DataError::new(source, format!("{what}: focal lengths ({}, {}) must be finite and positive", c.fx, c.fy)));
    }
    if !(c.cx.is_finite() && c.cy.is_finite()) {
        return Err(DataError::new(source, format!("{what}: principal point ({}, {}) is not finite", c.cx, c.cy)));
    }
    if let Some(d) = &c.distortion {
        if [d.k1, d.k2, d.k3, d.p1, d.p2].iter().any(|v| !v.is_finite()) {
            return Err(DataError::new(source, format!("{what}: distortion coefficients are not finite")));
        }
    }
    if !c.world_from_camera.is_finite() {
        return Err(DataError::new(source, format!("{what}: camera pose is not finite")));
    }
    Ok(())
}

/// A size a file declares as a float (JSON, COLMAP text) as an image side: a positive integer
/// within the image limits.
pub(crate) fn declared_side(source: &Path, what: &str, v: f64) -> Result<usize, DataError> {
    let max = crate::image_io::MAX_IMAGE_SIDE;
    if !(v.is_finite() && v >= 1.0 && v <= max as f64 && v.fract() == 0.0) {
        return Err(DataError::new(source, format!("{what}: image size {v} is not an integer in 1..={max}")));
    }
    Ok(v as usize)
}

/// Build a world_from_camera (OpenCV axes) from a camera→world rotation and centre.
pub(crate) fn world_from_camera(r: DMat3, c: DVec3) -> DMat4 {
    DMat4::from_cols(r.x_axis.extend(0.0), r.y_axis.extend(0.0), r.z_axis.extend(0.0), c.extend(1.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auto_downscale_keeps_within_the_side_and_pixel_limits() {
        // Within both: full size (the bundled example, the Ethiopian head, DTU at 400x300).
        assert_eq!(auto_downscale(&[(200, 200); 28]), 1);
        assert_eq!(auto_downscale(&[(512, 512); 66]), 1);
        assert_eq!(auto_downscale(&[(1536, 1024); 40]), 1);
        // The side: 24 MP DSLR frames to 1500 wide; then the pixels: 50 of those are 75 MP, so 1/5.
        assert_eq!(auto_downscale(&[(6000, 4000); 20]), 4);
        assert_eq!(auto_downscale(&[(6000, 4000); 50]), 5);
        // Video frames: 300 of 1920x1080 are 69 MP at 1/3, over the budget: 1/4.
        assert_eq!(auto_downscale(&[(1920, 1080); 300]), 4);
        // The largest view decides the side; no views, no scaling.
        assert_eq!(auto_downscale(&[(800, 600), (3000, 200)]), 2);
        assert_eq!(auto_downscale(&[]), 1);
        for sizes in [vec![(6000, 4000); 50], vec![(1920, 1080); 300], vec![(100_000, 10); 3]] {
            let n = auto_downscale(&sizes);
            let px: usize = sizes.iter().map(|&(w, h)| (w / n) * (h / n)).sum();
            assert!(px <= AUTO_MAX_PIXELS && sizes.iter().all(|&(w, h)| w.max(h).div_ceil(n) <= AUTO_MAX_SIDE), "{n}");
        }
    }

    #[test]
    fn downscale_parses_auto_or_a_positive_factor() {
        assert_eq!("auto".parse::<Downscale>(), Ok(Downscale::Auto));
        assert_eq!("AUTO".parse::<Downscale>(), Ok(Downscale::Auto));
        assert_eq!("3".parse::<Downscale>(), Ok(Downscale::By(3)));
        for bad in ["0", "-1", "1.5", "half", ""] {
            assert!(bad.parse::<Downscale>().is_err(), "{bad}");
        }
        assert_eq!(Downscale::By(2).to_string(), "2");
        assert_eq!(Downscale::Auto.to_string(), "auto");
    }

    fn cam() -> Camera {
        let r = DMat3::from_rotation_y(0.3) * DMat3::from_rotation_x(-0.2);
        Camera {
            width: 64,
            height: 48,
            fx: 50.0,
            fy: 52.0,
            cx: 31.0,
            cy: 25.0,
            distortion: Some(Distortion { k1: -0.1, k2: 0.02, k3: 0.0, p1: 0.001, p2: -0.002 }),
            world_from_camera: world_from_camera(r, DVec3::new(0.2, -0.1, -3.0)),
        }
    }

    #[test]
    fn ray_and_project_are_inverse() {
        let c = cam();
        for &(px, py) in &[(0.5, 0.5), (31.0, 25.0), (63.5, 47.5), (10.2, 40.7)] {
            let (o, d) = c.ray(px, py);
            let p = c.project(o + d * 2.5).unwrap();
            assert!((p.x - px).abs() < 1e-6 && (p.y - py).abs() < 1e-6, "({px},{py}) -> {p}");
        }
        // the principal point looks along +z of the camera
        let mut c2 = c.clone();
        c2.distortion = None;
        let (_, d) = c2.ray(c2.cx, c2.cy);
        assert!((d - c2.forward()).length() < 1e-12);
        assert!(c2.project(c2.center() - c2.forward()).is_none(), "behind the camera");
    }

    #[test]
    fn downscale_keeps_projection_consistent() {
        let mut c = cam();
        c.distortion = None;
        let d = c.downscaled(4);
        let p = DVec3::new(0.1, 0.2, 0.3);
        let (a, b) = (c.project(p).unwrap(), d.project(p).unwrap());
        assert!((a / 4.0 - b).length() < 1e-9);
        let img = ImageF32 { width: 4, height: 2, channels: 1, data: vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0] };
        assert_eq!(downscale(&img, 2).data, vec![3.5, 5.5]);
    }
}
