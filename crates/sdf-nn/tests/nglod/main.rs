//! NGLOD and the hash grid: the f64 CPU reference against finite differences, the kernels
//! against the reference (both grid-scatter paths, both objectives, batch sizes that are not
//! multiples of the workgroup), levels of detail, training on a sphere, model files; the hash
//! grid's own tests are in `hashgrid.rs`. One test binary so every test shares one device and
//! its compiled pipelines (lavapipe JIT costs seconds per pipeline).

mod hashgrid;
#[path = "../support/mod.rs"]
mod support;

use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use sdf_geom::Mesh;
use sdf_nn::nglod::{Encoding, LevelStorage, Objective, SampleSource, ScatterMode, cpu};
use sdf_nn::{
    GpuContext, Nglod, NglodConfig, NglodError, NglodGpu, NglodTrainConfig, NglodTrainer,
    QueryKernel,
};

fn gpu() -> &'static GpuContext {
    let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
    eprintln!("adapter: {}", gpu.describe());
    gpu
}

/// A model whose features are large enough (0.3·N) that the grids, not just the biases, decide
/// the output and many ReLUs are active. Sparse levels get the band around a sphere of radius
/// 0.5: a shell, so that test points fall both inside and outside it.
fn lively_model(config: NglodConfig, seed: u64) -> Nglod {
    let mut m = Nglod::new(config).unwrap();
    if m.needs_bands() {
        m.place_bands(|p| (p.length() - 0.5).abs()).unwrap();
        let band = &m.bands()[0];
        let level = (band_resolution(&m) as usize + 1).pow(3);
        assert!(
            band.len() > 8 && band.len() < level,
            "the band holds {} of {level} vertices: not a partial band",
            band.len()
        );
    }
    let layout = m.layout().clone();
    let mut rng = Pcg64::seed_from_u64(seed);
    for p in &mut m.params_mut()[..layout.w0] {
        *p = rng.random_range(-0.5..0.5);
    }
    m
}

/// Random points, mostly in the box, a few outside (where the grids clamp).
fn points(n: usize, seed: u64) -> Vec<Vec3> {
    let mut rng = Pcg64::seed_from_u64(seed);
    (0..n)
        .map(|i| {
            let s = if i % 17 == 0 { 1.3 } else { 1.0 };
            Vec3::new(
                rng.random_range(-s..s),
                rng.random_range(-s..s),
                rng.random_range(-s..s),
            )
        })
        .collect()
}

fn targets(n: usize, seed: u64) -> Vec<f32> {
    let mut rng = Pcg64::seed_from_u64(seed);
    (0..n).map(|_| rng.random_range(-0.5..0.5)).collect()
}

fn f64s(v: &[f32]) -> Vec<f64> {
    v.iter().map(|&x| f64::from(x)).collect()
}

fn band_resolution(m: &Nglod) -> u32 {
    *m.config().resolutions.last().unwrap()
}

/// `config` with its finest level sparse.
fn sparse(config: NglodConfig) -> NglodConfig {
    NglodConfig {
        sparse_levels: 1,
        ..config
    }
}

/// `tiny()` as a hash grid: a fourth level of 12 cells (2197 vertices) hashed into a table of
/// 1024 entries, so that colliding vertices share their features; the other levels fit
/// theirs. The levels' 2 features each are concatenated into 8 MLP inputs.
fn tiny_hashed() -> NglodConfig {
    let c = NglodConfig {
        resolutions: vec![2, 3, 8, 12],
        feature_dim: 2,
        encoding: Encoding::Hashed {
            log2_table_size: 10,
        },
        ..tiny()
    };
    assert_eq!(c.storage(3), LevelStorage::Hashed(1024));
    assert_eq!(c.storage(2), LevelStorage::Dense);
    c
}

/// The `small` preset as a hash grid: its finest level (17³ vertices) hashed into 1024 entries.
fn small_hashed() -> NglodConfig {
    let c = NglodConfig {
        encoding: Encoding::Hashed {
            log2_table_size: 10,
        },
        ..NglodConfig::small()
    };
    assert_eq!(c.storage(2), LevelStorage::Hashed(1024));
    c
}

/// A tiny configuration for finite differences: every parameter is checked.
fn tiny() -> NglodConfig {
    NglodConfig {
        resolutions: vec![2, 3, 8],
        feature_dim: 3,
        hidden: 6,
        seed: 7,
        sparse_levels: 0,
        band_cells: sdf_nn::nglod::DEFAULT_BAND_CELLS,
        encoding: Default::default(),
    }
}

#[test]
fn cpu_reference_gradient_matches_finite_differences() {
    for config in [tiny(), sparse(tiny()), tiny_hashed()] {
        reference_gradient_matches_finite_differences(config);
    }
}

