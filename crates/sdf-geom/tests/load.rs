//! Loading real meshes, and every error case of the loaders.

mod common;

use common::{Gltf, IDENTITY, cube, data, temp_dir, write, write_gltf};
use glam::Vec3;
use sdf_geom::{GeomError, Mesh, SignedDistance, load_mesh};

#[test]
fn loads_obj_meshes_with_reports() {
    let (m, r) = load_mesh(data("spot.obj")).unwrap();
    assert_eq!((r.format, r.triangles, r.vertices), ("obj", 5856, 2930));
    assert_eq!(m.triangles.len(), 5856);
    assert!(r.warnings.is_empty());

    // Quads are fan-triangulated and counted; the one face repeated with the opposite
    // orientation is kept and reported.
    let (m, r) = load_mesh(data("suzanne.obj")).unwrap();
    assert_eq!(r.polygons_triangulated, 468);
    assert_eq!(m.triangles.len(), 968);
    assert_eq!(r.opposite_duplicate_faces, 1);

    // spider: 56 zero-area faces dropped and counted; its missing spider.mtl is only a warning.
    let (m, r) = load_mesh(data("spider.obj")).unwrap();
    assert_eq!(r.input_triangles, 1368);
    assert_eq!(r.degenerate_faces, 56);
    assert_eq!(m.triangles.len(), 1368 - 56);
    assert_eq!(
        r.triangles + r.degenerate_faces + r.duplicate_faces,
        r.input_triangles
    );
    assert!(r.warnings.iter().any(|w| w.contains("spider.mtl")), "{r:?}");
    m.validate().unwrap();
}

#[test]
fn loads_glb_with_instances() {
    let (m, r) = load_mesh(data("duck.glb")).unwrap();
    assert_eq!((r.format, r.triangles, r.instances), ("glb", 4212, 1));
    m.validate().unwrap();

    // pins.glb: 2 meshes instanced by 7 mesh nodes; every instance counts.
    let (m, r) = load_mesh(data("pins.glb")).unwrap();
    assert_eq!(r.instances, 7);
    assert_eq!(m.triangles.len(), 3408);
}

#[test]
fn extension_dispatch_is_case_insensitive() {
    let dir = temp_dir("case");
    let src = std::fs::read(data("suzanne.obj")).unwrap();
    let p = write(&dir, "SUZANNE.OBJ", src);
    assert_eq!(load_mesh(p).unwrap().0.triangles.len(), 968);
}

#[test]
fn gltf_node_transforms_instances_strips_fans_and_mirroring() {
    let (v, t) = cube();
    let dir = temp_dir("gltf");
    // Two instances: identity, and translated by +3 in x.
    let mut shifted = IDENTITY;
    shifted[12] = 3.0;
    let p = write_gltf(
        &dir,
        "two.gltf",
        &Gltf {
            positions: &v,
            indices: Some(&t),
            matrices: vec![IDENTITY, shifted],
            ..Default::default()
        },
    );
    let (m, r) = load_mesh(&p).unwrap();
    assert_eq!((r.instances, r.triangles), (2, 24));
    let b = m.bounds();
    assert_eq!((b.min, b.max), (Vec3::ZERO, Vec3::new(4.0, 1.0, 1.0)));
    let sdf = SignedDistance::new(&m).unwrap();
    assert!(sdf.signed_distance(Vec3::new(3.5, 0.5, 0.5)) < 0.0);
    assert!(sdf.signed_distance(Vec3::new(2.0, 0.5, 0.5)) > 0.0);

    // A mirroring transform (negative determinant) flips the winding back: inside stays inside.
    let mut mirror = IDENTITY;
    mirror[0] = -1.0;
    let p = write_gltf(
        &dir,
        "mirror.gltf",
        &Gltf {
            positions: &v,
            indices: Some(&t),
            matrices: vec![mirror],
            ..Default::default()
        },
    );
    let (m, _) = load_mesh(&p).unwrap();
    let sdf = SignedDistance::new(&m).unwrap();
    assert!((sdf.signed_distance(Vec3::new(-0.5, 0.5, 0.5)) + 0.5).abs() < 1e-6);

    // A strip and a fan covering the unit square in the z = 0 plane, normals +z.
    let quad = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [1.0, 1.0, 0.0],
    ];
    let p = write_gltf(
        &dir,
        "strip.gltf",
        &Gltf {
            positions: &quad,
            mode: 5,
            ..Default::default()
        },
    );
    let (m, r) = load_mesh(&p).unwrap();
    assert_eq!((r.strips_fans_converted, m.triangles.len()), (1, 2));
    for t in &m.triangles {
        let [a, b, c] = m.corners(t).unwrap();
        assert!(
            (b - a).cross(c - a).z > 0.0,
            "strip winding must alternate correctly"
        );
    }
    let fan = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [1.0, 1.0, 0.0],
        [0.0, 1.0, 0.0],
    ];
    let p = write_gltf(
        &dir,
        "fan.gltf",
        &Gltf {
            positions: &fan,
            indices: Some(&[0, 1, 2, 3]),
            mode: 6,
            ..Default::default()
        },
    );
    let (m, r) = load_mesh(&p).unwrap();
    assert_eq!((r.strips_fans_converted, m.triangles.len()), (1, 2));
    assert!((m.area() - 1.0).abs() < 1e-9);
    for t in &m.triangles {
        let [a, b, c] = m.corners(t).unwrap();
        assert!((b - a).cross(c - a).z > 0.0);
    }
}

