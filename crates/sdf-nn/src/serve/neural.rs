//! [`NeuralSdf`]: one type over the three architectures for people who use a trained model: query it
//! on the GPU or the CPU, get normals, embed it in a renderer's WGSL.
//!
//! Points are in the original mesh's coordinates and distances in its units, unless a method
//! says `normalized`. Outside the normalised box `[-1, 1]³`, which is all a model was trained
//! on, the distance is extended as `Φ(clamp(x)) + |x − clamp(x)|` (the distance to the box plus
//! the model's value at the nearest box point): a sphere tracer coming from far away then steps
//! safely up to the box instead of trusting an extrapolating network. Every path (GPU, CPU,
//! WGSL) applies the same rule, so they agree. The GPU calls refuse NaN and infinite points
//! ([`crate::QueryError::NonFinitePoint`]): kernels need not propagate NaN, so their answer
//! would be an arbitrary number, where the CPU's is NaN.

use std::path::Path;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};

use glam::Vec3;
use rayon::prelude::*;

use crate::gpu::{GpuContext, GpuTimer, SirenActivations};
use crate::model_file::{ModelFile, Normalization};
use crate::nglod::{Nglod, NglodGpu};
use crate::serve::error::{NeuralSdfError, QueryError};
use crate::serve::network::{GpuNetwork, Network};
use crate::serve::query::{
    QueryBuffers, QueryBuffersDescriptor, QueryOutputs, QuerySpace, QueryTicket, QueryTransfer,
};
use crate::serve::wgsl::{self, EmbedError, SdfBindGroup};
use crate::siren::{self, LayerKernels, Siren, SirenGpu, SirenGpuOptions};

/// Most points the host-side methods send in one submission; larger inputs are split.
const HOST_CHUNK: usize = 1 << 18;

/// Architecture name of NGLOD model files.
const NGLOD_ARCHITECTURE: &str = "nglod";
/// Architecture name of hash-grid model files.
const HASHGRID_ARCHITECTURE: &str = "hashgrid";

/// A trained neural SDF, either architecture.
pub struct NeuralSdf {
    network: Network,
    normalization: Normalization,
    file: ModelFile,
    lod: Option<usize>,
    /// The kernels a SIREN's GPU side runs on.
    siren_kernels: LayerKernels,
    /// [`NeuralSdf::set_siren_coop_min_points`] (`None`: the served default).
    siren_coop_min_points: Option<Option<u32>>,
    gpu: Mutex<Option<GpuSide>>,
    /// Identifies the model to the [`QueryBuffers`] made for it.
    id: u64,
    /// The query buffers of the host-side methods (`eval`, ...), one per kind and device.
    host_queries: Mutex<Vec<QueryBuffers>>,
}

/// What [`NeuralSdf`] keeps per device: the network's GPU side and, where the device has
/// timestamp queries, the timer of [`NeuralSdf::eval_normalized_timed`].
struct GpuSide {
    device: wgpu::Device,
    network: GpuNetwork,
    timer: Option<GpuTimer>,
}

impl std::fmt::Debug for NeuralSdf {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("NeuralSdf")
            .field("architecture", &self.architecture())
            .field("params", &self.param_count())
            .field("normalization", &self.normalization)
            .field("lod", &self.lod)
            .finish_non_exhaustive()
    }
}

impl NeuralSdf {
    /// Loads a model file written by `train`. Every error names the file: those of reading it
    /// ([`NeuralSdfError::ModelFile`]) do already, and those of the model in it come as
    /// [`NeuralSdfError::InvalidModel`].
    pub fn load(path: impl AsRef<Path>) -> Result<Self, NeuralSdfError> {
        let path = path.as_ref();
        Self::from_model_file(ModelFile::load(path)?).map_err(|reason| {
            NeuralSdfError::InvalidModel {
                path: path.to_owned(),
                reason: Box::new(reason),
            }
        })
    }

