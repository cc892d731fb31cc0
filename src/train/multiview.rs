//! Stage 1's multi-view photo-consistency term: the photos compared with each other at the traced
//! surface, not only with the radiance net's colour.
//!
//! The colour loss compares each pixel with what the radiance net says the surface shows there;
//! a surface in the wrong place is then partly explained by the net (a view-dependent colour, a
//! texture painted onto a bump) and the geometry stops moving. Here the 3×3 patch a training ray
//! sees in its own photo is compared with the patches that the point it hit projects to in the
//! nearest other photos (the mean of the `best` closest matches, so views that are occluded there
//! or show a highlight do not count, as [`super::photo::carve_concavities`] scores them). The cost's
//! slope along the ray, by central differences, moves the surface point the way the colour
//! moves it (implicit differentiation, `dx/df = −v/(∇f·v)`). A textureless surface scores alike
//! at every depth and gets no push.
//!
//! A 3×3 patch places a surface to about a pixel, and the cost keeps a floor where lighting
//! differs between photos: held to the end of a run the term pulls a finished surface toward
//! that optimum, so stage 1 fades it out ([`super::stage1::Stage1Config::photo_consistency_end`])
//! and the colour loss finishes the shape.

use glam::{DMat4, DVec3};

use super::photo::{dot, nearest_by_direction, solid_bits, sub, Pixels};
use super::stage1::TrainData;

/// How many of the nearest photos (by direction from the frame's centre) a reference photo is
/// compared with.
pub const NEIGHBOURS: usize = 8;

/// Stage 1's cost is the mean of this many best-matching neighbour patches.
pub const BEST: usize = 2;

/// The term's settings ([`super::stage1::Stage1Config::photo_consistency`]).
#[derive(Clone, Copy, Debug)]
pub struct PhotoConsistency {
    pub weight: f32,
    /// The cost is the mean of this many best-matching neighbour patches.
    pub best: usize,
    /// Central-difference step along the ray (normalised units).
    pub depth_step: f32,
}

/// The training photos' cameras as the term projects into them.
#[derive(Debug)]
pub struct MultiView {
    camera_from_world: Vec<DMat4>,
    centres: Vec<[f32; 3]>,
    neighbours: Vec<Vec<usize>>,
    /// The photos' sRGB, filtered by [`prefilter`] (every patch, the reference's at pixel centres
    /// and the neighbours' interpolated, then shows the same blur).
    images: Vec<Vec<f32>>,
    /// Each view's mask as [`solid_bits`].
    solid: Vec<Vec<u64>>,
}

/// A separable [1, 2, 1]/4 filter of an RGB image (edges clamped): bilinear interpolation blurs a
/// patch by up to half a pixel depending on where it lands, so unfiltered the cost would favour
/// depths that project onto pixel centres. Measured with the weight held to the end of the run
/// (`bench train --set photo_consistency=4 --set photo_consistency_end=1`), unfiltered ->
/// filtered: the example's field Chamfer 0.270% -> 0.200%, NC 0.9812 -> 0.9842; the bowl's
/// 1.191% -> 1.201%, NC 0.9358 -> 0.9395.
fn prefilter(rgb: &[f32], w: usize, h: usize) -> Vec<f32> {
    let pass = |src: &[f32], horizontal: bool| -> Vec<f32> {
        let mut out = vec![0.0f32; src.len()];
        for y in 0..h {
            for x in 0..w {
                let (a, b) = if horizontal { ((y * w + x.saturating_sub(1)), (y * w + (x + 1).min(w - 1))) } else { (y.saturating_sub(1) * w + x, (y + 1).min(h - 1) * w + x) };
                let c = y * w + x;
                for ch in 0..3 {
                    out[3 * c + ch] = 0.25 * src[3 * a + ch] + 0.5 * src[3 * c + ch] + 0.25 * src[3 * b + ch];
                }
            }
        }
        out
    };
    pass(&pass(rgb, true), false)
}

