//! The command-line flags the binaries share, each defined, parsed and checked once: the GPU to
//! run on ([`GpuFlags`], which every binary that touches a GPU flattens and opens its GPU
//! through) and how to train ([`TrainingFlags`], `train`'s and `corpus`'s), with the few
//! helpers their output shares.

mod source;
mod training;

use sdf_eval::run::{self, RunError};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use sdf_nn::ground_truth::{LabelProgress, ProgressSink};
use sdf_nn::{GpuContext, GpuError, GpuOptions, GroundTruthDevice};

pub use source::{Source, SourceFlags, check_level};
pub use training::{DistanceArg, PresetArg, TrainingFlags};

/// Which GPU to run on. The environment's settings (`HWSDF_ADAPTER`, `WGPU_ADAPTER_NAME`,
/// `WGPU_BACKEND`, `HWSDF_MAPPABLE_STORAGE`, `HWSDF_NO_COOP`, `HWSDF_STEP_LAYOUT`) apply as
/// [`GpuOptions::from_env`] reads them; `--adapter` wins over the environment's adapter.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct GpuFlags {
    /// The adapter to run on: its index or PCI bus id as `gpu-info` lists them, or part of its
    /// name (default: the environment's `HWSDF_ADAPTER`, else the best one found).
    #[arg(long, value_name = "ADAPTER")]
    pub adapter: Option<String>,
}

impl GpuFlags {
    /// The GPU options of the environment with `--adapter` over them. Unknown values of the
    /// environment's variables are errors naming the allowed ones.
    pub fn options(&self) -> Result<GpuOptions, GpuError> {
        Ok(GpuOptions::from_env()?.with_adapter(self.adapter.as_deref(), "--adapter"))
    }

    /// Opens the GPU these flags choose.
    pub fn open(&self) -> Result<GpuContext, GpuError> {
        GpuContext::with_options(&self.options()?)
    }
}

/// `--ground-truth`: where exact distances are computed (the training samples' labels, the
/// evaluation sets', `sdf`'s output).
#[derive(clap::Args, Clone, Copy, Debug, Default)]
pub struct GroundTruthFlags {
    /// Where exact distances (training labels, evaluation sets) are computed. `auto`: on the GPU
    /// unless the adapter is a CPU (lavapipe: the CPU path is faster there) or the mesh does not
    /// fit the GPU's limits (then on the CPU, with a warning).
    #[arg(long, value_enum, default_value = "auto")]
    pub ground_truth: GroundTruthArg,
}

/// The values of `--ground-truth`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum GroundTruthArg {
    /// The GPU kernels; an error where the mesh does not fit the device (naming the limit) or
    /// the GPU's labels of a probe disagree with the CPU's.
    Gpu,
    /// The CPU (rayon).
    Cpu,
    /// The GPU unless the adapter is a CPU, the mesh does not fit it or its labels of a probe
    /// disagree with the CPU's.
    #[default]
    Auto,
}

/// When `train` and `sdf` speak while they label: the estimate before, progress lines during.
/// Hidden: the defaults are what a user wants; tests set them to 0 to see the lines on small
/// runs.
#[derive(clap::Args, Clone, Copy, Debug)]
pub struct LabelFlags {
    /// Print the estimate of the labelling time when it passes this many seconds.
    #[arg(long, hide = true, default_value_t = 2.0)]
    pub label_estimate_after: f64,
    /// Print a progress line once a labelling call has run this many seconds, and every this
    /// many seconds after.
    #[arg(long, hide = true, default_value_t = 3.0)]
    pub label_progress_every: f64,
}

impl LabelFlags {
    /// Progress lines on stderr for [`sdf_nn::Labeller::with_progress`]: `labelling:
    /// 120000/300000 (40%), 12 s so far, ETA 18 s`, for calls that run longer than
    /// `--label-progress-every` seconds, at most one line per that many seconds (and the last
    /// part's).
    pub fn progress(&self) -> ProgressSink {
        let every = self.label_progress_every;
        let last: Mutex<Option<Instant>> = Mutex::new(None);
        Arc::new(move |p: &LabelProgress| {
            if p.elapsed.as_secs_f64() < every {
                return;
            }
            let mut last = last.lock().unwrap_or_else(|e| e.into_inner());
            let finished = p.done >= p.total;
            if !finished && last.is_some_and(|t| t.elapsed().as_secs_f64() < every) {
                return;
            }
            *last = Some(Instant::now());
            eprintln!(
                "labelling: {}/{} ({:.0}%), {} so far, ETA {}",
                p.done,
                p.total,
                100.0 * p.done as f64 / p.total.max(1) as f64,
                run::duration(p.elapsed.as_secs_f64()),
                p.eta()
                    .map_or_else(|| "?".to_owned(), |d| run::duration(d.as_secs_f64()))
            );
        })
    }
}

