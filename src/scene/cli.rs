//! The `info` command: read a scene and print what was found.

use std::path::PathBuf;

use serde_json::json;

use super::{load, Downscale, ReadOptions, Scene, Split};
use crate::context::Context;

#[derive(Debug, clap::Args)]
pub struct InfoArgs {
    /// Scene folder (transforms*.json, cameras_sphere.npz, poses_bounds.npy or COLMAP sparse/0) or file.
    pub scene: PathBuf,
    /// Image downscale: `auto` (full size unless the photos are larger than the model resolves,
    /// see `scene::auto_downscale`) or an integer factor; intrinsics follow.
    #[arg(long, default_value_t = Downscale::Auto)]
    pub downscale: Downscale,
    /// Measure the views' silhouette agreement but leave none out.
    #[arg(long)]
    pub keep_all_views: bool,
}

fn stats(v: impl Iterator<Item = f64>) -> Option<(f64, f64, f64)> {
    let v: Vec<f64> = v.collect();
    if v.is_empty() {
        return None;
    }
    let (lo, hi) = v.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| (a.min(*x), b.max(*x)));
    Some((lo, v.iter().sum::<f64>() / v.len() as f64, hi))
}

/// The `info` summary as JSON (also used by tests).
pub fn summary(scene: &Scene) -> serde_json::Value {
    let splits: serde_json::Map<String, serde_json::Value> = [Split::Train, Split::Val, Split::Test]
        .iter()
        .map(|s| (s.name().to_string(), json!(scene.views_in(*s).count())))
        .collect();
    let mut sizes: Vec<(usize, usize)> = scene.views.iter().map(|v| (v.camera.width, v.camera.height)).collect();
    sizes.sort();
    sizes.dedup();
    let st = |f: &dyn Fn(&super::Camera) -> f64| {
        stats(scene.views.iter().map(|v| f(&v.camera))).map(|(a, m, b)| json!({"min": a, "mean": m, "max": b}))
    };
    let dist = stats(scene.views.iter().map(|v| v.camera.center().length())).map(|(a, m, b)| json!({"min": a, "mean": m, "max": b}));
    let cov = stats(scene.views.iter().filter_map(|v| v.mask_coverage()));
    let train: Vec<&super::View> = scene.views_in(Split::Train).collect();
    let texture = super::texture::photo_texture(&train);
    let n = &scene.normalisation;
    json!({
        "source": scene.source.display().to_string(),
        "format": scene.format,
        "format_name": scene.format.name(),
        "views": scene.views.len(),
        "splits": splits,
        "resolutions": sizes.iter().map(|(w, h)| format!("{w}x{h}")).collect::<Vec<_>>(),
        "downscale": scene.downscale,
        "downscale_note": scene.downscale_note,
        "intrinsics": {
            "fx": st(&|c| c.fx), "fy": st(&|c| c.fy), "cx": st(&|c| c.cx), "cy": st(&|c| c.cy),
            "fov_x_deg": st(&|c| c.fov_x().to_degrees()),
            "distorted_views": scene.views.iter().filter(|v| v.camera.distortion.is_some()).count(),
            "pixel_convention": "pixel (i, j) centre at (i + 0.5, j + 0.5)",
        },
        "camera_distance_normalised": dist,
        "normalisation": {
            "center_world": n.center.to_array(), "scale": n.scale, "method": n.method,
        },
        "units": super::normalise::CaptureUnits::from_scale(n.scale),
        "up_axis": {"vector_world": n.up_axis.to_array(), "nearest": n.up_axis_name},
        "masks": {
            "views_with_mask": scene.views.iter().filter(|v| v.mask.is_some()).count(),
            "coverage": cov.map(|(a, m, b)| json!({"min": a, "mean": m, "max": b})),
        },
        "silhouettes": scene.silhouettes,
        "photo_texture": {
            "contrast": texture,
            "textureless": texture.map(|t| t < super::texture::TEXTURELESS_BELOW),
            "threshold": super::texture::TEXTURELESS_BELOW,
            "what": "75th percentile of the band-pass contrast of log luminance inside the training masks (src/scene/texture.rs)",
        },
    })
}

