//! The WGSL embedding of `NeuralSdf`: the snippet plus a caller's shader validates with naga for
//! both architectures and several shapes (levels of detail included), declares only `hwsdf_`
//! names, and, run on the device through `NeuralSdf::bind_group`, matches the CPU's distances
//! and normals at points inside and outside the box; two models under their own prefixes share
//! one shader; a scene snippet's local Lipschitz lookups match the CPU's. One test binary, one
//! shared device.

#[path = "support/mod.rs"]
mod support;

use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use sdf_nn::{
    EmbedError, GpuContext, NeuralSdf, Nglod, NglodConfig, Normalization, Siren, SirenConfig,
    serve::network::Network,
};

fn gpu() -> &'static GpuContext {
    let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
    eprintln!("adapter: {}", gpu.describe());
    gpu
}

/// A normalisation that is not the identity, so the baked constants are exercised.
fn normalization() -> Normalization {
    Normalization {
        center: Vec3::new(0.3, -1.25, 2.0).as_dvec3(),
        scale: 0.4,
    }
}

fn siren(config: SirenConfig, seed: u64) -> NeuralSdf {
    let m = Siren::new(config, seed).unwrap();
    NeuralSdf::from_model_file(m.to_model_file(normalization(), serde_json::Value::Null)).unwrap()
}

/// An NGLOD model whose grid features are large enough that the grids, not the biases, decide
/// the output and many ReLUs are active. Sparse levels hold the band around a sphere of radius
/// 0.5.
fn nglod(config: NglodConfig, seed: u64, lod: Option<usize>) -> NeuralSdf {
    let mut m = Nglod::new(config).unwrap();
    if m.needs_bands() {
        m.place_bands(|p| (p.length() - 0.5).abs()).unwrap();
    }
    let w0 = m.layout().w0;
    let mut rng = Pcg64::seed_from_u64(seed);
    for p in &mut m.params_mut()[..w0] {
        *p = rng.random_range(-0.5..0.5);
    }
    let mut sdf =
        NeuralSdf::from_model_file(m.to_model_file(normalization(), serde_json::Value::Null))
            .unwrap();
    sdf.set_lod(lod).unwrap();
    sdf
}

/// A caller's shader: its own resources at group `user`, a compute entry point and a fragment
/// entry point, both calling the two functions.
fn user_shader(user: u32) -> String {
    format!(
        r#"
@group({user}) @binding(0) var<storage, read> points: array<vec4<f32>>;
@group({user}) @binding(1) var<storage, read_write> results: array<vec4<f32>>;

@compute @workgroup_size(64)
fn eval_points(@builtin(global_invocation_id) gid: vec3<u32>) {{
    let i = gid.x;
    if i >= arrayLength(&points) {{
        return;
    }}
    let p = points[i].xyz;
    results[i] = vec4<f32>(hwsdf_distance(p), hwsdf_normal(p));
}}

@fragment
fn shade(@builtin(position) frag: vec4<f32>) -> @location(0) vec4<f32> {{
    let p = vec3<f32>(frag.xy * 0.01, 0.5);
    let n = hwsdf_normal(p);
    let d = hwsdf_distance(p) + hwsdf_distance_normalized(p);
    return vec4<f32>(n * 0.5 + 0.5, select(0.0, 1.0, d < 0.0));
}}
"#
    )
}

fn validate(source: &str) -> naga::Module {
    let module = naga::front::wgsl::parse_str(source)
        .unwrap_or_else(|e| panic!("parse: {}\n{source}", e.emit_to_string(source)));
    naga::valid::Validator::new(
        naga::valid::ValidationFlags::all(),
        naga::valid::Capabilities::empty(),
    )
    .validate(&module)
    .unwrap_or_else(|e| panic!("validate: {}\n{source}", e.emit_to_string(source)));
    module
}

/// The `small` preset with its finest level sparse.
fn sparse_small() -> NglodConfig {
    NglodConfig {
        sparse_levels: 1,
        ..NglodConfig::small()
    }
}