impl GroundTruthFlags {
    /// The device asked for.
    pub fn device(&self) -> GroundTruthDevice {
        match self.ground_truth {
            GroundTruthArg::Gpu => GroundTruthDevice::Gpu,
            GroundTruthArg::Cpu => GroundTruthDevice::Cpu,
            GroundTruthArg::Auto => GroundTruthDevice::Auto,
        }
    }
}

/// Checks the size of an evaluation's sets as `flag` (`--points`, `--eval-points`) gives it:
/// at least one point, and within [`run::EVAL_MEMORY_BUDGET`].
pub fn check_eval_points(flag: &str, points: usize) -> Result<(), RunError> {
    run::check_eval_points(points).map_err(|e| match e {
        // The library's refusal of empty sets, named by the flag.
        RunError::Options(_) if points == 0 => {
            RunError::Options(format!("{flag} must be at least 1"))
        }
        other => other,
    })
}

/// Errors when `path`, given by `flag`, is named for another known format than the `format` a
/// command writes (extension `ext`, lower case, no dot): `extract --out mesh.ply` wrote OBJ text
/// under a name PLY readers refuse, and `load_mesh` then read it as what its name says. Names
/// ending in `ext` (any case), in no extension, or in one no format here goes by (`d.npy.out`,
/// a `mktemp` name) pass.
///
/// ```
/// use std::path::Path;
/// use hwsdf::cli::check_out_format;
/// assert!(check_out_format("--out", Path::new("spot.OBJ"), "obj", "OBJ").is_ok());
/// assert!(check_out_format("--out", Path::new("spot"), "obj", "OBJ").is_ok());
/// assert!(check_out_format("--out", Path::new("/tmp/tmp.Xf3kQ9"), "obj", "OBJ").is_ok());
/// let e = check_out_format("--out", Path::new("spot.ply"), "obj", "OBJ").unwrap_err();
/// assert_eq!(e, "--out spot.ply: this writes OBJ; give the file the extension .obj");
/// ```
pub fn check_out_format(
    flag: &str,
    path: &std::path::Path,
    ext: &str,
    format: &str,
) -> Result<(), String> {
    /// Extensions of formats that a user may mean instead (meshes, images, arrays, tables,
    /// models): a name ending in one of them, not `ext`, is refused.
    const KNOWN: &[&str] = &[
        "obj",
        "ply",
        "stl",
        "off",
        "glb",
        "gltf",
        "fbx",
        "dae",
        "3mf",
        "usd",
        "usdz",
        "png",
        "jpg",
        "jpeg",
        "bmp",
        "gif",
        "tga",
        "tif",
        "tiff",
        "webp",
        "exr",
        "hdr",
        "npy",
        "npz",
        "csv",
        "txt",
        "json",
        "toml",
        "yaml",
        "yml",
        "safetensors",
        "pt",
        "pth",
        "onnx",
        "h5",
    ];
    let named = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    match named {
        Some(e) if e != ext && KNOWN.contains(&e.as_str()) => Err(format!(
            "{flag} {}: this writes {format}; give the file the extension .{ext}",
            path.display()
        )),
        _ => Ok(()),
    }
}

/// A loss as progress lines and reports print it: four significant digits whatever its scale
/// (a fitted NGLOD's loss is ~1e-6, which fixed decimals would print as 0).
///
/// ```
/// assert_eq!(hwsdf::cli::format_loss(3.14159e-6), "3.142e-6");
/// assert_eq!(hwsdf::cli::format_loss(0.5), "5.000e-1");
/// ```
pub fn format_loss(loss: f32) -> String {
    format!("{loss:.3e}")
}
