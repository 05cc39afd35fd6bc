//! One glTF mesh instance into the merged mesh: each primitive's mode and indices checked, its
//! positions read, morphed to the default pose and placed, its strips and fans made triangles.

use std::path::Path;
use std::rc::Rc;

use glam::{DMat4, DVec3, Vec3};

use super::accessors::{Vec3Format, read_accessor, vec3_format};
use super::{in_message, node_error};
use crate::GeomError;
use crate::mesh::LoadReport;

/// Adds `weights[i]` times morph target i's POSITION displacements to `positions` (the
/// primitive's own, in mesh space): the default pose. Targets without POSITION, and weights of 0,
/// change nothing; returns whether any position moved. Weights beyond the targets (or targets
/// beyond the weights) are a warning in `report`, if given, as the glTF specification wants the
/// counts equal.
fn morph(
    prim: &gltf::Primitive,
    mesh: usize,
    weights: &[f32],
    buffers: &[Rc<[u8]>],
    positions: &mut [Vec3],
    report: Option<&mut LoadReport>,
) -> Result<bool, String> {
    if weights.iter().all(|&w| w == 0.0) || prim.morph_targets().len() == 0 {
        return Ok(false);
    }
    let targets: Vec<_> = prim.morph_targets().collect();
    if let Some(report) = report
        && targets.len() != weights.len()
    {
        report.warnings.push(format!(
            "mesh {mesh} primitive {}: {} morph targets but {} weights (the extra ones ignored)",
            prim.index(),
            targets.len(),
            weights.len()
        ));
    }
    let mut moved = false;
    for (t, (target, &w)) in targets.iter().zip(weights).enumerate() {
        if !w.is_finite() {
            return Err(format!("morph target {t} has weight {w}"));
        }
        let Some(acc) = target.positions() else {
            continue;
        };
        if w == 0.0 {
            continue;
        }
        let format = Vec3Format::described(&acc, &format!("morph target {t}: POSITION"))?;
        if acc.count() != positions.len() {
            return Err(format!(
                "morph target {t}: {} POSITION displacements for {} vertices",
                acc.count(),
                positions.len()
            ));
        }
        let what = format!("morph target {t} POSITION");
        for (p, d) in positions.iter_mut().zip(format.read(&acc, buffers, &what)?) {
            *p += w * d;
        }
        moved = true;
    }
    Ok(moved)
}

/// The merged mesh being built from a glTF scene: every instance's vertices and triangles, and
/// the report of what was read.
#[derive(Default)]
pub(super) struct Merged {
    /// In f64: a node's transform may place the mesh far from the origin, where f32 would round
    /// its shape; the loader recentres them before they become f32.
    pub(super) vertices: Vec<DVec3>,
    pub(super) triangles: Vec<[u32; 3]>,
    pub(super) report: LoadReport,
    /// The first point or line primitive skipped: the error where nothing else has triangles.
    pub(super) skipped_mode: Option<GeomError>,
}

/// Adds one instance of `mesh` (all its primitives, placed by `world`, posed by `morph_weights`)
/// to `out`. `node` is the instancing node, named in transform errors; `warn` gives the mesh's
/// warnings (its first instance only).
#[allow(clippy::too_many_arguments)]
pub(super) fn add_gltf_mesh(
    path: &Path,
    node: Option<&gltf::Node>,
    mesh: &gltf::Mesh,
    world: DMat4,
    morph_weights: &[f32],
    warn: bool,
    buffers: &[Rc<[u8]>],
    out: &mut Merged,
) -> Result<(), GeomError> {
    let flip = world.determinant() < 0.0;
    let parse_err = |prim: usize, message: String| GeomError::Parse {
        path: path.to_path_buf(),
        line: None,
        message: format!("mesh {} primitive {prim}: {message}", mesh.index()),
    };
    for prim in mesh.primitives() {
        // Points and lines beside the faces (a CAD export's edges) enclose nothing: skipped.
        if let Err(err) = check_mode(path, mesh, &prim) {
            if warn {
                out.report.warnings.push(format!(
                    "mesh {} primitive {} is {}, which encloses nothing (skipped)",
                    mesh.index(),
                    prim.index(),
                    mode_name(prim.mode()).unwrap_or("points or lines")
                ));
            }
            out.skipped_mode.get_or_insert(err);
            continue;
        }
        let Some(pos_acc) = prim.get(&gltf::Semantic::Positions) else {
            if !warn {
                continue;
            }
            out.report.warnings.push(format!(
                "mesh {} primitive {} has no POSITION attribute (skipped)",
                mesh.index(),
                prim.index()
            ));
            continue;
        };
        let pos_format = vec3_format(path, &pos_acc, "POSITION")?;
        if pos_acc.count() == 0 {
            continue;
        }
        // Indices are validated before any position is read: type, then bounds.
        let index_size = match prim.indices() {
            Some(acc) => Some(index_size(&acc).map_err(|m| parse_err(prim.index(), m))?),
            None => None,
        };
        let mut local_positions = pos_format
            .read(&pos_acc, buffers, "POSITION")
            .map_err(|m| parse_err(prim.index(), m))?;
        let n = local_positions.len();
        let indices: Vec<u32> = match (prim.indices(), index_size) {
            (Some(acc), Some(size)) => read_accessor(&acc, size, buffers, "indices")
                .map_err(|m| parse_err(prim.index(), m))?
                .iter()
                .map(|b| {
                    let mut a = [0u8; 4];
                    a[..b.len()].copy_from_slice(b);
                    u32::from_le_bytes(a)
                })
                .collect(),
            _ => (0..n as u32).collect(),
        };
        if morph(
            &prim,
            mesh.index(),
            morph_weights,
            buffers,
            &mut local_positions,
            warn.then_some(&mut out.report),
        )
        .map_err(|m| parse_err(prim.index(), m))?
        {
            out.report.morphed_primitives += 1;
        }
        let base = out.vertices.len();
        let vertices = &mut out.vertices;
        vertices.extend(
            local_positions
                .iter()
                .map(|&p| world.transform_point3(p.as_dvec3())),
        );
        // A finite transform can still overflow a finite vertex: blame the transform, not the
        // vertex data (a non-finite position in the data is left for `clean` to report).
        if let Some(node) = node
            && let Some(i) = (0..n).find(|&i| {
                local_positions[i].is_finite() && !vertices[base + i].as_vec3().is_finite()
            })
        {
            return Err(node_error(
                path,
                node,
                format!(
                    "its transform takes mesh {} primitive {} vertex {i} from {} to {}, which is not finite in float32",
                    mesh.index(),
                    prim.index(),
                    local_positions[i],
                    vertices[base + i].as_vec3()
                ),
            ));
        }
        let local = primitive_triangles(mesh, &prim, indices, warn, &mut out.report);
        check_indices(path, mesh, &prim, &local, n)?;
        let base = u32::try_from(base + n)
            .map(|_| base as u32)
            .map_err(|_| parse_err(prim.index(), "more than 2^32 vertices".into()))?;
        out.triangles.extend(local.into_iter().map(|t| {
            let t = t.map(|i| i + base);
            if flip { [t[0], t[2], t[1]] } else { t }
        }));
    }
    Ok(())
}

