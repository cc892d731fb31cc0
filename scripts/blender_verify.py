"""Render an exported pii-bake asset in Blender (bpy, Cycles) and report PSNR/SSIM.

The .glb and, separately, the USD (lookdev.usda: the asset plus a DomeLight on env.exr) are
imported into fresh scenes, lit by the same environment EXR and rendered from the given cameras.
Optionally an analytic reference (the shape and material built directly in Blender: a dense
primitive mesh and a procedural node material, see --analytic) is rendered from the same cameras,
and/or reference images are read from --reference-dir. A JSON report lists PSNR/SSIM of every
pair (glb vs reference, usd vs reference, usd vs glb).

Axes and environment convention (see ../shared/conventions.md): our world is glTF's (+Y up);
Blender's glTF importer maps (x, y, z) -> (x, -z, y). env.exr is written in the OpenEXR/USD
latlong convention (image centre along +Z, u = 0.25 along +X); Blender's world texture puts the
image centre along Blender +X (= our +X) and u = 0.25 along Blender +Y (= our -Z), so the world
lookup vector is rotated by +90 degrees about Blender Z to show the EXR the USD way.

Cameras JSON: [{"position": [x, y, z], "target": [x, y, z], "fov_deg": 40}, ...] in our world
frame (metres, +Y up); optional per camera: "up" (the image's up direction, default world +Y),
"width"/"height" (pixels; default --size square) with fov_deg then the horizontal field of view,
"shift_x"/"shift_y" (the principal point off centre as Blender's lens shift: the optical axis lands
at pixel (w/2 - shift_x*s, h/2 + shift_y*s), s the larger side, y down).

Reference images with an alpha channel (photos with their masks) are compared inside the mask:
PSNR weighted by the reference's alpha, SSIM on both images composited over black by it. Such
references hold the object's own colour at the silhouette (straight alpha), so the check renders
with --film-transparent: a render over the world would mix the world into every silhouette pixel
(a bright sky then reads as a light fringe the asset does not have).

--relight NAME ENV REFDIR (repeatable) renders the .glb again under each relight map ENV, taken
in Blender's World convention as it is (the frame the .glb imports into, the one a scene made by
make_scene.py renders its relit ground truth in), and scores it against REFDIR/ref_cam{i}.png as
rendered and after one factor per colour channel in linear light ("psnr_aligned": the
light/albedo scale ambiguity removed, as `pii-bake eval` scores relit views).

Usage:
  python scripts/blender_verify.py --asset-dir DIR --cameras cams.json --out OUTDIR
      [--analytic sphere|torus --material gradient|checker --metres-per-unit S --origin-shift X Y Z]
      [--reference-dir REFS] [--relight NAME ENV REFDIR ...] [--size 96] [--samples 64] [--json report.json]
"""
import argparse
import glob
import json
import math
import os
import sys

import bpy
import numpy as np
from mathutils import Vector


def to_blender(p):
    return Vector((p[0], -p[2], p[1]))


def reset_scene(args):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = args.samples
    scene.cycles.use_denoising = args.denoise
    scene.cycles.seed = 1
    scene.cycles.max_bounces = 4
    scene.render.resolution_x = args.size
    scene.render.resolution_y = args.size
    scene.render.resolution_percentage = 100
    # --film-transparent: the asset alone, its colour straight (not mixed with the world at the
    # silhouette) and its coverage as alpha, as the references of a masked comparison have it.
    scene.render.film_transparent = args.film_transparent
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGBA" if args.film_transparent else "RGB"
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.display_settings.display_device = "sRGB"
    return scene


