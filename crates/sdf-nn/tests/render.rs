//! Sphere tracing (`sdf_nn::render`): an exact sphere model renders to the analytic silhouette,
//! its centre pixel has the analytic Lambert shade, PNGs round-trip, bad options are errors.
//! One test binary, one shared device.

use glam::{Vec3, Vec4};
use sdf_nn::{
    GpuContext, NeuralSdf, Nglod, Normalization, RenderError, RenderOptions, Renderer,
    serve::render::Camera,
};

fn gpu() -> &'static GpuContext {
    let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
    eprintln!("adapter: {}", gpu.describe());
    gpu
}

/// Sphere radius in the normalised cube.
const RADIUS: f32 = 0.6;
/// Cells per axis of the sphere model's grid: trilinear interpolation of `|x| − ρ` is then
/// within ~(h²/8)/ρ ≈ 8e-4 of the exact distance near the surface (h = 2/32), far below a pixel.
const RES: u32 = 32;

/// An NGLOD model that is exactly (up to trilinear interpolation) the SDF of a sphere of
/// radius `RADIUS` (normalised units) about the box centre, with no training.
fn sphere_model(normalization: Normalization) -> NeuralSdf {
    let model = Nglod::from_sdf(RES, |p| p.length() - RADIUS).unwrap();
    NeuralSdf::from_model_file(model.to_model_file(normalization, serde_json::Value::Null)).unwrap()
}

/// Mesh coordinates that are not the normalised ones: the sphere's centre is at `center` and
/// its radius is `RADIUS / scale` in mesh units.
fn normalization() -> Normalization {
    Normalization {
        center: Vec3::new(1.0, -2.0, 0.5).as_dvec3(),
        scale: 0.25,
    }
}

#[test]
fn sphere_model_is_a_sphere_on_the_cpu() {
    let n = normalization();
    let sdf = sphere_model(n);
    let r = RADIUS / n.scale;
    for (i, dir) in [Vec3::X, Vec3::new(1.0, 2.0, -0.5).normalize(), -Vec3::Y]
        .into_iter()
        .enumerate()
    {
        for k in [0.5, 0.95, 1.0, 1.05, 2.0, 3.0] {
            let p = n.center.as_vec3() + dir * r * k;
            let d = sdf.eval_cpu(&[p])[0];
            // Outside the box (|q| > 1 on some axis) the box rule still gives the exact value
            // along an axis; along a diagonal it is an upper bound.
            let exact = r * (k - 1.0);
            assert!(
                (d - exact).abs() < 4e-3 / n.scale || (k > 1.6 && i == 1 && d >= exact - 1e-3),
                "dir {dir}, k {k}: {d} vs {exact}"
            );
        }
    }
}

#[test]
fn sphere_silhouette_and_shading_match_analytic() {
    let gpu = gpu();
    let n = normalization();
    let sdf = sphere_model(n);
    let t = std::time::Instant::now();
    let renderer = Renderer::new(gpu, &sdf).unwrap();
    let compile = t.elapsed();
    let mut banded = Renderer::new(gpu, &sdf).unwrap();
    banded.set_max_submission_macs(1);
    for (width, height, yaw, pitch) in [(160u32, 120u32, 35.0f32, 20.0f32), (96, 128, -70.0, -45.0)]
    {
        let options = RenderOptions {
            width,
            height,
            yaw_degrees: yaw,
            pitch_degrees: pitch,
            background: Vec4::ZERO,
            ..RenderOptions::default()
        };
        let t = std::time::Instant::now();
        let image = renderer.render(gpu, &options).unwrap();
        assert_eq!(renderer.band_rows(&options), height.next_multiple_of(8));
        // In bands of 8 rows, one submission each: the same pixels.
        assert_eq!(banded.band_rows(&options), 8);
        assert!(banded.render(gpu, &options).unwrap().pixels == image.pixels);
        eprintln!(
            "{width}x{height}: compile {compile:.2?}, render {:.2?}",
            t.elapsed()
        );
        assert_eq!(image.pixels.len(), (width * height * 4) as usize);
        let covered = image.pixels.chunks(4).filter(|p| p[3] > 0).count();

        // The silhouette of a sphere seen from distance D is a cone of half-angle asin(ρ/D)
        // around the view axis, a circle of radius f·tan(α) pixels with f = (H/2)/tan(fov/2).
        let cam = Camera::orbit(n, &options);
        let rho = RADIUS / n.scale;
        let dist = cam.eye.distance(n.center.as_vec3());
        let alpha = (rho / dist).asin();
        let f = height as f32 * 0.5 / cam.tan_half_fov_y;
        let radius_px = f * alpha.tan();
        let expected = std::f32::consts::PI * radius_px * radius_px;
        let rel = (covered as f32 - expected).abs() / expected;
        eprintln!(
            "covered {covered} px, analytic {expected:.1} px (radius {radius_px:.1} px): rel err {rel:.4}"
        );
        // Pixel sampling and the hit tolerance (a quarter pixel) move the rim by under a pixel:
        // a relative area change of at most 2/radius_px; allow half of that.
        assert!(
            rel < 1.0 / radius_px,
            "coverage {covered} vs {expected} ({rel})"
        );

        // Centre pixel: the normal faces the camera, so the shade is ambient + (1 − ambient)·l_z.
        let l = options.light.normalize();
        let shade = options.ambient + (1.0 - options.ambient) * l.z.max(0.0);
        let centre = image.pixel(width / 2, height / 2);
        for (c, &got) in centre[..3].iter().enumerate() {
            let want = (options.albedo[c] * shade).powf(1.0 / 2.2) * 255.0;
            // The pixel centre is off the axis by half a pixel at most when a side is even.
            assert!(
                (f32::from(got) - want).abs() <= 3.0,
                "centre channel {c}: {got} vs {want}"
            );
        }
        assert_eq!(centre[3], 255);
        // Corners miss and keep the (transparent) background.
        assert_eq!(image.pixel(0, 0), [0, 0, 0, 0]);
        assert_eq!(image.pixel(width - 1, height - 1), [0, 0, 0, 0]);
    }
}