#[test]
fn gltf_external_bin_and_missing_bin_is_named() {
    let (v, t) = cube();
    let dir = temp_dir("bin");
    let g = Gltf {
        positions: &v,
        indices: Some(&t),
        external: Some("cube%20data.bin"),
        ..Default::default()
    };
    // The URI is percent-encoded; the file on disk has a space.
    let (json, buf) = common::gltf_json(&g);
    write(&dir, "cube data.bin", &buf);
    let p = write(&dir, "cube.gltf", json);
    assert_eq!(load_mesh(&p).unwrap().0.triangles.len(), 12);

    std::fs::remove_file(dir.join("cube data.bin")).unwrap();
    let err = load_mesh(&p).unwrap_err();
    match &err {
        GeomError::MissingBuffer { buffer, .. } => {
            assert!(buffer.ends_with("cube data.bin"), "{buffer:?}")
        }
        e => panic!("expected MissingBuffer, got {e:?}"),
    }
    assert!(err.to_string().contains("cube data.bin"), "{err}");
}

#[test]
fn gltf_missing_texture_does_not_matter() {
    let (v, t) = cube();
    let dir = temp_dir("tex");
    let p = write_gltf(
        &dir,
        "textured.gltf",
        &Gltf {
            positions: &v,
            indices: Some(&t),
            image_uri: Some("does-not-exist.png"),
            ..Default::default()
        },
    );
    let (m, _) = load_mesh(&p).unwrap();
    assert_eq!(m.triangles.len(), 12);
}

#[test]
fn gltf_points_and_lines_are_rejected() {
    let (v, _) = cube();
    let dir = temp_dir("modes");
    for (mode, name) in [
        (0, "POINTS"),
        (1, "LINES"),
        (2, "LINE_LOOP"),
        (3, "LINE_STRIP"),
    ] {
        let p = write_gltf(
            &dir,
            &format!("m{mode}.gltf"),
            &Gltf {
                positions: &v,
                mode,
                ..Default::default()
            },
        );
        match load_mesh(&p) {
            Err(GeomError::UnsupportedPrimitiveMode { mode: m, .. }) => assert_eq!(m, name),
            other => panic!("mode {mode}: expected UnsupportedPrimitiveMode, got {other:?}"),
        }
    }
}

/// Points and lines beside triangles (a CAD export's edges drawn as LINES) are skipped with a
/// warning: the faces load. Only a file of nothing else is refused (above).
#[test]
fn gltf_lines_beside_triangles_are_skipped() {
    let (v, t) = cube();
    let dir = temp_dir("modes-mixed");
    let (json, _) = common::gltf_json(&Gltf {
        positions: &v,
        indices: Some(&t),
        ..Default::default()
    });
    // A LINES primitive (the cube's corners as segments) and a POINTS one before the faces.
    let json = json.replacen(
        r#""primitives":[{"#,
        r#""primitives":[{"attributes":{"POSITION":0},"mode":1},{"attributes":{"POSITION":0},"mode":0},{"#,
        1,
    );
    let (m, report) = load_mesh(write(&dir, "edges.gltf", json)).expect("the faces load");
    assert_eq!(m.triangles.len(), 12);
    for (k, mode) in [(0, "LINES"), (1, "POINTS")] {
        assert!(
            report
                .warnings
                .iter()
                .any(|w| w.contains(&format!("primitive {k}")) && w.contains(mode)),
            "{:?}",
            report.warnings
        );
    }
}

/// Loads a cube glTF that uses and requires the given extensions.
fn load_cube_with_extensions(
    dir: &std::path::Path,
    used: &[&str],
    required: &[&str],
) -> Result<(Mesh, sdf_geom::LoadReport), GeomError> {
    let (v, t) = cube();
    let name = format!("{}.gltf", used.join("+"));
    let p = write_gltf(
        dir,
        &name,
        &Gltf {
            positions: &v,
            indices: Some(&t),
            extensions_used: used,
            extensions_required: required,
            ..Default::default()
        },
    );
    load_mesh(&p)
}

/// An `Unsupported` error that names `ext`.
fn assert_unsupported(result: Result<(Mesh, sdf_geom::LoadReport), GeomError>, ext: &str) {
    let err = result.unwrap_err();
    assert!(
        matches!(&err, GeomError::Unsupported { feature, .. } if feature.contains(ext)),
        "{err:?}"
    );
    assert!(err.to_string().contains("not supported"), "{err}");
}