fn shapes() -> Vec<(&'static str, NeuralSdf)> {
    let one_level = NglodConfig {
        resolutions: vec![3],
        feature_dim: 1,
        hidden: 1,
        seed: 3,
        sparse_levels: 0,
        band_cells: 0,
        encoding: Default::default(),
    };
    vec![
        (
            "siren 8x1",
            siren(
                SirenConfig {
                    width: 8,
                    hidden_layers: 1,
                    omega0: 30.0,
                },
                1,
            ),
        ),
        ("siren small 64x3", siren(SirenConfig::small(), 2)),
        ("siren reference 256x4", siren(SirenConfig::reference(), 3)),
        ("nglod small", nglod(NglodConfig::small(), 1, None)),
        ("nglod small lod 1", nglod(NglodConfig::small(), 1, Some(1))),
        ("nglod small lod 2", nglod(NglodConfig::small(), 1, Some(2))),
        (
            "nglod default preset",
            nglod(NglodConfig::default_preset(), 2, None),
        ),
        ("nglod 1 level F=1 H=1", nglod(one_level, 3, None)),
        (
            "nglod small, finest level sparse",
            nglod(sparse_small(), 4, None),
        ),
        (
            "hashgrid small, 11 of 16 levels hashed",
            nglod(NglodConfig::hashgrid_small(), 5, None),
        ),
        (
            "hashgrid 3 levels, the finest hashed",
            nglod(NglodConfig::hashgrid(3, 4, 24, 2, 10, 8), 6, None),
        ),
    ]
}

#[test]
fn snippet_with_user_shader_validates_with_naga() {
    for (name, sdf) in shapes() {
        for (model_group, user_group) in [(1, 0), (0, 2), (3, 1)] {
            let source = format!("{}\n{}", sdf.wgsl(model_group), user_shader(user_group));
            eprintln!("{name}: group {model_group}, {} bytes", source.len());
            let module = validate(&source);
            let binding = module
                .global_variables
                .iter()
                .find(|(_, v)| v.name.as_deref() == Some("hwsdf_params"))
                .and_then(|(_, v)| v.binding)
                .expect("hwsdf_params is bound");
            assert_eq!((binding.group, binding.binding), (model_group, 0), "{name}");
        }
        // The snippet alone is valid too (nothing it needs is left to the caller).
        validate(&sdf.wgsl(0));
    }
}

/// Every name the snippet puts in the caller's module carries the prefix.
#[test]
fn snippet_declares_only_prefixed_names() {
    for (name, sdf) in shapes() {
        let module = validate(&sdf.wgsl(0));
        let mut names: Vec<String> = Vec::new();
        names.extend(
            module
                .global_variables
                .iter()
                .filter_map(|(_, v)| v.name.clone()),
        );
        names.extend(module.constants.iter().filter_map(|(_, c)| c.name.clone()));
        names.extend(module.functions.iter().filter_map(|(_, f)| f.name.clone()));
        names.extend(module.types.iter().filter_map(|(_, t)| t.name.clone()));
        assert!(!names.is_empty());
        for n in names {
            assert!(
                n.starts_with("hwsdf_") || n.starts_with("HWSDF_"),
                "{name}: `{n}` is not prefixed"
            );
        }
        for f in [
            "hwsdf_distance",
            "hwsdf_normal",
            "hwsdf_distance_normalized",
        ] {
            assert!(
                module
                    .functions
                    .iter()
                    .any(|(_, g)| g.name.as_deref() == Some(f)),
                "{name}: {f} missing"
            );
        }
    }
}

/// Points in mesh coordinates whose normalised images fill `[-1.4, 1.4]³` (a fifth of them
/// outside the box) with a few exactly on the box's faces.
fn points(n: usize, seed: u64) -> Vec<Vec3> {
    let norm = normalization();
    let mut rng = Pcg64::seed_from_u64(seed);
    (0..n)
        .map(|i| {
            let mut q = Vec3::new(
                rng.random_range(-1.4..1.4),
                rng.random_range(-1.4..1.4),
                rng.random_range(-1.4..1.4),
            );
            if i % 5 != 0 {
                q = q.clamp(Vec3::splat(-0.999), Vec3::splat(0.999));
            }
            norm.to_original(q)
        })
        .collect()
}

