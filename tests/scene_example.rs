//! The bundled example scene (tests/data/example, made by scripts/make_scene.py --scene spot): view counts,
//! resolution, and projections of known object positions.

use std::path::Path;

use glam::DVec3;
use pii_bake::eval::mesh::Mesh;
use pii_bake::scene::{load, normalise, Format, ReadOptions, Split};

mod common;

use common::{copy_dir, example};

#[test]
fn example_scene_cameras_and_known_points() {
    let scene = load(&example(), &ReadOptions::default()).unwrap();
    assert_eq!(scene.format, Format::Transforms);
    assert_eq!(scene.views_in(Split::Train).count(), 24);
    assert_eq!(scene.views_in(Split::Test).count(), 4);
    // The rendered views agree: no view is excluded, and the worst one carves a sliver alone.
    let sc = &scene.silhouettes;
    assert!(sc.excluded.is_empty() && sc.note.is_none(), "{sc:?}");
    assert!(sc.worst_kept.as_ref().unwrap().1 < 0.2 * pii_bake::scene::consistency::SOLO_CARVE_ABOVE, "{sc:?}");
    let meta: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(example().join("scene.json")).unwrap()).unwrap();
    let probes: Vec<DVec3> = meta["probe_points"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| DVec3::new(p[0].as_f64().unwrap(), p[1].as_f64().unwrap(), p[2].as_f64().unwrap()))
        .collect();
    assert!(probes.len() >= 8);
    let n = &scene.normalisation;
    assert_eq!(n.up_axis_name, "+Z", "Blender world is Z-up");
    for v in &scene.views {
        let c = &v.camera;
        assert_eq!((c.width, c.height), (200, 200));
        // The generator aims every camera at the bound's centre = the normalised origin, which must land
        // exactly on the image centre (pixel-corner convention: (w/2, h/2)).
        let o = c.project(DVec3::ZERO).unwrap();
        assert!((o.x - 100.0).abs() < 1e-4 && (o.y - 100.0).abs() < 1e-4, "{}: origin at {o}", v.name);
        assert!(c.center().length() > 1.0, "camera inside the unit sphere");
        // Every surface point projects inside the object's silhouette (alpha) in every view.
        for p in &probes {
            let q = c.project(n.to_normalised(*p)).unwrap();
            let mut best = 0.0f32;
            for dy in [-1.0, 0.0, 1.0] {
                for dx in [-1.0, 0.0, 1.0] {
                    best = best.max(v.mask_at(q.x + dx, q.y + dy));
                }
            }
            assert!(best >= 0.5, "{}: surface point {p} projects to {q}, outside the silhouette", v.name);
        }
    }
    // The ground-truth mesh lies inside the unit sphere after normalisation (bound radius x 1.1 -> 1).
    let mesh = Mesh::read(&example().join("gt/mesh.obj")).unwrap();
    let r = mesh.positions.iter().map(|p| n.to_normalised(*p).length()).fold(0.0, f64::max);
    assert!(r <= 1.0 / normalise::MARGIN + 1e-5 && r > 0.85, "{r}");
}

#[test]
fn a_view_where_the_object_is_cropped_does_not_shrink_the_bound() {
    // The example without its scene.json bound (so the masks' visual hull sets the normalisation),
    // and a copy where three training views keep only the left 110 of their 200 columns (same
    // intrinsics): the object runs out of their frames. A view must not reject what it cannot
    // see, or the bound shrinks and the object leaves the unit sphere. Neither may it exclude
    // those views as disagreeing.
    let dir = tempfile::tempdir().unwrap();
    let copy = |dst: &Path| {
        for sub in ["train", "test"] {
            copy_dir(&example().join(sub), &dst.join(sub));
        }
        for f in ["transforms_train.json", "transforms_test.json"] {
            std::fs::copy(example().join(f), dst.join(f)).unwrap();
        }
    };
    let (full, cropped) = (dir.path().join("full"), dir.path().join("cropped"));
    copy(&full);
    copy(&cropped);
    let tf = cropped.join("transforms_train.json");
    let mut j: serde_json::Value = serde_json::from_slice(&std::fs::read(&tf).unwrap()).unwrap();
    let fx = 100.0 / (0.5 * j["camera_angle_x"].as_f64().unwrap()).tan();
    for k in [3, 9, 15] {
        let frame = &mut j["frames"][k];
        let png = cropped.join(format!("{}.png", frame["file_path"].as_str().unwrap()));
        let img = image::open(&png).unwrap().crop_imm(0, 0, 110, 200);
        img.save(&png).unwrap();
        for (key, v) in [("fl_x", fx), ("fl_y", fx), ("cx", 100.0), ("cy", 100.0), ("w", 110.0), ("h", 200.0)] {
            frame[key] = serde_json::json!(v);
        }
    }
    std::fs::write(&tf, serde_json::to_vec_pretty(&j).unwrap()).unwrap();
    let a = load(&full, &ReadOptions::default()).unwrap();
    let b = load(&cropped, &ReadOptions::default()).unwrap();
    assert!(a.normalisation.method.contains("visual hull"), "{}", a.normalisation.method);
    assert_eq!(b.views.iter().filter(|v| v.camera.width == 110).count(), 3);
    assert!(b.silhouettes.excluded.is_empty(), "{:?}", b.silhouettes);
    let (na, nb) = (&a.normalisation, &b.normalisation);
    assert!((na.center - nb.center).length() * na.scale < 0.01, "centre {} vs {}", na.center, nb.center);
    assert!((nb.scale / na.scale - 1.0).abs() < 0.01, "scale {} vs {}", na.scale, nb.scale);
}
