//! Tests of the serving path against the CPU reference.

use glam::Vec3;

use crate::serve::network::GpuNetwork;
use crate::{GpuContext, NeuralSdf, Nglod, NglodConfig, Normalization, Siren, SirenConfig};

fn gpu() -> &'static GpuContext {
    GpuContext::shared().expect("a GPU adapter (lavapipe in CI)")
}

fn sdf(file: crate::ModelFile) -> NeuralSdf {
    NeuralSdf::from_model_file(file).unwrap()
}

/// Points in and around the model's cube, with an odd count.
fn points() -> Vec<Vec3> {
    (0..301)
        .map(|i| {
            let t = i as f32 * 0.37;
            Vec3::new(t.sin(), (1.3 * t).cos(), (0.7 * t).sin()) * 1.2
        })
        .collect()
}

/// `write_points` packs every point (a length that is not 16 bytes per point panics).
#[test]
fn write_points_packs_vec4() {
    for n in [0, 1, 2, 301] {
        let pts = &points()[..n];
        let mut bytes = vec![0xAAu8; n * 16];
        super::write_points(wgpu::WriteOnly::from_mut(bytes.as_mut_slice()), pts);
        let want: Vec<[f32; 4]> = pts.iter().map(|p| [p.x, p.y, p.z, 1.0]).collect();
        assert_eq!(bytes, bytemuck::cast_slice::<_, u8>(&want), "{n} points");
    }
    let short = std::panic::catch_unwind(|| {
        let mut bytes = vec![0u8; 16];
        super::write_points(
            wgpu::WriteOnly::from_mut(bytes.as_mut_slice()),
            &points()[..2],
        );
    });
    assert!(short.is_err(), "a view too short for the points must panic");
}

fn assert_close(got: &[f32], want: &[f32], what: &str) {
    assert_eq!(got.len(), want.len(), "{what}");
    for (i, (a, b)) in got.iter().zip(want).enumerate() {
        assert!(
            (a - b).abs() <= 1e-4 * b.abs().max(1.0),
            "{what} {i}: {a} vs {b}"
        );
    }
}

/// Serves model file `a`, checks it, uploads `b`'s parameters into its GPU network with
/// `upload`, and checks that the next query answers with `b`'s values.
fn check_upload(
    what: &str,
    a: crate::ModelFile,
    b: crate::ModelFile,
    upload: impl FnOnce(&mut GpuNetwork) -> Result<(), crate::NeuralSdfError>,
) {
    let (gpu, pts) = (gpu(), points());
    let served = sdf(a);
    let want_b = sdf(b).eval_cpu(&pts);
    let got = served.eval(gpu, &pts).unwrap();
    assert_close(&got, &served.eval_cpu(&pts), what);
    served.with_gpu(gpu, |net, _| upload(net)).unwrap();
    let got = served.eval(gpu, &pts).unwrap();
    assert_close(&got, &want_b, &format!("{what} after upload"));
}

/// A served model's networks skip refreshing their derived weights (NGLOD's MLP uniform,
/// SIREN's packed row-blocked weights) on every query; new parameters uploaded into them must
/// still reach the next query.
#[test]
fn frozen_networks_follow_uploads() {
    let gpu = gpu();
    let id = Normalization::identity();
    let a = Nglod::new(NglodConfig::small()).unwrap();
    // Same configuration, other parameters (the MLP's included).
    let b = Nglod::from_params(
        a.config().clone(),
        a.params().iter().map(|&x| 0.25 - 0.5 * x).collect(),
    )
    .unwrap();
    let (fa, fb) = (
        a.to_model_file(id, serde_json::Value::Null),
        b.to_model_file(id, serde_json::Value::Null),
    );
    // What the file holds (its grids rounded to f16).
    let b = Nglod::from_model_file(&fb).unwrap();
    check_upload("nglod", fa, fb, |net| match net {
        GpuNetwork::Nglod(m) => Ok(m.upload(gpu, &b)?),
        GpuNetwork::Siren(_) => unreachable!(),
    });
    let a = Siren::new(SirenConfig::small(), 1).unwrap();
    let b = Siren::new(SirenConfig::small(), 2).unwrap();
    let (fa, fb) = (
        a.to_model_file(id, serde_json::Value::Null),
        b.to_model_file(id, serde_json::Value::Null),
    );
    check_upload("siren", fa, fb, |net| match net {
        GpuNetwork::Siren(s) => Ok(s.upload(gpu, &b)?),
        GpuNetwork::Nglod(_) => unreachable!(),
    });
}

