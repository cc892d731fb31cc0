//! Checkpoints: bit-exact round trips (special values, metadata, order, optimiser state),
//! `load_into` name/shape checks, missing/corrupt/truncated/foreign files → errors naming the file,
//! and the file read back by an independent Python reader of the safetensors format (numpy).

use pii_bake::backend::Backend;
use pii_bake::nn::adam::{AdamConfig, AdamState};
use pii_bake::nn::encoding::EncodingConfig;
use pii_bake::nn::params::ParamStore;

fn sample_store() -> ParamStore {
    let mut s = ParamStore::new();
    let special = vec![
        0.0,
        -0.0,
        1.0,
        f32::MIN_POSITIVE / 3.0, // subnormal
        f32::MAX,
        f32::INFINITY,
        f32::NEG_INFINITY,
        f32::from_bits(0x7fc0_1234), // NaN with a payload
        -1.234_567_9e-20,
        std::f32::consts::PI,
        7.0,
        -8.5,
    ];
    s.insert("sdf/layer0/weight", &[3, 4], special).unwrap();
    let grid = EncodingConfig::HashGrid {
        levels: 2,
        features_per_level: 2,
        log2_table_size: 6,
        base_resolution: 2,
        per_level_scale: 2.0,
        bound: 1.0,
    };
    s.insert("sdf/encoding", &[grid.num_params()], grid.init_params(3))
        .unwrap();
    s.insert("a_bias", &[5], vec![0.5; 5]).unwrap();
    s.insert("empty", &[0, 3], vec![]).unwrap();
    s.set_config(&grid).unwrap();
    s.set_step(1234);
    s
}

fn bits(s: &ParamStore) -> Vec<(String, Vec<usize>, Vec<u32>)> {
    s.iter()
        .map(|t| {
            (
                t.name.clone(),
                t.shape.clone(),
                t.data.iter().map(|v| v.to_bits()).collect(),
            )
        })
        .collect()
}

#[test]
fn round_trip_is_bit_exact_with_metadata_and_order() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ckpt/model.safetensors");
    let s = sample_store();
    s.save(&path).unwrap();
    assert_eq!(
        std::fs::read_dir(path.parent().unwrap()).unwrap().count(),
        1,
        "temporary file left behind"
    );
    let back = ParamStore::load(&path).unwrap();
    assert_eq!(
        bits(&back),
        bits(&s),
        "tensors, shapes, bits and insertion order"
    );
    assert_eq!(back.step(), Some(1234));
    let cfg: EncodingConfig = serde_json::from_str(back.config_json().unwrap()).unwrap();
    assert_eq!(
        serde_json::to_string(&cfg).unwrap(),
        s.config_json().unwrap()
    );
    assert_eq!(back.metadata, s.metadata);
}

#[test]
fn optimiser_state_round_trips_through_a_backend() {
    let b = Backend::cpu();
    let mut s = ParamStore::new();
    s.insert("w", &[2, 2], vec![1.0, 2.0, 3.0, 4.0]).unwrap();
    let mut p = s.to_backend(&b, "w").unwrap();
    let mut st = AdamState::new(&b, 4);
    for _ in 0..3 {
        b.adam_step(
            &AdamConfig::default(),
            &mut st,
            &mut p,
            &b.upload(&[0.1, -0.2, 0.3, -0.4]),
            1e-2,
        )
        .unwrap();
    }
    s.from_backend(&b, "w", &p).unwrap();
    s.put_adam_state(&b, "w", &st).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("opt.safetensors");
    s.save(&path).unwrap();
    let back = ParamStore::load(&path).unwrap();
    let st2 = back
        .adam_state(&b, "w")
        .unwrap()
        .expect("optimiser state stored");
    assert_eq!(st2.step, 3);
    assert_eq!(b.to_vec(&st2.m).unwrap(), b.to_vec(&st.m).unwrap());
    assert_eq!(b.to_vec(&st2.v).unwrap(), b.to_vec(&st.v).unwrap());
    assert_eq!(back.data("w").unwrap(), b.to_vec(&p).unwrap().as_slice());
    assert!(back.adam_state(&b, "other").unwrap().is_none());
    // A model store without optimiser tensors still accepts this file in load_into.
    let mut model = ParamStore::new();
    model.insert("w", &[2, 2], vec![0.0; 4]).unwrap();
    model.load_into(&path).unwrap();
    assert_eq!(model.data("w"), back.data("w"));
    assert!(model.adam_state(&b, "w").unwrap().is_some());
}

#[test]
fn load_into_checks_every_name_and_shape() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.safetensors");
    sample_store().save(&path).unwrap();

    let mut same = sample_store();
    for t in same.iter().map(|t| t.name.clone()).collect::<Vec<_>>() {
        let len = same.data(&t).unwrap().len();
        same.set_data(&t, vec![9.0; len]).unwrap();
    }
    same.load_into(&path).unwrap();
    assert_eq!(bits(&same), bits(&sample_store()));

    // Shape mismatch: names the file and the tensor, changes nothing.
    let mut wrong = sample_store();
    wrong
        .upsert("sdf/layer0/weight", &[4, 3], vec![1.0; 12])
        .unwrap();
    let before = bits(&wrong);
    let err = wrong.load_into(&path).unwrap_err().to_string();
    assert!(
        err.contains("m.safetensors")
            && err.contains("sdf/layer0/weight")
            && err.contains("[3, 4]"),
        "{err}"
    );
    assert_eq!(
        bits(&wrong),
        before,
        "a failed load_into must not change the store"
    );

    // A tensor the model needs is missing from the file.
    let mut more = sample_store();
    more.insert("radiance/w", &[2], vec![0.0; 2]).unwrap();
    let err = more.load_into(&path).unwrap_err().to_string();
    assert!(err.contains("no tensor \"radiance/w\""), "{err}");

    // The file has a tensor the model does not.
    let mut fewer = ParamStore::new();
    fewer.insert("a_bias", &[5], vec![0.0; 5]).unwrap();
    let err = fewer.load_into(&path).unwrap_err().to_string();
    assert!(err.contains("does not have"), "{err}");
}