/// Draco and meshopt cannot be decoded here. Required, they are refused by name; listed as
/// used only, the file holds the geometry uncompressed as well (the specification's fallback),
/// which is read, with a warning, unless that copy is missing too.
#[test]
fn gltf_draco_and_meshopt_are_refused_unless_there_is_a_fallback() {
    let dir = temp_dir("compressed");
    let (v, t) = cube();
    for ext in ["KHR_draco_mesh_compression", "EXT_meshopt_compression"] {
        assert_unsupported(load_cube_with_extensions(&dir, &[ext], &[ext]), ext);
        let (m, r) = load_cube_with_extensions(&dir, &[ext], &[]).unwrap();
        assert_eq!(
            (m.vertices.len(), m.triangles.len() * 3),
            (v.len(), t.len())
        );
        assert!(
            r.warnings.iter().any(|w| w.contains("uncompressed copy")),
            "{r:?}"
        );
    }
    // The same files without their uncompressed copy.
    let edit = |ext: &str, change: &dyn Fn(&mut serde_json::Value)| {
        let p = dir.join(format!("{ext}.gltf"));
        let mut json: serde_json::Value =
            serde_json::from_slice(&std::fs::read(&p).unwrap()).unwrap();
        change(&mut json);
        let p = dir.join(format!("{ext}-no-fallback.gltf"));
        std::fs::write(&p, serde_json::to_vec(&json).unwrap()).unwrap();
        load_mesh(&p)
    };
    // Draco: a compressed primitive whose accessors keep their buffer views is read from them;
    // without the POSITION accessor's buffer view there is nothing to read.
    let draco = "KHR_draco_mesh_compression";
    let compress = |j: &mut serde_json::Value| {
        j["meshes"][0]["primitives"][0]["extensions"] =
            serde_json::json!({ draco: { "bufferView": 0, "attributes": { "POSITION": 0 } } });
    };
    let (m, r) = edit(draco, &compress).unwrap();
    assert_eq!(m.triangles.len() * 3, t.len());
    assert!(r.warnings.iter().any(|w| w.contains("Draco")), "{r:?}");
    let r = edit(draco, &|j| {
        compress(j);
        let pos = j["meshes"][0]["primitives"][0]["attributes"]["POSITION"]
            .as_u64()
            .unwrap() as usize;
        j["accessors"][pos]
            .as_object_mut()
            .unwrap()
            .remove("bufferView");
    });
    assert_unsupported(r, draco);
    // meshopt: a buffer that is only a placeholder for the compressed data.
    let meshopt = "EXT_meshopt_compression";
    let r = edit(meshopt, &|j| {
        j["buffers"][0]["extensions"] = serde_json::json!({ meshopt: { "fallback": true } });
    });
    assert_unsupported(r, meshopt);
}

#[test]
fn gltf_unknown_required_extensions_are_rejected_by_name() {
    let dir = temp_dir("required");
    for ext in ["VENDOR_made_up", "KHR_draco_mesh_compression"] {
        assert_unsupported(load_cube_with_extensions(&dir, &[ext], &[ext]), ext);
    }
    // Appearance-only extensions, and those read (GPU instancing and quantised attributes; this
    // cube uses neither), required or merely used, do not stop the geometry.
    for ext in [
        "KHR_materials_unlit",
        "KHR_texture_transform",
        "EXT_mesh_gpu_instancing",
        "KHR_mesh_quantization",
    ] {
        let (mesh, _) = load_cube_with_extensions(&dir, &[ext, "VENDOR_optional"], &[ext])
            .unwrap_or_else(|e| panic!("{ext}: {e}"));
        assert_eq!(mesh.triangles.len(), 12);
    }
}

#[test]
fn gltf_index_out_of_range() {
    let (v, _) = cube();
    let dir = temp_dir("gidx");
    let p = write_gltf(
        &dir,
        "idx.gltf",
        &Gltf {
            positions: &v,
            indices: Some(&[0, 1, 2, 0, 1, 8]),
            ..Default::default()
        },
    );
    // Named by file, mesh and primitive; the triangle and index are the primitive's own.
    let err = load_mesh(&p).unwrap_err();
    match &err {
        GeomError::GltfIndexOutOfRange {
            mesh: 0,
            mesh_name: None,
            primitive: 0,
            index: 8,
            vertex_count: 8,
            triangle: 1,
            ..
        } => {}
        other => panic!("expected GltfIndexOutOfRange, got {other:?}"),
    }
    assert_eq!(
        err.to_string(),
        format!(
            "{}: mesh 0 primitive 0: triangle 1 uses vertex index 8, but the primitive has only 8 vertices",
            p.display()
        )
    );
}

#[test]
fn gltf_parse_errors() {
    let dir = temp_dir("gparse");
    let p = write(&dir, "bad.gltf", "{ this is not json");
    assert!(matches!(load_mesh(&p), Err(GeomError::Parse { .. })));
    let p = write(&dir, "bad.glb", b"glTF\x02\x00\x00\x00garbage");
    assert!(matches!(load_mesh(&p), Err(GeomError::Parse { .. })));
}

#[test]
fn missing_file_and_unknown_extension() {
    let err = load_mesh(data("no-such-mesh.obj")).unwrap_err();
    assert!(matches!(err, GeomError::Io { .. }), "{err:?}");
    assert!(err.to_string().contains("no-such-mesh.obj"));
    // A directory is not read as a file.
    let dir = temp_dir("dir").join("folder.obj");
    std::fs::create_dir_all(&dir).unwrap();
    assert!(matches!(
        load_mesh(&dir),
        Err(GeomError::NotARegularFile {
            kind: "directory",
            ..
        })
    ));

    for name in ["mesh.stl", "mesh", "mesh.obj.bak"] {
        match load_mesh(name) {
            Err(GeomError::UnknownExtension { .. }) => {}
            other => panic!("{name}: expected UnknownExtension, got {other:?}"),
        }
    }
}