/// Runs `user_shader`'s compute entry point with the model at group 1 on the shared device,
/// the way a renderer would: its own bind group at 0, `NeuralSdf::bind_group` at 1.
fn eval_on_gpu(sdf: &NeuralSdf, pts: &[Vec3]) -> Vec<[f32; 4]> {
    let gpu = gpu();
    eval_on_device(gpu.device(), gpu.queue(), sdf, pts)
}

/// [`eval_on_gpu`] on any device, with nothing of HW SDF's GPU context.
fn eval_on_device(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    sdf: &NeuralSdf,
    pts: &[Vec3],
) -> Vec<[f32; 4]> {
    let source = format!("{}\n{}", sdf.wgsl(1), user_shader(0));
    let sdf_group = sdf.bind_group(device).expect("weights fit");
    run_user_shader(
        device,
        queue,
        &source,
        &[(&sdf_group.layout, &sdf_group.bind_group)],
        pts,
    )
}

/// A caller's compute entry point `eval_points` over its points and results at group 0, running
/// `body` for each point `i` (WGSL statements; `points[i]` its input, `results[i]` its output).
fn point_kernel(body: &str) -> String {
    format!(
        r#"
@group(0) @binding(0) var<storage, read> points: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read_write> results: array<vec4<f32>>;

@compute @workgroup_size(64)
fn eval_points(@builtin(global_invocation_id) gid: vec3<u32>) {{
    let i = gid.x;
    if i >= arrayLength(&points) {{
        return;
    }}
{body}
}}
"#
    )
}

/// Runs the compute entry point `eval_points` of `source` over `pts`: the caller's points and
/// results at group 0 (`vec4` each), the models' bind groups at groups 1, 2, ….
fn run_user_shader(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    source: &str,
    groups: &[(&wgpu::BindGroupLayout, &wgpu::BindGroup)],
    pts: &[Vec3],
) -> Vec<[f32; 4]> {
    let inputs: Vec<[f32; 4]> = pts.iter().map(|p| p.extend(0.0).to_array()).collect();
    run_user_shader_vec4(device, queue, source, groups, &inputs)
}

/// [`run_user_shader`] for inputs that use all four lanes of `points[i]`.
fn run_user_shader_vec4(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    source: &str,
    groups: &[(&wgpu::BindGroupLayout, &wgpu::BindGroup)],
    inputs: &[[f32; 4]],
) -> Vec<[f32; 4]> {
    use wgpu::util::DeviceExt;
    let input: Vec<f32> = inputs.iter().flatten().copied().collect();
    let points = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("points"),
        contents: bytemuck::cast_slice(&input),
        usage: wgpu::BufferUsages::STORAGE,
    });
    let bytes = (inputs.len() * 16) as u64;
    let results = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("results"),
        size: bytes,
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        mapped_at_creation: false,
    });
    let readback = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("readback"),
        size: bytes,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let storage = |binding, read_only| wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only },
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    };
    let user_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some("user"),
        entries: &[storage(0, true), storage(1, false)],
    });
    let layouts: Vec<Option<&wgpu::BindGroupLayout>> = std::iter::once(Some(&user_layout))
        .chain(groups.iter().map(|g| Some(g.0)))
        .collect();
    let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some("user"),
        bind_group_layouts: &layouts,
        immediate_size: 0,
    });
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some("user + hwsdf"),
        source: wgpu::ShaderSource::Wgsl(source.into()),
    });
    let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some("eval_points"),
        layout: Some(&layout),
        module: &module,
        entry_point: Some("eval_points"),
        compilation_options: Default::default(),
        cache: None,
    });
    let user_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("user"),
        layout: &user_layout,
        entries: &[
            wgpu::BindGroupEntry {
                binding: 0,
                resource: points.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 1,
                resource: results.as_entire_binding(),
            },
        ],
    });
    let mut enc = device.create_command_encoder(&Default::default());
    {
        let mut pass = enc.begin_compute_pass(&Default::default());
        pass.set_pipeline(&pipeline);
        pass.set_bind_group(0, &user_group, &[]);
        for (i, g) in groups.iter().enumerate() {
            pass.set_bind_group(i as u32 + 1, g.1, &[]);
        }
        pass.dispatch_workgroups((inputs.len() as u32).div_ceil(64), 1, 1);
    }
    enc.copy_buffer_to_buffer(&results, 0, &readback, 0, bytes);
    queue.submit([enc.finish()]);
    readback
        .slice(..)
        .map_async(wgpu::MapMode::Read, |r| r.expect("mapping the results"));
    device
        .poll(wgpu::PollType::wait_indefinitely())
        .expect("device alive");
    let view = readback.slice(..).get_mapped_range().expect("mapped");
    bytemuck::pod_collect_to_vec(&view)
}

