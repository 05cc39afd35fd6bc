//! The hash grid's own tests: colliding vertices share their features on the CPU and the GPU,
//! the presets' sizes, model files, serving, and fits of a sphere (points from the CPU pool) and
//! of a shared mesh (points drawn and labelled on the GPU). The
//! kernels' agreement with the f64 reference and the reference's with finite differences are
//! in `main.rs`, beside NGLOD's (`tiny_hashed`, `small_hashed`).

use glam::Vec3;
use sdf_geom::SignedDistance;
use sdf_nn::nglod::{Encoding, LevelStorage, SampleSource, ScatterMode, hash_vertex};
use sdf_nn::{
    NeuralSdf, NeuralSdfError, Nglod, NglodConfig, NglodError, NglodGpu, NglodTrainConfig,
    NglodTrainer,
};

use super::{gpu, icosphere, lively_model, scratch, sphere_sign_accuracy};

/// One hashed level of `resolution` cells, one feature per entry of a table of 1024, and an MLP
/// that passes the feature through (`relu(z + 10) − 10`), as `Nglod::from_sdf` builds: the
/// model's value at a grid vertex is the feature of that vertex's entry.
fn pass_through(resolution: u32, table: &[f32]) -> Nglod {
    let config = NglodConfig {
        resolutions: vec![resolution],
        feature_dim: 1,
        hidden: 1,
        seed: 0,
        sparse_levels: 0,
        band_cells: 0,
        encoding: Encoding::Hashed {
            log2_table_size: 10,
        },
    };
    assert_eq!(config.storage(0), LevelStorage::Hashed(1024));
    let mut params = table.to_vec();
    params.extend([1.0, 10.0, 1.0, -10.0]);
    Nglod::from_params(config, params).unwrap()
}

/// The point of `[-1, 1]³` at vertex `v` of a grid of `resolution` cells.
fn vertex_point(v: [u32; 3], resolution: u32) -> Vec3 {
    Vec3::new(v[0] as f32, v[1] as f32, v[2] as f32) * (2.0 / resolution as f32) - 1.0
}

#[test]
fn colliding_vertices_share_their_features_on_the_cpu_and_the_gpu() {
    // 12 cells: 2197 vertices into 1024 entries. Find two vertices that collide, and one that
    // does not collide with them.
    let r = 12;
    let mask = 1023;
    let vertices: Vec<[u32; 3]> = (0..=r)
        .flat_map(|x| (0..=r).flat_map(move |y| (0..=r).map(move |z| [x, y, z])))
        .collect();
    let a = vertices[100];
    let b = *vertices
        .iter()
        .find(|&&v| v != a && hash_vertex(v, mask) == hash_vertex(a, mask))
        .expect("2197 vertices in 1024 entries collide");
    let c = *vertices
        .iter()
        .find(|&&v| hash_vertex(v, mask) != hash_vertex(a, mask))
        .unwrap();
    // instant-ngp's hash, spelt out once: the kernels and the Python loader repeat it.
    let expect = (a[0] ^ a[1].wrapping_mul(2_654_435_761) ^ a[2].wrapping_mul(805_459_861)) & mask;
    assert_eq!(hash_vertex(a, mask), expect);

    let mut table = vec![0f32; 1024];
    table[hash_vertex(a, mask) as usize] = 0.75;
    table[hash_vertex(c, mask) as usize] = -0.25;
    let model = pass_through(r, &table);
    let pts = [vertex_point(a, r), vertex_point(b, r), vertex_point(c, r)];
    let want = [0.75, 0.75, -0.25];
    let cpu = model.eval_cpu(&pts, None).unwrap();
    let gpu_ctx = gpu();
    let g = NglodGpu::new(gpu_ctx, &model, ScatterMode::Auto).unwrap();
    let on_gpu = g.eval(gpu_ctx, &pts, None).unwrap();
    for i in 0..3 {
        assert!(
            (cpu[i] - want[i]).abs() < 1e-6,
            "CPU {i}: {} vs {}",
            cpu[i],
            want[i]
        );
        assert!(
            (on_gpu[i] - want[i]).abs() < 1e-6,
            "GPU {i}: {} vs {}",
            on_gpu[i],
            want[i]
        );
    }

    // Training gradient: both colliding vertices pull on the one entry. A point at each with
    // target 0 gives d loss / d entry = 2 · 0.75 per point (÷ 2 points) = 1.5 for the shared
    // entry, and the entry of c none.
    let (loss, grad) = g
        .loss_and_gradient(
            gpu_ctx,
            &pts[..2],
            &[0.0, 0.0],
            sdf_nn::nglod::Objective::Full,
        )
        .unwrap();
    assert!((loss - 0.5625).abs() < 1e-5, "loss {loss}");
    let shared = hash_vertex(a, mask) as usize;
    assert!(
        (grad[shared] - 1.5).abs() < 1e-5,
        "gradient of the shared entry {}",
        grad[shared]
    );
    assert_eq!(grad[hash_vertex(c, mask) as usize], 0.0);
}

