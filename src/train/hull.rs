//! Stage 0: the visual hull of the masks as a signed distance grid.
//!
//! Every voxel centre of a cube `[-bound, bound]^3` (normalised scene space) is projected into
//! each view; a voxel is carved away when it lands on background in any view that sees it.
//! The occupancy is turned into a signed distance (negative inside) with an exact Euclidean
//! distance transform (Felzenszwalb–Huttenlocher, separable, O(n) per axis), so the grid can be
//! sphere-traced and meshed like any other SDF. The hull bounds the object for training, gives
//! the preview geometry of `bake`, and is the occluder for photo projection.

use rayon::prelude::*;

/// A dense scalar grid over the cube `[-bound, bound]^3`, samples at voxel centres, x fastest.
#[derive(Clone, Debug)]
pub struct Grid3 {
    pub res: usize,
    pub bound: f32,
    pub data: Vec<f32>,
}

impl Grid3 {
    pub fn new(res: usize, bound: f32, fill: f32) -> Self {
        Self { res, bound, data: vec![fill; res * res * res] }
    }

    /// Voxel size in scene units.
    pub fn spacing(&self) -> f32 {
        2.0 * self.bound / self.res as f32
    }

    /// Centre of voxel (i, j, k).
    pub fn centre(&self, i: usize, j: usize, k: usize) -> [f32; 3] {
        let h = self.spacing();
        let c = |a: usize| -self.bound + (a as f32 + 0.5) * h;
        [c(i), c(j), c(k)]
    }

    /// Centre of the voxel at `index` in `data` (x fastest).
    pub fn centre_of(&self, index: usize) -> [f32; 3] {
        self.centre(index % self.res, (index / self.res) % self.res, index / (self.res * self.res))
    }

    fn at(&self, i: usize, j: usize, k: usize) -> f32 {
        self.data[(k * self.res + j) * self.res + i]
    }

    /// Trilinear interpolation with clamping at the border; outside the cube the value is
    /// extended by the distance to the cube (keeps an SDF an upper bound out there).
    pub fn sample(&self, p: [f32; 3]) -> f32 {
        let h = self.spacing();
        let mut outside = 0.0f32;
        let mut idx = [0usize; 3];
        let mut frac = [0f32; 3];
        for a in 0..3 {
            let q = p[a].clamp(-self.bound, self.bound);
            outside += (p[a] - q) * (p[a] - q);
            let g = ((q + self.bound) / h - 0.5).clamp(0.0, (self.res - 1) as f32);
            let i0 = (g.floor() as usize).min(self.res.saturating_sub(2));
            idx[a] = i0;
            frac[a] = g - i0 as f32;
        }
        let [i, j, k] = idx;
        let [fx, fy, fz] = frac;
        let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
        let c00 = lerp(self.at(i, j, k), self.at(i + 1, j, k), fx);
        let c10 = lerp(self.at(i, j + 1, k), self.at(i + 1, j + 1, k), fx);
        let c01 = lerp(self.at(i, j, k + 1), self.at(i + 1, j, k + 1), fx);
        let c11 = lerp(self.at(i, j + 1, k + 1), self.at(i + 1, j + 1, k + 1), fx);
        lerp(lerp(c00, c10, fy), lerp(c01, c11, fy), fz) + outside.sqrt()
    }

    /// Central-difference gradient of [`Grid3::sample`] with a step of half a voxel.
    pub fn gradient(&self, p: [f32; 3]) -> [f32; 3] {
        let e = 0.5 * self.spacing();
        let mut g = [0.0; 3];
        for a in 0..3 {
            let (mut pp, mut pm) = (p, p);
            pp[a] += e;
            pm[a] -= e;
            g[a] = (self.sample(pp) - self.sample(pm)) / (2.0 * e);
        }
        g
    }
}

