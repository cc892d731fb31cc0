//! glTF, USD and EXR writers, thumbnails; the `export` command.

pub mod bench;
pub mod cli;
