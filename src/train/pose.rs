//! Camera pose refinement in stage 1 ([`Stage1Config::pose_lr`]): each training view's pose is
//! corrected while the SDF trains, as IDR trains its cameras, so that registration errors of a
//! degree or a few pixels (what structure-from-motion leaves on a hard capture) do not erode the
//! surface.
//!
//! Each view carries a rotation about its own centre and a shift of its centre, applied on the
//! left of its camera-to-world pose: `world_from_camera' = [R(ω)·R | c + δc]`, so its rays become
//! `o' = o + δc`, `d' = R(ω)·d`. The gradient comes from the per-ray gradients of the loss in the
//! ray's origin and direction ([`super::stage1::RayGrads`]): `∂L/∂δc = Σ ∂L/∂o` and, for a
//! rotation `ε` applied on the left of the current one, `∂L/∂ε = Σ d × ∂L/∂d`. Adam runs on that
//! tangent (the step is composed into the stored rotation, then the tangent is zero again), in
//! units of a pixel at the object: a translation unit is the scene's pixel footprint and a
//! rotation unit is the footprint over the camera's distance to the object, so `pose_lr` reads as
//! pixels per step for both.
//!
//! The state is `f32` (rotation vectors and shifts) and its Adam moments, saved with the
//! checkpoint, so a resumed run continues the same curve.

use glam::{DMat4, DQuat, DVec3};
use serde::Serialize;

use super::stage1::{adam_host, Batch, RayGrads};
use crate::backend::{Backend, BackendError};
use crate::nn::adam::{host_grad_norm, AdamConfig, AdamState};
use crate::nn::params::ParamStore;
use crate::scene::{Camera, View};
use crate::util::DataError;
use std::path::Path;

/// Each view's pose correction and its optimiser state.
#[derive(Debug)]
pub struct PoseRefinement {
    /// Rotation vector (axis × angle, radians) of each view's correction.
    pub rotation: Vec<[f32; 3]>,
    /// Shift of each view's centre (normalised world units).
    pub translation: Vec<[f32; 3]>,
    adam: AdamState,
    /// Updates applied.
    pub steps: u64,
}

/// The solution of the 7×7 system `a x = b` (Gaussian elimination with partial pivoting); None
/// where it is singular.
fn solve7(mut a: [[f64; 7]; 7], mut b: [f64; 7]) -> Option<[f64; 7]> {
    for col in 0..7 {
        let piv = (col..7).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))?;
        if a[piv][col].abs() < 1e-12 {
            return None;
        }
        a.swap(col, piv);
        b.swap(col, piv);
        for r in col + 1..7 {
            let f = a[r][col] / a[col][col];
            for k in col..7 {
                a[r][k] -= f * a[col][k];
            }
            b[r] -= f * b[col];
        }
    }
    let mut x = [0f64; 7];
    for r in (0..7).rev() {
        let s: f64 = (r + 1..7).map(|k| a[r][k] * x[k]).sum();
        x[r] = (b[r] - s) / a[r][r];
    }
    Some(x)
}

/// One view's correction as reported (`poses.json`, `train_report.json`).
#[derive(Clone, Debug, Serialize)]
pub struct ViewCorrection {
    pub view: usize,
    pub rotation_deg: f64,
    /// The centre's shift, normalised world units.
    pub translation: f64,
    /// Both as pixels at the object: the shift and the rotation's arc at the object's distance
    /// over the scene's pixel footprint.
    pub translation_px: f64,
    pub rotation_px: f64,
}

/// Parameters per view: 3 translation then 3 rotation.
const PER_VIEW: usize = 6;

impl PoseRefinement {
    pub fn new(host: &Backend, views: usize) -> Self {
        Self { rotation: vec![[0.0; 3]; views], translation: vec![[0.0; 3]; views], adam: AdamState::new(host, PER_VIEW * views), steps: 0 }
    }

    pub fn views(&self) -> usize {
        self.rotation.len()
    }

    fn quat(&self, v: usize) -> DQuat {
        DQuat::from_scaled_axis(DVec3::from(self.rotation[v].map(f64::from)))
    }

    fn shift(&self, v: usize) -> DVec3 {
        DVec3::from(self.translation[v].map(f64::from))
    }

    /// `camera` (view `v`'s as read) with its correction.
    pub fn camera(&self, camera: &Camera, v: usize) -> Camera {
        let q = self.quat(v);
        let r = glam::DMat3::from_quat(q) * camera.rotation();
        let c = camera.center() + self.shift(v);
        Camera { world_from_camera: DMat4::from_cols(r.x_axis.extend(0.0), r.y_axis.extend(0.0), r.z_axis.extend(0.0), c.extend(1.0)), ..camera.clone() }
    }

