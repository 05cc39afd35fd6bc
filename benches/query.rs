//! The query path a user calls, `NeuralSdf`, against what it is made of, so that a per-call
//! floor (issue 13) shows up in `cargo bench`:
//! - `roundtrip/empty`: the smallest submit and readback there is (a 40-byte copy into a
//!   persistent mappable buffer, map, wait) — the floor no readback query can go below;
//! - `nglod_<preset>/kernel`: `NglodGpu::eval` (the kernel bench's path);
//! - `nglod_<preset>/neural_sdf`: `NeuralSdf::eval_normalized`, the path the reports time for
//!   wall figures;
//! - `nglod_<preset>/neural_sdf_timed`: `NeuralSdf::eval_normalized_timed`, the separate call
//!   the reports take kernel times from;
//! - `nglod_<preset>/serve_submit_wait`: the serving API, `submit_query` then `wait`, into
//!   caller-owned buffers and a reused host vector;
//! - `nglod_<preset>/old_report_path`: the report's path before issue 13, rebuilt from the
//!   public pieces it was made of (a rayon clamp to the box, `NglodGpu::eval_timed` with its
//!   staging buffer per call, a second submission for the readback and a second wait for the
//!   timestamps), kept as the reference the floor is measured against;
//!
//! each at 10 points (where only the floor is left) and at 3000.
//!
//! The presets are NGLOD's `small` and `default` and the hash grid's `hashgrid_small` and
//! `hashgrid_default` (served by the same kernels).
//!
//! Run: `cargo bench --bench query`. `QUERY_BENCH_PRESETS=small` runs one preset,
//! `QUERY_BENCH_POINTS=1,10,64` other batch sizes (default 10 and 3000).
//!
//! On a shared, loaded machine criterion's separate runs drift with the load. Set
//! `QUERY_BENCH_INTERLEAVED=ROUNDS` to run the variants instead in turn, one call each per round,
//! so that every variant sees the same load, and print the minimum, the 10th percentile and the
//! median of each (no criterion). This mode adds rows that split a query's floor into its parts:
//! `roundtrip/upload` (the empty round trip after a `Queue::write_buffer` of the points),
//! `roundtrip/dispatch` (after one empty dispatch) and `serve_recorded` (`record_query` on points
//! already on the GPU, a copy and a readback: a query without its upload), and runs SIREN's
//! `kernel`, `neural_sdf` and `neural_sdf_timed` for the presets of
//! `QUERY_BENCH_SIREN_PRESETS=small,default` (default `small`) on the kernels of
//! `QUERY_BENCH_SIREN_KERNELS` (default `auto`; `tiled` runs the fused kernel, whose queries take
//! one dispatch, on any adapter; a list such as `tiled,coop` runs each in the same rounds, its
//! rows named after it). Both models also get `resident` (`record_query` on points already on
//! the GPU, submitted and waited for, the values left there: what PyTorch's eval of a device
//! tensor measures), and, where the device maps storage buffers (not with
//! `HWSDF_MAPPABLE_STORAGE=0`), `serve_mapped` (the serving API with `QueryTransfer::Mapped`).
//! Before them, `transfer` rows split a mapped query's host-side transfers (no kernel): see
//! `transfer_split`.
//!
//! Two more modes, instead of the above: `QUERY_BENCH_PHASES=ROUNDS` times one mapped query
//! phase by phase (`phase_split`), and `QUERY_BENCH_LATENCY=ROUNDS` how long the GPU takes to
//! answer a submission by what it holds and how long it sat idle before (`latency_split`).

use std::time::Duration;

use criterion::{BenchmarkId, Criterion, Throughput};
use glam::Vec3;
use rayon::prelude::*;
use sdf_nn::gpu::GpuTimer;
use sdf_nn::nglod::ScatterMode;
use sdf_nn::{
    GpuContext, NeuralSdf, Nglod, NglodConfig, NglodGpu, Normalization, QueryBuffers,
    QueryBuffersDescriptor, QuerySpace, QueryTransfer,
};

/// Query buffers for `n` points in the normalised cube, values only.
fn normalized_buffers(gpu: &GpuContext, sdf: &NeuralSdf, n: usize) -> QueryBuffers {
    buffers_with(gpu, sdf, n, QueryTransfer::Auto)
}

/// [`normalized_buffers`] with [`QueryTransfer::Mapped`] (no copies: the kernel reads and
/// writes mapped memory), where the device maps storage buffers.
fn mapped_buffers(gpu: &GpuContext, sdf: &NeuralSdf, n: usize) -> Option<QueryBuffers> {
    gpu.maps_storage()
        .then(|| buffers_with(gpu, sdf, n, QueryTransfer::Mapped))
}

fn buffers_with(
    gpu: &GpuContext,
    sdf: &NeuralSdf,
    n: usize,
    transfer: QueryTransfer,
) -> QueryBuffers {
    sdf.create_query_buffers(
        gpu,
        &QueryBuffersDescriptor {
            capacity: n as u32,
            space: QuerySpace::Normalized,
            transfer,
            ..Default::default()
        },
    )
    .unwrap()
}

/// The serving API's round: `submit_query` of `pts`, then `wait`, the values into `out`.
fn serve(
    gpu: &GpuContext,
    sdf: &NeuralSdf,
    buffers: &mut QueryBuffers,
    pts: &[Vec3],
    out: &mut Vec<f32>,
) {
    let ticket = sdf.submit_query(gpu, buffers, pts).unwrap();
    out.clear();
    buffers.wait(gpu, ticket).unwrap().extend_values(out);
}