/// Prints the scene's summary and returns the scene (the CLI adds what needs `train`).
pub fn run(args: &InfoArgs, ctx: &Context) -> anyhow::Result<Scene> {
    let scene = load(&args.scene, &ReadOptions { downscale: args.downscale, keep_all_views: args.keep_all_views })?;
    let s = summary(&scene);
    ctx.emit("scene_info", s.clone());
    let f3 = |v: &serde_json::Value| -> String {
        if v.is_null() {
            return "-".into();
        }
        format!("{:.3} / {:.3} / {:.3}", v["min"].as_f64().unwrap_or(0.0), v["mean"].as_f64().unwrap_or(0.0), v["max"].as_f64().unwrap_or(0.0))
    };
    let n = &scene.normalisation;
    ctx.say(format!("scene        {}", scene.source.display()));
    ctx.say(format!("format       {}", scene.format.name()));
    ctx.say(format!(
        "views        {} (train {}, val {}, test {})",
        scene.views.len(),
        s["splits"]["train"],
        s["splits"]["val"],
        s["splits"]["test"]
    ));
    ctx.say(format!(
        "resolution   {}{}",
        s["resolutions"].as_array().map(|a| a.iter().filter_map(|x| x.as_str()).collect::<Vec<_>>().join(", ")).unwrap_or_default(),
        if scene.downscale > 1 { format!(" (read at 1/{})", scene.downscale) } else { String::new() }
    ));
    if let Some(note) = &scene.downscale_note {
        ctx.say(note.clone());
    }
    let i = &s["intrinsics"];
    ctx.say(format!("fx  min/mean/max  {}", f3(&i["fx"])));
    ctx.say(format!("fy  min/mean/max  {}", f3(&i["fy"])));
    ctx.say(format!("cx  min/mean/max  {}", f3(&i["cx"])));
    ctx.say(format!("cy  min/mean/max  {}", f3(&i["cy"])));
    ctx.say(format!("fov_x (deg)       {}", f3(&i["fov_x_deg"])));
    ctx.say(format!("distorted views   {}", i["distorted_views"]));
    ctx.say(format!(
        "normalisation     x_norm = (x - [{:.4}, {:.4}, {:.4}]) * {:.5}  ({})",
        n.center.x, n.center.y, n.center.z, n.scale, n.method
    ));
    ctx.say(format!("units             {}", s["units"]["why"].as_str().unwrap_or_default()));
    ctx.say(format!("camera distance (normalised) {}", f3(&s["camera_distance_normalised"])));
    ctx.say(format!("up axis           [{:.3}, {:.3}, {:.3}] (nearest {})", n.up_axis.x, n.up_axis.y, n.up_axis.z, n.up_axis_name));
    ctx.say(format!("masks             {} views, coverage {}", s["masks"]["views_with_mask"], f3(&s["masks"]["coverage"])));
    let sc = &scene.silhouettes;
    match &sc.worst_kept {
        Some((name, worst)) => ctx.say(format!(
            "silhouettes       {} views kept: the median view carves {:.2}% of the hull alone, the worst {:.2}% ({name})",
            sc.views - sc.excluded.len(),
            100.0 * sc.median_solo_carve,
            100.0 * worst
        )),
        None => ctx.say("silhouettes       - (needs masks on at least 4 views)"),
    }
    for e in &sc.excluded {
        ctx.say(format!(
            "  EXCLUDED        {} ({}): carves {:.1}% of the others' hull alone: a wrong pose or mask",
            e.name,
            e.image,
            100.0 * e.solo_carve
        ));
    }
    if let Some(note) = &sc.note {
        ctx.say(format!("  WARNING         {note}"));
    }
    let pt = &s["photo_texture"];
    ctx.say(match (pt["contrast"].as_f64(), pt["textureless"].as_bool()) {
        (Some(t), Some(true)) => format!("photo texture     {t:.3} (below {}: textureless, albedo and lighting poorly separable)", pt["threshold"]),
        (Some(t), _) => format!("photo texture     {t:.3}"),
        _ => "photo texture     - (needs masks)".to_string(),
    });
    Ok(scene)
}
