//! Hostile and odd input files (issue 17 part A, issue 14's OBJ names): every case ends in a typed
//! error, or in the correct mesh where one is possible. Fixtures are generated here.

mod common;

use std::path::Path;

use base64::Engine as _;
use common::{cube, temp_dir, write};
use sdf_geom::{GeomError, LoadOptions, load_mesh, load_mesh_with};

const TRI_OBJ: &str = "v 0 0 0\nv 1 0 0\nv 0 1 0\n";

#[test]
fn obj_trailing_comments_bom_and_latin1_names_load() {
    let dir = temp_dir("objtext");
    let p = write(
        &dir,
        "comments.obj",
        "v 0 0 0 # origin\nv 1 0 0 #x\nv 0 1 0\t# y\nf 1 2 3 # the face\n",
    );
    let (m, _) = load_mesh(&p).unwrap();
    assert_eq!((m.vertices.len(), m.triangles.len()), (3, 1));

    let mut bom = b"\xEF\xBB\xBF".to_vec();
    bom.extend_from_slice(format!("{TRI_OBJ}f 1 2 3\n").as_bytes());
    let (m, _) = load_mesh(write(&dir, "bom.obj", bom)).unwrap();
    assert_eq!(m.triangles.len(), 1);

    // "Würfel" and "grün" in Latin-1: not UTF-8.
    let mut latin1 = b"g W\xFCrfel\nusemtl gr\xFCn\n".to_vec();
    latin1.extend_from_slice(format!("{TRI_OBJ}f 1 2 3\r\n").as_bytes());
    let (m, _) = load_mesh(write(&dir, "latin1.obj", latin1)).unwrap();
    assert_eq!(m.triangles.len(), 1);

    // A real error in a Latin-1 file still names the file, the line and the reason.
    let bad = b"g W\xFCrfel\nv 0 0 0\nv 1 zwei 0\nv 0 1 0\nf 1 2 3\n";
    let err = load_mesh(write(&dir, "bad-latin1.obj", bad)).unwrap_err();
    match &err {
        GeomError::Parse { line: Some(3), .. } => {}
        e => panic!("expected a parse error at line 3, got {e:?}"),
    }
    let msg = err.to_string();
    assert!(
        msg.contains("bad-latin1.obj") && msg.contains("zwei"),
        "{msg}"
    );
}

#[cfg(unix)]
#[test]
fn fifos_devices_and_huge_files_are_refused_unread() {
    let dir = temp_dir("special");
    let fifo = dir.join("mesh.obj");
    let ok = std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .unwrap()
        .success();
    assert!(ok, "mkfifo failed");
    // Would block forever if opened for reading.
    match load_mesh(&fifo) {
        Err(GeomError::NotARegularFile { kind: "FIFO", .. }) => {}
        other => panic!("expected NotARegularFile, got {other:?}"),
    }
    let link = dir.join("zero.glb");
    std::os::unix::fs::symlink("/dev/zero", &link).unwrap();
    match load_mesh(&link) {
        Err(GeomError::NotARegularFile {
            kind: "character device",
            ..
        }) => {}
        other => panic!("expected NotARegularFile, got {other:?}"),
    }
    let npy_link = dir.join("points.npy");
    std::os::unix::fs::symlink("/dev/zero", &npy_link).unwrap();
    assert!(matches!(
        sdf_geom::npy::read_points(&npy_link),
        Err(GeomError::NotARegularFile { .. })
    ));
    // A sparse file over the limit: refused from its size, before reading.
    let big = dir.join("big.obj");
    let f = std::fs::File::create(&big).unwrap();
    f.set_len(sdf_geom::MAX_FILE_BYTES + 1).unwrap();
    match load_mesh(&big) {
        Err(GeomError::FileTooLarge { size, limit, .. }) => {
            assert_eq!((size, limit), (limit + 1, sdf_geom::MAX_FILE_BYTES))
        }
        other => panic!("expected FileTooLarge, got {other:?}"),
    }
}

// ---------------------------------------------------------------------------------------------------
// glTF documents written by hand

/// The cube's buffer: 8 float32 VEC3 positions (96 bytes), 36 u32 indices (144 bytes), then `extra`.
fn cube_buffer(extra: &[u8]) -> Vec<u8> {
    let (v, t) = cube();
    let mut b: Vec<u8> = v.iter().flatten().flat_map(|x| x.to_le_bytes()).collect();
    b.extend(t.iter().flat_map(|x| x.to_le_bytes()));
    b.extend_from_slice(extra);
    b
}

fn data_uri(b: &[u8]) -> String {
    format!(
        "data:application/octet-stream;base64,{}",
        base64::engine::general_purpose::STANDARD.encode(b)
    )
}

/// A glTF document: one buffer (`uri`, `len` bytes), the given views, accessors and nodes; mesh 0 is
/// a triangle list with POSITION accessor 0 and index accessor `indices` (if any).
fn doc(
    uri: &str,
    len: usize,
    views: &str,
    accessors: &str,
    indices: Option<u32>,
    nodes: &str,
    roots: &str,
) -> String {
    let idx = indices
        .map(|i| format!(r#","indices":{i}"#))
        .unwrap_or_default();
    format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[{roots}]}}],"nodes":[{nodes}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}{idx}}}]}}],
        "buffers":[{{"byteLength":{len},"uri":"{uri}"}}],"bufferViews":[{views}],"accessors":[{accessors}]}}"#
    )
}

const CUBE_VIEWS: &str =
    r#"{"buffer":0,"byteOffset":0,"byteLength":96},{"buffer":0,"byteOffset":96,"byteLength":144}"#;
const POS: &str =
    r#"{"bufferView":0,"componentType":5126,"count":8,"type":"VEC3","min":[0,0,0],"max":[1,1,1]}"#;

/// The cube of `cube_buffer(&[])` with its buffer at `uri`, its u32 indices (accessor 1) and
/// the nodes `nodes`, node 0 the scene's root.
fn cube_doc(uri: &str, nodes: &str) -> String {
    let idx = r#"{"bufferView":1,"componentType":5125,"count":36,"type":"SCALAR"}"#;
    doc(
        uri,
        cube_buffer(&[]).len(),
        CUBE_VIEWS,
        &format!("{POS},{idx}"),
        Some(1),
        nodes,
        "0",
    )
}

/// The cube with index accessor `index_acc` (accessor 1), one node.
fn cube_with_indices(index_acc: &str) -> String {
    let b = cube_buffer(&[]);
    doc(
        &data_uri(&b),
        b.len(),
        CUBE_VIEWS,
        &format!("{POS},{index_acc}"),
        Some(1),
        r#"{"mesh":0}"#,
        "0",
    )
}

fn load_text(dir: &Path, name: &str, json: &str) -> Result<sdf_geom::Mesh, GeomError> {
    load_mesh(write(dir, name, json)).map(|(m, _)| m)
}

fn parse_message(r: Result<sdf_geom::Mesh, GeomError>) -> String {
    match r {
        Err(GeomError::Parse { message, .. }) => message,
        other => panic!("expected a parse error, got {other:?}"),
    }
}