/// `record_query` of the first `n` points already in `buffers`, submitted and waited for, the
/// values left on the GPU: what PyTorch's eval of a device tensor measures.
fn resident_query(gpu: &GpuContext, sdf: &NeuralSdf, buffers: &mut QueryBuffers, n: usize) {
    let mut enc = gpu.device().create_command_encoder(&Default::default());
    sdf.record_query(gpu, &mut enc, buffers, n as u32).unwrap();
    gpu.queue().submit([enc.finish()]);
    gpu.wait().unwrap();
}

/// `record_query` of the first `n` points already in `buffers`, the values read back through
/// `staging`: a query without its upload.
fn recorded_query(
    gpu: &GpuContext,
    sdf: &NeuralSdf,
    buffers: &mut QueryBuffers,
    n: usize,
    staging: &wgpu::Buffer,
) -> Vec<f32> {
    let mut enc = gpu.device().create_command_encoder(&Default::default());
    sdf.record_query(gpu, &mut enc, buffers, n as u32).unwrap();
    submit_and_read(gpu, enc, buffers.results(), staging)
}

/// Copies the start of `src` into the whole of the mappable `staging` at the end of `enc`,
/// submits, and reads `staging` back after `GpuContext::wait`: the readback every row of this
/// bench ends with.
fn submit_and_read(
    gpu: &GpuContext,
    enc: wgpu::CommandEncoder,
    src: &wgpu::Buffer,
    staging: &wgpu::Buffer,
) -> Vec<f32> {
    submit_and_read_after(gpu, enc, src, staging, || gpu.wait().unwrap())
}

/// [`submit_and_read`], waiting for the submission with `wait`.
fn submit_and_read_after(
    gpu: &GpuContext,
    mut enc: wgpu::CommandEncoder,
    src: &wgpu::Buffer,
    staging: &wgpu::Buffer,
    wait: impl FnOnce(),
) -> Vec<f32> {
    enc.copy_buffer_to_buffer(src, 0, staging, 0, staging.size());
    gpu.queue().submit([enc.finish()]);
    let slice = staging.slice(..);
    slice.map_async(wgpu::MapMode::Read, |r| r.unwrap());
    wait();
    let v: Vec<f32> = bytemuck::pod_collect_to_vec(&slice.get_mapped_range().unwrap());
    staging.unmap();
    v
}

/// A mappable buffer to read `size` bytes back into.
fn readback_buffer(gpu: &GpuContext, label: &str, size: u64) -> wgpu::Buffer {
    gpu.device().create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

/// The batch sizes of `QUERY_BENCH_POINTS` (default 10 and 3000).
fn batch_sizes() -> Vec<usize> {
    std::env::var("QUERY_BENCH_POINTS")
        .ok()
        .map(|s| s.split(',').filter_map(|n| n.trim().parse().ok()).collect())
        .filter(|v: &Vec<usize>| !v.is_empty())
        .unwrap_or_else(|| vec![10, 3000])
}

fn presets() -> Vec<(&'static str, NglodConfig)> {
    let which = std::env::var("QUERY_BENCH_PRESETS").unwrap_or_default();
    [
        ("small", NglodConfig::small()),
        ("default", NglodConfig::default_preset()),
        ("hashgrid_small", NglodConfig::hashgrid_small()),
        ("hashgrid_default", NglodConfig::hashgrid_default()),
    ]
    .into_iter()
    .filter(|(n, _)| which.is_empty() || which.split(',').any(|w| w == *n))
    .collect()
}

/// A submit of one 40-byte copy and its readback through a persistent mappable buffer, waited
/// for by `GpuContext::wait` and by a plain blocking wait.
fn empty_roundtrip(c: &mut Criterion, gpu: &GpuContext) {
    let src = gpu.storage_zeroed("bench src", 40).unwrap();
    let staging = readback_buffer(gpu, "bench staging", 40);
    let mut g = c.benchmark_group("roundtrip");
    g.sample_size(20)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(3));
    g.bench_function("empty", |b| {
        b.iter(|| {
            let enc = gpu.device().create_command_encoder(&Default::default());
            submit_and_read(gpu, enc, &src, &staging)
        })
    });
    // The same with a plain blocking wait, as `GpuContext::wait` did before it polled first
    // (`SPIN_WAIT`): how much of the round trip is the blocking wait's wake-up.
    g.bench_function("empty_blocking", |b| {
        b.iter(|| {
            let enc = gpu.device().create_command_encoder(&Default::default());
            submit_and_read_after(gpu, enc, &src, &staging, || {
                gpu.device()
                    .poll(wgpu::PollType::wait_indefinitely())
                    .unwrap();
            })
        })
    });
    g.finish();
}

/// An NGLOD model of `cfg` and the `NeuralSdf` serving it (identity normalisation). A sparse
/// level holds the band around a sphere of about a real mesh's size.
fn nglod_model(cfg: NglodConfig) -> (Nglod, NeuralSdf) {
    let mut model = Nglod::new(cfg).unwrap();
    if model.needs_bands() {
        model.place_bands(|p| (p.length() - 0.6).abs()).unwrap();
    }
    let sdf = NeuralSdf::from_model_file(
        model.to_model_file(Normalization::identity(), serde_json::Value::Null),
    )
    .unwrap();
    (model, sdf)
}

/// The `NeuralSdf` serving `siren` (identity normalisation).
fn siren_sdf(siren: &sdf_nn::Siren) -> NeuralSdf {
    NeuralSdf::from_model_file(
        siren.to_model_file(Normalization::identity(), serde_json::Value::Null),
    )
    .unwrap()
}