#[test]
fn png_round_trips_and_writes_atomically() {
    let gpu = gpu();
    let sdf = sphere_model(Normalization::identity());
    let options = RenderOptions {
        width: 40,
        height: 24,
        ..RenderOptions::default()
    };
    let image = sdf_nn::render(gpu, &sdf, &options).unwrap();
    let dir = std::env::temp_dir().join(format!("hwsdf-render-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("sphere.png");
    image.save_png(&path).unwrap();
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap()));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    assert_eq!((info.width, info.height), (40, 24));
    assert_eq!(info.color_type, png::ColorType::Rgba);
    assert_eq!(&buf[..info.buffer_size()], &image.pixels[..]);
    // Only the file itself is left in the directory (no temporary).
    let entries: Vec<_> = std::fs::read_dir(&dir).unwrap().collect();
    assert_eq!(entries.len(), 1);
    let missing = dir.join("no/such/dir/x.png");
    assert!(matches!(
        image.save_png(&missing),
        Err(RenderError::Io { .. })
    ));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn bad_options_are_errors() {
    let sdf = sphere_model(Normalization::identity());
    let gpu = gpu();
    for (w, h) in [(0, 10), (10, 0), (20000, 10)] {
        let options = RenderOptions {
            width: w,
            height: h,
            ..RenderOptions::default()
        };
        assert!(matches!(
            sdf_nn::render(gpu, &sdf, &options),
            Err(RenderError::BadSize { .. })
        ));
    }
    let options = RenderOptions {
        fov_y_degrees: 0.0,
        ..RenderOptions::default()
    };
    let err = sdf_nn::render(gpu, &sdf, &options).unwrap_err();
    assert!(matches!(err, RenderError::BadOption(_)), "{err}");
    assert!(err.to_string().contains("fov_y_degrees"));
}

/// The tracer also compiles and runs with a SIREN snippet on the device (naga validation alone
/// does not exercise the driver's compiler).
#[test]
fn siren_model_renders() {
    let gpu = gpu();
    let siren = sdf_nn::Siren::new(
        sdf_nn::SirenConfig {
            width: 16,
            hidden_layers: 2,
            omega0: 30.0,
        },
        4,
    )
    .unwrap();
    let sdf =
        NeuralSdf::from_model_file(siren.to_model_file(normalization(), serde_json::Value::Null))
            .unwrap();
    let options = RenderOptions {
        width: 24,
        height: 24,
        ..RenderOptions::default()
    };
    let t = std::time::Instant::now();
    let image = sdf_nn::render(gpu, &sdf, &options).unwrap();
    eprintln!("siren 24x24 in {:.2?} (JIT included)", t.elapsed());
    assert_eq!(image.pixels.len(), 24 * 24 * 4);
    assert!(image.pixels.chunks(4).all(|p| p[3] == 255));
}

/// A SIREN renders the same image with its activations in private arrays (GPUs) and in a
/// scratch buffer (CPU adapters, from 32 units wide): both forms compile and run on the device,
/// the surface (a random network's, at the level of its median over the box) is in view, and
/// the pixels agree.
#[test]
fn siren_renders_alike_from_private_arrays_and_scratch() {
    use sdf_nn::{GpuOptions, SirenActivations};
    let siren = sdf_nn::Siren::new(
        sdf_nn::SirenConfig {
            width: 8,
            hidden_layers: 2,
            omega0: 30.0,
        },
        6,
    )
    .unwrap();
    let sdf =
        NeuralSdf::from_model_file(siren.to_model_file(normalization(), serde_json::Value::Null))
            .unwrap();
    let n = normalization();
    let box_points: Vec<Vec3> = (0..1001)
        .map(|i| {
            let t = i as f32 / 1001.0;
            let p = Vec3::new((t * 97.0).fract(), (t * 61.0).fract(), t) * 2.0 - 1.0;
            n.center.as_vec3() + p / n.scale
        })
        .collect();
    let mut values = sdf.eval_cpu(&box_points);
    values.sort_by(f32::total_cmp);
    let options = RenderOptions {
        width: 24,
        height: 24,
        level: values[500],
        ..RenderOptions::default()
    };
    let images: Vec<_> = [SirenActivations::Private, SirenActivations::Scratch]
        .into_iter()
        .map(|form| {
            let gpu = GpuContext::with_options(&GpuOptions {
                siren_activations: Some(form),
                ..GpuOptions::from_env().unwrap()
            })
            .unwrap();
            sdf_nn::render(&gpu, &sdf, &options).unwrap()
        })
        .collect();
    let background = (options.background * 255.0)
        .round()
        .to_array()
        .map(|c| c as u8);
    let hits = images[0]
        .pixels
        .chunks(4)
        .filter(|p| *p != &background[..])
        .count();
    assert!(hits > 50, "only {hits} of 576 pixels show the surface");
    let differing = images[0]
        .pixels
        .chunks(4)
        .zip(images[1].pixels.chunks(4))
        .filter(|(a, b)| a.iter().zip(*b).any(|(x, y)| x.abs_diff(*y) > 1))
        .count();
    assert!(
        differing <= 2,
        "{differing} pixels differ between the forms"
    );
}
