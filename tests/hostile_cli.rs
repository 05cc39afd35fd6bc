//! The CLI fuzz suite: malformed and hostile inputs, generated here at test time, run through the
//! built binaries with a timeout and a memory cap.
//!
//! Each case must end in a typed error (non-zero exit, an `error:` line naming the problem) or in
//! a correct result, and never in a panic, a signal, a hang, an exit 0 with a bad result, a
//! changed input file or a stray temporary file. Every file in the case's folder is hashed
//! before and after the run; only the outputs the case names may appear or change.
//!
//! Classes (issue 17): user files destroyed (aliasing outputs, planted links), silent wrong
//! results (NaN/inf model weights, negative learning rates, diverging training), unbounded memory
//! (`eval --points 1e9`, `extract --resolution 4096`, sizes declared in model files), special
//! files (FIFOs, `/dev/zero`, folders), and malformed files of every family that loads today
//! (OBJ, glTF/GLB, .npy, safetensors) and CLI values (NaN, inf, negative, huge numbers).
//!
//! [`MESH_READER_CASES`] holds the mesh and points reader cases (URI confinement, special files as
//! meshes and points, malformed glTF accessors, huge coordinates, far query points); they run in
//! `mesh_reader_cases`.

use std::collections::BTreeMap;
use std::ffi::OsString;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use hwsdf::geom::Normalization;
use hwsdf::nn::model_file::Tensor;
use hwsdf::nn::{ModelFile, Nglod, NglodConfig, Siren, SirenConfig};

/// Address-space cap of each child. The budgets under test are 4 GiB of estimated need; a
/// request refused up front stays far below this, one that allocates first does not.
const MEMORY_CAP: u64 = 3 << 30;
/// Wall-clock limit of a case that never reaches the GPU.
const QUICK: Duration = Duration::from_secs(30);
/// Wall-clock limit of a case that starts the GPU (lavapipe compiles shaders on the CPU).
const GPU: Duration = Duration::from_secs(180);

fn bin_path(name: &str) -> &'static str {
    match name {
        "train" => env!("CARGO_BIN_EXE_train"),
        "eval" => env!("CARGO_BIN_EXE_eval"),
        "extract" => env!("CARGO_BIN_EXE_extract"),
        "render" => env!("CARGO_BIN_EXE_render"),
        "sdf" => env!("CARGO_BIN_EXE_sdf"),
        "corpus" => env!("CARGO_BIN_EXE_corpus"),
        "query" => env!("CARGO_BIN_EXE_query"),
        other => panic!("no binary {other}"),
    }
}