/// A dispatch that does nothing (query.wgsl's `prepare` with a point count of 0) and its bind
/// group: one kernel launch without work.
fn empty_dispatch(gpu: &GpuContext) -> (wgpu::ComputePipeline, wgpu::BindGroup) {
    let pipeline = gpu
        .pipeline(&sdf_nn::shaders::QUERY, "prepare", &[])
        .unwrap();
    let u = gpu.uniform("bench empty uniforms", &[0u32; 8]);
    let (p, q) = (
        gpu.storage_zeroed("bench p", 16).unwrap(),
        gpu.storage_zeroed("bench q", 12).unwrap(),
    );
    let entries = [(0, &u), (1, &p), (2, &q)].map(|(binding, b)| wgpu::BindGroupEntry {
        binding,
        resource: b.as_entire_binding(),
    });
    let group = gpu.device().create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("bench empty"),
        layout: &pipeline.get_bind_group_layout(0),
        entries: &entries,
    });
    (pipeline, group)
}

/// Asks for `slice`'s mapping; the flag turns true once its callback has run.
fn request_map(
    slice: wgpu::BufferSlice<'_>,
    mode: wgpu::MapMode,
) -> std::sync::Arc<std::sync::atomic::AtomicBool> {
    use std::sync::atomic::{AtomicBool, Ordering};
    let done = std::sync::Arc::new(AtomicBool::new(false));
    let flag = std::sync::Arc::clone(&done);
    slice.map_async(mode, move |r| flag.store(r.is_ok(), Ordering::Release));
    done
}

/// Polls `gpu` until `done`; returns the number of polls.
fn poll_until(gpu: &GpuContext, done: &std::sync::atomic::AtomicBool) -> u32 {
    let mut polls = 0;
    while !done.load(std::sync::atomic::Ordering::Acquire) {
        gpu.device().poll(wgpu::PollType::Poll).unwrap();
        polls += 1;
    }
    polls
}

fn nglod(c: &mut Criterion, gpu: &GpuContext) {
    for (name, cfg) in presets() {
        let (model, sdf) = nglod_model(cfg);
        let net = NglodGpu::new(gpu, &model, ScatterMode::Auto).unwrap();
        let mut g = c.benchmark_group(format!("nglod_{name}"));
        g.sample_size(20)
            .warm_up_time(Duration::from_secs(1))
            .measurement_time(Duration::from_secs(3));
        for n in batch_sizes() {
            let pts: Vec<Vec3> = sdf_geom::sample::uniform_box(n, 42);
            // Compile and allocate outside the timing.
            net.eval(gpu, &pts, None).unwrap();
            sdf.eval_normalized(gpu, &pts).unwrap();
            g.throughput(Throughput::Elements(n as u64));
            g.bench_with_input(BenchmarkId::new("kernel", n), &pts, |b, pts| {
                b.iter(|| net.eval(gpu, pts, None).unwrap())
            });
            g.bench_with_input(BenchmarkId::new("neural_sdf", n), &pts, |b, pts| {
                b.iter(|| sdf.eval_normalized(gpu, pts).unwrap())
            });
            g.bench_with_input(BenchmarkId::new("neural_sdf_timed", n), &pts, |b, pts| {
                b.iter(|| sdf.eval_normalized_timed(gpu, pts).unwrap())
            });
            let mut buffers = normalized_buffers(gpu, &sdf, n);
            let mut out = Vec::with_capacity(n);
            g.bench_with_input(BenchmarkId::new("serve_submit_wait", n), &pts, |b, pts| {
                b.iter(|| serve(gpu, &sdf, &mut buffers, pts, &mut out))
            });
            if let Some(timer) = GpuTimer::new(gpu) {
                g.bench_with_input(BenchmarkId::new("old_report_path", n), &pts, |b, pts| {
                    b.iter(|| old_report_path(gpu, &net, &timer, pts))
                });
            }
        }
        g.finish();
    }
}

/// `NeuralSdf::eval_normalized_timed` as it was at ff1c4ae for NGLOD (see the module docs).
fn old_report_path(
    gpu: &GpuContext,
    net: &NglodGpu,
    timer: &GpuTimer,
    points: &[Vec3],
) -> (Vec<f32>, u64) {
    let (clamped, outside): (Vec<Vec3>, Vec<f32>) = points
        .par_iter()
        .map(|&p| {
            let c = p.clamp(Vec3::NEG_ONE, Vec3::ONE);
            (c, p.distance(c))
        })
        .unzip();
    let (mut d, ns) = net.eval_timed(gpu, &clamped, None, timer).unwrap();
    for (d, o) in d.iter_mut().zip(outside) {
        *d += o;
    }
    (d, ns)
}

/// A named call to time.
type Variant<'a> = (String, Box<dyn FnMut() + 'a>);