def make_world(scene, env_path, convention="usd"):
    """The EXR as the world. convention "usd": the map is in the OpenEXR/USD convention (centre
    along +Z of the glTF/USD frame), rotated 90 degrees about Blender's Z to read that way;
    "blender": the map is already in Blender's World convention and is used as it is."""
    world = bpy.data.worlds.new("World")
    scene.world = world
    world.use_nodes = True
    nt = world.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputWorld")
    bg = nt.nodes.new("ShaderNodeBackground")
    if env_path:
        tex = nt.nodes.new("ShaderNodeTexEnvironment")
        tex.image = bpy.data.images.load(env_path)
        tex.image.colorspace_settings.name = "Linear Rec.709"
        coord = nt.nodes.new("ShaderNodeTexCoord")
        mapping = nt.nodes.new("ShaderNodeMapping")
        mapping.vector_type = "POINT"
        angle = 90.0 if convention == "usd" else 0.0
        mapping.inputs["Rotation"].default_value = (0.0, 0.0, math.radians(angle))
        nt.links.new(coord.outputs["Generated"], mapping.inputs["Vector"])
        nt.links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
        nt.links.new(tex.outputs["Color"], bg.inputs["Color"])
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
    return world


def add_camera(scene, cam, size):
    data = bpy.data.cameras.new("cam")
    w, h = int(cam.get("width", size)), int(cam.get("height", size))
    scene.render.resolution_x, scene.render.resolution_y = w, h
    data.sensor_fit = "HORIZONTAL"
    data.angle_x = math.radians(cam.get("fov_deg", 40.0))
    # Principal point off centre, in units of the image's larger side: the optical axis lands at
    # pixel (w/2 - shift_x*s, h/2 + shift_y*s), y down.
    data.shift_x = float(cam.get("shift_x", 0.0))
    data.shift_y = float(cam.get("shift_y", 0.0))
    obj = bpy.data.objects.new("cam", data)
    scene.collection.objects.link(obj)
    pos = to_blender(cam["position"])
    target = to_blender(cam["target"])
    obj.location = pos
    if "up" in cam:
        # Camera axes: -Z looks at the target, +Y is the image's up.
        from mathutils import Matrix
        back = (pos - target).normalized()
        up = to_blender(cam["up"])
        right = up.cross(back).normalized()
        up = back.cross(right)
        obj.rotation_mode = "QUATERNION"
        obj.rotation_quaternion = Matrix((right, up, back)).transposed().to_quaternion()
    else:
        obj.rotation_mode = "QUATERNION"
        obj.rotation_quaternion = (target - pos).to_track_quat("-Z", "Y")
    scene.camera = obj
    return obj


def render_cameras(scene, cameras, prefix, size):
    paths = []
    for i, cam in enumerate(cameras):
        obj = add_camera(scene, cam, size)
        path = f"{prefix}_cam{i}.png"
        scene.render.filepath = path
        bpy.ops.render.render(write_still=True)
        bpy.data.objects.remove(obj)
        paths.append(path)
    return paths


