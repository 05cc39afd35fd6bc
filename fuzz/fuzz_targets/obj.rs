//! OBJ text through the mesh loader (tobj, our pre-pass, validation and clean-up).
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = sdf_geom::parse_mesh(data, "obj", std::path::Path::new("fuzz.obj"));
});
