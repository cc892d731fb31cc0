//! UV-space rasterisation and texture baking.
//!
//! Every triangle is rasterised in UV space with conservative coverage (a texel is covered when
//! its square touches the triangle); a covered texel maps to the surface point at its
//! barycentrics (clamped into the triangle), which one Newton step projects onto the SDF's zero
//! set; the material field gives albedo and roughness there. Texels no chart covers are then
//! filled from their nearest covered neighbours (breadth-first dilation over the whole
//! image), so mipmaps and bilinear filtering never pull in background.

use std::time::Instant;

use crate::backend::{Backend, BackendError};
use crate::mesh::field::{MaterialField, SdfField};
use crate::mesh::uv::UvMesh;

/// Baked textures: linear albedo RGB and roughness, `size`² texels, row 0 at the top (glTF UV v = 0).
#[derive(Clone, Debug)]
pub struct BakedTextures {
    pub size: usize,
    pub albedo: Vec<[f32; 3]>,
    pub roughness: Vec<f32>,
    /// Metallic, where the material field gives it (else None: a dielectric asset).
    pub metallic: Option<Vec<f32>>,
    pub stats: BakeStats,
}

#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct BakeStats {
    pub size: usize,
    pub covered_texels: usize,
    /// Triangles with (near) zero area in UV space: skipped, their texels filled by dilation.
    pub degenerate_uv_triangles: usize,
    pub seconds_raster: f64,
    pub seconds_fields: f64,
    pub seconds_dilate: f64,
}

/// The texel (index) → surface sample map produced by rasterisation.
#[derive(Clone, Debug, Default)]
pub struct Coverage {
    pub texels: Vec<u32>,
    pub points: Vec<[f32; 3]>,
    pub normals: Vec<[f32; 3]>,
    pub degenerate: usize,
}

/// Rasterise every UV triangle into a `size`² grid with conservative coverage. A texel covered
/// by several triangles takes the one whose interior is closest to its centre.
pub fn rasterize(mesh: &UvMesh, size: usize) -> Coverage {
    let n = size * size;
    // Best (smallest) outside distance in texels per texel, and its sample.
    let mut best = vec![f32::INFINITY; n];
    let mut sample: Vec<([f32; 3], [f32; 3])> = vec![([0.0; 3], [0.0; 3]); n];
    let mut degenerate = 0;
    let s = size as f32;
    for t in mesh.indices.chunks_exact(3) {
        let (i0, i1, i2) = (t[0] as usize, t[1] as usize, t[2] as usize);
        let p = [mesh.uvs[i0], mesh.uvs[i1], mesh.uvs[i2]].map(|uv| [uv[0] * s, uv[1] * s]);
        let area2 =
            (p[1][0] - p[0][0]) * (p[2][1] - p[0][1]) - (p[2][0] - p[0][0]) * (p[1][1] - p[0][1]);
        if !area2.is_finite() || area2.abs() < 1e-6 {
            degenerate += 1;
            continue;
        }
        // Edge lengths to turn edge functions into distances (texels).
        let edge_len = [0, 1, 2].map(|k| {
            let (a, b) = (p[(k + 1) % 3], p[(k + 2) % 3]);
            ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2))
                .sqrt()
                .max(1e-12)
        });
        // Half the texel diagonal: a square touches the triangle when its centre is within it.
        let margin = std::f32::consts::FRAC_1_SQRT_2;
        let x0 = (p.iter().map(|q| q[0]).fold(f32::INFINITY, f32::min) - 1.0)
            .floor()
            .max(0.0) as usize;
        let x1 = (p.iter().map(|q| q[0]).fold(f32::NEG_INFINITY, f32::max) + 1.0)
            .ceil()
            .min(s - 1.0) as usize;
        let y0 = (p.iter().map(|q| q[1]).fold(f32::INFINITY, f32::min) - 1.0)
            .floor()
            .max(0.0) as usize;
        let y1 = (p.iter().map(|q| q[1]).fold(f32::NEG_INFINITY, f32::max) + 1.0)
            .ceil()
            .min(s - 1.0) as usize;
        for y in y0..=y1 {
            for x in x0..=x1 {
                let c = [x as f32 + 0.5, y as f32 + 0.5];
                // Barycentrics of the texel centre.
                let mut b = [0.0f32; 3];
                for k in 0..3 {
                    let (a, bb) = (p[(k + 1) % 3], p[(k + 2) % 3]);
                    b[k] =
                        ((bb[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (bb[1] - a[1])) / area2;
                }
                // Signed distance outside the triangle (texels): the worst edge.
                let dist = (0..3)
                    .map(|k| -b[k] * area2.abs() / edge_len[k])
                    .fold(f32::NEG_INFINITY, f32::max);
                if dist > margin {
                    continue;
                }
                let idx = y * size + x;
                if dist >= best[idx] {
                    continue;
                }
                best[idx] = dist;
                // Clamp into the triangle and renormalise.
                let mut bc = b.map(|v| v.max(0.0));
                let sum = bc[0] + bc[1] + bc[2];
                bc = bc.map(|v| v / sum);
                let mut pt = [0.0f32; 3];
                let mut nm = [0.0f32; 3];
                for k in 0..3 {
                    let vi = t[k] as usize;
                    for j in 0..3 {
                        pt[j] += bc[k] * mesh.positions[vi][j];
                        nm[j] += bc[k] * mesh.normals[vi][j];
                    }
                }
                sample[idx] = (pt, crate::mesh::normalize(nm));
            }
        }
    }
    let mut cov = Coverage {
        degenerate,
        ..Default::default()
    };
    for (i, d) in best.iter().enumerate() {
        if d.is_finite() {
            cov.texels.push(i as u32);
            cov.points.push(sample[i].0);
            cov.normals.push(sample[i].1);
        }
    }
    cov
}

