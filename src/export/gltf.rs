//! Binary glTF 2.0 (.glb) from gltf-json structs: one mesh, one metallic-roughness material with
//! an sRGB baseColor PNG and a linear ORM PNG (R = 1, G = roughness, B = metallic), embedded. The
//! metallic factor is 1 where the material has a metallic channel (the texture's B then carries it),
//! else 0 (B is 0).

use std::collections::BTreeMap;

use gltf_json as json;
use json::validation::{Checked::Valid, USize64};

use super::AssetGeometry;

/// Build the .glb bytes. `provenance` becomes `asset.extras`.
pub fn glb_bytes(
    geo: &AssetGeometry,
    albedo_png: &[u8],
    orm_png: &[u8],
    metallic: bool,
    material_name: &str,
    asset_name: &str,
    provenance: &serde_json::Value,
) -> Result<Vec<u8>, String> {
    let mut bin: Vec<u8> = Vec::new();
    let mut root = json::Root::default();
    let buffer = root.push(json::Buffer {
        byte_length: USize64(0), // patched below
        name: None,
        uri: None,
        extensions: None,
        extras: None,
    });
    let view = |root: &mut json::Root,
                bin: &mut Vec<u8>,
                bytes: &[u8],
                target: Option<json::buffer::Target>| {
        while bin.len() % 4 != 0 {
            bin.push(0);
        }
        let offset = bin.len();
        bin.extend_from_slice(bytes);
        root.push(json::buffer::View {
            buffer,
            byte_length: USize64(bytes.len() as u64),
            byte_offset: Some(USize64(offset as u64)),
            byte_stride: None,
            name: None,
            target: target.map(Valid),
            extensions: None,
            extras: None,
        })
    };
    let accessor = |root: &mut json::Root,
                    view: json::Index<json::buffer::View>,
                    count: usize,
                    ct: json::accessor::ComponentType,
                    ty: json::accessor::Type,
                    minmax: Option<([f32; 3], [f32; 3])>| {
        root.push(json::Accessor {
            buffer_view: Some(view),
            byte_offset: Some(USize64(0)),
            count: USize64(count as u64),
            component_type: Valid(json::accessor::GenericComponentType(ct)),
            type_: Valid(ty),
            min: minmax.map(|(lo, _)| serde_json::json!(lo)),
            max: minmax.map(|(_, hi)| serde_json::json!(hi)),
            name: None,
            normalized: false,
            sparse: None,
            extensions: None,
            extras: None,
        })
    };
    use json::accessor::{ComponentType as C, Type as T};
    use json::buffer::Target;
    let n = geo.positions.len();
    let iv = view(
        &mut root,
        &mut bin,
        bytemuck::cast_slice(&geo.indices),
        Some(Target::ElementArrayBuffer),
    );
    let pv = view(
        &mut root,
        &mut bin,
        bytemuck::cast_slice(&geo.positions),
        Some(Target::ArrayBuffer),
    );
    let nv = view(
        &mut root,
        &mut bin,
        bytemuck::cast_slice(&geo.normals),
        Some(Target::ArrayBuffer),
    );
    let tv = view(
        &mut root,
        &mut bin,
        bytemuck::cast_slice(&geo.uvs),
        Some(Target::ArrayBuffer),
    );
    let av = view(&mut root, &mut bin, albedo_png, None);
    let ov = view(&mut root, &mut bin, orm_png, None);
    while bin.len() % 4 != 0 {
        bin.push(0);
    }
    root.buffers[buffer.value()].byte_length = USize64(bin.len() as u64);

    let ia = accessor(&mut root, iv, geo.indices.len(), C::U32, T::Scalar, None);
    let (lo, hi) = geo.bounds();
    let pa = accessor(&mut root, pv, n, C::F32, T::Vec3, Some((lo, hi)));
    let na = accessor(&mut root, nv, n, C::F32, T::Vec3, None);
    let ta = accessor(&mut root, tv, n, C::F32, T::Vec2, None);

    let sampler = root.push(json::texture::Sampler {
        mag_filter: Some(Valid(json::texture::MagFilter::Linear)),
        min_filter: Some(Valid(json::texture::MinFilter::LinearMipmapLinear)),
        wrap_s: Valid(json::texture::WrappingMode::ClampToEdge),
        wrap_t: Valid(json::texture::WrappingMode::ClampToEdge),
        name: None,
        extensions: None,
        extras: None,
    });
    let texture = |root: &mut json::Root, view, name: &str| {
        let image = root.push(json::Image {
            buffer_view: Some(view),
            mime_type: Some(json::image::MimeType("image/png".into())),
            name: Some(name.into()),
            uri: None,
            extensions: None,
            extras: None,
        });
        root.push(json::Texture {
            name: Some(name.into()),
            sampler: Some(sampler),
            source: image,
            extensions: None,
            extras: None,
        })
    };
    let albedo_tex = texture(&mut root, av, "albedo");
    let orm_tex = texture(&mut root, ov, "orm");
    let info = |index| json::texture::Info {
        index,
        tex_coord: 0,
        extensions: None,
        extras: None,
    };
    let material = root.push(json::Material {
        alpha_cutoff: None,
        alpha_mode: Valid(json::material::AlphaMode::Opaque),
        double_sided: false,
        name: Some(material_name.into()),
        pbr_metallic_roughness: json::material::PbrMetallicRoughness {
            base_color_factor: json::material::PbrBaseColorFactor([1.0; 4]),
            base_color_texture: Some(info(albedo_tex)),
            metallic_factor: json::material::StrengthFactor(if metallic { 1.0 } else { 0.0 }),
            roughness_factor: json::material::StrengthFactor(1.0),
            metallic_roughness_texture: Some(info(orm_tex)),
            extensions: None,
            extras: None,
        },
        normal_texture: None,
        occlusion_texture: None,
        emissive_texture: None,
        emissive_factor: json::material::EmissiveFactor([0.0; 3]),
        extensions: None,
        extras: None,
    });
    let mut attributes = BTreeMap::new();
    attributes.insert(Valid(json::mesh::Semantic::Positions), pa);
    attributes.insert(Valid(json::mesh::Semantic::Normals), na);
    attributes.insert(Valid(json::mesh::Semantic::TexCoords(0)), ta);
    let mesh = root.push(json::Mesh {
        name: Some(asset_name.into()),
        primitives: vec![json::mesh::Primitive {
            attributes,
            indices: Some(ia),
            material: Some(material),
            mode: Valid(json::mesh::Mode::Triangles),
            targets: None,
            extensions: None,
            extras: None,
        }],
        weights: None,
        extensions: None,
        extras: None,
    });
    let node = root.push(json::Node {
        mesh: Some(mesh),
        name: Some(asset_name.into()),
        ..Default::default()
    });
    let scene = root.push(json::Scene {
        nodes: vec![node],
        name: Some(asset_name.into()),
        extensions: None,
        extras: None,
    });
    root.scene = Some(scene);
    root.asset.generator = Some(format!("pii-bake {}", env!("CARGO_PKG_VERSION")));
    root.asset.extras = Some(
        json::extras::RawValue::from_string(provenance.to_string())
            .map_err(|e| format!("provenance: {e}"))?,
    );

    let mut text = root.to_vec().map_err(|e| e.to_string())?;
    while text.len() % 4 != 0 {
        text.push(b' ');
    }
    Ok(pack_glb(&text, &bin))
}

/// The GLB container: 12-byte header, a JSON chunk (space-padded) and a BIN chunk (zero-padded).
pub fn pack_glb(json_chunk: &[u8], bin_chunk: &[u8]) -> Vec<u8> {
    let total = 12 + 8 + json_chunk.len() + 8 + bin_chunk.len();
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json_chunk.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(json_chunk);
    out.extend_from_slice(&(bin_chunk.len() as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(bin_chunk);
    out
}
