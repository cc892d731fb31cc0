"""Ground-truth scene generator for pii-bake (Blender 5.0.1 as a Python module, `bpy`).

Renders one synthetic scene in the NeRF/Blender `transforms_{train,test}.json` format with Cycles on the CPU,
deterministically (fixed seed, fixed sample count, fixed thread count, denoiser off, no metadata stamps),
view transform "Standard", transparent film, one Principled BSDF per object (albedo and roughness from image
textures; metallic 0, except the `metal` scene's, from a metallic texture), lit only by an HDR latlong world from
`shared/data/envmaps`.

Usage:
    python scripts/make_scene.py --scene {spot,bowl,glossy,textureless,metal,bunny} --out DIR [--width 200] [--height 200]
        [--train 24] [--test 4] [--samples 64] [--gt-samples 16] [--env-width 512] [--threads 2]
        [--data ../shared/data]

Output layout (all paths relative to DIR; the world frame is Blender's: right-handed, +Z up, metres):
    transforms_train.json, transforms_test.json   NeRF/Blender format: camera_angle_x, frames[].file_path
                                                  (no extension, .png), frames[].transform_matrix =
                                                  camera-to-world with OpenGL camera axes (-Z forward, +Y up).
                                                  Blender's pixel grid: pixel (i, j) covers [i, i+1]x[j, j+1],
                                                  principal point = image centre (w/2, h/2).
    train/r_NNN.png, test/r_NNN.png               RGBA 8-bit, colour sRGB-encoded, straight alpha = coverage.
    test/r_NNN_albedo.png                         GT base colour (sRGB-encoded RGBA, alpha = coverage).
    test/r_NNN_roughness.png                      GT perceptual roughness R (linear 8-bit, R=G=B, alpha).
    test/r_NNN_normal.png                         GT world-space shading normal n, stored as n*0.5+0.5 (linear).
    test/r_NNN_metallic.png                       GT metallic (linear 8-bit, R=G=B, alpha; the `metal` scene only).
    test/r_NNN_relit_<env>.png                    the test view relit by another environment (sRGB RGBA).
    env/train.exr, env/<env>.exr                  the environments exactly as rendered with (linear float
                                                  latlong, 2:1), in **Blender's World convention**: +Z up,
                                                  image centre (u = 0.5) looks along world +X, u = 0.25 along
                                                  world +Y, row 0 = zenith (src/sg/env.rs LatlongConvention::Blender
                                                  once the scene's Z-up world is mapped to glTF's Y-up frame as
                                                  (x, y, z) -> (x, z, -y)).
    gt/mesh.obj                                   GT triangle mesh in the world frame (v, f; 1-based).
    gt/albedo_*.png, gt/roughness_*.png           the textures used (sRGB albedo, linear roughness; linear
    gt/metallic_*.png                             metallic where a scene has one).
    scene.json                                    metadata: scene kind, world frame, env convention, GT file
                                                  naming, probe points on the surface, render settings.
    render_log.json                               wall-clock time per phase (not deterministic; not compared).

Measured (200x200, 24 train + 4 test views, 64 spp, GT passes 16 spp, 2 relit envs, env 256x128, 2 threads on a
shared 2-core CPU): spot 235 s, bowl 498 s, glossy 254 s; textureless (the bowl's shapes, one uniform matte
colour each; 512x256 envs, the CPU not shared) 159 s; bunny (512x256 envs, the CPU shared) 115 s. The bundled example tests/data/example is
`--scene spot --width 200 --height 200 --train 24 --test 4 --samples 64 --env-width 256`.
"""

import argparse
import json
import math
import os
import struct
import sys
import time

import bpy
from mathutils import Matrix
import numpy as np

SCRIPT_VERSION = 1


