//! Scenes from the command line, as a user runs them on the shipped example
//! (`examples/scene/scene.toml`, two trained models): `query` (points, normals, rays, closest
//! points, levels; a single model too), `render --scene`, `extract --scene --level`, and every
//! bad input refused with a clear error and a non-zero exit, never a panic.

mod common;

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use common::{bin, scratch_in, stderr};
use glam::Vec3;
use hwsdf::geom::npy;
use hwsdf::nn::serve::scene::Scene;
use hwsdf::nn::{NeuralSdf, Nglod, Normalization};

fn scratch(name: &str) -> PathBuf {
    scratch_in("scene-cli", name)
}

fn example() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/scene/scene.toml")
}

/// The example scene, loaded once (the CPU reference of every answer).
fn scene() -> &'static Scene {
    static SCENE: OnceLock<Scene> = OnceLock::new();
    SCENE.get_or_init(|| Scene::load(example()).expect("the shipped example loads"))
}

/// A baked sphere of radius 0.5 around (1, 0, 0), in a box of half side 1 (mesh units).
fn sphere_model() -> &'static PathBuf {
    static PATH: OnceLock<PathBuf> = OnceLock::new();
    PATH.get_or_init(|| {
        let path = scratch("sphere.safetensors");
        let n = Normalization {
            center: glam::DVec3::X,
            scale: 1.0,
        };
        Nglod::from_sdf(16, |p| p.length() - 0.5)
            .unwrap()
            .to_model_file(n, serde_json::Value::Null)
            .save(&path)
            .unwrap();
        path
    })
}

fn points(n: usize, half: f32) -> Vec<Vec3> {
    // A fixed low-discrepancy set: no RNG needed.
    (0..n)
        .map(|i| {
            let f = |k: f32| ((i as f32 + 0.5) * k).fract() * 2.0 - 1.0;
            Vec3::new(f(0.618_034), f(0.754_877_7), f(0.569_840_3)) * half
        })
        .collect()
}

fn run_ok(cmd: &mut std::process::Command) {
    let o = cmd.output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(!stderr(&o).contains("panicked"));
}

fn assert_clean_failure(cmd: &mut std::process::Command, needle: &str) {
    let o = cmd.output().unwrap();
    let err = stderr(&o);
    assert!(!o.status.success(), "expected failure; stderr: {err}");
    assert!(!err.contains("panicked"), "panicked: {err}");
    assert!(
        err.to_lowercase().contains(&needle.to_lowercase()),
        "{needle:?} not in: {err}"
    );
}

/// Distances and normals of the scene at points, at level 0 and at a level c: the CPU's.
#[test]
fn query_points_of_a_scene() {
    let (p, d, n) = (scratch("p.npy"), scratch("d.npy"), scratch("n.npy"));
    let pts = points(500, 1.5);
    npy::write_points(&p, &pts).unwrap();
    for level in [0.0f32, 0.1] {
        run_ok(
            bin("query")
                .arg("--scene")
                .arg(example())
                .arg("--points")
                .arg(&p)
                .arg("--out")
                .arg(&d)
                .arg("--normals")
                .arg(&n)
                .args(["--level", &level.to_string()]),
        );
        let got = npy::read_f32(&d).unwrap();
        let normals = npy::read_points(&n).unwrap();
        let want = scene().distances_and_gradients(&pts, level);
        let mut other_normal = 0;
        for (i, w) in want.iter().enumerate() {
            assert!(
                (got[i] - w.distance).abs() < 1e-4,
                "point {i}: {} vs {}",
                got[i],
                w.distance
            );
            assert!(
                (normals[i].length() - 1.0).abs() < 1e-3,
                "normal {i}: {}",
                normals[i]
            );
            // Where two leaves tie within rounding the GPU may take the other one's normal.
            if !normals[i].abs_diff_eq(w.gradient.normalize_or_zero(), 1e-2) {
                other_normal += 1;
            }
        }
        assert!(
            other_normal <= 5,
            "{other_normal} of 500 normals differ from the CPU's"
        );
    }
}

