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
//! // `auto`: the GPU where the adapter is not a CPU, the mesh's trees fit it and a probe's
//! // labels agree with the CPU's.
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
use std::time::{Duration, Instant};

use glam::Vec3;
use sdf_geom::SignedDistance;
use serde::{Deserialize, Serialize};

use super::agreement::{self, Agreement};
use super::{GpuGroundTruth, GroundTruthError, Kernel};
use crate::gpu::GpuContext;

/// The winding number from which a point is inside (`sdf_geom`'s sign rule).
const INSIDE_WINDING: f32 = 0.5;

/// Where a run's exact ground truth is computed, as asked (`--ground-truth`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum GroundTruthDevice {
    /// The CPU's [`SignedDistance`] (rayon).
    Cpu,
    /// The GPU kernels ([`GpuGroundTruth`]); an error where the mesh does not fit the device or
    /// the GPU's labels of a probe disagree with the CPU's.
    Gpu,
    /// The GPU where the adapter is not a CPU (lavapipe labels 5–17 % as fast as the CPU path),
    /// the mesh's trees fit it and its labels of a probe agree with the CPU's, else the CPU
    /// (with [`Labeller::fallback`] saying why when the adapter is a GPU).
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

/// Whether `device` tries the GPU on an adapter that is a CPU or not (`cpu_adapter`): `gpu`
/// always, `auto` where the adapter is not a CPU, `cpu` never. Whether the mesh fits and the
/// probe agrees is then [`checked_gpu_truth`]'s, and what a failure does [`gpu_or_fallback`]'s.
fn tries_gpu(device: GroundTruthDevice, cpu_adapter: bool) -> bool {
    match device {
        GroundTruthDevice::Cpu => false,
        GroundTruthDevice::Gpu => true,
        GroundTruthDevice::Auto => !cpu_adapter,
    }
}

/// What [`Labeller::choose`] does with the GPU's truth: uses it; where the mesh's trees do
/// not fit the device, the upload failed (out of device memory) or the probe's labels
/// disagree, `auto` falls back to the CPU (`Ok(Err(why))`) and `gpu` fails.
fn gpu_or_fallback<T>(
    device: GroundTruthDevice,
    truth: Result<T, GroundTruthError>,
) -> Result<Result<T, String>, GroundTruthError> {
    match (device, truth) {
        (_, Ok(g)) => Ok(Ok(g)),
        (GroundTruthDevice::Auto, Err(e)) => Ok(Err(fallback_reason(&e))),
        (_, Err(e)) => Err(e),
    }
}

/// The trees of `sdf` uploaded to `gpu` (checked against its limits first:
/// [`GpuGroundTruth::new`]), once the GPU's signed distances at the probe points have been
/// found to agree with the CPU's.
fn checked_gpu_truth(
    gpu: &GpuContext,
    sdf: &SignedDistance,
) -> Result<GpuGroundTruth, GroundTruthError> {
    let g = GpuGroundTruth::new(gpu, sdf)?;
    probe_agreement(gpu, &g, sdf)?.check()?;
    Ok(g)
}

/// How the labels of `g` compare with those of `sdf` at the probe points of `sdf`'s mesh
/// ([`agreement::probe`]).
fn probe_agreement(
    gpu: &GpuContext,
    g: &GpuGroundTruth,
    sdf: &SignedDistance,
) -> Result<Agreement, GroundTruthError> {
    let probe = agreement::probe(&sdf.gpu_trees());
    let on_gpu = g.signed_distance(gpu, &probe.points)?;
    let cpu = sdf.signed_distance_batch(&probe.points);
    let winding = sdf.winding_number_batch(&probe.points);
    Ok(Agreement::of(&probe, &cpu, &winding, &on_gpu))
}

/// The warning of `auto` falling back to the CPU because of `e`.
fn fallback_reason(e: &GroundTruthError) -> String {
    format!("ground truth on the CPU instead of the GPU: {e}")
}

/// How far a long labelling call has got, for progress lines ([`Labeller::with_progress`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LabelProgress {
    /// Points labelled so far in this call.
    pub done: usize,
    /// Points of the call.
    pub total: usize,
    /// Time since the call began.
    pub elapsed: Duration,
}

impl LabelProgress {
    /// The time left at the rate so far (`None` before any point is done).
    pub fn eta(&self) -> Option<Duration> {
        (self.done > 0).then(|| {
            self.elapsed
                .mul_f64((self.total - self.done.min(self.total)) as f64 / self.done as f64)
        })
    }
}

/// Where a [`Labeller`] reports progress: called after each part of a long call, from the
/// labelling thread (NGLOD's samplers label on their own threads).
pub type ProgressSink = Arc<dyn Fn(&LabelProgress) + Send + Sync>;