def parse_args(argv):
    here = os.path.dirname(os.path.abspath(__file__))
    default_data = os.path.normpath(os.path.join(here, "..", "..", "shared", "data"))
    if not os.path.isdir(default_data):
        default_data = "/work/shared/data"
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scene", choices=["spot", "bowl", "glossy", "textureless", "metal", "bunny"], required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--width", type=int, default=200)
    p.add_argument("--height", type=int, default=200)
    p.add_argument("--train", type=int, default=24)
    p.add_argument("--test", type=int, default=4)
    p.add_argument("--samples", type=int, default=64, help="Cycles samples per pixel for shaded views")
    p.add_argument("--gt-samples", type=int, default=16, help="samples for the albedo/roughness/normal passes")
    p.add_argument("--env-width", type=int, default=512, help="width of the environments used (2:1 latlong)")
    p.add_argument("--threads", type=int, default=2, help="fixed Cycles thread count (determinism)")
    p.add_argument("--no-relight", action="store_true", help="skip the relit test views")
    p.add_argument("--data", default=os.environ.get("PII_SHARED_DATA", default_data))
    return p.parse_args(argv)


# Environments: training map and the two relighting maps per scene.
ENVS = {
    "spot": ("blender_studiolights/courtyard.exr", ["blender_studiolights/sunset.exr", "invrender/envmap6.exr"]),
    "bowl": ("blender_studiolights/sunrise.exr", ["blender_studiolights/studio.exr", "blender_studiolights/city.exr"]),
    "glossy": ("blender_studiolights/forest.exr", ["blender_studiolights/interior.exr", "invrender/envmap12.exr"]),
    "textureless": ("blender_studiolights/courtyard.exr", ["blender_studiolights/studio.exr", "invrender/envmap3.exr"]),
    "metal": ("blender_studiolights/courtyard.exr", ["blender_studiolights/sunset.exr", "invrender/envmap6.exr"]),
    "bunny": ("blender_studiolights/city.exr", ["blender_studiolights/forest.exr", "invrender/envmap3.exr"]),
}


def env_name(rel):
    return os.path.splitext(os.path.basename(rel))[0]


# ---------------------------------------------------------------- textures


def save_texture(name, pixels_rgba, path, non_color):
    """Write an 8-bit PNG texture from float RGBA (rows bottom-up, Blender's order) and load it back."""
    h, w, _ = pixels_rgba.shape
    img = bpy.data.images.new(name, w, h, alpha=True, float_buffer=False)
    if non_color:
        img.colorspace_settings.name = "Non-Color"
    img.pixels.foreach_set(np.ascontiguousarray(pixels_rgba, dtype=np.float32).ravel())
    img.filepath_raw = path
    img.file_format = "PNG"
    img.save()
    bpy.data.images.remove(img)
    strip_png_metadata(path)
    loaded = bpy.data.images.load(path)
    if non_color:
        loaded.colorspace_settings.name = "Non-Color"
    return loaded


def uv_grid(n):
    v, u = np.meshgrid((np.arange(n) + 0.5) / n, (np.arange(n) + 0.5) / n, indexing="ij")
    return u, v


def rgba(r, g, b):
    return np.stack([r, g, b, np.ones_like(r)], axis=-1)


def roughness_pattern(n, lo, hi, freq):
    """Smooth spatially varying roughness in [lo, hi] (stored as the PNG's value, linear)."""
    u, v = uv_grid(n)
    t = 0.5 + 0.25 * np.sin(2 * math.pi * freq * u) + 0.25 * np.cos(2 * math.pi * freq * v)
    r = lo + (hi - lo) * t
    return rgba(r, r, r)


def checker_albedo(n, c0, c1, cells):
    u, v = uv_grid(n)
    k = ((np.floor(u * cells) + np.floor(v * cells)) % 2)[..., None]
    col = np.array(c0)[None, None, :] * (1 - k) + np.array(c1)[None, None, :] * k
    return rgba(col[..., 0], col[..., 1], col[..., 2])


# ---------------------------------------------------------------- materials