impl MultiView {
    pub fn new(data: &TrainData) -> Self {
        let centres: Vec<[f32; 3]> = data.views.iter().map(|v| v.camera.center().as_vec3().to_array()).collect();
        let neighbours = nearest_by_direction(&centres, NEIGHBOURS);
        let images = data.views.iter().map(|v| prefilter(&v.rgb, v.camera.width, v.camera.height)).collect();
        let solid = data.views.iter().map(|v| solid_bits(&v.mask)).collect();
        Self { camera_from_world: data.views.iter().map(|v| v.camera.world_from_camera.inverse()).collect(), centres, neighbours, images, solid }
    }

    /// Project through these poses (camera → world, one per view) from here on: the pose
    /// refinement's corrected cameras. The neighbours stay those of the poses as read.
    pub fn set_poses(&mut self, world_from_camera: &[DMat4]) {
        for (v, m) in world_from_camera.iter().enumerate().take(self.camera_from_world.len()) {
            self.camera_from_world[v] = m.inverse();
            self.centres[v] = m.w_axis.truncate().as_vec3().to_array();
        }
    }

    fn project(&self, data: &TrainData, v: usize, p: [f32; 3]) -> Option<[f32; 2]> {
        let q = data.views[v].camera.project_camera_point(self.camera_from_world[v].transform_point3(DVec3::from(p.map(f64::from))))?;
        Some([q.x as f32, q.y as f32])
    }

    /// The 3×3 patch around continuous pixel coordinates `px` (pixel centres at +0.5), bilinear,
    /// in the training photos' sRGB after [`prefilter`]; None if any pixel is off the image or
    /// off the mask.
    fn patch(&self, data: &TrainData, v: usize, px: [f32; 2]) -> Option<[[f32; 3]; 9]> {
        let view = &data.views[v];
        let (w, h) = (view.camera.width, view.camera.height);
        Pixels::new(w, h, Some(&view.mask), &self.images[v], w, h, 3).with_solid(Some(&self.solid[v])).patch(px)
    }

    /// The patch cost (mean |a − b| over the patch and channels) of view `v` at point `p`
    /// against `reference`; None off `v`'s image or mask.
    fn patch_cost(&self, data: &TrainData, v: usize, reference: &[[f32; 3]; 9], p: [f32; 3]) -> Option<f32> {
        let c = self.patch(data, v, self.project(data, v, p)?)?;
        let mut e = 0.0;
        for (a, b) in c.iter().zip(reference) {
            for ch in 0..3 {
                e += (a[ch] - b[ch]).abs();
            }
        }
        Some(e / 27.0)
    }

    /// The cost of `p` and of `p ± eps·dir` against view `r`'s patch `reference`: the mean patch
    /// cost of the `best` neighbours of `r` that match best at `p`, among those that lie on `r`'s
    /// side of the point and show all three points on their masks, the same views at all three
    /// depths (a view that drops out at one depth would otherwise read as a slope). None when
    /// fewer than `best` views qualify.
    #[allow(clippy::too_many_arguments)]
    fn costs(&self, data: &TrainData, r: usize, reference: &[[f32; 3]; 9], p: [f32; 3], dir: [f32; 3], eps: f32, best: usize, buf: &mut Vec<[f32; 3]>) -> Option<[f32; 3]> {
        buf.clear();
        let to_ref = sub(self.centres[r], p);
        let at = |t: f32| [0, 1, 2].map(|a| p[a] + t * dir[a]);
        for &v in &self.neighbours[r] {
            if dot(sub(self.centres[v], p), to_ref) <= 0.0 {
                continue;
            }
            let (Some(c0), Some(c1), Some(c2)) = (self.patch_cost(data, v, reference, p), self.patch_cost(data, v, reference, at(eps)), self.patch_cost(data, v, reference, at(-eps))) else {
                continue;
            };
            buf.push([c0, c1, c2]);
        }
        if buf.len() < best || best == 0 {
            return None;
        }
        buf.sort_by(|a, b| a[0].total_cmp(&b[0]));
        let mut out = [0.0f32; 3];
        for c in &buf[..best] {
            for i in 0..3 {
                out[i] += c[i] / best as f32;
            }
        }
        Some(out)
    }