    /// Move `batch`'s rays (drawn from the cameras as read, `batch.view` their views) by their
    /// views' corrections.
    pub fn apply(&self, batch: &mut Batch) {
        let q: Vec<(glam::Quat, glam::Vec3)> = (0..self.views()).map(|v| (self.quat(v).as_quat(), self.shift(v).as_vec3())).collect();
        for (i, &v) in batch.view.iter().enumerate() {
            let (q, t) = q[v as usize];
            let o = glam::Vec3::from(batch.rays.origins[i]) + t;
            let d = (q * glam::Vec3::from(batch.rays.dirs[i])).normalize();
            batch.rays.origins[i] = o.to_array();
            batch.rays.dirs[i] = d.to_array();
        }
    }

    /// The gradient in each view's `[δc, ε]` (ε: a rotation on the left of the current one) from
    /// the batch's per-ray gradients; `None` when a value is not finite.
    pub fn view_gradient(&self, batch: &Batch, g: &RayGrads) -> Option<Vec<f64>> {
        let mut out = vec![0f64; PER_VIEW * self.views()];
        for (i, &v) in batch.view.iter().enumerate() {
            let (go, gd) = (DVec3::from(g.origin[i].map(f64::from)), DVec3::from(g.dir[i].map(f64::from)));
            let d = DVec3::from(batch.rays.dirs[i].map(f64::from));
            let gr = d.cross(gd);
            let o = &mut out[PER_VIEW * v as usize..PER_VIEW * (v as usize + 1)];
            for a in 0..3 {
                o[a] += go[a];
                o[3 + a] += gr[a];
            }
        }
        out.iter().all(|x| x.is_finite()).then_some(out)
    }

    /// One Adam step of `lr` pixels at the object on the views' gradient `grad`
    /// ([`PoseRefinement::view_gradient`]), `footprint` the scene's pixel footprint and
    /// `distance[v]` view v's distance to the object's centre.
    pub fn step(&mut self, grad: &[f64], lr: f32, footprint: f32, centres: &[[f32; 3]]) -> Result<(), BackendError> {
        let nv = self.views();
        if grad.len() != PER_VIEW * nv || centres.len() != nv {
            return Err(BackendError::Shape(format!("pose refinement: {} gradient values and {} camera centres for {nv} views", grad.len(), centres.len())));
        }
        let distance: Vec<f32> = centres.iter().map(|c| glam::Vec3::from(*c).length()).collect();
        // Units of a pixel at the object: the parameter p = δ / unit, so ∂L/∂p = unit · ∂L/∂δ.
        let unit = |v: usize, k: usize| if k < 3 { footprint as f64 } else { (footprint / distance[v].max(1e-6)) as f64 };
        let g: Vec<f32> = (0..PER_VIEW * nv).map(|i| (grad[i] * unit(i / PER_VIEW, i % PER_VIEW)) as f32).collect();
        if host_grad_norm(&[&g]).is_none() {
            return Err(BackendError::Config("pose refinement: a non-finite gradient reached the optimiser".into()));
        }
        let mut p = vec![0f32; PER_VIEW * nv];
        let cfg = AdamConfig { eps: 1e-15, ..AdamConfig::with_lr(lr) };
        adam_host(&cfg, &mut p, g, &mut self.adam, lr)?;
        for v in 0..nv {
            let s = &p[PER_VIEW * v..PER_VIEW * (v + 1)];
            for a in 0..3 {
                self.translation[v][a] += (s[a] as f64 * unit(v, a)) as f32;
            }
            let e = DVec3::new(s[3] as f64, s[4] as f64, s[5] as f64) * unit(v, 3);
            let q = (DQuat::from_scaled_axis(e) * self.quat(v)).normalize();
            self.rotation[v] = q.to_scaled_axis().as_vec3().to_array();
        }
        self.remove_common_motion(centres);
        self.steps += 1;
        Ok(())
    }