#[test]
fn presets_are_hash_grids_of_the_stated_sizes() {
    let d = NglodConfig::hashgrid_default();
    d.validate().unwrap();
    assert_eq!(d.architecture(), "hashgrid");
    assert_eq!(d.levels(), 16);
    assert_eq!((d.resolutions[0], d.resolutions[15]), (16, 512));
    // A geometric progression: the ratio of successive levels is about constant.
    let ratios: Vec<f64> = d
        .resolutions
        .windows(2)
        .map(|w| f64::from(w[1]) / f64::from(w[0]))
        .collect();
    assert!(
        ratios.iter().all(|&q| (q - 1.26).abs() < 0.08),
        "{:?}",
        d.resolutions
    );
    assert_eq!(d.input_dim(), 32);
    let small = NglodConfig::hashgrid_small();
    small.validate().unwrap();
    let m = Nglod::new(small).unwrap();
    // Stored as NGLOD stores: f16 tables, f32 MLP. No larger than NGLOD's default file (about
    // 0.5-1 MB, the design document's storage column).
    let w0 = m.layout().w0;
    let bytes = 2 * w0 + 4 * (m.param_count() - w0);
    assert!(bytes <= 1_000_000, "{bytes} bytes");
    // The coarse levels fit their tables; the fine ones are hashed.
    let c = m.config();
    assert_eq!(c.storage(0), LevelStorage::Dense);
    assert_eq!(c.storage(15), LevelStorage::Hashed(1 << 14));
    // Hashing is what makes the fine levels affordable: 257³ vertices would be 17 M.
    assert!(m.param_count() < 600_000, "{}", m.param_count());
}

#[test]
fn invalid_hash_configurations_are_typed_errors() {
    let bad = |c: NglodConfig, word: &str| {
        let e = c.validate().unwrap_err();
        assert!(
            matches!(&e, NglodError::InvalidConfig(m) if m.contains(word)),
            "{e} (wanted `{word}`)"
        );
    };
    let mut c = NglodConfig::hashgrid_small();
    c.encoding = Encoding::Hashed {
        log2_table_size: 40,
    };
    bad(c, "log2_table_size");
    let mut c = NglodConfig::hashgrid_small();
    c.sparse_levels = 1;
    bad(c, "sparse");
    // 16 levels of 4 features: 64 MLP inputs.
    let mut c = NglodConfig::hashgrid_small();
    c.feature_dim = 4;
    bad(c, "MLP inputs");
    let mut c = NglodConfig::hashgrid_small();
    c.resolutions = vec![8; 17];
    bad(c, "levels");
    let mut c = NglodConfig::hashgrid_small();
    c.resolutions[3] = 5000;
    bad(c, "resolution");
}

