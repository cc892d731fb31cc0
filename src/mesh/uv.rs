//! UV unwrap with `uvunwrap` (pure Rust: chart segmentation, LSCM + ARAP, shape packing).
//!
//! Chosen over xatlas-rs, whose bindings do not link on Linux (MSVC-mangled names) and which took
//! ~1.1 s on a 5k-triangle sphere against uvunwrap's 65–83 ms (../shared/toolchain.md). The
//! atlas is packed into one square page of the texture size; UVs follow glTF (0, 0 at the top
//! left of the image, v grows downward).

use super::Mesh;

#[derive(Debug, thiserror::Error)]
pub enum UvError {
    #[error("UV unwrap failed: {0}")]
    Unwrap(String),
    #[error("UV unwrap needed {0} atlas pages; one is supported (raise the texture size)")]
    Pages(u32),
}

/// A mesh with UVs: seam vertices are duplicated; `xref` maps each vertex to the input vertex.
#[derive(Clone, Debug, Default)]
pub struct UvMesh {
    pub positions: Vec<[f32; 3]>,
    pub normals: Vec<[f32; 3]>,
    /// glTF convention, in [0, 1] of a `texture_size`² image.
    pub uvs: Vec<[f32; 2]>,
    pub indices: Vec<u32>,
    pub xref: Vec<u32>,
    pub charts: u32,
    /// Fraction of the texture covered by charts.
    pub utilization: f32,
    pub texture_size: u32,
}

/// Unwrap `mesh` into a `texture_size`² atlas with `padding` empty texels around each chart.
pub fn unwrap(
    mesh: &Mesh,
    normals: &[[f32; 3]],
    texture_size: u32,
    padding: u32,
) -> Result<UvMesh, UvError> {
    let input = uvunwrap::MeshInput::new(&mesh.positions, &mesh.indices);
    let options = uvunwrap::Options {
        density: uvunwrap::Density::Auto {
            page_size: texture_size,
        },
        padding,
        ..Default::default()
    };
    let atlas =
        uvunwrap::generate(&[input], &options).map_err(|e| UvError::Unwrap(e.to_string()))?;
    if atlas.page_count > 1 {
        return Err(UvError::Pages(atlas.page_count));
    }
    let out = &atlas.meshes[0];
    // The page may be cropped to the rows in use: rescale v into the square texture.
    let su = atlas.width as f32 / texture_size as f32;
    let sv = atlas.height as f32 / texture_size as f32;
    let mut m = UvMesh {
        indices: out.indices.clone(),
        charts: atlas.chart_count,
        utilization: atlas.utilization * su * sv,
        texture_size,
        ..Default::default()
    };
    for v in &out.vertices {
        m.positions.push(mesh.positions[v.xref as usize]);
        m.normals.push(normals[v.xref as usize]);
        m.uvs.push([v.uv[0] * su, v.uv[1] * sv]);
        m.xref.push(v.xref);
    }
    Ok(m)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unwrap_keeps_triangles_and_uvs_in_range() {
        let m = crate::mesh::topology::tests_support::octahedron();
        let normals: Vec<[f32; 3]> = m
            .positions
            .iter()
            .map(|&p| crate::mesh::normalize(p))
            .collect();
        let uv = unwrap(&m, &normals, 256, 2).unwrap();
        assert_eq!(uv.indices.len(), m.indices.len());
        assert!(uv
            .uvs
            .iter()
            .all(|t| (0.0..=1.0).contains(&t[0]) && (0.0..=1.0).contains(&t[1])));
        for (i, &x) in uv.xref.iter().enumerate() {
            assert_eq!(uv.positions[i], m.positions[x as usize]);
        }
        assert!(
            uv.charts >= 1 && uv.utilization > 0.05 && uv.utilization <= 1.0,
            "{uv:?}"
        );
    }
}
