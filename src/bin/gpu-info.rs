//! Prints the adapter HW SDF would use and every adapter wgpu can see.
//!
//! `WGPU_ADAPTER_NAME` and `WGPU_BACKEND` are honoured exactly as in training.

use std::process::ExitCode;

fn main() -> ExitCode {
    let all = hwsdf::nn::gpu::list_adapters();
    eprintln!(
        "adapters wgpu can see: {}",
        if all.is_empty() {
            "none".into()
        } else {
            all.join("; ")
        }
    );
    match hwsdf::nn::GpuContext::new() {
        Ok(gpu) => {
            println!("{}", gpu.describe());
            println!(
                "float atomics: {}, timestamps: {}",
                gpu.has_float_atomics(),
                gpu.has_timestamps()
            );
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(2)
        }
    }
}
