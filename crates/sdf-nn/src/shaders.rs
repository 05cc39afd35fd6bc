//! Every WGSL shader of the project, embedded from the top-level `shaders/` folder, with the
//! device features each one needs.

/// A WGSL source file and what it needs from the device.
#[derive(Clone, Copy, Debug)]
pub struct Shader {
    /// File name in `shaders/`, also the cache key and the debug label.
    pub name: &'static str,
    /// WGSL source.
    pub source: &'static str,
    /// Device features the shader uses; the context refuses to compile it without them.
    pub required_features: wgpu::Features,
}

macro_rules! shader {
    ($name:literal, $features:expr) => {
        Shader {
            name: $name,
            source: include_str!(concat!("../../../shaders/", $name)),
            required_features: $features,
        }
    };
}

/// The shared Adam optimiser step.
pub const ADAM: Shader = shader!("adam.wgsl", wgpu::Features::empty());

/// SIREN's tiled GEMM with the sine forward / backward epilogues.
pub const SIREN_GEMM: Shader = shader!("siren_gemm.wgsl", wgpu::Features::empty());
/// SIREN's output layer, loss and its derivative.
pub const SIREN_HEAD: Shader = shader!("siren_head.wgsl", wgpu::Features::empty());
/// SIREN's batch sampling and reductions.
pub const SIREN_TRAIN: Shader = shader!("siren_train.wgsl", wgpu::Features::empty());

/// NGLOD inference (grid interpolation + MLP).
pub const NGLOD_FORWARD: Shader = shader!("nglod_forward.wgsl", wgpu::Features::empty());
/// NGLOD forward + backward per row, grid scatter with native float atomics.
pub const NGLOD_TRAIN_ATOMIC: Shader = shader!(
    "nglod_train_atomic.wgsl",
    wgpu::Features::SHADER_FLOAT32_ATOMIC
);
/// NGLOD forward + backward per row, grid scatter by compare-exchange (any adapter).
pub const NGLOD_TRAIN_CAS: Shader = shader!("nglod_train_cas.wgsl", wgpu::Features::empty());
/// NGLOD MLP-gradient and loss reduction.
pub const NGLOD_REDUCE: Shader = shader!("nglod_reduce.wgsl", wgpu::Features::empty());

/// Every shader, for validation.
pub const ALL: &[Shader] = &[
    ADAM,
    SIREN_GEMM,
    SIREN_HEAD,
    SIREN_TRAIN,
    NGLOD_FORWARD,
    NGLOD_TRAIN_ATOMIC,
    NGLOD_TRAIN_CAS,
    NGLOD_REDUCE,
];

#[cfg(test)]
mod tests {
    use super::*;

    /// naga capabilities that correspond to a set of wgpu features. Validating with only these
    /// makes accidental use of any other capability fail.
    fn capabilities_for(features: wgpu::Features) -> naga::valid::Capabilities {
        use naga::valid::Capabilities as C;
        let mut caps = C::empty();
        if features.contains(wgpu::Features::SHADER_FLOAT32_ATOMIC) {
            caps |= C::SHADER_FLOAT32_ATOMIC;
        }
        if features.contains(wgpu::Features::SUBGROUP) {
            caps |= C::SUBGROUP;
        }
        if features.contains(wgpu::Features::SHADER_F16) {
            caps |= C::SHADER_FLOAT16;
        }
        caps
    }

    #[test]
    fn compile_shaders() {
        for shader in ALL {
            let module = naga::front::wgsl::parse_str(shader.source)
                .unwrap_or_else(|e| panic!("{}: {}", shader.name, e.emit_to_string(shader.source)));
            naga::valid::Validator::new(
                naga::valid::ValidationFlags::all(),
                capabilities_for(shader.required_features),
            )
            .validate(&module)
            .unwrap_or_else(|e| panic!("{}: {}", shader.name, e.emit_to_string(shader.source)));
        }
    }

    /// A shader file that is not in [`ALL`] would escape validation.
    #[test]
    fn every_shader_file_is_registered() {
        let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../../shaders");
        let mut on_disk: Vec<String> = std::fs::read_dir(dir)
            .expect("shaders/ exists")
            .filter_map(|e| e.ok())
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| n.ends_with(".wgsl"))
            .collect();
        on_disk.sort();
        let mut registered: Vec<String> = ALL.iter().map(|s| s.name.to_owned()).collect();
        registered.sort();
        registered.dedup();
        assert_eq!(on_disk, registered);
    }
}