const TRI_OBJ: &str = "v 0 0 0\nv 1 0 0\nv 0 1 0\n";

#[test]
fn obj_parse_error_has_line() {
    let dir = temp_dir("oparse");
    let p = write(
        &dir,
        "bad.obj",
        format!("# header\n{TRI_OBJ}v 1.0 oops 2.0\nf 1 2 3\n"),
    );
    match load_mesh(&p) {
        Err(GeomError::Parse { line: Some(5), .. }) => {}
        other => panic!("expected a parse error at line 5, got {other:?}"),
    }
    let p = write(&dir, "badface.obj", format!("{TRI_OBJ}f 1 2 x\n"));
    let err = load_mesh(&p).unwrap_err();
    assert!(
        matches!(err, GeomError::Parse { line: Some(4), .. }),
        "{err:?}"
    );
    assert!(err.to_string().contains("line 4"), "{err}");
}

/// Line ends of every platform: LF, CRLF (Windows) and a lone CR (classic Mac OS), which
/// tobj alone reads as one line.
#[test]
fn obj_line_endings_of_every_platform() {
    let dir = temp_dir("eol");
    let lf = load_mesh(data("spot.obj")).unwrap().0;
    let text = std::fs::read_to_string(data("spot.obj")).unwrap();
    for (name, eol) in [("crlf.obj", "\r\n"), ("cr.obj", "\r")] {
        let p = write(&dir, name, text.replace('\n', eol));
        let (m, r) = load_mesh(&p).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(m.triangles, lf.triangles, "{name}");
        assert_eq!(m.vertices, lf.vertices, "{name}");
        assert!(r.warnings.is_empty(), "{name}: {r:?}");
    }
}

#[test]
fn obj_without_triangles() {
    let dir = temp_dir("notri");
    let p = write(&dir, "points.obj", TRI_OBJ);
    assert!(matches!(
        load_mesh(&p),
        Err(GeomError::NoTriangles { dropped: 0 })
    ));
    let p = write(&dir, "empty.obj", "");
    assert!(matches!(load_mesh(&p), Err(GeomError::NoTriangles { .. })));
    // Only a degenerate triangle (collinear corners): dropped, then nothing is left.
    let p = write(
        &dir,
        "degenerate.obj",
        "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n",
    );
    assert!(matches!(
        load_mesh(&p),
        Err(GeomError::NoTriangles { dropped: 1 })
    ));
    // Lines only.
    let p = write(&dir, "lines.obj", format!("{TRI_OBJ}l 1 2\nl 2 3\n"));
    assert!(matches!(load_mesh(&p), Err(GeomError::NoTriangles { .. })));
}

#[test]
fn obj_non_finite_coordinates() {
    let dir = temp_dir("nan");
    for (i, bad) in ["nan", "inf", "-inf", "NaN"].iter().enumerate() {
        let p = write(
            &dir,
            &format!("nan{i}.obj"),
            format!("v 0 0 0\nv 1 {bad} 0\nv 0 1 0\nf 1 2 3\n"),
        );
        match load_mesh(&p) {
            Err(GeomError::NonFiniteVertex { vertex: 1, .. }) => {}
            other => panic!("{bad}: expected NonFiniteVertex, got {other:?}"),
        }
    }
}

#[test]
fn obj_index_out_of_range() {
    let dir = temp_dir("oidx");
    let p = write(&dir, "idx.obj", format!("{TRI_OBJ}f 1 2 3\nf 1 2 7\n"));
    match load_mesh(&p) {
        Err(GeomError::ObjIndexOutOfRange {
            index: 7,
            vertex_count: 3,
            face: 1,
            line: 5,
            ..
        }) => {}
        other => panic!("expected ObjIndexOutOfRange, got {other:?}"),
    }
    // A relative index keeps its sign, and its line.
    let p = write(&dir, "neg.obj", format!("{TRI_OBJ}f -1 -2 -4\n"));
    let err = load_mesh(&p).unwrap_err();
    assert!(
        matches!(
            err,
            GeomError::ObjIndexOutOfRange {
                index: -4,
                line: 4,
                face: 0,
                vertex_count: 3,
                ..
            }
        ),
        "{err:?}"
    );
    assert_eq!(
        err.to_string(),
        format!(
            "{}: line 4: face 0 uses relative vertex index -4, but only 3 vertices come before it",
            p.display()
        )
    );
    let p = write(&dir, "neg99.obj", format!("{TRI_OBJ}f 1 2 -99\n"));
    let msg = load_mesh(&p).unwrap_err().to_string();
    assert!(
        msg.contains("neg99.obj: line 4:") && msg.contains("relative vertex index -99"),
        "{msg}"
    );
}

#[test]
fn obj_negative_indices_and_polygons() {
    let dir = temp_dir("neg");
    let p = write(
        &dir,
        "quad.obj",
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf -4 -3 -2 -1\n",
    );
    let (m, r) = load_mesh(&p).unwrap();
    assert_eq!((m.triangles.len(), r.polygons_triangulated), (2, 1));
    assert!((m.area() - 1.0).abs() < 1e-9);
}