fn reference_gradient_matches_finite_differences(config: NglodConfig) {
    let model = lively_model(config.clone(), 1);
    let params = f64s(model.params());
    let pts = points(24, 2);
    let y = targets(24, 3);
    let sparse = format!("{} with {}", config.architecture(), config.sparse_levels);
    for objective in [Objective::Full, Objective::AllPrefixes] {
        let (_, grad) = cpu::loss_and_gradient(&model, &params, &pts, &y, objective).unwrap();
        let scale = grad.iter().fold(0.0f64, |m, g| m.max(g.abs()));
        let h = 1e-6;
        let mut p = params.clone();
        let mut worst = 0.0f64;
        for i in 0..params.len() {
            p[i] = params[i] + h;
            let (lp, _) = cpu::loss_and_gradient(&model, &p, &pts, &y, objective).unwrap();
            p[i] = params[i] - h;
            let (lm, _) = cpu::loss_and_gradient(&model, &p, &pts, &y, objective).unwrap();
            p[i] = params[i];
            let fd = (lp - lm) / (2.0 * h);
            worst = worst.max((fd - grad[i]).abs() / scale);
        }
        assert!(
            worst < 1e-6,
            "{sparse} sparse, {objective:?}: worst gradient error {worst:e} (relative to max \
             |g| = {scale:e})"
        );
    }
}

#[test]
fn prefix_objective_is_the_sum_of_prefix_losses() {
    let model = lively_model(sparse(tiny()), 4);
    let params = f64s(model.params());
    let pts = points(10, 5);
    let y = targets(10, 6);
    let (all, _) =
        cpu::loss_and_gradient(&model, &params, &pts, &y, Objective::AllPrefixes).unwrap();
    let mut sum = 0.0;
    // The value served: beyond the box, plus the distance to it.
    let gap = |p: Vec3| f64::from(p.distance(p.clamp(Vec3::NEG_ONE, Vec3::ONE)));
    for lod in 1..=3 {
        for (&p, &t) in pts.iter().zip(&y) {
            let r = cpu::forward(&model, &params, p, lod).unwrap() + gap(p) - f64::from(t);
            sum += r * r / pts.len() as f64;
        }
    }
    assert!((all - sum).abs() < 1e-12 * sum.max(1.0), "{all} vs {sum}");
    let (full, _) = cpu::loss_and_gradient(&model, &params, &pts, &y, Objective::Full).unwrap();
    assert!(full < all);
}

#[test]
fn cpu_f32_eval_and_spatial_gradient_match_reference() {
    for config in [tiny(), sparse(tiny()), tiny_hashed()] {
        cpu_f32_matches_reference(config);
    }
}

fn cpu_f32_matches_reference(config: NglodConfig) {
    let levels = config.levels();
    let model = lively_model(config, 8);
    let params = f64s(model.params());
    // Inside the box only: the spatial gradient is zero across the faces, where the grid clamps.
    let pts: Vec<Vec3> = points(200, 9)
        .into_iter()
        .filter(|p| p.abs().max_element() < 0.999)
        .collect();
    for lod in 1..=levels {
        let got = model.eval_cpu(&pts, Some(lod)).unwrap();
        let grads = model.gradient_cpu(&pts, Some(lod)).unwrap();
        let mut bad = 0;
        for ((&p, &v), &g) in pts.iter().zip(&got).zip(&grads) {
            let want = cpu::forward(&model, &params, p, lod).unwrap();
            assert!(
                (f64::from(v) - want).abs() < 1e-5 * want.abs().max(1.0),
                "{v} vs {want}"
            );
            let h = 1e-4f32;
            let fd: Vec<f64> = (0..3)
                .map(|a| {
                    let mut e = Vec3::ZERO;
                    e[a] = h;
                    let (pp, pm) = (p + e, p - e);
                    let fp = cpu::forward(&model, &params, pp, lod).unwrap();
                    let fm = cpu::forward(&model, &params, pm, lod).unwrap();
                    // The step actually taken, after rounding the points to f32.
                    (fp - fm) / f64::from(pp[a] - pm[a])
                })
                .collect();
            let err = (0..3)
                .map(|a| (f64::from(g[a]) - fd[a]).abs())
                .fold(0.0, f64::max);
            let mag = fd.iter().fold(1.0f64, |m, x| m.max(x.abs()));
            // A difference that straddles a cell face or a ReLU kink is not a derivative.
            if err > 1e-3 * mag {
                bad += 1;
            }
        }
        assert!(
            bad <= 2,
            "lod {lod}: {bad} of {} spatial gradients off",
            pts.len()
        );
    }
    assert!(model.eval_cpu(&pts, None).unwrap() == model.eval_cpu(&pts, Some(levels)).unwrap());
}