/// Project points onto the SDF's zero set with Newton steps `p ← p − f(p)·∇f/|∇f|²`; normals
/// become the SDF gradient there.
pub fn project_to_surface(
    backend: &Backend,
    sdf: &dyn SdfField,
    points: &mut [[f32; 3]],
    normals: &mut [[f32; 3]],
    steps: usize,
) -> Result<(), BackendError> {
    for _ in 0..steps {
        let s = sdf.eval(backend, points)?;
        for (i, p) in points.iter_mut().enumerate() {
            let g = s.gradients[i];
            let g2 = crate::mesh::dot(g, g);
            if g2 > 1e-12 && s.values[i].is_finite() {
                let k = s.values[i] / g2;
                *p = [p[0] - k * g[0], p[1] - k * g[1], p[2] - k * g[2]];
                normals[i] = crate::mesh::normalize(g);
            }
        }
    }
    Ok(())
}

/// Fill every texel not in `filled` from covered neighbours, ring by ring (breadth first):
/// each new texel is the mean of its already-filled 8-neighbours. Texels unreachable (no covered
/// texel at all) get `fallback`.
pub fn dilate<T: Copy + Default>(
    size: usize,
    data: &mut [T],
    filled: &mut [bool],
    mean: impl Fn(&[T]) -> T,
    fallback: T,
) {
    let mut frontier: Vec<usize> = Vec::new();
    let neighbours = |i: usize| {
        let (x, y) = ((i % size) as i64, (i / size) as i64);
        let mut out = [usize::MAX; 8];
        let mut k = 0;
        for dy in -1..=1i64 {
            for dx in -1..=1i64 {
                if dx == 0 && dy == 0 {
                    continue;
                }
                let (nx, ny) = (x + dx, y + dy);
                if nx >= 0 && ny >= 0 && (nx as usize) < size && (ny as usize) < size {
                    out[k] = ny as usize * size + nx as usize;
                }
                k += 1;
            }
        }
        out
    };
    for i in 0..size * size {
        if !filled[i] && neighbours(i).iter().any(|&j| j != usize::MAX && filled[j]) {
            frontier.push(i);
        }
    }
    let mut vals: Vec<T> = Vec::with_capacity(8);
    while !frontier.is_empty() {
        let mut updates = Vec::with_capacity(frontier.len());
        for &i in &frontier {
            if filled[i] {
                continue;
            }
            vals.clear();
            vals.extend(
                neighbours(i)
                    .iter()
                    .filter(|&&j| j != usize::MAX && filled[j])
                    .map(|&j| data[j]),
            );
            if !vals.is_empty() {
                updates.push((i, mean(&vals)));
            }
        }
        let mut next = Vec::new();
        for &(i, v) in &updates {
            data[i] = v;
            filled[i] = true;
        }
        for &(i, _) in &updates {
            for j in neighbours(i) {
                if j != usize::MAX && !filled[j] {
                    next.push(j);
                }
            }
        }
        next.sort_unstable();
        next.dedup();
        frontier = next;
    }
    for (d, f) in data.iter_mut().zip(filled.iter()) {
        if !*f {
            *d = fallback;
        }
    }
}