/// The variants in turn, `rounds` calls each (see the module docs).
fn interleaved(gpu: &GpuContext, rounds: usize) {
    let src = gpu.storage_zeroed("bench src", 40).unwrap();
    let staging = readback_buffer(gpu, "bench staging", 40);
    let timer = GpuTimer::new(gpu);
    // A launch without work, to split a query's cost into the submit+readback, one kernel
    // launch, and the kernel's work.
    let (empty_pipeline, empty_group) = empty_dispatch(gpu);
    for (name, cfg) in presets() {
        let (model, sdf) = nglod_model(cfg);
        let net = NglodGpu::new(gpu, &model, ScatterMode::Auto).unwrap();
        for n in batch_sizes() {
            let pts: Vec<Vec3> = sdf_geom::sample::uniform_box(n, 42);
            let mut buffers = normalized_buffers(gpu, &sdf, n);
            let mut out = Vec::with_capacity(n);
            let host: Vec<[f32; 4]> = pts.iter().map(|p| [p.x, p.y, p.z, 1.0]).collect();
            let upload_dst = gpu.storage_zeroed("bench upload", n as u64 * 16).unwrap();
            let mut resident = normalized_buffers(gpu, &sdf, n);
            resident.upload(gpu, &pts).unwrap();
            let resident_staging = readback_buffer(gpu, "bench resident staging", n as u64 * 4);
            let mut resident_only = normalized_buffers(gpu, &sdf, n);
            resident_only.upload(gpu, &pts).unwrap();
            let mut mapped = mapped_buffers(gpu, &sdf, n);
            let mut mapped_out = Vec::with_capacity(n);
            // The floor of any query: one submission (with or without one empty dispatch) and
            // the readback of 10 floats.
            let roundtrip = |dispatch: bool| {
                let mut enc = gpu.device().create_command_encoder(&Default::default());
                if dispatch {
                    let mut pass = enc.begin_compute_pass(&Default::default());
                    pass.set_pipeline(&empty_pipeline);
                    pass.set_bind_group(0, &empty_group, &[]);
                    pass.dispatch_workgroups(1, 1, 1);
                }
                std::hint::black_box(submit_and_read(gpu, enc, &src, &staging));
            };
            let mut variants: Vec<Variant<'_>> = vec![
                ("roundtrip/empty".into(), Box::new(|| roundtrip(false))),
                (
                    "roundtrip/upload".into(),
                    Box::new(|| {
                        gpu.queue()
                            .write_buffer(&upload_dst, 0, bytemuck::cast_slice(&host));
                        roundtrip(false)
                    }),
                ),
                ("roundtrip/dispatch".into(), Box::new(|| roundtrip(true))),
                (
                    "serve_recorded".into(),
                    Box::new(|| {
                        std::hint::black_box(recorded_query(
                            gpu,
                            &sdf,
                            &mut resident,
                            n,
                            &resident_staging,
                        ));
                    }),
                ),
                (
                    "resident".into(),
                    Box::new(|| resident_query(gpu, &sdf, &mut resident_only, n)),
                ),
                (
                    "kernel".into(),
                    Box::new(|| {
                        std::hint::black_box(net.eval(gpu, &pts, None).unwrap());
                    }),
                ),
                (
                    "neural_sdf".into(),
                    Box::new(|| {
                        std::hint::black_box(sdf.eval_normalized(gpu, &pts).unwrap());
                    }),
                ),
                (
                    "neural_sdf_timed".into(),
                    Box::new(|| {
                        std::hint::black_box(sdf.eval_normalized_timed(gpu, &pts).unwrap());
                    }),
                ),
                (
                    "serve_submit_wait".into(),
                    Box::new(|| serve(gpu, &sdf, &mut buffers, &pts, &mut out)),
                ),
            ];
            if let Some(m) = mapped.as_mut() {
                variants.push((
                    "serve_mapped".into(),
                    Box::new(|| serve(gpu, &sdf, m, &pts, &mut mapped_out)),
                ));
            }
            if let Some(t) = &timer {
                variants.push((
                    "old_report_path".into(),
                    Box::new(|| {
                        std::hint::black_box(old_report_path(gpu, &net, t, &pts));
                    }),
                ));
            }
            report_interleaved(&format!("nglod_{name} n={n:5}"), &mut variants, rounds);
        }
    }
}

/// The SIREN presets of the interleaved mode: `QUERY_BENCH_SIREN_PRESETS=small,default`
/// (default `small`; issue 13's SIREN target is on `default`).
fn siren_presets() -> Vec<(&'static str, sdf_nn::SirenConfig)> {
    let list = std::env::var("QUERY_BENCH_SIREN_PRESETS").unwrap_or_else(|_| "small".into());
    let mut out = Vec::new();
    for name in list.split(',').map(str::trim) {
        match name {
            "small" => out.push(("small", sdf_nn::SirenConfig::small())),
            "default" => out.push(("default", sdf_nn::SirenConfig::default())),
            other => panic!("QUERY_BENCH_SIREN_PRESETS: unknown preset {other:?}"),
        }
    }
    out
}

/// SIREN, each preset of [`siren_presets`]: its kernel path (`SirenGpu::eval`) against
/// `NeuralSdf`'s wall path and timed call, in turn like [`interleaved`] (the SIREN
/// target: the wall path adds at most 50 µs to the kernel time).
fn interleaved_siren(gpu: &GpuContext, rounds: usize) {
    for (name, config) in siren_presets() {
        interleaved_siren_preset(gpu, rounds, name, config);
    }
}

/// The SIREN kernels of the interleaved mode: `QUERY_BENCH_SIREN_KERNELS=tiled,coop` (default
/// `auto`); with more than one, each row is named after its kernels and they run in turn in the
/// same rounds.
fn siren_kernels() -> Vec<sdf_nn::siren::LayerKernels> {
    std::env::var("QUERY_BENCH_SIREN_KERNELS")
        .unwrap_or_else(|_| "auto".into())
        .split(',')
        .map(|k| {
            k.trim()
                .parse()
                .unwrap_or_else(|e| panic!("QUERY_BENCH_SIREN_KERNELS: {e}"))
        })
        .collect()
}

/// One SIREN network behind every path the interleaved mode times, on one kernel family.
struct SirenPaths {
    name: String,
    net: sdf_nn::SirenGpu,
    sdf: NeuralSdf,
}