#[test]
fn gpu_forward_matches_cpu_at_every_lod() {
    for config in [
        NglodConfig::small(),
        sparse(NglodConfig::small()),
        small_hashed(),
    ] {
        gpu_forward_matches_cpu(config);
    }
}

fn gpu_forward_matches_cpu(config: NglodConfig) {
    let gpu = gpu();
    let model = lively_model(config.clone(), 10);
    let params = f64s(model.params());
    let g = NglodGpu::new(gpu, &model, ScatterMode::Auto).unwrap();
    // 1037: not a multiple of the 64-wide workgroup.
    let pts = points(1037, 11);
    for lod in [1, 2, 3] {
        let got = g.eval(gpu, &pts, Some(lod)).unwrap();
        assert_eq!(got.len(), pts.len());
        let worst = pts
            .iter()
            .zip(&got)
            .map(|(&p, &v)| {
                let want = cpu::forward(&model, &params, p, lod).unwrap();
                (f64::from(v) - want).abs() / want.abs().max(1.0)
            })
            .fold(0.0, f64::max);
        assert!(
            worst < 1e-5,
            "{} sparse, lod {lod}: worst error {worst:e}",
            config.sparse_levels
        );
    }
    assert_eq!(
        g.eval(gpu, &pts[..5], None).unwrap(),
        g.eval(gpu, &pts[..5], Some(3)).unwrap()
    );
    assert!(g.eval(gpu, &[], None).unwrap().is_empty());
    // Inputs larger than one dispatch are split, with the same results.
    let whole = g.eval(gpu, &pts, None).unwrap();
    let mut split = NglodGpu::new(gpu, &model, ScatterMode::Auto).unwrap();
    split.set_max_points_per_dispatch(100);
    assert_eq!(split.eval(gpu, &pts, None).unwrap(), whole);
    assert!(matches!(
        g.eval(gpu, &pts, Some(0)),
        Err(NglodError::InvalidLod { .. })
    ));
    assert!(matches!(
        g.eval(gpu, &pts, Some(4)),
        Err(NglodError::InvalidLod { .. })
    ));
}

#[test]
fn gpu_gradients_match_cpu_on_both_scatter_paths_and_both_kernels() {
    // tiny(): 3 summed features (a partial vec4 in the subgroup sums) and 6 hidden units (fewer
    // than a subgroup's lanes); tiny_hashed(): 4 levels of 2, a colliding hashed level.
    for config in [
        NglodConfig::small(),
        sparse(NglodConfig::small()),
        small_hashed(),
        tiny(),
        tiny_hashed(),
    ] {
        gpu_gradients_match_cpu(config);
    }
}

/// The training kernels this adapter runs: one row per invocation, and one per subgroup where
/// the adapter has subgroups.
fn train_kernels(gpu: &GpuContext) -> Vec<QueryKernel> {
    let mut kernels = vec![QueryKernel::PerInvocation];
    if gpu.subgroups_within(64).is_some() {
        kernels.push(QueryKernel::PerSubgroup);
    } else {
        eprintln!("adapter has no usable subgroups: only one row per invocation is tested");
    }
    kernels
}

/// Points beyond the box are fitted to the value served there: the network at the clamped
/// point plus the distance to the box. A model of the half-space `x ≤ 1` (whose face is the
/// box's) has no loss at points beyond that face labelled with their true distance, on the CPU
/// and on both GPU kernels; fitted to the clamped value alone, those labels pulled the face's
/// value up to about a quarter of the near-surface σ.
#[test]
fn points_beyond_the_box_are_fitted_as_served() {
    let gpu = gpu();
    let model = Nglod::from_sdf(8, |p| p.x - 1.0).unwrap();
    let pts = [
        Vec3::new(1.2, 0.1, -0.3),
        Vec3::new(1.01, -0.7, 0.4),
        Vec3::new(0.5, 0.0, 0.0),
    ];
    let y = [0.2, 0.01, -0.5];
    let (loss, _) =
        cpu::loss_and_gradient(&model, &f64s(model.params()), &pts, &y, Objective::Full).unwrap();
    assert!(loss < 1e-10, "CPU loss {loss}");
    for kernel in train_kernels(gpu) {
        let mut g = NglodGpu::new(gpu, &model, ScatterMode::CompareExchange).unwrap();
        g.set_train_kernel(gpu, Some(kernel)).unwrap();
        let (loss, _) = g.loss_and_gradient(gpu, &pts, &y, Objective::Full).unwrap();
        assert!(loss < 1e-10, "{kernel:?} loss {loss}");
    }
}

