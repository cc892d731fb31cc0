// Shared indexing helpers. Large 1-D launches spread workgroups over x and y
// (Rust: backend::gpu::groups_1d); this recovers the linear invocation index.
fn linear_index(gid: vec3<u32>, nwg: vec3<u32>, wg_size: u32) -> u32 {
    return gid.x + gid.y * nwg.x * wg_size;
}