/// The serving types cross threads (a renderer's or a planner's workers): no field, such
/// as the commands recorded ahead, may take that away.
#[test]
fn serving_types_are_send_and_sync() {
    fn send_sync<T: Send + Sync>() {}
    send_sync::<crate::QueryBuffers>();
    send_sync::<crate::serve::query::QueryTicket>();
    send_sync::<NeuralSdf>();
}

/// `submit_query` records the next query while this one runs and submits those commands
/// when the next query has the same size and level of detail. A query of another size,
/// another level of detail, or after another recording into the buffers (which rewrites
/// their uniforms) must not run them; plain and timed queries alternate, as the reports
/// run them. NGLOD's query is one dispatch on every adapter.
#[test]
fn prepared_queries_answer_like_fresh_ones() {
    use crate::serve::query::{QueryBuffers, QueryBuffersDescriptor, QueryTransfer};
    let gpu = gpu();
    if !gpu.maps_storage() {
        eprintln!("skipped: {} does not map storage buffers", gpu.describe());
        return;
    }
    let mut model = Nglod::new(NglodConfig::small()).unwrap();
    if model.needs_bands() {
        model.place_bands(|p| (p.length() - 0.6).abs()).unwrap();
    }
    let mut served = sdf(model.to_model_file(Normalization::identity(), serde_json::Value::Null));
    let mut buffers = served
        .create_query_buffers(
            gpu,
            &QueryBuffersDescriptor {
                capacity: 301,
                transfer: QueryTransfer::Mapped,
                ..Default::default()
            },
        )
        .unwrap();
    // Every query gets points of its own, so stale commands show as stale results.
    let sets: Vec<Vec<Vec3>> = (0..8)
        .map(|k| {
            points()
                .iter()
                .map(|p| *p * (1.0 - 0.07 * k as f32))
                .collect()
        })
        .collect();
    let query = |served: &NeuralSdf, buffers: &mut QueryBuffers, pts: &[Vec3], timed: bool| {
        let ticket = served.submit_query_timed(gpu, buffers, pts, timed).unwrap();
        let mut got = Vec::new();
        buffers.wait(gpu, ticket).unwrap().extend_values(&mut got);
        if timed {
            served.read_query_ns(gpu).unwrap();
        }
        assert_close(
            &got,
            &served.eval_cpu(pts),
            &format!("{} points", pts.len()),
        );
    };
    for (i, pts) in sets[..4].iter().enumerate() {
        query(&served, &mut buffers, pts, i % 2 == 1);
    }
    // The third and fourth ran on commands recorded by the first and second.
    assert_eq!(buffers.prepared_used(), 2);
    // Another size.
    query(&served, &mut buffers, &sets[4][..100], false);
    assert_eq!(buffers.prepared_used(), 2);
    // A recording of 7 points in between rewrites the uniforms: the commands recorded for
    // 100 points would answer only 7 of them.
    let mut enc = gpu.device().create_command_encoder(&Default::default());
    served.record_query(gpu, &mut enc, &mut buffers, 7).unwrap();
    gpu.queue().submit([enc.finish()]);
    gpu.wait().unwrap();
    query(&served, &mut buffers, &sets[5][..100], false);
    assert_eq!(buffers.prepared_used(), 2);
    query(&served, &mut buffers, &sets[6][..100], false);
    assert_eq!(buffers.prepared_used(), 3);
    // Another level of detail.
    served.set_lod(Some(1)).unwrap();
    query(&served, &mut buffers, &sets[7][..100], false);
    assert_eq!(buffers.prepared_used(), 3);
}