fn interleaved_siren_preset(
    gpu: &GpuContext,
    rounds: usize,
    preset: &str,
    config: sdf_nn::SirenConfig,
) {
    let siren = sdf_nn::Siren::new(config, 1).unwrap();
    let kernels = siren_kernels();
    let mut paths: Vec<SirenPaths> = kernels
        .iter()
        .map(|&k| {
            let options = sdf_nn::siren::SirenGpuOptions {
                kernels: k,
                ..Default::default()
            };
            let net = sdf_nn::SirenGpu::with_options(gpu, &siren, &options).unwrap();
            let mut sdf = siren_sdf(&siren);
            sdf.set_siren_kernels(k).unwrap();
            let name = if kernels.len() > 1 {
                format!("{}/", k.name())
            } else {
                String::new()
            };
            SirenPaths { name, net, sdf }
        })
        .collect();
    for n in batch_sizes() {
        let pts: Vec<Vec3> = sdf_geom::sample::uniform_box(n, 42);
        let mut gpu_ns: Vec<Vec<f64>> = vec![Vec::with_capacity(rounds); paths.len()];
        let mut variants: Vec<Variant<'_>> = Vec::new();
        for (p, ns) in paths.iter_mut().zip(gpu_ns.iter_mut()) {
            let (name, net, sdf) = (&p.name, &mut p.net, &p.sdf);
            let mut staged = normalized_buffers(gpu, sdf, n);
            let mut resident = normalized_buffers(gpu, sdf, n);
            resident.upload(gpu, &pts).unwrap();
            let mut resident_only = normalized_buffers(gpu, sdf, n);
            resident_only.upload(gpu, &pts).unwrap();
            let resident_staging = readback_buffer(gpu, "bench resident staging", n as u64 * 4);
            let mapped = mapped_buffers(gpu, sdf, n);
            let pts = &pts;
            variants.push((
                format!("{name}kernel"),
                Box::new(move || {
                    std::hint::black_box(net.eval(gpu, pts).unwrap());
                }),
            ));
            variants.push((
                format!("{name}neural_sdf"),
                Box::new(move || {
                    std::hint::black_box(sdf.eval_normalized(gpu, pts).unwrap());
                }),
            ));
            variants.push((
                format!("{name}neural_sdf_timed"),
                Box::new(move || {
                    let (v, t) = sdf.eval_normalized_timed(gpu, pts).unwrap();
                    ns.extend(t.map(|t| t as f64 / 1e3));
                    std::hint::black_box(v);
                }),
            ));
            let mut out = Vec::with_capacity(n);
            variants.push((
                format!("{name}serve_submit_wait"),
                Box::new(move || serve(gpu, sdf, &mut staged, pts, &mut out)),
            ));
            // Points already on the GPU, the values read back: a query without its upload.
            variants.push((
                format!("{name}serve_recorded"),
                Box::new(move || {
                    std::hint::black_box(recorded_query(
                        gpu,
                        sdf,
                        &mut resident,
                        n,
                        &resident_staging,
                    ));
                }),
            ));
            variants.push((
                format!("{name}resident"),
                Box::new(move || resident_query(gpu, sdf, &mut resident_only, n)),
            ));
            if let Some(mut m) = mapped {
                let mut out = Vec::with_capacity(n);
                variants.push((
                    format!("{name}serve_mapped"),
                    Box::new(move || serve(gpu, sdf, &mut m, pts, &mut out)),
                ));
            }
        }
        report_interleaved(&format!("siren_{preset} n={n:5}"), &mut variants, rounds);
        drop(variants);
        for (p, ns) in paths.iter().zip(gpu_ns.iter_mut()) {
            if !ns.is_empty() {
                ns.sort_by(f64::total_cmp);
                println!(
                    "siren_{preset} n={n:5} {}kernel time (timestamps) median {:8.1} µs",
                    p.name,
                    ns[ns.len() / 2]
                );
            }
        }
    }
}

