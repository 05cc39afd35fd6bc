//! The `sdf` binary: reads N×3 float32/float64 .npy points, writes N float32 signed distances.

use std::path::{Path, PathBuf};
use std::process::Command;

use glam::Vec3;
use hwsdf::geom::{SignedDistance, load_mesh, npy, sample};

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

fn temp_dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("hwsdf-cli-{}-{tag}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn sdf(args: &[&std::ffi::OsStr]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_sdf"))
        .args(args)
        .output()
        .expect("run sdf")
}

#[test]
fn writes_signed_distances_in_mesh_and_normalised_coordinates() {
    let dir = temp_dir("ok");
    let mesh_path = data("spot.obj");
    let (mesh, _) = load_mesh(&mesh_path).unwrap();
    let (unit, norm) = mesh.normalized();
    let unit_pts: Vec<Vec3> = sample::uniform_box(500, 1);
    let mesh_pts: Vec<Vec3> = unit_pts.iter().map(|&p| norm.to_original(p)).collect();

    // float32 input, mesh coordinates.
    let inp = dir.join("pts.npy");
    npy::write_points(&inp, &mesh_pts).unwrap();
    let out = dir.join("d.npy");
    let o = sdf(&[
        mesh_path.as_os_str(),
        "--points".as_ref(),
        inp.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let d = npy::read_f32(&out).unwrap();
    let expect = SignedDistance::new(&mesh)
        .unwrap()
        .signed_distance_batch(&mesh_pts);
    assert_eq!(d, expect);
    assert!(d.iter().any(|&x| x < 0.0) && d.iter().any(|&x| x > 0.0));

    // float64 input, normalised coordinates.
    let mut bytes = npy_header("<f8", unit_pts.len());
    bytes.extend(
        unit_pts
            .iter()
            .flat_map(|p| p.to_array())
            .flat_map(|v| (v as f64).to_le_bytes()),
    );
    let inp64 = dir.join("pts64.npy");
    std::fs::write(&inp64, bytes).unwrap();
    let out2 = dir.join("d2.npy");
    let o = sdf(&[
        mesh_path.as_os_str(),
        "--points".as_ref(),
        inp64.as_os_str(),
        "--out".as_ref(),
        out2.as_os_str(),
        "--normalized".as_ref(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let d2 = npy::read_f32(&out2).unwrap();
    let expect = SignedDistance::new(&unit)
        .unwrap()
        .signed_distance_batch(&unit_pts);
    assert_eq!(d2, expect);
    // The two runs agree up to the scale.
    for (a, b) in d.iter().zip(&d2) {
        assert!((norm.distance_to_original(*b) - a).abs() < 1e-4);
    }
}

fn npy_header(descr: &str, n: usize) -> Vec<u8> {
    let mut h = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': ({n}, 3), }}");
    while (10 + h.len() + 1) % 64 != 0 {
        h.push(' ');
    }
    h.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend((h.len() as u16).to_le_bytes());
    out.extend(h.as_bytes());
    out
}

#[test]
fn clear_errors_and_no_partial_output() {
    let dir = temp_dir("err");
    let mesh_path = data("suzanne.obj");
    let out = dir.join("d.npy");
    let run = |points: &Path, mesh: &Path| {
        sdf(&[
            mesh.as_os_str(),
            "--points".as_ref(),
            points.as_os_str(),
            "--out".as_ref(),
            out.as_os_str(),
        ])
    };
    let cases: Vec<(&str, Vec<u8>, &str)> = vec![
        ("garbage.npy", b"not an npy file".to_vec(), "magic"),
        (
            "int.npy",
            [npy_header("<i4", 1), vec![0; 12]].concat(),
            "dtype",
        ),
        (
            "short.npy",
            [npy_header("<f4", 4), vec![0; 8]].concat(),
            "truncated",
        ),
        (
            "nan.npy",
            [
                npy_header("<f4", 1),
                [f32::NAN, 0.0, 0.0]
                    .iter()
                    .flat_map(|v| v.to_le_bytes())
                    .collect(),
            ]
            .concat(),
            "not finite",
        ),
    ];
    for (name, bytes, needle) in cases {
        let p = dir.join(name);
        std::fs::write(&p, bytes).unwrap();
        let o = run(&p, &mesh_path);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{name} should fail");
        assert!(err.contains(needle) && err.contains(name), "{name}: {err}");
        assert!(!out.exists(), "{name}: no output on error");
    }
    let good = dir.join("good.npy");
    npy::write_points(&good, &[Vec3::ZERO]).unwrap();
    let o = run(&good, &dir.join("missing.obj"));
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("missing.obj"));
    let o = run(&dir.join("nope.npy"), &mesh_path);
    assert!(String::from_utf8_lossy(&o.stderr).contains("nope.npy"));
    assert!(!out.exists());
}

/// `--ground-truth gpu` gives the CPU's distances within 1e-6 of the box diagonal (closed, open
/// and multi-part meshes, OBJ and GLB, points in mesh coordinates), `auto` one of the two, and
/// an unknown value is clap's error.
#[test]
fn gpu_and_cpu_ground_truth_agree() {
    let dir = temp_dir("gt");
    for name in ["spot.obj", "suzanne.obj", "pins.glb"] {
        let mesh_path = data(name);
        let (mesh, _) = load_mesh(&mesh_path).unwrap();
        let (unit, norm) = mesh.normalized();
        let mut unit_pts = sample::uniform_box(1000, 2);
        unit_pts.extend(sample::near_surface(&unit, 1000, 0.01, 3));
        let pts: Vec<Vec3> = unit_pts.iter().map(|&p| norm.to_original(p)).collect();
        let inp = dir.join(format!("{name}.npy"));
        npy::write_points(&inp, &pts).unwrap();
        let run = |device: &str| {
            let out = dir.join(format!("{name}.{device}.npy"));
            let o = sdf(&[
                mesh_path.as_os_str(),
                "--points".as_ref(),
                inp.as_os_str(),
                "--out".as_ref(),
                out.as_os_str(),
                "--ground-truth".as_ref(),
                device.as_ref(),
            ]);
            assert!(
                o.status.success(),
                "{name} {device}: {}",
                String::from_utf8_lossy(&o.stderr)
            );
            npy::read_f32(&out).unwrap()
        };
        let (gpu, cpu, auto) = (run("gpu"), run("cpu"), run("auto"));
        assert_eq!(
            cpu,
            SignedDistance::new(&mesh)
                .unwrap()
                .signed_distance_batch(&pts)
        );
        let tol = 1e-6 * mesh.bounds().diagonal();
        let worst = gpu
            .iter()
            .zip(&cpu)
            .map(|(g, c)| (g - c).abs())
            .fold(0.0f32, f32::max);
        eprintln!("{name}: max |gpu - cpu| = {worst:e} (tolerance {tol:e})");
        assert!(worst <= tol, "{name}: {worst} > {tol}");
        assert!(auto == cpu || auto == gpu, "{name}: auto is neither path");
    }
    let o = sdf(&[
        data("spot.obj").as_os_str(),
        "--points".as_ref(),
        "x.npy".as_ref(),
        "--out".as_ref(),
        "y.npy".as_ref(),
        "--ground-truth".as_ref(),
        "fast".as_ref(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("possible values: gpu, cpu, auto"),
        "{err}"
    );
}

/// A mesh far from the origin (spot moved by 10⁷) with float64 points in its own coordinates
/// (moved the same way): the distances of the mesh where it was.
#[test]
fn a_mesh_far_from_the_origin_gives_the_distances_of_the_mesh_near_it() {
    let dir = temp_dir("far");
    let (spot, _) = load_mesh(data("spot.obj")).unwrap();
    let (_, norm) = spot.normalized();
    let offset = glam::DVec3::new(1e7, -2e7, 3e7);
    let mut obj = String::new();
    for v in &spot.vertices {
        let p = v.as_dvec3() + offset;
        obj.push_str(&format!("v {} {} {}\n", p.x, p.y, p.z));
    }
    for t in &spot.triangles {
        obj.push_str(&format!("f {} {} {}\n", t[0] + 1, t[1] + 1, t[2] + 1));
    }
    let far = dir.join("far_spot.obj");
    std::fs::write(&far, obj).unwrap();
    let pts: Vec<Vec3> = sample::uniform_box(1000, 4)
        .iter()
        .map(|&p| norm.to_original(p))
        .collect();
    let write64 = |name: &str, shift: glam::DVec3| {
        let mut bytes = npy_header("<f8", pts.len());
        for p in &pts {
            let q = p.as_dvec3() + shift;
            bytes.extend(q.to_array().iter().flat_map(|v| v.to_le_bytes()));
        }
        let path = dir.join(name);
        std::fs::write(&path, bytes).unwrap();
        path
    };
    let (near_pts, far_pts) = (
        write64("near.npy", glam::DVec3::ZERO),
        write64("far.npy", offset),
    );
    let run = |mesh: &Path, points: &Path, out: &str| {
        let out = dir.join(out);
        let o = sdf(&[
            mesh.as_os_str(),
            "--points".as_ref(),
            points.as_os_str(),
            "--out".as_ref(),
            out.as_os_str(),
            "--ground-truth".as_ref(),
            "cpu".as_ref(),
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        npy::read_f32(&out).unwrap()
    };
    let want = run(&data("spot.obj"), &near_pts, "near.npy.out");
    let got = run(&far, &far_pts, "far.npy.out");
    let tol = 1e-6 * spot.bounds().diagonal();
    for (g, w) in got.iter().zip(&want) {
        assert!((g - w).abs() <= tol, "{g} {w}");
    }
    assert!(want.iter().any(|&d| d < 0.0));
}

/// A mesh that labels slowly (50 000 random triangles spanning the box: about 1 ms per point on
/// 2 cores) says how long labelling will take before it starts, and how far it has got while it
/// runs. The thresholds are forced to 0 (hidden flags) so that the lines do not depend on the
/// machine's speed; their format is checked, not their times.
#[test]
fn slow_labelling_says_how_long_and_how_far() {
    let dir = temp_dir("slow");
    let mut rng = 0x2545_F491_4F6C_DD1Du64;
    let mut uniform = || {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        (rng >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0
    };
    let n = 50_000;
    let mut obj = String::with_capacity(n * 100);
    for _ in 0..3 * n {
        obj.push_str(&format!("v {} {} {}\n", uniform(), uniform(), uniform()));
    }
    for i in 0..n {
        obj.push_str(&format!("f {} {} {}\n", 3 * i + 1, 3 * i + 2, 3 * i + 3));
    }
    let mesh = dir.join("soup.obj");
    std::fs::write(&mesh, obj).unwrap();
    let points = dir.join("points.npy");
    npy::write_points(&points, &sample::uniform_box(5000, 6)).unwrap();
    let out = dir.join("d.npy");
    let o = sdf(&[
        mesh.as_os_str(),
        "--points".as_ref(),
        points.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
        "--ground-truth".as_ref(),
        "cpu".as_ref(),
        "--label-estimate-after".as_ref(),
        "0".as_ref(),
        "--label-progress-every".as_ref(),
        "0".as_ref(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    let estimate = err
        .lines()
        .find(|l| l.starts_with("labelling: about 5000 exact distances on the CPU, estimated "))
        .unwrap_or_else(|| panic!("no estimate line: {err}"));
    assert!(estimate.contains(" µs each, measured on "), "{estimate}");
    // 5000 points in parts of 1024: five progress lines, the last one complete.
    let progress: Vec<&str> = err
        .lines()
        .filter(|l| l.starts_with("labelling: ") && l.contains(" so far, ETA "))
        .collect();
    assert_eq!(progress.len(), 5, "{err}");
    assert!(
        progress[0].starts_with("labelling: 1024/5000 (20%), "),
        "{err}"
    );
    assert!(
        progress[4].starts_with("labelling: 5000/5000 (100%), "),
        "{err}"
    );
    assert!(progress[4].ends_with("ETA 0 s"), "{err}");
    // The estimate came before the first progress line.
    assert!(err.find(estimate) < err.find(progress[0]));
    assert_eq!(npy::read_f32(&out).unwrap().len(), 5000);
}