def analytic_reference(args):
    """The analytic shape as a dense primitive with the analytic material as nodes."""
    s = args.metres_per_unit
    shift = args.origin_shift
    # Blender location of the scene origin.
    origin = to_blender([shift[0], shift[1], shift[2]])
    if args.analytic == "sphere":
        bpy.ops.mesh.primitive_uv_sphere_add(segments=256, ring_count=128, radius=0.8 * s, location=origin)
    elif args.analytic == "torus":
        bpy.ops.mesh.primitive_torus_add(
            major_radius=0.55 * s, minor_radius=0.22 * s, major_segments=384, minor_segments=128, location=origin
        )
    else:
        raise SystemExit(f"no Blender reference for the analytic shape {args.analytic!r} (sphere, torus)")
    obj = bpy.context.active_object
    bpy.ops.object.shade_smooth()
    mat = bpy.data.materials.new("analytic")
    mat.use_nodes = True
    nt = mat.node_tree
    bsdf = nt.nodes["Principled BSDF"]
    bsdf.inputs["Metallic"].default_value = 0.0
    coord = nt.nodes.new("ShaderNodeTexCoord")
    xyz = nt.nodes.new("ShaderNodeSeparateXYZ")
    nt.links.new(coord.outputs["Object"], xyz.inputs["Vector"])

    def madd(inp, mul, add, clamp=True):
        n = nt.nodes.new("ShaderNodeMath")
        n.operation = "MULTIPLY_ADD"
        n.use_clamp = clamp
        nt.links.new(inp, n.inputs[0])
        n.inputs[1].default_value = mul
        n.inputs[2].default_value = add
        return n.outputs[0]

    if args.material == "gradient":
        # Scene coordinates: x_s = X / s, y_s = Z / s (Blender Z is our +Y).
        t = madd(xyz.outputs["Z"], 0.5 / s, 0.5)
        mix = nt.nodes.new("ShaderNodeMix")
        mix.data_type = "RGBA"
        mix.clamp_factor = True
        nt.links.new(t, mix.inputs["Factor"])
        mix.inputs["A"].default_value = (0.1, 0.2, 0.8, 1.0)
        mix.inputs["B"].default_value = (0.9, 0.7, 0.1, 1.0)
        nt.links.new(mix.outputs["Result"], bsdf.inputs["Base Color"])
        r = madd(madd(xyz.outputs["X"], 0.5 / s, 0.5), 0.6, 0.2)
        nt.links.new(r, bsdf.inputs["Roughness"])
    elif args.material == "checker":
        # parity(floor(x_s / c) + floor(y_s / c) + floor(z_s / c)), c = 0.25 scene units;
        # z_s = -Y / s.
        c = 0.25

        def math(op, *inputs):
            n = nt.nodes.new("ShaderNodeMath")
            n.operation = op
            for i, v in enumerate(inputs):
                if isinstance(v, float):
                    n.inputs[i].default_value = v
                else:
                    nt.links.new(v, n.inputs[i])
            return n.outputs[0]

        fx = math("FLOOR", math("MULTIPLY", xyz.outputs["X"], 1.0 / (s * c)))
        fy = math("FLOOR", math("MULTIPLY", xyz.outputs["Z"], 1.0 / (s * c)))
        fz = math("FLOOR", math("MULTIPLY", xyz.outputs["Y"], -1.0 / (s * c)))
        parity = math("FLOORED_MODULO", math("ADD", math("ADD", fx, fy), fz), 2.0)
        mix = nt.nodes.new("ShaderNodeMix")
        mix.data_type = "RGBA"
        nt.links.new(parity, mix.inputs["Factor"])
        mix.inputs["A"].default_value = (0.8, 0.1, 0.1, 1.0)
        mix.inputs["B"].default_value = (0.9, 0.9, 0.85, 1.0)
        nt.links.new(mix.outputs["Result"], bsdf.inputs["Base Color"])
        nt.links.new(math("MULTIPLY_ADD", parity, 0.5, 0.3), bsdf.inputs["Roughness"])
    else:
        raise SystemExit(f"no Blender reference for the material {args.material!r} (gradient, checker)")
    obj.data.materials.append(mat)


def import_summary(result):
    """What an import produced: operator result, meshes, materials and their images."""
    images = []
    for img in bpy.data.images:
        if img.type != "IMAGE" or img.source != "FILE" and not img.packed_file:
            continue
        if img.name.lower().endswith(".exr") or (img.filepath or "").lower().endswith(".exr"):
            continue  # the environment
        images.append(
            {
                "name": img.name,
                "colorspace": img.colorspace_settings.name,
                "size": list(img.size),
                "has_data": bool(img.has_data or img.size[0] > 0),
            }
        )
    return {
        "result": sorted(result),
        "meshes": [o.name for o in bpy.context.scene.objects if o.type == "MESH"],
        "materials": [m.name for m in bpy.data.materials if m.users > 0],
        "images": images,
    }


def load_pixels(path, with_alpha=False):
    img = bpy.data.images.load(path)
    w, h = img.size
    px = np.array(img.pixels[:], dtype=np.float64).reshape(h, w, 4)
    bpy.data.images.remove(img)
    return (px[:, :, :3], px[:, :, 3]) if with_alpha else px[:, :, :3]


def psnr(a, b, weight=None):
    """PSNR in dB of images in [0, 1] (weighted by a mask if given), capped at 99 dB (identical
    images) to stay valid JSON."""
    if weight is None:
        mse = float(np.mean((a - b) ** 2))
    else:
        mse = float(np.sum(weight[:, :, None] * (a - b) ** 2) / max(3.0 * weight.sum(), 1e-12))
    return 99.0 if mse <= 10.0**-9.9 else min(99.0, 10.0 * math.log10(1.0 / mse))