#[test]
fn broken_or_missing_mtl_does_not_matter() {
    let dir = temp_dir("mtl");
    let p = write(
        &dir,
        "missing.obj",
        format!("mtllib nowhere.mtl\nusemtl red\n{TRI_OBJ}f 1 2 3\n"),
    );
    let (m, r) = load_mesh(&p).unwrap();
    assert_eq!(m.triangles.len(), 1);
    assert!(
        r.warnings.iter().any(|w| w.contains("nowhere.mtl")),
        "{r:?}"
    );
    // Names outside the file's folder are not looked for (a file must not learn which paths
    // exist elsewhere), and many missing ones make one warning.
    let many: String = (0..1000).map(|i| format!("mtllib lost{i}.mtl\n")).collect();
    let p = write(
        &dir,
        "probing.obj",
        format!("mtllib /etc/nowhere.mtl\nmtllib ../up.mtl\n{many}{TRI_OBJ}f 1 2 3\n"),
    );
    let (_, r) = load_mesh(&p).unwrap();
    assert_eq!(r.warnings.len(), 1, "{r:?}");
    assert!(r.warnings[0].contains("lost0.mtl and 999 more"), "{r:?}");
    // Nor through a link out of the folder, whether the name there exists or not.
    #[cfg(unix)]
    {
        let outside = temp_dir("mtl-outside");
        write(&outside, "there.mtl", "newmtl x\n");
        std::os::unix::fs::symlink(&outside, dir.join("out")).unwrap();
        for lib in ["out/there.mtl", "out/nowhere.mtl"] {
            let p = write(
                &dir,
                "linked.obj",
                format!("mtllib {lib}\n{TRI_OBJ}f 1 2 3\n"),
            );
            let (_, r) = load_mesh(&p).unwrap();
            assert!(r.warnings.is_empty(), "{lib}: {r:?}");
        }
    }

    write(
        &dir,
        "broken.mtl",
        "newmtl\nKd what is this\n\u{0}\u{1}garbage map_Kd\n",
    );
    let p = write(
        &dir,
        "broken.obj",
        format!("mtllib broken.mtl\nusemtl x\n{TRI_OBJ}f 1 2 3\n"),
    );
    let (m, _) = load_mesh(&p).unwrap();
    assert_eq!(m.triangles.len(), 1);
}

#[test]
fn raw_meshes_are_validated_and_cleaned() {
    let tri = vec![Vec3::ZERO, Vec3::X, Vec3::Y];
    assert!(matches!(
        Mesh::from_raw(tri.clone(), vec![[0, 1, 3]]),
        Err(GeomError::IndexOutOfRange { index: 3, .. })
    ));
    assert!(matches!(
        Mesh::from_raw(vec![Vec3::ZERO, Vec3::X, Vec3::NAN], vec![[0, 1, 2]]),
        Err(GeomError::NonFiniteVertex { vertex: 2, .. })
    ));
    assert!(matches!(
        Mesh::from_raw(tri.clone(), vec![]),
        Err(GeomError::NoTriangles { dropped: 0 })
    ));
    // Exact duplicate dropped, opposite copy kept, degenerate dropped, unreferenced vertex removed.
    let mut verts = tri.clone();
    verts.push(Vec3::X); // an unwelded copy of vertex 1
    verts.push(Vec3::splat(9.0)); // unreferenced
    let (m, r) = Mesh::from_raw(
        verts,
        vec![[0, 1, 2], [1, 2, 0], [0, 3, 2], [0, 2, 1], [0, 1, 3]],
    )
    .unwrap();
    assert_eq!(r.duplicate_faces, 2, "{r:?}");
    assert_eq!(r.opposite_duplicate_faces, 1);
    assert_eq!(r.degenerate_faces, 1);
    assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 1]]);
    assert_eq!(m.vertices.len(), 3);

    // Hand-built meshes that break the rules are caught by validate and SignedDistance::new.
    let bad = Mesh {
        vertices: tri.clone(),
        triangles: vec![[0, 1, 5]],
    };
    assert!(matches!(
        bad.validate(),
        Err(GeomError::IndexOutOfRange { .. })
    ));
    assert!(matches!(
        SignedDistance::new(&bad),
        Err(GeomError::IndexOutOfRange { .. })
    ));
    assert!(matches!(
        SignedDistance::new(&Mesh::default()),
        Err(GeomError::NoTriangles { .. })
    ));
    let flat = Mesh {
        vertices: vec![Vec3::ZERO, Vec3::X, Vec3::X * 2.0],
        triangles: vec![[0, 1, 2]],
    };
    assert!(matches!(
        SignedDistance::new(&flat),
        Err(GeomError::NoTriangles { .. })
    ));
}

#[test]
fn normalization_round_trips() {
    let (m, _) = load_mesh(data("teapot.obj")).unwrap();
    let (u, n) = m.normalized();
    let b = u.bounds();
    assert!((b.half_extent().max_element() - 1.0).abs() < 1e-6);
    assert!(b.center().length() < 1e-6);
    // Aspect ratio kept.
    let (bo, bn) = (m.bounds().half_extent(), b.half_extent());
    assert!(((bo.y / bo.x) - (bn.y / bn.x)).abs() < 1e-5);
    for &v in m.vertices.iter().take(50) {
        assert!((n.to_original(n.to_normalized(v)) - v).length() < 1e-5);
    }
    assert!((n.distance_to_original(n.distance_to_normalized(0.25)) - 0.25).abs() < 1e-6);
    let id = sdf_geom::Normalization::identity();
    assert_eq!(id.to_normalized(Vec3::ONE), Vec3::ONE);
}