/// Bake albedo, roughness (and metallic where the field gives it) of `material` over `mesh`'s
/// atlas at `size`².
pub fn bake(
    backend: &Backend,
    sdf: &dyn SdfField,
    material: &dyn MaterialField,
    mesh: &UvMesh,
    size: usize,
) -> Result<BakedTextures, BackendError> {
    let t = Instant::now();
    let mut cov = rasterize(mesh, size);
    let seconds_raster = t.elapsed().as_secs_f64();
    let t = Instant::now();
    const CHUNK: usize = 1 << 18;
    let mut albedo = vec![[0.0f32; 3]; size * size];
    let mut roughness = vec![0.0f32; size * size];
    let mut metallic: Option<Vec<f32>> = None;
    let mut filled = vec![false; size * size];
    for start in (0..cov.texels.len()).step_by(CHUNK) {
        let end = (start + CHUNK).min(cov.texels.len());
        project_to_surface(
            backend,
            sdf,
            &mut cov.points[start..end],
            &mut cov.normals[start..end],
            1,
        )?;
        let m = material.eval(backend, &cov.points[start..end], &cov.normals[start..end])?;
        if m.albedo.len() != end - start
            || m.roughness.len() != end - start
            || !(m.metallic.is_empty() || m.metallic.len() == end - start)
        {
            return Err(BackendError::Shape(format!(
                "material field {} returned {} albedo / {} roughness / {} metallic values for {} points",
                material.name(),
                m.albedo.len(),
                m.roughness.len(),
                m.metallic.len(),
                end - start
            )));
        }
        if !m.metallic.is_empty() && metallic.is_none() {
            metallic = Some(vec![0.0f32; size * size]);
        }
        for (k, &ti) in cov.texels[start..end].iter().enumerate() {
            let ti = ti as usize;
            let a = m.albedo[k];
            let r = m.roughness[k];
            let mt = m.metallic.get(k).copied().unwrap_or(0.0);
            // A non-finite material value is treated as uncovered (filled by dilation).
            if a.iter().all(|v| v.is_finite()) && r.is_finite() && mt.is_finite() {
                albedo[ti] = a.map(|v| v.clamp(0.0, 1.0));
                roughness[ti] = r.clamp(0.0, 1.0);
                if let Some(mm) = metallic.as_mut() {
                    mm[ti] = mt.clamp(0.0, 1.0);
                }
                filled[ti] = true;
            }
        }
    }
    let seconds_fields = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let covered = filled.iter().filter(|&&f| f).count();
    let mut filled2 = filled.clone();
    let mean1 = |v: &[f32]| v.iter().sum::<f32>() / v.len() as f32;
    if let Some(mm) = metallic.as_mut() {
        dilate(size, mm, &mut filled.clone(), mean1, 0.0);
    }
    let mean3 = |v: &[[f32; 3]]| {
        let n = v.len() as f32;
        let s = v
            .iter()
            .fold([0.0f32; 3], |a, b| [a[0] + b[0], a[1] + b[1], a[2] + b[2]]);
        [s[0] / n, s[1] / n, s[2] / n]
    };
    dilate(size, &mut albedo, &mut filled, mean3, [0.5; 3]);
    dilate(size, &mut roughness, &mut filled2, mean1, 0.5);
    let seconds_dilate = t.elapsed().as_secs_f64();
    let stats = BakeStats {
        size,
        covered_texels: covered,
        degenerate_uv_triangles: cov.degenerate,
        seconds_raster,
        seconds_fields,
        seconds_dilate,
    };
    Ok(BakedTextures {
        size,
        albedo,
        roughness,
        metallic,
        stats,
    })
}

