//! The query API on real GPU and CPU paths: `NeuralSdf::eval` agrees with `eval_cpu` for both
//! architectures (in mesh coordinates, inside and outside the box, normals too), and a sphere
//! model extracts to a mesh on the sphere. `scripts/load_model.py`, which evaluates a model file
//! from its tensors alone with numpy, agrees with `NeuralSdf` for SIREN, NGLOD and the hash grid.

use glam::Vec3;
use hwsdf::eval::run::extract_mesh;
use hwsdf::nn::{
    GpuContext, GpuError, NeuralSdf, NeuralSdfError, Nglod, NglodConfig, Normalization,
    QueryBuffersDescriptor, QueryError, QueryOutputs, QuerySpace, QueryTransfer, Siren,
    SirenConfig, siren::LayerKernels,
};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

fn gpu() -> &'static GpuContext {
    GpuContext::shared().expect("a GPU adapter (lavapipe in CI)")
}

/// Mesh coordinates that differ from the normalised ones.
fn normalization() -> Normalization {
    Normalization {
        center: Vec3::new(3.0, -1.0, 0.25).as_dvec3(),
        scale: 0.5,
    }
}

/// A SIREN on the adapter's own kernels, an NGLOD, and the SIREN again on the two ways a
/// SIREN query runs whatever the adapter: the tiled fused kernel, which answers in one dispatch
/// (the mapping into the cube and the rule outside it inside the kernel), and the row-blocked
/// kernels between `query.wgsl`'s two ends.
fn models() -> Vec<NeuralSdf> {
    let siren = Siren::new(SirenConfig::small(), 3).unwrap();
    let nglod = Nglod::new(NglodConfig::small()).unwrap();
    let siren_on = |kernels: LayerKernels| {
        let mut sdf = NeuralSdf::from_model_file(
            siren.to_model_file(normalization(), serde_json::Value::Null),
        )
        .unwrap();
        sdf.set_siren_kernels(kernels).unwrap();
        sdf
    };
    vec![
        siren_on(LayerKernels::Auto),
        NeuralSdf::from_model_file(nglod.to_model_file(normalization(), serde_json::Value::Null))
            .unwrap(),
        siren_on(LayerKernels::Tiled),
        siren_on(LayerKernels::RowBlocked),
    ]
}

/// The parameter count is the network's: a file that also holds a checkpoint's optimiser
/// moments (twice as many floats again) reports the same count as the plain model file.
#[test]
fn param_count_is_the_networks() {
    let siren = Siren::new(SirenConfig::small(), 3).unwrap();
    let nglod = Nglod::new(NglodConfig::small()).unwrap();
    // The default preset has a sparse level, whose vertex lists are not parameters either.
    let sparse = Nglod::new(NglodConfig::default()).unwrap();
    for (file, n) in [
        (
            siren.to_model_file(normalization(), serde_json::Value::Null),
            siren.params().len(),
        ),
        (
            nglod.to_model_file(normalization(), serde_json::Value::Null),
            nglod.param_count(),
        ),
        (
            sparse.to_model_file(normalization(), serde_json::Value::Null),
            sparse.param_count(),
        ),
    ] {
        assert_eq!(file.param_count(), n);
        let sdf = NeuralSdf::from_model_file(file.clone()).unwrap();
        assert_eq!(sdf.param_count(), n);
        let mut checkpoint = file;
        for name in ["optimizer.m", "optimizer.v"] {
            checkpoint.tensors.push(hwsdf::nn::model_file::Tensor::f32(
                name,
                vec![n],
                vec![0.0; n],
            ));
        }
        assert_eq!(checkpoint.param_count(), 3 * n);
        assert_eq!(
            NeuralSdf::from_model_file(checkpoint)
                .unwrap()
                .param_count(),
            n
        );
    }
}

/// Points in mesh coordinates covering the model's box and beyond it.
fn points(n: usize) -> Vec<Vec3> {
    points_of(&normalization(), n)
}

/// [`points`] in the mesh coordinates of `norm`.
fn points_of(norm: &Normalization, n: usize) -> Vec<Vec3> {
    let mut rng = Pcg64::seed_from_u64(7);
    (0..n)
        .map(|_| {
            let local = Vec3::new(
                rng.random_range(-1.6..1.6),
                rng.random_range(-1.6..1.6),
                rng.random_range(-1.6..1.6),
            );
            norm.to_original(local)
        })
        .collect()
}