/// The cleaner against the rule it implements, written the plain way (a set of the oriented
/// triangles kept so far): on soups full of welded copies of vertices (same position, other
/// index, ±0), repeated faces in every rotation, reversed faces, collapsed and collinear faces,
/// the same triangles in the same order and the same counts.
#[test]
fn cleaning_keeps_the_first_of_each_face_as_a_sequential_pass_does() {
    use std::collections::{HashMap, HashSet};
    fn reference(vertices: &[Vec3], triangles: &[[u32; 3]]) -> (Vec<[u32; 3]>, [usize; 3]) {
        let key = |v: Vec3| (v + Vec3::ZERO).to_array().map(f32::to_bits);
        let mut first: HashMap<[u32; 3], u32> = HashMap::new();
        let weld: Vec<u32> = (0..vertices.len() as u32)
            .map(|i| *first.entry(key(vertices[i as usize])).or_insert(i))
            .collect();
        let rot = |t: [u32; 3]| {
            let m = t
                .iter()
                .position(|&x| x == *t.iter().min().unwrap())
                .unwrap();
            [t[m], t[(m + 1) % 3], t[(m + 2) % 3]]
        };
        let (mut seen, mut kept, mut counts) = (HashSet::new(), Vec::new(), [0; 3]);
        for &t in triangles {
            let w = t.map(|i| weld[i as usize]);
            let [a, b, c] = t.map(|i| vertices[i as usize].as_dvec3());
            if w[0] == w[1]
                || w[1] == w[2]
                || w[0] == w[2]
                || (b - a).cross(c - a) == glam::DVec3::ZERO
            {
                counts[0] += 1;
            } else if seen.contains(&rot(w)) {
                counts[1] += 1;
            } else {
                counts[2] += usize::from(seen.contains(&rot([w[0], w[2], w[1]])));
                seen.insert(rot(w));
                kept.push(t);
            }
        }
        (kept, counts)
    }
    let mut state = 7u64;
    let mut next = |n: u64| {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 33) % n
    };
    let mut totals = [0; 3];
    for round in 0..20 {
        // Few distinct positions, many copies: collisions of every kind are common.
        let positions: Vec<Vec3> = (0..6 + round)
            .map(|_| Vec3::new(next(4) as f32, next(4) as f32, next(3) as f32 - 1.0))
            .collect();
        let vertices: Vec<Vec3> = (0..40)
            .map(|_| {
                let p = positions[next(positions.len() as u64) as usize];
                // A negative zero is the same position as a positive one.
                if next(4) == 0 {
                    Vec3::from_array(p.to_array().map(|c| if c == 0.0 { -0.0 } else { c }))
                } else {
                    p
                }
            })
            .collect();
        let n = vertices.len() as u64;
        let mut triangles: Vec<[u32; 3]> = Vec::new();
        for _ in 0..300 {
            let t = [next(n) as u32, next(n) as u32, next(n) as u32];
            triangles.push(t);
            match next(4) {
                0 => triangles.push([t[1], t[2], t[0]]),
                1 => triangles.push([t[0], t[2], t[1]]),
                _ => {}
            }
        }
        let (want, [degenerate, duplicate, opposite]) = reference(&vertices, &triangles);
        for (t, c) in totals.iter_mut().zip([degenerate, duplicate, opposite]) {
            *t += c;
        }
        match Mesh::from_raw(vertices.clone(), triangles.clone()) {
            Ok((mesh, report)) => {
                assert_eq!(
                    (report.degenerate_faces, report.duplicate_faces),
                    (degenerate, duplicate),
                    "round {round}"
                );
                assert_eq!(report.opposite_duplicate_faces, opposite, "round {round}");
                // The mesh's indices are renumbered over the vertices kept: compare positions.
                let corners = |v: &[Vec3], t: &[[u32; 3]]| -> Vec<[Vec3; 3]> {
                    t.iter().map(|t| t.map(|i| v[i as usize])).collect()
                };
                assert_eq!(
                    corners(&mesh.vertices, &mesh.triangles),
                    corners(&vertices, &want),
                    "round {round}"
                );
            }
            Err(e) => assert!(want.is_empty(), "round {round}: {e}"),
        }
    }
    assert!(
        totals.iter().all(|&t| t > 100),
        "soups without every case: {totals:?}"
    );
}

/// Normalised vertices of two loads of one mesh agree within `tol` of the box (the same
/// vertices in the same order).
fn assert_same_shape(a: &Mesh, b: &Mesh, tol: f32) {
    assert_eq!(a.triangles, b.triangles);
    assert_eq!(a.vertices.len(), b.vertices.len());
    let worst = a
        .vertices
        .iter()
        .zip(&b.vertices)
        .map(|(p, q)| (*p - *q).abs().max_element())
        .fold(0.0f32, f32::max);
    assert!(worst <= tol, "normalised vertices differ by {worst}");
}