def principled_material(name, albedo_img, rough_img, metal_img=None):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nt = mat.node_tree
    for n in list(nt.nodes):
        nt.nodes.remove(n)
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
    bsdf.inputs["Metallic"].default_value = 0.0
    uv = nt.nodes.new("ShaderNodeTexCoord")
    ta = nt.nodes.new("ShaderNodeTexImage")
    ta.image = albedo_img
    ta.interpolation = "Linear"
    tr = nt.nodes.new("ShaderNodeTexImage")
    tr.image = rough_img
    tr.interpolation = "Linear"
    nt.links.new(uv.outputs["UV"], ta.inputs["Vector"])
    nt.links.new(uv.outputs["UV"], tr.inputs["Vector"])
    nt.links.new(ta.outputs["Color"], bsdf.inputs["Base Color"])
    nt.links.new(tr.outputs["Color"], bsdf.inputs["Roughness"])
    if metal_img is not None:
        tm = nt.nodes.new("ShaderNodeTexImage")
        tm.image = metal_img
        tm.interpolation = "Linear"
        nt.links.new(uv.outputs["UV"], tm.inputs["Vector"])
        nt.links.new(tm.outputs["Color"], bsdf.inputs["Metallic"])
    nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    # Keep handles for the ground-truth passes (emission swaps).
    mat["pii_albedo"] = albedo_img.name
    mat["pii_rough"] = rough_img.name
    if metal_img is not None:
        mat["pii_metal"] = metal_img.name
    return mat


def textured(ob, name, albedo_px, rough_px, tex_dir):
    """Give `ob` one Principled material `name` from an albedo and a roughness texture, written as
    gt/albedo_<name>.png and gt/roughness_<name>.png."""
    a = save_texture(name + "_albedo", albedo_px, os.path.join(tex_dir, "albedo_%s.png" % name), non_color=False)
    r = save_texture(name + "_rough", rough_px, os.path.join(tex_dir, "roughness_%s.png" % name), non_color=True)
    ob.data.materials.clear()
    ob.data.materials.append(principled_material(name, a, r))


def emission_material(name, kind, albedo_img=None, rough_img=None, metal_img=None):
    """Emission-only material that outputs a GT quantity: albedo, roughness, metallic (0 without a metallic
    texture) or normal*0.5+0.5."""
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nt = mat.node_tree
    for n in list(nt.nodes):
        nt.nodes.remove(n)
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    em = nt.nodes.new("ShaderNodeEmission")
    em.inputs["Strength"].default_value = 1.0
    if kind in ("albedo", "roughness"):
        uv = nt.nodes.new("ShaderNodeTexCoord")
        t = nt.nodes.new("ShaderNodeTexImage")
        t.image = albedo_img if kind == "albedo" else rough_img
        t.interpolation = "Linear"
        nt.links.new(uv.outputs["UV"], t.inputs["Vector"])
        nt.links.new(t.outputs["Color"], em.inputs["Color"])
    elif kind == "metallic":
        if metal_img is None:
            em.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
        else:
            uv = nt.nodes.new("ShaderNodeTexCoord")
            t = nt.nodes.new("ShaderNodeTexImage")
            t.image = metal_img
            t.interpolation = "Linear"
            nt.links.new(uv.outputs["UV"], t.inputs["Vector"])
            nt.links.new(t.outputs["Color"], em.inputs["Color"])
    else:
        geo = nt.nodes.new("ShaderNodeNewGeometry")
        ma = nt.nodes.new("ShaderNodeVectorMath")
        ma.operation = "MULTIPLY_ADD"
        ma.inputs[1].default_value = (0.5, 0.5, 0.5)
        ma.inputs[2].default_value = (0.5, 0.5, 0.5)
        nt.links.new(geo.outputs["Normal"], ma.inputs[0])
        nt.links.new(ma.outputs["Vector"], em.inputs["Color"])
    nt.links.new(em.outputs["Emission"], out.inputs["Surface"])
    return mat


# ---------------------------------------------------------------- geometry