def ssim(a, b):
    """Mean SSIM of the luminance with an 11x11 Gaussian window (sigma 1.5)."""
    wl = np.array([0.2126, 0.7152, 0.0722])
    x, y = a @ wl, b @ wl
    g = np.exp(-((np.arange(11) - 5) ** 2) / (2 * 1.5**2))
    g /= g.sum()

    def blur(z):
        z = np.apply_along_axis(lambda r: np.convolve(r, g, mode="valid"), 1, z)
        return np.apply_along_axis(lambda c: np.convolve(c, g, mode="valid"), 0, z)

    c1, c2 = 0.01**2, 0.03**2
    mx, my = blur(x), blur(y)
    sxx = blur(x * x) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(x * y) - mx * my
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return float(s.mean())


def srgb_decode(x):
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def srgb_encode(x):
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1.0 / 2.4) - 0.055)


def channel_scales(pairs):
    """One factor per colour channel on the renders, over every (render, reference, alpha)
    triple: the weighted least-squares fit in linear light of the render to the reference, as
    `pii-bake eval` removes the light/albedo scale ambiguity from relit views."""
    num, den = np.zeros(3), np.zeros(3)
    for a, b, w in pairs:
        la, lb = srgb_decode(a), srgb_decode(b)
        num += np.einsum("hw,hwc->c", w, la * lb)
        den += np.einsum("hw,hwc->c", w, la * la)
    return np.where(den > 0.0, num / np.maximum(den, 1e-30), 1.0)


def compare(name, paths_a, paths_b, aligned=False):
    rows = []
    loaded = []
    for pa, pb in zip(paths_a, paths_b):
        a, (b, alpha) = load_pixels(pa), load_pixels(pb, with_alpha=True)
        if a.shape != b.shape:
            rows.append({"a": pa, "b": pb, "error": f"size {a.shape} vs {b.shape}"})
            continue
        if alpha.min() < 1.0:
            # A reference with a mask (a photo): compare the object only.
            m = alpha[:, :, None]
            rows.append({"a": pa, "b": pb, "masked": True, "psnr": psnr(a, b, alpha), "ssim": ssim(a * m, b * m)})
            loaded.append((len(rows) - 1, a, b, alpha))
        else:
            rows.append({"a": pa, "b": pb, "psnr": psnr(a, b), "ssim": ssim(a, b)})
            loaded.append((len(rows) - 1, a, b, np.ones_like(alpha)))
    ok = [r for r in rows if "psnr" in r]
    out = {
        "pair": name,
        "images": rows,
        "min_psnr": min((r["psnr"] for r in ok), default=None),
        "mean_psnr": float(np.mean([r["psnr"] for r in ok])) if ok else None,
        "min_ssim": min((r["ssim"] for r in ok), default=None),
    }
    if aligned and loaded:
        scale = channel_scales([(a, b, w) for _, a, b, w in loaded])
        for i, a, b, w in loaded:
            rows[i]["psnr_aligned"] = psnr(srgb_encode(srgb_decode(a) * scale), b, w)
        out["channel_scale"] = scale.tolist()
        out["mean_psnr_aligned"] = float(np.mean([rows[i]["psnr_aligned"] for i, *_ in loaded]))
    return out