/// Runs `variants` in turn `rounds` times after one untimed call each and prints min, p10 and
/// median per variant.
fn report_interleaved(prefix: &str, variants: &mut [Variant<'_>], rounds: usize) {
    let mut times: Vec<Vec<f64>> = vec![Vec::with_capacity(rounds); variants.len()];
    for (_, f) in variants.iter_mut() {
        f(); // compile and allocate outside the timing
    }
    for _ in 0..rounds {
        for ((_, f), t) in variants.iter_mut().zip(&mut times) {
            let start = std::time::Instant::now();
            f();
            t.push(start.elapsed().as_secs_f64() * 1e6);
        }
    }
    for ((v, _), t) in variants.iter().zip(&mut times) {
        print_quantiles(&format!("{prefix} {v:24}"), t);
    }
}

/// Prints `label`, then the minimum, 10th percentile and median of the microseconds in `t`
/// (sorted in place): the line every interleaved row is.
fn print_quantiles(label: &str, t: &mut [f64]) {
    t.sort_by(f64::total_cmp);
    println!(
        "{label} min {:8.1} µs  p10 {:8.1} µs  median {:8.1} µs",
        t[0],
        t[t.len() / 10],
        t[t.len() / 2]
    );
}

/// Where a mapped query's transfers spend their time, without a kernel, on buffers made as
/// `QueryTransfer::Mapped` makes them (points `STORAGE | COPY_DST | MAP_WRITE`, on a discrete
/// GPU write-combined device memory across the bus; results `STORAGE | COPY_SRC | MAP_READ`):
/// - `map_write_cycle`: the points mapped for writing (polled until mapped) and unmapped;
/// - `pack_host`: the points padded to vec4 into a host vector;
/// - `memcpy_mapped`: that vector copied into the mapped points in one `memcpy` (uploads
///   before session 20 did both);
/// - `write_mapped`: the points written into the mapped points by `sdf_nn::serve::query::write_points`,
///   one 16-byte store each (what uploads do now);
/// - `read_mapped`: the mapped results (one float per point) read into a host vector.
fn transfer_split(gpu: &GpuContext, rounds: usize) {
    use std::time::Instant;
    if !gpu.maps_storage() {
        println!("transfer split: this device does not map storage buffers");
        return;
    }
    let map = |buffer: &wgpu::Buffer, mode: wgpu::MapMode| {
        poll_until(gpu, &request_map(buffer.slice(..), mode));
    };
    let mut sizes = batch_sizes();
    sizes.push(50_000);
    for n in sizes {
        let pts: Vec<Vec3> = sdf_geom::sample::uniform_box(n, 42);
        let buffer = |label, size, usage| {
            gpu.device().create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage: wgpu::BufferUsages::STORAGE | usage,
                mapped_at_creation: false,
            })
        };
        let points = buffer(
            "bench mapped points",
            n as u64 * 16,
            wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_WRITE,
        );
        let results = buffer(
            "bench mapped results",
            n as u64 * 4,
            wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::MAP_READ,
        );
        let names = [
            "map_write_cycle",
            "pack_host",
            "memcpy_mapped",
            "write_mapped",
            "read_mapped",
        ];
        let mut times: Vec<Vec<f64>> = vec![Vec::with_capacity(rounds); names.len()];
        let mut host: Vec<[f32; 4]> = Vec::with_capacity(n);
        let mut out: Vec<f32> = Vec::with_capacity(n);
        let mut timed = |i: usize, f: &mut dyn FnMut()| {
            let start = Instant::now();
            f();
            times[i].push(start.elapsed().as_secs_f64() * 1e6);
        };
        for _ in 0..=rounds {
            timed(0, &mut || {
                map(&points, wgpu::MapMode::Write);
                points.unmap();
            });
            map(&points, wgpu::MapMode::Write);
            timed(1, &mut || {
                host.clear();
                host.extend(pts.iter().map(|p| [p.x, p.y, p.z, 1.0]));
            });
            timed(2, &mut || {
                let mut view = points.slice(..).get_mapped_range_mut().unwrap();
                view.copy_from_slice(bytemuck::cast_slice(&host));
            });
            timed(3, &mut || {
                let mut view = points.slice(..).get_mapped_range_mut().unwrap();
                sdf_nn::serve::query::write_points(view.slice(..), &pts);
            });
            points.unmap();
            map(&results, wgpu::MapMode::Read);
            timed(4, &mut || {
                out.clear();
                out.extend_from_slice(bytemuck::cast_slice(
                    &results.slice(..).get_mapped_range().unwrap(),
                ));
            });
            results.unmap();
        }
        for (name, t) in names.iter().zip(&mut times) {
            t.remove(0); // the first round maps and faults pages in
            print_quantiles(&format!("transfer n={n:6} {name:16}"), t);
        }
    }
}