#[test]
fn hash_grid_model_file_round_trips_and_rejects_what_disagrees() {
    let model = lively_model(NglodConfig::hashgrid_small(), 30);
    let file = model.to_model_file(sdf_nn::Normalization::identity(), serde_json::Value::Null);
    assert_eq!(file.metadata.architecture, "hashgrid");
    assert_eq!(file.metadata.config["encoding"]["kind"], "hashed");
    assert_eq!(file.metadata.config["encoding"]["log2_table_size"], 14);
    let c = model.config();
    // A level that fits its table is [s, s, s, F]; a hashed one is [T, F].
    assert_eq!(file.tensors[0].shape, [9, 9, 9, 2]);
    assert_eq!(file.tensors[15].shape, [1 << 14, 2]);
    let mlp = file
        .tensors
        .iter()
        .find(|t| t.name == "mlp.0.weight")
        .unwrap();
    assert_eq!(mlp.shape, [c.hidden as usize, 32]);
    let path = scratch("hashgrid.safetensors");
    file.save(&path).unwrap();
    let loaded = sdf_nn::ModelFile::load(&path).unwrap();
    let back = Nglod::from_model_file(&loaded).unwrap();
    assert_eq!(back.config(), c);
    let bits = |m: &Nglod| m.params().iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&back), bits(&Nglod::from_model_file(&file).unwrap()));
    let pts = super::points(300, 31);
    let a = back.eval_cpu(&pts, None).unwrap();
    let b = model.eval_cpu(&pts, None).unwrap();
    assert!(
        a.iter()
            .zip(&b)
            .all(|(x, y)| (x - y).abs() < 2e-2 * y.abs().max(1.0))
    );

    // The file's architecture must agree with its configuration, both ways.
    let mut other = file.clone();
    other.metadata.architecture = "nglod".into();
    let e = Nglod::from_model_file(&other).unwrap_err();
    assert!(e.to_string().contains("hashgrid"), "{e}");
    let nglod = lively_model(NglodConfig::small(), 32)
        .to_model_file(sdf_nn::Normalization::identity(), serde_json::Value::Null);
    let mut other = nglod;
    other.metadata.architecture = "hashgrid".into();
    assert!(Nglod::from_model_file(&other).is_err());
    // A table size that disagrees with the tensors.
    let mut other = file.clone();
    other.metadata.config["encoding"]["log2_table_size"] = 15.into();
    assert!(matches!(
        Nglod::from_model_file(&other),
        Err(NglodError::ModelFile(_))
    ));
    // A table size out of range is refused before anything is allocated.
    let mut other = file;
    other.metadata.config["encoding"]["log2_table_size"] = 60.into();
    assert!(matches!(
        Nglod::from_model_file(&other),
        Err(NglodError::InvalidConfig(_))
    ));
}

#[test]
fn a_served_hash_grid_answers_like_the_cpu_and_has_one_level_of_detail() {
    let model = lively_model(NglodConfig::hashgrid_small(), 33);
    let norm = sdf_nn::Normalization {
        center: Vec3::new(1.0, -2.0, 0.5).as_dvec3(),
        scale: 0.5,
    };
    let mut sdf =
        NeuralSdf::from_model_file(model.to_model_file(norm, serde_json::Value::Null)).unwrap();
    assert_eq!(sdf.architecture(), "hashgrid");
    // The serving kernels (distances, and distances with normals) in mesh coordinates, points
    // inside and outside the box.
    let gpu = gpu();
    let pts: Vec<Vec3> = super::points(1000, 34)
        .into_iter()
        .map(|p| norm.to_original(p))
        .collect();
    let d = sdf.eval(gpu, &pts).unwrap();
    let dn = sdf.eval_with_normals(gpu, &pts).unwrap();
    let want = sdf.eval_with_normals_cpu(&pts);
    let mut normal_outliers = 0;
    for i in 0..pts.len() {
        let (w, wn) = want[i];
        let tol = 2e-5 * (1.0 + w.abs());
        assert!((d[i] - w).abs() <= tol, "{}: {} vs {w}", pts[i], d[i]);
        assert!((dn[i].0 - w).abs() <= tol, "{}: {} vs {w}", pts[i], dn[i].0);
        // A ReLU or a cell face that rounding puts on different sides flips a normal.
        if (dn[i].1 - wn).length() > 1e-3 {
            normal_outliers += 1;
        }
    }
    assert!(normal_outliers <= 3, "{normal_outliers} normals differ");
    sdf.set_lod(Some(16)).unwrap();
    sdf.set_lod(None).unwrap();
    assert!(matches!(
        sdf.set_lod(Some(3)),
        Err(NeuralSdfError::NoLevels("hashgrid"))
    ));
}

