//! Neural fields: encodings (frequency PE, multiresolution hash grid), MLPs with forward and
//! backward (parameter and input gradients), Adam, the parameter store and checkpoints.

pub mod adam;
pub mod encoding;
pub mod params;
pub mod bench;
pub mod field;
pub mod mlp;
pub mod simd;
