//! Every WGSL file under shaders/ (with the shared library prepended, as the launcher does)
//! parses and validates with naga. CPU-only: no adapter needed.

use std::path::Path;

use pii_bake::backend::gpu::{shaders, validate_wgsl};

fn wgsl_files(dir: &Path, out: &mut Vec<std::path::PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            wgsl_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "wgsl") {
            out.push(p);
        }
    }
}

#[test]
fn every_wgsl_file_validates_with_naga() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("shaders");
    let mut files = Vec::new();
    wgsl_files(&root, &mut files);
    files.sort();
    assert!(files.len() >= 3, "expected shader files under {root:?}");
    let mut failures = Vec::new();
    for f in &files {
        let src = std::fs::read_to_string(f).unwrap();
        // Library files are validated on their own; kernel files with the library prepended.
        let is_lib = f.parent().is_some_and(|p| p.ends_with("lib"));
        let full = if is_lib { shaders::LIB.to_string() } else { shaders::prepend_lib(&src) };
        if let Err(e) = validate_wgsl(&f.display().to_string(), &full) {
            failures.push(format!("{}:\n{e}", f.display()));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n\n"));
}

#[test]
fn a_broken_shader_is_an_error_not_a_panic() {
    let err = validate_wgsl("broken", "fn f( { }").unwrap_err();
    assert!(err.to_string().contains("broken"), "{err}");
}