/// A SIREN query larger than one of the network's launches takes the path that splits it
/// and copies through the network's workspace; it must agree with the bound one.
#[test]
fn siren_queries_beyond_one_launch_are_split() {
    let gpu = gpu();
    let siren = Siren::new(SirenConfig::small(), 3).unwrap();
    let served = sdf(siren.to_model_file(Normalization::identity(), serde_json::Value::Null));
    let pts = points();
    let want = served.eval_cpu(&pts);
    assert_close(&served.eval(gpu, &pts).unwrap(), &want, "one launch");
    served
        .with_gpu(gpu, |net, _| {
            if let GpuNetwork::Siren(s) = net {
                let options = crate::siren::SirenGpuOptions {
                    max_points_per_launch: 64,
                    ..*s.options()
                };
                s.set_options(gpu, &options)?;
            }
            Ok(())
        })
        .unwrap();
    // Another count: the launches bound for 301 points would otherwise be reused.
    let pts = &pts[..300];
    let got = served.eval(gpu, pts).unwrap();
    assert_close(&got, &want[..300], "split into launches of 64");
    let normals = served.eval_with_normals(gpu, pts).unwrap();
    let want_n = served.eval_with_normals_cpu(pts);
    for (i, ((da, na), (db, nb))) in normals.iter().zip(&want_n).enumerate() {
        assert!(
            (da - db).abs() <= 1e-4 * db.abs().max(1.0),
            "{i}: {da} vs {db}"
        );
        assert!((*na - *nb).length() < 1e-3, "{i}: {na} vs {nb}");
    }
}

/// A SIREN whose kernels run an inference in one dispatch answers queries in that one
/// dispatch, points to results (the tiled fused kernel here; the cooperative-matrix one is
/// checked where the adapter has it, in `tests/siren_gpu.rs`); the row-blocked kernels, and
/// a capacity beyond the fused kernel's batches, go through `query.wgsl`'s two ends. Both
/// answer alike, in mesh coordinates, inside the box and beyond it.
#[test]
fn siren_queries_take_one_dispatch_where_the_kernels_allow() {
    let gpu = gpu();
    let norm = Normalization {
        center: Vec3::new(-2.0, 0.5, 1.0).as_dvec3(),
        scale: 0.25,
    };
    let siren = Siren::new(SirenConfig::small(), 5).unwrap();
    let pts: Vec<Vec3> = points().iter().map(|&p| norm.to_original(p)).collect();
    for (kernels, capacity, one_dispatch) in [
        (crate::siren::LayerKernels::Tiled, 400, true),
        (crate::siren::LayerKernels::RowBlocked, 400, false),
        // Past the fused kernel's batches on a CPU adapter; GPUs fuse every batch.
        (crate::siren::LayerKernels::Tiled, 10_000, !gpu.is_cpu()),
    ] {
        let mut served = sdf(siren.to_model_file(norm, serde_json::Value::Null));
        served.set_siren_kernels(kernels).unwrap();
        for outputs in [
            crate::QueryOutputs::Values,
            crate::QueryOutputs::ValuesAndNormals,
        ] {
            let desc = crate::QueryBuffersDescriptor {
                capacity,
                outputs,
                ..Default::default()
            };
            let mut buffers = served.create_query_buffers(gpu, &desc).unwrap();
            assert_eq!(
                matches!(buffers.kernels, super::Kernels::Siren(_)),
                one_dispatch,
                "{kernels:?} capacity {capacity}"
            );
            let what = format!("{kernels:?} {outputs:?} capacity {capacity}");
            let values = served.eval_cpu(&pts);
            let normals = served.eval_with_normals_cpu(&pts);
            // Counts that change between queries: the one dispatch rewrites its row count.
            for n in [301, 17, 300] {
                let ticket = served.submit_query(gpu, &mut buffers, &pts[..n]).unwrap();
                let got = buffers.wait(gpu, ticket).unwrap().floats();
                let what = format!("{what} n={n}");
                if outputs == crate::QueryOutputs::Values {
                    assert_close(&got, &values[..n], &what);
                    continue;
                }
                assert_eq!(got.len(), 4 * n, "{what}");
                for (i, (g, (d, n))) in got.chunks_exact(4).zip(&normals).enumerate() {
                    assert!((g[0] - d).abs() <= 1e-4 * d.abs().max(1.0), "{what} {i}");
                    let gn = Vec3::new(g[1], g[2], g[3]);
                    assert!((gn - *n).length() < 1e-3, "{what} {i}: {gn} vs {n}");
                }
            }
        }
    }
}