/// Two models in one shader, each under its own prefix at its own group (a SIREN as `left`
/// at 1, a sparse NGLOD as `right_2` at 2): naga validates the module, it runs, and each
/// name answers with its own model (against `eval_cpu`). Their sum and difference are written
/// too, as a scene would combine them.
#[test]
fn two_prefixed_models_share_one_shader() {
    let left = siren(
        SirenConfig {
            width: 16,
            hidden_layers: 2,
            omega0: 30.0,
        },
        5,
    );
    let right = nglod(sparse_small(), 6, None);
    let user = point_kernel(
        "let p = points[i].xyz;\n\
         let a = left_distance(p);\n\
         let b = right_2_distance(p);\n\
         let n = left_normal(p) + right_2_normal(p);\n\
         results[i] = vec4<f32>(a, b, min(a, b), n.x * 0.0 + a - b);",
    );
    let source = format!(
        "{}\n{}\n{user}",
        left.wgsl_with_prefix(1, "left").unwrap(),
        right.wgsl_with_prefix(2, "right_2").unwrap()
    );
    let module = validate(&source);
    // Nothing of either snippet is left under the default prefix.
    assert!(!source.contains("hwsdf_") && !source.contains("HWSDF_"));
    assert!(
        module
            .functions
            .iter()
            .any(|(_, f)| f.name.as_deref() == Some("left_distance"))
    );
    let gpu = gpu();
    let (gl, gr) = (
        left.bind_group(gpu.device()).unwrap(),
        right.bind_group(gpu.device()).unwrap(),
    );
    let pts = points(300, 21);
    let groups = [(&gl.layout, &gl.bind_group), (&gr.layout, &gr.bind_group)];
    let out = run_user_shader(gpu.device(), gpu.queue(), &source, &groups, &pts);
    let (cl, cr) = (left.eval_cpu(&pts), right.eval_cpu(&pts));
    let unit = 1.0 / left.normalization().scale;
    for (i, o) in out.iter().enumerate() {
        for (got, want, what) in [
            (o[0], cl[i], "left"),
            (o[1], cr[i], "right"),
            (o[2], cl[i].min(cr[i]), "min"),
            (o[3], cl[i] - cr[i], "difference"),
        ] {
            let err = (got - want).abs() / (unit * (1.0 + (want / unit).abs()));
            assert!(err < 1e-3, "{what} at point {i}: GPU {got} vs CPU {want}");
        }
    }
}