#[test]
fn missing_corrupt_truncated_and_foreign_files_are_errors() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nope.safetensors");
    let err = ParamStore::load(&missing).unwrap_err().to_string();
    assert!(
        err.contains("nope.safetensors") && err.contains("cannot read"),
        "{err}"
    );

    let garbage = dir.path().join("garbage.safetensors");
    std::fs::write(&garbage, b"this is not a checkpoint at all, just some text").unwrap();
    let err = ParamStore::load(&garbage).unwrap_err().to_string();
    assert!(
        err.contains("garbage.safetensors") && err.contains("not a valid safetensors"),
        "{err}"
    );

    let good = dir.path().join("good.safetensors");
    sample_store().save(&good).unwrap();
    let bytes = std::fs::read(&good).unwrap();
    for cut in [0, 4, 8, 40, bytes.len() - 1] {
        let truncated = dir.path().join(format!("cut{cut}.safetensors"));
        std::fs::write(&truncated, &bytes[..cut]).unwrap();
        let err = ParamStore::load(&truncated).unwrap_err().to_string();
        assert!(err.contains(&format!("cut{cut}.safetensors")), "{err}");
    }
    // Flipped bytes inside the JSON header.
    let mut bad = bytes.clone();
    for b in &mut bad[9..20] {
        *b = b'}';
    }
    let corrupt = dir.path().join("corrupt.safetensors");
    std::fs::write(&corrupt, &bad).unwrap();
    assert!(ParamStore::load(&corrupt).is_err());

    // A valid safetensors file with an F64 tensor (not a pii-bake checkpoint).
    let data: Vec<u8> = [1.0f64, 2.0].iter().flat_map(|v| v.to_le_bytes()).collect();
    let view =
        safetensors::tensor::TensorView::new(safetensors::Dtype::F64, vec![2], &data).unwrap();
    let foreign = dir.path().join("f64.safetensors");
    std::fs::write(
        &foreign,
        safetensors::serialize([("x", view)], None).unwrap(),
    )
    .unwrap();
    let err = ParamStore::load(&foreign).unwrap_err().to_string();
    assert!(err.contains("F64") && err.contains("\"x\""), "{err}");
}

#[test]
fn store_errors_on_bad_inserts() {
    let mut s = ParamStore::new();
    assert!(s.insert("w", &[2, 3], vec![0.0; 5]).is_err());
    s.insert("w", &[2, 3], vec![0.0; 6]).unwrap();
    assert!(s
        .insert("w", &[6], vec![0.0; 6])
        .unwrap_err()
        .to_string()
        .contains("already"));
    assert!(s.set_data("w", vec![0.0; 7]).is_err());
    assert!(s.set_data("x", vec![]).is_err());
    assert!(s.to_backend(&Backend::cpu(), "x").is_err());
    assert!(s.upsert("w", &[3], vec![0.0; 4]).is_err());
    assert_eq!(
        s.get("w").unwrap().shape,
        vec![2, 3],
        "a failed upsert keeps the old tensor"
    );
}

/// An independent reader (Python + numpy, parsing the documented safetensors layout: 8-byte
/// little-endian header size, JSON header, raw little-endian data) sees the same values.
#[test]
fn python_reads_the_checkpoint() {
    let python = std::env::var("PII_PYTHON").unwrap_or_else(|_| {
        panic!("PII_PYTHON is not set: run the tests with `bash scripts/test.sh`, which sets it to the venv's python")
    });
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("py.safetensors");
    let mut s = ParamStore::new();
    s.insert("w", &[2, 3], vec![1.5, -2.0, 0.25, 1e-3, 3e30, -7.0])
        .unwrap();
    s.insert("b", &[3], vec![0.1, 0.2, 0.3]).unwrap();
    s.set_step(42);
    s.save(&path).unwrap();
    let script = r#"
import json, struct, sys
import numpy as np
raw = open(sys.argv[1], 'rb').read()
n = struct.unpack('<Q', raw[:8])[0]
header = json.loads(raw[8:8 + n])
data = raw[8 + n:]
meta = header.pop('__metadata__')
out = {'step': meta['step']}
for name, info in header.items():
    assert info['dtype'] == 'F32', info
    a, b = info['data_offsets']
    arr = np.frombuffer(data[a:b], dtype='<f4').reshape(info['shape'])
    out[name] = {'shape': list(arr.shape), 'values': [float(v) for v in arr.ravel()]}
print(json.dumps(out))
"#;
    let run = std::process::Command::new(&python)
        .args(["-c", script, path.to_str().unwrap()])
        .output()
        .unwrap_or_else(|e| panic!("cannot run PII_PYTHON={python}: {e}"));
    assert!(
        run.status.success(),
        "python failed: {}",
        String::from_utf8_lossy(&run.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&run.stdout).unwrap();
    assert_eq!(v["step"], "42");
    for t in s.iter() {
        assert_eq!(
            v[&t.name]["shape"],
            serde_json::json!(t.shape),
            "{}",
            t.name
        );
        let vals: Vec<f32> = v[&t.name]["values"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap() as f32)
            .collect();
        assert_eq!(vals, t.data, "{}", t.name);
    }
}