    /// The term at the traced surface points: `points[k]`, hit by the ray of view `views[k]`
    /// through pixel `pixels[k]` along `dirs[k]`, with `gdotv[k] = ∇f·v`. Returns the loss (the
    /// weight times the mean cost over the points that have one) and its gradient with respect
    /// to `f(x0)` at each point (zero where the ray meets the surface at `−∇f·v ≤ grazing_cos`).
    #[allow(clippy::too_many_arguments)]
    pub fn term(&self, data: &TrainData, settings: &PhotoConsistency, views: &[u32], pixels: &[[f32; 2]], points: &[[f32; 3]], dirs: &[[f32; 3]], gdotv: &[f32], grazing_cos: f32) -> (f64, Vec<f32>) {
        use rayon::prelude::*;
        let eps = settings.depth_step;
        let per: Vec<Option<(f32, f32)>> = (0..points.len())
            .into_par_iter()
            .map_init(Vec::new, |buf, k| {
                let r = views[k] as usize;
                let reference = self.patch(data, r, pixels[k])?;
                let [c0, ahead, behind] = self.costs(data, r, &reference, points[k], dirs[k], eps, settings.best, buf)?;
                Some((c0, (ahead - behind) / (2.0 * eps)))
            })
            .collect();
        let n = per.iter().flatten().count();
        let mut d = vec![0.0f32; points.len()];
        if n == 0 {
            return (0.0, d);
        }
        let w = settings.weight as f64 / n as f64;
        let mut loss = 0.0;
        for (k, c) in per.iter().enumerate() {
            let Some((c0, slope)) = c else { continue };
            loss += w * *c0 as f64;
            if gdotv[k] < -grazing_cos && slope.is_finite() {
                d[k] = (-(w as f32) * slope) / gdotv[k];
            }
        }
        (loss, d)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image_io::ImageF32;
    use crate::scene::{Camera, Split, View};
    use glam::DVec4;

    /// A 48×48 pinhole camera at `eye` looking at the origin (OpenCV axes).
    fn camera(eye: DVec3) -> Camera {
        let f = (-eye).normalize();
        let r = f.cross(DVec3::Y).normalize();
        let d = f.cross(r);
        let m = DMat4::from_cols(r.extend(0.0), d.extend(0.0), f.extend(0.0), DVec4::new(eye.x, eye.y, eye.z, 1.0));
        Camera { width: 48, height: 48, fx: 60.0, fy: 60.0, cx: 24.0, cy: 24.0, distortion: None, world_from_camera: m }
    }

    /// Views of the plane z = 0 painted with `paint`, from above.
    fn plane_views(paint: impl Fn(f64, f64) -> [f32; 3]) -> Vec<View> {
        [DVec3::new(0.0, 0.0, 3.0), DVec3::new(0.7, 0.1, 2.9), DVec3::new(-0.6, 0.3, 2.9), DVec3::new(0.1, -0.7, 2.9), DVec3::new(0.4, 0.6, 2.9)]
            .iter()
            .enumerate()
            .map(|(i, &eye)| {
                let camera = camera(eye);
                let mut image = ImageF32::new(48, 48, 3);
                for y in 0..48 {
                    for x in 0..48 {
                        let (o, d) = camera.ray(x as f64 + 0.5, y as f64 + 0.5);
                        let p = o + d * (-o.z / d.z);
                        image.data[3 * (y * 48 + x)..3 * (y * 48 + x) + 3].copy_from_slice(&paint(p.x, p.y));
                    }
                }
                View { name: format!("v{i}"), split: Split::Train, camera, image, mask: Some(vec![1.0; 48 * 48]), image_path: format!("v{i}.png").into() }
            })
            .collect()
    }

    #[test]
    fn the_prefilter_keeps_flat_colour_and_spreads_an_impulse_over_its_neighbours() {
        let flat = vec![0.3f32; 3 * 5 * 4];
        assert!(prefilter(&flat, 5, 4).iter().all(|v| (v - 0.3).abs() < 1e-6));
        let mut dot = vec![0.0f32; 3 * 5 * 5];
        dot[3 * 12] = 1.0;
        let f = prefilter(&dot, 5, 5);
        let at = |x: usize, y: usize| f[3 * (y * 5 + x)];
        assert_eq!((at(2, 2), at(1, 2), at(2, 3), at(1, 1), at(0, 2)), (0.25, 0.125, 0.125, 0.0625, 0.0));
        assert!((f.iter().step_by(3).sum::<f32>() - 1.0).abs() < 1e-6 && f[3 * 12 + 1] == 0.0);
    }

    #[test]
    fn the_cost_is_lowest_on_the_surface_and_its_slope_moves_the_point_onto_it() {
        let views = plane_views(|x, y| {
            [(0.5 + 0.4 * (9.0 * x).sin()) as f32, (0.5 + 0.4 * (11.0 * y).cos()) as f32, (0.5 + 0.3 * (7.0 * (x + y)).sin()) as f32]
        });
        let refs: Vec<&View> = views.iter().collect();
        let data = TrainData::new(&refs, 1.0).unwrap();
        let mv = MultiView::new(&data);
        let settings = PhotoConsistency { weight: 1.0, best: 2, depth_step: 0.01 };
        // The rays of view 0 through a few pixels near the centre; the plane's SDF is z, so
        // ∇f·v = v_z.
        for px in [[20.5f32, 22.5], [24.5, 24.5], [27.5, 21.5]] {
            let (o, d) = data.views[0].camera.ray(px[0] as f64, px[1] as f64);
            let t = -o.z / d.z;
            let at = |s: f64| (o + d * (t + s)).as_vec3().to_array();
            let dir = d.as_vec3().to_array();
            let run = |s: f64| mv.term(&data, &settings, &[0], &[px], &[at(s)], &[dir], &[dir[2]], 0.05);
            let (on, _) = run(0.0);
            let (beyond, d_beyond) = run(0.04);
            let (before, d_before) = run(-0.04);
            assert!(on < 0.5 * beyond.min(before), "cost on the surface {on} vs 0.04 beyond {beyond}, before {before}");
            // Beyond the surface the loss rises with depth: raising f there would take the point
            // deeper, so d/df > 0 (descent lowers f and lifts the surface toward the camera);
            // in front, the opposite.
            assert!(d_beyond[0] > 0.0 && d_before[0] < 0.0, "{} {}", d_beyond[0], d_before[0]);
            // A ray that meets the surface near grazing (−∇f·v = 0.1, below the threshold 0.2)
            // is not moved.
            let (_, d_grazing) = mv.term(&data, &settings, &[0], &[px], &[at(0.04)], &[dir], &[-0.1], 0.2);
            assert_eq!(d_grazing[0], 0.0);
        }
        // A textureless plane: every depth alike, no cost and no push.
        let flat = plane_views(|_, _| [0.4, 0.5, 0.6]);
        let refs: Vec<&View> = flat.iter().collect();
        let data = TrainData::new(&refs, 1.0).unwrap();
        let mv = MultiView::new(&data);
        let (o, d) = data.views[0].camera.ray(24.5, 24.5);
        let p = (o + d * (-o.z / d.z + 0.04)).as_vec3().to_array();
        let dir = d.as_vec3().to_array();
        let (l, g) = mv.term(&data, &settings, &[0], &[[24.5, 24.5]], &[p], &[dir], &[dir[2]], 0.05);
        assert!(l.abs() < 1e-6 && g[0].abs() < 1e-4, "{l} {}", g[0]);
    }
}