def add_uv_sphere(name, radius, location, segments=64, rings=32):
    bpy.ops.mesh.primitive_uv_sphere_add(segments=segments, ring_count=rings, radius=radius, location=location,
                                         calc_uvs=True)
    ob = bpy.context.active_object
    ob.name = name
    bpy.ops.object.shade_smooth()
    return ob


def build_spot(args, tex_dir):
    path = os.path.join(args.data, "meshes", "spot", "spot_triangulated.obj")
    bpy.ops.wm.obj_import(filepath=path, forward_axis="NEGATIVE_Z", up_axis="Y")
    ob = bpy.context.selected_objects[0]
    ob.name = "spot"
    bpy.context.view_layer.objects.active = ob
    bpy.ops.object.shade_smooth()
    alb = bpy.data.images.load(os.path.join(args.data, "meshes", "spot", "spot_texture.png"))
    alb_small = alb.copy()
    alb_small.scale(256, 256)
    alb_px = np.array(alb_small.pixels[:], dtype=np.float32).reshape(256, 256, 4)
    textured(ob, "spot", alb_px, roughness_pattern(256, 0.3, 0.8, 3), tex_dir)
    return [ob]


def build_metal(args, tex_dir):
    # Spot with metal patches: a checker of metallic 1 and 0 (large cells, so both show in every view) over
    # spot's albedo (a metal's reflectance colour where metallic) and roughness. A dielectric-only model can
    # give a metal's albedo-coloured highlights only to the light.
    objs = build_spot(args, tex_dir)
    m = save_texture("spot_metal", checker_albedo(256, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), 4),
                     os.path.join(tex_dir, "metallic_spot.png"), non_color=True)
    ob = objs[0]
    old = ob.data.materials[0]
    a, r = bpy.data.images[old["pii_albedo"]], bpy.data.images[old["pii_rough"]]
    ob.data.materials.clear()
    ob.data.materials.append(principled_material("spot_metal", a, r, m))
    return objs


def build_bunny(args, tex_dir):
    # The Stanford bunny (a scan: thin ears, a bumpy surface, open holes in its base), scaled from
    # its ~0.16 m to about 1.6 m across like the other scenes, UVs by Blender's smart projection, a
    # checker albedo (its cells cut at chart seams: texture everywhere) and a smooth roughness pattern. An
    # object none of the other scenes resemble, with parts a few pixels thin at 200 px.
    path = os.path.join(args.data, "meshes", "stanford-bunny.obj")
    bpy.ops.wm.obj_import(filepath=path, forward_axis="NEGATIVE_Z", up_axis="Y")
    ob = bpy.context.selected_objects[0]
    ob.name = "bunny"
    bpy.context.view_layer.objects.active = ob
    ob.scale = (10.0, 10.0, 10.0)
    bpy.ops.object.transform_apply(location=False, rotation=True, scale=True)
    lo = np.array([min(v.co[k] for v in ob.data.vertices) for k in range(3)])
    hi = np.array([max(v.co[k] for v in ob.data.vertices) for k in range(3)])
    c = 0.5 * (lo + hi)
    for v in ob.data.vertices:
        v.co = (v.co[0] - c[0], v.co[1] - c[1], v.co[2] - c[2])
    bpy.ops.object.mode_set(mode="EDIT")
    bpy.ops.mesh.select_all(action="SELECT")
    bpy.ops.uv.smart_project(angle_limit=math.radians(66.0), island_margin=0.01)
    bpy.ops.object.mode_set(mode="OBJECT")
    bpy.ops.object.shade_smooth()
    textured(ob, "bunny", checker_albedo(256, (0.75, 0.7, 0.6), (0.3, 0.45, 0.25), 10), roughness_pattern(256, 0.3, 0.7, 2),
             tex_dir)
    return [ob]


