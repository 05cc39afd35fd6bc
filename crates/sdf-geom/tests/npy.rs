//! The .npy reader and writer.

mod common;

use common::{temp_dir, write};
use glam::Vec3;
use sdf_geom::{GeomError, npy};

fn header(descr: &str, fortran: bool, shape: &str) -> Vec<u8> {
    let mut h = format!(
        "{{'descr': '{descr}', 'fortran_order': {}, 'shape': {shape}, }}",
        if fortran { "True" } else { "False" }
    );
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
fn round_trip_f32_points_and_distances() {
    let dir = temp_dir("npy");
    let pts = vec![Vec3::new(1.0, -2.5, 3.25), Vec3::new(0.0, 1e-7, -1e7)];
    let p = dir.join("pts.npy");
    npy::write_points(&p, &pts).unwrap();
    let bytes = std::fs::read(&p).unwrap();
    assert_eq!(&bytes[..8], b"\x93NUMPY\x01\x00");
    let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    assert_eq!((10 + hlen) % 64, 0);
    assert_eq!(npy::read_points(&p).unwrap(), pts);

    let d = vec![0.5f32, -1.25, f32::MAX];
    let q = dir.join("d.npy");
    npy::write_f32(&q, &d).unwrap();
    assert_eq!(npy::read_f32(&q).unwrap(), d);
    // No temporary file is left behind.
    let left: Vec<_> = std::fs::read_dir(&dir).unwrap().collect();
    assert_eq!(left.len(), 2);
    // Empty arrays.
    npy::write_points(&p, &[]).unwrap();
    assert!(npy::read_points(&p).unwrap().is_empty());
}

#[test]
fn reads_f64_fortran_big_endian_and_v2() {
    let dir = temp_dir("npy64");
    let vals = [1.0f64, 2.0, 3.0, 4.0, 5.0, 6.0];
    let mut b = header("<f8", false, "(2, 3)");
    b.extend(vals.iter().flat_map(|v| v.to_le_bytes()));
    let p = write(&dir, "f8.npy", &b);
    assert_eq!(
        npy::read_points(&p).unwrap(),
        vec![Vec3::new(1.0, 2.0, 3.0), Vec3::new(4.0, 5.0, 6.0)]
    );

    // Fortran order: column-major, x of all points first.
    let mut b = header("<f4", true, "(2, 3)");
    b.extend(vals.iter().flat_map(|v| (*v as f32).to_le_bytes()));
    let p = write(&dir, "fortran.npy", &b);
    assert_eq!(
        npy::read_points(&p).unwrap(),
        vec![Vec3::new(1.0, 3.0, 5.0), Vec3::new(2.0, 4.0, 6.0)]
    );

    let mut b = header(">f4", false, "(1, 3)");
    b.extend([1.0f32, 2.0, 3.0].iter().flat_map(|v| v.to_be_bytes()));
    let p = write(&dir, "be.npy", &b);
    assert_eq!(
        npy::read_points(&p).unwrap(),
        vec![Vec3::new(1.0, 2.0, 3.0)]
    );

    // Version 2 header (4-byte length).
    let h = "{'descr': '<f4', 'fortran_order': False, 'shape': (1, 3), }\n";
    let mut b = b"\x93NUMPY\x02\x00".to_vec();
    b.extend((h.len() as u32).to_le_bytes());
    b.extend(h.as_bytes());
    b.extend([7.0f32, 8.0, 9.0].iter().flat_map(|v| v.to_le_bytes()));
    let p = write(&dir, "v2.npy", &b);
    assert_eq!(
        npy::read_points(&p).unwrap(),
        vec![Vec3::new(7.0, 8.0, 9.0)]
    );
}

fn expect_npy_error(bytes: &[u8], needle: &str) {
    let dir = temp_dir("npybad");
    let p = write(&dir, "bad.npy", bytes);
    match npy::read_points(&p) {
        Err(e @ GeomError::Npy { .. }) => {
            assert!(
                e.to_string().contains(needle),
                "{e} should mention {needle:?}"
            )
        }
        other => panic!("expected an Npy error mentioning {needle:?}, got {other:?}"),
    }
}

#[test]
fn bad_npy_files_get_clear_errors() {
    expect_npy_error(b"hello world, not numpy", "magic");
    expect_npy_error(b"", "magic");
    let mut b = header("<i4", false, "(1, 3)");
    b.extend([0u8; 12]);
    expect_npy_error(&b, "dtype");
    let mut b = header("<f4", false, "(2, 2)");
    b.extend([0u8; 16]);
    expect_npy_error(&b, "shape");
    let mut b = header("<f4", false, "(6,)");
    b.extend([0u8; 24]);
    expect_npy_error(&b, "shape");
    let mut b = header("<f4", false, "(4, 3)");
    b.extend([0u8; 20]);
    expect_npy_error(&b, "truncated");
    let mut b = header("<f4", false, "(1, 3)");
    b.truncate(20);
    expect_npy_error(&b, "truncated");
    let mut b = b"\x93NUMPY\x09\x00".to_vec();
    b.extend([0u8; 10]);
    expect_npy_error(&b, "version");
    // A structured dtype, as numpy writes it (a list, not a string).
    let h = "{'descr': [('x', '<f4')], 'fortran_order': False, 'shape': (1, 3), }\n";
    let mut b = b"\x93NUMPY\x01\x00".to_vec();
    b.extend((h.len() as u16).to_le_bytes());
    b.extend(h.as_bytes());
    b.extend([0u8; 12]);
    expect_npy_error(&b, "dtype");
    // A structured dtype whose field name holds `'descr': '<f4'` (numpy writes its repr as
    // below): the dict's own 'descr' is the list, not the field name's text.
    let h =
        "{'descr': [(\"x', 'descr': '<f4'\", '<f8')], 'fortran_order': False, 'shape': (2, 3), }\n";
    let mut b = b"\x93NUMPY\x01\x00".to_vec();
    b.extend((h.len() as u16).to_le_bytes());
    b.extend(h.as_bytes());
    b.extend([0u8; 48]);
    expect_npy_error(&b, "structured");
    // What Python's literal_eval (numpy's reader) joins or skips: each header below is a
    // float64 array for numpy; refused rather than read another way.
    for (h, says) in [
        (
            "{'descr': '<f8', # 'descr': '<f4',\n 'fortran_order': False, 'shape': (2, 3), }\n",
            "'#' outside",
        ),
        (
            "{'descr': '<f4', 'des' 'cr': '<f8', 'fortran_order': False, 'shape': (2, 3), }\n",
            "side by side",
        ),
        (
            "{'descr': '<f4', '''descr''': '<f8', 'fortran_order': False, 'shape': (2, 3), }\n",
            "side by side",
        ),
        (
            "{'descr': '<f4', 'des' u'cr': '<f8', 'fortran_order': False, 'shape': (2, 3), }\n",
            "prefixed",
        ),
        (
            "{'descr': '<f4', 'desc\\x72': '<f8', 'fortran_order': False, 'shape': (2, 3), }\n",
            "escape",
        ),
        (
            "{'descr': '<f4', ('descr'): '<f8', 'fortran_order': False, 'shape': (2, 3), }\n",
            "not a plain string",
        ),
    ] {
        let mut b = b"\x93NUMPY\x01\x00".to_vec();
        b.extend((h.len() as u16).to_le_bytes());
        b.extend(h.as_bytes());
        b.extend([0u8; 48]);
        expect_npy_error(&b, says);
    }

    let missing = temp_dir("npymissing").join("none.npy");
    assert!(matches!(
        npy::read_points(&missing),
        Err(GeomError::Io { .. })
    ));
    // Writing into a directory that does not exist fails cleanly.
    let err = npy::write_f32(temp_dir("w").join("no/such/dir.npy"), &[1.0]).unwrap_err();
    assert!(matches!(err, GeomError::Write { .. }));
}

/// A key given twice: the last one counts, as in Python's dict literals (what `numpy.load` reads).
#[test]
fn repeated_header_keys_take_the_last_value() {
    let h = "{'descr': '<f8', 'fortran_order': False, 'shape': (2, 3), 'descr': '<f4', \"shape\": (1, 3), }\n";
    let mut b = b"\x93NUMPY\x01\x00".to_vec();
    b.extend((h.len() as u16).to_le_bytes());
    b.extend(h.as_bytes());
    for x in [1.0f32, 2.0, 3.0] {
        b.extend(x.to_le_bytes());
    }
    let p = write(&temp_dir("npydup"), "dup.npy", &b);
    assert_eq!(
        npy::read_points(&p).unwrap(),
        vec![Vec3::new(1.0, 2.0, 3.0)]
    );
}

/// Tables of any width round-trip, and a table of another width is refused with the shape.
#[test]
fn tables_round_trip_and_check_their_width() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("rays.npy");
    let values: Vec<f32> = (0..12).map(|i| i as f32 * 0.5 - 1.0).collect();
    sdf_geom::npy::write_table(&path, &values, 6).unwrap();
    assert_eq!(sdf_geom::npy::read_table(&path, 6).unwrap(), values);
    let err = sdf_geom::npy::read_table(&path, 3).unwrap_err().to_string();
    assert!(err.contains("[2, 6]") && err.contains("(N, 3)"), "{err}");
    // Points are tables of width 3.
    let points = dir.path().join("points.npy");
    sdf_geom::npy::write_table(&points, &values, 3).unwrap();
    let p = sdf_geom::npy::read_points(&points).unwrap();
    assert_eq!(p[3], glam::Vec3::new(3.5, 4.0, 4.5));
    // Values that do not make whole rows are refused, and nothing is written: the header
    // would have declared fewer than follow it.
    let ragged = dir.path().join("ragged.npy");
    for (values, columns) in [(&values[..5], 2), (&values[..], 0)] {
        let err = sdf_geom::npy::write_table(&ragged, values, columns).unwrap_err();
        assert!(err.to_string().contains("whole rows"), "{err}");
        let wide: Vec<f64> = values.iter().map(|&v| v.into()).collect();
        assert!(sdf_geom::npy::write_table_f64(&ragged, &wide, columns).is_err());
    }
    assert!(!ragged.exists());
}
