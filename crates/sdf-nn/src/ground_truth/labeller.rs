//! One meaning of "the ground truth" for every caller that labels points: a [`Labeller`] holds
//! a mesh's CPU [`SignedDistance`] and, where the run chose the GPU, its [`GpuGroundTruth`];
//! the trainers' samples, the evaluation sets and the `sdf` binary all ask it, never the two
//! paths directly.
//!
//! ```no_run
//! use std::sync::Arc;
//! use sdf_geom::{SignedDistance, load_mesh, sample};
//! use sdf_nn::GpuContext;
//! use sdf_nn::ground_truth::{GroundTruthDevice, Labeller};
//!
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let (mesh, _) = load_mesh("tests/data/spot.obj")?;
//! let sdf = Arc::new(SignedDistance::new(&mesh.normalized().0)?);
//! let gpu = GpuContext::shared()?;
//! // `auto`: the GPU where the adapter is not a CPU and the mesh's trees fit it.
//! let labels = Labeller::choose(gpu, sdf, GroundTruthDevice::Auto)?;
//! if let Some(why) = labels.fallback() {
//!     eprintln!("warning: {why}");
//! }
//! let d = labels.signed_distance_batch(&sample::uniform_box(10_000, 1))?;
//! println!("{} labels on the {}", d.len(), labels.path());
//! # Ok(())
//! # }
//! ```

use std::fmt;
use std::str::FromStr;
use std::sync::Arc;

use glam::Vec3;
use sdf_geom::SignedDistance;
use serde::{Deserialize, Serialize};

use super::{GpuGroundTruth, GroundTruthError};
use crate::gpu::GpuContext;

/// The winding number from which a point is inside (`sdf_geom`'s sign rule).
const INSIDE_WINDING: f32 = 0.5;

/// Where a run's exact ground truth is computed, as asked (`--ground-truth`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum GroundTruthDevice {
    /// The CPU's [`SignedDistance`] (rayon).
    Cpu,
    /// The GPU kernels ([`GpuGroundTruth`]); an error where the mesh does not fit the device.
    Gpu,
    /// The GPU where the adapter is not a CPU (lavapipe labels 5–17 % as fast as the CPU path)
    /// and the mesh's trees fit it, else the CPU (with [`Labeller::fallback`] saying why when
    /// the mesh did not fit).
    #[default]
    Auto,
}

impl GroundTruthDevice {
    /// Every value, in the order `--help` lists them.
    pub const ALL: [GroundTruthDevice; 3] = [
        GroundTruthDevice::Gpu,
        GroundTruthDevice::Cpu,
        GroundTruthDevice::Auto,
    ];

    /// `"cpu"`, `"gpu"` or `"auto"`.
    pub fn name(self) -> &'static str {
        match self {
            GroundTruthDevice::Cpu => "cpu",
            GroundTruthDevice::Gpu => "gpu",
            GroundTruthDevice::Auto => "auto",
        }
    }
}

impl fmt::Display for GroundTruthDevice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A `--ground-truth` value that is none of `gpu`, `cpu`, `auto`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown ground-truth device {0:?}: expected gpu, cpu or auto")]
pub struct UnknownDevice(pub String);

impl FromStr for GroundTruthDevice {
    type Err = UnknownDevice;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .find(|d| d.name().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| UnknownDevice(s.to_owned()))
    }
}

/// Where labels were computed: what reports record (`"ground_truth": "gpu"`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum GroundTruthPath {
    /// [`SignedDistance`] on the CPU.
    Cpu,
    /// [`GpuGroundTruth`].
    Gpu,
}

impl GroundTruthPath {
    /// `"cpu"` or `"gpu"`.
    pub fn name(self) -> &'static str {
        match self {
            GroundTruthPath::Cpu => "cpu",
            GroundTruthPath::Gpu => "gpu",
        }
    }
}