def bowl_and_ball():
    """A hemispherical bowl (open at the top, thick wall) holding a ball: strong interreflection and
    self-shadowing inside the bowl."""
    bowl = add_uv_sphere("bowl", 1.0, (0.0, 0.0, 0.0))
    me = bowl.data
    import bmesh

    bm = bmesh.new()
    bm.from_mesh(me)
    bmesh.ops.delete(bm, geom=[v for v in bm.verts if v.co.z > 0.2], context="VERTS")
    bm.to_mesh(me)
    bm.free()
    mod = bowl.modifiers.new("wall", "SOLIDIFY")
    mod.thickness = 0.08
    mod.offset = 1.0
    bpy.context.view_layer.objects.active = bowl
    bpy.ops.object.modifier_apply(modifier="wall")
    ball = add_uv_sphere("ball", 0.45, (0.0, 0.0, -0.5))
    return bowl, ball


def build_bowl(args, tex_dir):
    bowl, ball = bowl_and_ball()
    textured(bowl, "bowl", checker_albedo(256, (0.8, 0.75, 0.7), (0.55, 0.2, 0.15), 8), roughness_pattern(256, 0.35, 0.75, 2),
             tex_dir)
    textured(ball, "ball", checker_albedo(256, (0.2, 0.45, 0.75), (0.85, 0.85, 0.3), 6), roughness_pattern(256, 0.2, 0.5, 4),
             tex_dir)
    return [bowl, ball]


def build_textureless(args, tex_dir):
    # The bowl and ball in one uniform matte colour each: no texture for photo-consistency or the
    # photometric loss to lock onto, only shading, silhouettes and interreflection (a known failure
    # case for multi-view stereo and inverse rendering alike).
    bowl, ball = bowl_and_ball()
    for ob, colour, rough in ((bowl, (0.7, 0.68, 0.62), 0.5), (ball, (0.35, 0.5, 0.7), 0.4)):
        textured(ob, ob.name, checker_albedo(16, colour, colour, 1), roughness_pattern(16, rough, rough, 1), tex_dir)
    return [bowl, ball]


def build_glossy(args, tex_dir):
    # A smooth sphere and a torus, roughness 0.05-0.15: a known failure case for SG shading.
    s = add_uv_sphere("sphere", 0.6, (0.0, 0.0, 0.0))
    bpy.ops.mesh.primitive_torus_add(major_radius=0.9, minor_radius=0.2, major_segments=64, minor_segments=24,
                                     location=(0.0, 0.0, -0.1), generate_uvs=True)
    t = bpy.context.active_object
    t.name = "torus"
    t.rotation_euler = (0.35, 0.0, 0.0)
    bpy.ops.object.shade_smooth()
    textured(s, "sphere", checker_albedo(256, (0.7, 0.1, 0.1), (0.9, 0.8, 0.6), 6), roughness_pattern(256, 0.05, 0.15, 2),
             tex_dir)
    textured(t, "torus", checker_albedo(256, (0.15, 0.15, 0.2), (0.6, 0.65, 0.7), 12), roughness_pattern(256, 0.05, 0.15, 3),
             tex_dir)
    return [s, t]


def world_triangles(objs):
    """Evaluated world-space vertices and triangles of all objects (one merged mesh)."""
    deps = bpy.context.evaluated_depsgraph_get()
    verts, tris = [], []
    for ob in objs:
        ev = ob.evaluated_get(deps)
        me = ev.to_mesh()
        me.calc_loop_triangles()
        mw = np.array(ob.matrix_world)
        co = np.array([v.co for v in me.vertices], dtype=np.float64)
        co = co @ mw[:3, :3].T + mw[:3, 3]
        base = sum(len(v) for v in verts)
        verts.append(co)
        tris.extend([[base + i for i in t.vertices] for t in me.loop_triangles])
        ev.to_mesh_clear()
    return np.concatenate(verts), np.array(tris, dtype=np.int64)


def write_obj(path, verts, tris):
    lines = ["# pii-bake make_scene.py ground-truth mesh, world frame (+Z up, metres)"]
    lines += ["v %.6f %.6f %.6f" % tuple(v) for v in verts]
    lines += ["f %d %d %d" % (t[0] + 1, t[1] + 1, t[2] + 1) for t in tris]
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


# ---------------------------------------------------------------- cameras, world, render