    /// Take out of the corrections the part every view shares: a turn, a shift and a scale of the
    /// whole rig about the object (least squares, each view's residual in pixels at the object),
    /// which moves the cameras and the object together and which no photo can tell; left in, it
    /// drifts the run's frame off the one the poses were read in (the frame held-out views and a
    /// ground truth are in) and the SDF follows. Needs 4 views at least (7 shared unknowns).
    fn remove_common_motion(&mut self, centres: &[[f32; 3]]) {
        let nv = self.views();
        if nv < 4 {
            return;
        }
        // Unknowns g = [ω (3), t (3), s]: view i's correction ≈ a turn ω and, for its centre c,
        // a move ω × c + t + s·c.
        let mut ata = [[0f64; 7]; 7];
        let mut atb = [0f64; 7];
        let mut add = |row: [f64; 7], b: f64| {
            for i in 0..7 {
                atb[i] += row[i] * b;
                for j in 0..7 {
                    ata[i][j] += row[i] * row[j];
                }
            }
        };
        for v in 0..nv {
            let c = DVec3::from(centres[v].map(f64::from));
            let d = c.length().max(1e-6);
            let w = self.quat(v).to_scaled_axis();
            let t = self.shift(v);
            for a in 0..3 {
                let mut row = [0f64; 7];
                row[a] = d;
                add(row, d * w[a]);
            }
            // (ω × c)_a = Σ_b (e_b × c)_a ω_b.
            for a in 0..3 {
                let mut row = [0f64; 7];
                for b in 0..3 {
                    row[b] = DVec3::AXES[b].cross(c)[a];
                }
                row[3 + a] = 1.0;
                row[6] = c[a];
                add(row, t[a]);
            }
        }
        let Some(g) = solve7(ata, atb) else { return };
        let (rg, tg, scale) = (DQuat::from_scaled_axis(DVec3::new(g[0], g[1], g[2])), DVec3::new(g[3], g[4], g[5]), 1.0 + g[6]);
        if !(scale > 0.5 && g.iter().all(|x| x.is_finite())) {
            return;
        }
        // Undo that similarity on every corrected camera.
        let inv = rg.inverse();
        for v in 0..nv {
            let c = DVec3::from(centres[v].map(f64::from));
            let q = (inv * self.quat(v)).normalize();
            let centre = inv * (c + self.shift(v) - tg) / scale;
            self.rotation[v] = q.to_scaled_axis().as_vec3().to_array();
            self.translation[v] = (centre - c).as_vec3().to_array();
        }
    }

    /// Each view's correction, in pixels at the object as well.
    pub fn corrections(&self, footprint: f32, distance: &[f32]) -> Vec<ViewCorrection> {
        (0..self.views())
            .map(|v| {
                let angle = self.quat(v).to_axis_angle().1;
                let angle = if angle > std::f64::consts::PI { 2.0 * std::f64::consts::PI - angle } else { angle };
                let t = self.shift(v).length();
                let fp = footprint.max(1e-12) as f64;
                ViewCorrection {
                    view: v,
                    rotation_deg: angle.to_degrees(),
                    translation: t,
                    translation_px: t / fp,
                    rotation_px: angle * distance.get(v).copied().unwrap_or(0.0) as f64 / fp,
                }
            })
            .collect()
    }

    pub fn save(&self, host: &Backend, st: &mut ParamStore) -> Result<(), BackendError> {
        let nv = self.views();
        st.insert("pose_rotation", &[nv, 3], self.rotation.iter().flatten().copied().collect())?;
        st.insert("pose_translation", &[nv, 3], self.translation.iter().flatten().copied().collect())?;
        st.put_adam_state(host, "pose", &self.adam)?;
        st.metadata.insert("pose_steps".into(), self.steps.to_string());
        Ok(())
    }

    /// The state [`PoseRefinement::save`] wrote, or None where the checkpoint has none.
    pub fn load(host: &Backend, st: &ParamStore) -> Result<Option<Self>, String> {
        let (Some(r), Some(t)) = (st.data("pose_rotation"), st.data("pose_translation")) else { return Ok(None) };
        let views = r.len() / 3;
        if r.len() != 3 * views || t.len() != 3 * views {
            return Err(format!("the pose refinement holds {} and {} values, but this run has {views} views (3 each)", r.len(), t.len()));
        }
        if r.iter().chain(t).any(|x| !x.is_finite()) {
            return Err("the pose refinement holds NaN/Inf values".into());
        }
        let mut p = Self::new(host, views);
        p.rotation = r.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
        p.translation = t.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
        if let Some(a) = st.adam_state(host, "pose").map_err(|e| e.to_string())? {
            if a.m.len() != PER_VIEW * views {
                return Err(format!("the pose refinement's optimiser holds {} values, but this run's {views} views need {}", a.m.len(), PER_VIEW * views));
            }
            p.adam = a;
        }
        p.steps = st.metadata.get("pose_steps").and_then(|s| s.parse().ok()).unwrap_or(0);
        Ok(Some(p))
    }
}