#[test]
fn gpu_and_cpu_agree_for_both_architectures() {
    let gpu = gpu();
    // 1237: not a multiple of any workgroup size.
    let pts = points(1237);
    for model in models() {
        let g = model.eval(gpu, &pts).unwrap();
        let c = model.eval_cpu(&pts);
        assert_eq!(g.len(), pts.len());
        for (i, (a, b)) in g.iter().zip(&c).enumerate() {
            assert!(
                (a - b).abs() <= 1e-4 * b.abs().max(1.0),
                "{} {:?} point {i}: GPU {a} vs CPU {b}",
                model.architecture(),
                model.siren_kernels()
            );
        }
        let gn = model.eval_with_normals(gpu, &pts).unwrap();
        let cn = model.eval_with_normals_cpu(&pts);
        for (i, ((da, na), (db, nb))) in gn.iter().zip(&cn).enumerate() {
            let what = format!("{} {:?}", model.architecture(), model.siren_kernels());
            assert!(
                (da - db).abs() <= 1e-4 * db.abs().max(1.0),
                "{what} {i}: {da} vs {db}"
            );
            assert!(
                (*na - *nb).length() < 1e-3,
                "{what} {i}: normal {na} vs {nb}"
            );
            assert!(na.length() < 1.0 + 1e-4);
        }
        // Distances are in mesh units: outside the box the distance-to-box term dominates,
        // scaled by 1/scale.
        let far = normalization().to_original(Vec3::new(5.0, 0.0, 0.0));
        let d = model.eval_cpu(&[far])[0];
        assert!(d > (5.0 - 1.0 - 2.0) / normalization().scale, "{d}");
    }
}

#[test]
fn levels_of_detail_apply_to_nglod_only() {
    let mut m = models();
    let pts = points(301);
    assert!(m[0].set_lod(Some(1)).is_err(), "SIREN has no levels");
    let full = m[1].eval_cpu(&pts);
    m[1].set_lod(Some(1)).unwrap();
    let coarse = m[1].eval_cpu(&pts);
    let coarse_gpu = m[1].eval(gpu(), &pts).unwrap();
    assert_ne!(full, coarse);
    for (a, b) in coarse_gpu.iter().zip(&coarse) {
        assert!((a - b).abs() <= 1e-4 * b.abs().max(1.0));
    }
    assert!(
        m[1].set_lod(Some(4)).is_err(),
        "the small preset has 3 levels"
    );
}

#[test]
fn a_sphere_model_extracts_to_the_sphere() {
    let radius = 0.6;
    let model = Nglod::from_sdf(32, |p| p.length() - radius).unwrap();
    let sdf =
        NeuralSdf::from_model_file(model.to_model_file(normalization(), serde_json::Value::Null))
            .unwrap();
    let (mesh, stats) = extract_mesh(gpu(), &sdf, 64).unwrap();
    assert!(mesh.triangles.len() > 1000, "{stats:?}");
    let norm = normalization();
    // In mesh coordinates: centred on `center`, radius `radius / scale`. Tolerance: the model's
    // interpolation error plus the surface-nets vertex placement, well under one cell.
    let cell = 2.1 / 64.0 / norm.scale;
    for v in &mesh.vertices {
        let r = (*v - norm.center.as_vec3()).length();
        assert!(
            (r - radius / norm.scale).abs() < 0.2 * cell,
            "vertex at radius {r}"
        );
    }
}