    /// A model from a model file in memory.
    pub fn from_model_file(file: ModelFile) -> Result<Self, NeuralSdfError> {
        let network = match file.metadata.architecture.as_str() {
            siren::ARCHITECTURE => Network::Siren(Siren::from_model_file(&file)?),
            NGLOD_ARCHITECTURE | HASHGRID_ARCHITECTURE => {
                Network::Nglod(Nglod::from_model_file(&file)?)
            }
            other => return Err(NeuralSdfError::UnknownArchitecture(other.to_owned())),
        };
        Ok(NeuralSdf {
            network,
            normalization: file.metadata.normalization,
            file,
            lod: None,
            siren_kernels: LayerKernels::Auto,
            siren_coop_min_points: None,
            gpu: Mutex::new(None),
            id: next_id(),
            host_queries: Mutex::new(Vec::new()),
        })
    }

    /// `"siren"`, `"nglod"` or `"hashgrid"` (a hash grid is served by the NGLOD network's
    /// code: [`crate::nglod::Encoding::Hashed`]).
    pub fn architecture(&self) -> &'static str {
        match &self.network {
            Network::Siren(_) => siren::ARCHITECTURE,
            Network::Nglod(m) => m.config().architecture(),
        }
    }

    /// The network.
    pub fn network(&self) -> &Network {
        &self.network
    }

    /// The model file it came from (metadata included).
    pub fn model_file(&self) -> &ModelFile {
        &self.file
    }

    /// The map from mesh coordinates to the model's normalised cube.
    pub fn normalization(&self) -> Normalization {
        self.normalization
    }

    /// Number of the network's parameters (a checkpoint's optimiser moments, which its file
    /// also holds, are not parameters).
    pub fn param_count(&self) -> usize {
        match &self.network {
            Network::Siren(s) => s.params().len(),
            Network::Nglod(m) => m.param_count(),
        }
    }

    /// Evaluates NGLOD models with only their first `lod` levels (`None`: all). An error for
    /// SIREN, for a hash grid's levels short of all of them, or for a level the model does not
    /// have.
    pub fn set_lod(&mut self, lod: Option<usize>) -> Result<(), NeuralSdfError> {
        match (&self.network, lod) {
            (_, None) => {}
            (Network::Siren(_), Some(_)) => return Err(NeuralSdfError::NoLevels("siren")),
            // A hash grid's MLP reads every level's features at once, so a prefix of its levels
            // is an input it never saw in training: only the whole model is a level.
            (Network::Nglod(m), Some(k))
                if m.config().architecture() == HASHGRID_ARCHITECTURE
                    && k != m.config().levels() =>
            {
                return Err(NeuralSdfError::NoLevels(HASHGRID_ARCHITECTURE));
            }
            (Network::Nglod(m), Some(k)) => {
                m.config().lod(Some(k))?;
            }
        }
        self.lod = lod;
        Ok(())
    }

    /// The level of detail in use (`None`: all levels).
    pub fn lod(&self) -> Option<usize> {
        self.lod
    }

    /// Chooses the kernels a SIREN model runs on (default [`LayerKernels::Auto`]), for example
    /// [`LayerKernels::CoopF16`]: f16 cooperative matrices (tensor cores) where the device has
    /// them, at some cost in accuracy. [`QueryBuffers`] made before the change are refused
    /// after it ([`QueryError::Foreign`]); make new ones. An error for NGLOD models and hash grids.
    pub fn set_siren_kernels(&mut self, kernels: LayerKernels) -> Result<(), NeuralSdfError> {
        if let Network::Nglod(_) = self.network {
            return Err(NeuralSdfError::NoLayerKernels(self.architecture()));
        }
        if kernels != self.siren_kernels {
            self.siren_kernels = kernels;
            self.reset_gpu_side();
        }
        Ok(())
    }

    /// The kernels a SIREN model runs on.
    pub fn siren_kernels(&self) -> LayerKernels {
        self.siren_kernels
    }

    /// With [`LayerKernels::Auto`], SIREN queries of values of at least `points` points run on
    /// f16 cooperative matrices where the device has them, `None` never (see
    /// [`crate::siren::SirenGpuOptions::coop_min_points`]). The default is
    /// [`crate::siren::auto_coop_min_points`]: [`crate::siren::COOP_AUTO_MIN_POINTS`] on GPUs
    /// for networks at least [`crate::siren::COOP_AUTO_MIN_WIDTH`] wide. [`QueryBuffers`] made
    /// before the change are refused after it; make new ones. An error for NGLOD models and hash
    /// grids.
    pub fn set_siren_coop_min_points(&mut self, points: Option<u32>) -> Result<(), NeuralSdfError> {
        if let Network::Nglod(_) = self.network {
            return Err(NeuralSdfError::NoLayerKernels(self.architecture()));
        }
        self.siren_coop_min_points = Some(points);
        self.reset_gpu_side();
        Ok(())
    }

    /// Drops the GPU network and the host query buffers (rebuilt on next use) and takes a new
    /// identity, so that query buffers made before are refused.
    fn reset_gpu_side(&mut self) {
        *self.gpu.get_mut().unwrap_or_else(|e| e.into_inner()) = None;
        self.host_queries
            .get_mut()
            .unwrap_or_else(|e| e.into_inner())
            .clear();
        self.id = next_id();
    }

    /// Self-contained WGSL defining `hwsdf_distance`, `hwsdf_normal` (mesh coordinates) and
    /// their `_normalized` variants, reading the weights from `@group(group) @binding(0)`. See
    /// the [`wgsl`] module. The current level of detail
    /// ([`NeuralSdf::set_lod`]) is baked in.
    pub fn wgsl(&self, group: u32) -> String {
        self.wgsl_with_activations(group, SirenActivations::Private)
    }

    /// [`NeuralSdf::wgsl`] in the form for `activations`: the scratch form reads the names of
    /// [`wgsl::scratch_source`], which the kernel provides.
    pub(crate) fn wgsl_with_activations(
        &self,
        group: u32,
        activations: SirenActivations,
    ) -> String {
        wgsl::generate(
            self.network(),
            self.normalization(),
            self.lod(),
            group,
            wgsl::Lanes::One,
            activations,
        )
    }

    /// [`NeuralSdf::wgsl`] with every name the snippet declares starting with `prefix` instead
    /// of `hwsdf` (`{prefix}_distance`, `{prefix}_normal`, `{prefix}_params`, …) and its upper
    /// case instead of `HWSDF` (`{PREFIX}_CENTER`, …), so that several models live in one
    /// shader, each at its own group; give them prefixes that differ other than in case. The
    /// prefix is an ASCII letter followed by letters, digits or underscores
    /// ([`EmbedError::Prefix`] otherwise).
    pub fn wgsl_with_prefix(&self, group: u32, prefix: &str) -> Result<String, EmbedError> {
        wgsl::with_prefix(&self.wgsl(group), prefix)
    }

    /// Uploads the weights to `device` and creates the bind group (and its layout) that the
    /// snippet of [`NeuralSdf::wgsl`] reads, visible to compute and fragment stages.
    pub fn bind_group(&self, device: &wgpu::Device) -> Result<SdfBindGroup, EmbedError> {
        wgsl::bind_group(self.network(), device)
    }

    /// Buffers for queries of this model on `gpu`'s device (see the [`query`] module).
    ///
    /// [`query`]: crate::serve::query
    pub fn create_query_buffers(
        &self,
        gpu: &GpuContext,
        desc: &QueryBuffersDescriptor<'_>,
    ) -> Result<QueryBuffers, NeuralSdfError> {
        if desc.capacity == 0 {
            return Err(QueryError::Invalid("capacity 0".into()).into());
        }
        self.with_gpu(gpu, |network, _| {
            QueryBuffers::new(gpu, network, self.id, self.normalization, desc)
        })
    }

    /// Records a query of the first `n` points of [`QueryBuffers::points`] into `enc`; the
    /// results land in [`QueryBuffers::results`] when `enc` has run, and stay on the GPU.
    ///
    /// The point count goes through the queue when it changes, taking effect at the next
    /// submission: record one [`QueryBuffers`] at most once per submission (use one per batch).
    pub fn record_query(
        &self,
        gpu: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        buffers: &mut QueryBuffers,
        n: u32,
    ) -> Result<(), NeuralSdfError> {
        buffers.check_owner(self.id, gpu)?;
        buffers.check_free()?;
        self.record_unchecked(gpu, enc, buffers, n, false)
    }

    /// Uploads `points`, records their query, copies the results to the staging buffer and
    /// submits, without waiting: redeem the ticket with [`QueryBuffers::wait`].
    pub fn submit_query(
        &self,
        gpu: &GpuContext,
        buffers: &mut QueryBuffers,
        points: &[Vec3],
    ) -> Result<QueryTicket, NeuralSdfError> {
        self.submit_query_timed(gpu, buffers, points, false)
    }

    /// [`NeuralSdf::submit_query`], with the query's passes timed by this model's
    /// [`GpuTimer`] when `timed` (read it with [`NeuralSdf::read_query_ns`] after waiting).
    pub(crate) fn submit_query_timed(
        &self,
        gpu: &GpuContext,
        buffers: &mut QueryBuffers,
        points: &[Vec3],
        timed: bool,
    ) -> Result<QueryTicket, NeuralSdfError> {
        buffers.submit(gpu, self.id, points, self.lod, timed, |buffers, enc, n| {
            self.record_unchecked(gpu, enc, buffers, n, timed)
        })
    }

    /// The GPU nanoseconds of the last timed query's passes (first to last), from this
    /// model's timer; `None` without timestamp queries. Call after its ticket was waited on.
    pub(crate) fn read_query_ns(&self, gpu: &GpuContext) -> Result<Option<u64>, NeuralSdfError> {
        self.with_gpu(gpu, |_, timer| match timer {
            Some(t) => Ok(Some(t.read_ns(gpu)?)),
            None => Ok(None),
        })
    }

    /// Records a query of `n` points into `enc` with this model's GPU network, bracketing the
    /// passes with the model's timer when `timed` and the device has timestamp queries,
    /// without checking that `buffers` are this model's and free (the callers have).
    fn record_unchecked(
        &self,
        gpu: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        buffers: &mut QueryBuffers,
        n: u32,
        timed: bool,
    ) -> Result<(), NeuralSdfError> {
        self.with_gpu(gpu, |network, timer| {
            buffers.record(gpu, enc, network, self.lod, n, timer.filter(|_| timed))
        })
    }

    /// Signed distances at `points` (mesh coordinates, mesh units), on the GPU. Any number of
    /// points: large inputs are split into several submissions. Runs on the serving path of
    /// [`crate::serve::query`] with buffers the model keeps per device: one upload, one submission and
    /// one readback per call, nothing allocated on the GPU after the first call.
    ///
    /// A model far from the origin for its size ([`Normalization::is_far`]: trained from
    /// georeferenced or CAD coordinates) has its points mapped into its cube on the host, with
    /// its centre in f64, as [`NeuralSdf::eval_cpu`] does: the kernels' f32 centre would round
    /// its shape (at 10⁷ by up to half a unit).
    pub fn eval(&self, gpu: &GpuContext, points: &[Vec3]) -> Result<Vec<f32>, NeuralSdfError> {
        let mut out = Vec::with_capacity(points.len());
        let (points, space) = self.mesh_points(points);
        self.host_query(gpu, &points, space, QueryOutputs::Values, false, |r| {
            r.extend_values(&mut out)
        })?;
        self.to_mesh_units(space, out.iter_mut());
        Ok(out)
    }

    /// `points` in mesh coordinates as the GPU takes them: as they are, or for a far model
    /// ([`NeuralSdf::eval`]) mapped into the cube on the host.
    fn mesh_points<'p>(&self, points: &'p [Vec3]) -> (std::borrow::Cow<'p, [Vec3]>, QuerySpace) {
        let n = self.normalization;
        if !n.is_far() {
            return (points.into(), QuerySpace::Mesh);
        }
        (
            self.normalized_points(points).into(),
            QuerySpace::Normalized,
        )
    }

    /// `points` (mesh coordinates) in the model's cube, mapped on the host with the centre in
    /// f64 ([`crate::Normalization::to_normalized`]).
    fn normalized_points(&self, points: &[Vec3]) -> Vec<Vec3> {
        let n = self.normalization;
        points.par_iter().map(|&p| n.to_normalized(p)).collect()
    }

    /// Distances of a query in `space` ([`NeuralSdf::mesh_points`]) into mesh units.
    fn to_mesh_units<'d>(&self, space: QuerySpace, distances: impl Iterator<Item = &'d mut f32>) {
        if space == QuerySpace::Normalized {
            for d in distances {
                *d = self.normalization.distance_to_original(*d);
            }
        }
    }

    /// Signed distances at `points` in the normalised cube, in normalised units, on the GPU.
    pub fn eval_normalized(
        &self,
        gpu: &GpuContext,
        points: &[Vec3],
    ) -> Result<Vec<f32>, NeuralSdfError> {
        let mut out = Vec::with_capacity(points.len());
        self.host_query(
            gpu,
            points,
            QuerySpace::Normalized,
            QueryOutputs::Values,
            false,
            |r| r.extend_values(&mut out),
        )?;
        Ok(out)
    }

    /// [`NeuralSdf::eval_normalized`], also returning the pure GPU time of the query's passes
    /// in nanoseconds (from the first kernel's start to the last one's end, summed over the
    /// submissions of a large input), from timestamp queries (see [`GpuTimer`]); `None` when the
    /// device has none. It excludes uploads, readbacks and the host's work.
    ///
    /// The timestamps' resolve and readback cost wall time: time the wall clock with
    /// [`NeuralSdf::eval_normalized`] and the GPU with this, in separate calls.
    pub fn eval_normalized_timed(
        &self,
        gpu: &GpuContext,
        points: &[Vec3],
    ) -> Result<(Vec<f32>, Option<u64>), NeuralSdfError> {
        let mut out = Vec::with_capacity(points.len());
        let ns = self.host_query(
            gpu,
            points,
            QuerySpace::Normalized,
            QueryOutputs::Values,
            true,
            |r| r.extend_values(&mut out),
        )?;
        Ok((out, ns))
    }

    /// Signed distances and unit normals (the normalised analytic gradient) at `points` in
    /// mesh coordinates, both from the GPU: SIREN's gradient from its forward-mode kernels,
    /// NGLOD's from its analytic-gradient kernel. A far model's points are mapped on the host,
    /// as [`NeuralSdf::eval`]'s.
    pub fn eval_with_normals(
        &self,
        gpu: &GpuContext,
        points: &[Vec3],
    ) -> Result<Vec<(f32, Vec3)>, NeuralSdfError> {
        let mut out = Vec::with_capacity(points.len());
        let (points, space) = self.mesh_points(points);
        self.host_query(
            gpu,
            &points,
            space,
            QueryOutputs::ValuesAndNormals,
            false,
            |r| r.extend_values_and_normals(&mut out),
        )?;
        self.to_mesh_units(space, out.iter_mut().map(|(d, _)| d));
        Ok(out)
    }

    /// The host-side methods' one path: `points` in chunks through this model's own
    /// [`QueryBuffers`] of that kind, each chunk's results handed to `take`. With `timed`, the
    /// summed GPU nanoseconds of the chunks (`None` without timestamp queries).
    fn host_query(
        &self,
        gpu: &GpuContext,
        points: &[Vec3],
        space: QuerySpace,
        outputs: QueryOutputs,
        timed: bool,
        mut take: impl FnMut(&crate::serve::query::QueryResults<'_>),
    ) -> Result<Option<u64>, NeuralSdfError> {
        let mut all = self.host_queries.lock().unwrap_or_else(|e| e.into_inner());
        let want = points.len().clamp(1, HOST_CHUNK);
        let found = all
            .iter()
            .position(|b| b.space() == space && b.outputs() == outputs && b.belongs_to(gpu));
        let index = match found {
            Some(i) if all[i].capacity() as usize >= want => i,
            _ => {
                // Grow by powers of two from 4096, so small calls do not reallocate each time.
                let capacity = want.max(4096).next_power_of_two().min(HOST_CHUNK) as u32;
                let buffers = self.create_query_buffers(
                    gpu,
                    &QueryBuffersDescriptor {
                        label: Some("hwsdf host query"),
                        capacity,
                        outputs,
                        space,
                        // Every host-side query reads its results back: no copies where the
                        // device maps storage (on an H100 15–18 µs less per query than
                        // through staging; docs/benchmarks).
                        transfer: if gpu.maps_storage() {
                            QueryTransfer::Mapped
                        } else {
                            QueryTransfer::Staged
                        },
                        kernel: None,
                    },
                )?;
                match found {
                    Some(i) => {
                        all[i] = buffers;
                        i
                    }
                    None => {
                        all.push(buffers);
                        all.len() - 1
                    }
                }
            }
        };
        let buffers = &mut all[index];
        let mut gpu_ns = (timed && gpu.has_timestamps()).then_some(0u64);
        for chunk in points.chunks(buffers.capacity() as usize) {
            let ticket = self.submit_query_timed(gpu, buffers, chunk, timed)?;
            take(&buffers.wait(gpu, ticket)?);
            if let Some(ns) = gpu_ns.as_mut() {
                *ns += self.read_query_ns(gpu)?.unwrap_or(0);
            }
        }
        Ok(gpu_ns)
    }

    /// Signed distances at `points` (mesh coordinates, mesh units) on CPU threads, for machines
    /// without a GPU and for physics or path-planning code. Agrees with [`NeuralSdf::eval`].
    pub fn eval_cpu(&self, points: &[Vec3]) -> Vec<f32> {
        let n = self.normalization;
        let local = self.normalized_points(points);
        self.eval_cpu_normalized(&local)
            .into_iter()
            .map(|d| n.distance_to_original(d))
            .collect()
    }

    /// Signed distances at normalised `points` on CPU threads, in normalised units.
    pub fn eval_cpu_normalized(&self, points: &[Vec3]) -> Vec<f32> {
        let (clamped, outside) = clamp_to_box(points);
        let d = match &self.network {
            Network::Siren(s) => s.eval_cpu(&clamped),
            Network::Nglod(m) => m
                .eval_cpu(&clamped, self.lod)
                .expect("lod was validated by set_lod"),
        };
        d.into_iter().zip(outside).map(|(d, o)| d + o).collect()
    }

    /// Distances and unit normals on CPU threads (mesh coordinates and units).
    pub fn eval_with_normals_cpu(&self, points: &[Vec3]) -> Vec<(f32, Vec3)> {
        let n = self.normalization;
        let local = self.normalized_points(points);
        let (clamped, outside) = clamp_to_box(&local);
        let raw: Vec<(f32, Vec3)> = match &self.network {
            Network::Siren(s) => s.eval_with_gradient_cpu(&clamped),
            Network::Nglod(m) => {
                let d = m.eval_cpu(&clamped, self.lod).expect("lod was validated");
                let g = m
                    .gradient_cpu(&clamped, self.lod)
                    .expect("lod was validated");
                d.into_iter().zip(g).collect()
            }
        };
        raw.into_iter()
            .zip(local.iter().zip(&clamped).zip(outside))
            .map(|((d, g), ((p, c), o))| (n.distance_to_original(d + o), outward_normal(g, *p, *c)))
            .collect()
    }

    /// Runs `f` on this model's GPU network for `gpu`'s device (and its timer, where the device
    /// has timestamp queries), creating them on first use (or when called with another device).
    pub(crate) fn with_gpu<T>(
        &self,
        gpu: &GpuContext,
        f: impl FnOnce(&mut GpuNetwork, Option<&GpuTimer>) -> Result<T, NeuralSdfError>,
    ) -> Result<T, NeuralSdfError> {
        let mut slot = self.gpu.lock().unwrap_or_else(|e| e.into_inner());
        let stale = !matches!(&*slot, Some(side) if side.device == *gpu.device());
        if stale {
            let network = match &self.network {
                Network::Siren(s) => {
                    let options = SirenGpuOptions {
                        kernels: self.siren_kernels,
                        ..SirenGpuOptions::default()
                    };
                    let coop = self.siren_coop_min_points;
                    let net = SirenGpu::new_frozen(gpu, s, &options, coop)?;
                    GpuNetwork::Siren(Box::new(net))
                }
                Network::Nglod(m) => GpuNetwork::Nglod(Box::new(NglodGpu::new_frozen(gpu, m)?)),
            };
            *slot = Some(GpuSide {
                device: gpu.device().clone(),
                network,
                timer: GpuTimer::new(gpu),
            });
        }
        let side = slot.as_mut().expect("filled above");
        f(&mut side.network, side.timer.as_ref())
    }
}