impl fmt::Display for GroundTruthPath {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Where [`Labeller::choose`] labels.
#[derive(Debug, PartialEq)]
enum Decision {
    /// On the CPU; with `auto` on a GPU, why (the mesh does not fit).
    Cpu(Option<String>),
    /// On the GPU.
    Gpu,
}

/// Where `device` labels on an adapter that is a CPU or not (`cpu_adapter`), for a mesh whose
/// trees fit the device and the kernels or not (`fits`, run only where it matters): `gpu` where
/// it fits (else `fits`'s error), `cpu` always, `auto` on a GPU where it fits, else on the CPU
/// (with the reason where the adapter is a GPU).
fn decide(
    device: GroundTruthDevice,
    cpu_adapter: bool,
    fits: impl FnOnce() -> Result<(), GroundTruthError>,
) -> Result<Decision, GroundTruthError> {
    Ok(match device {
        GroundTruthDevice::Cpu => Decision::Cpu(None),
        GroundTruthDevice::Gpu => {
            fits()?;
            Decision::Gpu
        }
        GroundTruthDevice::Auto if cpu_adapter => Decision::Cpu(None),
        GroundTruthDevice::Auto => match fits() {
            Ok(()) => Decision::Gpu,
            Err(e) => Decision::Cpu(Some(fallback_reason(&e))),
        },
    })
}

/// The warning of `auto` falling back to the CPU because of `e`.
fn fallback_reason(e: &GroundTruthError) -> String {
    format!("ground truth on the CPU instead of the GPU: {e}")
}

/// A mesh's exact labels on the path a run chose: signed and unsigned distances, winding
/// numbers and sides, for batches of points (normalised or mesh units: those of the
/// [`SignedDistance`]). Cheap to clone (the trees are shared).
#[derive(Clone)]
pub struct Labeller<'g> {
    cpu: Arc<SignedDistance>,
    gpu: Option<(&'g GpuContext, Arc<GpuGroundTruth>)>,
    fallback: Option<String>,
}

impl fmt::Debug for Labeller<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Labeller")
            .field("path", &self.path())
            .field("fallback", &self.fallback)
            .finish_non_exhaustive()
    }
}

impl Labeller<'static> {
    /// Labels on the CPU: `sdf`'s batch queries (rayon).
    pub fn cpu(sdf: Arc<SignedDistance>) -> Self {
        Labeller {
            cpu: sdf,
            gpu: None,
            fallback: None,
        }
    }
}

impl<'g> Labeller<'g> {
    /// Labels of `sdf` on the path `device` asks for on `gpu` (see [`GroundTruthDevice`]).
    ///
    /// # Errors
    /// With [`GroundTruthDevice::Gpu`]: [`GroundTruthError::TreeTooLarge`] or
    /// [`GroundTruthError::TreeTooDeep`] naming the limit where the mesh does not fit, and the
    /// device's errors. `Auto` falls back to the CPU instead, and says why in
    /// [`Labeller::fallback`].
    pub fn choose(
        gpu: &'g GpuContext,
        sdf: Arc<SignedDistance>,
        device: GroundTruthDevice,
    ) -> Result<Self, GroundTruthError> {
        let fits = || GpuGroundTruth::check_limits(&sdf.gpu_trees(), &gpu.limits());
        match decide(device, gpu.is_cpu(), fits)? {
            Decision::Cpu(fallback) => Ok(Labeller {
                fallback,
                ..Labeller::cpu(sdf)
            }),
            Decision::Gpu => match (device, GpuGroundTruth::new(gpu, &sdf)) {
                (_, Ok(g)) => Ok(Labeller {
                    cpu: sdf,
                    gpu: Some((gpu, Arc::new(g))),
                    fallback: None,
                }),
                // The upload itself failed (out of device memory): `auto` still has the CPU.
                (GroundTruthDevice::Auto, Err(e)) => Ok(Labeller {
                    fallback: Some(fallback_reason(&e)),
                    ..Labeller::cpu(sdf)
                }),
                (_, Err(e)) => Err(e),
            },
        }
    }

    /// Labels on the GPU of `gpu` (the trees of `sdf` uploaded once).
    ///
    /// # Errors
    /// As [`GpuGroundTruth::new`].
    pub fn on_gpu(gpu: &'g GpuContext, sdf: Arc<SignedDistance>) -> Result<Self, GroundTruthError> {
        let g = GpuGroundTruth::new(gpu, &sdf)?;
        Ok(Labeller {
            cpu: sdf,
            gpu: Some((gpu, Arc::new(g))),
            fallback: None,
        })
    }

    /// Which path the labels come from.
    pub fn path(&self) -> GroundTruthPath {
        if self.gpu.is_some() {
            GroundTruthPath::Gpu
        } else {
            GroundTruthPath::Cpu
        }
    }

    /// Why `auto` chose the CPU although the adapter is a GPU (the mesh did not fit it), for a
    /// warning line; `None` otherwise.
    pub fn fallback(&self) -> Option<&str> {
        self.fallback.as_deref()
    }

    /// The CPU signed distance (the one the GPU's trees were built from).
    pub fn sdf(&self) -> &Arc<SignedDistance> {
        &self.cpu
    }

    /// Signed distances, as [`SignedDistance::signed_distance_batch`]: negative inside, NaN
    /// for non-finite points.
    ///
    /// # Errors
    /// The GPU's ([`GroundTruthError::Gpu`]); the CPU path does not fail.
    pub fn signed_distance_batch(&self, points: &[Vec3]) -> Result<Vec<f32>, GroundTruthError> {
        match &self.gpu {
            Some((gpu, g)) => g.signed_distance(gpu, points),
            None => Ok(self.cpu.signed_distance_batch(points)),
        }
    }