fn gpu_gradients_match_cpu(config: NglodConfig) {
    let gpu = gpu();
    let model = lively_model(config.clone(), 12);
    let params = f64s(model.params());
    // 301 points: not a multiple of the workgroup; ×3 prefixes spans several reduction chunks.
    let pts = points(301, 13);
    let y = targets(301, 14);
    let mut modes = vec![ScatterMode::CompareExchange];
    if gpu.has_float_atomics() {
        modes.push(ScatterMode::FloatAtomics);
    } else {
        eprintln!("adapter has no float atomics: only the compare-exchange path is tested");
    }
    for (mode, kernel) in modes
        .into_iter()
        .flat_map(|m| train_kernels(gpu).into_iter().map(move |k| (m, k)))
    {
        let mut g = NglodGpu::new(gpu, &model, mode).unwrap();
        assert_eq!(g.uses_float_atomics(), mode == ScatterMode::FloatAtomics);
        g.set_train_kernel(gpu, Some(kernel)).unwrap();
        assert_eq!(g.train_kernel(gpu, 301), kernel);
        for objective in [Objective::Full, Objective::AllPrefixes] {
            let (loss, grad) = g.loss_and_gradient(gpu, &pts, &y, objective).unwrap();
            let (want_loss, want) =
                cpu::loss_and_gradient(&model, &params, &pts, &y, objective).unwrap();
            assert!(
                (loss - want_loss).abs() < 1e-5 * want_loss,
                "{mode:?} {kernel:?} {objective:?}: loss {loss} vs {want_loss}"
            );
            let scale = want.iter().fold(0.0f64, |m, g| m.max(g.abs()));
            let worst = grad
                .iter()
                .zip(&want)
                .map(|(&a, &b)| (f64::from(a) - b).abs() / scale)
                .fold(0.0, f64::max);
            assert!(
                worst < 1e-5,
                "{} sparse, {mode:?} {kernel:?} {objective:?}: worst gradient error {worst:e} \
                 of max |g| {scale:e}",
                config.sparse_levels
            );
        }
        // The gradient buffer is left zeroed for the next caller.
        let left: Vec<f32> = gpu.read_back(g.grads_buffer()).unwrap();
        assert!(left.iter().all(|&x| x == 0.0));
    }
}

/// The fraction of `test` points where `g`'s sign says inside exactly when the point is inside
/// the sphere of `radius` about the origin.
fn sphere_sign_accuracy(
    gpu: &GpuContext,
    g: &NglodGpu,
    radius: f32,
    test: &[Vec3],
    lod: Option<usize>,
) -> f64 {
    let pred = g.eval(gpu, test, lod).unwrap();
    let correct = test
        .iter()
        .zip(&pred)
        .filter(|&(p, &d)| (p.length() < radius) == (d < 0.0))
        .count();
    correct as f64 / test.len() as f64
}

/// An icosphere of radius `r` (subdivided `levels` times).
fn icosphere(r: f32, levels: usize) -> Mesh {
    Mesh::icosphere(r, levels as u32)
}

#[test]
fn trains_a_sphere_with_correct_signs_at_every_lod() {
    let gpu = gpu();
    let radius = 0.6;
    let mesh = icosphere(radius, 3);
    let model = Nglod::new(NglodConfig::small()).unwrap();
    // A tenth of the design document's epoch keeps this test short; the mix is the same.
    let config = NglodTrainConfig {
        epochs: 3,
        uniform_points: 10_000,
        near_points: 20_000,
        surface_points: 20_000,
        objective: Objective::AllPrefixes,
        // Small epochs need small batches to take enough steps.
        batch_size: 512,
        seed: 3,
        ..Default::default()
    };
    let mut trainer = NglodTrainer::new(gpu, &model, &mesh, config).unwrap();
    let report = trainer.train().unwrap();
    eprintln!("{report:#?}");
    assert_eq!(report.epochs.len(), 3);
    assert!(report.final_loss.is_finite());
    assert!(report.epochs[2].loss < report.epochs[0].loss);

    let test = sdf_geom::sample::uniform_box(20_000, 99);
    let g = trainer.gpu_model();
    for lod in [3, 2, 1] {
        let frac = sphere_sign_accuracy(gpu, g, radius, &test, Some(lod));
        eprintln!(
            "lod {lod}: correct sign on {:.3}% of box points",
            frac * 100.0
        );
        // The spec's bar is the full model; coarser levels of detail must still be usable.
        let bar = if lod == 3 { 0.99 } else { 0.97 };
        assert!(frac >= bar, "lod {lod}: {frac}");
    }
    let training = trainer.training_json(Some(&report));
    assert_eq!(training["epochs_done"], 3);
    assert_eq!(training["objective"], "AllPrefixes");
    // The host model read back evaluates like the GPU one.
    let host = trainer.model().unwrap();
    let a = host.eval_cpu(&test[..500], None).unwrap();
    let b = g.eval(gpu, &test[..500], None).unwrap();
    for (x, y) in a.iter().zip(&b) {
        assert!((x - y).abs() < 1e-5, "{x} vs {y}");
    }
}