/// A mesh far from the origin for its size (spot moved by 10⁷, as a georeferenced or CAD file
/// places it) keeps its shape: positions are read in f64 and recentred on their f64 centre
/// before they become f32, the report says where (`origin`), and the normalisation, moved by
/// the origin, maps back to the file's coordinates. In f32 the 10⁷ offset would have put
/// every vertex on a 1-unit grid (spot is about 2 units wide): a handful of distinct points.
#[test]
fn far_meshes_keep_their_shape() {
    let dir = temp_dir("far");
    let (spot, report) = load_mesh(data("spot.obj")).unwrap();
    assert_eq!(report.origin, glam::DVec3::ZERO);
    let (unit, n0) = spot.normalized();
    let offset = glam::DVec3::new(1e7, -2e7, 3e7);
    let mut obj = String::new();
    for v in &spot.vertices {
        let p = v.as_dvec3() + offset;
        obj.push_str(&format!("v {} {} {}\n", p.x, p.y, p.z));
    }
    for t in &spot.triangles {
        obj.push_str(&format!("f {} {} {}\n", t[0] + 1, t[1] + 1, t[2] + 1));
    }
    let far_path = write(&dir, "far_spot.obj", obj);
    let (far, far_report) = load_mesh(&far_path).unwrap();
    let origin = far_report.origin;
    assert!(
        (origin - (n0.center + offset)).abs().max_element() < 1e-6,
        "{origin}"
    );
    assert!(
        far_report
            .warnings
            .iter()
            .any(|w| w.contains("far from the origin")),
        "{:?}",
        far_report.warnings
    );
    let (far_unit, local) = far.normalized();
    assert_same_shape(&unit, &far_unit, 1e-6);
    assert!((local.scale / n0.scale - 1.0).abs() < 1e-6);
    // Back to the file's coordinates: within 1e-6 of the mesh's size, in f64.
    let n = local.translated(origin);
    let size = 1.0 / n0.scale as f64;
    for (u, v) in far_unit.vertices.iter().zip(&spot.vertices) {
        let back = n.to_original_f64(*u);
        let want = v.as_dvec3() + offset;
        assert!(
            (back - want).abs().max_element() <= 1e-6 * size,
            "{back} {want}"
        );
    }
    // What f32 coordinates would have made of it.
    let mut grid: Vec<[u32; 3]> = spot
        .vertices
        .iter()
        .map(|v| {
            (v.as_dvec3() + offset)
                .as_vec3()
                .to_array()
                .map(f32::to_bits)
        })
        .collect();
    grid.sort_unstable();
    grid.dedup();
    assert!(grid.len() < 100, "{} distinct f32 positions", grid.len());

    // glTF: spot's positions placed by a node 10⁷ away, composed in f64.
    let positions: Vec<[f32; 3]> = spot.vertices.iter().map(|v| v.to_array()).collect();
    let indices: Vec<u32> = spot.triangles.iter().flatten().copied().collect();
    let mut m = common::IDENTITY;
    m[12..15].copy_from_slice(&[1e7, -2e7, 3e7]);
    let g = common::Gltf {
        positions: &positions,
        indices: Some(&indices),
        matrices: vec![m],
        ..Default::default()
    };
    let (far_gltf, gltf_report) = load_mesh(write_gltf(&dir, "far_spot.gltf", &g)).unwrap();
    assert!(
        (gltf_report.origin - (n0.center + offset))
            .abs()
            .max_element()
            < 1e-6
    );
    assert_same_shape(&unit, &far_gltf.normalized().0, 1e-6);
    // A stray position no triangle uses, placed at the origin, does not hide how far the mesh
    // is (its box decided it, and the mesh was rounded to f32 at 10⁷).
    let mut with_stray = positions.clone();
    with_stray.push([-1e7, 2e7, -3e7]);
    let g = common::Gltf {
        positions: &with_stray,
        ..g
    };
    let (stray, report) = load_mesh(write_gltf(&dir, "far_stray.gltf", &g)).unwrap();
    assert!(report.origin.length() > 1e7, "{:?}", report.origin);
    assert_same_shape(&unit, &stray.normalized().0, 1e-6);
}