    /// Unsigned distances |d| (the closest point's distance; no winding number needed).
    ///
    /// # Errors
    /// As [`Labeller::signed_distance_batch`].
    pub fn unsigned_distance_batch(&self, points: &[Vec3]) -> Result<Vec<f32>, GroundTruthError> {
        Ok(match &self.gpu {
            Some((gpu, g)) => g
                .closest_points(gpu, points)?
                .into_iter()
                .map(|(_, d)| d)
                .collect(),
            None => self
                .cpu
                .closest_point_batch(points)
                .iter()
                .map(|c| c.distance)
                .collect(),
        })
    }

    /// Generalised winding numbers, as [`SignedDistance::winding_number_batch`].
    ///
    /// # Errors
    /// As [`Labeller::signed_distance_batch`].
    pub fn winding_number_batch(&self, points: &[Vec3]) -> Result<Vec<f32>, GroundTruthError> {
        match &self.gpu {
            Some((gpu, g)) => g.winding_numbers(gpu, points),
            None => Ok(self.cpu.winding_number_batch(points)),
        }
    }

    /// Whether each point is inside (a winding number of at least 1/2), as
    /// [`SignedDistance::is_inside_batch`]; non-finite points are outside.
    ///
    /// # Errors
    /// As [`Labeller::signed_distance_batch`].
    pub fn is_inside_batch(&self, points: &[Vec3]) -> Result<Vec<bool>, GroundTruthError> {
        Ok(match &self.gpu {
            Some(_) => self
                .winding_number_batch(points)?
                .into_iter()
                .map(|w| w >= INSIDE_WINDING)
                .collect(),
            None => self.cpu.is_inside_batch(points),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn devices_parse_and_print_their_names() {
        for d in GroundTruthDevice::ALL {
            assert_eq!(d.to_string().parse::<GroundTruthDevice>(), Ok(d));
        }
        assert_eq!("GPU".parse(), Ok(GroundTruthDevice::Gpu));
        assert_eq!(GroundTruthDevice::default(), GroundTruthDevice::Auto);
        let e = "tpu".parse::<GroundTruthDevice>().unwrap_err();
        assert!(e.to_string().contains("gpu, cpu or auto"), "{e}");
        assert_eq!(
            serde_json::to_string(&GroundTruthPath::Gpu).unwrap(),
            "\"gpu\""
        );
    }

    /// `auto` labels on the CPU on a CPU adapter (silently) and where the mesh does not fit
    /// (saying why); `gpu` then fails naming the limit; `cpu` never asks whether it fits.
    #[test]
    fn auto_falls_back_where_the_mesh_does_not_fit_and_gpu_refuses() {
        let sdf = SignedDistance::new(&sdf_geom::Mesh::icosphere(0.5, 3)).unwrap();
        let trees = sdf.gpu_trees();
        let small = wgpu::Limits {
            max_storage_buffer_binding_size: 1 << 10,
            ..wgpu::Limits::downlevel_defaults()
        };
        let tight = || GpuGroundTruth::check_limits(&trees, &small);
        let roomy = || GpuGroundTruth::check_limits(&trees, &wgpu::Limits::downlevel_defaults());
        let never = || -> Result<(), GroundTruthError> { panic!("fit checked needlessly") };
        use GroundTruthDevice::{Auto, Cpu, Gpu};
        assert_eq!(decide(Auto, false, roomy).unwrap(), Decision::Gpu);
        assert_eq!(decide(Auto, true, never).unwrap(), Decision::Cpu(None));
        assert_eq!(decide(Cpu, false, never).unwrap(), Decision::Cpu(None));
        match decide(Auto, false, tight).unwrap() {
            Decision::Cpu(Some(why)) => {
                assert!(why.contains("max_storage_buffer_binding_size"), "{why}")
            }
            other => panic!("{other:?}"),
        }
        let err = decide(Gpu, false, tight).unwrap_err();
        assert!(
            matches!(err, GroundTruthError::TreeTooLarge { limit_name, .. } if limit_name == "max_storage_buffer_binding_size"),
            "{err:?}"
        );
        assert_eq!(decide(Gpu, true, roomy).unwrap(), Decision::Gpu);
    }

    #[test]
    fn the_cpu_labeller_is_the_signed_distance() {
        let sdf = Arc::new(SignedDistance::new(&sdf_geom::Mesh::icosphere(0.5, 2)).unwrap());
        let labels = Labeller::cpu(sdf.clone());
        let points = sdf_geom::sample::uniform_box(500, 3);
        assert_eq!(labels.path(), GroundTruthPath::Cpu);
        assert_eq!(
            labels.signed_distance_batch(&points).unwrap(),
            sdf.signed_distance_batch(&points)
        );
        let inside = labels.is_inside_batch(&points).unwrap();
        assert!(inside.iter().any(|&i| i) && inside.iter().any(|&i| !i));
        let unsigned = labels.unsigned_distance_batch(&points).unwrap();
        let signed = labels.signed_distance_batch(&points).unwrap();
        for (u, s) in unsigned.iter().zip(&signed) {
            assert_eq!(*u, s.abs());
        }
    }
}