/// A prefix is an identifier, or a clear error: nothing else reaches the caller's shader.
#[test]
fn prefixes_that_are_not_identifiers_are_refused() {
    let sdf = nglod(NglodConfig::small(), 1, None);
    for bad in ["", "1abc", "_x", "a-b", "a b", "ünï", &"x".repeat(65)] {
        let err = sdf.wgsl_with_prefix(0, bad).unwrap_err();
        assert!(matches!(err, EmbedError::Prefix(_)), "{bad}: {err}");
        assert!(err.to_string().contains("identifier"), "{err}");
    }
    for good in ["a", "Bunny2", "scene_left", &"x".repeat(64)] {
        let snippet = sdf.wgsl_with_prefix(0, good).unwrap();
        validate(&snippet);
        assert!(snippet.contains(&format!("fn {good}_distance(")));
    }
    // The default prefix gives the plain snippet back.
    assert_eq!(sdf.wgsl_with_prefix(3, "hwsdf").unwrap(), sdf.wgsl(3));
}

/// The network's raw gradient magnitude at each point's clamped normalised image: where it is
/// tiny the normal's direction is ill-conditioned and is not compared.
fn gradient_norms(sdf: &NeuralSdf, pts: &[Vec3]) -> Vec<f32> {
    let n = sdf.normalization();
    let local: Vec<Vec3> = pts
        .iter()
        .map(|&p| n.to_normalized(p).clamp(Vec3::NEG_ONE, Vec3::ONE))
        .collect();
    let g = match sdf.network() {
        Network::Siren(s) => s.gradient_cpu(&local),
        Network::Nglod(m) => m.gradient_cpu(&local, sdf.lod()).unwrap(),
    };
    g.iter().map(|g| g.length()).collect()
}

/// GPU snippet vs `eval_cpu` / `eval_with_normals_cpu`, distances relative to the model's
/// scale. `max_normal_outliers` allows for ReLU and cell boundaries that f32 rounding puts on
/// different sides on the two paths (NGLOD's gradient is discontinuous there).
fn check_against_cpu(
    name: &str,
    sdf: &NeuralSdf,
    dist_tol: f32,
    normal_tol: f32,
    max_normal_outliers: usize,
) {
    let pts = points(777, 11);
    let t = std::time::Instant::now();
    let gpu_out = eval_on_gpu(sdf, &pts);
    eprintln!(
        "{name}: {} points on the GPU in {:.2?} (JIT included)",
        pts.len(),
        t.elapsed()
    );
    let cpu_d = sdf.eval_cpu(&pts);
    let cpu_n = sdf.eval_with_normals_cpu(&pts);
    let norms = gradient_norms(sdf, &pts);
    let unit = 1.0 / sdf.normalization().scale;
    let mut worst_d = 0f32;
    let mut worst_n = 0f32;
    let mut outliers = 0;
    for (i, ((g, &d), (_, n))) in gpu_out.iter().zip(&cpu_d).zip(&cpu_n).enumerate() {
        let err = (g[0] - d).abs() / (unit * (1.0 + (d / unit).abs()));
        worst_d = worst_d.max(err);
        assert!(
            err <= dist_tol,
            "{name}: point {i} {:?}: GPU {} vs CPU {d} (rel err {err})",
            pts[i],
            g[0]
        );
        let gn = Vec3::new(g[1], g[2], g[3]);
        let inside = sdf
            .normalization()
            .to_normalized(pts[i])
            .abs()
            .max_element()
            <= 1.0;
        if inside && norms[i] < 1e-3 {
            continue;
        }
        let e = (gn - *n).length();
        worst_n = worst_n.max(if e > normal_tol { 0.0 } else { e });
        if e > normal_tol {
            outliers += 1;
            eprintln!("{name}: normal outlier at {i}: GPU {gn} vs CPU {n}");
        }
        assert!(
            (gn.length() - 1.0).abs() < 1e-4,
            "{name}: GPU normal {gn} not unit"
        );
    }
    eprintln!(
        "{name}: worst rel distance error {worst_d:.2e}, worst normal error {worst_n:.2e}, {outliers} outliers"
    );
    assert!(
        outliers <= max_normal_outliers,
        "{name}: {outliers} normals differ by more than {normal_tol}"
    );
}

