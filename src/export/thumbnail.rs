//! A 256×256 preview: the mesh rasterised in software (z-buffer, orthographic three-quarter
//! view), albedo from the baked texture, simple Lambert shading, transparent background.

use super::AssetGeometry;

/// RGBA linear pixels (`size`², row 0 at the top).
pub fn render(geo: &AssetGeometry, albedo: &[[f32; 3]], tex_size: usize, size: usize) -> Vec<f32> {
    let (lo, hi) = geo.bounds();
    let c = [
        (lo[0] + hi[0]) * 0.5,
        (lo[1] + hi[1]) * 0.5,
        (lo[2] + hi[2]) * 0.5,
    ];
    let radius =
        ((hi[0] - lo[0]).powi(2) + (hi[1] - lo[1]).powi(2) + (hi[2] - lo[2]).powi(2)).sqrt() * 0.5;
    let radius = radius.max(1e-6);
    // Camera looking at the centre from the front-right, slightly above (+Y up, front +Z).
    let fwd = crate::mesh::normalize([-0.6, -0.45, -1.0]);
    let right = crate::mesh::normalize(crate::mesh::cross(fwd, [0.0, 1.0, 0.0]));
    let up = crate::mesh::cross(right, fwd);
    let light = crate::mesh::normalize([0.4, 0.8, 0.6]);
    let scale = size as f32 * 0.5 / (radius * 1.05);
    let project = |p: [f32; 3]| {
        let d = crate::mesh::sub(p, c);
        let x = crate::mesh::dot(d, right) * scale + size as f32 * 0.5;
        let y = size as f32 * 0.5 - crate::mesh::dot(d, up) * scale;
        [x, y, crate::mesh::dot(d, fwd)]
    };
    let sp: Vec<[f32; 3]> = geo.positions.iter().map(|&p| project(p)).collect();
    let mut depth = vec![f32::INFINITY; size * size];
    let mut img = vec![0.0f32; size * size * 4];
    for t in geo.indices.chunks_exact(3) {
        let v = [t[0] as usize, t[1] as usize, t[2] as usize];
        let (a, b, cc) = (sp[v[0]], sp[v[1]], sp[v[2]]);
        let area = (b[0] - a[0]) * (cc[1] - a[1]) - (cc[0] - a[0]) * (b[1] - a[1]);
        if area.abs() < 1e-12 {
            continue;
        }
        let x0 = a[0].min(b[0]).min(cc[0]).floor().max(0.0) as usize;
        let x1 = (a[0].max(b[0]).max(cc[0]).ceil() as usize).min(size - 1);
        let y0 = a[1].min(b[1]).min(cc[1]).floor().max(0.0) as usize;
        let y1 = (a[1].max(b[1]).max(cc[1]).ceil() as usize).min(size - 1);
        for y in y0..=y1 {
            for x in x0..=x1 {
                let p = [x as f32 + 0.5, y as f32 + 0.5];
                let w0 = ((b[0] - p[0]) * (cc[1] - p[1]) - (cc[0] - p[0]) * (b[1] - p[1])) / area;
                let w1 = ((cc[0] - p[0]) * (a[1] - p[1]) - (a[0] - p[0]) * (cc[1] - p[1])) / area;
                let w2 = 1.0 - w0 - w1;
                if w0 < 0.0 || w1 < 0.0 || w2 < 0.0 {
                    continue;
                }
                let z = w0 * a[2] + w1 * b[2] + w2 * cc[2];
                let i = y * size + x;
                if z >= depth[i] {
                    continue;
                }
                depth[i] = z;
                let w = [w0, w1, w2];
                let mut n = [0.0f32; 3];
                let mut uv = [0.0f32; 2];
                for k in 0..3 {
                    for (nj, vj) in n.iter_mut().zip(geo.normals[v[k]]) {
                        *nj += w[k] * vj;
                    }
                    uv[0] += w[k] * geo.uvs[v[k]][0];
                    uv[1] += w[k] * geo.uvs[v[k]][1];
                }
                let n = crate::mesh::normalize(n);
                let tx = ((uv[0] * tex_size as f32) as usize).min(tex_size - 1);
                let ty = ((uv[1] * tex_size as f32) as usize).min(tex_size - 1);
                let al = albedo[ty * tex_size + tx];
                let shade = 0.25 + 0.75 * crate::mesh::dot(n, light).max(0.0);
                img[i * 4..i * 4 + 4].copy_from_slice(&[
                    al[0] * shade,
                    al[1] * shade,
                    al[2] * shade,
                    1.0,
                ]);
            }
        }
    }
    img
}
