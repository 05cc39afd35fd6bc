//! Model files (safetensors with hwsdf metadata) through `ModelFile::from_bytes`.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = sdf_nn::model_file::ModelFile::from_bytes(data, std::path::Path::new("fuzz.safetensors"));
});