#[test]
fn siren_snippet_matches_cpu_on_gpu() {
    let sdf = siren(
        SirenConfig {
            width: 32,
            hidden_layers: 3,
            omega0: 30.0,
        },
        7,
    );
    check_against_cpu("siren 32x3", &sdf, 2e-5, 1e-3, 0);
}

#[test]
fn nglod_snippet_matches_cpu_on_gpu() {
    check_against_cpu(
        "nglod small",
        &nglod(NglodConfig::small(), 5, None),
        2e-5,
        1e-3,
        3,
    );
    check_against_cpu(
        "nglod small lod 2",
        &nglod(NglodConfig::small(), 5, Some(2)),
        2e-5,
        1e-3,
        3,
    );
    // The band's vertex table at binding 1, and points inside and outside the band.
    check_against_cpu(
        "nglod small, finest level sparse",
        &nglod(sparse_small(), 5, None),
        2e-5,
        1e-3,
        3,
    );
}

#[test]
fn hashgrid_snippet_matches_cpu_on_gpu() {
    // Concatenated levels, the coarse ones indexed, the fine ones hashed.
    check_against_cpu(
        "hashgrid small",
        &nglod(NglodConfig::hashgrid_small(), 5, None),
        2e-5,
        1e-3,
        3,
    );
}

/// `bind_group` on a device the caller created with plain wgpu and default limits, not through
/// HW SDF's context: the snippet evaluates the same there.
#[test]
fn bind_group_works_on_a_callers_own_device() {
    let instance =
        wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
    let adapter = pollster::block_on(wgpu::util::initialize_adapter_from_env_or_default(
        &instance, None,
    ))
    .expect("an adapter (lavapipe in CI)");
    let (device, queue) =
        pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor::default())).unwrap();
    let sdf = nglod(
        NglodConfig {
            resolutions: vec![2, 5],
            feature_dim: 2,
            hidden: 4,
            seed: 9,
            sparse_levels: 0,
            band_cells: 0,
            encoding: Default::default(),
        },
        9,
        None,
    );
    let pts = points(130, 4);
    let out = eval_on_device(&device, &queue, &sdf, &pts);
    let cpu = sdf.eval_with_normals_cpu(&pts);
    let unit = 1.0 / sdf.normalization().scale;
    for (g, (d, _)) in out.iter().zip(&cpu) {
        assert!(
            (g[0] - d).abs() <= 2e-5 * unit * (1.0 + (d / unit).abs()),
            "{} vs {d}",
            g[0]
        );
    }
}

