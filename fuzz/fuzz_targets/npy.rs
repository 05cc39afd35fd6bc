//! `.npy` point files through the points reader.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = sdf_geom::npy::parse_points(std::path::Path::new("fuzz.npy"), data);
});