/// A fresh model identity (see [`NeuralSdf::set_siren_kernels`]).
fn next_id() -> u64 {
    static NEXT: AtomicU64 = AtomicU64::new(0);
    NEXT.fetch_add(1, Ordering::Relaxed)
}

/// Points clamped to `[-1, 1]³`, and each point's distance to its clamped copy.
fn clamp_to_box(points: &[Vec3]) -> (Vec<Vec3>, Vec<f32>) {
    points
        .par_iter()
        .map(|&p| {
            let c = p.clamp(Vec3::NEG_ONE, Vec3::ONE);
            (c, p.distance(c))
        })
        .unzip()
}

/// The unit normal for the extended distance: the model's gradient inside the box, and outside
/// it the direction away from the box (the gradient of the distance-to-box term dominates there).
fn outward_normal(gradient: Vec3, p: Vec3, clamped: Vec3) -> Vec3 {
    let away = p - clamped;
    if away != Vec3::ZERO {
        away.normalize()
    } else {
        gradient.normalize_or_zero()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nglod::NglodConfig;
    use crate::siren::SirenConfig;

    /// A model far from the origin for its size (its centre 10⁷ + ½, not an f32) answers on
    /// the GPU as on the CPU, distances and normals: the kernels' f32 centre put every point
    /// half a unit off (a distance 0.5 wrong).
    #[test]
    fn a_far_model_answers_on_the_gpu_as_on_the_cpu() {
        let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
        let sphere = Nglod::from_sdf(16, |p| p.length() - 0.5).unwrap();
        let normalization = Normalization {
            center: glam::DVec3::new(1e7 + 0.5, 0.0, 0.0),
            scale: 0.5,
        };
        assert!(normalization.is_far());
        let file = sphere.to_model_file(normalization, serde_json::Value::Null);
        let sdf = NeuralSdf::from_model_file(file).unwrap();
        // Whole numbers near 10⁷ are f32s; the sphere (radius 1) is centred half-way between
        // two of them, so its distance at 10⁷ + k is |k − ½| − 1.
        let ks = [-2.0f32, -1.0, 0.0, 1.0, 2.0, 3.0];
        let points: Vec<Vec3> = ks.iter().map(|&k| Vec3::new(1e7 + k, 0.0, 0.0)).collect();
        let cpu = sdf.eval_cpu(&points);
        let cpu_normals = sdf.eval_with_normals_cpu(&points);
        let on_gpu = sdf.eval(gpu, &points).unwrap();
        let with_normals = sdf.eval_with_normals(gpu, &points).unwrap();
        for (i, &k) in ks.iter().enumerate() {
            let want = (k - 0.5).abs() - 1.0;
            assert!(
                (cpu[i] - want).abs() < 0.02,
                "{k}: CPU {} vs {want}",
                cpu[i]
            );
            assert!(
                (on_gpu[i] - cpu[i]).abs() < 1e-4,
                "{k}: {} vs {}",
                on_gpu[i],
                cpu[i]
            );
            let ((d, n), (_, cpu_n)) = (with_normals[i], cpu_normals[i]);
            assert!((d - cpu[i]).abs() < 1e-4, "{k}: {d} vs {}", cpu[i]);
            assert!(
                n.distance(cpu_n) < 1e-4 && n.x * (k - 0.5) > 0.0,
                "{k}: {n} vs {cpu_n}"
            );
        }
    }

    /// Model files that read fine but hold no valid model: every error of `load` names the file
    /// once, at the start (it used to begin with an empty path, `: metadata ...`).
    #[test]
    fn load_errors_name_the_file() {
        let dir = std::env::temp_dir().join(format!("hwsdf-neural-load-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let n = Normalization::identity();
        let siren = Siren::new(SirenConfig::small(), 1)
            .unwrap()
            .to_model_file(n, serde_json::Value::Null);
        let nglod = Nglod::new(NglodConfig::small())
            .unwrap()
            .to_model_file(n, serde_json::Value::Null);
        let edit = |f: &ModelFile, e: &dyn Fn(&mut ModelFile)| {
            let mut f = f.clone();
            e(&mut f);
            f
        };
        let config = |c: serde_json::Value| move |f: &mut ModelFile| f.metadata.config = c.clone();
        let cases: Vec<(&str, ModelFile, &str)> = vec![
            (
                "layers0",
                edit(
                    &siren,
                    &config(serde_json::json!({"width": 64, "hidden_layers": 0, "omega0": 10.0})),
                ),
                "metadata `config` is missing or invalid: SIREN needs",
            ),
            (
                "width0",
                edit(
                    &siren,
                    &config(serde_json::json!({"width": 0, "hidden_layers": 3, "omega0": 10.0})),
                ),
                "metadata `config` is missing or invalid: SIREN needs",
            ),
            (
                "omega",
                edit(
                    &siren,
                    &config(serde_json::json!({"width": 64, "hidden_layers": 3, "omega0": 1e30})),
                ),
                "omega0",
            ),
            (
                "siren_with_nglod_config",
                edit(&siren, &|f| {
                    f.metadata.config = nglod.metadata.config.clone()
                }),
                "metadata `config` is missing or invalid: ",
            ),
            (
                "shape",
                edit(&siren, &|f| {
                    let t = f
                        .tensors
                        .iter_mut()
                        .find(|t| t.name == "net.0.bias")
                        .unwrap();
                    t.shape = vec![32, 2];
                }),
                "tensor `net.0.bias` has shape [32, 2], expected [64]",
            ),
            (
                "missing",
                edit(&siren, &|f| {
                    let t = f
                        .tensors
                        .iter_mut()
                        .find(|t| t.name == "net.1.weight")
                        .unwrap();
                    t.name = "net.1.weights".into();
                }),
                "model file has no tensor `net.1.weight`",
            ),
            (
                "declared",
                edit(
                    &siren,
                    &config(
                        serde_json::json!({"width": 4096, "hidden_layers": 64, "omega0": 10.0}),
                    ),
                ),
                "the `config` metadata declares",
            ),
            (
                "architecture",
                edit(&siren, &|f| f.metadata.architecture = "tree".into()),
                "unknown architecture `tree`",
            ),
            (
                "nglod_config",
                edit(&nglod, &|f| {
                    f.metadata.config["resolutions"] = serde_json::json!([0, 4]);
                }),
                "invalid configuration: resolution 0",
            ),
            (
                "nglod_with_siren_config",
                edit(&nglod, &|f| {
                    f.metadata.config = siren.metadata.config.clone()
                }),
                "invalid configuration: model file `config` metadata",
            ),
        ];
        for (name, file, words) in cases {
            let path = dir.join(format!("{name}.safetensors"));
            file.save(&path).unwrap();
            let err = NeuralSdf::load(&path).unwrap_err();
            assert!(
                matches!(err, NeuralSdfError::InvalidModel { .. }),
                "{name}: {err:?}"
            );
            let msg = err.to_string();
            let want = format!("{}: ", path.display());
            assert!(
                msg.starts_with(&want) && !msg[want.len()..].starts_with(':'),
                "{name}: {msg}"
            );
            assert!(msg.contains(words), "{name}: {msg}");
            assert_eq!(
                msg.matches(&*path.display().to_string()).count(),
                1,
                "{msg}"
            );
            // In memory there is no file to name, and no empty one either.
            let msg = NeuralSdf::from_model_file(file).unwrap_err().to_string();
            assert!(
                !msg.starts_with(':') && msg.contains(words),
                "{name}: {msg}"
            );
        }
        // Errors of reading the file named it already: not twice.
        let path = dir.join("garbage.safetensors");
        std::fs::write(&path, b"garbage").unwrap();
        let msg = NeuralSdf::load(&path).unwrap_err().to_string();
        assert_eq!(
            msg.matches(&*path.display().to_string()).count(),
            1,
            "{msg}"
        );
        std::fs::remove_dir_all(&dir).ok();
    }
}