/// Rays hit where the CPU's tracer says, misses are marked, and the rows have 9 columns.
#[test]
fn query_rays_and_closest_points_of_a_scene() {
    let (r, h) = (scratch("r.npy"), scratch("h.npy"));
    // Rays from a ring around the scene towards its middle, and two that look away.
    let mut rays: Vec<f32> = (0..40)
        .flat_map(|i| {
            let a = i as f32 * 0.157;
            let o = Vec3::new(3.0 * a.cos(), -0.4 + 0.02 * i as f32, 3.0 * a.sin());
            let dir = -o + Vec3::new(0.0, -0.3, 0.0);
            [o.x, o.y, o.z, dir.x, dir.y, dir.z]
        })
        .collect();
    rays.extend([3.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 5.0, 0.0, 0.0, 1.0, 0.0]);
    npy::write_table(&r, &rays, 6).unwrap();
    run_ok(
        bin("query")
            .arg("--scene")
            .arg(example())
            .arg("--rays")
            .arg(&r)
            .arg("--out")
            .arg(&h),
    );
    let hits = npy::read_table(&h, 9).unwrap();
    let cpu = scene()
        .trace_rays(
            &rays
                .chunks_exact(6)
                .map(|c| hwsdf::nn::serve::scene::Ray {
                    origin: Vec3::new(c[0], c[1], c[2]),
                    direction: Vec3::new(c[3], c[4], c[5]),
                    max_distance: f32::INFINITY,
                })
                .collect::<Vec<_>>(),
            &Default::default(),
        )
        .unwrap();
    let mut hit_count = 0;
    for (i, (row, want)) in hits.chunks_exact(9).zip(&cpu).enumerate() {
        match want {
            Some(w) => {
                hit_count += 1;
                assert_eq!(row[0], 1.0, "ray {i}");
                assert!(
                    (row[1] - w.t).abs() < 1e-3 * (1.0 + w.t),
                    "ray {i}: t {} vs {}",
                    row[1],
                    w.t
                );
                assert_eq!(row[8] as usize, w.leaf, "ray {i}");
            }
            None => assert_eq!((row[0], row[8]), (0.0, -1.0), "ray {i}"),
        }
    }
    assert!(hit_count >= 30, "{hit_count} of 42 rays hit");

    let (p, c) = (scratch("cp.npy"), scratch("c.npy"));
    let pts = points(200, 1.2);
    npy::write_points(&p, &pts).unwrap();
    run_ok(
        bin("query")
            .arg("--scene")
            .arg(example())
            .arg("--closest")
            .arg(&p)
            .arg("--out")
            .arg(&c)
            .args(["--level", "0.05"]),
    );
    let rows = npy::read_table(&c, 6).unwrap();
    let mut converged = 0;
    for row in rows.chunks_exact(6) {
        if row[5] == 1.0 {
            converged += 1;
            let at = Vec3::new(row[0], row[1], row[2]);
            assert!(scene().distance(at, 0.05).abs() < 1e-4, "{at}");
            // The default tolerance, 10⁻⁵ of the scene's half-side.
            assert!(row[3] < 1e-5 / scene().frame(0.0).scale);
        }
    }
    assert!(converged >= 150, "{converged} of 200 converged");
}

/// A single model answers the same forms: distances at points, rays, closest points.
#[test]
fn query_a_single_model() {
    let model = NeuralSdf::load(sphere_model()).unwrap();
    let (p, d) = (scratch("sp.npy"), scratch("sd.npy"));
    let pts = points(100, 0.9)
        .into_iter()
        .map(|q| q + Vec3::X)
        .collect::<Vec<_>>();
    npy::write_points(&p, &pts).unwrap();
    run_ok(
        bin("query")
            .arg(sphere_model())
            .arg("--points")
            .arg(&p)
            .arg("--out")
            .arg(&d),
    );
    let got = npy::read_f32(&d).unwrap();
    for (g, w) in got.iter().zip(model.eval_cpu(&pts)) {
        assert!((g - w).abs() < 1e-4, "{g} vs {w}");
    }
    let (r, h) = (scratch("sr.npy"), scratch("sh.npy"));
    npy::write_table(&r, &[1.0, 0.0, -0.9, 0.0, 0.0, 1.0], 6).unwrap();
    run_ok(
        bin("query")
            .arg(sphere_model())
            .arg("--rays")
            .arg(&r)
            .arg("--out")
            .arg(&h),
    );
    let hit = npy::read_table(&h, 9).unwrap();
    assert_eq!(hit[0], 1.0);
    assert!((hit[1] - 0.4).abs() < 0.02, "t = {}", hit[1]);
}

