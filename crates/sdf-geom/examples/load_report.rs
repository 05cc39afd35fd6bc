//! Prints the load report of each mesh given on the command line.
//!
//! `cargo run --release -p sdf-geom --example load_report -- MESH...`

fn main() {
    for path in std::env::args().skip(1) {
        match sdf_geom::load_mesh(&path) {
            Ok((mesh, report)) => {
                let b = mesh.bounds();
                println!("{path}: {report:?} bounds {:?}..{:?}", b.min, b.max);
            }
            Err(e) => println!("{path}: error: {e}"),
        }
    }
}