def main():
    argv = sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else sys.argv[1:]
    ap = argparse.ArgumentParser()
    ap.add_argument("--asset-dir", required=True)
    ap.add_argument("--cameras", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--env", help="environment EXR (default: ASSET_DIR/env.exr)")
    ap.add_argument("--analytic", choices=["sphere", "torus"])
    ap.add_argument("--material", default="gradient", choices=["gradient", "checker"])
    ap.add_argument("--metres-per-unit", type=float, default=1.0)
    ap.add_argument("--origin-shift", type=float, nargs=3, default=[0.0, 0.0, 0.0])
    ap.add_argument("--reference-dir", help="reference images ref_cam{i}.png (e.g. photos)")
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--samples", type=int, default=64)
    ap.add_argument("--denoise", action="store_true")
    ap.add_argument("--film-transparent", action="store_true",
                    help="render the asset over a transparent film: straight colour at the silhouette "
                    "instead of colour mixed with the world (references with a mask are compared inside it)")
    ap.add_argument("--skip-usd", action="store_true")
    ap.add_argument("--json", help="report path (default: OUT/blender_report.json)")
    ap.add_argument("--env-convention", choices=["usd", "blender"], default="usd",
                    help="latlong convention of --env (pii-bake writes env.exr in the USD one)")
    ap.add_argument("--relight", nargs=3, action="append", default=[], metavar=("NAME", "ENV", "REFDIR"),
                    help="also render the .glb under ENV (a relight map in Blender's World convention, "
                    "the asset imported as it is) and score it against REFDIR/ref_cam{i}.png; repeatable")
    args = ap.parse_args(argv)

    os.makedirs(args.out, exist_ok=True)
    with open(args.cameras) as fh:
        cameras = json.load(fh)
    env = args.env or os.path.join(args.asset_dir, "env.exr")
    glbs = sorted(glob.glob(os.path.join(args.asset_dir, "*.glb")))
    if len(glbs) != 1:
        raise SystemExit(f"{args.asset_dir}: expected one .glb, found {len(glbs)}")

    report = {"asset_dir": args.asset_dir, "cameras": cameras, "size": args.size, "samples": args.samples, "pairs": []}
    renders = {}

    scene = reset_scene(args)
    make_world(scene, env, args.env_convention)
    report["glb_import"] = import_summary(bpy.ops.import_scene.gltf(filepath=glbs[0]))
    renders["glb"] = render_cameras(scene, cameras, os.path.join(args.out, "glb"), args.size)

    # The asset under other light: the imported .glb's scene with each relight map as its world,
    # in Blender's convention (the frame the .glb imports into), scored against the ground truth
    # rendered under that map.
    relit = []
    for name, relight_env, ref_dir in args.relight:
        make_world(scene, relight_env, "blender")
        paths = render_cameras(scene, cameras, os.path.join(args.out, f"relit_{name}"), args.size)
        refs = [os.path.join(ref_dir, f"ref_cam{i}.png") for i in range(len(cameras))]
        pair = compare(f"glb_relit_{name}_vs_reference", paths, refs, aligned=True)
        pair["env"] = relight_env
        relit.append(pair)

    if not args.skip_usd:
        scene = reset_scene(args)
        # A world must exist before the import for the DomeLight to become it.
        make_world(scene, None)
        result = bpy.ops.wm.usd_import(filepath=os.path.join(args.asset_dir, "lookdev.usda"))
        report["usd_import"] = import_summary(result)
        world_has_texture = any(n.type == "TEX_ENVIRONMENT" for n in scene.world.node_tree.nodes)
        report["usd_dome_light_became_world"] = world_has_texture
        if not world_has_texture:
            # Fall back to our own world so the geometry/material comparison still runs.
            make_world(scene, env)
        renders["usd"] = render_cameras(scene, cameras, os.path.join(args.out, "usd"), args.size)

    if args.analytic:
        scene = reset_scene(args)
        make_world(scene, env)
        analytic_reference(args)
        renders["ref"] = render_cameras(scene, cameras, os.path.join(args.out, "ref"), args.size)
    elif args.reference_dir:
        renders["ref"] = [os.path.join(args.reference_dir, f"ref_cam{i}.png") for i in range(len(cameras))]

    if "ref" in renders:
        report["pairs"].append(compare("glb_vs_reference", renders["glb"], renders["ref"]))
        if "usd" in renders:
            report["pairs"].append(compare("usd_vs_reference", renders["usd"], renders["ref"]))
    if "usd" in renders:
        report["pairs"].append(compare("usd_vs_glb", renders["usd"], renders["glb"]))
    report["pairs"].extend(relit)
    path = args.json or os.path.join(args.out, "blender_report.json")
    with open(path, "w") as fh:
        json.dump(report, fh, indent=2)
    print(json.dumps({p["pair"]: [p["min_psnr"], p["min_ssim"]] for p in report["pairs"]}))


if __name__ == "__main__":
    main()