/// Where one mapped query's wall time goes, phase by phase (`QUERY_BENCH_PHASES=ROUNDS`, on
/// the presets of `QUERY_BENCH_PRESETS` and `QUERY_BENCH_SIREN_PRESETS` and the batch sizes of
/// `QUERY_BENCH_POINTS`): the serving API's mapped round rebuilt from its public pieces with a
/// clock read between them (map the points, write them, encode, submit, ask for the results'
/// mapping, wait for it by polling, read, unmap); beside it the same round waited for with a
/// blocking wait, `resident` (encode, submit and wait for a query on device-local buffers, no
/// transfers), an empty submission waited for, and one idle `poll`. Then, in separate rounds,
/// the GPU time of the query's passes (timestamps around them) on the mapped buffers and on the
/// device-local ones: whether a kernel that reads and writes mapped memory runs slower.
fn phase_split(gpu: &GpuContext, rounds: usize) {
    use std::time::Instant;
    if !gpu.maps_storage() {
        println!("phase split: this device does not map storage buffers");
        return;
    }
    let mut models: Vec<(String, NeuralSdf)> = Vec::new();
    for (name, cfg) in presets() {
        models.push((format!("nglod_{name}"), nglod_model(cfg).1));
    }
    for (name, cfg) in siren_presets() {
        let siren = sdf_nn::Siren::new(cfg, 1).unwrap();
        models.push((format!("siren_{name}"), siren_sdf(&siren)));
    }
    let spin = |done: &std::sync::atomic::AtomicBool| poll_until(gpu, done);
    let spin_idle = || {
        let mut polls = 0u32;
        while !gpu
            .device()
            .poll(wgpu::PollType::Poll)
            .unwrap()
            .is_queue_empty()
        {
            polls += 1;
        }
        polls
    };
    for (name, sdf) in &models {
        for n in batch_sizes() {
            let pts: Vec<Vec3> = sdf_geom::sample::uniform_box(n, 42);
            let mut mapped = mapped_buffers(gpu, sdf, n).unwrap();
            let mut resident = buffers_with(gpu, sdf, n, QueryTransfer::Staged);
            resident.upload(gpu, &pts).unwrap();
            let (point_bytes, result_bytes) = (n as u64 * 16, n as u64 * 4);
            // The points written into the mapped points buffer, which is then unmapped.
            let write = |buffers: &QueryBuffers| {
                {
                    let slice = buffers.points().slice(..point_bytes);
                    let mut view = slice.get_mapped_range_mut().unwrap();
                    sdf_nn::serve::query::write_points(view.slice(..), &pts);
                }
                buffers.points().unmap();
            };
            // The mapped results read into `out`.
            let read = |buffers: &QueryBuffers, out: &mut Vec<f32>| {
                out.clear();
                out.extend_from_slice(bytemuck::cast_slice(
                    &buffers
                        .results()
                        .slice(..result_bytes)
                        .get_mapped_range()
                        .unwrap(),
                ));
            };
            let names = [
                "map_points",
                "write_points",
                "encode",
                "submit",
                "map_request",
                "wait (polls)",
                "read",
                "unmap",
                "total",
                "blocking: wait",
                "blocking: total",
                "resident: encode",
                "resident: submit",
                "resident: wait",
                "resident: total",
                "empty: submit+wait",
                "idle poll",
            ];
            let mut t: Vec<Vec<f64>> = vec![Vec::with_capacity(rounds); names.len()];
            let mut polls: Vec<f64> = Vec::with_capacity(rounds);
            let mut out: Vec<f32> = Vec::with_capacity(n);
            let us = |a: Instant, b: Instant| (b - a).as_secs_f64() * 1e6;
            // One mapped round; its clock readings (start, then after each phase).
            let mut mapped_round = |mapped: &mut QueryBuffers, blocking: bool| {
                let mut c = [Instant::now(); 9];
                let done = request_map(mapped.points().slice(..point_bytes), wgpu::MapMode::Write);
                spin(&done);
                c[1] = Instant::now();
                write(mapped);
                c[2] = Instant::now();
                let mut enc = gpu.device().create_command_encoder(&Default::default());
                sdf.record_query(gpu, &mut enc, mapped, n as u32).unwrap();
                let cmd = enc.finish();
                c[3] = Instant::now();
                let index = gpu.queue().submit([cmd]);
                c[4] = Instant::now();
                let done = request_map(mapped.results().slice(..result_bytes), wgpu::MapMode::Read);
                c[5] = Instant::now();
                let p = if blocking {
                    gpu.device()
                        .poll(wgpu::PollType::Wait {
                            submission_index: Some(index),
                            timeout: None,
                        })
                        .unwrap();
                    spin(&done)
                } else {
                    spin(&done)
                };
                c[6] = Instant::now();
                read(mapped, &mut out);
                c[7] = Instant::now();
                mapped.results().unmap();
                c[8] = Instant::now();
                (c, p)
            };
            // The same round with its command buffer encoded during the previous round's wait
            // (while the points are mapped): what a server that keeps the next submission
            // ready would see. Its clock: start, after writing, submit, wait, read and unmap.
            let mut next: Option<wgpu::CommandBuffer> = None;
            let mut pipelined_round = |sdf: &NeuralSdf, mapped: &mut QueryBuffers| {
                let c0 = Instant::now();
                spin(&request_map(
                    mapped.points().slice(..point_bytes),
                    wgpu::MapMode::Write,
                ));
                write(mapped);
                let cmd = next.take().unwrap_or_else(|| {
                    let mut enc = gpu.device().create_command_encoder(&Default::default());
                    sdf.record_query(gpu, &mut enc, mapped, n as u32).unwrap();
                    enc.finish()
                });
                gpu.queue().submit([cmd]);
                let c1 = Instant::now();
                let done = request_map(mapped.results().slice(..result_bytes), wgpu::MapMode::Read);
                let mut enc = gpu.device().create_command_encoder(&Default::default());
                sdf.record_query(gpu, &mut enc, mapped, n as u32).unwrap();
                next = Some(enc.finish());
                let c2 = Instant::now();
                spin(&done);
                let c3 = Instant::now();
                let mut out = Vec::with_capacity(n);
                read(mapped, &mut out);
                mapped.results().unmap();
                let c4 = Instant::now();
                std::hint::black_box(out);
                (us(c0, c1), us(c1, c2), us(c2, c3), us(c0, c4))
            };
            let mut piped: [Vec<f64>; 4] = Default::default();
            for round in 0..=rounds {
                let (c, p) = mapped_round(&mut mapped, false);
                let (b, _) = mapped_round(&mut mapped, true);
                let pr = pipelined_round(sdf, &mut mapped);
                if round > 0 {
                    for (v, x) in piped.iter_mut().zip([pr.0, pr.1, pr.2, pr.3]) {
                        v.push(x);
                    }
                }
                let e0 = Instant::now();
                let mut enc = gpu.device().create_command_encoder(&Default::default());
                sdf.record_query(gpu, &mut enc, &mut resident, n as u32)
                    .unwrap();
                let cmd = enc.finish();
                let e1 = Instant::now();
                gpu.queue().submit([cmd]);
                let e2 = Instant::now();
                spin_idle();
                let e3 = Instant::now();
                let enc = gpu.device().create_command_encoder(&Default::default());
                gpu.queue().submit([enc.finish()]);
                spin_idle();
                let e4 = Instant::now();
                gpu.device().poll(wgpu::PollType::Poll).unwrap();
                let e5 = Instant::now();
                if round == 0 {
                    continue; // the first round compiles and faults pages in
                }
                for i in 0..8 {
                    t[i].push(us(c[i], c[i + 1]));
                }
                t[8].push(us(c[0], c[8]));
                t[9].push(us(b[5], b[6]));
                t[10].push(us(b[0], b[8]));
                t[11].push(us(e0, e1));
                t[12].push(us(e1, e2));
                t[13].push(us(e2, e3));
                t[14].push(us(e0, e3));
                t[15].push(us(e3, e4));
                t[16].push(us(e4, e5));
                polls.push(f64::from(p));
            }
            for (label, t) in names.iter().zip(&mut t) {
                print_quantiles(&format!("phases {name} n={n:5} {label:20}"), t);
            }
            for (label, t) in [
                "pre-encoded: to submit",
                "pre-encoded: next enc",
                "pre-encoded: wait",
                "pre-encoded: total",
            ]
            .iter()
            .zip(&mut piped)
            {
                print_quantiles(&format!("phases {name} n={n:5} {label:20}"), t);
            }
            polls.sort_by(f64::total_cmp);
            println!(
                "phases {name} n={n:5} polls while waiting: median {}",
                polls[polls.len() / 2]
            );
            // The GPU time of the query's passes on either buffers, timestamps around them.
            if let Some(timer) = GpuTimer::new(gpu) {
                for (what, buffers) in [("mapped", &mut mapped), ("device-local", &mut resident)] {
                    if what == "mapped" {
                        let slice = buffers.points().slice(..point_bytes);
                        spin(&request_map(slice, wgpu::MapMode::Write));
                        write(buffers);
                    }
                    let mut ns: Vec<f64> = Vec::with_capacity(rounds);
                    for _ in 0..rounds.clamp(1, 200) {
                        let mut enc = gpu.device().create_command_encoder(&Default::default());
                        drop(enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                            label: Some("bench stamp start"),
                            timestamp_writes: Some(timer.writes(true, false)),
                        }));
                        sdf.record_query(gpu, &mut enc, buffers, n as u32).unwrap();
                        drop(enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                            label: Some("bench stamp end"),
                            timestamp_writes: Some(timer.writes(false, true)),
                        }));
                        timer.resolve(&mut enc);
                        gpu.queue().submit([enc.finish()]);
                        ns.push(timer.read_ns(gpu).unwrap() as f64 / 1e3);
                    }
                    print_quantiles(
                        &format!("phases {name} n={n:5} gpu span, {what:12}"),
                        &mut ns,
                    );
                }
            }
        }
    }
}