/// The refined poses' file in a stage-1 run folder (stage 2 trains through them).
pub const POSES: &str = "poses.json";

/// Write [`POSES`] (each training view's name, photo, corrected camera-to-world pose in the
/// normalised world, column-major, and its correction) into `run_dir`, atomically; returns the
/// summary `train_report.json` keeps.
pub fn write_poses(run_dir: &Path, p: &PoseRefinement, views: &[&View], refined: &[Camera], footprint: f32, distance: &[f32]) -> Result<serde_json::Value, DataError> {
    let corr = p.corrections(footprint, distance);
    let per_view: Vec<serde_json::Value> = views
        .iter()
        .zip(refined)
        .zip(&corr)
        .map(|((v, c), k)| {
            serde_json::json!({
                "name": v.name,
                "image": v.image_path.display().to_string(),
                "world_from_camera": c.world_from_camera.to_cols_array(),
                "correction": k,
            })
        })
        .collect();
    let n = corr.len().max(1) as f64;
    let mean = |f: &dyn Fn(&ViewCorrection) -> f64| corr.iter().map(f).sum::<f64>() / n;
    let max = |f: &dyn Fn(&ViewCorrection) -> f64| corr.iter().map(f).fold(0.0, f64::max);
    let summary = serde_json::json!({
        "views": corr.len(),
        "updates": p.steps,
        "mean_rotation_deg": mean(&|k| k.rotation_deg),
        "max_rotation_deg": max(&|k| k.rotation_deg),
        "mean_translation_px": mean(&|k| k.translation_px),
        "max_translation_px": max(&|k| k.translation_px),
        "file": POSES,
    });
    let doc = serde_json::json!({
        "about": "stage-1 camera pose refinement: each training view's corrected camera-to-world pose (OpenCV camera axes, the scene's normalised world, column-major 4x4)",
        "summary": summary,
        "views": per_view,
    });
    crate::util::atomic_write(&run_dir.join(POSES), serde_json::to_string_pretty(&doc).unwrap_or_default().as_bytes())?;
    Ok(summary)
}

/// Give `scene`'s training views the poses a stage-1 run refined ([`POSES`] in `run_dir`, if
/// it has one): returns how many views took one. A view of the run the scene no longer has, or a
/// malformed file, is an error naming the file.
pub fn apply_run_poses(run_dir: &Path, views: &mut [View]) -> Result<usize, DataError> {
    let path = run_dir.join(POSES);
    if !path.is_file() {
        return Ok(0);
    }
    let text = crate::util::read_text_bounded(&path, 64 << 20).map_err(|e| DataError::new(&path, e.to_string()))?;
    let doc: serde_json::Value = serde_json::from_str(&text).map_err(|e| DataError::new(&path, format!("not valid JSON: {e}")))?;
    let list = doc["views"].as_array().ok_or_else(|| DataError::new(&path, "no \"views\" list"))?;
    // Stage 1 trains on the training split, or on every view where the scene has none.
    let any_train = views.iter().any(|v| v.split == crate::scene::Split::Train);
    let mut n = 0;
    for e in list {
        let name = e["name"].as_str().ok_or_else(|| DataError::new(&path, "a view without a \"name\""))?;
        let m: Vec<f64> = e["world_from_camera"].as_array().map(|a| a.iter().filter_map(|x| x.as_f64()).collect()).unwrap_or_default();
        if m.len() != 16 || m.iter().any(|x| !x.is_finite()) {
            return Err(DataError::new(&path, format!("view {name:?}: \"world_from_camera\" must be 16 finite numbers")));
        }
        let Some(v) = views.iter_mut().find(|v| (!any_train || v.split == crate::scene::Split::Train) && v.name == name) else {
            return Err(DataError::new(&path, format!("view {name:?} of the stage-1 run is not among the scene's training views")));
        };
        v.camera.world_from_camera = DMat4::from_cols_slice(&m);
        n += 1;
    }
    Ok(n)
}

