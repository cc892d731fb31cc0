//! USD text layers (conventions.md): `asset.usda` (the component: defaultPrim, kind, assetInfo,
//! metersPerUnit = 1, upAxis = Y, payload), `payload.usda` (`geo` and `mtl` scopes: the mesh and a
//! UsdPreviewSurface material) and `lookdev.usda` (the asset referenced beside a DomeLight on the
//! environment EXR). Texture paths are relative (`@./textures/...@`); `primvars:st` has
//! t = 1 − v relative to glTF.

use std::fmt::Write;

use super::AssetGeometry;

/// File names inside the asset folder.
pub const ASSET: &str = "asset.usda";
pub const PAYLOAD: &str = "payload.usda";
pub const LOOKDEV: &str = "lookdev.usda";
pub const ALBEDO: &str = "textures/albedo.png";
pub const ORM: &str = "textures/orm.png";

fn header(default_prim: &str, doc: &str) -> String {
    format!(
        "#usda 1.0\n(\n    defaultPrim = \"{default_prim}\"\n    doc = \"{doc}\"\n    metersPerUnit = 1\n    upAxis = \"Y\"\n)\n\n"
    )
}

fn vec3_list(v: &[[f32; 3]]) -> String {
    let mut s = String::with_capacity(v.len() * 30);
    s.push('[');
    for (i, p) in v.iter().enumerate() {
        if i > 0 {
            s.push_str(", ");
        }
        let _ = write!(s, "({}, {}, {})", p[0], p[1], p[2]);
    }
    s.push(']');
    s
}

fn int_list(v: impl Iterator<Item = u32>) -> String {
    let items: Vec<String> = v.map(|i| i.to_string()).collect();
    format!("[{}]", items.join(", "))
}

/// The root layer of the component.
pub fn asset_layer(name: &str, version: &str, thumbnail: &str) -> String {
    let mut s = header(
        name,
        "pii-bake asset (geometry and material behind the payload)",
    );
    let _ = write!(
        s,
        r#"def Xform "{name}" (
    assetInfo = {{
        asset identifier = @./{ASSET}@
        string name = "{name}"
        dictionary previews = {{
            dictionary thumbnails = {{
                dictionary default = {{
                    asset defaultImage = @./{thumbnail}@
                }}
            }}
        }}
        string version = "{version}"
    }}
    kind = "component"
    prepend payload = @./{PAYLOAD}@
)
{{
}}
"#
    );
    s
}

/// The payload layer: geometry and material.
pub fn payload_layer(name: &str, material: &str, geo: &AssetGeometry, metallic: bool) -> String {
    let mut s = header(name, "pii-bake asset payload");
    let (lo, hi) = geo.bounds();
    // USD texture space has t = 1 - v relative to glTF (origin at the bottom left).
    let st: Vec<String> = geo
        .uvs
        .iter()
        .map(|t| format!("({}, {})", t[0], 1.0 - t[1]))
        .collect();
    let counts = int_list(std::iter::repeat_n(3u32, geo.indices.len() / 3));
    // The ORM texture's B carries metallic where the material has it (as the .glb's).
    let metallic_input = if metallic {
        format!("float inputs:metallic.connect = </{name}/mtl/{material}/orm.outputs:b>")
    } else {
        "float inputs:metallic = 0".to_string()
    };
    let _ = write!(
        s,
        r#"def Xform "{name}"
{{
    def Scope "geo"
    {{
        def Mesh "mesh" (
            prepend apiSchemas = ["MaterialBindingAPI"]
        )
        {{
            float3[] extent = [({}, {}, {}), ({}, {}, {})]
            int[] faceVertexCounts = {counts}
            int[] faceVertexIndices = {}
            rel material:binding = </{name}/mtl/{material}>
            normal3f[] normals = {} (
                interpolation = "vertex"
            )
            uniform token orientation = "rightHanded"
            point3f[] points = {}
            texCoord2f[] primvars:st = [{}] (
                interpolation = "vertex"
            )
            uniform token subdivisionScheme = "none"
        }}
    }}

    def Scope "mtl"
    {{
        def Material "{material}"
        {{
            token outputs:surface.connect = </{name}/mtl/{material}/surface.outputs:surface>

            def Shader "surface"
            {{
                uniform token info:id = "UsdPreviewSurface"
                color3f inputs:diffuseColor.connect = </{name}/mtl/{material}/albedo.outputs:rgb>
                {metallic_input}
                float inputs:roughness.connect = </{name}/mtl/{material}/orm.outputs:g>
                int inputs:useSpecularWorkflow = 0
                token outputs:surface
            }}

            def Shader "st_reader"
            {{
                uniform token info:id = "UsdPrimvarReader_float2"
                string inputs:varname = "st"
                float2 outputs:result
            }}

            def Shader "albedo"
            {{
                uniform token info:id = "UsdUVTexture"
                asset inputs:file = @./{ALBEDO}@
                token inputs:sourceColorSpace = "sRGB"
                float2 inputs:st.connect = </{name}/mtl/{material}/st_reader.outputs:result>
                token inputs:wrapS = "clamp"
                token inputs:wrapT = "clamp"
                float3 outputs:rgb
            }}

            def Shader "orm"
            {{
                uniform token info:id = "UsdUVTexture"
                asset inputs:file = @./{ORM}@
                token inputs:sourceColorSpace = "raw"
                float2 inputs:st.connect = </{name}/mtl/{material}/st_reader.outputs:result>
                token inputs:wrapS = "clamp"
                token inputs:wrapT = "clamp"
                float outputs:g
                float outputs:b
            }}
        }}
    }}
}}
"#,
        lo[0],
        lo[1],
        lo[2],
        hi[0],
        hi[1],
        hi[2],
        int_list(geo.indices.iter().copied()),
        vec3_list(&geo.normals),
        vec3_list(&geo.positions),
        st.join(", "),
    );
    s
}

/// The look-dev layer: the asset referenced under an assembly, lit by a DomeLight on the
/// latlong EXR (OpenEXR/USD convention: +Y up, image centre along +Z).
pub fn lookdev_layer(name: &str, env_exr: &str) -> String {
    let mut s = header(
        "lookdev",
        "pii-bake look-dev: the asset under its environment",
    );
    let _ = write!(
        s,
        r#"def Xform "lookdev" (
    kind = "assembly"
)
{{
    def "{name}" (
        prepend references = @./{ASSET}@
    )
    {{
    }}

    def DomeLight "environment"
    {{
        float inputs:intensity = 1
        asset inputs:texture:file = @./{env_exr}@
        token inputs:texture:format = "latlong"
    }}
}}
"#
    );
    s
}