/// A hash grid small enough for lavapipe: 6 levels of 2 features from 4 to 48 cells, tables of
/// 2¹² entries (the three finest levels hash), 32 hidden units.
fn test_grid() -> NglodConfig {
    let c = NglodConfig::hashgrid(6, 4, 48, 2, 12, 32);
    assert_eq!(c.storage(5), LevelStorage::Hashed(4096));
    c
}

#[test]
fn trains_a_sphere_with_correct_signs() {
    let gpu = gpu();
    let radius = 0.6;
    let mesh = icosphere(radius, 3);
    let model = Nglod::new(test_grid()).unwrap();
    let config = NglodTrainConfig {
        epochs: 3,
        uniform_points: 10_000,
        near_points: 20_000,
        surface_points: 20_000,
        batch_size: 1024,
        seed: 3,
        // 49 steps an epoch: submissions of the full 32 steps, each staging its uniforms (a
        // hash grid's 16 levels make them larger than NGLOD's 8 did).
        loss_every: 64,
        ..NglodTrainConfig::hashgrid()
    };
    let mut trainer = NglodTrainer::new(gpu, &model, &mesh, config).unwrap();
    let report = trainer.train().unwrap();
    assert!(report.epochs[2].loss < report.epochs[0].loss, "{report:#?}");
    let test = sdf_geom::sample::uniform_box(20_000, 99);
    let frac = sphere_sign_accuracy(gpu, trainer.gpu_model(), radius, &test, None);
    eprintln!(
        "hash grid, sphere: correct sign on {:.3}% of box points",
        frac * 100.0
    );
    assert!(frac >= 0.99, "{frac}");
    let host = trainer.model().unwrap();
    assert_eq!(host.config().architecture(), "hashgrid");
    let a = host.eval_cpu(&test[..500], None).unwrap();
    let b = trainer.gpu_model().eval(gpu, &test[..500], None).unwrap();
    for (x, y) in a.iter().zip(&b) {
        assert!((x - y).abs() < 1e-5, "{x} vs {y}");
    }
}

#[test]
fn trains_spot_with_correct_signs() {
    let gpu = gpu();
    let (mesh, _) = sdf_geom::load_mesh(crate::support::test_data("spot.obj")).unwrap();
    let (unit, _) = mesh.normalized();
    let model = Nglod::new(test_grid()).unwrap();
    let config = NglodTrainConfig {
        epochs: 4,
        uniform_points: 10_000,
        near_points: 20_000,
        surface_points: 20_000,
        batch_size: 1024,
        seed: 5,
        // The pool drawn, labelled and kept on the GPU (the sphere above uses the CPU's).
        sample_source: SampleSource::Gpu,
        ..NglodTrainConfig::hashgrid()
    };
    let mut trainer = NglodTrainer::new(gpu, &model, &unit, config).unwrap();
    trainer.train().unwrap();
    let exact = SignedDistance::new(&unit).unwrap();
    let test = sdf_geom::sample::uniform_box(20_000, 77);
    let want = exact.signed_distance_batch(&test);
    let got = trainer.gpu_model().eval(gpu, &test, None).unwrap();
    let right = got
        .iter()
        .zip(&want)
        .filter(|&(&g, &w)| (g < 0.0) == (w < 0.0))
        .count() as f64
        / test.len() as f64;
    eprintln!(
        "hash grid, spot: correct sign on {:.3}% of box points",
        right * 100.0
    );
    assert!(right >= 0.97, "{right}");
}