/// `query`'s tolerances are in proportion to the scene: rays into a sphere of radius 10⁻³
/// stop within 10⁻⁷ of it (the absolute 10⁻⁴ stopped up to a tenth of the radius short), and
/// rays into one of radius 10⁴ converge in f32 on the GPU (10⁻⁴ is below the spacing of f32
/// points there) and stop within 1.
#[test]
fn query_tolerances_scale_with_the_scene() {
    for (radius, tag) in [(1e-3_f32, "tiny"), (1e4, "huge")] {
        let file = scratch(&format!("{tag}.toml"));
        std::fs::write(
            &file,
            format!("[root]\ntype = \"sphere\"\nradius = {radius:e}\n"),
        )
        .unwrap();
        // Rays from three radii away, aimed at points within the sphere's disc (0.92 radii).
        let origin = Vec3::new(0.3, -0.2, -3.0) * radius;
        let rays: Vec<f32> = points(64, 0.65)
            .into_iter()
            .flat_map(|t| {
                let dir = Vec3::new(t.x, t.y, 0.0) * radius - origin;
                origin.to_array().into_iter().chain(dir.to_array())
            })
            .collect();
        let (r, h) = (
            scratch(&format!("{tag}-r.npy")),
            scratch(&format!("{tag}-h.npy")),
        );
        npy::write_table(&r, &rays, 6).unwrap();
        run_ok(
            bin("query")
                .arg("--scene")
                .arg(&file)
                .arg("--rays")
                .arg(&r)
                .arg("--out")
                .arg(&h),
        );
        let rows = npy::read_table(&h, 9).unwrap();
        let mut hits = 0;
        for (i, row) in rows.chunks_exact(9).enumerate() {
            if row[0] == 1.0 {
                hits += 1;
                let gap = Vec3::new(row[2], row[3], row[4]).length() - radius;
                // The tolerance (10⁻⁴ of the radius), and f32's rounding of the point.
                assert!(gap.abs() <= 1.2e-4 * radius, "{tag} ray {i}: |d| = {gap}");
            }
        }
        assert!(hits >= 60, "{tag}: {hits} of 64 rays hit");
    }
}

/// `render --scene` writes the PNG, and the scene is in it (not only background).
#[test]
fn render_a_scene() {
    let out = scratch("scene.png");
    run_ok(
        bin("render")
            .arg("--scene")
            .arg(example())
            .args(["--size", "40x32", "--out"])
            .arg(&out),
    );
    let bytes = std::fs::read(&out).unwrap();
    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
    let image = image_pixels(&bytes);
    let background = image[0];
    let lit = image.iter().filter(|p| **p != background).count();
    assert!(lit > 40 * 32 / 10, "only {lit} pixels show the scene");
}

/// `render MODEL` draws a model as `render --scene` draws the scene of that one leaf, pixel for
/// pixel: the same safe steps (by its Lipschitz bounds), the same framing.
#[test]
fn render_a_model_as_a_scene_of_one_leaf() {
    let model = sphere_model();
    let scene_file = model.with_file_name("one-leaf.toml");
    std::fs::write(
        &scene_file,
        "[models]\nsphere = \"sphere.safetensors\"\n\n[root]\ntype = \"model\"\nmodel = \"sphere\"\n",
    )
    .unwrap();
    let (as_model, as_scene) = (scratch("one-model.png"), scratch("one-leaf.png"));
    run_ok(
        bin("render")
            .arg(model)
            .args(["--size", "24x20", "--out"])
            .arg(&as_model),
    );
    run_ok(
        bin("render")
            .arg("--scene")
            .arg(&scene_file)
            .args(["--size", "24x20", "--out"])
            .arg(&as_scene),
    );
    let (a, b) = (
        image_pixels(&std::fs::read(&as_model).unwrap()),
        image_pixels(&std::fs::read(&as_scene).unwrap()),
    );
    assert!(
        a.iter().any(|p| *p != a[0]),
        "the model is not in the image"
    );
    assert_eq!(a, b);
}