/// The serving API on both architectures: caller-owned buffers reused across queries of
/// different sizes, values and normals agree with the CPU, mesh and normalised spaces, and the
/// misuses it promises to refuse are refused with typed errors.
#[test]
fn serving_api_reuses_buffers_and_refuses_misuse() {
    let gpu = gpu();
    let models = models();
    let mappable = gpu.maps_storage();
    // Both ways of moving data, whichever `Auto` picks on this adapter.
    for (model, transfer) in models
        .iter()
        .flat_map(|m| [(m, QueryTransfer::Staged), (m, QueryTransfer::Mapped)])
    {
        let arch = format!("{} {:?}", model.architecture(), model.siren_kernels());
        let desc = QueryBuffersDescriptor {
            label: Some("test"),
            capacity: 500,
            outputs: QueryOutputs::ValuesAndNormals,
            space: QuerySpace::Mesh,
            transfer,
            kernel: None,
        };
        if transfer == QueryTransfer::Mapped && !mappable {
            assert!(matches!(
                model.create_query_buffers(gpu, &desc),
                Err(NeuralSdfError::Query(QueryError::Invalid(_)))
            ));
            continue;
        }
        let mut buffers = model.create_query_buffers(gpu, &desc).unwrap();
        let mut got = Vec::new();
        for n in [500usize, 37, 1, 0, 499] {
            let pts = points(n);
            let ticket = model.submit_query(gpu, &mut buffers, &pts).unwrap();
            assert_eq!(ticket.len(), n);
            // One query in flight per buffers.
            assert!(matches!(
                model.submit_query(gpu, &mut buffers, &pts),
                Err(NeuralSdfError::Query(QueryError::Busy))
            ));
            // With mapped transfers the results buffer is mapped until the results are read:
            // recording another query into it meanwhile is refused, not a wgpu panic.
            if transfer == QueryTransfer::Mapped && n > 0 {
                let mut enc = gpu.device().create_command_encoder(&Default::default());
                assert!(matches!(
                    model.record_query(gpu, &mut enc, &mut buffers, n as u32),
                    Err(NeuralSdfError::Query(QueryError::Busy))
                ));
            }
            got.clear();
            buffers
                .wait(gpu, ticket)
                .unwrap()
                .extend_values_and_normals(&mut got);
            let want = model.eval_with_normals_cpu(&pts);
            assert_eq!(got.len(), n, "{arch} {transfer:?}");
            for (i, ((da, na), (db, nb))) in got.iter().zip(&want).enumerate() {
                assert!(
                    (da - db).abs() <= 1e-4 * db.abs().max(1.0),
                    "{arch} {transfer:?} n={n} {i}: {da} vs {db}"
                );
                assert!((*na - *nb).length() < 1e-3, "{arch} {i}: {na} vs {nb}");
            }
        }
        // Capacities whose buffers pass the device's limits are typed errors, whichever
        // transfer (the staging buffer used to be made first, and wgpu panicked on it).
        let huge = QueryBuffersDescriptor {
            capacity: u32::MAX,
            ..desc
        };
        assert!(
            matches!(
                model.create_query_buffers(gpu, &huge),
                Err(NeuralSdfError::Gpu(GpuError::BufferTooLarge { .. }))
            ),
            "{arch} {transfer:?}"
        );
        // A NaN or infinite point is refused up front (kernels need not propagate NaN), for
        // the serving calls and the plain ones alike.
        let mut bad = points(9);
        bad[4] = Vec3::new(0.1, f32::NAN, 0.0);
        assert!(matches!(
            model.submit_query(gpu, &mut buffers, &bad),
            Err(NeuralSdfError::Query(QueryError::NonFinitePoint {
                index: 4,
                ..
            }))
        ));
        bad[4] = Vec3::new(f32::INFINITY, 0.0, 0.0);
        assert!(matches!(
            model.eval_with_normals(gpu, &bad),
            Err(NeuralSdfError::Query(QueryError::NonFinitePoint {
                index: 4,
                ..
            }))
        ));
        // Too many points, buffers of another model.
        assert!(matches!(
            model.submit_query(gpu, &mut buffers, &points(501)),
            Err(NeuralSdfError::Query(QueryError::Capacity { .. }))
        ));
        let other = &models[if model.architecture() == "siren" {
            1
        } else {
            0
        }];
        assert!(matches!(
            other.submit_query(gpu, &mut buffers, &points(3)),
            Err(NeuralSdfError::Query(QueryError::Foreign))
        ));
        // Normalised space, values only.
        let mut norm = model
            .create_query_buffers(
                gpu,
                &QueryBuffersDescriptor {
                    capacity: 64,
                    space: QuerySpace::Normalized,
                    ..Default::default()
                },
            )
            .unwrap();
        let local: Vec<Vec3> = points(64)
            .iter()
            .map(|&p| normalization().to_normalized(p))
            .collect();
        let ticket = model.submit_query(gpu, &mut norm, &local).unwrap();
        // A ticket belongs to the buffers that made it: another's in-flight query (here of
        // fewer points, whose results it would have mapped out of bounds) is not it.
        let other_ticket = model.submit_query(gpu, &mut buffers, &points(2)).unwrap();
        assert!(!norm.is_ready(gpu, &other_ticket));
        assert!(matches!(
            norm.wait(gpu, other_ticket),
            Err(NeuralSdfError::Query(QueryError::StaleTicket))
        ));
        let mut d = Vec::new();
        norm.wait(gpu, ticket).unwrap().extend_values(&mut d);
        // A ticket not redeemed by its own buffers (`other_ticket` went to the wrong ones)
        // keeps them busy until they abandon its query.
        assert!(matches!(
            model.submit_query(gpu, &mut buffers, &points(5)),
            Err(NeuralSdfError::Query(QueryError::Busy))
        ));
        buffers.abandon(gpu).unwrap();
        buffers.abandon(gpu).unwrap();
        let again = model.submit_query(gpu, &mut buffers, &points(7)).unwrap();
        assert_eq!(buffers.wait(gpu, again).unwrap().len(), 7);
        for (a, b) in d.iter().zip(model.eval_cpu_normalized(&local)) {
            assert!(
                (a - b).abs() <= 1e-4 * b.abs().max(1.0),
                "{arch}: {a} vs {b}"
            );
        }
    }
}