/// On the CPU, a call with a progress sink is labelled in about this many parts (on the GPU,
/// in the kernels' own, [`GpuGroundTruth`]'s)...
const PROGRESS_PARTS: usize = 64;
/// ...of at least this many points (smaller calls in one part, with no progress call).
const MIN_PART: usize = 1024;

/// A mesh's exact labels on the path a run chose: signed and unsigned distances, winding
/// numbers and sides, for batches of points (normalised or mesh units: those of the
/// [`SignedDistance`]). Cheap to clone (the trees are shared).
#[derive(Clone)]
pub struct Labeller<'g> {
    cpu: Arc<SignedDistance>,
    gpu: Option<(&'g GpuContext, Arc<GpuGroundTruth>)>,
    fallback: Option<String>,
    progress: Option<ProgressSink>,
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
            progress: None,
        }
    }
}

impl<'g> Labeller<'g> {
    /// Labels of `sdf` on the path `device` asks for on `gpu` (see [`GroundTruthDevice`]).
    /// Before the GPU's labels are used, up to 192 probe points (beside the surface on both
    /// sides, and in the box) are labelled on both paths and compared: a device or driver the kernels
    /// were never proven on cannot spoil a run unseen.
    ///
    /// # Errors
    /// With [`GroundTruthDevice::Gpu`]: [`GroundTruthError::TreeTooLarge`] or
    /// [`GroundTruthError::TreeTooDeep`] naming the limit where the mesh does not fit,
    /// [`GroundTruthError::Disagrees`] where the probe's labels differ, and the device's
    /// errors. `Auto` falls back to the CPU instead, and says why in [`Labeller::fallback`].
    pub fn choose(
        gpu: &'g GpuContext,
        sdf: Arc<SignedDistance>,
        device: GroundTruthDevice,
    ) -> Result<Self, GroundTruthError> {
        if !tries_gpu(device, gpu.is_cpu()) {
            return Ok(Labeller::cpu(sdf));
        }
        match gpu_or_fallback(device, checked_gpu_truth(gpu, &sdf))? {
            Ok(g) => Ok(Labeller {
                gpu: Some((gpu, Arc::new(g))),
                ..Labeller::cpu(sdf)
            }),
            Err(why) => Ok(Labeller {
                fallback: Some(why),
                ..Labeller::cpu(sdf)
            }),
        }
    }