/// The fused kernel's query mode with several register blocks of rows per invocation: a
/// narrow network's workgroup then holds more rows than invocations, and the head and the
/// normals' finish handle two or three rows each.
#[test]
fn siren_one_dispatch_queries_with_row_blocks() {
    let gpu = gpu();
    let norm = Normalization {
        center: Vec3::new(0.5, 1.0, -1.5).as_dvec3(),
        scale: 2.0,
    };
    let cfg = SirenConfig {
        width: 20,
        hidden_layers: 2,
        omega0: 30.0,
    };
    let siren = Siren::new(cfg, 8).unwrap();
    let pts: Vec<Vec3> = points().iter().map(|&p| norm.to_original(p)).collect();
    for blocks in 1..=3 {
        let mut served = sdf(siren.to_model_file(norm, serde_json::Value::Null));
        served
            .set_siren_kernels(crate::siren::LayerKernels::Tiled)
            .unwrap();
        served
            .with_gpu(gpu, |net, _| {
                if let GpuNetwork::Siren(s) = net {
                    let options = crate::siren::SirenGpuOptions {
                        fused_row_blocks: blocks,
                        ..*s.options()
                    };
                    s.set_options(gpu, &options)?;
                    assert_eq!(s.fused_row_blocks(gpu), Some(blocks));
                }
                Ok(())
            })
            .unwrap();
        let what = format!("{blocks} row blocks");
        assert_close(
            &served.eval(gpu, &pts).unwrap(),
            &served.eval_cpu(&pts),
            &what,
        );
        let got = served.eval_with_normals(gpu, &pts).unwrap();
        for (i, ((d, n), (wd, wn))) in got
            .iter()
            .zip(served.eval_with_normals_cpu(&pts))
            .enumerate()
        {
            assert!(
                (d - wd).abs() <= 1e-4 * wd.abs().max(1.0),
                "{what} {i}: {d} vs {wd}"
            );
            assert!((*n - wn).length() < 1e-3, "{what} {i}: {n} vs {wn}");
        }
    }
}

/// Changing a SIREN's kernels rebuilds its GPU side under a new identity: query buffers
/// made before are refused, new ones answer on the new kernels. NGLOD has no kernels to
/// choose.
#[test]
fn siren_kernels_change_refuses_old_buffers() {
    let gpu = gpu();
    let id = Normalization::identity();
    let siren = Siren::new(SirenConfig::small(), 4).unwrap();
    let mut served = sdf(siren.to_model_file(id, serde_json::Value::Null));
    let pts = points();
    let want = served.eval_cpu(&pts);
    let desc = crate::QueryBuffersDescriptor {
        capacity: pts.len() as u32,
        space: crate::QuerySpace::Normalized,
        ..Default::default()
    };
    let mut old = served.create_query_buffers(gpu, &desc).unwrap();
    served
        .set_siren_kernels(crate::siren::LayerKernels::Tiled)
        .unwrap();
    assert!(matches!(
        served.submit_query(gpu, &mut old, &pts),
        Err(crate::NeuralSdfError::Query(crate::QueryError::Foreign))
    ));
    let mut new = served.create_query_buffers(gpu, &desc).unwrap();
    let ticket = served.submit_query(gpu, &mut new, &pts).unwrap();
    let got = new.wait(gpu, ticket).unwrap().floats();
    assert_close(&got, &want, "tiled kernels");
    served
        .with_gpu(gpu, |net, _| match net {
            GpuNetwork::Siren(s) => {
                assert!(s.runs_tiled());
                Ok(())
            }
            GpuNetwork::Nglod(_) => unreachable!(),
        })
        .unwrap();
    let nglod = Nglod::new(NglodConfig::small()).unwrap();
    let mut served = sdf(nglod.to_model_file(id, serde_json::Value::Null));
    assert!(matches!(
        served.set_siren_kernels(crate::siren::LayerKernels::Tiled),
        Err(crate::NeuralSdfError::NoLayerKernels("nglod"))
    ));
}