def fibonacci_dirs(n, offset, z_min, z_max):
    """n unit directions on a spherical band z in [z_min, z_max], golden-angle spiral."""
    golden = math.pi * (3.0 - math.sqrt(5.0))
    out = []
    for i in range(n):
        z = z_max - (z_max - z_min) * (i + 0.5) / n
        r = math.sqrt(max(0.0, 1.0 - z * z))
        phi = golden * i + offset
        out.append((r * math.cos(phi), r * math.sin(phi), z))
    return out


def look_at(cam_pos, target=(0.0, 0.0, 0.0)):
    """camera-to-world 4x4 (OpenGL axes: -Z forward, +Y up) looking at target with world +Z up."""
    c = np.array(cam_pos, dtype=np.float64)
    fwd = np.array(target) - c
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, np.array([0.0, 0.0, 1.0]))
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, -fwd, c
    return m


def setup_render(args):
    scene = bpy.context.scene
    r = scene.render
    r.engine = "CYCLES"
    r.resolution_x, r.resolution_y, r.resolution_percentage = args.width, args.height, 100
    r.film_transparent = True
    r.threads_mode = "FIXED"
    r.threads = args.threads
    r.image_settings.file_format = "PNG"
    r.image_settings.color_mode = "RGBA"
    r.image_settings.color_depth = "8"
    r.image_settings.compression = 90
    r.use_persistent_data = False
    for attr in dir(r):  # no date/time/render-time metadata in the PNGs (byte-identical reruns)
        if attr.startswith("use_stamp"):
            try:
                setattr(r, attr, False)
            except (AttributeError, TypeError):
                pass
    c = scene.cycles
    c.device = "CPU"
    c.samples = args.samples
    c.use_adaptive_sampling = False
    c.use_denoising = False
    c.seed = 0
    c.use_animated_seed = False
    c.sample_clamp_direct = 0.0
    c.sample_clamp_indirect = 0.0
    c.max_bounces = 8
    c.pixel_filter_type = "BLACKMAN_HARRIS"
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    scene.display_settings.display_device = "sRGB"
    return scene


def prepare_env(scene, src, dst, width):
    """Resize an environment to width x width/2, save it as a half-float ZIP EXR and load that file back:
    the saved file is exactly what lights the scene (the ground truth of the environment)."""
    img = bpy.data.images.load(src)
    img.colorspace_settings.name = "Linear Rec.709"
    small = img.copy()
    small.scale(width, width // 2)
    st = scene.render.image_settings
    saved = (st.file_format, st.color_mode, st.color_depth)
    st.file_format = "OPEN_EXR"
    st.color_mode = "RGB"
    st.color_depth = "16"
    st.exr_codec = "ZIP"
    small.save_render(dst, scene=scene)
    st.file_format, st.color_mode, st.color_depth = saved
    bpy.data.images.remove(small)
    bpy.data.images.remove(img)
    out = bpy.data.images.load(dst)
    out.colorspace_settings.name = "Linear Rec.709"
    return out


def setup_world(scene, env_img):
    world = bpy.data.worlds.new("env") if scene.world is None else scene.world
    scene.world = world
    world.use_nodes = True
    nt = world.node_tree
    for n in list(nt.nodes):
        nt.nodes.remove(n)
    out = nt.nodes.new("ShaderNodeOutputWorld")
    bg = nt.nodes.new("ShaderNodeBackground")
    tex = nt.nodes.new("ShaderNodeTexEnvironment")
    tex.image = env_img
    tex.interpolation = "Linear"
    tex.projection = "EQUIRECTANGULAR"
    bg.inputs["Strength"].default_value = 1.0
    nt.links.new(tex.outputs["Color"], bg.inputs["Color"])
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
    return tex, bg


KEEP_PNG_CHUNKS = (b"IHDR", b"PLTE", b"tRNS", b"IDAT", b"IEND")


def strip_png_metadata(path):
    """Keep only the image chunks: Cycles writes render timings as tEXt chunks (not reproducible)."""
    with open(path, "rb") as f:
        data = f.read()
    out, pos = [data[:8]], 8
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos:pos + 4])
        kind = data[pos + 4:pos + 8]
        if kind in KEEP_PNG_CHUNKS:
            out.append(data[pos:pos + 12 + n])
        pos += 12 + n
    with open(path, "wb") as f:
        f.write(b"".join(out))