#[test]
fn gltf_hand_written_cube_loads() {
    let dir = temp_dir("gcube");
    let m = load_text(
        &dir,
        "cube.gltf",
        &cube_with_indices(r#"{"bufferView":1,"componentType":5125,"count":36,"type":"SCALAR"}"#),
    )
    .unwrap();
    assert_eq!(m.triangles.len(), 12);
}

#[test]
fn gltf_bad_index_accessors_are_typed_errors() {
    let dir = temp_dir("gidxacc");
    // Float indices: the gltf crate reaches unreachable!() on these.
    let msg = parse_message(load_text(
        &dir,
        "float.gltf",
        &cube_with_indices(r#"{"bufferView":1,"componentType":5126,"count":36,"type":"SCALAR"}"#),
    ));
    assert!(msg.contains("component type F32"), "{msg}");
    // VEC3 indices used to load as a mesh.
    let msg = parse_message(load_text(
        &dir,
        "vec3.gltf",
        &cube_with_indices(r#"{"bufferView":1,"componentType":5125,"count":12,"type":"VEC3"}"#),
    ));
    assert!(msg.contains("SCALAR"), "{msg}");
    // More indices than the view holds.
    let msg = parse_message(load_text(
        &dir,
        "count.gltf",
        &cube_with_indices(r#"{"bufferView":1,"componentType":5125,"count":37,"type":"SCALAR"}"#),
    ));
    assert!(msg.contains("do not fit"), "{msg}");
    // A huge byteOffset must not overflow.
    let msg = parse_message(load_text(
        &dir,
        "offset.gltf",
        &cube_with_indices(
            r#"{"bufferView":1,"byteOffset":18446744073709551600,"componentType":5125,"count":36,"type":"SCALAR"}"#,
        ),
    ));
    assert!(!msg.is_empty());
}

#[test]
fn gltf_small_stride_and_views_outside_the_buffer_are_typed_errors() {
    let dir = temp_dir("gstride");
    let b = cube_buffer(&[]);
    // byteStride 4 < 12-byte VEC3 elements: an assertion in gltf's reader.
    let views = r#"{"buffer":0,"byteOffset":0,"byteLength":96,"byteStride":4},{"buffer":0,"byteOffset":96,"byteLength":144}"#;
    let json = doc(
        &data_uri(&b),
        b.len(),
        views,
        &format!(
            "{POS},{}",
            r#"{"bufferView":1,"componentType":5125,"count":36,"type":"SCALAR"}"#
        ),
        Some(1),
        r#"{"mesh":0}"#,
        "0",
    );
    let msg = parse_message(load_text(&dir, "stride.gltf", &json));
    assert!(msg.contains("byteStride 4"), "{msg}");
    // A view past the end of its buffer.
    let views = r#"{"buffer":0,"byteOffset":200,"byteLength":96},{"buffer":0,"byteOffset":96,"byteLength":144}"#;
    let json = doc(
        &data_uri(&b),
        b.len(),
        views,
        POS,
        None,
        r#"{"mesh":0}"#,
        "0",
    );
    let msg = parse_message(load_text(&dir, "view.gltf", &json));
    assert!(msg.contains("lies outside buffer 0"), "{msg}");
}

#[test]
fn gltf_sparse_indices_are_checked() {
    let dir = temp_dir("gsparse");
    let sparse_pos = |index: u32| {
        let b = cube_buffer(
            &[
                index.to_le_bytes(),
                5f32.to_le_bytes(),
                5f32.to_le_bytes(),
                5f32.to_le_bytes(),
            ]
            .concat(),
        );
        let views = format!(
            r#"{CUBE_VIEWS},{{"buffer":0,"byteOffset":240,"byteLength":4}},{{"buffer":0,"byteOffset":244,"byteLength":12}}"#
        );
        let acc = r#"{"bufferView":0,"componentType":5126,"count":8,"type":"VEC3","min":[0,0,0],"max":[5,5,5],"sparse":{"count":1,"indices":{"bufferView":2,"componentType":5125},"values":{"bufferView":3}}},{"bufferView":1,"componentType":5125,"count":36,"type":"SCALAR"}"#;
        doc(
            &data_uri(&b),
            b.len(),
            &views,
            acc,
            Some(1),
            r#"{"mesh":0}"#,
            "0",
        )
    };
    // In range: vertex 7 moves to (5, 5, 5).
    let m = load_text(&dir, "ok.gltf", &sparse_pos(7)).unwrap();
    assert!(
        m.vertices
            .iter()
            .any(|v| v.x == 5.0 && v.y == 5.0 && v.z == 5.0)
    );
    // Out of range: used to load silently.
    let msg = parse_message(load_text(&dir, "bad.gltf", &sparse_pos(99)));
    assert!(msg.contains("sparse index 99"), "{msg}");
}

/// `levels` levels of two nodes, each node having both nodes of the next level as children: 2^levels
/// paths to the last level, which instances mesh 0 if `mesh`.
fn dag(levels: usize, mesh: bool) -> String {
    let mut nodes = Vec::new();
    for l in 0..levels {
        for _ in 0..2 {
            nodes.push(format!(r#"{{"children":[{},{}]}}"#, 2 * l + 2, 2 * l + 3));
        }
    }
    let last = if mesh { r#"{"mesh":0}"# } else { "{}" };
    nodes.push(last.to_string());
    nodes.push(last.to_string());
    cube_scene(&nodes.join(","), "0,1")
}

/// A glTF document whose mesh 0 is the indexed cube, with `nodes` and the scene's `roots`.
fn cube_scene(nodes: &str, roots: &str) -> String {
    let b = cube_buffer(&[]);
    doc(
        &data_uri(&b),
        b.len(),
        CUBE_VIEWS,
        &format!(
            "{POS},{}",
            r#"{"bufferView":1,"componentType":5125,"count":36,"type":"SCALAR"}"#
        ),
        Some(1),
        nodes,
        roots,
    )
}

#[test]
fn gltf_shared_nodes_are_counted_not_expanded() {
    let dir = temp_dir("gdag");
    let t = std::time::Instant::now();
    // 2^41 instances of the cube: refused by count, naming it.
    let err = load_text(&dir, "dag.gltf", &dag(40, true)).unwrap_err();
    match &err {
        GeomError::SceneTooLarge {
            what: "mesh instances",
            count,
            limit,
            ..
        } => {
            assert_eq!((*count, *limit), (1 << 41, sdf_geom::MAX_INSTANCES))
        }
        e => panic!("expected SceneTooLarge, got {e:?}"),
    }
    assert!(err.to_string().contains("2199023255552"), "{err}");
    // The same graph without a mesh used to spin forever: now nothing to expand.
    assert!(matches!(
        load_text(&dir, "empty-dag.gltf", &dag(40, false)),
        Err(GeomError::NoTriangles { .. })
    ));
    // A small DAG is expanded: 2^3 instances of 12 triangles, all at the same place, so the
    // duplicates are dropped and counted.
    let (m, r) = load_mesh(write(&dir, "small-dag.gltf", dag(2, true))).unwrap();
    assert_eq!(
        (r.instances, r.input_triangles, m.triangles.len()),
        (8, 96, 12)
    );
    assert!(t.elapsed().as_secs() < 10, "{:?}", t.elapsed());
}

/// Few instances reached by many paths through a long chain of nodes (2^11 paths × 10 000
/// chain nodes), or through a node with many childless children (2^11 paths × 10 000 children
/// looked at): the instance count saw neither. Refused by the visits the expansion would make,
/// naming them.
#[test]
fn gltf_long_shared_chains_are_bounded_by_visits() {
    let dir = temp_dir("gchain");
    let (levels, many) = (10, 10_000);
    let start = 2 * levels + 2;
    let diamond = || {
        let mut nodes = Vec::new();
        for l in 0..levels {
            for _ in 0..2 {
                nodes.push(format!(r#"{{"children":[{},{}]}}"#, 2 * l + 2, 2 * l + 3));
            }
        }
        nodes.push(format!(r#"{{"children":[{start}]}}"#));
        nodes.push(format!(r#"{{"children":[{start}]}}"#));
        nodes
    };
    // A chain from `start` to the mesh.
    let mut chain = diamond();
    for k in 0..many - 1 {
        chain.push(format!(r#"{{"children":[{}]}}"#, start + k + 1));
    }
    chain.push(r#"{"mesh":0}"#.to_string());
    // `start` holds the mesh's node and many empty ones.
    let mut wide = diamond();
    let children: Vec<String> = (start + 1..=start + many).map(|c| c.to_string()).collect();
    wide.push(format!(r#"{{"children":[{}]}}"#, children.join(",")));
    wide.push(r#"{"mesh":0}"#.to_string());
    wide.extend((1..many).map(|_| "{}".to_string()));
    for (name, nodes) in [("chain", chain), ("wide", wide)] {
        let json = cube_scene(&nodes.join(","), "0,1");
        match load_text(&dir, &format!("{name}.gltf"), &json) {
            Err(GeomError::SceneTooLarge {
                what: "node visits",
                count,
                limit,
                ..
            }) => {
                assert!(
                    count > limit && limit == sdf_geom::MAX_NODE_VISITS,
                    "{name}: {count}"
                )
            }
            other => panic!("{name}: expected SceneTooLarge, got {other:?}"),
        }
    }
}

#[test]
fn gltf_node_cycles_are_errors() {
    let dir = temp_dir("gcycle");
    let b = cube_buffer(&[]);
    let acc = format!(
        "{POS},{}",
        r#"{"bufferView":1,"componentType":5125,"count":36,"type":"SCALAR"}"#
    );
    let json = doc(
        &data_uri(&b),
        b.len(),
        CUBE_VIEWS,
        &acc,
        Some(1),
        r#"{"mesh":0,"children":[1]},{"children":[0]}"#,
        "0",
    );
    let msg = parse_message(load_text(&dir, "cycle.gltf", &json));
    assert!(msg.contains("cycle"), "{msg}");
    let json = doc(
        &data_uri(&b),
        b.len(),
        CUBE_VIEWS,
        &acc,
        Some(1),
        r#"{"mesh":0,"children":[0]}"#,
        "0",
    );
    let msg = parse_message(load_text(&dir, "self.gltf", &json));
    assert!(msg.contains("cycle"), "{msg}");
}

#[test]
fn gltf_buffer_uris_stay_in_the_assets_folder() {
    let root = temp_dir("guri");
    let inside = root.join("assets");
    std::fs::create_dir_all(inside.join("sub")).unwrap();
    let b = cube_buffer(&[]);
    // A secret file next to the folder, with cube geometry in it and a size that must not leak.
    let mut secret = b.clone();
    secret.extend_from_slice(&[7u8; 1081]);
    write(&root, "secret.bin", &secret);
    write(&inside, "cube.bin", &b);
    let gltf = |uri: &str| cube_doc(uri, r#"{"mesh":0}"#);
    let secret_abs = root.join("secret.bin").display().to_string();
    for (i, uri) in [
        "../secret.bin",
        "..%2Fsecret.bin",
        "sub/../../secret.bin",
        secret_abs.as_str(),
        &format!("file://{secret_abs}"),
        "http://example.com/cube.bin",
    ]
    .iter()
    .enumerate()
    {
        let p = write(&inside, &format!("u{i}.gltf"), gltf(uri));
        let err = load_mesh(&p).unwrap_err();
        assert!(
            matches!(err, GeomError::UriRefused { buffer: 0, .. }),
            "{uri}: {err:?}"
        );
        let msg = err.to_string();
        assert!(!msg.contains(&secret.len().to_string()), "{msg}");
    }
    // A symbolic link inside the folder that points out of it.
    #[cfg(unix)]
    {
        std::os::unix::fs::symlink(root.join("secret.bin"), inside.join("link.bin")).unwrap();
        let p = write(&inside, "link.gltf", gltf("link.bin"));
        assert!(matches!(load_mesh(&p), Err(GeomError::UriRefused { .. })));
        // A link to a folder outside: refused alike whether the file named through it exists
        // or not (a missing-buffer error for one and a refusal for the other told which files
        // outside exist).
        std::os::unix::fs::symlink(&root, inside.join("out")).unwrap();
        // Dangling links too, to a file or a folder that is not there.
        std::os::unix::fs::symlink(root.join("no-such.bin"), inside.join("gone.bin")).unwrap();
        std::os::unix::fs::symlink(root.join("no-such"), inside.join("gone")).unwrap();
        for uri in [
            "out/secret.bin",
            "out/no-such.bin",
            "out/none/deeper.bin",
            "gone.bin",
            "gone/x.bin",
        ] {
            let p = write(&inside, "out.gltf", gltf(uri));
            let err = load_mesh(&p).unwrap_err();
            assert!(
                matches!(err, GeomError::UriRefused { .. }),
                "{uri}: {err:?}"
            );
        }
        // Opted in, the link is followed.
        let (m, _) = load_mesh_with(&p, &LoadOptions::with_external_uris(true)).unwrap();
        assert_eq!(m.triangles.len(), 12);
        // Even opted in, a device is not read.
        let p = write(&inside, "zero.gltf", gltf("/dev/zero"));
        assert!(matches!(
            load_mesh_with(&p, &LoadOptions::with_external_uris(true)),
            Err(GeomError::BufferNotARegularFile {
                index: 0,
                kind: "character device",
                ..
            })
        ));
    }
    // Inside the folder, plain and percent-encoded, still loads; opted in, ../ does too.
    for uri in ["cube.bin", "./sub/../cube.bin", "sub%2F..%2Fcube.bin"] {
        let p = write(&inside, "in.gltf", gltf(uri));
        assert_eq!(load_mesh(&p).unwrap().0.triangles.len(), 12, "{uri}");
    }
    let p = write(&inside, "out.gltf", gltf("../secret.bin"));
    let (m, _) = load_mesh_with(&p, &LoadOptions::with_external_uris(true)).unwrap();
    assert_eq!(m.triangles.len(), 12);
    // In memory there is no folder: only data: URIs.
    assert!(matches!(
        sdf_geom::parse_mesh(gltf("cube.bin").as_bytes(), "gltf", Path::new("mem.gltf")),
        Err(GeomError::UriRefused { .. })
    ));
}

// ---------------------------------------------------------------------------------------------------
// Numbers stay finite

use glam::Vec3;
use sdf_geom::{Mesh, SignedDistance, reference};

/// Relative error of the fast distance against the f64 brute force.
fn rel_err(mesh: &Mesh, sdf: &SignedDistance, p: Vec3) -> f64 {
    let (want, _) = reference::brute_force_distance(mesh, p);
    let got = sdf.unsigned_distance(p) as f64;
    assert!(got.is_finite(), "{p}: {got}");
    let signed = sdf.signed_distance(p) as f64;
    assert_eq!(signed.abs(), got, "{p}");
    (got - want).abs() / want.max(f64::MIN_POSITIVE)
}

#[test]
fn far_query_points_get_finite_correct_distances() {
    let mesh = Mesh::icosphere(1.0, 2);
    let sdf = SignedDistance::new(&mesh).unwrap();
    for p in [
        Vec3::new(1e20, 0.0, 0.0),
        Vec3::new(-3e19, 7e18, 1e19),
        Vec3::new(1e30, -3e29, 5e29),
        Vec3::new(2e38, -1e38, 1e38),
        Vec3::new(5000.0, 1.0, -2.0),
        Vec3::new(4000.0, 0.0, 0.0),
        Vec3::new(0.0, 3.0, 0.0),
    ] {
        let e = rel_err(&mesh, &sdf, p);
        assert!(e < 1e-6, "{p}: relative error {e}");
        assert!(sdf.signed_distance(p) > 0.0, "{p}: outside");
        assert_eq!(sdf.winding_number(p).round(), 0.0, "{p}");
        let c = sdf.closest_point(p);
        assert!(c.distance.is_finite() && c.point.is_finite(), "{p}: {c:?}");
        assert!((c.point.length() - 1.0).abs() < 0.1, "{p}: {c:?}");
    }
    // The batch path (Morton order) agrees.
    let pts = vec![Vec3::new(1e20, 0.0, 0.0); 5000];
    assert!(
        sdf.signed_distance_batch(&pts)
            .iter()
            .all(|d| (*d as f64 - 1e20).abs() < 1e14)
    );
}

#[test]
fn huge_and_tiny_coordinates_keep_distances_finite() {
    for scale in [1e38f32, 1e25, 1e-30, 1e-38] {
        let unit = Mesh::icosphere(1.0, 2);
        let mesh = Mesh {
            vertices: unit.vertices.iter().map(|v| *v * scale).collect(),
            triangles: unit.triangles.clone(),
        };
        let sdf = SignedDistance::new(&mesh).unwrap();
        for p in [
            Vec3::ZERO,
            Vec3::new(0.5, 0.2, 0.1) * scale,
            Vec3::new(1.7, -0.2, 0.1) * scale,
            Vec3::new(0.0, 0.0, 3.0) * scale,
        ] {
            let e = rel_err(&mesh, &sdf, p);
            assert!(e < 1e-5, "scale {scale}, {p}: relative error {e}");
        }
        assert!(
            sdf.signed_distance(Vec3::ZERO) < 0.0,
            "scale {scale}: centre inside"
        );
        assert!(sdf.signed_distance(Vec3::new(0.0, 0.0, 3.0) * scale) > 0.0);
        // Normalisation maps it onto the unit sphere's box, inside [-1, 1]^3.
        let (n, _) = mesh.normalized();
        let b = n.bounds();
        assert!(
            b.min.cmpge(Vec3::splat(-1.0)).all() && b.max.cmple(Vec3::ONE).all(),
            "{b:?}"
        );
        assert!(
            (b.max.max_element() - 1.0).abs() < 1e-5,
            "scale {scale}: {b:?}"
        );
    }
    // Coordinates near f32::MAX on both sides: the extent overflows f32 but not f64.
    let mesh = Mesh {
        vertices: vec![
            Vec3::new(-3e38, -3e38, 0.0),
            Vec3::new(3e38, -3e38, 0.0),
            Vec3::new(0.0, 3e38, 0.0),
            Vec3::new(0.0, 0.0, 3e38),
        ],
        triangles: vec![[0, 2, 1], [0, 1, 3], [1, 2, 3], [2, 0, 3]],
    };
    let (n, norm) = mesh.normalized();
    assert!(norm.scale < 1e-38 && norm.scale > 0.0, "{norm:?}");
    assert!(
        n.vertices
            .iter()
            .all(|v| v.is_finite() && v.abs().max_element() <= 1.0),
        "{n:?}"
    );
    let sdf = SignedDistance::new(&mesh).unwrap();
    let e = rel_err(&mesh, &sdf, Vec3::new(0.0, 0.0, -1e38));
    assert!(e < 1e-5, "{e}");
}

/// A soup of `n` random triangles in `[-1, 1]³`, each with corners within `size` of a random centre
/// (`size` 2: corners anywhere in the box, every triangle spanning it).
fn soup(n: usize, size: f32, seed: u64) -> Mesh {
    let c = sdf_geom::sample::uniform_box(n, seed);
    let d = sdf_geom::sample::uniform_box(3 * n, seed + 1);
    let vertices: Vec<Vec3> = (0..3 * n)
        .map(|i| (c[i / 3] + d[i] * size).clamp(Vec3::splat(-1.0), Vec3::ONE))
        .collect();
    let triangles = (0..n as u32)
        .map(|t| [3 * t, 3 * t + 1, 3 * t + 2])
        .collect();
    Mesh::from_raw(vertices, triangles).unwrap().0
}

/// Timing of one NGLOD `--preset small` epoch's sampling and labelling on triangle soups
/// (`cargo test --release -p sdf-geom --test hostile soup_timing -- --ignored --nocapture`).
///
/// Measured on the shared 2-core box (debug test profile, heavily loaded), 400k triangles, 20k
/// labels: corner spread 0.02 -> 30 us/point, 0.2 -> 1.0 ms/point, 2 (box-spanning) -> 20 ms/point.
/// Slowness, not a stall: every box-spanning triangle overlaps every query, so the BVH prunes
/// nothing and each label costs O(n).
#[test]
#[ignore]
fn soup_timing() {
    let n: usize = std::env::var("SOUP_TRIANGLES")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(400_000);
    let points: usize = std::env::var("SOUP_POINTS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(20_000);
    for size in [0.02f32, 0.2, 2.0] {
        let t = std::time::Instant::now();
        let mesh = soup(n, size, 5);
        let t_mesh = t.elapsed();
        let sdf = SignedDistance::new(&mesh).unwrap();
        let t_build = t.elapsed() - t_mesh;
        let mut pts = sdf_geom::sample::uniform_box(points / 3, 1);
        pts.extend(sdf_geom::sample::near_surface(
            &mesh,
            2 * points / 3,
            0.01,
            2,
        ));
        let t_sample = t.elapsed() - t_mesh - t_build;
        let s = std::time::Instant::now();
        let d = sdf.signed_distance_batch(&pts);
        let t_label = s.elapsed();
        assert!(d.iter().all(|x| x.is_finite()));
        eprintln!(
            "soup {n} triangles of size {size}: build {:.2} s, sample {:.2} s, label {} points {:.2} s ({:.1} us/point)",
            t_build.as_secs_f64(),
            t_sample.as_secs_f64(),
            pts.len(),
            t_label.as_secs_f64(),
            t_label.as_secs_f64() * 1e6 / pts.len() as f64
        );
    }
}

/// OBJ polylines (`l`) and points (`p`) enclose nothing: `tobj` would read one with three or more
/// vertices as a face. They are dropped and counted, like faces of fewer than three vertices; a
/// file of nothing else has no triangles. Line numbers in errors still count the dropped lines.
#[test]
fn obj_polylines_and_points_are_not_faces() {
    let dir = temp_dir("objlines");
    let quad = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\n";
    let p = write(
        &dir,
        "face-and-line.obj",
        format!("{quad}f 1 2 3\nl 2 4 3\np 1 2 4\nf 1 2\n"),
    );
    let (m, report) = load_mesh(&p).unwrap();
    assert_eq!(m.triangles.len(), 1, "{report:?}");
    let warnings = report.warnings.join("\n");
    assert!(
        warnings.contains("2 polyline (l) and point (p) elements ignored"),
        "{warnings}"
    );
    assert!(
        warnings.contains("1 faces with fewer than three vertices"),
        "{warnings}"
    );

    let only = write(
        &dir,
        "only-lines.obj",
        format!("{quad}l 1 2 3\nl 1 2 4 3\n"),
    );
    assert!(matches!(
        load_mesh(only),
        Err(GeomError::NoTriangles { .. })
    ));

    let bad = write(
        &dir,
        "bad-after-line.obj",
        format!("{quad}l 1 2 3\nv 1 x 0\n"),
    );
    match load_mesh(bad) {
        Err(GeomError::Parse { line: Some(6), .. }) => {}
        other => panic!("expected a parse error at line 6, got {other:?}"),
    }
}

/// glTF requires unit quaternions and matrices that decompose into TRS; the `gltf` crate checks
/// neither. An exporter's rounding is normalised away; a quaternion of length 2 (which would
/// scale the mesh by 4) or a projective matrix is an error naming the node.
#[test]
fn gltf_node_transforms_must_be_rigid_or_scaled() {
    let dir = temp_dir("gtransform");
    let uri = data_uri(&cube_buffer(&[]));
    let with_node = |node: &str| cube_doc(&uri, node);
    // 90° about z, written with 6 digits: within rounding of unit length.
    let m = load_text(
        &dir,
        "rounded.gltf",
        &with_node(r#"{"mesh":0,"rotation":[0,0,0.707107,0.707107]}"#),
    )
    .unwrap();
    let b = m.bounds();
    assert!(
        (b.max - glam::Vec3::new(0.0, 1.0, 1.0)).abs().max_element() < 1e-5,
        "{b:?}"
    );
    assert!(
        (b.min - glam::Vec3::new(-1.0, 0.0, 0.0))
            .abs()
            .max_element()
            < 1e-5,
        "{b:?}"
    );

    for (name, node, words) in [
        (
            "long.gltf",
            r#"{"mesh":0,"rotation":[1,1,1,1]}"#,
            "not a unit quaternion",
        ),
        (
            "zero.gltf",
            r#"{"mesh":0,"rotation":[0,0,0,0]}"#,
            "not a unit quaternion",
        ),
        (
            "projective.gltf",
            r#"{"mesh":0,"matrix":[1,0,0,0, 0,1,0,0, 0,0,1,5, 0,0,0,1]}"#,
            "projective",
        ),
    ] {
        match load_text(&dir, name, &with_node(node)) {
            Err(e @ GeomError::NodeTransform { node: 0, .. }) => {
                assert!(e.to_string().contains(words), "{name}: {e}")
            }
            other => panic!("{name}: expected NodeTransform, got {other:?}"),
        }
    }
}

/// A GLB that lists its BIN chunk as thousands of buffers, and a glTF that names one file
/// thousands of times under different spellings, load with the bytes held once (they used to be
/// copied per buffer: gigabytes from a few megabytes).
#[test]
fn gltf_buffers_are_read_once() {
    let dir = temp_dir("gbuffers");
    let mut bin = cube_buffer(&[]);
    let cube_len = bin.len();
    bin.resize(1 << 20, 0);
    let copies = 3000;
    let idx = r#"{"bufferView":1,"componentType":5125,"count":36,"type":"SCALAR"}"#;
    // A view on every buffer, so that every one is read.
    let views: Vec<String> = (1..copies)
        .map(|i| format!(r#"{{"buffer":{i},"byteLength":{cube_len}}}"#))
        .collect();
    let views = format!("{CUBE_VIEWS},{}", views.join(","));
    let glb_buffers = vec![format!(r#"{{"byteLength":{}}}"#, bin.len()); copies].join(",");
    let json = format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0]}}],"nodes":[{{"mesh":0}}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":1}}]}}],
        "buffers":[{glb_buffers}],"bufferViews":[{views}],"accessors":[{POS},{idx}]}}"#
    );
    let p = write(&dir, "many.glb", glb(&json, &bin));
    let peak = peak_rss_growth(|| {
        let (m, _) = load_mesh(&p).unwrap();
        assert_eq!(m.triangles.len(), 12);
    });
    // 3000 copies would be 3 GB.
    assert!(peak < 1 << 30, "loading grew the heap by {} MB", peak >> 20);

    write(&dir, "big.bin", &bin);
    let spellings: Vec<String> = (0..copies)
        .map(|i| {
            format!(
                r#"{{"byteLength":{},"uri":"{}big.bin"}}"#,
                bin.len(),
                "./".repeat(i % 50)
            )
        })
        .collect();
    let json = json.replace(&glb_buffers, &spellings.join(","));
    let p = write(&dir, "many.gltf", json);
    let peak = peak_rss_growth(|| {
        let (m, _) = load_mesh(&p).unwrap();
        assert_eq!(m.triangles.len(), 12);
    });
    assert!(peak < 1 << 30, "loading grew the heap by {} MB", peak >> 20);
}

/// A buffer that only an image's view uses (textures packed in their own .bin) is never read:
/// missing or shorter than it says, it does not stop the geometry.
#[test]
fn texture_only_buffers_are_not_read() {
    let dir = temp_dir("texbuf");
    let tri: Vec<u8> = [0f32, 0., 0., 1., 0., 0., 0., 1., 0.]
        .iter()
        .flat_map(|x| x.to_le_bytes())
        .collect();
    let json = format!(
        r#"{{"asset":{{"version":"2.0"}},
        "buffers":[{{"uri":"{}","byteLength":36}},{{"uri":"textures.bin","byteLength":4096}}],
        "bufferViews":[{{"buffer":0,"byteLength":36}},{{"buffer":1,"byteLength":4096}}],
        "accessors":[{{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3",
            "min":[0,0,0],"max":[1,1,0]}}],
        "images":[{{"bufferView":1,"mimeType":"image/png"}}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}}}]}}],
        "nodes":[{{"mesh":0}}],"scenes":[{{"nodes":[0]}}],"scene":0}}"#,
        data_uri(&tri)
    );
    let p = write(&dir, "textured.gltf", &json);
    let (m, _) = load_mesh(&p).expect("the missing textures.bin is never read");
    assert_eq!(m.triangles.len(), 1);
    write(&dir, "textures.bin", [0u8; 10]);
    let (m, _) = load_mesh(&p).expect("nor a short one");
    assert_eq!(m.triangles.len(), 1);
}

/// Buffers that only an animation's keyframes or a skin's inverse bind matrices use (an
/// `anim.bin` beside the geometry) are never read either: missing, they do not stop the rest
/// pose. An accessor that a mesh uses too is still read.
#[test]
fn animation_only_buffers_are_not_read() {
    let dir = temp_dir("animbuf");
    let tri: Vec<u8> = [0f32, 0., 0., 1., 0., 0., 0., 1., 0.]
        .iter()
        .flat_map(|x| x.to_le_bytes())
        .collect();
    let gltf = |position: usize| {
        format!(
            r#"{{"asset":{{"version":"2.0"}},
            "buffers":[{{"uri":"{}","byteLength":36}},{{"uri":"anim.bin","byteLength":4096}}],
            "bufferViews":[{{"buffer":0,"byteLength":36}},{{"buffer":1,"byteLength":4096}}],
            "accessors":[{{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3",
                "min":[0,0,0],"max":[1,1,0]}},
                {{"bufferView":1,"componentType":5126,"count":2,"type":"SCALAR","min":[0],"max":[1]}},
                {{"bufferView":1,"byteOffset":8,"componentType":5126,"count":3,"type":"VEC3",
                    "min":[0,0,0],"max":[1,1,1]}},
                {{"bufferView":1,"byteOffset":32,"componentType":5126,"count":1,"type":"MAT4"}}],
            "meshes":[{{"primitives":[{{"attributes":{{"POSITION":{position}}}}}]}}],
            "skins":[{{"joints":[1],"inverseBindMatrices":3}}],
            "animations":[{{"samplers":[{{"input":1,"output":2}}],
                "channels":[{{"sampler":0,"target":{{"node":1,"path":"translation"}}}}]}}],
            "nodes":[{{"mesh":0,"skin":0}},{{}}],"scenes":[{{"nodes":[0,1]}}],"scene":0}}"#,
            data_uri(&tri)
        )
    };
    let p = write(&dir, "animated.gltf", gltf(0));
    let (m, _) = load_mesh(&p).expect("the missing anim.bin is never read");
    assert_eq!(m.triangles.len(), 1);
    // The keyframes' accessor as the mesh's positions too: then anim.bin is needed.
    let p = write(&dir, "shared.gltf", gltf(2));
    match load_mesh(&p) {
        Err(GeomError::MissingBuffer { .. } | GeomError::Io { .. }) => {}
        other => panic!("{other:?}"),
    }
}

/// A GLB header whose length is shorter than the header itself: `gltf` subtracted 12 from it
/// unchecked (a panic in a debug build, a wrapped length in a release one); a parse error now.
#[test]
fn glb_headers_shorter_than_themselves_are_parse_errors() {
    let dir = temp_dir("glb-header");
    for length in [0u32, 11] {
        let mut bytes = b"glTF".to_vec();
        bytes.extend_from_slice(&2u32.to_le_bytes());
        bytes.extend_from_slice(&length.to_le_bytes());
        match load_mesh(write(&dir, &format!("short-{length}.glb"), &bytes)) {
            Err(GeomError::Parse { message, .. }) => {
                assert!(message.contains("header"), "{message}")
            }
            other => panic!("length {length}: {other:?}"),
        }
    }
    // Cut off inside the header.
    let p = write(&dir, "cut.glb", b"glTF\x02\x00");
    assert!(matches!(load_mesh(p), Err(GeomError::Parse { .. })));
}

/// A GLB container: the JSON chunk (padded with spaces) and the BIN chunk (padded with zeros).
fn glb(json: &str, bin: &[u8]) -> Vec<u8> {
    let mut j = json.as_bytes().to_vec();
    j.resize(j.len().next_multiple_of(4), b' ');
    let mut b = bin.to_vec();
    b.resize(b.len().next_multiple_of(4), 0);
    let total = 12 + 8 + j.len() + 8 + b.len();
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(j.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&j);
    out.extend_from_slice(&(b.len() as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(&b);
    out
}

/// How much the process's peak resident set grew while `f` ran (Linux; 0 elsewhere).
fn peak_rss_growth(f: impl FnOnce()) -> u64 {
    let peak = || {
        std::fs::read_to_string("/proc/self/status")
            .ok()
            .and_then(|s| {
                s.lines()
                    .find_map(|l| l.strip_prefix("VmHWM:"))
                    .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
            })
            .map_or(0, |kb| kb << 10)
    };
    let before = peak();
    f();
    peak().saturating_sub(before)
}

/// A mesh whose extent is subnormal in f32 cannot be normalised (1 / half-extent overflows):
/// a typed error instead of distances computed unscaled.
#[test]
fn meshes_too_small_to_normalise_are_errors() {
    let dir = temp_dir("tiny");
    let p = write(
        &dir,
        "tiny.obj",
        "v 0 0 0\nv 1e-40 0 0\nv 0 1e-40 0\nf 1 2 3\n",
    );
    match load_mesh(p) {
        Err(e @ GeomError::TooSmall { .. }) => {
            assert!(e.to_string().contains("too small to normalise"), "{e}")
        }
        other => panic!("expected TooSmall, got {other:?}"),
    }
    // 1e-30 is small but normalisable.
    let p = write(
        &dir,
        "small.obj",
        "v 0 0 0\nv 1e-30 0 0\nv 0 1e-30 0\nf 1 2 3\n",
    );
    let (m, _) = load_mesh(p).unwrap();
    assert_eq!(m.triangles.len(), 1);
}

/// Valid OBJ that `tobj` refused, over data no distance depends on: a tab after `usemtl`, a
/// bare `usemtl`, one-component texture coordinates, texture or normal indices out of range, and
/// `v/vt/vn`, `v//vn` and `v/vt` faces. Each loads its geometry.
#[test]
fn obj_texture_normal_and_material_oddities_load() {
    let dir = temp_dir("objattrs");
    for (name, body) in [
        ("usemtl-tab.obj", "usemtl\tred\nf 1 2 3\n"),
        ("usemtl-bare.obj", "usemtl\nf 1 2 3\n"),
        ("vt-1d.obj", "vt 0.5\nf 1/1 2/1 3/1\n"),
        ("vt-out-of-range.obj", "vt 0 0\nf 1/9 2/9 3/9\n"),
        ("vn-out-of-range.obj", "vn 0 0 1\nf 1//7 2//7 3//7\n"),
        ("all-three.obj", "vt 0 0\nvn 0 0 1\nf 1/1/1 2/1/1 3/1/1\n"),
    ] {
        let p = write(&dir, name, format!("{TRI_OBJ}{body}"));
        match load_mesh(&p) {
            Ok((m, _)) => assert_eq!(m.triangles.len(), 1, "{name}"),
            Err(e) => panic!("{name}: {e}"),
        }
    }
    // A vertex index out of range is still an error, on its line.
    let p = write(
        &dir,
        "bad-vertex.obj",
        format!("{TRI_OBJ}vt 0 0\nf 1/1 2/1 9/1\n"),
    );
    assert!(
        matches!(
            load_mesh(&p),
            Err(GeomError::ObjIndexOutOfRange {
                index: 9,
                line: 5,
                ..
            })
        ),
        "{:?}",
        load_mesh(&p)
    );
}

/// Vertex lines as exporters write them: with a w, with RGB or RGBA colours (`tobj` refused
/// RGBA). The colours are dropped and w divides; a count that means nothing (5, 8) or w = 0 is a
/// parse error on its line.
#[test]
fn obj_vertex_colours_and_w_load_and_bad_vertex_lines_name_their_line() {
    let dir = temp_dir("objvertex");
    let faces = "f 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n";
    let tet = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
    ];
    let plain: String = tet
        .iter()
        .map(|v| format!("v {} {} {}\n", v[0], v[1], v[2]))
        .collect();
    let (expected, _) = load_mesh(write(&dir, "plain.obj", format!("{plain}{faces}"))).unwrap();
    let with = |extra: &dyn Fn(usize) -> String| -> String {
        let vs: String = tet
            .iter()
            .enumerate()
            .map(|(i, v)| format!("v {} {} {}{}\n", v[0], v[1], v[2], extra(i)))
            .collect();
        format!("{vs}{faces}")
    };
    for (name, body) in [
        ("rgb.obj", with(&|i| format!(" 0.{i} 0.5 1"))),
        ("rgba.obj", with(&|i| format!(" 0.{i} 0.5 1 0.25"))),
        (
            "mixed.obj",
            with(&|i| {
                if i % 2 == 0 {
                    " 1 0 0".into()
                } else {
                    String::new()
                }
            }),
        ),
        ("w1.obj", with(&|_| " 1".into())),
    ] {
        let (m, _) = load_mesh(write(&dir, name, body)).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(m.triangles, expected.triangles, "{name}");
        assert_eq!(m.vertices, expected.vertices, "{name}");
    }
    // w = 2 halves the coordinates: the same shape, so the same normalised mesh.
    let halved: String = tet
        .iter()
        .map(|v| format!("v {} {} {} 2\n", 2.0 * v[0], 2.0 * v[1], 2.0 * v[2]))
        .collect();
    let (m, _) = load_mesh(write(&dir, "w2.obj", format!("{halved}{faces}"))).unwrap();
    assert_eq!(m.vertices, expected.vertices);
    for (name, bad, line) in [
        ("five.obj", "v 0 0 1 1 0", 4),
        ("eight.obj", "v 0 0 1 1 0 0 1 1", 4),
        ("w0.obj", "v 0 0 1 0", 4),
        ("word.obj", "v 0 0 one", 4),
    ] {
        let body = format!("v 0 0 0\nv 1 0 0\nv 0 1 0\n{bad}\n{faces}");
        match load_mesh(write(&dir, name, body)) {
            Err(GeomError::Parse {
                line: Some(l),
                message,
                ..
            }) => {
                assert_eq!(l, line, "{name}: {message}");
                assert!(message.contains(bad), "{name}: {message}");
            }
            other => panic!("{name}: {other:?}"),
        }
    }
}

/// A cube whose vertex 7 (1, 1, 1) one morph target moves by (0, 0, 1): the default pose is the
/// base plus the weights (the node's, else the mesh's) times the displacements, as a viewer
/// shows it before any animation.
#[test]
fn gltf_morph_targets_take_their_default_weights() {
    let dir = temp_dir("gmorph");
    let mut displacement = [0.0f32; 24];
    displacement[7 * 3 + 2] = 1.0;
    let extra: Vec<u8> = displacement.iter().flat_map(|x| x.to_le_bytes()).collect();
    let b = cube_buffer(&extra);
    let uri = data_uri(&b);
    let morphed = |mesh_weights: &str, node_weights: &str, target_acc: &str, target: &str| {
        format!(
            r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0]}}],
            "nodes":[{{"mesh":0{node_weights}}}],
            "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":1,
                "targets":[{{"POSITION":{target}}}]}}]{mesh_weights}}}],
            "buffers":[{{"byteLength":{},"uri":"{uri}"}}],
            "bufferViews":[{CUBE_VIEWS},{{"buffer":0,"byteOffset":240,"byteLength":96}}],
            "accessors":[{POS},{{"bufferView":1,"componentType":5125,"count":36,"type":"SCALAR"}},
                {target_acc}]}}"#,
            b.len()
        )
    };
    let target = r#"{"bufferView":2,"componentType":5126,"count":8,"type":"VEC3","min":[0,0,0],"max":[0,0,1]}"#;
    // The cube with vertex 7's z at 1 + w, written out.
    let moved = |w: f32| {
        let (mut v, t) = cube();
        v[7][2] += w;
        let mut bytes: Vec<u8> = v.iter().flatten().flat_map(|x| x.to_le_bytes()).collect();
        bytes.extend(t.iter().flat_map(|x| x.to_le_bytes()));
        let json = doc(
            &data_uri(&bytes),
            bytes.len(),
            CUBE_VIEWS,
            &format!(r#"{POS},{{"bufferView":1,"componentType":5125,"count":36,"type":"SCALAR"}}"#),
            Some(1),
            r#"{"mesh":0}"#,
            "0",
        );
        load_mesh(write(&dir, &format!("moved-{w}.gltf"), json))
            .unwrap()
            .0
    };
    for (name, mesh_w, node_w, w, morphed_count) in [
        ("mesh-weight.gltf", r#","weights":[0.5]"#, "", 0.5, 1),
        (
            "node-weight.gltf",
            r#","weights":[0.5]"#,
            r#","weights":[1.0]"#,
            1.0,
            1,
        ),
        (
            "node-zero.gltf",
            r#","weights":[0.5]"#,
            r#","weights":[0.0]"#,
            0.0,
            0,
        ),
        ("no-weights.gltf", "", "", 0.0, 0),
    ] {
        let (m, report) = load_mesh(write(&dir, name, morphed(mesh_w, node_w, target, "2")))
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        let expected = moved(w);
        assert_eq!(m.vertices, expected.vertices, "{name}");
        assert_eq!(m.triangles, expected.triangles, "{name}");
        assert_eq!(report.morphed_primitives, morphed_count, "{name}");
    }
    // More weights than targets: a warning, and the first weight applies.
    let (m, report) = load_mesh(write(
        &dir,
        "extra-weight.gltf",
        morphed(r#","weights":[0.5,2.0]"#, "", target, "2"),
    ))
    .unwrap();
    assert_eq!(m.vertices, moved(0.5).vertices);
    assert!(
        report
            .warnings
            .iter()
            .any(|w| w.contains("1 morph targets but 2 weights")),
        "{:?}",
        report.warnings
    );
    // Displacements that do not match the vertices, or of another type: parse errors.
    let short = target.replace(r#""count":8"#, r#""count":7"#);
    let msg = parse_message(load_text(
        &dir,
        "short.gltf",
        &morphed(r#","weights":[0.5]"#, "", &short, "2"),
    ));
    assert!(
        msg.contains("morph target 0: 7 POSITION displacements for 8 vertices"),
        "{msg}"
    );
    let ints = target.replace("5126", "5125");
    let msg = parse_message(load_text(
        &dir,
        "ints.gltf",
        &morphed(r#","weights":[0.5]"#, "", &ints, "2"),
    ));
    assert!(msg.contains("only VEC3 of float32"), "{msg}");
    // A target naming an accessor that does not exist is an error, not a panic.
    match load_text(
        &dir,
        "missing.gltf",
        &morphed(r#","weights":[0.5]"#, "", target, "9"),
    ) {
        Err(GeomError::Parse { .. }) => {}
        other => panic!("missing target accessor: {other:?}"),
    }
}

/// `EXT_mesh_gpu_instancing`: a node's mesh drawn once per instance, each instance's
/// translation · rotation · scale after the node's own transform, exactly as the same scene
/// written with one child node per instance. Bad attributes are typed errors, and instance
/// counts go into the scene limits before any buffer is read.
#[test]
fn gltf_gpu_instancing_draws_every_instance() {
    let dir = temp_dir("ginst");
    let h = std::f32::consts::FRAC_1_SQRT_2;
    let t = [[0.0f32, 0.0, 0.0], [3.0, 0.0, 0.0]];
    let r = [[0.0f32, 0.0, 0.0, 1.0], [0.0, 0.0, h, h]];
    let s = [[1.0f32, 1.0, 1.0], [2.0, 0.5, 1.0]];
    let mut extra: Vec<u8> = Vec::new();
    for v in t
        .iter()
        .flatten()
        .chain(r.iter().flatten())
        .chain(s.iter().flatten())
    {
        extra.extend(v.to_le_bytes());
    }
    // The rotations again as normalised bytes (offset 320): 90 / 127 ≈ 0.709.
    extra.extend([0u8, 0, 0, 127, 0, 0, 90, 90]);
    let b = cube_buffer(&extra);
    let uri = data_uri(&b);
    let views = format!(
        r#"{CUBE_VIEWS},{{"buffer":0,"byteOffset":240,"byteLength":24}},{{"buffer":0,"byteOffset":264,"byteLength":32}},{{"buffer":0,"byteOffset":296,"byteLength":24}},{{"buffer":0,"byteOffset":320,"byteLength":8}}"#
    );
    let idx = r#"{"bufferView":1,"componentType":5125,"count":36,"type":"SCALAR"}"#;
    let acc = |view: u32, ty: &str, count: u32| {
        format!(r#"{{"bufferView":{view},"componentType":5126,"count":{count},"type":"{ty}"}}"#)
    };
    let accessors = format!(
        "{POS},{idx},{},{},{}",
        acc(2, "VEC3", 2),
        acc(3, "VEC4", 2),
        acc(4, "VEC3", 2)
    );
    let scene = |nodes: &str, roots: &str, accessors: &str| {
        format!(
            r#"{{"asset":{{"version":"2.0"}},"extensionsUsed":["EXT_mesh_gpu_instancing"],
            "scene":0,"scenes":[{{"nodes":[{roots}]}}],"nodes":[{nodes}],
            "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":1}}]}}],
            "buffers":[{{"byteLength":{},"uri":"{uri}"}}],"bufferViews":[{views}],
            "accessors":[{accessors}]}}"#,
            b.len()
        )
    };
    let instanced = |attributes: &str, accessors: &str| {
        scene(
            &format!(
                r#"{{"mesh":0,"translation":[0,0,5],"extensions":{{"EXT_mesh_gpu_instancing":{{"attributes":{{{attributes}}}}}}}}}"#
            ),
            "0",
            accessors,
        )
    };
    let all = r#""TRANSLATION":2,"ROTATION":3,"SCALE":4"#;
    let (m, report) = load_mesh(write(&dir, "instanced.gltf", instanced(all, &accessors))).unwrap();
    let child = |i: usize| {
        format!(
            r#"{{"mesh":0,"translation":{:?},"rotation":{:?},"scale":{:?}}}"#,
            t[i], r[i], s[i]
        )
    };
    let explicit = scene(
        &format!(
            r#"{{"translation":[0,0,5],"children":[1,2]}},{},{}"#,
            child(0),
            child(1)
        ),
        "0",
        &accessors,
    );
    let (e, _) = load_mesh(write(&dir, "explicit.gltf", explicit)).unwrap();
    assert_eq!(report.instances, 2);
    assert_eq!(m.triangles.len(), 24);
    assert_eq!(m.triangles, e.triangles);
    // To rounding: the nodes' numbers are read in f64 from their JSON text (each f32's
    // shortest digits), the instances' from the buffer's f32 values.
    let worst = m
        .vertices
        .iter()
        .zip(&e.vertices)
        .map(|(a, b)| (*a - *b).abs().max_element())
        .fold(0.0f32, f32::max);
    assert!(worst < 1e-6, "worst vertex difference {worst}");
    // Rotations as normalised bytes: the same scene, to their rounding.
    let bytes = format!(
        r#"{accessors},{{"bufferView":5,"componentType":5120,"normalized":true,"count":2,"type":"VEC4"}}"#
    );
    let (q, _) = load_mesh(write(
        &dir,
        "byte-rotations.gltf",
        instanced(r#""TRANSLATION":2,"ROTATION":5,"SCALE":4"#, &bytes),
    ))
    .unwrap();
    assert_eq!(q.triangles, e.triangles);
    let worst = q
        .vertices
        .iter()
        .zip(&e.vertices)
        .map(|(a, b)| (*a - *b).abs().max_element())
        .fold(0.0f32, f32::max);
    assert!(worst < 1e-2, "byte rotations: worst vertex error {worst}");
    // Translations only: the rotation and scale default to none.
    let (m, _) = load_mesh(write(
        &dir,
        "translation-only.gltf",
        instanced(r#""TRANSLATION":2"#, &accessors),
    ))
    .unwrap();
    assert_eq!(m.triangles.len(), 24);

    let parse = |name: &str, json: String| match load_mesh(write(&dir, name, json)) {
        Err(GeomError::Parse { message, .. }) => message,
        other => panic!("{name}: expected a parse error, got {other:?}"),
    };
    let msg = parse("missing.gltf", instanced(r#""TRANSLATION":9"#, &accessors));
    assert!(
        msg.contains("TRANSLATION accessor 9 does not exist"),
        "{msg}"
    );
    let msg = parse("empty.gltf", instanced("", &accessors));
    assert!(msg.contains("its `attributes` are empty"), "{msg}");
    // Only a custom attribute: its count of instances, each without a transform of its own
    // (so the second copy's triangles are exact duplicates, which the clean-up drops).
    let (m, report) = load_mesh(write(
        &dir,
        "custom-only.gltf",
        instanced(r#""_ID":2"#, &accessors),
    ))
    .unwrap();
    assert_eq!((report.instances, m.triangles.len()), (2, 12));
    assert_eq!(report.duplicate_faces, 12);
    let one = format!(
        "{POS},{idx},{},{},{}",
        acc(2, "VEC3", 2),
        acc(3, "VEC4", 1),
        acc(4, "VEC3", 2)
    );
    let msg = parse("counts.gltf", instanced(all, &one));
    assert!(msg.contains("different counts"), "{msg}");
    // A rotation of length 2 (the scale would be 4 silently).
    let mut long = extra.clone();
    for (k, v) in [0.0f32, 0.0, 0.0, 2.0].iter().enumerate() {
        long[24 + 4 * k..28 + 4 * k].copy_from_slice(&v.to_le_bytes());
    }
    let b2 = cube_buffer(&long);
    let json = instanced(all, &accessors).replace(&uri, &data_uri(&b2));
    let msg = parse("long-rotation.gltf", json);
    assert!(
        msg.contains("instance 0: rotation") && msg.contains("not a unit quaternion"),
        "{msg}"
    );
    // A translation of another type is not supported, by name.
    let vec4 = format!(
        "{POS},{idx},{},{},{}",
        acc(3, "VEC4", 2),
        acc(3, "VEC4", 2),
        acc(4, "VEC3", 2)
    );
    match load_mesh(write(&dir, "vec4.gltf", instanced(all, &vec4))) {
        Err(GeomError::Unsupported { feature, .. }) => {
            assert!(
                feature.contains("EXT_mesh_gpu_instancing TRANSLATION"),
                "{feature}"
            )
        }
        other => panic!("vec4 translation: {other:?}"),
    }
    // 2^30 instances of the cube: refused by the limits before anything is read or built.
    let huge = format!(
        r#"{POS},{idx},{{"bufferView":2,"componentType":5126,"count":1073741824,"type":"VEC3"}}"#
    );
    let started = std::time::Instant::now();
    match load_mesh(write(
        &dir,
        "huge.gltf",
        instanced(r#""TRANSLATION":2"#, &huge),
    )) {
        Err(GeomError::SceneTooLarge { .. }) => {}
        other => panic!("2^30 instances: {other:?}"),
    }
    assert!(started.elapsed().as_secs() < 5);
}

/// `extras` may hold any JSON value (the glTF specification only recommends an object), on the
/// asset and on every object: a number, a string, an array or null must not stop the geometry.
#[test]
fn gltf_extras_of_any_type_load() {
    let dir = temp_dir("gextras");
    let base =
        cube_with_indices(r#"{"bufferView":1,"componentType":5125,"count":36,"type":"SCALAR"}"#);
    for (name, extras) in [
        ("number.gltf", "5"),
        ("string.gltf", r#""made by hand""#),
        ("array.gltf", "[1, {\"a\": 2}]"),
        ("null.gltf", "null"),
        ("object.gltf", r#"{"k": [true]}"#),
    ] {
        let json = base
            .replacen(
                r#"{"mesh":0}"#,
                &format!(r#"{{"mesh":0,"extras":{extras}}}"#),
                1,
            )
            .replacen(
                r#"{"version":"2.0"}"#,
                &format!(r#"{{"version":"2.0","extras":{extras}}}"#),
                1,
            );
        assert_ne!(json, base);
        let m = load_text(&dir, name, &json).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(m.triangles.len(), 12, "{name}");
    }
}

/// `KHR_mesh_quantization` (what gltfpack writes by default): the cube's positions as 8- and
/// 16-bit integers, normalised or not, with the strides glTF requires, load as the float cube;
/// signed ones also mirrored (-c), normalised values at -max clamping to -1. A 32-bit integer
/// position is still refused by name.
#[test]
fn gltf_quantized_positions_load() {
    let dir = temp_dir("gquant");
    let (v, t) = cube();
    let float = load_text(
        &dir,
        "float.gltf",
        &cube_with_indices(r#"{"bufferView":1,"componentType":5125,"count":36,"type":"SCALAR"}"#),
    )
    .unwrap();
    // (component type, bytes, stride, largest value when normalised, signed)
    let types = [
        (5120, 1, 4, 127.0f32, true),
        (5121, 1, 4, 255.0, false),
        (5122, 2, 8, 32767.0, true),
        (5123, 2, 8, 65535.0, false),
    ];
    let quantized = |ty: u32, size: usize, stride: usize, normalized: bool, scale: f32| {
        let mut b = Vec::new();
        for p in &v {
            for &c in p {
                let q = (c * scale) as i64;
                b.extend(&q.to_le_bytes()[..size]);
            }
            b.resize(b.len() + stride - 3 * size, 0);
        }
        let idx_off = b.len();
        b.extend(t.iter().flat_map(|x| x.to_le_bytes()));
        let (lo, hi) = (scale.min(0.0), scale.max(0.0));
        format!(
            r#"{{"asset":{{"version":"2.0"}},"extensionsUsed":["KHR_mesh_quantization"],
            "extensionsRequired":["KHR_mesh_quantization"],"scene":0,"scenes":[{{"nodes":[0]}}],
            "nodes":[{{"mesh":0}}],"meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":1}}]}}],
            "buffers":[{{"byteLength":{},"uri":"{}"}}],
            "bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":{idx_off},"byteStride":{stride}}},
                {{"buffer":0,"byteOffset":{idx_off},"byteLength":144}}],
            "accessors":[{{"bufferView":0,"componentType":{ty},"normalized":{normalized},"count":8,"type":"VEC3",
                "min":[{lo},{lo},{lo}],"max":[{hi},{hi},{hi}]}},
                {{"bufferView":1,"componentType":5125,"count":36,"type":"SCALAR"}}]}}"#,
            b.len(),
            data_uri(&b)
        )
    };
    for (ty, size, stride, max, signed) in types {
        for normalized in [false, true] {
            let scale = if normalized { max } else { 1.0 };
            let name = format!("q{ty}-{normalized}.gltf");
            let m = load_text(&dir, &name, &quantized(ty, size, stride, normalized, scale))
                .unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_eq!(m.vertices, float.vertices, "{name}");
            assert_eq!(m.triangles, float.triangles, "{name}");
            if signed {
                let name = format!("q{ty}-{normalized}-mirrored.gltf");
                let m = load_text(
                    &dir,
                    &name,
                    &quantized(ty, size, stride, normalized, -scale),
                )
                .unwrap_or_else(|e| panic!("{name}: {e}"));
                let mirrored: Vec<_> = float.vertices.iter().map(|&p| -p).collect();
                assert_eq!(m.vertices, mirrored, "{name}");
            }
        }
    }
    match load_text(&dir, "u32.gltf", &quantized(5125, 4, 12, false, 1.0)) {
        Err(GeomError::Unsupported { feature, .. }) => {
            assert!(
                feature.contains("POSITION accessor of type U32"),
                "{feature}"
            )
        }
        other => panic!("u32 positions: {other:?}"),
    }
}