/// Two scenes and a single model in one user shader, each under its own prefix at its own
/// group: a scene with a model and primitives (`city`, group 1), a scene of primitives alone
/// (`robot`, group 2, no weights) and the model alone (`single`, group 3). naga validates the
/// module, it runs, and each name answers as its CPU reference does.
#[test]
fn two_prefixed_scenes_and_a_model_share_one_shader() {
    use glam::Quat;
    use sdf_nn::serve::scene::{Primitive, Scene, SceneNode, Transform};
    use std::sync::Arc;
    let model = Arc::new(nglod(NglodConfig::small(), 8, None));
    let place = Transform::new(Vec3::new(0.5, 0.0, 0.0), Quat::from_rotation_y(0.7), 0.5);
    let city = Scene::new(SceneNode::SmoothUnion {
        k: 0.3,
        children: vec![
            SceneNode::model(model.clone(), place),
            SceneNode::primitive(
                Primitive::Box {
                    half_extents: Vec3::new(0.4, 0.2, 0.3),
                },
                Transform::from_translation(Vec3::new(-0.5, 0.1, 0.0)),
            ),
        ],
    })
    .unwrap();
    let robot = Scene::new(SceneNode::Difference(vec![
        SceneNode::primitive(
            Primitive::Torus {
                major: 0.8,
                minor: 0.25,
            },
            Transform::IDENTITY,
        ),
        SceneNode::primitive(
            Primitive::Sphere { radius: 0.4 },
            Transform::from_translation(Vec3::X * 0.8),
        ),
    ]))
    .unwrap();
    let user = point_kernel(
        "let p = points[i].xyz;\n\
         let n = city_normal(p);\n\
         results[i] = vec4<f32>(city_distance(p), robot_distance(p), single_distance(p), dot(n, n));",
    );
    let gpu = gpu();
    let limits = gpu.device().limits();
    let source = format!(
        "{}\n{}\n{}\n{user}",
        city.wgsl_with_prefix(1, "city", &limits).unwrap(),
        robot.wgsl_with_prefix(2, "robot", &limits).unwrap(),
        model.wgsl_with_prefix(3, "single").unwrap()
    );
    validate(&source);
    assert!(!source.contains("hwsdf_") && !source.contains("HWSDF_"));
    let (gc, gr) = (
        city.bind_group(gpu.device()).unwrap(),
        robot.bind_group(gpu.device()).unwrap(),
    );
    assert!(
        gr.params.is_empty(),
        "a scene of primitives binds no weights"
    );
    let gm = model.bind_group(gpu.device()).unwrap();
    let groups = [
        (&gc.layout, &gc.bind_group),
        (&gr.layout, &gr.bind_group),
        (&gm.layout, &gm.bind_group),
    ];
    let pts = points(300, 23);
    let out = run_user_shader(gpu.device(), gpu.queue(), &source, &groups, &pts);
    let (dc, dr, dm) = (
        city.distances(&pts, 0.0),
        robot.distances(&pts, 0.0),
        model.eval_cpu(&pts),
    );
    for (i, o) in out.iter().enumerate() {
        for (got, want, what) in [
            (o[0], dc[i], "city"),
            (o[1], dr[i], "robot"),
            (o[2], dm[i], "single"),
        ] {
            assert!(
                (got - want).abs() <= 1e-4 * (1.0 + want.abs()),
                "{what} at point {i} {}: GPU {got} vs CPU {want}",
                pts[i]
            );
        }
        assert!(
            (o[3] - 1.0).abs() < 1e-3,
            "city's normal at point {i} has length² {}",
            o[3]
        );
    }
}

