"""Render a unit sphere with Blender's Principled BSDF (Cycles) under a latlong environment, one
linear EXR per (metallic, roughness): the reference `pii-bake bench brdf` compares its SG shading
with. Orthographic camera on -Y looking along +Y (Blender's +Z up), ortho scale 2.2, so pixel
(i, j) of a `size`-wide image sees x = (i + 0.5)/size·2.2 − 1.1, z = 1.1 − (j + 0.5)/size·2.2.

Usage (Python 3.11 with `bpy`):
  python brdf_spheres.py --env MAP.exr --out DIR --roughness 0.1,0.5 --metallic 1,0 \
      --base 0.8,0.6,0.4 [--size 96] [--samples 128] [--distribution MULTI_GGX]
Writes DIR/m{metallic:.2f}_r{roughness:.2f}.exr (RGBA, alpha = coverage).
"""
import argparse
import os
import sys

import bpy

ORTHO_SCALE = 2.2


def floats(s):
    return [float(x) for x in s.split(",") if x]


def main(argv):
    p = argparse.ArgumentParser()
    p.add_argument("--env", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--roughness", type=floats, required=True)
    p.add_argument("--metallic", type=floats, required=True)
    p.add_argument("--base", type=floats, required=True)
    p.add_argument("--size", type=int, default=96)
    p.add_argument("--samples", type=int, default=128)
    p.add_argument("--distribution", default="MULTI_GGX")
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args(argv)
    if len(a.base) != 3:
        sys.exit("--base needs three values")
    os.makedirs(a.out, exist_ok=True)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    r = sc.render
    r.engine = "CYCLES"
    r.resolution_x = r.resolution_y = a.size
    r.resolution_percentage = 100
    r.film_transparent = True
    r.threads_mode = "FIXED"
    r.threads = a.threads
    r.image_settings.file_format = "OPEN_EXR"
    r.image_settings.color_mode = "RGBA"
    r.image_settings.color_depth = "32"
    c = sc.cycles
    c.device = "CPU"
    c.samples = a.samples
    c.use_adaptive_sampling = False
    c.use_denoising = False
    c.seed = 0
    c.sample_clamp_direct = 0.0
    c.sample_clamp_indirect = 0.0
    c.max_bounces = 8
    c.pixel_filter_type = "BOX"
    c.filter_width = 1.0
    sc.view_settings.view_transform = "Standard"
    world = bpy.data.worlds.new("env")
    sc.world = world
    world.use_nodes = True
    nt = world.node_tree
    for n in list(nt.nodes):
        nt.nodes.remove(n)
    out = nt.nodes.new("ShaderNodeOutputWorld")
    bg = nt.nodes.new("ShaderNodeBackground")
    tex = nt.nodes.new("ShaderNodeTexEnvironment")
    img = bpy.data.images.load(os.path.abspath(a.env))
    img.colorspace_settings.name = "Linear Rec.709"
    tex.image = img
    tex.interpolation = "Linear"
    nt.links.new(tex.outputs["Color"], bg.inputs["Color"])
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
    bpy.ops.mesh.primitive_uv_sphere_add(segments=256, ring_count=128, radius=1.0)
    bpy.ops.object.shade_smooth()
    sphere = bpy.context.active_object
    mat = bpy.data.materials.new("sphere")
    mat.use_nodes = True
    sphere.data.materials.append(mat)
    bsdf = next(n for n in mat.node_tree.nodes if n.type == "BSDF_PRINCIPLED")
    bsdf.distribution = a.distribution
    bsdf.inputs["Base Color"].default_value = (*a.base, 1.0)
    cam = bpy.data.cameras.new("cam")
    cam.type = "ORTHO"
    cam.ortho_scale = ORTHO_SCALE
    cam_obj = bpy.data.objects.new("cam", cam)
    sc.collection.objects.link(cam_obj)
    sc.camera = cam_obj
    cam_obj.location = (0.0, -5.0, 0.0)
    cam_obj.rotation_euler = (1.5707963267948966, 0.0, 0.0)
    for m in a.metallic:
        for rough in a.roughness:
            bsdf.inputs["Metallic"].default_value = m
            bsdf.inputs["Roughness"].default_value = rough
            r.filepath = os.path.join(os.path.abspath(a.out), f"m{m:.2f}_r{rough:.2f}.exr")
            bpy.ops.render.render(write_still=True)


if __name__ == "__main__":
    main(sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:])