    /// Labels on the GPU of `gpu` (the trees of `sdf` uploaded once), checked on a probe as
    /// [`Labeller::choose`] checks them.
    ///
    /// # Errors
    /// As [`GpuGroundTruth::new`], and [`GroundTruthError::Disagrees`].
    pub fn on_gpu(gpu: &'g GpuContext, sdf: Arc<SignedDistance>) -> Result<Self, GroundTruthError> {
        let g = checked_gpu_truth(gpu, &sdf)?;
        Ok(Labeller {
            gpu: Some((gpu, Arc::new(g))),
            ..Labeller::cpu(sdf)
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

    /// Why `auto` chose the CPU although the adapter is a GPU (the mesh did not fit it, or its
    /// labels of the probe disagreed with the CPU's), for a warning line; `None` otherwise.
    pub fn fallback(&self) -> Option<&str> {
        self.fallback.as_deref()
    }

    /// The CPU signed distance (the one the GPU's trees were built from).
    pub fn sdf(&self) -> &Arc<SignedDistance> {
        &self.cpu
    }

    /// These labels, reporting the progress of every call of more than a few thousand points
    /// to `sink`: on the CPU after each of about 64 parts, labelled one after another, each as
    /// one batch; on the GPU after each of the kernels' parts (2¹⁸ points on a CPU adapter, 2²⁰
    /// on a GPU), so that a call of fewer points reports once, at its end.
    pub fn with_progress(self, sink: ProgressSink) -> Self {
        Labeller {
            progress: Some(sink),
            ..self
        }
    }

    /// Seconds per signed distance on this path, measured on a prefix of `probe` (points like
    /// those the run will label): a first few points untimed (a GPU compiles its kernels on the
    /// first call), then batches that double until a quarter of a second has passed or the
    /// probe is spent. Returns the rate and the number of points it was measured on.
    ///
    /// # Errors
    /// As [`Labeller::signed_distance_batch`].
    pub fn time_per_label(&self, probe: &[Vec3]) -> Result<(f64, usize), GroundTruthError> {
        let warm = probe.len().min(64);
        self.signed(&probe[..warm])?;
        let (mut at, mut batch, mut timed) = (warm, 256usize, Duration::ZERO);
        while at < probe.len() && timed < PROBE_TIME {
            let end = (at + batch).min(probe.len());
            let t = Instant::now();
            self.signed(&probe[at..end])?;
            timed += t.elapsed();
            at = end;
            batch *= 2;
        }
        let n = at - warm;
        Ok((timed.as_secs_f64() / n.max(1) as f64, n))
    }

    /// Signed distances, as [`SignedDistance::signed_distance_batch`]: negative inside, NaN
    /// for non-finite points.
    ///
    /// # Errors
    /// The GPU's ([`GroundTruthError::Gpu`]); the CPU path does not fail.
    pub fn signed_distance_batch(&self, points: &[Vec3]) -> Result<Vec<f32>, GroundTruthError> {
        self.label(
            points,
            Kernel::Signed,
            |p| self.cpu.signed_distance_batch(p),
            |v| v[0],
        )
    }

    /// [`Labeller::signed_distance_batch`] in one batch.
    fn signed(&self, points: &[Vec3]) -> Result<Vec<f32>, GroundTruthError> {
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
        self.label(
            points,
            Kernel::Closest,
            |p| {
                let closest = self.cpu.closest_point_batch(p);
                closest.iter().map(|c| c.distance).collect()
            },
            |v| v[3],
        )
    }

    /// Generalised winding numbers, as [`SignedDistance::winding_number_batch`].
    ///
    /// # Errors
    /// As [`Labeller::signed_distance_batch`].
    pub fn winding_number_batch(&self, points: &[Vec3]) -> Result<Vec<f32>, GroundTruthError> {
        self.label(
            points,
            Kernel::Winding,
            |p| self.cpu.winding_number_batch(p),
            |v| v[0],
        )
    }

    /// Whether each point is inside (a winding number of at least 1/2), as
    /// [`SignedDistance::is_inside_batch`]; non-finite points are outside.
    ///
    /// # Errors
    /// As [`Labeller::signed_distance_batch`].
    pub fn is_inside_batch(&self, points: &[Vec3]) -> Result<Vec<bool>, GroundTruthError> {
        self.label(
            points,
            Kernel::Winding,
            |p| self.cpu.is_inside_batch(p),
            |v| v[0] >= INSIDE_WINDING,
        )
    }

    /// Labels of `points`: on the GPU, `kernel`'s values through `from_gpu` (one call over
    /// the points, in the kernels' own parts, each reported to the progress sink as it
    /// completes: the GPU never waits for the host between parts); on the CPU, `cpu` in one
    /// batch, or with a progress sink and many points in parts, reporting after each.
    fn label<T>(
        &self,
        points: &[Vec3],
        kernel: Kernel,
        cpu: impl Fn(&[Vec3]) -> Vec<T>,
        from_gpu: impl Fn(&[f32]) -> T,
    ) -> Result<Vec<T>, GroundTruthError> {
        let start = Instant::now();
        let total = points.len();
        let part = (total / PROGRESS_PARTS).max(MIN_PART);
        let sink = self.progress.as_ref().filter(|_| total > part);
        let report = |done| {
            if let Some(sink) = sink {
                sink(&LabelProgress {
                    done,
                    total,
                    elapsed: start.elapsed(),
                });
            }
        };
        if let Some((gpu, g)) = &self.gpu {
            let flat = g.run_reporting(gpu, points, kernel, &mut |done| report(done))?;
            return Ok(flat.chunks_exact(kernel.width()).map(from_gpu).collect());
        }
        if sink.is_none() {
            return Ok(cpu(points));
        }
        let mut out = Vec::with_capacity(total);
        for p in points.chunks(part) {
            out.extend(cpu(p));
            report(out.len());
        }
        Ok(out)
    }
}

/// How long [`Labeller::time_per_label`] measures, at least (unless its probe runs out).
const PROBE_TIME: Duration = Duration::from_millis(250);

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
        use GroundTruthDevice::{Auto, Cpu, Gpu};
        // The fit is asked only where the GPU is tried.
        assert!(tries_gpu(Auto, false) && tries_gpu(Gpu, true) && tries_gpu(Gpu, false));
        assert!(!tries_gpu(Auto, true) && !tries_gpu(Cpu, false) && !tries_gpu(Cpu, true));
        assert_eq!(gpu_or_fallback(Auto, roomy()).unwrap(), Ok(()));
        match gpu_or_fallback(Auto, tight()).unwrap() {
            Err(why) => assert!(why.contains("max_storage_buffer_binding_size"), "{why}"),
            other => panic!("{other:?}"),
        }
        let err = gpu_or_fallback(Gpu, tight()).unwrap_err();
        assert!(
            matches!(err, GroundTruthError::TreeTooLarge { limit_name, .. } if limit_name == "max_storage_buffer_binding_size"),
            "{err:?}"
        );
        assert_eq!(gpu_or_fallback(Gpu, roomy()).unwrap(), Ok(()));
    }

    /// The probe finds labels that are not the mesh's: the GPU's truth of a sphere checked
    /// against the CPU's of a smaller one disagrees (distances and signs), the same sphere's
    /// agrees; `auto` then falls back to the CPU saying why, `gpu` fails.
    #[test]
    fn labels_that_disagree_with_the_cpu_are_never_used() {
        let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
        let sdf = SignedDistance::new(&sdf_geom::Mesh::icosphere(0.5, 2)).unwrap();
        let other = SignedDistance::new(&sdf_geom::Mesh::icosphere(0.45, 2)).unwrap();
        let g = GpuGroundTruth::new(gpu, &other).unwrap();
        let wrong = probe_agreement(gpu, &g, &sdf).unwrap();
        assert!(wrong.misses > 0 && wrong.sign_misses > 0, "{wrong:?}");
        let right = GpuGroundTruth::new(gpu, &sdf).unwrap();
        let same = probe_agreement(gpu, &right, &sdf).unwrap();
        assert_eq!(same.misses, 0, "{same:?}");
        assert!(same.worst < 1e-6, "{same:?}");
        let why = gpu_or_fallback(GroundTruthDevice::Auto, wrong.check().map(|()| g))
            .unwrap()
            .unwrap_err();
        assert!(why.contains("disagrees with the CPU's"), "{why}");
        let err = gpu_or_fallback(GroundTruthDevice::Gpu, wrong.check()).unwrap_err();
        assert!(matches!(err, GroundTruthError::Disagrees { .. }), "{err:?}");
        assert!(gpu_or_fallback(GroundTruthDevice::Gpu, same.check()).is_ok());
    }

    /// With a progress sink a long call comes in parts, each reported, and gives the same
    /// labels; a short call is one batch, unreported; the probe measures a positive rate.
    #[test]
    fn long_calls_report_their_progress() {
        use std::sync::Mutex;
        let sdf = Arc::new(SignedDistance::new(&sdf_geom::Mesh::icosphere(0.5, 2)).unwrap());
        let seen: Arc<Mutex<Vec<LabelProgress>>> = Arc::default();
        let sink = seen.clone();
        let labels = Labeller::cpu(sdf.clone())
            .with_progress(Arc::new(move |p| sink.lock().unwrap().push(*p)));
        let points = sdf_geom::sample::uniform_box(20_000, 5);
        assert_eq!(
            labels.signed_distance_batch(&points).unwrap(),
            sdf.signed_distance_batch(&points)
        );
        let seen = std::mem::take(&mut *seen.lock().unwrap());
        assert_eq!(seen.len(), 20_000usize.div_ceil(MIN_PART));
        assert!(seen.windows(2).all(|w| w[0].done < w[1].done));
        let last = seen.last().unwrap();
        assert_eq!((last.done, last.total), (20_000, 20_000));
        assert_eq!(last.eta(), Some(Duration::ZERO));
        let half = LabelProgress {
            done: 50,
            total: 100,
            elapsed: Duration::from_secs(3),
        };
        assert_eq!(half.eta(), Some(Duration::from_secs(3)));
        labels.is_inside_batch(&points[..100]).unwrap();
        let (rate, n) = labels.time_per_label(&points).unwrap();
        assert!(rate > 0.0 && n > 0 && n <= 20_000 - 64, "{rate} {n}");
    }

    /// On the GPU a long call is reported part by part as the kernels' parts complete (262 144
    /// points each on a CPU adapter, 2²⁰ on a GPU), and gives the labels of one call without a
    /// sink.
    #[test]
    fn gpu_labels_report_their_progress() {
        use std::sync::Mutex;
        let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
        let sdf = Arc::new(SignedDistance::new(&sdf_geom::Mesh::icosphere(0.5, 1)).unwrap());
        let seen: Arc<Mutex<Vec<usize>>> = Arc::default();
        let sink = seen.clone();
        let plain = Labeller::on_gpu(gpu, sdf.clone()).unwrap();
        let labels = plain
            .clone()
            .with_progress(Arc::new(move |p| sink.lock().unwrap().push(p.done)));
        let points = sdf_geom::sample::uniform_box(270_000, 6);
        let inside = labels.is_inside_batch(&points).unwrap();
        let part = super::super::part_size(gpu, Kernel::Winding);
        let mut want: Vec<usize> = (part..270_000).step_by(part).collect();
        want.push(270_000);
        assert_eq!(*seen.lock().unwrap(), want);
        assert_eq!(inside, plain.is_inside_batch(&points).unwrap());
        let cpu = sdf.is_inside_batch(&points);
        let differ = inside.iter().zip(&cpu).filter(|(a, b)| a != b).count();
        assert!(differ <= 2, "{differ} sides differ from the CPU's");
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