/// A time budget plans the run after its first epoch: a budget no epoch fits in keeps the
/// least (`epochs`), a budget every epoch fits in runs `max_epochs`; the pool samples for the
/// epochs added, and every epoch reports the plan. A run resumed part-way through an epoch
/// plans after it too (at the pace of the steps it ran), counting its least from the resumed
/// epoch: its provisional length may end with that epoch.
#[test]
fn a_time_budget_plans_the_number_of_epochs() {
    let gpu = gpu();
    let mesh = icosphere(0.5, 1);
    let model = Nglod::new(NglodConfig::small()).unwrap();
    let config = |seconds: f64, least: usize, max_epochs: usize| NglodTrainConfig {
        epochs: least,
        uniform_points: 2_000,
        near_points: 1_000,
        surface_points: 1_000,
        batch_size: 1_000,
        // Blocks refreshed every epoch: the added epochs need freshly sampled blocks.
        pool_blocks: 2,
        refresh_every: 1,
        time_budget: Some(sdf_nn::nglod::TimeBudget {
            seconds,
            max_epochs,
        }),
        ..Default::default()
    };
    let train = |trainer: &mut NglodTrainer| {
        let mut planned = Vec::new();
        let report = trainer.train_with(|e| planned.push(e.planned)).unwrap();
        (report.epochs.len(), planned, report.length_plans)
    };
    let run = |seconds: f64, least: usize, max_epochs: usize| {
        let mut trainer =
            NglodTrainer::new(gpu, &model, &mesh, config(seconds, least, max_epochs)).unwrap();
        let (epochs, planned, plans) = train(&mut trainer);
        assert_eq!(trainer.epochs_done(), epochs);
        assert_eq!(plans, 2);
        (epochs, planned)
    };
    assert_eq!(run(0.0, 2, 50), (2, vec![2, 2]));
    assert_eq!(run(1e9, 1, 4), (4, vec![4, 4, 4, 4]));
    // Resumed in epoch 1 with 2 of its 4 steps done, its last provisional epoch: the plan after
    // it runs to max_epochs (5 in all: 4 here, each reporting what it plans).
    let fresh = NglodTrainer::new(gpu, &model, &mesh, config(0.0, 1, 5)).unwrap();
    let state = fresh.optimizer_state().unwrap();
    let mut resumed = NglodTrainer::new(gpu, &model, &mesh, config(1e9, 1, 5)).unwrap();
    resumed.resume(&state, 1, 2).unwrap();
    assert_eq!(train(&mut resumed), (4, vec![4, 4, 4, 4], 2));
    assert_eq!(resumed.epochs_done(), 5);
}

#[test]
fn divergence_is_a_typed_error() {
    let gpu = gpu();
    let mesh = icosphere(0.5, 1);
    let model = Nglod::new(NglodConfig::small()).unwrap();
    let mut config = NglodTrainConfig {
        epochs: 2,
        uniform_points: 2_000,
        near_points: 1_000,
        surface_points: 1_000,
        batch_size: 500,
        loss_every: 1,
        ..Default::default()
    };
    config.adam.lr = 1e30;
    let mut trainer = NglodTrainer::new(gpu, &model, &mesh, config).unwrap();
    let err = trainer.train().unwrap_err();
    assert!(matches!(err, NglodError::Diverged { .. }), "{err}");
}

