//! Prints the adapter HW SDF would use, then (on stderr) every adapter wgpu can see with the
//! index and PCI bus id that `--adapter` / `HWSDF_ADAPTER` take.
//!
//! `--adapter`, `HWSDF_ADAPTER`, `WGPU_ADAPTER_NAME` and `WGPU_BACKEND` are honoured exactly as
//! in training: `gpu-info --adapter X` shows the adapter `train --adapter X` would use.

use std::process::ExitCode;

use clap::Parser;
use hwsdf::cli::GpuFlags;

/// Show the adapter HW SDF would use, and every adapter it can choose from.
#[derive(Parser, Debug)]
#[command(version)]
struct Args {
    #[command(flatten)]
    gpu: GpuFlags,
}

fn main() -> ExitCode {
    // SAFETY: first thing in main, before any other thread exists.
    unsafe { hwsdf::nn::gpu::skip_device_select_layer_when_headless() };
    let args = Args::parse();
    let all = hwsdf::nn::gpu::list_adapters();
    eprintln!(
        "adapters wgpu can see (--adapter / HWSDF_ADAPTER take the index, the PCI bus id or part of the name):"
    );
    if all.is_empty() {
        eprintln!("  none");
    }
    for a in &all {
        eprintln!("  {a}");
    }
    match args.gpu.open() {
        Ok(gpu) => {
            println!("{}", gpu.describe());
            println!(
                "float atomics: {}, timestamps: {}, f16 cooperative matrices (f32 accumulators): {}",
                gpu.has_float_atomics(),
                gpu.has_timestamps(),
                gpu.coop_f16_tile()
                    .map_or("none".to_owned(), |t| format!("{t}x{t}x{t}"))
            );
            let info = gpu.adapter_info();
            let limits = gpu.limits();
            println!(
                "subgroup size: {}..{}, workgroup memory: {} KiB, invocations per workgroup: {}, storage binding: {} MiB",
                info.subgroup_min_size,
                info.subgroup_max_size,
                limits.max_compute_workgroup_storage_size / 1024,
                limits.max_compute_invocations_per_workgroup,
                limits.max_storage_buffer_binding_size / (1024 * 1024)
            );
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(2)
        }
    }
}