/// The mean distance in pixels between where cameras `a` and `b` put the centre of the
/// normalised world and six points at half its radius on the axes: a pose error as the photos see
/// it (a small turn and a shift across the view look alike from afar). None where a point is
/// behind either camera.
pub fn reprojection_error_px(a: &Camera, b: &Camera) -> Option<f64> {
    let pts = [[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [-0.5, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, -0.5, 0.0], [0.0, 0.0, 0.5], [0.0, 0.0, -0.5]];
    let mut sum = 0.0;
    for p in pts {
        let p = DVec3::from(p);
        sum += (a.project(p)? - b.project(p)?).length();
    }
    Some(sum / pts.len() as f64)
}

/// `cameras` each turned about its own centre by a normal random angle of `degrees` (about a
/// random axis) and its centre shifted by a normal random step whose size at the camera's
/// distance from the object is the same angle: what `bench train --pose-noise` trains on.
pub fn perturbed(cameras: &[Camera], degrees: f64, seed: u64) -> Vec<Camera> {
    use rand_distr::{Distribution, StandardNormal};
    let mut rng = crate::util::rng(seed ^ 0x9053_0015);
    cameras
        .iter()
        .map(|c| {
            let mut n = || -> f64 { StandardNormal.sample(&mut rng) };
            let axis = DVec3::new(n(), n(), n()).normalize_or(DVec3::Y);
            let angle = degrees.to_radians() * n();
            let shift = DVec3::new(n(), n(), n()) * (degrees.to_radians() * c.center().length() / 3f64.sqrt());
            let r = glam::DMat3::from_axis_angle(axis, angle) * c.rotation();
            let centre = c.center() + shift;
            Camera { world_from_camera: DMat4::from_cols(r.x_axis.extend(0.0), r.y_axis.extend(0.0), r.z_axis.extend(0.0), centre.extend(1.0)), ..c.clone() }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image_io::ImageF32;
    use crate::scene::Split;

    fn view(name: &str, split: Split, x: f64) -> View {
        let camera = Camera { width: 4, height: 4, fx: 4.0, fy: 4.0, cx: 2.0, cy: 2.0, distortion: None, world_from_camera: DMat4::from_translation(DVec3::new(x, 0.0, -3.0)) };
        View { name: name.into(), split, camera, image: ImageF32::new(4, 4, 3), mask: None, image_path: format!("{name}.png").into() }
    }

    #[test]
    fn a_step_moves_each_view_by_about_the_rate_and_the_cameras_and_rays_agree() {
        let host = Backend::cpu();
        let mut p = PoseRefinement::new(&host, 2);
        // View 0: the loss falls as its centre moves +x and as it turns about +y; view 1 has none.
        let g = vec![-1.0, 0.0, 0.0, 0.0, -2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        p.step(&g, 0.5, 0.01, &[[3.0, 0.0, 0.0], [0.0, 0.0, 3.0]]).unwrap();
        // Adam's first step is the rate: half a pixel, 0.005 units and 0.005/3 radians.
        assert!((p.translation[0][0] - 0.005).abs() < 1e-6, "{:?}", p.translation);
        assert!((p.rotation[0][1] - 0.005 / 3.0).abs() < 1e-7, "{:?}", p.rotation);
        assert_eq!((p.translation[1], p.rotation[1]), ([0.0; 3], [0.0; 3]));
        let c = p.corrections(0.01, &[3.0, 3.0]);
        assert!((c[0].translation_px - 0.5).abs() < 1e-3 && (c[0].rotation_px - 0.5).abs() < 1e-3, "{c:?}");
        // The corrected camera's rays are the batch's moved rays.
        let v = view("a", Split::Train, 0.2);
        let cam = p.camera(&v.camera, 0);
        let (o0, d0) = v.camera.ray(1.3, 2.7);
        let (o1, d1) = cam.ray(1.3, 2.7);
        let mut b = Batch::default();
        b.rays.origins.push(o0.as_vec3().to_array());
        b.rays.dirs.push(d0.as_vec3().to_array());
        b.view.push(0);
        p.apply(&mut b);
        assert!((glam::Vec3::from(b.rays.origins[0]) - o1.as_vec3()).length() < 1e-6);
        assert!((glam::Vec3::from(b.rays.dirs[0]) - d1.as_vec3()).length() < 1e-6);
        // A non-finite gradient reaches nothing.
        assert!(p.view_gradient(&b, &RayGrads { origin: vec![[f32::NAN, 0.0, 0.0]], dir: vec![[0.0; 3]], across_every: 1 }).is_none());
    }

    #[test]
    fn a_turn_shift_and_scale_of_the_whole_rig_is_taken_out_and_a_single_views_correction_kept() {
        let host = Backend::cpu();
        let centres: Vec<[f32; 3]> = (0..8)
            .map(|i| {
                let a = i as f32 * 0.785;
                [3.0 * a.cos(), if i % 2 == 0 { 0.8 } else { -0.5 }, 3.0 * a.sin()]
            })
            .collect();
        let mut p = PoseRefinement::new(&host, 8);
        // Every camera moved by one similarity about the object: a 0.3° turn, a shift, 0.2% larger.
        let rg = DQuat::from_scaled_axis(DVec3::new(0.2, -0.4, 0.3).normalize() * 0.3f64.to_radians());
        let (tg, s) = (DVec3::new(0.004, -0.002, 0.003), 1.002);
        for v in 0..8 {
            let c = DVec3::from(centres[v].map(f64::from));
            p.rotation[v] = rg.to_scaled_axis().as_vec3().to_array();
            p.translation[v] = (s * (rg * c) + tg - c).as_vec3().to_array();
        }
        // ... and view 3 alone turned 0.5° more.
        let own = DQuat::from_scaled_axis(DVec3::Y * 0.5f64.to_radians());
        p.rotation[3] = (own * rg).to_scaled_axis().as_vec3().to_array();
        p.remove_common_motion(&centres);
        let c = p.corrections(0.01, &centres.iter().map(|c| glam::Vec3::from(*c).length()).collect::<Vec<_>>());
        // The shared part is gone from the others (to the few hundredths of a pixel view 3's own
        // turn leaves in the fit); view 3 keeps most of its own 0.5°.
        for k in c.iter().filter(|k| k.view != 3) {
            assert!(k.translation_px + k.rotation_px < 0.25 * (0.5f64.to_radians() * 3.0 / 0.01), "{k:?}");
        }
        assert!(c[3].rotation_deg > 0.35 && c[3].rotation_deg < 0.55, "{:?}", c[3]);
        // With no view of its own the whole rig's motion is taken out, to the linear fit's
        // second order (a hundredth of a pixel here).
        let mut q = PoseRefinement::new(&host, 8);
        for v in 0..8 {
            let cv = DVec3::from(centres[v].map(f64::from));
            q.rotation[v] = rg.to_scaled_axis().as_vec3().to_array();
            q.translation[v] = (s * (rg * cv) + tg - cv).as_vec3().to_array();
        }
        q.remove_common_motion(&centres);
        for v in 0..8 {
            let (r, t) = (glam::Vec3::from(q.rotation[v]).length(), glam::Vec3::from(q.translation[v]).length());
            assert!(r < 1e-5 && t < 1e-4, "view {v}: {r} rad, {t} units left");
        }
    }

    #[test]
    fn refined_poses_reach_the_training_views_by_name_and_a_bad_file_is_named() {
        let host = Backend::cpu();
        let dir = tempfile::tempdir().unwrap();
        let train = [view("a", Split::Train, 0.0), view("b", Split::Train, 1.0)];
        let mut p = PoseRefinement::new(&host, 2);
        p.translation[1] = [0.0, 0.25, 0.0];
        let refs: Vec<&View> = train.iter().collect();
        let refined: Vec<Camera> = refs.iter().enumerate().map(|(i, v)| p.camera(&v.camera, i)).collect();
        let summary = write_poses(dir.path(), &p, &refs, &refined, 0.01, &[3.0, 3.0]).unwrap();
        assert!((summary["max_translation_px"].as_f64().unwrap() - 25.0).abs() < 1e-3, "{summary}");
        let mut scene = vec![view("t", Split::Test, 5.0), view("b", Split::Train, 1.0), view("a", Split::Train, 0.0)];
        assert_eq!(apply_run_poses(dir.path(), &mut scene).unwrap(), 2);
        assert_eq!(scene[1].camera.world_from_camera, refined[1].world_from_camera);
        assert_eq!(scene[2].camera.world_from_camera, refined[0].world_from_camera);
        assert_eq!(scene[0].camera.world_from_camera, view("t", Split::Test, 5.0).camera.world_from_camera);
        // A run without the file leaves the poses; a view the scene lacks and a broken file are errors naming it.
        assert_eq!(apply_run_poses(&dir.path().join("none"), &mut scene).unwrap(), 0);
        let mut other = vec![view("a", Split::Train, 0.0)];
        let e = apply_run_poses(dir.path(), &mut other).unwrap_err().to_string();
        assert!(e.contains(POSES) && e.contains("\"b\""), "{e}");
        std::fs::write(dir.path().join(POSES), "{ not json").unwrap();
        let e = apply_run_poses(dir.path(), &mut scene).unwrap_err().to_string();
        assert!(e.contains(POSES) && e.contains("JSON"), "{e}");
    }
}