/// Texture size: the smallest power of two (256..=4096) giving `texels_per_feature` texels
/// across the material's smallest feature (or 1/256 of the object's size when it has none),
/// given the surface area and the atlas utilisation to expect.
pub fn choose_texture_size(surface_area: f64, object_size: f64, feature_size: Option<f32>) -> u32 {
    let texel = match feature_size {
        Some(f) if f > 0.0 => (f as f64 / 16.0).min(object_size / 256.0),
        _ => object_size / 256.0,
    };
    let utilization = 0.6;
    let side = (surface_area / (texel * texel) / utilization).sqrt();
    (side.max(1.0) as u32).next_power_of_two().clamp(256, 4096)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quad_mesh() -> UvMesh {
        UvMesh {
            positions: vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [1.0, 1.0, 0.0],
                [0.0, 1.0, 0.0],
            ],
            normals: vec![[0.0, 0.0, 1.0]; 4],
            uvs: vec![[0.25, 0.25], [0.75, 0.25], [0.75, 0.75], [0.25, 0.75]],
            indices: vec![0, 1, 2, 0, 2, 3],
            xref: vec![0, 1, 2, 3],
            charts: 1,
            utilization: 0.25,
            texture_size: 16,
        }
    }

    #[test]
    fn conservative_coverage_of_a_square_chart() {
        let cov = rasterize(&quad_mesh(), 16);
        // The chart spans texels 4..12 (8×8 centres inside) plus a conservative ring (3..=12);
        // near the 45° corners the edge-distance test may take one more texel, never further.
        for y in 3..=12u32 {
            for x in 3..=12u32 {
                assert!(
                    cov.texels.contains(&(y * 16 + x)),
                    "texel ({x}, {y}) not covered"
                );
            }
        }
        assert!(cov.texels.len() <= 104, "{}", cov.texels.len());
        assert!(cov
            .texels
            .iter()
            .all(|&t| (2..=13).contains(&(t % 16)) && (2..=13).contains(&(t / 16))));
        assert!(!cov.texels.contains(&(2 * 16 + 2)));
        // Surface points interpolate positions: texel (8, 8) centre → uv (8.5/16) → (0.5625·2 − 0.5).
        let k = cov.texels.iter().position(|&t| t == 8 * 16 + 8).unwrap();
        let p = cov.points[k];
        assert!(
            (p[0] - (8.5 / 16.0 - 0.25) * 2.0).abs() < 1e-5
                && (p[1] - (8.5 / 16.0 - 0.25) * 2.0).abs() < 1e-5
        );
    }

    #[test]
    fn degenerate_uv_triangle_is_skipped_and_counted() {
        let mut m = quad_mesh();
        m.uvs.push([0.5, 0.5]);
        m.positions.push([0.5, 0.5, 0.0]);
        m.normals.push([0.0, 0.0, 1.0]);
        m.xref.push(4);
        m.indices.extend_from_slice(&[0, 2, 4]); // collinear in UV: zero area
        let cov = rasterize(&m, 16);
        assert_eq!(cov.degenerate, 1);
        assert!(cov.points.iter().flatten().all(|v| v.is_finite()));
    }

    #[test]
    fn dilation_fills_everything_from_the_nearest_texels() {
        let size = 8;
        let mut data = vec![0.0f32; 64];
        let mut filled = vec![false; 64];
        data[0] = 1.0;
        filled[0] = true;
        data[63] = 3.0;
        filled[63] = true;
        dilate(
            size,
            &mut data,
            &mut filled,
            |v: &[f32]| v.iter().sum::<f32>() / v.len() as f32,
            -1.0,
        );
        assert!(filled.iter().all(|&f| f));
        assert_eq!(data[1], 1.0);
        assert_eq!(data[62], 3.0);
        assert!(data.iter().all(|&v| (1.0..=3.0).contains(&v)));
        let mut empty = vec![0.0f32; 4];
        let mut none = vec![false; 4];
        dilate(2, &mut empty, &mut none, |v: &[f32]| v[0], 0.5);
        assert_eq!(empty, vec![0.5; 4]);
    }

    #[test]
    fn texture_size_follows_area_and_detail() {
        let sphere_area = 4.0 * std::f64::consts::PI * 0.64;
        let coarse = choose_texture_size(sphere_area, 1.6, None);
        let fine = choose_texture_size(sphere_area, 1.6, Some(0.05));
        assert!(coarse.is_power_of_two() && fine.is_power_of_two());
        assert!(fine > coarse, "{fine} vs {coarse}");
        assert_eq!(choose_texture_size(1e-6, 1.0, None), 256);
        assert_eq!(choose_texture_size(1e6, 1.0, Some(1e-3)), 4096);
    }
}