/// A model of a mesh far from the origin for its size (trained from georeferenced or CAD
/// coordinates: its centre kept in f64) keeps its shape through `query`, `extract` and `render`:
/// float64 points and ray origins keep their precision, output points come out as float64, the
/// OBJ's vertices in f64. (In f32 at 10⁷ the sphere collapsed onto a one-unit grid: extract
/// wrote three distinct positions, render a blank image, query errors up to 1.)
#[test]
fn far_models_keep_their_coordinates() {
    let centre = glam::DVec3::new(1.0e7 + 0.25, -2.0e7, 3.0e7);
    let sphere = Nglod::from_sdf(32, |p| p.length() - 0.5).unwrap();
    let model = scratch("far.safetensors");
    let far = Normalization {
        center: centre,
        scale: 1.0,
    };
    sphere
        .to_model_file(far, serde_json::Value::Null)
        .save(&model)
        .unwrap();
    let near = NeuralSdf::from_model_file(
        sphere.to_model_file(Normalization::identity(), serde_json::Value::Null),
    )
    .unwrap();

    // Distances at float64 points: those of the same model about the origin.
    let offsets = points(50, 0.9);
    let rows: Vec<f64> = offsets
        .iter()
        .flat_map(|o| (o.as_dvec3() + centre).to_array())
        .collect();
    let (p, d) = (scratch("far-p.npy"), scratch("far-d.npy"));
    npy::write_table_f64(&p, &rows, 3).unwrap();
    run_ok(
        bin("query")
            .arg(&model)
            .arg("--points")
            .arg(&p)
            .arg("--out")
            .arg(&d),
    );
    let got = npy::read_f32(&d).unwrap();
    for ((g, w), o) in got.iter().zip(near.eval_cpu(&offsets)).zip(&offsets) {
        assert!((g - w).abs() < 1e-4, "at centre + {o}: {g} vs {w}");
    }

    // A ray from 3 units away along -x stops on the sphere, its point in float64.
    let (r, h) = (scratch("far-r.npy"), scratch("far-h.npy"));
    let origin = centre + glam::DVec3::X * 3.0;
    npy::write_table_f64(&r, &[origin.x, origin.y, origin.z, -1.0, 0.0, 0.0], 6).unwrap();
    run_ok(
        bin("query")
            .arg(&model)
            .arg("--rays")
            .arg(&r)
            .arg("--out")
            .arg(&h),
    );
    let hit = npy::read_table_f64(&h, 9).unwrap();
    assert_eq!(hit[0], 1.0, "{hit:?}");
    assert!((hit[1] - 2.5).abs() < 0.02, "t = {}", hit[1]);
    let point = glam::DVec3::new(hit[2], hit[3], hit[4]) - centre;
    assert!(
        (point - glam::DVec3::X * 0.5).length() < 0.02,
        "hit at centre + {point}"
    );

    // The extracted surface lies on the sphere about the f64 centre.
    let obj = scratch("far.obj");
    run_ok(
        bin("extract")
            .arg(&model)
            .args(["--resolution", "32", "--out"])
            .arg(&obj),
    );
    let text = std::fs::read_to_string(&obj).unwrap();
    let vertices: Vec<glam::DVec3> = text
        .lines()
        .filter_map(|l| l.strip_prefix("v "))
        .map(|l| {
            let c: Vec<f64> = l.split_whitespace().map(|x| x.parse().unwrap()).collect();
            glam::DVec3::new(c[0], c[1], c[2])
        })
        .collect();
    assert!(vertices.len() > 100, "{} vertices", vertices.len());
    for v in &vertices {
        let r = (*v - centre).length();
        assert!((r - 0.5).abs() < 0.03, "vertex at radius {r}");
    }

    // `eval` against a mesh at that centre (an octahedron of half-extent 1, so the loader
    // gives it this normalisation) scores the surface too: extracted in the normalised frame
    // (in mesh coordinates the extraction collapsed and eval failed with "no triangles").
    let octahedron = scratch("far-octahedron.obj");
    let mut text = String::new();
    for d in [
        glam::DVec3::X,
        -glam::DVec3::X,
        glam::DVec3::Y,
        -glam::DVec3::Y,
        glam::DVec3::Z,
        -glam::DVec3::Z,
    ] {
        let v = centre + d;
        text.push_str(&format!("v {} {} {}\n", v.x, v.y, v.z));
    }
    for f in [
        [1, 3, 5],
        [3, 2, 5],
        [2, 4, 5],
        [4, 1, 5],
        [3, 1, 6],
        [2, 3, 6],
        [4, 2, 6],
        [1, 4, 6],
    ] {
        text.push_str(&format!("f {} {} {}\n", f[0], f[1], f[2]));
    }
    std::fs::write(&octahedron, text).unwrap();
    let diamond = scratch("far-octahedron.safetensors");
    Nglod::from_sdf(32, |p| (p.abs().element_sum() - 1.0) / 3f32.sqrt())
        .unwrap()
        .to_model_file(far, serde_json::Value::Null)
        .save(&diamond)
        .unwrap();
    let o = bin("eval")
        .arg(&diamond)
        .arg(&octahedron)
        .args(["--json", "--points", "2000", "--surface-resolution", "32"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    // The loader's warning reaches the user (train, eval and corpus dropped it).
    assert!(stderr(&o).contains("far from the origin"), "{}", stderr(&o));
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let chamfer = report["chamfer_l1"].as_f64().expect("a surface score");
    assert!(chamfer < 0.02, "Chamfer-L1 {chamfer}");

    // The render shows it.
    let png = scratch("far.png");
    run_ok(
        bin("render")
            .arg(&model)
            .args(["--size", "24x20", "--out"])
            .arg(&png),
    );
    let image = image_pixels(&std::fs::read(&png).unwrap());
    let lit = image.iter().filter(|p| **p != image[0]).count();
    assert!(lit > 24 * 20 / 10, "only {lit} pixels show the model");
}

fn image_pixels(png: &[u8]) -> Vec<[u8; 4]> {
    let decoder = png::Decoder::new(std::io::Cursor::new(png));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    buf[..info.buffer_size()]
        .chunks_exact(4)
        .map(|c| [c[0], c[1], c[2], c[3]])
        .collect()
}

/// `extract --scene --level c` writes a mesh whose vertices lie on the level set.
#[test]
fn extract_a_scene_at_a_level() {
    let out = scratch("scene.obj");
    run_ok(
        bin("extract")
            .arg("--scene")
            .arg(example())
            .args(["--resolution", "48", "--level", "0.03", "--out"])
            .arg(&out),
    );
    let (mesh, _) = hwsdf::geom::load_mesh(&out).unwrap();
    assert!(
        mesh.triangles.len() > 500,
        "{} triangles",
        mesh.triangles.len()
    );
    let d = scene().distances(&mesh.vertices, 0.03);
    let h = 2.0 / scene().frame(0.03).scale / 48.0;
    let worst = d.iter().fold(0f32, |m, x| m.max(x.abs()));
    assert!(
        worst < h,
        "a vertex is {worst} from the level set (cell {h})"
    );
}

/// Bad input: clear errors, non-zero exits, no panics.
#[test]
fn bad_scene_input_is_refused() {
    let out = scratch("bad.npy");
    let p = scratch("bp.npy");
    npy::write_points(&p, &[Vec3::ZERO]).unwrap();
    // A level beyond the box.
    assert_clean_failure(
        bin("query")
            .arg("--scene")
            .arg(example())
            .arg("--points")
            .arg(&p)
            .arg("--out")
            .arg(&out)
            .args(["--level", "40"]),
        "beyond the scene's box",
    );
    assert_clean_failure(
        bin("query")
            .arg(sphere_model())
            .arg("--points")
            .arg(&p)
            .arg("--out")
            .arg(&out)
            .args(["--level", "-1.5"]),
        "beyond the model's box",
    );
    // A zero direction names the ray.
    let r = scratch("br.npy");
    npy::write_table(
        &r,
        &[0.0, 0.0, 3.0, 0.0, 0.0, -1.0, 0.0, 0.0, 3.0, 0.0, 0.0, 0.0],
        6,
    )
    .unwrap();
    assert_clean_failure(
        bin("query")
            .arg("--scene")
            .arg(example())
            .arg("--rays")
            .arg(&r)
            .arg("--out")
            .arg(&out),
        "ray 1: direction",
    );
    // Directions read in float64 are normalised before f32: 1e39 or 1e-50 per unit is the
    // unit direction (f32 made them infinite or zero, and the rays were refused), and so are
    // 1e200 and 1e-200 (whose squares overflow or vanish in f64).
    let scaled = scratch("scaled_rays.npy");
    let table: Vec<f64> = [1.0, 1e39, 1e-50, 1e200, 1e-200]
        .iter()
        .flat_map(|s| [0.0, 0.0, 3.0, 0.0, 0.0, -s])
        .collect();
    npy::write_table_f64(&scaled, &table, 6).unwrap();
    let hits = scratch("scaled_hits.npy");
    run_ok(
        bin("query")
            .arg("--scene")
            .arg(example())
            .arg("--rays")
            .arg(&scaled)
            .arg("--out")
            .arg(&hits),
    );
    let rows = npy::read_table(&hits, 9).unwrap();
    assert_eq!(rows[0], 1.0, "{rows:?}");
    for row in rows.chunks_exact(9) {
        assert_eq!(row, &rows[..9], "{rows:?}");
    }
    // An output that would replace one of the scene's models is refused before anything is
    // read or written (a copy of the example, so that a failure cannot harm the shipped one).
    let copy = scratch("scene-copy");
    std::fs::create_dir_all(&copy).unwrap();
    for name in [
        "scene.toml",
        "spot.nglod.safetensors",
        "teapot.nglod.safetensors",
    ] {
        std::fs::copy(example().with_file_name(name), copy.join(name)).unwrap();
    }
    let model = copy.join("teapot.nglod.safetensors");
    let before = std::fs::read(&model).unwrap();
    for bin_name in ["query", "render", "extract"] {
        let mut cmd = bin(bin_name);
        cmd.arg("--scene").arg(copy.join("scene.toml"));
        if bin_name == "query" {
            cmd.arg("--points").arg(&p);
        }
        assert_clean_failure(
            cmd.arg("--out").arg(&model),
            "is the same file as the input",
        );
    }
    assert_eq!(std::fs::read(&model).unwrap(), before);
    // An over-relaxation outside [1, 2).
    let good = scratch("good_ray.npy");
    npy::write_table(&good, &[0.0, 0.0, 3.0, 0.0, 0.0, -1.0], 6).unwrap();
    assert_clean_failure(
        bin("query")
            .arg("--scene")
            .arg(example())
            .arg("--rays")
            .arg(&good)
            .args(["--over-relaxation", "2"])
            .arg("--out")
            .arg(&out),
        "over-relaxation 2 must lie in [1, 2)",
    );
    // Rays need six columns.
    assert_clean_failure(
        bin("query")
            .arg("--scene")
            .arg(example())
            .arg("--rays")
            .arg(&p)
            .arg("--out")
            .arg(&out),
        "(N, 6)",
    );
    // A scene file with a syntax error, and one naming a missing model file.
    let broken = scratch("broken.toml");
    std::fs::write(&broken, "[root]\ntype = \"sphere\"\nradius = \n").unwrap();
    assert_clean_failure(
        bin("render")
            .arg("--scene")
            .arg(&broken)
            .arg("--out")
            .arg(scratch("x.png")),
        "line 3",
    );
    let missing = scratch("missing.toml");
    std::fs::write(
        &missing,
        "[models]\nghost = \"ghost.safetensors\"\n[root]\ntype = \"model\"\nmodel = \"ghost\"\n",
    )
    .unwrap();
    assert_clean_failure(
        bin("extract")
            .arg("--scene")
            .arg(&missing)
            .arg("--out")
            .arg(scratch("x.obj")),
        "ghost",
    );
    // --lod is a model's.
    assert_clean_failure(
        bin("render")
            .arg("--scene")
            .arg(example())
            .args(["--lod", "1", "--out"])
            .arg(scratch("y.png")),
        "--lod applies to a model",
    );
    // A model and a scene at once.
    assert_clean_failure(
        bin("query")
            .arg(sphere_model())
            .arg("--scene")
            .arg(example())
            .arg("--points")
            .arg(&p)
            .arg("--out")
            .arg(&out),
        "cannot be used with",
    );
}