def render_to(scene, path):
    scene.render.filepath = path
    bpy.ops.render.render(write_still=True)
    strip_png_metadata(path)


def main(argv):
    args = parse_args(argv)
    out = os.path.abspath(args.out)
    for d in ("train", "test", "env", "gt"):
        os.makedirs(os.path.join(out, d), exist_ok=True)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    times = {}
    t0 = time.time()
    tex_dir = os.path.join(out, "gt")
    objs = {"spot": build_spot, "bowl": build_bowl, "glossy": build_glossy, "textureless": build_textureless,
            "metal": build_metal, "bunny": build_bunny}[args.scene](args, tex_dir)
    has_metal = any("pii_metal" in s.material for ob in objs for s in ob.material_slots)
    verts, tris = world_triangles(objs)
    write_obj(os.path.join(out, "gt", "mesh.obj"), verts, tris)
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    center = 0.5 * (lo + hi)
    radius = float(np.max(np.linalg.norm(verts - center, axis=1)))
    # probe points: deterministic surface vertices, for projection tests
    idx = np.linspace(0, len(verts) - 1, 16).astype(int)
    probes = [[round(float(x), 6) for x in verts[i]] for i in idx]

    scene = setup_render(args)
    train_env, relight_envs = ENVS[args.scene]
    env_imgs = {"train": prepare_env(scene, os.path.join(args.data, "envmaps", train_env),
                                     os.path.join(out, "env", "train.exr"), args.env_width)}
    if not args.no_relight:
        for rel in relight_envs:
            env_imgs[env_name(rel)] = prepare_env(scene, os.path.join(args.data, "envmaps", rel),
                                                  os.path.join(out, "env", env_name(rel) + ".exr"), args.env_width)
    tex_node, bg = setup_world(scene, env_imgs["train"])

    cam_data = bpy.data.cameras.new("cam")
    cam_data.sensor_fit = "HORIZONTAL"
    fov_x = math.radians(40.0)
    cam_data.angle_x = fov_x
    cam_data.clip_start, cam_data.clip_end = 0.05, 100.0
    cam = bpy.data.objects.new("cam", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    aspect_min = min(args.width, args.height) / args.width
    half = math.atan(math.tan(fov_x / 2) * aspect_min)
    dist = float(1.15 * radius / math.sin(half))
    times["setup_s"] = time.time() - t0

    splits = {
        "train": [c * dist + center for c in np.array(fibonacci_dirs(args.train, 0.0, -0.35, 0.95))],
        "test": [c * dist + center for c in np.array(fibonacci_dirs(args.test, 1.3, -0.2, 0.8))],
    }
    frames = {}
    for split, positions in splits.items():
        t1 = time.time()
        frames[split] = []
        for i, pos in enumerate(positions):
            m = look_at(pos, center)
            cam.matrix_world = Matrix(m.tolist())
            bpy.context.view_layer.update()
            name = "r_%03d" % i
            render_to(scene, os.path.join(out, split, name + ".png"))
            frames[split].append({"file_path": "./%s/%s" % (split, name),
                                  "transform_matrix": [[round(float(x), 9) for x in row] for row in m]})
        times["%s_views_s" % split] = time.time() - t1

    # ground-truth passes for the test views: emission swaps, world off
    t1 = time.time()
    saved_mats = {ob.name: [s.material for s in ob.material_slots] for ob in objs}
    bg.inputs["Strength"].default_value = 0.0
    scene.cycles.samples = args.gt_samples
    scene.cycles.max_bounces = 0
    for kind in ("albedo", "roughness", "normal") + (("metallic",) if has_metal else ()):
        scene.view_settings.view_transform = "Standard" if kind == "albedo" else "Raw"
        for ob in objs:
            for slot in ob.material_slots:
                orig = saved_mats[ob.name][0]
                metal = bpy.data.images[orig["pii_metal"]] if "pii_metal" in orig else None
                slot.material = emission_material("%s_%s" % (ob.name, kind), kind,
                                                  bpy.data.images[orig["pii_albedo"]],
                                                  bpy.data.images[orig["pii_rough"]], metal)
        for i, fr in enumerate(frames["test"]):
            cam.matrix_world = Matrix(fr["transform_matrix"])
            bpy.context.view_layer.update()
            render_to(scene, os.path.join(out, "test", "r_%03d_%s.png" % (i, kind)))
    for ob in objs:
        for slot, mat in zip(ob.material_slots, saved_mats[ob.name]):
            slot.material = mat
    times["gt_passes_s"] = time.time() - t1

    # relit test views
    t1 = time.time()
    scene.view_settings.view_transform = "Standard"
    scene.cycles.samples = args.samples
    scene.cycles.max_bounces = 8
    bg.inputs["Strength"].default_value = 1.0
    relit = [k for k in env_imgs if k != "train"]
    for key in relit:
        tex_node.image = env_imgs[key]
        for i, fr in enumerate(frames["test"]):
            cam.matrix_world = Matrix(fr["transform_matrix"])
            bpy.context.view_layer.update()
            render_to(scene, os.path.join(out, "test", "r_%03d_relit_%s.png" % (i, key)))
    times["relit_views_s"] = time.time() - t1

    for split in ("train", "test"):
        doc = {"camera_angle_x": fov_x, "frames": frames[split]}
        with open(os.path.join(out, "transforms_%s.json" % split), "w") as f:
            json.dump(doc, f, indent=1)
    meta = {
        "generator": "scripts/make_scene.py v%d, Blender %s, Cycles CPU" % (SCRIPT_VERSION, bpy.app.version_string),
        "scene": args.scene,
        "world": {"up": "+Z", "handedness": "right", "units": "metres"},
        "bound": {"center": [round(float(x), 6) for x in center], "radius": round(radius, 6)},
        "probe_points": probes,
        "mesh": "gt/mesh.obj",
        "env": {
            "train": "env/train.exr",
            "train_source": train_env,
            "relight": {k: "env/%s.exr" % k for k in relit},
            "convention": "blender",
            "convention_note": "Blender World: +Z up, u=0.5 looks along +X, u=0.25 along +Y, row 0 = zenith",
        },
        "test_gt": {
            "rgb": "test/{name}.png",
            "albedo": "test/{name}_albedo.png (sRGB RGBA)",
            "roughness": "test/{name}_roughness.png (linear, R=G=B)",
            "normal": "test/{name}_normal.png (linear, world normal * 0.5 + 0.5)",
            "relit": "test/{name}_relit_{env}.png (sRGB RGBA)",
            **({"metallic": "test/{name}_metallic.png (linear, R=G=B)"} if has_metal else {}),
        },
        "render": {"width": args.width, "height": args.height, "samples": args.samples,
                   "gt_samples": args.gt_samples, "seed": 0, "threads": args.threads, "denoiser": False,
                   "view_transform": "Standard", "film_transparent": True, "max_bounces": 8,
                   "env_width": args.env_width, "camera_angle_x_deg": 40.0, "camera_distance": round(dist, 6)},
    }
    with open(os.path.join(out, "scene.json"), "w") as f:
        json.dump(meta, f, indent=1)
    times["total_s"] = time.time() - t0
    with open(os.path.join(out, "render_log.json"), "w") as f:
        json.dump({k: round(v, 2) for k, v in times.items()}, f, indent=1)
    print("make_scene: %s -> %s in %.1f s %s" % (args.scene, out, times["total_s"], json.dumps(times)))


if __name__ == "__main__":
    main(sys.argv[1:])
