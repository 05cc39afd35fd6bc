//! Shared helpers for the integration tests.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use base64::Engine as _;

/// A mesh from the repository's `tests/data`.
pub fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/data")
        .join(name)
}

/// A fresh, empty temporary directory for one test.
pub fn temp_dir(tag: &str) -> PathBuf {
    static N: AtomicUsize = AtomicUsize::new(0);
    let dir = std::env::temp_dir().join(format!(
        "sdf-geom-test-{}-{tag}-{}",
        std::process::id(),
        N.fetch_add(1, Ordering::Relaxed)
    ));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("create temp dir");
    dir
}

/// Writes `text` to `dir/name` and returns the path.
pub fn write(dir: &Path, name: &str, bytes: impl AsRef<[u8]>) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, bytes).expect("write fixture");
    p
}

/// A unit cube [0,1]^3, outward-oriented: 8 positions, 12 triangles.
pub fn cube() -> (Vec<[f32; 3]>, Vec<u32>) {
    let v = (0..8)
        .map(|i| [(i & 1) as f32, ((i >> 1) & 1) as f32, ((i >> 2) & 1) as f32])
        .collect();
    let t = vec![
        0, 2, 1, 1, 2, 3, 4, 5, 6, 5, 7, 6, 0, 1, 4, 1, 5, 4, 2, 6, 3, 3, 6, 7, 0, 4, 2, 2, 4, 6,
        1, 3, 5, 3, 7, 5,
    ];
    (v, t)
}

/// Options for [`gltf_json`].
pub struct Gltf<'a> {
    pub positions: &'a [[f32; 3]],
    pub indices: Option<&'a [u32]>,
    pub mode: u32,
    /// Node matrices (column-major); one node per matrix, all instancing mesh 0.
    pub matrices: Vec<[f32; 16]>,
    /// How the buffer is stored: `None` = base64 data URI, `Some(name)` = external file name.
    pub external: Option<&'a str>,
    pub extensions_used: &'a [&'a str],
    pub extensions_required: &'a [&'a str],
    pub image_uri: Option<&'a str>,
}

impl Default for Gltf<'_> {
    fn default() -> Self {
        Gltf {
            positions: &[],
            indices: None,
            mode: 4,
            matrices: vec![IDENTITY],
            external: None,
            extensions_used: &[],
            extensions_required: &[],
            image_uri: None,
        }
    }
}

pub const IDENTITY: [f32; 16] = [
    1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
];

/// Builds a minimal glTF JSON document; returns (json, buffer bytes).
pub fn gltf_json(g: &Gltf) -> (String, Vec<u8>) {
    let mut buf: Vec<u8> = g
        .positions
        .iter()
        .flatten()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let pos_len = buf.len();
    let idx_off = buf.len();
    if let Some(ix) = g.indices {
        buf.extend(ix.iter().flat_map(|v| v.to_le_bytes()));
    }
    let mut min = [f32::INFINITY; 3];
    let mut max = [f32::NEG_INFINITY; 3];
    for p in g.positions {
        for k in 0..3 {
            min[k] = min[k].min(p[k]);
            max[k] = max[k].max(p[k]);
        }
    }
    let uri = match g.external {
        Some(name) => name.to_string(),
        None => format!(
            "data:application/octet-stream;base64,{}",
            base64::engine::general_purpose::STANDARD.encode(&buf)
        ),
    };
    let mut views = vec![format!(
        r#"{{"buffer":0,"byteOffset":0,"byteLength":{pos_len}}}"#
    )];
    let mut accessors = vec![format!(
        r#"{{"bufferView":0,"componentType":5126,"count":{},"type":"VEC3","min":[{},{},{}],"max":[{},{},{}]}}"#,
        g.positions.len(),
        min[0],
        min[1],
        min[2],
        max[0],
        max[1],
        max[2]
    )];
    let mut prim = format!(r#"{{"attributes":{{"POSITION":0}},"mode":{}"#, g.mode);
    if let Some(ix) = g.indices {
        views.push(format!(
            r#"{{"buffer":0,"byteOffset":{idx_off},"byteLength":{}}}"#,
            ix.len() * 4
        ));
        accessors.push(format!(
            r#"{{"bufferView":1,"componentType":5125,"count":{},"type":"SCALAR"}}"#,
            ix.len()
        ));
        prim.push_str(r#","indices":1"#);
    }
    if g.image_uri.is_some() {
        prim.push_str(r#","material":0"#);
    }
    prim.push('}');
    let nodes: Vec<String> = g
        .matrices
        .iter()
        .map(|m| {
            let m: Vec<String> = m.iter().map(|x| format!("{x}")).collect();
            format!(r#"{{"mesh":0,"matrix":[{}]}}"#, m.join(","))
        })
        .collect();
    let scene_nodes: Vec<String> = (0..g.matrices.len()).map(|i| i.to_string()).collect();
    let ext: Vec<String> = g
        .extensions_used
        .iter()
        .map(|e| format!("\"{e}\""))
        .collect();
    let mut json = format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[{}]}}],"nodes":[{}],"meshes":[{{"primitives":[{prim}]}}],"buffers":[{{"byteLength":{},"uri":"{uri}"}}],"bufferViews":[{}],"accessors":[{}]"#,
        scene_nodes.join(","),
        nodes.join(","),
        buf.len(),
        views.join(","),
        accessors.join(",")
    );
    if !ext.is_empty() {
        json.push_str(&format!(r#","extensionsUsed":[{}]"#, ext.join(",")));
    }
    if !g.extensions_required.is_empty() {
        let req: Vec<String> = g
            .extensions_required
            .iter()
            .map(|e| format!("\"{e}\""))
            .collect();
        json.push_str(&format!(r#","extensionsRequired":[{}]"#, req.join(",")));
    }
    if let Some(img) = g.image_uri {
        json.push_str(&format!(
            r#","images":[{{"uri":"{img}"}}],"textures":[{{"source":0}}],"materials":[{{"pbrMetallicRoughness":{{"baseColorTexture":{{"index":0}}}}}}]"#
        ));
    }
    json.push('}');
    (json, buf)
}

/// Writes a glTF (and its external buffer if requested) into `dir`; returns the .gltf path.
pub fn write_gltf(dir: &Path, name: &str, g: &Gltf) -> PathBuf {
    let (json, buf) = gltf_json(g);
    if let Some(ext) = g.external {
        write(dir, ext, &buf);
    }
    write(dir, name, json)
}