/// What a case must end in.
enum Expect {
    /// Non-zero exit with an error message containing this (case-insensitive).
    Error(&'static str),
    /// Exit 0, and this check on the case's folder passes.
    Success(fn(&Path) -> Result<(), String>),
}

struct Case {
    name: String,
    bin: &'static str,
    args: Vec<OsString>,
    /// Files (in the case folder) the run may create or replace.
    outputs: Vec<&'static str>,
    expect: Expect,
    limit: Duration,
}

fn case(name: &str, bin: &'static str, args: &[&str], expect: Expect) -> Case {
    Case {
        name: name.to_owned(),
        bin,
        args: args.iter().map(OsString::from).collect(),
        outputs: Vec::new(),
        expect,
        limit: QUICK,
    }
}

impl Case {
    fn outputs(mut self, outputs: &[&'static str]) -> Self {
        self.outputs = outputs.to_vec();
        self
    }

    fn gpu(mut self) -> Self {
        self.limit = GPU;
        self
    }
}

/// FNV-1a, 64 bits: enough to notice a changed file.
fn hash(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

/// Every entry of `dir` by name: a hash for regular files, a tag for the rest (never read: a
/// FIFO would block).
fn snapshot(dir: &Path) -> BTreeMap<String, String> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| {
            let e = e.unwrap();
            let name = e.file_name().to_string_lossy().into_owned();
            let meta = std::fs::symlink_metadata(e.path()).unwrap();
            let tag = if meta.file_type().is_symlink() {
                format!(
                    "link to {}",
                    std::fs::read_link(e.path()).unwrap().display()
                )
            } else if meta.is_file() {
                format!("{:016x}", hash(&std::fs::read(e.path()).unwrap()))
            } else {
                "special".to_owned()
            };
            (name, tag)
        })
        .collect()
}

struct Outcome {
    code: Option<i32>,
    stderr: String,
    elapsed: Duration,
    timed_out: bool,
}

/// Runs `bin` in `dir` with the memory cap and the time limit.
fn run(bin: &str, args: &[OsString], dir: &Path, limit: Duration) -> Outcome {
    use std::os::unix::process::CommandExt;
    let mut cmd = Command::new(bin_path(bin));
    cmd.args(args)
        .current_dir(dir)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .env("RUST_BACKTRACE", "0");
    // SAFETY: setrlimit is async-signal-safe; nothing else runs between fork and exec.
    unsafe {
        cmd.pre_exec(|| {
            let cap = libc::rlimit {
                rlim_cur: MEMORY_CAP,
                rlim_max: MEMORY_CAP,
            };
            let no_core = libc::rlimit {
                rlim_cur: 0,
                rlim_max: 0,
            };
            if libc::setrlimit(libc::RLIMIT_AS, &cap) != 0
                || libc::setrlimit(libc::RLIMIT_CORE, &no_core) != 0
            {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    let start = Instant::now();
    let mut child = cmd.spawn().expect("spawn");
    // Read stderr on a thread so a chatty child never blocks on a full pipe.
    let mut pipe = child.stderr.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut s = Vec::new();
        let _ = pipe.read_to_end(&mut s);
        String::from_utf8_lossy(&s).into_owned()
    });
    let mut timed_out = false;
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if start.elapsed() > limit {
            timed_out = true;
            let _ = child.kill();
            break child.wait().unwrap();
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    Outcome {
        code: status.code(),
        stderr: reader.join().unwrap(),
        elapsed: start.elapsed(),
        timed_out,
    }
}

/// Runs one case in a fresh copy of the fixtures; `Err` says what went wrong.
fn check(case: &Case, fixtures: &Fixtures) -> Result<Duration, String> {
    let dir = fixtures.fresh_dir(&case.name);
    let before = snapshot(&dir);
    let out = run(case.bin, &case.args, &dir, case.limit);
    let after = snapshot(&dir);
    let last = out
        .stderr
        .trim_end()
        .lines()
        .last()
        .unwrap_or("")
        .to_owned();
    let fail = |why: String| Err(format!("{why}\n      stderr: {}", out.stderr.trim_end()));
    if out.timed_out {
        return fail(format!("hung: killed after {:.0?}", case.limit));
    }
    let Some(code) = out.code else {
        return fail("killed by a signal".into());
    };
    if out.stderr.contains("panicked") {
        return fail("panicked".into());
    }
    for (name, tag) in &before {
        if case.outputs.contains(&name.as_str()) {
            continue;
        }
        match after.get(name) {
            Some(t) if t == tag => {}
            Some(_) => return fail(format!("input {name} changed")),
            None => return fail(format!("input {name} was removed")),
        }
    }
    if let Some(extra) = after
        .keys()
        .find(|n| !before.contains_key(*n) && !case.outputs.contains(&n.as_str()))
    {
        return fail(format!("left a stray file behind: {extra}"));
    }
    match &case.expect {
        Expect::Error(needle) => {
            if code == 0 {
                return fail(format!("exit 0, expected an error about {needle:?}"));
            }
            let msg = out.stderr.to_lowercase();
            if !msg.contains("error") || !msg.contains(&needle.to_lowercase()) {
                return fail(format!("exit {code}, but the message lacks {needle:?}"));
            }
            // Refused cases write nothing.
            if let Some(o) = case
                .outputs
                .iter()
                .find(|o| !before.contains_key(**o) && after.contains_key(**o))
            {
                return fail(format!("failed but wrote {o}"));
            }
        }
        Expect::Success(verify) => {
            if code != 0 {
                return fail(format!("exit {code}, expected success ({last})"));
            }
            if let Err(e) = verify(&dir) {
                return fail(format!("exit 0 but wrong result: {e}"));
            }
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
    Ok(out.elapsed)
}

/// Runs every case, reports each, and fails with the list of failures.
fn run_all(cases: &[Case], fixtures: &Fixtures) -> Vec<String> {
    let mut failures = Vec::new();
    for c in cases {
        match check(c, fixtures) {
            Ok(t) => eprintln!("ok    {:<44} {:>6.2} s", c.name, t.as_secs_f64()),
            Err(e) => {
                eprintln!("FAIL  {:<44} {e}", c.name);
                failures.push(format!("{} ({} {:?}): {e}", c.name, c.bin, c.args));
            }
        }
    }
    failures
}

// ---------------------------------------------------------------------------------------------
// Fixtures, generated at test time.

struct Fixtures {
    root: PathBuf,
    /// File name and bytes of each fixture, copied into every case's folder.
    files: Vec<(String, Vec<u8>)>,
}

impl Fixtures {
    fn new(tag: &str) -> Fixtures {
        let root = std::env::temp_dir().join(format!("hwsdf-hostile-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        std::fs::create_dir_all(&root).unwrap();
        let mut files: Vec<(String, Vec<u8>)> = Vec::new();
        let mut add = |name: &str, bytes: Vec<u8>| files.push((name.to_owned(), bytes));

        add("cube.obj", CUBE_OBJ.as_bytes().to_vec());
        add(
            "points.npy",
            npy_f32(&[0.0, 0.0, 0.0, 2.0, 0.5, 0.5], "(2, 3)"),
        );

        // A model whose distance is exactly the plane x = 0.3 in its box: NGLOD with one 4-cell
        // level holding x + 2 at each vertex (trilinear interpolation reproduces it), one ReLU
        // unit and bias -2.3.
        let plane = plane_model();
        add("plane.safetensors", plane.to_bytes().unwrap());

        // The same with one NaN and one inf weight.
        for (name, v) in [
            ("nan.safetensors", f32::NAN),
            ("inf.safetensors", f32::INFINITY),
        ] {
            let mut m = plane.clone();
            m.tensors[0].data[7] = v;
            add(name, m.to_bytes().unwrap());
        }
        // Finite weights whose sums overflow f32: the model evaluates to ∞ or NaN everywhere.
        let mut huge = plane.clone();
        for t in &mut huge.tensors {
            // The grids are stored as f16 (at most 65504), the MLP as f32.
            let v = if t.name.starts_with("grids") {
                6e4
            } else {
                3e38
            };
            t.data.iter_mut().for_each(|x| *x = v);
        }
        add("huge.safetensors", huge.to_bytes().unwrap());
        // A model without a surface in its box: Φ ≥ 97 everywhere.
        add(
            "no_surface.safetensors",
            plane_model_with_bias(100.0).to_bytes().unwrap(),
        );
        // A 36 kB SIREN that claims width 4096 × 64 layers: 1.07 G parameters, 4.3 GB.
        let mut siren = Siren::new(SirenConfig::small(), 0)
            .unwrap()
            .to_model_file(identity(), serde_json::json!({}));
        siren.metadata.config =
            serde_json::json!({"width": 4096, "hidden_layers": 64, "omega0": 30.0});
        add("claims_huge.safetensors", siren.to_bytes().unwrap());
        // NGLOD config with resolution 500 (2 GB of grids) and the small tensors.
        let mut big = plane.clone();
        big.metadata.config["resolutions"] = serde_json::json!([500]);
        add("claims_grid500.safetensors", big.to_bytes().unwrap());
        // Eight sparse levels of 255 cells: a few kB that would need 134 M table entries.
        let mut tables = plane.clone();
        tables.metadata.config["resolutions"] = serde_json::json!(vec![255; 8]);
        tables.metadata.config["sparse_levels"] = serde_json::json!(8);
        add(
            "claims_sparse_tables.safetensors",
            tables.to_bytes().unwrap(),
        );

        let good = plane.to_bytes().unwrap();
        add("empty.safetensors", Vec::new());
        add("truncated.safetensors", good[..good.len() - 5].to_vec());
        add("header_only.safetensors", good[..40].to_vec());
        // Header length u64::MAX, then a length far past the end.
        let mut huge_header = u64::MAX.to_le_bytes().to_vec();
        huge_header.extend_from_slice(b"{}");
        add("header_len_max.safetensors", huge_header);
        let mut long_header = (90u64 << 20).to_le_bytes().to_vec();
        long_header.extend_from_slice(b"{\"__metadata__\":{}}");
        add("header_len_90m.safetensors", long_header);
        add(
            "garbage.safetensors",
            b"\x10\x00\x00\x00\x00\x00\x00\x00not json at all!".to_vec(),
        );
        // Shapes whose product overflows, offsets past the end, an i32 tensor (models hold
        // F32, F16 and U32 ones).
        add(
            "shape_overflow.safetensors",
            safetensors_raw(
                r#"{"w":{"dtype":"F32","shape":[4611686018427387904,4611686018427387904],"data_offsets":[0,4]}}"#,
                4,
            ),
        );
        add(
            "offsets_past_end.safetensors",
            safetensors_raw(
                r#"{"w":{"dtype":"F32","shape":[1000],"data_offsets":[0,4000]}}"#,
                4,
            ),
        );
        let mut i32 = plane.to_bytes().unwrap();
        let at = i32.windows(5).position(|w| w == b"\"F32\"").unwrap();
        i32[at..at + 5].copy_from_slice(b"\"I32\"");
        add("i32.safetensors", i32);

        // Checkpoints: the plane model with optimiser moments and a run record.
        let n = plane.param_count();
        let checkpoint = |lr: f64, v: f32| {
            let mut c = plane.clone();
            for (name, value) in [("optimizer.m", 0.0), ("optimizer.v", v)] {
                c.tensors.push(Tensor::f32(name, vec![n], vec![value; n]));
            }
            c.metadata.training = serde_json::json!({
                "checkpoint": true, "adam_step": 1, "lr": lr, "done": 1,
                "model": "nglod", "preset": "small",
            });
            // Trained on cube.obj, which the cases resume it on.
            c.metadata.normalization = cube_normalization();
            c.to_bytes().unwrap()
        };
        add("negative_lr.checkpoint.safetensors", checkpoint(-1e-3, 0.0));
        add("nan_lr.checkpoint.safetensors", checkpoint(1e39, 0.0));
        add("negative_v.checkpoint.safetensors", checkpoint(1e-3, -1.0));
        let mut done5: ModelFile =
            ModelFile::from_bytes(&checkpoint(1e-3, 0.0), Path::new("done5")).unwrap();
        done5.metadata.training["done"] = 5.into();
        add("done5.checkpoint.safetensors", done5.to_bytes().unwrap());
        // A sound checkpoint of another mesh (normalised as the identity, where cube.obj
        // normalises about scale 2).
        let mut other: ModelFile =
            ModelFile::from_bytes(&checkpoint(1e-3, 0.0), Path::new("plane")).unwrap();
        other.metadata.normalization = identity();
        add("plane.checkpoint.safetensors", other.to_bytes().unwrap());
        let mut resnet: ModelFile =
            ModelFile::from_bytes(&checkpoint(1e-3, 0.0), Path::new("resnet")).unwrap();
        resnet.metadata.training["model"] = "resnet".into();
        add("resnet.checkpoint.safetensors", resnet.to_bytes().unwrap());

        hashgrid_fixtures(&mut add, &plane);

        // Meshes that load today's readers must refuse.
        add("empty.obj", Vec::new());
        add(
            "nan_vertex.obj",
            b"v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n".to_vec(),
        );
        add(
            "bad_index.obj",
            b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99\n".to_vec(),
        );
        add(
            "binary.obj",
            (0..4096u32)
                .map(|i| (i.wrapping_mul(2_654_435_761) >> 24) as u8)
                .collect(),
        );
        add("garbage.gltf", b"{ this is not json".to_vec());
        add(
            "truncated.glb",
            b"glTF\x02\x00\x00\x00\xff\xff\xff\x7f".to_vec(),
        );
        add("empty.glb", Vec::new());

        // Points files.
        add("nan_points.npy", npy_f32(&[0.0, f32::NAN, 0.0], "(1, 3)"));
        let beyond_f32 = [0.0, 1e39f64, 0.0];
        let bytes = beyond_f32.iter().flat_map(|v| v.to_le_bytes());
        add("beyond_f32_points.npy", npy_of("<f8", bytes, "(1, 3)"));
        add("garbage.npy", b"not an npy file".to_vec());
        add("empty.npy", Vec::new());

        Fixtures { root, files }
    }

    /// A new folder holding every fixture, plus the special entries (FIFO, links, folders).
    fn fresh_dir(&self, name: &str) -> PathBuf {
        let dir = self.root.join(name.replace(['/', ' '], "_"));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        for (n, bytes) in &self.files {
            std::fs::write(dir.join(n), bytes).unwrap();
        }
        let c = std::ffi::CString::new(dir.join("fifo").to_str().unwrap()).unwrap();
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        std::os::unix::fs::symlink("cube.obj", dir.join("cube_link.obj")).unwrap();
        std::os::unix::fs::symlink("plane.safetensors", dir.join("model_link.safetensors"))
            .unwrap();
        std::fs::hard_link(dir.join("cube.obj"), dir.join("cube_hard.obj")).unwrap();
        std::fs::create_dir(dir.join("folder")).unwrap();
        dir
    }
}

/// Hash-grid model files (issue 39) that disagree with themselves: see [`hashgrid_cases`].
fn hashgrid_fixtures(add: &mut impl FnMut(&str, Vec<u8>), plane: &ModelFile) {
    // Two levels: 4 cells (125 vertices, stored densely) and 64 cells hashed into a table of
    // 2^10 entries, one feature each; an MLP of 2 hidden units.
    let grid = |log2: u32| {
        let config = NglodConfig {
            seed: 1,
            ..NglodConfig::hashgrid(2, 4, 64, 1, log2, 2)
        };
        Nglod::new(config)
            .unwrap()
            .to_model_file(identity(), serde_json::json!({}))
    };
    let good = grid(10);
    assert_eq!(good.metadata.architecture, "hashgrid");
    add("hashgrid.safetensors", good.to_bytes().unwrap());
    let edited = |edit: &dyn Fn(&mut ModelFile)| {
        let mut f = good.clone();
        edit(&mut f);
        f.to_bytes().unwrap()
    };
    // The config's table is 4 times the stored one (more than the file holds), then half of it.
    add(
        "hashgrid_table_larger.safetensors",
        edited(&|f| f.metadata.config["encoding"]["log2_table_size"] = 12.into()),
    );
    let mut wide = grid(11);
    wide.metadata.config["encoding"]["log2_table_size"] = 10.into();
    add(
        "hashgrid_table_smaller.safetensors",
        wide.to_bytes().unwrap(),
    );
    add(
        "hashgrid_table_2_40.safetensors",
        edited(&|f| f.metadata.config["encoding"]["log2_table_size"] = 40.into()),
    );
    add(
        "hashgrid_table_negative.safetensors",
        edited(&|f| f.metadata.config["encoding"]["log2_table_size"] = (-3).into()),
    );
    add(
        "hashgrid_17_levels.safetensors",
        edited(&|f| f.metadata.config["resolutions"] = serde_json::json!(vec![4; 17])),
    );
    // The file says "hashgrid", its config describes NGLOD (no encoding: summed levels)...
    add(
        "hashgrid_summed.safetensors",
        edited(&|f| {
            f.metadata
                .config
                .as_object_mut()
                .unwrap()
                .remove("encoding");
        }),
    );
    // ... and the reverse, an "nglod" file whose config is a hash grid's.
    add(
        "nglod_hashed.safetensors",
        edited(&|f| f.metadata.architecture = "nglod".into()),
    );
    // A plane NGLOD under a hash grid's name.
    let mut plane_named = plane.clone();
    plane_named.metadata.architecture = "hashgrid".into();
    add(
        "plane_says_hashgrid.safetensors",
        plane_named.to_bytes().unwrap(),
    );
    // Non-finite features in the hashed table and in the dense level.
    for (name, tensor, v) in [
        ("hashgrid_nan.safetensors", "grids.1", f32::NAN),
        ("hashgrid_inf.safetensors", "grids.0", f32::INFINITY),
    ] {
        add(
            name,
            edited(&|f| {
                let t = f.tensors.iter_mut().find(|t| t.name == tensor).unwrap();
                t.data[5] = v;
            }),
        );
    }
    // A hash grid's checkpoint, and one whose run record says "hashgrid" over NGLOD's tensors.
    let checkpoint = |file: &ModelFile| {
        let mut c = file.clone();
        let n = c.param_count();
        for name in ["optimizer.m", "optimizer.v"] {
            c.tensors.push(Tensor::f32(name, vec![n], vec![0.0; n]));
        }
        c.metadata.training = serde_json::json!({
            "checkpoint": true, "adam_step": 1, "lr": 1e-2, "done": 1,
            "model": "hashgrid", "preset": "small",
        });
        c.metadata.normalization = cube_normalization();
        c.to_bytes().unwrap()
    };
    add("hashgrid.checkpoint.safetensors", checkpoint(&good));
    add(
        "nglod_says_hashgrid.checkpoint.safetensors",
        checkpoint(plane),
    );
}

/// cube.obj's normalisation (its half-extent is 1/2).
fn cube_normalization() -> Normalization {
    Normalization {
        center: glam::DVec3::ZERO,
        scale: 2.0,
    }
}

fn identity() -> Normalization {
    Normalization {
        center: glam::Vec3::ZERO.as_dvec3(),
        scale: 1.0,
    }
}

fn plane_model() -> ModelFile {
    plane_model_with_bias(-2.3)
}

/// [`plane_model`] with another output bias: +100 puts the plane outside the box (no surface).
fn plane_model_with_bias(bias: f32) -> ModelFile {
    let config = NglodConfig {
        resolutions: vec![4],
        feature_dim: 1,
        hidden: 1,
        seed: 0,
        sparse_levels: 0,
        band_cells: 0,
        encoding: Default::default(),
    };
    // Grid `[ix, iy, iz, f]`, vertex ix at x = -1 + ix / 2.
    let mut params: Vec<f32> = (0..125)
        .map(|i| -1.0 + (i / 25) as f32 * 0.5 + 2.0)
        .collect();
    params.extend_from_slice(&[1.0, 0.0, 1.0, bias]);
    Nglod::from_params(config, params)
        .unwrap()
        .to_model_file(identity(), serde_json::json!({}))
}

/// A safetensors file from a raw JSON header and `data` zero bytes.
fn safetensors_raw(header: &str, data: usize) -> Vec<u8> {
    let mut out = (header.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(header.as_bytes());
    out.resize(out.len() + data, 0);
    out
}

/// A little-endian float32 .npy file.
fn npy_f32(values: &[f32], shape: &str) -> Vec<u8> {
    npy_of("<f4", values.iter().flat_map(|v| v.to_le_bytes()), shape)
}

/// A little-endian .npy file of type `descr` holding `data`.
fn npy_of(descr: &str, data: impl IntoIterator<Item = u8>, shape: &str) -> Vec<u8> {
    let mut header = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out.extend(data);
    out
}

/// A closed unit cube, 12 triangles, outward normals.
const CUBE_OBJ: &str = "v -0.5 -0.5 -0.5\nv 0.5 -0.5 -0.5\nv 0.5 0.5 -0.5\nv -0.5 0.5 -0.5\n\
v -0.5 -0.5 0.5\nv 0.5 -0.5 0.5\nv 0.5 0.5 0.5\nv -0.5 0.5 0.5\n\
f 1 3 2\nf 1 4 3\nf 5 6 7\nf 5 7 8\nf 1 2 6\nf 1 6 5\nf 4 8 7\nf 4 7 3\nf 1 5 8\nf 1 8 4\nf 2 3 7\nf 2 7 6\n";

// ---------------------------------------------------------------------------------------------
// Result checks for the cases that succeed.

/// `plane.obj`: a mesh whose every vertex inside the model's box `[-1, 1]³` lies on x = 0.3
/// (within a cell; outside the box the grid is clamped and the model is not a plane).
fn plane_obj(dir: &Path) -> Result<(), String> {
    let text = std::fs::read_to_string(dir.join("plane.obj")).map_err(|e| e.to_string())?;
    let vertices: Vec<Vec<f32>> = text
        .lines()
        .filter_map(|l| l.strip_prefix("v "))
        .map(|l| l.split_whitespace().map(|v| v.parse().unwrap()).collect())
        .collect();
    let inside: Vec<&Vec<f32>> = vertices
        .iter()
        .filter(|v| v.iter().all(|c| c.abs() <= 1.0))
        .collect();
    if inside.len() < 1000 || !text.lines().any(|l| l.starts_with("f ")) {
        return Err(format!("{} vertices in the box, no surface", inside.len()));
    }
    match inside.iter().find(|v| (v[0] - 0.3).abs() > 0.05) {
        Some(v) => Err(format!("vertex at {v:?}, expected x = 0.3")),
        None => Ok(()),
    }
}

/// `d.npy`: the cube's distances at (0, 0, 0) and (2, 0.5, 0.5): -0.5 and 1.5.
fn cube_distances(dir: &Path) -> Result<(), String> {
    let d = hwsdf::geom::npy::read_f32(dir.join("d.npy")).map_err(|e| e.to_string())?;
    let ok = d.len() == 2 && (d[0] + 0.5).abs() < 1e-5 && (d[1] - 1.5).abs() < 1e-5;
    ok.then_some(())
        .ok_or(format!("distances {d:?}, expected [-0.5, 1.5]"))
}

fn png(dir: &Path) -> Result<(), String> {
    let bytes = std::fs::read(dir.join("image.png")).map_err(|e| e.to_string())?;
    bytes
        .starts_with(b"\x89PNG")
        .then_some(())
        .ok_or("not a PNG".into())
}

// ---------------------------------------------------------------------------------------------
// The cases.

fn cases() -> Vec<Case> {
    use Expect::{Error, Success};
    vec![
        // A user's file destroyed: outputs aliasing inputs or each other.
        case(
            "train --out mesh",
            "train",
            &["cube.obj", "--out", "cube.obj"],
            Error("same file"),
        ),
        case(
            "train --report mesh",
            "train",
            &["cube.obj", "--out", "m.safetensors", "--report", "cube.obj"],
            Error("same file"),
        ),
        case(
            "train --report via symlink",
            "train",
            &[
                "cube.obj",
                "--out",
                "m.safetensors",
                "--report",
                "cube_link.obj",
            ],
            Error("same file"),
        ),
        case(
            "train --out hard link",
            "train",
            &["cube.obj", "--out", "cube_hard.obj"],
            Error("same file"),
        ),
        case(
            "train --out == --report",
            "train",
            &[
                "cube.obj",
                "--out",
                "m.safetensors",
                "--report",
                "./m.safetensors",
            ],
            Error("same file"),
        ),
        case(
            "train --out resume checkpoint",
            "train",
            &[
                "cube.obj",
                "--resume",
                "negative_lr.checkpoint.safetensors",
                "--out",
                "negative_lr.checkpoint.safetensors",
            ],
            Error("same file"),
        ),
        case(
            "train --out missing folder",
            "train",
            &["cube.obj", "--out", "missing/m.safetensors"],
            Error("does not exist"),
        ),
        case(
            "train --out is a folder",
            "train",
            &["cube.obj", "--out", "folder"],
            Error("not a regular file"),
        ),
        case(
            "sdf --out points",
            "sdf",
            &["cube.obj", "--points", "points.npy", "--out", "points.npy"],
            Error("same file"),
        ),
        case(
            "sdf --out mesh",
            "sdf",
            &["cube.obj", "--points", "points.npy", "--out", "cube.obj"],
            Error("same file"),
        ),
        case(
            "extract --out model",
            "extract",
            &["plane.safetensors", "--out", "plane.safetensors"],
            Error("same file"),
        ),
        case(
            "extract --out model symlink",
            "extract",
            &["plane.safetensors", "--out", "model_link.safetensors"],
            Error("same file"),
        ),
        case(
            "render --out model",
            "render",
            &["plane.safetensors", "--out", "plane.safetensors"],
            Error("same file"),
        ),
        case(
            "render --out missing folder",
            "render",
            &["plane.safetensors", "--out", "missing/i.png"],
            Error("does not exist"),
        ),
        // An output named for another format than the one written: OBJ text as mesh.ply, a
        // PNG as .jpg, a model file as .obj (which `load_mesh` then read as an OBJ).
        case(
            "extract --out PLY",
            "extract",
            &["plane.safetensors", "--out", "o.ply"],
            Error("give the file the extension .obj"),
        ),
        case(
            "render --out JPEG",
            "render",
            &["plane.safetensors", "--out", "i.jpg"],
            Error("give the file the extension .png"),
        ),
        case(
            "query --normals CSV",
            "query",
            &[
                "plane.safetensors",
                "--points",
                "points.npy",
                "--out",
                "d.npy",
                "--normals",
                "n.csv",
            ],
            Error("--normals n.csv: this writes .npy"),
        ),
        case(
            "sdf --out text",
            "sdf",
            &["cube.obj", "--points", "points.npy", "--out", "d.txt"],
            Error("give the file the extension .npy"),
        ),
        case(
            "train --out OBJ",
            "train",
            &["cube.obj", "--out", "m.obj"],
            Error("give the file the extension .safetensors"),
        ),
        case(
            "corpus --out mesh",
            "corpus",
            &[".", "--out", "cube.obj"],
            Error("same file"),
        ),
        // Silent wrong results from model files.
        case(
            "extract NaN weights",
            "extract",
            &["nan.safetensors", "--out", "o.obj"],
            Error("finite"),
        ),
        case(
            "render inf weights",
            "render",
            &["inf.safetensors", "--out", "i.png"],
            Error("finite"),
        ),
        case(
            "eval NaN weights",
            "eval",
            &["nan.safetensors", "cube.obj"],
            Error("finite"),
        ),
        case(
            "train --out x.json, the report's default name",
            "train",
            &["cube.obj", "--out", "m.json"],
            Error("would also be the report's default name"),
        ),
        case(
            "resume a checkpoint of the other model",
            "train",
            &[
                "cube.obj",
                "--model",
                "siren",
                "--resume",
                "done5.checkpoint.safetensors",
            ],
            Error("done5.checkpoint.safetensors: the checkpoint is of a nglod model, not siren"),
        ),
        // Models that load but cannot be scored, shown or meshed.
        case(
            "eval overflowing weights",
            "eval",
            &["huge.safetensors", "cube.obj", "--points", "200"],
            Error("finite distances"),
        )
        .gpu(),
        case(
            "render overflowing weights",
            "render",
            &["huge.safetensors", "--out", "h.png", "--size", "16x16"],
            Error("finite distances"),
        )
        .gpu(),
        case(
            "extract a model without a surface",
            "extract",
            &[
                "no_surface.safetensors",
                "--resolution",
                "8",
                "--out",
                "n.obj",
            ],
            Error("does not cross the box"),
        )
        .gpu(),
        // Lengths and loss settings the checks must explain (negative numbers included: clap
        // would call them unknown flags).
        case(
            "train --steps past the most",
            "train",
            &[
                "cube.obj",
                "--model",
                "siren",
                "--steps",
                "18446744073709551615",
            ],
            Error("at most"),
        ),
        case(
            "train --lr negative",
            "train",
            &["cube.obj", "--lr", "-0.5"],
            Error("learning rate must be finite and positive, not -0.5"),
        ),
        case(
            "train --alpha 0",
            "train",
            &["cube.obj", "--model", "siren", "--alpha", "0"],
            Error("alpha, the sharpness"),
        ),
        case(
            "train --eikonal-weight negative",
            "train",
            &["cube.obj", "--model", "siren", "--eikonal-weight", "-1"],
            Error("eikonal loss weight must be finite and non-negative, not -1"),
        ),
        case(
            "train --sign-weight NaN",
            "train",
            &["cube.obj", "--model", "siren", "--sign-weight", "NaN"],
            Error("sign loss weight must be finite and non-negative, not NaN"),
        ),
        case(
            "resume past the length asked",
            "train",
            &[
                "cube.obj",
                "--preset",
                "small",
                "--epochs",
                "2",
                "--resume",
                "done5.checkpoint.safetensors",
                "--out",
                "m.safetensors",
            ],
            Error("done5.checkpoint.safetensors: the checkpoint has done 5 epochs already"),
        )
        .gpu(),
        case(
            "resume on another mesh",
            "train",
            &[
                "cube.obj",
                "--epochs",
                "2",
                "--resume",
                "plane.checkpoint.safetensors",
                "--out",
                "m.safetensors",
            ],
            Error(
                "plane.checkpoint.safetensors: the checkpoint was trained on another mesh (normalised about centre [0, 0, 0], scale 1; this mesh: centre [0, 0, 0], scale 2)",
            ),
        )
        .gpu(),
        // Without --model and --preset a resume takes both from the checkpoint (NGLOD `small`
        // here, where a CPU adapter's default model is the hash grid and NGLOD's preset on any
        // adapter is `default`), so the check that refuses it is the length's.
        case(
            "resume with the checkpoint's model and preset",
            "train",
            &[
                "cube.obj",
                "--epochs",
                "2",
                "--resume",
                "done5.checkpoint.safetensors",
                "--out",
                "m.safetensors",
            ],
            Error("done5.checkpoint.safetensors: the checkpoint has done 5 epochs already"),
        )
        .gpu(),
        // A checkpoint of a model this build does not know, resumed without --model: named as
        // such before anything else runs.
        case(
            "resume a checkpoint of an unknown model",
            "train",
            &[
                "cube.obj",
                "--resume",
                "resnet.checkpoint.safetensors",
                "--out",
                "m.safetensors",
            ],
            Error(
                "resnet.checkpoint.safetensors: the checkpoint names no model this build trains (resnet)",
            ),
        ),
        // Checkpoint hyperparameters.
        case(
            "resume negative lr",
            "train",
            &[
                "cube.obj",
                "--preset",
                "small",
                "--resume",
                "negative_lr.checkpoint.safetensors",
                "--out",
                "m.safetensors",
            ],
            Error("learning rate"),
        ),
        case(
            "resume lr 1e39",
            "train",
            &[
                "cube.obj",
                "--preset",
                "small",
                "--resume",
                "nan_lr.checkpoint.safetensors",
                "--out",
                "m.safetensors",
            ],
            Error("learning rate"),
        ),
        case(
            "resume negative moment",
            "train",
            &[
                "cube.obj",
                "--preset",
                "small",
                "--resume",
                "negative_v.checkpoint.safetensors",
                "--out",
                "m.safetensors",
            ],
            Error("second moment"),
        ),
        case(
            "resume a plain model",
            "train",
            &[
                "cube.obj",
                "--resume",
                "plane.safetensors",
                "--out",
                "m.safetensors",
            ],
            Error("not a checkpoint"),
        ),
        // Sizes declared in model files.
        case(
            "siren claims 4096x64",
            "extract",
            &["claims_huge.safetensors", "--out", "o.obj"],
            Error("declares"),
        ),
        case(
            "nglod claims resolution 500",
            "extract",
            &["claims_grid500.safetensors", "--out", "o.obj"],
            Error("declares"),
        ),
        case(
            "nglod claims eight sparse levels of 255 cells",
            "extract",
            &["claims_sparse_tables.safetensors", "--out", "o.obj"],
            Error("tables"),
        ),
        // Malformed safetensors.
        case(
            "model empty",
            "extract",
            &["empty.safetensors", "--out", "o.obj"],
            Error("safetensors"),
        ),
        case(
            "model truncated",
            "extract",
            &["truncated.safetensors", "--out", "o.obj"],
            Error("safetensors"),
        ),
        case(
            "model header only",
            "extract",
            &["header_only.safetensors", "--out", "o.obj"],
            Error("safetensors"),
        ),
        case(
            "model header length u64::MAX",
            "extract",
            &["header_len_max.safetensors", "--out", "o.obj"],
            Error("safetensors"),
        ),
        case(
            "model header length 90 MB",
            "extract",
            &["header_len_90m.safetensors", "--out", "o.obj"],
            Error("safetensors"),
        ),
        case(
            "model garbage",
            "render",
            &["garbage.safetensors", "--out", "i.png"],
            Error("safetensors"),
        ),
        case(
            "model shape overflow",
            "extract",
            &["shape_overflow.safetensors", "--out", "o.obj"],
            Error("safetensors"),
        ),
        case(
            "model offsets past end",
            "extract",
            &["offsets_past_end.safetensors", "--out", "o.obj"],
            Error("safetensors"),
        ),
        case(
            "model i32 tensor",
            "extract",
            &["i32.safetensors", "--out", "o.obj"],
            Error("safetensors"),
        ),
        // Special files as models.
        case(
            "model is a FIFO",
            "extract",
            &["fifo", "--out", "o.obj"],
            Error("not a regular file"),
        ),
        case(
            "model is /dev/zero",
            "render",
            &["/dev/zero", "--out", "i.png"],
            Error("not a regular file"),
        ),
        case(
            "model is a folder",
            "eval",
            &["folder", "cube.obj"],
            Error("not a regular file"),
        ),
        case(
            "model missing",
            "extract",
            &["nothing.safetensors", "--out", "o.obj"],
            Error("no such file"),
        ),
        case(
            "eval --surface-resolution 1",
            "eval",
            &["plane.safetensors", "cube.obj", "--surface-resolution", "1"],
            Error("--surface-resolution 1 is out of range"),
        ),
        case(
            "eval --surface-resolution 5000",
            "eval",
            &[
                "plane.safetensors",
                "cube.obj",
                "--surface-resolution",
                "5000",
            ],
            Error("out of range: 0 (skip) or 2 to 4096"),
        ),
        // Memory budgets.
        case(
            "eval --points 1e9",
            "eval",
            &["plane.safetensors", "cube.obj", "--points", "1000000000"],
            Error("budget"),
        ),
        case(
            "train --eval-points 1e9",
            "train",
            &[
                "cube.obj",
                "--eval-points",
                "1000000000",
                "--out",
                "m.safetensors",
            ],
            Error("budget"),
        ),
        case(
            "extract --resolution 4096",
            "extract",
            &[
                "plane.safetensors",
                "--resolution",
                "4096",
                "--out",
                "o.obj",
            ],
            Error("budget"),
        )
        .gpu(),
        case(
            "extract --resolution 4097",
            "extract",
            &[
                "plane.safetensors",
                "--resolution",
                "4097",
                "--out",
                "o.obj",
            ],
            Error("out of range"),
        ),
        case(
            "extract --max-memory-gib nan",
            "extract",
            &[
                "plane.safetensors",
                "--max-memory-gib",
                "nan",
                "--out",
                "o.obj",
            ],
            Error("positive"),
        ),
        // CLI values.
        case(
            "train --lr nan",
            "train",
            &[
                "cube.obj",
                "--model",
                "siren",
                "--preset",
                "small",
                "--steps",
                "1",
                "--lr",
                "nan",
                "--out",
                "m.safetensors",
            ],
            Error("learning rate"),
        ),
        case(
            "train --lr -1",
            "train",
            &[
                "cube.obj",
                "--model",
                "nglod",
                "--preset",
                "small",
                "--epochs",
                "1",
                "--lr=-1",
                "--out",
                "m.safetensors",
            ],
            Error("learning rate"),
        ),
        case(
            "train --alpha inf",
            "train",
            &[
                "cube.obj",
                "--model",
                "siren",
                "--preset",
                "small",
                "--steps",
                "1",
                "--alpha",
                "inf",
                "--out",
                "m.safetensors",
            ],
            Error(
                "alpha, the sharpness of the off-surface term exp(−α|Φ|), must be finite and positive, not inf",
            ),
        ),
        case(
            "train --steps 0",
            "train",
            &["cube.obj", "--model", "siren", "--steps", "0"],
            Error("at least 1"),
        ),
        case(
            "train --eval-points 0",
            "train",
            &["cube.obj", "--eval-points", "0"],
            Error("at least 1"),
        ),
        case(
            "train siren --lr-final",
            "train",
            &["cube.obj", "--model", "siren", "--lr-final", "0.5"],
            Error("apply to NGLOD"),
        ),
        case(
            "train nglod --plateau-patience",
            "train",
            &["cube.obj", "--plateau-patience", "100"],
            Error("--plateau-patience applies to SIREN"),
        ),
        case(
            "train siren --plateau-patience ten",
            "train",
            &["cube.obj", "--model", "siren", "--plateau-patience", "ten"],
            Error("--plateau-patience"),
        ),
        case(
            "train --lr-final nan",
            "train",
            &["cube.obj", "--lr-final", "nan"],
            Error("--lr-final must be finite"),
        ),
        case(
            "train --batch 0",
            "train",
            &["cube.obj", "--batch", "0"],
            Error("--batch must lie in 1..=65536, not 0"),
        ),
        case(
            "train siren --batch",
            "train",
            &["cube.obj", "--model", "siren", "--batch", "4096"],
            Error("--batch applies to NGLOD"),
        ),
        case(
            "corpus --lr with both models",
            "corpus",
            &[".", "--lr", "1e-3"],
            Error("--lr sets one model's learning rate"),
        ),
        case(
            "corpus siren --epochs",
            "corpus",
            &[".", "--model", "siren", "--epochs", "3"],
            Error("--epochs applies to NGLOD"),
        ),
        case(
            "corpus --sparse-levels 9",
            "corpus",
            &[".", "--model", "nglod", "--sparse-levels", "9"],
            Error("sparse"),
        ),
        // The model is named once: "NGLOD: invalid configuration", not "NGLOD: invalid NGLOD ...".
        case(
            "train --resolutions 0,4",
            "train",
            &["cube.obj", "--resolutions", "0,4", "--out", "m.safetensors"],
            Error("NGLOD: invalid configuration: resolution 0"),
        ),
        // A valid configuration of 10⁹ parameters: refused by the device's limit before the
        // host allocates and fills 4 GB of them (under the memory cap, an abort before).
        case(
            "train --resolutions 1000",
            "train",
            &[
                "cube.obj",
                "--model",
                "nglod",
                "--resolutions",
                "1000",
                "--sparse-levels",
                "0",
                "--features",
                "1",
                "--hidden",
                "8",
                "--out",
                "m.safetensors",
            ],
            Error("NGLOD parameters"),
        ),
        case(
            "train --pool 10000,1",
            "train",
            &["cube.obj", "--model", "nglod", "--pool", "10000,1", "--out", "m.safetensors"],
            Error("more than 2^32 / 3 points"),
        ),
        // Under 2^32 points, but not their coordinates, which the kernels index in u32.
        case(
            "train --pool 3000,1",
            "train",
            &["cube.obj", "--model", "nglod", "--pool", "3000,1", "--out", "m.safetensors"],
            Error("more than 2^32 / 3 points"),
        ),
        case(
            "corpus --eval-points 0",
            "corpus",
            &[".", "--eval-points", "0"],
            Error("at least 1"),
        ),
        case(
            "eval --points 0",
            "eval",
            &["plane.safetensors", "cube.obj", "--points", "0"],
            Error("at least 1"),
        ),
        case(
            "render --size 0",
            "render",
            &["plane.safetensors", "--out", "i.png", "--size", "0"],
            Error("size"),
        ),
        case(
            "render --size huge",
            "render",
            &[
                "plane.safetensors",
                "--out",
                "i.png",
                "--size",
                "100000x100000",
            ],
            Error("size"),
        ),
        case(
            "render --frame-radius -1",
            "render",
            &["plane.safetensors", "--out", "i.png", "--frame-radius=-1"],
            Error("radius"),
        ),
        case(
            "render --yaw nan",
            "render",
            &["plane.safetensors", "--out", "i.png", "--yaw", "nan"],
            Error("yaw"),
        ),
        case(
            "extract --lod 9",
            "extract",
            &["plane.safetensors", "--lod", "9", "--out", "o.obj"],
            Error("level of detail"),
        ),
        // Malformed meshes and points that today's readers refuse.
        case(
            "mesh empty obj",
            "sdf",
            &["empty.obj", "--points", "points.npy", "--out", "d.npy"],
            Error(""),
        ),
        case(
            "mesh NaN vertex",
            "sdf",
            &["nan_vertex.obj", "--points", "points.npy", "--out", "d.npy"],
            Error(""),
        ),
        case(
            "mesh bad index",
            "sdf",
            &["bad_index.obj", "--points", "points.npy", "--out", "d.npy"],
            Error(""),
        ),
        case(
            "mesh binary garbage obj",
            "sdf",
            &["binary.obj", "--points", "points.npy", "--out", "d.npy"],
            Error(""),
        ),
        case(
            "mesh garbage gltf",
            "sdf",
            &["garbage.gltf", "--points", "points.npy", "--out", "d.npy"],
            Error(""),
        ),
        case(
            "mesh truncated glb",
            "sdf",
            &["truncated.glb", "--points", "points.npy", "--out", "d.npy"],
            Error(""),
        ),
        case(
            "mesh empty glb",
            "train",
            &["empty.glb", "--out", "m.safetensors"],
            Error(""),
        ),
        case(
            "points NaN",
            "sdf",
            &["cube.obj", "--points", "nan_points.npy", "--out", "d.npy"],
            Error("not finite"),
        ),
        // A float64 point f32 cannot hold, named as the file gives it.
        case(
            "points beyond float32",
            "sdf",
            &["cube.obj", "--points", "beyond_f32_points.npy", "--out", "d.npy"],
            Error("point 0 is too far from the mesh for float32: [0, 1000000000000000000000000000000000000000, 0]"),
        ),
        case(
            "points garbage",
            "sdf",
            &["cube.obj", "--points", "garbage.npy", "--out", "d.npy"],
            Error(""),
        ),
        case(
            "points empty file",
            "sdf",
            &["cube.obj", "--points", "empty.npy", "--out", "d.npy"],
            Error(""),
        ),
        // Correct results where one is possible.
        case(
            "sdf on the cube",
            "sdf",
            &["cube.obj", "--points", "points.npy", "--out", "d.npy"],
            Success(cube_distances),
        )
        .outputs(&["d.npy"]),
        case(
            "sdf --out replaces an old output",
            "sdf",
            &["cube.obj", "--points", "points.npy", "--out", "empty.npy"],
            Success(|d| {
                let n =
                    hwsdf::geom::npy::read_f32(d.join("empty.npy")).map_err(|e| e.to_string())?;
                (n.len() == 2).then_some(()).ok_or("not replaced".into())
            }),
        )
        .outputs(&["empty.npy"]),
        case(
            "extract the plane",
            "extract",
            &[
                "plane.safetensors",
                "--resolution",
                "64",
                "--out",
                "plane.obj",
            ],
            Success(plane_obj),
        )
        .outputs(&["plane.obj"])
        .gpu(),
        case(
            "render the plane",
            "render",
            &["plane.safetensors", "--out", "image.png", "--size", "32"],
            Success(png),
        )
        .outputs(&["image.png"])
        .gpu(),
        // Training that diverges ends in a typed error and saves nothing.
        case(
            "train --eikonal-weight 1e38",
            "train",
            &[
                "cube.obj",
                "--model",
                "siren",
                "--preset",
                "small",
                "--steps",
                "2",
                "--eikonal-weight",
                "1e38",
                "--eval-points",
                "1000",
                "--out",
                "m.safetensors",
            ],
            Error("diverged"),
        )
        .gpu(),
        // A folder no one can create files in, root included.
        case(
            "extract --out read-only folder",
            "extract",
            &["plane.safetensors", "--out", "/proc/o.obj"],
            Error("not writable"),
        ),
    ]
}

/// The mesh and points reader cases (URI confinement, regular-file checks for meshes and points,
/// glTF accessors, coordinates near f32::MAX, far query points), run by `mesh_reader_cases`.
const MESH_READER_CASES: &[(&str, &str, &[&str])] = &[
    (
        "mesh is a FIFO",
        "sdf",
        &["fifo", "--points", "points.npy", "--out", "d.npy"],
    ),
    (
        "mesh is /dev/zero",
        "sdf",
        &["/dev/zero.obj", "--points", "points.npy", "--out", "d.npy"],
    ),
    (
        "points are a FIFO",
        "sdf",
        &["cube.obj", "--points", "fifo", "--out", "d.npy"],
    ),
    (
        "gltf buffer outside its folder",
        "sdf",
        &[
            "outside_uri.gltf",
            "--points",
            "points.npy",
            "--out",
            "d.npy",
        ],
    ),
    (
        "gltf accessor past its buffer",
        "sdf",
        &[
            "bad_accessor.gltf",
            "--points",
            "points.npy",
            "--out",
            "d.npy",
        ],
    ),
    (
        "obj with BOM and comments",
        "sdf",
        &["bom.obj", "--points", "points.npy", "--out", "d.npy"],
    ),
    (
        "obj coordinates near 1e38",
        "sdf",
        &[
            "huge_coords.obj",
            "--points",
            "points.npy",
            "--out",
            "d.npy",
        ],
    ),
    (
        "far query points",
        "sdf",
        &["cube.obj", "--points", "far_points.npy", "--out", "d.npy"],
    ),
    (
        "npy shape claims 1e12 points",
        "sdf",
        &[
            "cube.obj",
            "--points",
            "npy_huge_shape.npy",
            "--out",
            "d.npy",
        ],
    ),
];

/// Extra fixtures of the mesh-reader cases.
fn mesh_reader_fixtures(dir: &Path) {
    let w = |name: &str, bytes: &[u8]| std::fs::write(dir.join(name), bytes).unwrap();
    w("outside_uri.gltf", br#"{"asset":{"version":"2.0"},"buffers":[{"uri":"../../../../etc/passwd","byteLength":36}],"bufferViews":[{"buffer":0,"byteLength":36}],"accessors":[{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3"}],"meshes":[{"primitives":[{"attributes":{"POSITION":0}}]}],"nodes":[{"mesh":0}],"scenes":[{"nodes":[0]}]}"#);
    w("bad_accessor.gltf", br#"{"asset":{"version":"2.0"},"buffers":[{"uri":"data:application/octet-stream;base64,AAAAAAAAAAAAAAAA","byteLength":12}],"bufferViews":[{"buffer":0,"byteLength":12}],"accessors":[{"bufferView":0,"componentType":5126,"count":1000000,"type":"VEC3"}],"meshes":[{"primitives":[{"attributes":{"POSITION":0}}]}],"nodes":[{"mesh":0}],"scenes":[{"nodes":[0]}]}"#);
    w(
        "bom.obj",
        format!("\u{feff}# a comment\n{CUBE_OBJ}").as_bytes(),
    );
    w(
        "huge_coords.obj",
        CUBE_OBJ.replace("0.5", "1e38").as_bytes(),
    );
    w(
        "far_points.npy",
        &npy_f32(&[1e30, 0.0, 0.0, -3e38, 1.0, 0.0], "(2, 3)"),
    );
    w(
        "npy_huge_shape.npy",
        &npy_f32(&[0.0; 3], "(1000000000000, 3)"),
    );
}

#[test]
fn hostile_inputs_end_in_typed_errors_or_correct_results() {
    let fixtures = Fixtures::new("main");
    let start = Instant::now();
    let cases = cases();
    let failures = run_all(&cases, &fixtures);
    eprintln!(
        "{} cases in {:.1} s",
        cases.len(),
        start.elapsed().as_secs_f64()
    );
    if failures.is_empty() {
        let _ = std::fs::remove_dir_all(&fixtures.root);
    }
    assert!(
        failures.is_empty(),
        "{} of {} hostile cases failed:\n{}",
        failures.len(),
        cases.len(),
        failures.join("\n")
    );
}

/// The mesh and points reader cases: each must end in a typed error or in a correct result
/// (exit 0 only if the distances written are finite), never hang or crash.
#[test]
fn mesh_reader_cases() {
    let fixtures = Fixtures::new("mesh-reader");
    let mut failures = Vec::new();
    for &(name, bin, args) in MESH_READER_CASES {
        let dir = fixtures.fresh_dir(name);
        mesh_reader_fixtures(&dir);
        let c = Case {
            name: name.to_owned(),
            bin,
            args: args.iter().map(OsString::from).collect(),
            outputs: vec!["d.npy"],
            expect: Expect::Error(""),
            limit: QUICK,
        };
        let before = snapshot(&dir);
        let out = run(c.bin, &c.args, &dir, c.limit);
        let after = snapshot(&dir);
        let changed = before
            .iter()
            .any(|(n, t)| n != "d.npy" && after.get(n) != Some(t));
        let finite = || {
            hwsdf::geom::npy::read_f32(dir.join("d.npy"))
                .is_ok_and(|d| d.iter().all(|x| x.is_finite()))
        };
        let verdict = if out.timed_out {
            Some("hung".to_owned())
        } else if out.code.is_none() {
            Some("killed by a signal".into())
        } else if out.stderr.contains("panicked") {
            Some("panicked".into())
        } else if changed {
            Some("changed an input".into())
        } else if out.code == Some(0) && !finite() {
            Some("exit 0 with non-finite or missing distances".into())
        } else if out.code != Some(0) && !out.stderr.contains("error") {
            Some("failed without an error message".into())
        } else {
            None
        };
        match verdict {
            None => eprintln!("ok    {name}"),
            Some(v) => {
                eprintln!("FAIL  {name}: {v}\n      {}", out.stderr.trim_end());
                failures.push(format!("{name}: {v}"));
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// Ctrl-C during `train`'s final evaluation ends the run at once (exit 130): the model saved
/// before the evaluation stays, no report is written, and no temporary file is left.
#[test]
fn ctrl_c_during_the_evaluation_is_honoured() {
    use std::io::BufRead;
    let fixtures = Fixtures::new("ctrlc");
    let dir = fixtures.fresh_dir("ctrlc");
    let before = snapshot(&dir);
    // Two million evaluation points: building the sets alone takes many seconds.
    let mut child = Command::new(bin_path("train"))
        .args([
            "cube.obj", "--model", "siren", "--preset", "small", "--steps", "1",
        ])
        .args(["--eval-points", "2000000", "--out", "m.safetensors"])
        .current_dir(&dir)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    let stderr = std::io::BufReader::new(child.stderr.take().unwrap());
    std::thread::spawn(move || {
        for line in stderr.lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    let start = Instant::now();
    let mut log = Vec::new();
    loop {
        match rx.recv_timeout(Duration::from_secs(1)) {
            Ok(line) => {
                let evaluating = line.contains("evaluating");
                log.push(line);
                if evaluating {
                    break;
                }
            }
            Err(_) if start.elapsed() > GPU => {
                let _ = child.kill();
                panic!("training did not reach the evaluation: {log:#?}");
            }
            Err(_) => {}
        }
        if let Some(status) = child.try_wait().unwrap() {
            panic!("train ended before the evaluation ({status}): {log:#?}");
        }
    }
    std::thread::sleep(Duration::from_millis(500));
    let sent = Instant::now();
    assert_eq!(unsafe { libc::kill(child.id() as i32, libc::SIGINT) }, 0);
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if sent.elapsed() > Duration::from_secs(10) {
            let _ = child.kill();
            panic!("Ctrl-C during the evaluation was ignored for 10 s");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let waited = sent.elapsed();
    assert_eq!(status.code(), Some(130), "{status}");
    assert!(waited < Duration::from_secs(3), "took {waited:?}");
    let after = snapshot(&dir);
    let new: Vec<&String> = after.keys().filter(|k| !before.contains_key(*k)).collect();
    assert_eq!(new, ["m.safetensors"], "only the model is written");
    let _ = std::fs::remove_dir_all(&fixtures.root);
}

/// Hash-grid model files that disagree with themselves or claim what they do not hold: each
/// ends in a typed error from the model's checks, before anything the size of its claims is
/// allocated (the address-space cap of [`MEMORY_CAP`] would kill a run that tried).
fn hashgrid_cases() -> Vec<Case> {
    use Expect::{Error, Success};
    vec![
        case(
            "hashgrid config's table larger than its tensors",
            "extract",
            &["hashgrid_table_larger.safetensors", "--out", "o.obj"],
            Error("declares"),
        )
        .outputs(&["o.obj"]),
        case(
            "hashgrid config's table smaller than its tensors",
            "render",
            &["hashgrid_table_smaller.safetensors", "--out", "i.png"],
            Error("grids.1"),
        )
        .outputs(&["i.png"]),
        case(
            "hashgrid table of 2^40 entries",
            "eval",
            &["hashgrid_table_2_40.safetensors", "cube.obj"],
            Error("log2_table_size must be in"),
        ),
        case(
            "hashgrid table of 2^-3 entries",
            "extract",
            &["hashgrid_table_negative.safetensors", "--out", "o.obj"],
            Error("config"),
        )
        .outputs(&["o.obj"]),
        case(
            "hashgrid of 17 levels",
            "query",
            &[
                "hashgrid_17_levels.safetensors",
                "--points",
                "points.npy",
                "--out",
                "d.npy",
            ],
            Error("17 levels; between 1 and 16"),
        )
        .outputs(&["d.npy"]),
        case(
            "a hashgrid file with NGLOD's config",
            "extract",
            &["hashgrid_summed.safetensors", "--out", "o.obj"],
            Error("the file says `hashgrid` but its configuration describes a `nglod` model"),
        )
        .outputs(&["o.obj"]),
        case(
            "an nglod file with a hash grid's config",
            "render",
            &["nglod_hashed.safetensors", "--out", "i.png"],
            Error("the file says `nglod` but its configuration describes a `hashgrid` model"),
        )
        .outputs(&["i.png"]),
        case(
            "NGLOD's plane named hashgrid",
            "eval",
            &["plane_says_hashgrid.safetensors", "cube.obj"],
            Error("describes a `nglod` model"),
        ),
        case(
            "hashgrid NaN in its hashed table",
            "extract",
            &["hashgrid_nan.safetensors", "--out", "o.obj"],
            Error("finite"),
        )
        .outputs(&["o.obj"]),
        case(
            "hashgrid inf in its dense level",
            "query",
            &[
                "hashgrid_inf.safetensors",
                "--points",
                "points.npy",
                "--out",
                "d.npy",
            ],
            Error("finite"),
        )
        .outputs(&["d.npy"]),
        case(
            "hashgrid --lod short of all its levels",
            "render",
            &["hashgrid.safetensors", "--lod", "1", "--out", "i.png"],
            Error("levels of detail exist only for NGLOD models"),
        )
        .outputs(&["i.png"]),
        case(
            "resume a hash grid's checkpoint as NGLOD",
            "train",
            &[
                "cube.obj",
                "--model",
                "nglod",
                "--resume",
                "hashgrid.checkpoint.safetensors",
                "--out",
                "m.safetensors",
            ],
            Error("the checkpoint is of a hashgrid model, not nglod"),
        )
        .outputs(&["m.safetensors", "m.json"]),
        case(
            "resume NGLOD's tensors recorded as a hash grid",
            "train",
            &[
                "cube.obj",
                "--model",
                "hashgrid",
                "--preset",
                "small",
                "--resume",
                "nglod_says_hashgrid.checkpoint.safetensors",
                "--out",
                "m.safetensors",
            ],
            Error("the checkpoint holds a nglod model, not hashgrid"),
        )
        .outputs(&["m.safetensors", "m.json", "m.checkpoint.safetensors"])
        .gpu(),
        // The well-formed file loads: the cases above fail for what they claim, not for being
        // hash grids.
        case(
            "hashgrid well formed",
            "eval",
            &[
                "hashgrid.safetensors",
                "cube.obj",
                "--points",
                "500",
                "--surface-resolution",
                "0",
            ],
            Success(|_| Ok(())),
        )
        .gpu(),
    ]
}

#[test]
fn hostile_hash_grid_files_end_in_typed_errors() {
    let fixtures = Fixtures::new("hashgrid");
    let cases = hashgrid_cases();
    let failures = run_all(&cases, &fixtures);
    if failures.is_empty() {
        let _ = std::fs::remove_dir_all(&fixtures.root);
    }
    assert!(
        failures.is_empty(),
        "{} of {} hash-grid cases failed:\n{}",
        failures.len(),
        cases.len(),
        failures.join("\n")
    );
}