/// How long the GPU takes to answer a submission, by what the submission ends with and how
/// long the GPU sat idle before it (`QUERY_BENCH_LATENCY=ROUNDS`): an empty command buffer, a
/// 4-byte copy, an empty dispatch, an empty dispatch then the copy, and a SIREN `default` query
/// of 3000 points on device-local buffers, each submitted after the host spun for 0, 50, 300
/// or 2000 µs with nothing in flight, and waited for by polling. Prints p10, median and p90.
fn latency_split(gpu: &GpuContext, rounds: usize) {
    use std::time::Instant;
    let src = gpu.storage_zeroed("bench src", 16).unwrap();
    let dst = gpu.storage_zeroed("bench dst", 16).unwrap();
    let (empty_pipeline, empty_group) = empty_dispatch(gpu);
    let sdf = siren_sdf(&sdf_nn::Siren::new(sdf_nn::SirenConfig::default(), 1).unwrap());
    let n = 3000;
    let mut resident = buffers_with(gpu, &sdf, n, QueryTransfer::Staged);
    resident
        .upload(gpu, &sdf_geom::sample::uniform_box(n, 42))
        .unwrap();
    let kinds = ["empty", "copy", "dispatch", "dispatch+copy", "siren_query"];
    let gaps_us = [0u64, 50, 300, 2000];
    let mut t: Vec<Vec<f64>> = vec![Vec::with_capacity(rounds); kinds.len() * gaps_us.len()];
    for round in 0..=rounds {
        for (g, &gap) in gaps_us.iter().enumerate() {
            for (k, kind) in kinds.iter().enumerate() {
                let mut enc = gpu.device().create_command_encoder(&Default::default());
                if kind.starts_with("dispatch") {
                    let mut pass = enc.begin_compute_pass(&Default::default());
                    pass.set_pipeline(&empty_pipeline);
                    pass.set_bind_group(0, &empty_group, &[]);
                    pass.dispatch_workgroups(1, 1, 1);
                }
                if kind.ends_with("copy") {
                    enc.copy_buffer_to_buffer(&src, 0, &dst, 0, 4);
                }
                if *kind == "siren_query" {
                    sdf.record_query(gpu, &mut enc, &mut resident, n as u32)
                        .unwrap();
                }
                let cmd = enc.finish();
                let idle = Instant::now();
                while idle.elapsed().as_micros() < u128::from(gap) {
                    std::hint::spin_loop();
                }
                let start = Instant::now();
                gpu.queue().submit([cmd]);
                while !gpu
                    .device()
                    .poll(wgpu::PollType::Poll)
                    .unwrap()
                    .is_queue_empty()
                {}
                if round > 0 {
                    t[g * kinds.len() + k].push(start.elapsed().as_secs_f64() * 1e6);
                }
            }
        }
    }
    for (g, gap) in gaps_us.iter().enumerate() {
        for (k, kind) in kinds.iter().enumerate() {
            let t = &mut t[g * kinds.len() + k];
            t.sort_by(f64::total_cmp);
            println!(
                "latency idle {gap:5} µs {kind:14} p10 {:7.1} µs  median {:7.1} µs  p90 {:7.1} µs",
                t[t.len() / 10],
                t[t.len() / 2],
                t[t.len() * 9 / 10]
            );
        }
    }
}

fn main() {
    let gpu = GpuContext::shared().expect("a GPU adapter");
    eprintln!("adapter: {}", gpu.describe());
    if let Some(rounds) = std::env::var("QUERY_BENCH_LATENCY")
        .ok()
        .and_then(|s| s.parse::<usize>().ok())
    {
        latency_split(gpu, rounds.max(1));
        return;
    }
    if let Some(rounds) = std::env::var("QUERY_BENCH_PHASES")
        .ok()
        .and_then(|s| s.parse::<usize>().ok())
    {
        phase_split(gpu, rounds.max(1));
        return;
    }
    if let Some(rounds) = std::env::var("QUERY_BENCH_INTERLEAVED")
        .ok()
        .and_then(|s| s.parse::<usize>().ok())
    {
        transfer_split(gpu, rounds.max(1));
        interleaved(gpu, rounds.max(1));
        interleaved_siren(gpu, rounds.max(1));
        return;
    }
    let mut c = Criterion::default().configure_from_args();
    empty_roundtrip(&mut c, gpu);
    nglod(&mut c, gpu);
    c.final_summary();
}