/// The glTF name of a point or line mode; `None` for the triangle modes.
fn mode_name(mode: gltf::mesh::Mode) -> Option<&'static str> {
    use gltf::mesh::Mode;
    match mode {
        Mode::Points => Some("POINTS"),
        Mode::Lines => Some("LINES"),
        Mode::LineLoop => Some("LINE_LOOP"),
        Mode::LineStrip => Some("LINE_STRIP"),
        _ => None,
    }
}

/// [`GeomError::UnsupportedPrimitiveMode`] for points and lines, which enclose nothing.
fn check_mode(path: &Path, mesh: &gltf::Mesh, prim: &gltf::Primitive) -> Result<(), GeomError> {
    match mode_name(prim.mode()) {
        Some(mode) => Err(GeomError::UnsupportedPrimitiveMode {
            path: path.to_path_buf(),
            mesh: mesh.index(),
            primitive: prim.index(),
            mode,
        }),
        None => Ok(()),
    }
}

/// Bytes per index of an index accessor: SCALAR of unsigned byte, short or int, else what is
/// wrong with it.
fn index_size(acc: &gltf::Accessor) -> Result<usize, String> {
    use gltf::accessor::{DataType, Dimensions};
    if acc.dimensions() != Dimensions::Scalar {
        return Err(format!(
            "index accessor {} has type {:?}; indices must be SCALAR",
            acc.index(),
            acc.dimensions()
        ));
    }
    match acc.data_type() {
        DataType::U8 => Ok(1),
        DataType::U16 => Ok(2),
        DataType::U32 => Ok(4),
        t => Err(format!(
            "index accessor {} has component type {t:?}; indices must be unsigned byte, short or int",
            acc.index()
        )),
    }
}

/// A primitive's triangles from its indices: strips and fans converted (and counted in
/// `report`), lists taken three at a time (with a warning, if `warn`, for a remainder).
fn primitive_triangles(
    mesh: &gltf::Mesh,
    prim: &gltf::Primitive,
    indices: Vec<u32>,
    warn: bool,
    report: &mut LoadReport,
) -> Vec<[u32; 3]> {
    use gltf::mesh::Mode;
    match prim.mode() {
        Mode::TriangleStrip => {
            report.strips_fans_converted += 1;
            (0..indices.len().saturating_sub(2))
                .map(|i| {
                    if i % 2 == 0 {
                        [indices[i], indices[i + 1], indices[i + 2]]
                    } else {
                        [indices[i + 1], indices[i], indices[i + 2]]
                    }
                })
                .collect()
        }
        Mode::TriangleFan => {
            report.strips_fans_converted += 1;
            (0..indices.len().saturating_sub(2))
                .map(|i| [indices[i + 1], indices[i + 2], indices[0]])
                .collect()
        }
        _ => {
            if warn && !indices.len().is_multiple_of(3) {
                report.warnings.push(format!(
                    "mesh {} primitive {}: {} indices, not a multiple of 3; the last {} ignored",
                    mesh.index(),
                    prim.index(),
                    indices.len(),
                    indices.len() % 3
                ));
            }
            indices
                .chunks_exact(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect()
        }
    }
}

/// [`GeomError::GltfIndexOutOfRange`] for the first index of `local` that is not below `n`, the
/// primitive's vertex count.
fn check_indices(
    path: &Path,
    mesh: &gltf::Mesh,
    prim: &gltf::Primitive,
    local: &[[u32; 3]],
    n: usize,
) -> Result<(), GeomError> {
    for (k, t) in local.iter().enumerate() {
        for &i in t {
            if i as usize >= n {
                return Err(GeomError::GltfIndexOutOfRange {
                    path: path.to_path_buf(),
                    mesh: mesh.index(),
                    mesh_name: mesh.name().map(in_message),
                    primitive: prim.index(),
                    triangle: k,
                    index: i,
                    vertex_count: n,
                });
            }
        }
    }
    Ok(())
}