/// A mesh wound the wrong way throughout (closed, every part clockwise seen from outside, as
/// some exporters write them) is turned over with a warning, so that its inside reads as
/// inside: spot reversed gives spot's signed distances. A hollow solid (its inner surface turned
/// in on purpose), a mesh with one part wound right, and an open reversed mesh stay as they are.
#[test]
fn inside_out_meshes_are_turned_over() {
    let (spot, report) = load_mesh(data("spot.obj")).unwrap();
    assert!(!report.turned_inside_out);
    let reversed = Mesh {
        vertices: spot.vertices.clone(),
        triangles: spot.triangles.iter().map(|t| [t[0], t[2], t[1]]).collect(),
    };
    let (turned, report) = Mesh::from_raw(reversed.vertices, reversed.triangles).unwrap();
    assert!(report.turned_inside_out);
    assert!(
        report.warnings.iter().any(|w| w.contains("inside out")),
        "{:?}",
        report.warnings
    );
    let (a, b) = (
        SignedDistance::new(&spot).unwrap(),
        SignedDistance::new(&turned).unwrap(),
    );
    for p in [
        Vec3::new(0.0, 0.3, 0.0),
        Vec3::new(0.1, 0.2, -0.3),
        Vec3::X * 2.0,
    ] {
        assert_eq!(a.signed_distance(p), b.signed_distance(p), "at {p}");
    }
    assert!(a.signed_distance(Vec3::new(0.0, 0.3, 0.0)) < 0.0);

    // A unit cube with a smaller cube inside turned in: a hollow solid, kept.
    let (v, t) = cube();
    let mut vertices: Vec<Vec3> = v.iter().map(|p| Vec3::from_array(*p)).collect();
    vertices.extend(v.iter().map(|p| Vec3::from_array(*p) * 0.5 + 0.25));
    let mut triangles: Vec<[u32; 3]> = t.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    triangles.extend(t.chunks_exact(3).map(|c| [c[0] + 8, c[2] + 8, c[1] + 8]));
    let (hollow, report) = Mesh::from_raw(vertices.clone(), triangles.clone()).unwrap();
    assert!(!report.turned_inside_out);
    let sd = SignedDistance::new(&hollow).unwrap();
    assert!(sd.signed_distance(Vec3::splat(0.1)) < 0.0, "in the wall");
    assert!(sd.signed_distance(Vec3::splat(0.5)) > 0.0, "in the cavity");
    // The whole of it turned in: its inner part then winds outward, so it is not wound the
    // wrong way throughout and stays as it is (no guess at which part is wrong).
    let all_in: Vec<[u32; 3]> = triangles.iter().map(|t| [t[0], t[2], t[1]]).collect();
    let (_, report) = Mesh::from_raw(vertices, all_in).unwrap();
    assert!(!report.turned_inside_out);

    // Two separate cubes: an inward-facing room around an object wound right stays as it is
    // (their total volume is negative: turning the whole over would turn the object inside
    // out); both wound in are turned over.
    let room: Vec<Vec3> = v
        .iter()
        .map(|p| (Vec3::from_array(*p) - 0.5) * 8.0)
        .collect();
    let object: Vec<Vec3> = v.iter().map(|p| Vec3::from_array(*p)).collect();
    let vertices: Vec<Vec3> = room.into_iter().chain(object).collect();
    let inward = |c: &[u32], o: u32| [c[0] + o, c[2] + o, c[1] + o];
    let outward = |c: &[u32], o: u32| [c[0] + o, c[1] + o, c[2] + o];
    let room_in_object_out: Vec<[u32; 3]> = t
        .chunks_exact(3)
        .map(|c| inward(c, 0))
        .chain(t.chunks_exact(3).map(|c| outward(c, 8)))
        .collect();
    let (_, report) = Mesh::from_raw(vertices.clone(), room_in_object_out).unwrap();
    assert!(!report.turned_inside_out);
    let both_in: Vec<[u32; 3]> = t
        .chunks_exact(3)
        .map(|c| inward(c, 0))
        .chain(t.chunks_exact(3).map(|c| inward(c, 8)))
        .collect();
    let (_, report) = Mesh::from_raw(vertices, both_in).unwrap();
    assert!(report.turned_inside_out);

    // An open box (the cube less one face) wound in: no inside to turn, kept.
    let open: Vec<[u32; 3]> = t
        .chunks_exact(3)
        .skip(2)
        .map(|c| [c[0], c[2], c[1]])
        .collect();
    let cube_vertices: Vec<Vec3> = v.iter().map(|p| Vec3::from_array(*p)).collect();
    let (_, report) = Mesh::from_raw(cube_vertices, open).unwrap();
    assert!(!report.turned_inside_out);
}

/// An L-shaped prism whose ends are concave hexagons, each listed from the corner beside the
/// notch: ear clipping keeps the notch empty (a fan from that corner covered it twice, once
/// each way, and added a sheet across it).
#[test]
fn concave_obj_polygons_keep_their_shape() {
    let dir = temp_dir("concave");
    let l = [[2, 1], [1, 1], [1, 2], [0, 2], [0, 0], [2, 0]];
    let mut text = String::new();
    for z in [0, 1] {
        for [x, y] in l {
            text.push_str(&format!("v {x} {y} {z}\n"));
        }
    }
    // The bottom faces -z (clockwise from above), the top +z, then the six walls.
    text.push_str("f 6 5 4 3 2 1\nf 7 8 9 10 11 12\n");
    for i in 0..6 {
        let (a, b) = (i + 1, (i + 1) % 6 + 1);
        text.push_str(&format!("f {a} {b} {} {}\n", b + 6, a + 6));
    }
    let p = write(&dir, "l.obj", &text);
    let (m, r) = load_mesh(&p).unwrap();
    assert_eq!((r.polygons_triangulated, r.concave_polygons), (8, 2));
    assert!(r.warnings.is_empty(), "{:?}", r.warnings);
    // Two ends of area 3 and walls of perimeter 8: nothing doubled, nothing across the notch.
    assert!((m.area() - 14.0).abs() < 1e-9, "area {}", m.area());
    let sdf = SignedDistance::new(&m).unwrap();
    let notch = Vec3::new(1.5, 1.5, 0.5);
    assert!(!sdf.is_inside(notch));
    // In the file's coordinates: the notch's walls are half a unit away.
    assert!((sdf.signed_distance(notch) - 0.5).abs() < 1e-6);
    assert!(sdf.is_inside(Vec3::new(0.5, 1.5, 0.5)));
}
