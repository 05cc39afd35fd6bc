//! glTF JSON or GLB (dispatched on the `glTF` magic) through the mesh loader: document parsing,
//! validation, the node graph, our accessor reader and clean-up.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = sdf_geom::parse_mesh(data, "gltf", std::path::Path::new("fuzz.gltf"));
});