/// How `python3 scripts/load_model.py` can run here: `Ok` when python3 imports numpy and
/// safetensors; otherwise, under CI (`CI=true`, where `.ci/run` installs them) a failure, and
/// elsewhere `Err` with the reason, which the caller prints as it skips.
fn python_with_numpy() -> Result<(), String> {
    let probe = std::process::Command::new("python3")
        .args(["-c", "import numpy, safetensors"])
        .output();
    let missing = match probe {
        Ok(o) if o.status.success() => return Ok(()),
        Ok(o) => format!(
            "python3 cannot import numpy and safetensors ({})",
            String::from_utf8_lossy(&o.stderr)
                .lines()
                .last()
                .unwrap_or("")
        ),
        Err(e) => format!("python3 does not run: {e}"),
    };
    assert!(
        std::env::var("CI").as_deref() != Ok("true"),
        "{missing} (CI installs them: python3 -m pip install numpy safetensors)"
    );
    Err(missing)
}

/// The distances `scripts/load_model.py` prints for `model` at `points`.
fn load_model_py(model: &std::path::Path, points: &[Vec3]) -> Vec<f32> {
    // Beside HWSDF_TEST_DATA (tests/data) where it is set, as in gpu-compare's pack.
    let script = std::env::var_os("HWSDF_TEST_DATA")
        .map(|data| std::path::PathBuf::from(data).join("../../scripts"))
        .unwrap_or_else(|| std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts"))
        .join("load_model.py");
    let coords: Vec<String> = points
        .iter()
        .flat_map(|p| p.to_array())
        .map(|c| format!("{c:e}"))
        .collect();
    let o = std::process::Command::new("python3")
        .arg(script)
        .arg(model)
        .args(&coords)
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "load_model.py failed: {}{out}",
        String::from_utf8_lossy(&o.stderr)
    );
    // `sdf(x, y, z) = d`, one line per point.
    out.lines()
        .filter(|l| l.starts_with("sdf("))
        .map(|l| l.rsplit("= ").next().unwrap().trim().parse().unwrap())
        .collect()
}

/// On the faces of a model's box, where a box-shaped mesh's faces lie once normalised, a
/// normal is the inside's gradient, on the CPU and the GPU (the derivative across a face was
/// taken as the clamped outside's, 0: a cube's face normal came out along the face). A linear
/// field, exact under trilinear interpolation, at points on faces, an edge, corners and inside.
#[test]
fn normals_on_the_box_faces_are_the_insides() {
    let g = Vec3::new(0.3, -0.5, 0.8);
    let model = Nglod::from_sdf(8, move |p| p.dot(g)).unwrap();
    let identity = Normalization {
        center: glam::DVec3::ZERO,
        scale: 1.0,
    };
    let sdf =
        NeuralSdf::from_model_file(model.to_model_file(identity, serde_json::Value::Null)).unwrap();
    let pts = [
        Vec3::new(1.0, 0.3, -0.2),
        Vec3::new(-1.0, 0.5, 0.1),
        Vec3::new(0.2, 1.0, -1.0),
        Vec3::ONE,
        -Vec3::ONE,
        Vec3::new(0.1, 0.2, 0.3),
    ];
    let want = g.normalize();
    let gpu_normals = sdf.eval_with_normals(gpu(), &pts).unwrap();
    for (path, got) in [
        ("cpu", sdf.eval_with_normals_cpu(&pts)),
        ("gpu", gpu_normals),
    ] {
        for (p, (_, n)) in pts.iter().zip(got) {
            assert!((n - want).length() < 1e-2, "{path} at {p}: {n} vs {want}");
        }
    }
}