/// Squared Euclidean distance transform of a 1-D sampled function (Felzenszwalb & Huttenlocher
/// 2012): `d[q] = min_p (q - p)^2 + f[p]`. `f` uses a large value for "no seed".
fn edt_1d(f: &[f32], d: &mut [f32], v: &mut [usize], z: &mut [f32]) {
    let n = f.len();
    if n == 0 {
        return;
    }
    let mut k = 0usize;
    v[0] = 0;
    z[0] = f32::NEG_INFINITY;
    z[1] = f32::INFINITY;
    for q in 1..n {
        loop {
            let p = v[k];
            let s = ((f[q] + (q * q) as f32) - (f[p] + (p * p) as f32)) / (2.0 * (q as f32 - p as f32));
            if s <= z[k] && k > 0 {
                k -= 1;
                continue;
            }
            if s <= z[k] {
                // k == 0 and the new parabola dominates from -inf.
                v[0] = q;
                z[0] = f32::NEG_INFINITY;
                z[1] = f32::INFINITY;
                break;
            }
            k += 1;
            v[k] = q;
            z[k] = s;
            z[k + 1] = f32::INFINITY;
            break;
        }
    }
    k = 0;
    for (q, dq) in d.iter_mut().enumerate() {
        while z[k + 1] < q as f32 {
            k += 1;
        }
        let p = v[k];
        let dx = q as f32 - p as f32;
        *dq = dx * dx + f[p];
    }
}

/// Squared distance (in voxels) from every voxel to the nearest seed voxel (`seed[i] == true`).
fn edt_3d(seed: &[bool], res: usize) -> Vec<f32> {
    const FAR: f32 = 1e20;
    let mut g: Vec<f32> = seed.iter().map(|&s| if s { 0.0 } else { FAR }).collect();
    // One pass per axis; each line is independent.
    for axis in 0..3 {
        let stride = [1, res, res * res][axis];
        let lines: Vec<usize> = (0..res * res)
            .map(|l| {
                let (a, b) = (l % res, l / res);
                match axis {
                    0 => (b * res + a) * res,     // (0, a, b): lines along x
                    1 => b * res * res + a,       // (a, 0, b): lines along y
                    _ => b * res + a,             // (a, b, 0): lines along z
                }
            })
            .collect();
        let results: Vec<Vec<f32>> = lines
            .par_iter()
            .map(|&start| {
                let f: Vec<f32> = (0..res).map(|t| g[start + t * stride]).collect();
                let mut d = vec![0.0; res];
                let (mut v, mut z) = (vec![0usize; res], vec![0f32; res + 1]);
                edt_1d(&f, &mut d, &mut v, &mut z);
                d
            })
            .collect();
        for (start, d) in lines.iter().zip(results) {
            for (t, val) in d.into_iter().enumerate() {
                g[start + t * stride] = val.min(FAR);
            }
        }
    }
    g
}

/// Exact signed distance (negative inside) of a triangle mesh on the grid's voxel centres: the
/// distance to the closest point of its surface, signed by which side the voxel lies on. The side
/// is the parity of surface crossings along a line through the voxel, taken along each of the
/// three axes and decided by majority, so a line that grazes an edge, or a small hole in a mesh
/// that is not quite closed, does not flip a whole column. `mesh` is in the grid's frame.
pub fn mesh_signed_distance(mesh: &crate::eval::mesh::Mesh, res: usize, bound: f32) -> Grid3 {
    use glam::DVec3;
    let mut grid = Grid3::new(res, bound, 0.0);
    let h = grid.spacing() as f64;
    let c = |a: usize| -bound as f64 + (a as f64 + 0.5) * h;
    // votes[id]: how many of the three axes call the voxel inside.
    let mut votes = vec![0u8; res * res * res];
    for axis in 0..3 {
        let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
        // Triangles binned by the columns (u, v) their bounding box covers.
        let mut bins: Vec<Vec<u32>> = vec![Vec::new(); res * res];
        for (t, tri) in mesh.triangles.iter().enumerate() {
            let p = tri.map(|i| mesh.positions[i as usize]);
            let lo = |a: usize| (((p[0][a].min(p[1][a]).min(p[2][a]) + bound as f64) / h - 0.5).floor().max(0.0) as usize).min(res - 1);
            let hi = |a: usize| (((p[0][a].max(p[1][a]).max(p[2][a]) + bound as f64) / h - 0.5).ceil().max(0.0) as usize).min(res - 1);
            for a in lo(u)..=hi(u) {
                for b in lo(v)..=hi(v) {
                    bins[a * res + b].push(t as u32);
                }
            }
        }
        let inside_cols: Vec<Vec<bool>> = (0..res * res)
            .into_par_iter()
            .map(|col| {
                // A line slightly off the voxel centres, so it does not pass through the vertices
                // of meshes built on the same lattice.
                let (pu, pv) = (c(col / res) + 1.3e-4 * h, c(col % res) + 0.7e-4 * h);
                let mut hits: Vec<f64> = bins[col]
                    .iter()
                    .filter_map(|&t| {
                        let p: [DVec3; 3] = mesh.triangles[t as usize].map(|i| mesh.positions[i as usize]);
                        let (a, b, q) = (p[0], p[1], p[2]);
                        let det = (b[u] - a[u]) * (q[v] - a[v]) - (q[u] - a[u]) * (b[v] - a[v]);
                        if det.abs() < 1e-18 {
                            return None;
                        }
                        let s = ((pu - a[u]) * (q[v] - a[v]) - (q[u] - a[u]) * (pv - a[v])) / det;
                        let w = ((b[u] - a[u]) * (pv - a[v]) - (pu - a[u]) * (b[v] - a[v])) / det;
                        (s >= 0.0 && w >= 0.0 && s + w <= 1.0).then(|| a[axis] + s * (b[axis] - a[axis]) + w * (q[axis] - a[axis]))
                    })
                    .collect();
                hits.sort_by(f64::total_cmp);
                let mut k = 0;
                (0..res)
                    .map(|i| {
                        let x = c(i);
                        while k < hits.len() && hits[k] < x {
                            k += 1;
                        }
                        k % 2 == 1
                    })
                    .collect()
            })
            .collect();
        for (col, ins) in inside_cols.iter().enumerate() {
            let (a, b) = (col / res, col % res);
            for (i, &inn) in ins.iter().enumerate() {
                let mut idx = [0usize; 3];
                idx[axis] = i;
                idx[u] = a;
                idx[v] = b;
                if inn {
                    votes[(idx[2] * res + idx[1]) * res + idx[0]] += 1;
                }
            }
        }
    }
    let tree = crate::eval::mesh::TriBvh::new(mesh);
    grid.data.par_iter_mut().enumerate().for_each(|(id, d)| {
        let (i, j, k) = (id % res, (id / res) % res, id / (res * res));
        let dist = tree.nearest(DVec3::new(c(i), c(j), c(k))).map_or(f64::INFINITY, |(_, d2)| d2.sqrt());
        *d = if votes[id] >= 2 { -dist as f32 } else { dist as f32 };
    });
    grid
}