#[test]
fn model_file_round_trips_bit_for_bit() {
    let model = lively_model(NglodConfig::small(), 20);
    let norm = sdf_nn::Normalization {
        center: Vec3::new(0.5, -1.0, 2.0).as_dvec3(),
        scale: 0.25,
    };
    let file = model.to_model_file(norm, serde_json::json!({"epochs": 3}));
    let names: Vec<&str> = file.tensors.iter().map(|t| t.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "grids.0",
            "grids.1",
            "grids.2",
            "mlp.0.weight",
            "mlp.0.bias",
            "mlp.2.weight",
            "mlp.2.bias"
        ]
    );
    assert_eq!(file.tensors[2].shape, [17, 17, 17, 4]);
    assert_eq!(file.tensors[3].shape, [32, 4]);
    let path = scratch("roundtrip.safetensors");
    file.save(&path).unwrap();
    let loaded = sdf_nn::ModelFile::load(&path).unwrap();
    assert_eq!(loaded.metadata.normalization, norm);
    assert_eq!(loaded.metadata.architecture, "nglod");
    let back = Nglod::from_model_file(&loaded).unwrap();
    assert_eq!(back.config(), model.config());
    // The file holds exactly what the in-memory file does: f32 MLP, grid features rounded to f16.
    let bits = |m: &Nglod| m.params().iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&back), bits(&Nglod::from_model_file(&file).unwrap()));
    let w0 = model.layout().w0;
    assert_eq!(bits(&back)[w0..], bits(&model)[w0..]);
    for (&stored, &trained) in back.params()[..w0].iter().zip(&model.params()[..w0]) {
        assert!((stored - trained).abs() <= trained.abs() * 2f32.powi(-11) + 1e-7);
    }
    assert_eq!(file.tensors[0].dtype, sdf_nn::model_file::TensorDtype::F16);
    assert_eq!(file.tensors[3].dtype, sdf_nn::model_file::TensorDtype::F32);
    // Half the grid bytes of an all-f32 file.
    let size = std::fs::metadata(&path).unwrap().len() as usize;
    assert!(size < 4 * model.param_count() * 6 / 10, "{size} bytes");

    // Wrong shapes and architectures are typed errors, not panics.
    let mut bad = file.clone();
    bad.tensors[3].shape = vec![4, 32];
    assert!(matches!(
        Nglod::from_model_file(&bad),
        Err(NglodError::ModelFile(_))
    ));
    let mut other = file;
    other.metadata.architecture = "siren".into();
    assert!(Nglod::from_model_file(&other).is_err());
}

#[test]
fn sparse_model_file_round_trips_and_rejects_bad_vertex_lists() {
    let model = lively_model(sparse(NglodConfig::small()), 21);
    let n = model.bands()[0].len();
    let file = model.to_model_file(sdf_nn::Normalization::identity(), serde_json::Value::Null);
    let names: Vec<&str> = file.tensors.iter().map(|t| t.name.as_str()).collect();
    assert_eq!(
        &names[..4],
        ["grids.0", "grids.1", "grids.2", "grids.2.vertices"]
    );
    assert_eq!(file.tensors[2].shape, [n, 4]);
    assert_eq!(file.tensors[3].shape, [n]);
    let path = scratch("sparse.safetensors");
    file.save(&path).unwrap();
    let back = Nglod::from_model_file(&sdf_nn::ModelFile::load(&path).unwrap()).unwrap();
    // What the file holds: the grids rounded to f16 (model_file_round_trips_bit_for_bit).
    let model = Nglod::from_model_file(&file).unwrap();
    assert_eq!(back, model);
    assert_eq!(file.tensors[3].dtype, sdf_nn::model_file::TensorDtype::U32);
    // The vertex list is not counted as parameters (checkpoints size Adam's state by it).
    assert_eq!(file.param_count(), model.param_count());
    let pts = points(500, 22);
    assert_eq!(
        back.eval_cpu(&pts, None).unwrap(),
        model.eval_cpu(&pts, None).unwrap()
    );

    // Vertex lists that are not increasing, out of range, or not integers; a length that does
    // not match the features: typed errors.
    let level = 17 * 17 * 17;
    for (what, edit) in [
        ("repeated", 0usize),
        ("out of range", 1),
        ("fractional", 2),
        ("negative", 3),
        ("one short", 4),
    ] {
        let mut bad = file.clone();
        let v = &mut bad.tensors[3];
        match edit {
            0 => v.data[1] = v.data[0],
            1 => *v.data.last_mut().unwrap() = level as f32,
            2 => v.data[0] = 0.5,
            3 => v.data[0] = -1.0,
            _ => {
                v.data.pop();
                v.shape = vec![n - 1];
            }
        }
        let err = Nglod::from_model_file(&bad);
        assert!(
            matches!(
                err,
                Err(NglodError::InvalidConfig(_) | NglodError::ModelFile(_))
            ),
            "{what}: {err:?}"
        );
    }
}