/// `scripts/load_model.py` evaluates every architecture's file as `NeuralSdf` does, within
/// 1e-4 relative (its printed six decimals are the floor): a SIREN, an NGLOD with a sparse
/// finest level and a hash grid whose features and weights are all of order one (a fresh
/// model's grids are 0.01·N(0, 1), which would hide a wrong lookup), with coarse dense levels
/// and finer hashed ones, at points inside and outside the box of a normalisation that is not
/// the identity, near the origin and far from it (a centre that is no f32, which the file keeps
/// in f64 and the map uses in f64).
#[test]
fn load_model_py_agrees_with_neural_sdf() {
    if let Err(why) = python_with_numpy() {
        eprintln!("note: skipping the load_model.py check: {why}");
        return;
    }
    let mut rng = Pcg64::seed_from_u64(39);
    let mut order_one = |config: NglodConfig| {
        let n = Nglod::new(config.clone()).unwrap().param_count();
        let params = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
        Nglod::from_params(config, params).unwrap()
    };
    // Levels of 4, 10, 25 and 64 cells: the first (125 vertices) dense, the others hashed
    // into tables of 2^10 entries.
    let hashgrid = order_one(NglodConfig::hashgrid(4, 4, 64, 2, 10, 8));
    assert_eq!(
        hashgrid.config().storage(1),
        hwsdf::nn::nglod::LevelStorage::Hashed(1024)
    );
    // A sparse finest level of 32 cells whose band is the vertices near a sphere.
    let mut nglod = Nglod::new(NglodConfig {
        resolutions: vec![4, 8, 16, 32],
        sparse_levels: 1,
        ..NglodConfig::small()
    })
    .unwrap();
    nglod.place_bands(|p| p.length() - 0.6).unwrap();
    assert!(!nglod.bands()[0].vertices().is_empty());
    for p in nglod.params_mut() {
        *p = rng.random_range(-1.0..1.0);
    }
    let files = [
        (
            "siren",
            Siren::new(SirenConfig::small(), 5)
                .unwrap()
                .to_model_file(normalization(), serde_json::Value::Null),
        ),
        (
            "nglod",
            nglod.to_model_file(normalization(), serde_json::Value::Null),
        ),
        (
            "hashgrid",
            hashgrid.to_model_file(normalization(), serde_json::Value::Null),
        ),
    ];
    let dir = std::env::temp_dir().join(format!("hwsdf-load-model-py-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let far = Normalization {
        center: glam::DVec3::new(1_000_000.3, -2_000_000.7, 5.0),
        scale: 0.5,
    };
    for (name, file) in files.into_iter().flat_map(|(name, file)| {
        let mut moved = file.clone();
        moved.metadata.normalization = far;
        [(name, file), (name, moved)]
    }) {
        assert_eq!(file.metadata.architecture, name);
        let norm = file.metadata.normalization;
        let pts = points_of(&norm, 40);
        let path = dir.join(format!("{name}.safetensors"));
        file.save(&path).unwrap();
        // The file as saved (f16 grids) is what both read.
        let rust = NeuralSdf::load(&path).unwrap().eval_cpu(&pts);
        let python = load_model_py(&path, &pts);
        assert_eq!(python.len(), pts.len(), "{name}");
        for (i, (p, r)) in python.iter().zip(&rust).enumerate() {
            assert!(
                (p - r).abs() <= 1e-4 * r.abs().max(1e-2),
                "{name} at {}: load_model.py {p}, NeuralSdf {r}",
                pts[i]
            );
        }
        // Not all alike: the check compares distances that vary.
        let spread = rust.iter().fold(0.0f32, |m, d| m.max((d - rust[0]).abs()));
        assert!(spread > 0.1, "{name}: {rust:?}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