/// A scene snippet's local Lipschitz lookups against `LocalLipschitz::bound`: the model's
/// (`{prefix}_m0_lip`, normalised point and gap) and a leaf's (`{prefix}_leaf_1_lip`, a point
/// and a gap in scene units, the leaf turned, moved and at half scale), at points inside and
/// outside the box, with gaps from tiny (the cell's bound) to large (the block's, then the
/// estimate). In the same shader, the culling's floors: the model's cell floor
/// (`{prefix}_m0_floor`, against `CellFloors::at`) and the placed leaf's lower bound
/// (`{prefix}_leaf_1_lb`), which lies below the leaf's value everywhere.
#[test]
fn scene_snippets_look_up_the_cpus_local_bounds_and_floors() {
    use glam::Quat;
    use sdf_nn::serve::scene::{Scene, SceneNode, Transform};
    use std::sync::Arc;
    let spot = Arc::new(NeuralSdf::load(support::example_model("spot.nglod.safetensors")).unwrap());
    let placed = Transform::new(Vec3::new(0.4, -0.3, 0.2), Quat::from_rotation_y(0.9), 0.5);
    let scene = Scene::new(SceneNode::Union(vec![
        SceneNode::model(spot.clone(), Transform::IDENTITY),
        SceneNode::model(spot.clone(), placed),
    ]))
    .unwrap();
    let user = point_kernel(
        "let q = points[i];\n\
         results[i] = vec4<f32>(s_m0_lip(q.xyz, q.w), s_leaf_1_lip(q.xyz, q.w), \
         s_m0_floor(clamp(q.xyz, vec3<f32>(-1.0), vec3<f32>(1.0))), s_leaf_1_lb(q.xyz));",
    );
    let gpu = gpu();
    let limits = gpu.device().limits();
    let source = format!(
        "{}\n{user}",
        scene.wgsl_with_prefix(1, "s", &limits).unwrap()
    );
    validate(&source);
    let group = scene.bind_group(gpu.device()).unwrap();
    let mut rng = Pcg64::seed_from_u64(29);
    let inputs: Vec<[f32; 4]> = (0..4000)
        .map(|_| {
            [
                rng.random_range(-1.3..1.3),
                rng.random_range(-1.3..1.3),
                rng.random_range(-1.3..1.3),
                10f32.powf(rng.random_range(-4.0..0.0))
                    * if rng.random_bool(0.5) { 1.0 } else { -1.0 },
            ]
        })
        .collect();
    // Each input is a point (xyz) and a gap (w).
    let groups = [(&group.layout, &group.bind_group)];
    let out = run_user_shader_vec4(gpu.device(), gpu.queue(), &source, &groups, &inputs);
    let local = scene.model_local_lipschitz(0).unwrap();
    let n = spot.normalization();
    let points: Vec<Vec3> = inputs.iter().map(|i| Vec3::new(i[0], i[1], i[2])).collect();
    // The leaf's mesh frame (its placement undone).
    let mesh: Vec<Vec3> = points.iter().map(|&x| placed.apply_inverse(x)).collect();
    let (mut model_differ, mut leaf_differ, mut below_estimate) = (0, 0, 0);
    for (((input, x), mesh), o) in inputs.iter().zip(&points).zip(&mesh).zip(&out) {
        let g = input[3];
        let want = local.bound(*x, g).max(1.0);
        model_differ += usize::from(o[0] != want);
        below_estimate += usize::from(want < local.global());
        // The leaf: its mesh frame → normalised; the gap over the leaf's scale, times the
        // normalisation's.
        let q = n.to_normalized(*mesh);
        let want = local.bound(q, g / placed.scale * n.scale).max(1.0);
        leaf_differ += usize::from((o[1] - want).abs() > 1e-6 * want);
    }
    // None differ on lavapipe; rounding could put a ball just inside a cell on one side and
    // just outside on the other.
    assert!(
        model_differ <= 4,
        "{model_differ} of 4000 model lookups differ"
    );
    assert!(
        leaf_differ <= 4,
        "{leaf_differ} of 4000 leaf lookups differ"
    );
    assert!(
        below_estimate > 1000,
        "only {below_estimate} lookups below the estimate"
    );
    // The floors: the leaf's bound is (|x − c| + the floor at c) in normalised units, c the
    // clamp of its normalised point x, in scene units.
    let floors = scene.model_cell_floors(0).unwrap();
    let values = spot.eval_cpu(&mesh);
    let (mut floor_differ, mut lb_differ, mut above, mut tight) = (0, 0, 0, 0);
    for (((x, mesh), value), o) in points.iter().zip(&mesh).zip(&values).zip(&out) {
        let c = x.clamp(Vec3::NEG_ONE, Vec3::ONE);
        floor_differ += usize::from(o[2] != floors.at(c));
        let q = n.to_normalized(*mesh);
        let qc = q.clamp(Vec3::NEG_ONE, Vec3::ONE);
        let want = placed.scale * (q.distance(qc) + floors.at(qc)) / n.scale;
        lb_differ += usize::from((o[3] - want).abs() > 1e-5 * (1.0 + want.abs()));
        let value = placed.scale * value;
        above += usize::from(o[3] > value + 1e-6);
        // Two cells' sides (normalised), against the box's one floor's 0.4 plus the value.
        tight += usize::from(value - o[3] < 0.2 * placed.scale / n.scale);
    }
    assert!(floor_differ <= 4, "{floor_differ} of 4000 floors differ");
    assert!(lb_differ <= 4, "{lb_differ} of 4000 leaf floors differ");
    assert_eq!(above, 0, "{above} leaf floors above the leaf's value");
    assert!(
        tight > 3600,
        "only {tight} of 4000 leaf floors within 0.2 of the value"
    );
}