/// The trainer gives a fresh sparse model the band around its mesh, and the model trains.
#[test]
fn a_sparse_model_takes_its_band_from_the_mesh_and_trains() {
    let gpu = gpu();
    let radius = 0.6;
    let mesh = icosphere(radius, 3);
    let model = Nglod::new(sparse(NglodConfig::small())).unwrap();
    assert!(model.needs_bands());
    let config = NglodTrainConfig {
        epochs: 3,
        uniform_points: 10_000,
        near_points: 20_000,
        surface_points: 20_000,
        batch_size: 512,
        seed: 4,
        ..Default::default()
    };
    let mut trainer = NglodTrainer::new(gpu, &model, &mesh, config).unwrap();
    let report = trainer.train().unwrap();
    assert!(report.epochs[2].loss < report.epochs[0].loss);
    let trained = trainer.model().unwrap();
    assert!(!trained.needs_bands());
    let band = &trained.bands()[0];
    // The shell around a sphere of radius 0.6 at 16 cells: between a tenth and half the level.
    assert!(
        band.len() > 491 && band.len() < 2456,
        "{} band vertices",
        band.len()
    );
    assert_eq!(trained.param_count(), model.param_count() + band.len() * 4);
    let test = sdf_geom::sample::uniform_box(20_000, 98);
    let frac = sphere_sign_accuracy(gpu, trainer.gpu_model(), radius, &test, None);
    assert!(frac >= 0.99, "correct sign on {frac} of box points");
    // A trained sparse model continues training as it is: its band is kept.
    let again = NglodTrainer::new(gpu, &trained, &mesh, NglodTrainConfig::default()).unwrap();
    assert_eq!(again.model().unwrap().bands(), trained.bands());
}

#[test]
fn trains_with_the_compare_exchange_fallback() {
    let gpu = gpu();
    let mesh = icosphere(0.5, 2);
    let model = Nglod::new(NglodConfig::small()).unwrap();
    let config = NglodTrainConfig {
        epochs: 2,
        uniform_points: 4_000,
        near_points: 8_000,
        surface_points: 8_000,
        batch_size: 512,
        scatter: ScatterMode::CompareExchange,
        // A constant rate: two epochs of the default cosine decay leave the second at a tenth.
        lr_final: None,
        ..Default::default()
    };
    let mut trainer = NglodTrainer::new(gpu, &model, &mesh, config).unwrap();
    assert!(!trainer.gpu_model().uses_float_atomics());
    let report = trainer.train().unwrap();
    assert!(
        report.epochs[1].loss < 0.5 * report.epochs[0].loss,
        "{report:#?}"
    );
}

/// A profiled step times the step's four launches (and, with the points drawn on the GPU, the
/// draw's three first) and counts as a step (that it leaves no loss behind for the next epoch's
/// read is a unit test of `train/profile.rs`).
#[test]
fn a_profiled_step_times_each_launch() {
    let gpu = gpu();
    let Some(mut profiler) = sdf_nn::gpu::PassProfiler::new(gpu, 16) else {
        eprintln!("no timestamp queries on this adapter: nothing to profile");
        return;
    };
    let mesh = icosphere(0.5, 2);
    let model = Nglod::new(NglodConfig::small()).unwrap();
    for source in [SampleSource::CpuPool, SampleSource::Gpu] {
        let config = NglodTrainConfig {
            epochs: 1,
            uniform_points: 1_000,
            near_points: 1_000,
            surface_points: 1_000,
            batch_size: 1_000,
            sample_source: source,
            ..Default::default()
        };
        let mut trainer = NglodTrainer::new(gpu, &model, &mesh, config).unwrap();
        let first = trainer.train().unwrap();
        let times = trainer.profile_step(&mut profiler, true).unwrap();
        let labels: Vec<&str> = times.iter().map(|t| t.label.as_str()).collect();
        let rows = match trainer.training_json(None)["train_kernel"].as_str() {
            Some("subgroup") => "train_rows_sg",
            _ => "train_rows",
        };
        let mut want = vec![rows, "mlp_partial", "mlp_reduce", "adam"];
        if source == SampleSource::Gpu {
            want.splice(
                0..0,
                [
                    "draw",
                    "bin_count",
                    "bin_scan",
                    "bin_scatter",
                    "signed_distance",
                    "gather",
                ],
            );
        }
        assert_eq!(labels, want);
        assert_eq!(
            trainer.optimizer_state().unwrap().step as usize,
            first.steps + 1
        );
        assert_eq!(trainer.training_json(None)["steps_done"], first.steps + 1);
    }
}