/// Signed distance (scene units, negative inside) from a boolean occupancy grid. The zero level
/// lies half a voxel outside the inside voxels' centres, i.e. on the voxel faces.
pub fn signed_distance(inside: &[bool], res: usize, bound: f32) -> Grid3 {
    let h = 2.0 * bound / res as f32;
    let outside: Vec<bool> = inside.iter().map(|&b| !b).collect();
    let d_to_inside = edt_3d(inside, res);
    let d_to_outside = edt_3d(&outside, res);
    let data = (0..inside.len())
        .into_par_iter()
        .map(|i| {
            if inside[i] {
                -(d_to_outside[i].sqrt() - 0.5) * h
            } else {
                (d_to_inside[i].sqrt() - 0.5) * h
            }
        })
        .collect();
    Grid3 { res, bound, data }
}

/// What hull carving needs from a view: project a normalised-space point to pixel coordinates
/// (None if behind the camera) and look up the mask there (None outside the image).
pub trait MaskView: Sync {
    fn project(&self, p: [f32; 3]) -> Option<[f32; 2]>;
    fn mask_at(&self, px: [f32; 2]) -> Option<f32>;
}

/// Carve the visual hull: a voxel stays when every view that sees it puts it on the foreground
/// (mask ≥ `threshold`). Voxels seen by fewer than `min_views` views are carved too.
pub fn carve(views: &[&dyn MaskView], res: usize, bound: f32, threshold: f32, min_views: usize) -> Vec<bool> {
    let grid = Grid3::new(res, bound, 0.0);
    (0..res * res * res)
        .into_par_iter()
        .map(|idx| {
            let (i, j, k) = (idx % res, (idx / res) % res, idx / (res * res));
            let p = grid.centre(i, j, k);
            let mut seen = 0;
            for v in views {
                let Some(px) = v.project(p) else { continue };
                let Some(m) = v.mask_at(px) else { continue };
                if m < threshold {
                    return false;
                }
                seen += 1;
            }
            seen >= min_views
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distance_transform_of_a_ball_is_its_sdf() {
        let (res, bound, r) = (48, 1.0f32, 0.6f32);
        let g0 = Grid3::new(res, bound, 0.0);
        let inside: Vec<bool> = (0..res * res * res)
            .map(|idx| {
                let c = g0.centre(idx % res, (idx / res) % res, idx / (res * res));
                (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt() < r
            })
            .collect();
        let sdf = signed_distance(&inside, res, bound);
        let h = sdf.spacing();
        let mut worst = 0.0f32;
        for p in [[0.0f32, 0.0, 0.0], [0.3, -0.2, 0.1], [0.9, 0.1, 0.0], [0.5, 0.5, 0.5], [-0.7, 0.0, 0.2]] {
            let exact = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - r;
            worst = worst.max((sdf.sample(p) - exact).abs());
        }
        assert!(worst < 1.5 * h, "worst |sdf error| {worst} vs voxel {h}");
        let g = sdf.gradient([0.6, 0.0, 0.0]);
        assert!(g[0] > 0.8 && g[1].abs() < 0.2, "{g:?}");
        // Outside the cube the value keeps growing.
        assert!(sdf.sample([3.0, 0.0, 0.0]) > 1.9);
    }

    #[test]
    fn mesh_signed_distance_of_a_sphere_is_its_sdf_even_with_a_hole() {
        let (res, bound, r) = (40, 1.0f32, 0.6f64);
        let mut mesh = crate::eval::mesh::uv_sphere(r, 24, 48);
        let g = mesh_signed_distance(&mesh, res, bound);
        // The facets lie at most r·(1 − cos(π/24)) inside the sphere.
        let facet = (r * (1.0 - (std::f64::consts::PI / 24.0).cos())) as f32;
        let mut worst = 0.0f32;
        for (id, d) in g.data.iter().enumerate() {
            let c = g.centre(id % res, (id / res) % res, id / (res * res));
            let exact = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt() - r as f32;
            worst = worst.max((d - exact).abs());
        }
        assert!(worst < facet + 1e-4, "worst |sdf error| {worst} vs facet depth {facet}");
        // A missing triangle flips the parity of the lines through it. With one axis a whole
        // half-column would change side; with the majority of three only voxels next to the hole
        // (where lines along two axes both pass through it) may.
        let gone = mesh.triangles.len() / 3 + 7;
        let t = mesh.triangles.remove(gone);
        let p = t.map(|i| mesh.positions[i as usize]);
        let centroid = (p[0] + p[1] + p[2]) / 3.0;
        let extent = (0..3).map(|k| (p[k] - centroid).length()).fold(0.0, f64::max) + 1.8 * g.spacing() as f64;
        let holed = mesh_signed_distance(&mesh, res, bound);
        let mut flipped = 0;
        for (id, (a, b)) in g.data.iter().zip(&holed.data).enumerate() {
            if (*a < 0.0) != (*b < 0.0) {
                flipped += 1;
                let c = g.centre(id % res, (id / res) % res, id / (res * res));
                let d = (glam::DVec3::from(c.map(f64::from)) - centroid).length();
                assert!(d <= extent, "a voxel {d} from the hole changed side (hole extent {extent})");
            }
        }
        assert!(flipped <= 8, "{flipped} voxels changed side because of one missing triangle");
    }

    struct Ortho {
        axis: usize,
        r: f32,
    }
    impl MaskView for Ortho {
        fn project(&self, p: [f32; 3]) -> Option<[f32; 2]> {
            let (a, b) = match self.axis {
                0 => (p[1], p[2]),
                1 => (p[0], p[2]),
                _ => (p[0], p[1]),
            };
            Some([a, b])
        }
        fn mask_at(&self, px: [f32; 2]) -> Option<f32> {
            Some(if px[0] * px[0] + px[1] * px[1] < self.r * self.r { 1.0 } else { 0.0 })
        }
    }

    #[test]
    fn three_orthographic_discs_carve_a_steinmetz_solid() {
        let views: Vec<Ortho> = (0..3).map(|axis| Ortho { axis, r: 0.5 }).collect();
        let refs: Vec<&dyn MaskView> = views.iter().map(|v| v as &dyn MaskView).collect();
        let res = 40;
        let inside = carve(&refs, res, 1.0, 0.5, 3);
        let frac = inside.iter().filter(|&&b| b).count() as f64 / inside.len() as f64;
        // Tricylinder volume 8(2 - sqrt 2) r^3 in a cube of side 2.
        let expected = 8.0 * (2.0 - 2f64.sqrt()) * 0.125 / 8.0;
        assert!((frac - expected).abs() < 0.1 * expected, "{frac} vs {expected}");
    }
}