/// Crafted counts that once cost unbounded time or memory, or crashed (found in review): every
/// one now ends quickly in a typed error, or loads with one warning per mesh, not per instance.
#[test]
fn gltf_crafted_counts_are_bounded() {
    let dir = temp_dir("gcounts");
    // A triangle's three indices, then three positions.
    let mut b: Vec<u8> = [0u32, 1, 2].iter().flat_map(|x| x.to_le_bytes()).collect();
    for v in [0.0f32, 0., 0., 1., 0., 0., 0., 1., 0.] {
        b.extend(v.to_le_bytes());
    }
    let uri = data_uri(&b);
    let views = r#"{"buffer":0,"byteOffset":0,"byteLength":12},{"buffer":0,"byteOffset":12,"byteLength":36}"#;
    // A VEC3 accessor of `count` elements, zeros but for `n` sparse ones.
    let sparse = |count: u64, n: u32| {
        format!(
            r#"{{"componentType":5126,"count":{count},"type":"VEC3","min":[0,0,0],"max":[1,1,1],"sparse":{{"count":{n},"indices":{{"bufferView":0,"componentType":5125}},"values":{{"bufferView":1}}}}}}"#
        )
    };
    let doc = |nodes: &str, meshes: &str, accessors: &str| {
        format!(
            r#"{{"asset":{{"version":"2.0"}},"extensionsUsed":["EXT_mesh_gpu_instancing"],"scene":0,"scenes":[{{"nodes":[0]}}],"nodes":[{nodes}],"meshes":[{meshes}],"buffers":[{{"byteLength":{},"uri":"{uri}"}}],"bufferViews":[{views}],"accessors":[{accessors}]}}"#,
            b.len()
        )
    };
    let instanced = |acc: u32| {
        format!(
            r#"{{"mesh":0,"extensions":{{"EXT_mesh_gpu_instancing":{{"attributes":{{"TRANSLATION":{acc}}}}}}}}}"#
        )
    };
    let quick = |name: &str, json: String| {
        let started = std::time::Instant::now();
        let r = load_mesh(write(&dir, name, json));
        assert!(
            started.elapsed().as_secs() < 5,
            "{name}: {:?}",
            started.elapsed()
        );
        r
    };
    // 64 primitives of 2^58 positions each: the vertex total wrapped to 0 in release builds
    // (and overflowed in debug), then one accessor's element list aborted the process.
    let prims = vec![r#"{"attributes":{"POSITION":0},"indices":1}"#; 64].join(",");
    let idx = r#"{"bufferView":0,"componentType":5125,"count":3,"type":"SCALAR"}"#;
    let wrap = doc(
        r#"{"mesh":0}"#,
        &format!(r#"{{"primitives":[{prims}]}}"#),
        &format!("{},{idx}", sparse(1 << 58, 1)),
    );
    assert!(matches!(
        quick("wrap.gltf", wrap),
        Err(GeomError::SceneTooLarge { .. })
    ));
    // 100 000 empty morph targets on 20 000 instances: 2·10⁹ target visits.
    let targets = vec!["{}"; 100_000].join(",");
    let empty = doc(
        &instanced(1),
        &format!(r#"{{"primitives":[{{"attributes":{{"POSITION":0}},"targets":[{targets}]}}]}}"#),
        &format!("{},{}", sparse(3, 3), sparse(20_000, 1)),
    );
    assert!(matches!(
        quick("empty-targets.gltf", empty),
        Err(GeomError::SceneTooLarge { .. })
    ));
    // 80 targets of 300 000 positions, all weighted: 24 M target positions read.
    let targets = vec![r#"{"POSITION":0}"#; 80].join(",");
    let weights = vec!["0.001"; 80].join(",");
    let heavy = doc(
        r#"{"mesh":0}"#,
        &format!(
            r#"{{"primitives":[{{"attributes":{{"POSITION":0}},"targets":[{targets}]}}],"weights":[{weights}]}}"#
        ),
        &sparse(300_000, 3),
    );
    assert!(matches!(
        quick("heavy-targets.gltf", heavy),
        Err(GeomError::SceneTooLarge { .. })
    ));
    // 20 000 instances of a mesh whose primitives each have a warning: one warning each.
    let prims = [r#"{"attributes":{"POSITION":1},"targets":[{"POSITION":1}]}"#; 5].join(",");
    let warn = doc(
        &instanced(2),
        &format!(r#"{{"primitives":[{{"attributes":{{"POSITION":0}}}},{prims}],"weights":[1,1]}}"#),
        &format!("{},{},{}", sparse(3, 3), sparse(1, 1), sparse(20_000, 1)),
    );
    let (_, report) = quick("warnings.gltf", warn).unwrap();
    assert_eq!(report.instances, 20_000);
    assert!(
        report.warnings.len() <= 10,
        "{} warnings",
        report.warnings.len()
    );
    assert!(
        report
            .warnings
            .iter()
            .any(|w| w.contains("mesh 0 primitive 1: 1 morph targets but 2 weights")),
        "{:?}",
        report.warnings
    );
}

/// OBJ errors found in review: a face may use vertices defined after it (tobj checks indices
/// when the object ends), so another error is placed on its own line and an index error names
/// the index that is out of range; an infinite, NaN or zero w is an error on its line (tobj
/// divided by it, putting the vertex at 0 silently); a corner without its vertex index
/// (`f /1 2 3`) is an error on its line, not a dropped face.
#[test]
fn obj_forward_references_w_and_empty_corners() {
    let dir = temp_dir("objreview");
    let (m, _) = load_mesh(write(
        &dir,
        "forward.obj",
        "f 1 2 3\nv 0 0 0\nv 1 0 0\nv 0 1 0\n",
    ))
    .unwrap();
    assert_eq!(m.triangles.len(), 1);
    // A w that f32 rounds to 0 is a number in f64, which tobj divides by: coordinates and w
    // both tiny give an ordinary triangle.
    let (m, _) = load_mesh(write(
        &dir,
        "w-tiny.obj",
        "v 0 0 0 1e-50
v 1e-50 0 0 1e-50
v 0 2e-50 0 1e-50
f 1 2 3
",
    ))
    .unwrap();
    assert!((m.area() - 1.0).abs() < 1e-9, "area {}", m.area());
    for (name, body, line) in [
        (
            "forward-bad-v.obj",
            "f 1 2 3\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 2\n",
            5,
        ),
        (
            "w-inf.obj",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 5 5 5 inf\nf 1 2 3\nf 1 2 4\n",
            4,
        ),
        ("w-nan.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0 nan\nf 1 2 3\n", 3),
        ("w-zero.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0 0\nf 1 2 3\n", 3),
        (
            "empty-corner.obj",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf /1 2 3\nf 1 2 4\n",
            5,
        ),
    ] {
        match load_mesh(write(&dir, name, body)) {
            Err(GeomError::Parse {
                line: Some(l),
                message,
                ..
            }) => {
                assert_eq!(l, line, "{name}: {message}")
            }
            other => panic!("{name}: {other:?}"),
        }
    }
    // An index beyond the vertices its object ends with: the index named, on its face.
    match load_mesh(write(
        &dir,
        "forward-oob.obj",
        "f 1 2 4\nv 0 0 0\nv 1 0 0\nv 0 1 0\n",
    )) {
        Err(GeomError::ObjIndexOutOfRange {
            index: 4,
            vertex_count: 3,
            line: 1,
            ..
        }) => {}
        other => panic!("forward-oob: {other:?}"),
    }
    // Objects and groups do not restart the numbering (OBJ's indices are the file's), and they
    // are merged: an index a later object defines is that vertex, as within one object.
    let (mesh, report) = load_mesh(write(
        &dir,
        "object-forward.obj",
        "v 0 0 0\nv 1 0 0\nf 1 2 3\no b\nv 0 1 0\nf 1 3 2\n",
    ))
    .unwrap();
    assert_eq!((mesh.vertices.len(), report.input_triangles), (3, 2));
}

/// Many objects and groups cost what one does: tobj built a model, with its own copy of the
/// vertices it used, for each (20 M one-face groups in a 200 MB file passed every bound and took
/// gigabytes).
#[test]
fn obj_groups_do_not_multiply_the_vertices() {
    let dir = temp_dir("objgroups");
    let mut text = String::from("v 0 0 0\nv 1 0 0\nv 0 1 0\n");
    for i in 0..20_000 {
        text.push_str(if i % 2 == 0 { "g part\n" } else { "o part\n" });
        text.push_str("f 1 2 3\n");
    }
    let (mesh, report) = load_mesh(write(&dir, "groups.obj", &text)).unwrap();
    assert_eq!(report.input_vertices, 3, "{report:?}");
    assert_eq!(report.input_triangles, 20_000, "{report:?}");
    assert_eq!(mesh.triangles.len(), 1, "{report:?}");
}

/// What the specification asks of writers and the loader does without: a POSITION accessor
/// without `min` and `max` loads (with a warning), and a primitive without POSITION is skipped
/// (with a warning) while the mesh's other primitives load. Either failed the whole file.
#[test]
fn gltf_without_position_bounds_or_positions_load() {
    let dir = temp_dir("glenient");
    let uri = data_uri(&cube_buffer(&[]));
    let idx = r#"{"bufferView":1,"componentType":5125,"count":36,"type":"SCALAR"}"#;
    let cube = |position: &str, nodes: &str| {
        let accessors = format!("{position},{idx}");
        let len = cube_buffer(&[]).len();
        doc(&uri, len, CUBE_VIEWS, &accessors, Some(1), nodes, "0")
    };
    let loads_saying = |name: &str, json: String, warning: &str| {
        let (mesh, report) = load_mesh(write(&dir, name, json)).unwrap();
        assert_eq!(mesh.triangles.len(), 12);
        assert!(
            report.warnings.iter().any(|w| w.contains(warning)),
            "{name}: {report:?}"
        );
    };
    let unbounded = r#"{"bufferView":0,"componentType":5126,"count":8,"type":"VEC3"}"#;
    loads_saying(
        "unbounded.gltf",
        cube(unbounded, r#"{"mesh":0}"#),
        "1 POSITION accessors without bounds",
    );
    // A second primitive with no POSITION beside the cube's.
    let json = cube(POS, r#"{"mesh":0}"#).replace(
        r#""indices":1}]"#,
        r#""indices":1},{"attributes":{"NORMAL":0},"indices":1}]"#,
    );
    loads_saying(
        "no-position.gltf",
        json,
        "has no POSITION attribute (skipped)",
    );
    // Other findings of the validation stay errors.
    let json = cube(POS, r#"{"mesh":7}"#);
    assert!(matches!(
        load_mesh(write(&dir, "bad-mesh.gltf", json)),
        Err(GeomError::Parse { .. })
    ));
}

/// Node transforms keep the file's f64 digits: two parts placed at x = 6 378 137.1 and .4 (an
/// Earth-centred survey coordinate) stay 0.3 apart, by translation or by matrix. `gltf` reads
/// them as f32, which put the parts at .0 and .5.
#[test]
fn gltf_node_transforms_keep_their_f64_digits() {
    let dir = temp_dir("gprecise");
    let uri = data_uri(&cube_buffer(&[]));
    let nodes = r#"{"children":[1,2]},{"mesh":0,"translation":[6378137.1,0,0]},
        {"mesh":0,"matrix":[1,0,0,0,0,1,0,0,0,0,1,0,6378137.4,-2.5,0,1]}"#;
    let (mesh, report) = load_mesh(write(&dir, "survey.gltf", cube_doc(&uri, nodes))).unwrap();
    let x = |v: &glam::Vec3| v.x as f64 + report.origin.x;
    let lowest = mesh.vertices.iter().map(x).fold(f64::INFINITY, f64::min);
    let highest = mesh
        .vertices
        .iter()
        .map(x)
        .fold(f64::NEG_INFINITY, f64::max);
    // The cube spans [0, 1]: the parts from .1 to 1.1 and from .4 to 1.4.
    assert!((lowest - 6378137.1).abs() < 1e-6, "{lowest}");
    assert!((highest - 6378138.4).abs() < 1e-6, "{highest}");
    let y = mesh.vertices.iter().map(|v| v.y as f64 + report.origin.y);
    assert!((y.fold(f64::INFINITY, f64::min) + 2.5).abs() < 1e-6);
}

/// Node transforms with numbers beyond float32 (1e39 reads as infinity): an error naming the
/// node, by index and name, never a non-finite vertex blamed on the vertex data. Also for
/// transforms that overflow only once composed with their ancestors', or on a vertex.
#[test]
fn gltf_non_finite_node_transforms_name_the_node() {
    let dir = temp_dir("gnonfinite");
    let uri = data_uri(&cube_buffer(&[]));
    let with_nodes = |nodes: &str| cube_doc(&uri, nodes);
    for (name, nodes, node, node_name, words) in [
        (
            "scale.gltf",
            r#"{"mesh":0,"name":"arm","scale":[1e39,1,1]}"#,
            0,
            Some("arm"),
            "its scale [inf, 1.0, 1.0] is not finite",
        ),
        (
            "translation.gltf",
            r#"{"mesh":0,"translation":[0,-1e39,0]}"#,
            0,
            None,
            "its translation [0.0, -inf, 0.0] is not finite",
        ),
        (
            "rotation.gltf",
            r#"{"mesh":0,"rotation":[0,0,0,1e39]}"#,
            0,
            None,
            "its rotation",
        ),
        (
            "matrix.gltf",
            r#"{"mesh":0,"matrix":[1,0,0,0, 0,1e39,0,0, 0,0,1,0, 0,0,0,1]}"#,
            0,
            None,
            "its matrix",
        ),
        (
            "composed.gltf",
            r#"{"children":[1],"scale":[1e30,1,1]},{"mesh":0,"name":"leaf","scale":[1e30,1,1]}"#,
            1,
            Some("leaf"),
            "composed with its ancestors' is not finite",
        ),
        (
            "vertex.gltf",
            r#"{"mesh":0,"translation":[3e38,0,0],"scale":[3e38,1,1]}"#,
            0,
            None,
            "its transform takes mesh 0 primitive 0 vertex 1 from [1, 0, 0] to [inf, 0, 0]",
        ),
    ] {
        let p = write(&dir, name, with_nodes(nodes));
        let err = load_mesh(&p).unwrap_err();
        match &err {
            GeomError::NodeTransform {
                node: n, name: nn, ..
            } if *n == node && nn.as_deref() == node_name => {}
            other => panic!("{name}: expected NodeTransform for node {node}, got {other:?}"),
        }
        let msg = err.to_string();
        let head = match node_name {
            Some(n) => format!("{}: node {node} ({n:?}): ", p.display()),
            None => format!("{}: node {node}: ", p.display()),
        };
        assert!(
            msg.starts_with(&head) && msg.contains(words),
            "{name}: {msg}"
        );
    }
}

/// An index out of range names the glTF mesh (and its name) and the primitive, with the
/// triangle counted within the primitive.
#[test]
fn gltf_index_out_of_range_names_mesh_and_primitive() {
    let dir = temp_dir("gidxprim");
    let bad: Vec<u8> = [0u32, 1, 8].iter().flat_map(|i| i.to_le_bytes()).collect();
    let b = cube_buffer(&bad);
    let json = format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0]}}],"nodes":[{{"mesh":0}}],
        "meshes":[{{"name":"lid","primitives":[{{"attributes":{{"POSITION":0}},"indices":1}},
            {{"attributes":{{"POSITION":0}},"indices":2}}]}}],
        "buffers":[{{"byteLength":{},"uri":"{}"}}],
        "bufferViews":[{CUBE_VIEWS},{{"buffer":0,"byteOffset":240,"byteLength":12}}],
        "accessors":[{POS},{{"bufferView":1,"componentType":5125,"count":36,"type":"SCALAR"}},
            {{"bufferView":2,"componentType":5125,"count":3,"type":"SCALAR"}}]}}"#,
        b.len(),
        data_uri(&b)
    );
    let p = write(&dir, "lid.gltf", json);
    let err = load_mesh(&p).unwrap_err();
    assert!(
        matches!(
            &err,
            GeomError::GltfIndexOutOfRange {
                mesh: 0,
                mesh_name: Some(n),
                primitive: 1,
                triangle: 0,
                index: 8,
                vertex_count: 8,
                ..
            } if n == "lid"
        ),
        "{err:?}"
    );
    assert_eq!(
        err.to_string(),
        format!(
            "{}: mesh 0 (\"lid\") primitive 1: triangle 0 uses vertex index 8, but the primitive has only 8 vertices",
            p.display()
        )
    );
}

/// A buffer `uri` that is empty, `.`, a folder or a FIFO: an error naming the glTF, the buffer
/// and its uri (it used to name only the folder: "/tmp/x is not a regular file").
#[test]
fn gltf_buffer_uris_that_are_not_files_name_the_buffer() {
    let dir = temp_dir("gbufdir");
    std::fs::create_dir_all(dir.join("sub")).unwrap();
    let gltf = |uri: &str| cube_doc(uri, r#"{"mesh":0}"#);
    // Empty: refused as it is written, whatever it would resolve to.
    for options in [
        LoadOptions::default(),
        LoadOptions::with_external_uris(true),
    ] {
        let p = write(&dir, "empty.gltf", gltf(""));
        let err = load_mesh_with(&p, &options).unwrap_err();
        assert!(
            matches!(&err, GeomError::UriRefused { buffer: 0, uri, .. } if uri.is_empty()),
            "{err:?}"
        );
        assert!(err.to_string().contains("is empty"), "{err}");
    }
    let mut cases = vec![
        (".", "directory"),
        ("sub", "directory"),
        ("sub/", "directory"),
    ];
    #[cfg(unix)]
    {
        let ok = std::process::Command::new("mkfifo")
            .arg(dir.join("fifo.bin"))
            .status()
            .unwrap()
            .success();
        assert!(ok, "mkfifo failed");
        cases.push(("fifo.bin", "FIFO"));
    }
    for (i, (uri, kind)) in cases.into_iter().enumerate() {
        let p = write(&dir, &format!("u{i}.gltf"), gltf(uri));
        let err = load_mesh(&p).unwrap_err();
        match &err {
            GeomError::BufferNotARegularFile {
                gltf,
                index: 0,
                uri: u,
                kind: k,
                ..
            } if gltf == &p && u == uri && *k == kind => {}
            other => panic!("{uri}: expected BufferNotARegularFile, got {other:?}"),
        }
        let msg = err.to_string();
        assert!(
            msg.starts_with(&format!("{}: buffer 0 (uri {uri:?}): ", p.display()))
                && msg.ends_with(&format!("is not a regular file (it is a {kind})")),
            "{msg}"
        );
    }
    // A missing file names them too.
    let p = write(&dir, "missing.gltf", gltf("nothing.bin"));
    let msg = load_mesh(&p).unwrap_err().to_string();
    assert!(
        msg.starts_with(&format!(
            "{}: buffer 0 (uri \"nothing.bin\"): cannot read ",
            p.display()
        )),
        "{msg}"
    );
}