/// A run stopped part-way through an epoch records the steps it did; a resume finishes that
/// epoch on the same points in the same order, so it ends where an uninterrupted run ends.
#[test]
fn an_interrupted_epoch_resumes_where_it_stopped() {
    use std::sync::Arc;
    use std::sync::atomic::{AtomicBool, Ordering};
    let gpu = gpu();
    let mesh = icosphere(0.5, 2);
    let model = Nglod::new(NglodConfig::small()).unwrap();
    let config = NglodTrainConfig {
        epochs: 2,
        uniform_points: 2_000,
        near_points: 2_000,
        surface_points: 2_000,
        // 12 steps per epoch, loss read (and stop flag polled) every 4.
        batch_size: 512,
        loss_every: 4,
        pool_blocks: 2,
        refresh_every: 1,
        seed: 11,
        ..Default::default()
    };
    let steps_per_epoch = 12;

    let mut straight = NglodTrainer::new(gpu, &model, &mesh, config.clone()).unwrap();
    let full = straight.train().unwrap();
    assert_eq!(full.steps, 2 * steps_per_epoch);
    let want = straight.model().unwrap();

    // Stop at the first read-back of epoch 1: 4 of its 12 steps done.
    let mut first = NglodTrainer::new(gpu, &model, &mesh, config.clone()).unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    first.set_stop_flag(stop.clone());
    let part = first
        .train_with(|_| stop.store(true, Ordering::Relaxed))
        .unwrap();
    assert!(part.stopped_early);
    assert_eq!(part.epochs.len(), 2);
    assert_eq!(part.epochs[1].steps, 4);
    // The unfinished epoch is not counted as done.
    assert_eq!(first.epochs_done(), 1);
    assert_eq!(first.epoch_steps_done(), 4);
    let json = first.training_json(Some(&part));
    assert_eq!(json["epochs_done"], 1);
    assert_eq!(json["epoch_steps_done"], 4);

    let state = first.optimizer_state().unwrap();
    let halfway = first.model().unwrap();
    let mut resumed = NglodTrainer::new(
        gpu,
        &halfway,
        &mesh,
        NglodTrainConfig {
            epochs: 1,
            ..config.clone()
        },
    )
    .unwrap();
    // A step count past the epoch's end is refused.
    assert!(resumed.resume(&state, 1, steps_per_epoch).is_err());
    resumed.resume(&state, 1, 4).unwrap();
    let rest = resumed.train().unwrap();
    assert_eq!(rest.epochs.len(), 1);
    assert_eq!(rest.epochs[0].epoch, 1);
    assert_eq!(rest.epochs[0].steps, steps_per_epoch - 4);
    assert_eq!(resumed.epochs_done(), 2);
    assert_eq!(resumed.epoch_steps_done(), 0);
    assert_eq!(
        resumed.optimizer_state().unwrap().step,
        2 * steps_per_epoch as u32
    );
    let got = resumed.model().unwrap();
    // Float atomics may sum in another order: equal up to rounding, not bit for bit. Skipping
    // or repeating the 8 remaining steps moves the parameters by far more.
    let diff = |a: &Nglod, b: &Nglod| {
        a.params()
            .iter()
            .zip(b.params())
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max)
    };
    let err = diff(&got, &want);
    let skipped = diff(&halfway, &want);
    eprintln!("resumed vs straight: {err:.3e}; stopped vs straight: {skipped:.3e}");
    assert!(err < 1e-4 && err * 20.0 < skipped, "{err} vs {skipped}");
}

/// Progressive training: until a level is added its grid gets no gradient, so it keeps its
/// initial values; the coarse level trains from the first epoch.
#[test]
fn progressive_training_adds_levels_one_at_a_time() {
    let gpu = gpu();
    let mesh = icosphere(0.5, 2);
    let model = Nglod::new(NglodConfig::small()).unwrap();
    let layout = model.layout();
    let config = NglodTrainConfig {
        epochs: 2,
        uniform_points: 1_000,
        near_points: 1_000,
        surface_points: 1_000,
        batch_size: 512,
        grow_every: Some(1),
        lr_final: Some(0.1),
        ..Default::default()
    };
    let mut t = NglodTrainer::new(gpu, &model, &mesh, config).unwrap();
    let report = t.train().unwrap();
    assert_eq!(
        report.epochs.iter().map(|e| e.levels).collect::<Vec<_>>(),
        [1, 2]
    );
    // The learning rate decays over the run.
    assert!(report.epochs[1].lr < report.epochs[0].lr);
    let trained = t.model().unwrap();
    let grid = |m: &Nglod, l: usize| {
        m.params()
            [layout.grid_offsets[l]..layout.grid_offsets.get(l + 1).copied().unwrap_or(layout.w0)]
            .to_vec()
    };
    assert_ne!(grid(&trained, 0), grid(&model, 0));
    assert_ne!(grid(&trained, 1), grid(&model, 1));
    assert_eq!(
        grid(&trained, 2),
        grid(&model, 2),
        "level 3 was never trained"
    );
}

/// `name` in this process's own folder under the temp folder: not cargo's target folder, so that
/// the binary also runs where it was carried without its build tree (scripts/gpu-compare.sh).
fn scratch(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("hwsdf-nglod-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}