/// The query stages' uniforms have the layout `query.wgsl` reads.
#[test]
fn query_uniforms_mirror_the_shader() {
    crate::shaders::assert_mirrors!(
        super::QueryUniforms,
        crate::shaders::QUERY,
        "Query",
        [n_points, streams, normals, scale, center]
    );
}

/// The one-point-per-subgroup kernel (`QueryKernel::PerSubgroup`) against the CPU, distances
/// and distances with normals in mesh coordinates, on networks whose every width matters to
/// it: NGLOD with 6 features (a partial `vec4` of inputs), 40 hidden units (not a multiple of
/// any subgroup's width) and a sparse finest level; a hash grid of 5 levels (more than the
/// 8-lane groups of a 32-wide subgroup), the finer ones hashed. 301 points: the last
/// workgroup is part empty.
#[test]
fn subgroup_queries_match_the_cpu() {
    use crate::serve::query::{QueryBuffersDescriptor, QueryKernel, QueryOutputs};
    let gpu = gpu();
    if gpu.subgroups_within(64).is_none() {
        eprintln!("skipped: {} has no usable subgroups", gpu.describe());
        return;
    }
    let mut sparse = Nglod::new(NglodConfig {
        resolutions: vec![2, 4, 8, 16],
        feature_dim: 6,
        hidden: 40,
        seed: 5,
        sparse_levels: 1,
        ..NglodConfig::small()
    })
    .unwrap();
    sparse.place_bands(|p| (p.length() - 0.5).abs()).unwrap();
    let hashed = Nglod::new(NglodConfig::hashgrid(5, 4, 40, 2, 11, 24)).unwrap();
    let n = Normalization {
        center: glam::DVec3::new(0.2, -0.1, 0.3),
        scale: 0.8,
    };
    let pts = points();
    for (name, model) in [("nglod", sparse), ("hashgrid", hashed)] {
        let served = sdf(model.to_model_file(n, serde_json::Value::Null));
        for outputs in [QueryOutputs::Values, QueryOutputs::ValuesAndNormals] {
            let mut buffers = served
                .create_query_buffers(
                    gpu,
                    &QueryBuffersDescriptor {
                        capacity: pts.len() as u32,
                        outputs,
                        kernel: Some(QueryKernel::PerSubgroup),
                        ..Default::default()
                    },
                )
                .unwrap();
            let ticket = served.submit_query(gpu, &mut buffers, &pts).unwrap();
            let results = buffers.wait(gpu, ticket).unwrap();
            if outputs == QueryOutputs::Values {
                let mut got = Vec::new();
                results.extend_values(&mut got);
                assert_close(&got, &served.eval_cpu(&pts), name);
                continue;
            }
            let mut got = Vec::new();
            results.extend_values_and_normals(&mut got);
            let want = served.eval_with_normals_cpu(&pts);
            for (i, ((d, normal), (wd, wnormal))) in got.iter().zip(&want).enumerate() {
                assert!(
                    (d - wd).abs() <= 1e-4 * wd.abs().max(1.0),
                    "{name} {i}: {d} vs {wd}"
                );
                assert!(
                    normal.abs_diff_eq(*wnormal, 2e-3),
                    "{name} {i}: normal {normal} vs {wnormal}"
                );
            }
        }
    }
}
