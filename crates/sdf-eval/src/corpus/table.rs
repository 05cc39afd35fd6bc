//! The table merged from a results folder: the design document's Markdown table with the
//! progress of the corpus, the failures, and the meshes whose sign errors lie far from the
//! surface.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;

use super::{CorpusError, CorpusMesh, CorpusSettings, Entry, Record, StateDir};
use crate::run::{ModelKind, Report};

/// The table built from a results folder, and what it knows about progress.
#[derive(Debug)]
pub struct Merge {
    /// Finished and failed entries by model name and relative path.
    pub entries: BTreeMap<(&'static str, String), Entry>,
    /// Mesh × model pairs expected.
    pub expected: usize,
    /// Pairs without a result yet.
    pub missing: usize,
    /// Result files that do not parse (ignored; redone by the next run).
    pub corrupt: Vec<String>,
    /// Result files that could not be read (an I/O error: left out, not redone).
    pub unreadable: Vec<String>,
    /// The settings the results were made with (`None` for a folder from before they were
    /// recorded), or why their record cannot be read.
    pub settings: Result<Option<CorpusSettings>, CorpusError>,
}

/// Reads every expected result of `meshes` × `models` from `state`.
pub fn merge(state: &StateDir, meshes: &[CorpusMesh], models: &[ModelKind]) -> Merge {
    let mut m = Merge {
        entries: BTreeMap::new(),
        expected: meshes.len() * models.len(),
        missing: 0,
        corrupt: Vec::new(),
        unreadable: Vec::new(),
        settings: state.read_settings(),
    };
    for mesh in meshes {
        for &model in models {
            match state.read(&mesh.rel, model) {
                Record::Missing => m.missing += 1,
                Record::Corrupt(why) => {
                    m.missing += 1;
                    m.corrupt.push(why);
                }
                Record::Unreadable(why) => {
                    m.missing += 1;
                    m.unreadable.push(why);
                }
                Record::Entry(e) => {
                    m.entries.insert((model.name(), mesh.rel.clone()), e);
                }
            }
        }
    }
    m
}

/// An F1 to three decimals, or "n/a" where it is undefined (a mesh without an inside).
pub fn f1_cell(x: Option<f64>) -> String {
    x.map_or_else(|| "n/a".to_owned(), |v| format!("{v:.3}"))
}

/// The reference row under a model's table: its label and the averages (F1 in the box, F1
/// near the surface) of the design document's 50 meshes.
fn reference(model: ModelKind) -> (&'static str, f64, f64) {
    match model {
        ModelKind::Siren => ("design document (50 meshes)", 0.90, 0.89),
        ModelKind::Nglod => ("design document (50 meshes)", 0.98, 0.94),
        // The design document has no hash-grid row: NGLOD's figures are the bar its successor
        // must clear, labelled as NGLOD's.
        ModelKind::Hashgrid => ("design document, NGLOD (50 meshes)", 0.98, 0.94),
    }
}

impl Merge {
    /// Finished pairs.
    pub fn done(&self) -> usize {
        self.entries
            .values()
            .filter(|e| matches!(e, Entry::Done(_)))
            .count()
    }

    /// Failed pairs with their errors: `(relative path, model, error)`.
    pub fn failed(&self) -> Vec<(&str, &str, &str)> {
        self.entries
            .iter()
            .filter_map(|((model, rel), e)| match e {
                Entry::Failed { error, .. } => Some((rel.as_str(), *model, error.as_str())),
                Entry::Done(_) => None,
            })
            .collect()
    }

    /// Whether every expected pair has a finished or failed result.
    pub fn complete(&self) -> bool {
        self.missing == 0
    }

    /// "N of M meshes done, F failed" (mesh × model pairs when several models run).
    pub fn status(&self) -> String {
        format!(
            "{} of {} done, {} failed{}",
            self.done(),
            self.expected,
            self.failed().len(),
            if self.missing > 0 {
                format!(", {} not yet run", self.missing)
            } else {
                String::new()
            }
        )
    }

    /// The design document's table: one section per model, a row per mesh, the averages and
    /// the reference row. Depends only on the results folder, so a sharded run and a single
    /// process over the same meshes write the same table.
    pub fn markdown(&self) -> String {
        let mut s = String::new();
        let reports: Vec<&Report> = self
            .entries
            .values()
            .filter_map(|e| match e {
                Entry::Done(r) => Some(r.as_ref()),
                Entry::Failed { .. } => None,
            })
            .collect();
        let all_presets: BTreeSet<&str> = reports.iter().map(|r| r.preset.as_str()).collect();
        let adapters: BTreeSet<&str> = reports.iter().map(|r| r.adapter.as_str()).collect();
        // Reports from before the path was recorded labelled on the CPU.
        let paths: BTreeSet<&str> = reports
            .iter()
            .map(|r| r.ground_truth.map_or("cpu", |p| p.name()))
            .collect();
        let list = |set: &BTreeSet<&str>| {
            if set.is_empty() {
                "none yet".to_owned()
            } else {
                set.iter().copied().collect::<Vec<_>>().join("; ")
            }
        };
        // One preset for the table, or each model's where they differ (SIREN's `small` beside
        // NGLOD's `default` on a CPU adapter).
        let presets = if all_presets.len() <= 1 {
            format!("Preset `{}`", list(&all_presets))
        } else {
            let of = |kind: ModelKind| {
                let set: BTreeSet<&str> = reports
                    .iter()
                    .filter(|r| r.model == kind.name())
                    .map(|r| r.preset.as_str())
                    .collect();
                (!set.is_empty()).then(|| format!("{} `{}`", kind.label(), list(&set)))
            };
            let each: Vec<String> = ModelKind::ALL.into_iter().filter_map(of).collect();
            format!("Presets {}", each.join(", "))
        };
        let _ = writeln!(
            s,
            "{presets}, adapter {}, ground truth on {}. {}.\n",
            list(&adapters),
            list(&paths),
            self.status()
        );
        for kind in ModelKind::ALL {
            let model = kind.name();
            let rows: Vec<_> = self
                .entries
                .iter()
                .filter(|((m, _), _)| *m == model)
                .collect();
            if rows.is_empty() {
                continue;
            }
            let heading = match kind {
                ModelKind::Hashgrid => "Hash grid",
                _ => kind.label(),
            };
            let _ = writeln!(s, "### {heading}\n");
            if let Ok(Some(settings)) = &self.settings
                && let Some(m) = settings.models.get(model)
            {
                let _ = writeln!(s, "Settings: {m}; eval points {}.\n", settings.eval_points);
            }
            let _ = writeln!(
                s,
                "| mesh | F1 in bounding box | F1 near surface | mean | ambiguous box / near | train s | ns/point | µs/3000 | params | file bytes |"
            );
            let _ = writeln!(
                s,
                "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"
            );
            let (mut fb, mut fnr, mut n, mut left_out) = (0.0, 0.0, 0usize, 0usize);
            let mut done: Vec<(&str, &Report)> = Vec::new();
            for ((_, mesh), e) in &rows {
                match e {
                    Entry::Done(r) => {
                        done.push((mesh.as_str(), r.as_ref()));
                        let _ = writeln!(
                            s,
                            "| {} | {} | {} | {} | {} | {:.0} | {:.0} | {:.0} | {} | {} |",
                            table_cell(mesh),
                            f1_cell(r.f1_bbox),
                            f1_cell(r.f1_near_surface),
                            f1_cell(r.f1_mean),
                            ambiguous_cell(r),
                            r.train_seconds,
                            r.per_point_ns,
                            r.batch3000_us,
                            r.params,
                            r.file_bytes
                        );
                        // A mesh without an inside has no F1: left out of the averages.
                        if let (Some(b), Some(near)) = (r.f1_bbox, r.f1_near_surface) {
                            fb += b;
                            fnr += near;
                            n += 1;
                        } else {
                            left_out += 1;
                        }
                    }
                    Entry::Failed { error, .. } => {
                        let _ = writeln!(
                            s,
                            "| {} | failed: {} | | | | | | | | |",
                            table_cell(mesh),
                            table_cell(error)
                        );
                    }
                }
            }
            if left_out > 0 {
                let _ = writeln!(
                    s,
                    "| n/a: {left_out} mesh(es) without an inside (F1 undefined), left out of the average | | | | | | | | | |"
                );
            }
            if n > 0 {
                let (label, rb, rn) = reference(kind);
                let _ = writeln!(
                    s,
                    "| **average ({n} meshes)** | **{:.3}** | **{:.3}** | **{:.3}** | | | | | | |",
                    fb / n as f64,
                    fnr / n as f64,
                    0.5 * (fb + fnr) / n as f64
                );
                let _ = writeln!(
                    s,
                    "| {label} | {rb:.2} | {rn:.2} | {:.3} | | | | | | |",
                    0.5 * (rb + rn)
                );
            }
            if let Some(line) = wrong_regions(&done) {
                let _ = writeln!(s, "\n{line}");
            }
            let _ = writeln!(s);
        }
        s
    }
}

/// The fractions of a result's box and near-surface points whose inside or outside is
/// ambiguous (winding number between 0.2 and 0.8: open meshes), which explain a low or null F1:
/// `"0.0% / 12.3%"`, or `n/a` in results from before they were recorded.
fn ambiguous_cell(r: &Report) -> String {
    match (r.ambiguous_bbox, r.ambiguous_near_surface) {
        (Some(b), Some(n)) => format!("{:.1}% / {:.1}%", b * 100.0, n * 100.0),
        _ => "n/a".to_owned(),
    }
}

/// Meshes listed by name in [`wrong_regions`]' line.
const WRONG_REGIONS_LISTED: usize = 5;

/// What kind of sign errors a model's `done` results have, as one line under its table: the
/// meshes with box points of the wrong sign more than 0.05 from the surface (whole regions of
/// the wrong sign, not a displaced surface), the worst first. `None` when no result has the
/// counts (results written before they existed).
fn wrong_regions(done: &[(&str, &Report)]) -> Option<String> {
    let counted: Vec<(&str, u64, u64)> = done
        .iter()
        .filter_map(|(mesh, r)| {
            r.sign_errors_bbox.map(|e| {
                (
                    *mesh,
                    e.false_inside.beyond_0_05(),
                    e.false_outside.beyond_0_05(),
                )
            })
        })
        .collect();
    if counted.is_empty() {
        return None;
    }
    let uncounted = done.len() - counted.len();
    let mut far: Vec<_> = counted.iter().filter(|c| c.1 + c.2 > 0).collect();
    far.sort_by_key(|c| std::cmp::Reverse(c.1 + c.2));
    let mut line = if far.is_empty() {
        format!(
            "Wrong-sign regions: none on {} mesh(es); every box point of the wrong sign lies within \
             0.05 of the surface (a surface a little off, not a region of the wrong sign).",
            counted.len()
        )
    } else {
        let listed: Vec<String> = far
            .iter()
            .take(WRONG_REGIONS_LISTED)
            .map(|(mesh, fi, fo)| format!("{mesh} {fi} / {fo}"))
            .collect();
        format!(
            "Wrong-sign regions (box points of the wrong sign more than 0.05 from the surface, \
             false inside / false outside): {} of {} mesh(es); {}{}.",
            far.len(),
            counted.len(),
            listed.join(", "),
            if far.len() > WRONG_REGIONS_LISTED {
                ", ..."
            } else {
                ""
            }
        )
    };
    if uncounted > 0 {
        line += &format!(" ({uncounted} result(s) predate these counts.)");
    }
    Some(line)
}

/// `text` as one Markdown table cell: its `|` escaped (a mesh named `p|q.obj` split its row),
/// line breaks as spaces.
fn table_cell(text: &str) -> String {
    text.replace('|', "\\|").replace(['\n', '\r'], " ")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A finished NGLOD result on `mesh` whose box sign errors are `(false inside, false
    /// outside)` counts by band (`None`: a result from before the counts).
    fn report(mesh: &str, errors: Option<([u64; 4], [u64; 4])>) -> Report {
        let bands = |b: [u64; 4]| {
            serde_json::json!({
                "within_0_01": b[0], "within_0_05": b[1], "within_0_2": b[2], "beyond_0_2": b[3]
            })
        };
        let mut r = serde_json::json!({
            "mesh": mesh, "model": "nglod", "preset": "small", "params": 1, "file_bytes": 1,
            "f1_bbox": 0.99, "f1_near_surface": 0.95, "f1_mean": 0.97,
            "sign_accuracy_bbox": 0.99, "sign_accuracy_near_surface": 0.95,
            "near_surface_mean_abs_error": 0.001, "near_surface_max_abs_error": 0.01,
            "per_point_ns": 1.0, "batch3000_us": 1.0, "gpu_per_point_ns": null,
            "train_seconds": 1.0, "trained": 1, "final_loss": 0.0, "eval_points": 1000,
            "adapter": "test", "hwsdf_version": "0", "training": null
        });
        if let Some((fi, fo)) = errors {
            r["sign_errors_bbox"] =
                serde_json::json!({ "false_inside": bands(fi), "false_outside": bands(fo) });
        }
        serde_json::from_value(r).unwrap()
    }

    /// A run that read no loss (SIREN shorter than one loss window) is recorded and read back,
    /// not taken for an unreadable result and trained again by every rerun.
    #[test]
    fn a_result_without_a_loss_reads_back() {
        let root = std::env::temp_dir().join(format!("hwsdf-noloss-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let state = StateDir::for_table(&root.join("results.md"), &[]);
        state.create().unwrap();
        let mut r = report("a.obj", None);
        r.final_loss = None;
        state
            .write("a.obj", ModelKind::Siren, &Entry::Done(Box::new(r)))
            .unwrap();
        let all = vec![CorpusMesh::new(&root, "a.obj")];
        let m = merge(&state, &all, &[ModelKind::Siren]);
        assert_eq!(
            (m.done(), m.missing, m.corrupt.len()),
            (1, 0, 0),
            "{:?}",
            m.corrupt
        );
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn wrong_regions_name_the_meshes_with_far_sign_errors() {
        let near_only = report("near.obj", Some(([5, 2, 0, 0], [3, 0, 0, 0])));
        let ghost = report("ghost.obj", Some(([1, 0, 4, 30], [0, 0, 0, 0])));
        let hollow = report("hollow.obj", Some(([0, 0, 0, 0], [0, 1, 2, 1])));
        let old = report("old.obj", None);
        assert_eq!(wrong_regions(&[("old.obj", &old)]), None);
        assert_eq!(
            wrong_regions(&[("near.obj", &near_only)]).unwrap(),
            "Wrong-sign regions: none on 1 mesh(es); every box point of the wrong sign lies \
             within 0.05 of the surface (a surface a little off, not a region of the wrong sign)."
        );
        // The worst first; the errors within 0.05 do not count.
        let line = wrong_regions(&[
            ("hollow.obj", &hollow),
            ("near.obj", &near_only),
            ("ghost.obj", &ghost),
            ("old.obj", &old),
        ])
        .unwrap();
        assert_eq!(
            line,
            "Wrong-sign regions (box points of the wrong sign more than 0.05 from the surface, \
             false inside / false outside): 2 of 3 mesh(es); ghost.obj 34 / 0, hollow.obj 0 / 3. \
             (1 result(s) predate these counts.)"
        );
        // Past five meshes the list ends in an ellipsis.
        let many: Vec<Report> = (0..7)
            .map(|i| report(&format!("m{i}.obj"), Some(([0, 0, 0, i + 1], [0; 4]))))
            .collect();
        let names: Vec<String> = (0..7).map(|i| format!("m{i}.obj")).collect();
        let rows: Vec<(&str, &Report)> = names.iter().map(String::as_str).zip(&many).collect();
        let line = wrong_regions(&rows).unwrap();
        assert!(
            line.contains("7 of 7 mesh(es); m6.obj 7 / 0, m5.obj 6 / 0"),
            "{line}"
        );
        assert!(line.ends_with("m2.obj 3 / 0, ...."), "{line}");
    }

    /// The table has the ambiguous fractions beside F1, so that a low F1 on an open mesh
    /// explains itself; results from before they were recorded show `n/a`.
    #[test]
    fn the_table_shows_the_ambiguous_fractions() {
        let root = std::env::temp_dir().join(format!("hwsdf-corpus-amb-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let state = StateDir::for_table(&root.join("results.md"), &[]);
        state.create().unwrap();
        let mut open = report("open.obj", None);
        open.ambiguous_bbox = Some(0.0123);
        open.ambiguous_near_surface = Some(0.25);
        let old = report("old.obj", None);
        // A name with a `|` keeps its row's cells (escaped).
        let piped = report("p|q.obj", None);
        for (rel, r) in [("open.obj", open), ("old.obj", old), ("p|q.obj", piped)] {
            state
                .write(rel, ModelKind::Nglod, &Entry::Done(Box::new(r)))
                .unwrap();
        }
        let all = vec![
            CorpusMesh::new(&root, "open.obj"),
            CorpusMesh::new(&root, "old.obj"),
            CorpusMesh::new(&root, "p|q.obj"),
        ];
        let table = merge(&state, &all, &[ModelKind::Nglod]).markdown();
        assert!(
            table.contains("| mean | ambiguous box / near | train s |"),
            "{table}"
        );
        assert!(
            table.contains("| open.obj | 0.990 | 0.950 | 0.970 | 1.2% / 25.0% |"),
            "{table}"
        );
        assert!(
            table.contains("| old.obj | 0.990 | 0.950 | 0.970 | n/a |"),
            "{table}"
        );
        assert!(table.contains("| p\\|q.obj | 0.990 |"), "{table}");
        // Every row has the header's number of cells.
        let cells = |line: &str| line.replace("\\|", "").matches('|').count();
        let header = table.lines().find(|l| l.starts_with("| mesh")).unwrap();
        for line in table.lines().filter(|l| l.starts_with('|')) {
            assert_eq!(cells(line), cells(header), "{line}");
        }
        let _ = std::fs::remove_dir_all(&root);
    }

    /// Each model has its own section; the hash grid's is measured against NGLOD's figures,
    /// labelled as NGLOD's (the design document has no hash grid).
    #[test]
    fn the_hash_grid_has_its_own_section_against_nglods_figures() {
        let root = std::env::temp_dir().join(format!("hwsdf-corpus-hg-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let state = StateDir::for_table(&root.join("results.md"), &[]);
        state.create().unwrap();
        let mut grid = report("a.obj", None);
        grid.model = "hashgrid".into();
        grid.f1_bbox = Some(0.5);
        for (model, r) in [
            (ModelKind::Nglod, report("a.obj", None)),
            (ModelKind::Hashgrid, grid),
        ] {
            state
                .write("a.obj", model, &Entry::Done(Box::new(r)))
                .unwrap();
        }
        let all = vec![CorpusMesh::new(&root, "a.obj")];
        let m = merge(&state, &all, &ModelKind::ALL);
        assert_eq!((m.expected, m.done(), m.missing), (3, 2, 1));
        let table = m.markdown();
        let nglod = table.find("### NGLOD").expect("an NGLOD section");
        let hashgrid = table.find("### Hash grid").expect("a hash-grid section");
        assert!(nglod < hashgrid && !table.contains("### SIREN"), "{table}");
        let (nglod, hashgrid) = table.split_at(hashgrid);
        assert!(nglod.contains("| a.obj | 0.990 |"), "{table}");
        assert!(hashgrid.contains("| a.obj | 0.500 |"), "{table}");
        assert!(
            nglod.contains("| design document (50 meshes) | 0.98 | 0.94 |"),
            "{table}"
        );
        assert!(
            hashgrid.contains("| design document, NGLOD (50 meshes) | 0.98 | 0.94 |"),
            "{table}"
        );
        let _ = std::fs::remove_dir_all(&root);
    }

    #[test]
    fn a_corrupt_record_is_never_merged() {
        let root = std::env::temp_dir().join(format!("hwsdf-corpus-merge-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let state = StateDir::for_table(&root.join("results.md"), &[]);
        state.create().unwrap();
        let all = vec![
            CorpusMesh::new(&root, "a.obj"),
            CorpusMesh::new(&root, "b.obj"),
            CorpusMesh::new(&root, "c.obj"),
        ];
        let failed = Entry::Failed {
            mesh: "a.obj".into(),
            model: "nglod".into(),
            error: "no triangles".into(),
        };
        state.write("a.obj", ModelKind::Nglod, &failed).unwrap();
        // What a writer killed half-way through a file would leave, if it wrote in place.
        std::fs::write(state.record("b.obj", ModelKind::Nglod), "{\"mesh\": \"b.o").unwrap();
        let m = merge(&state, &all, &[ModelKind::Nglod]);
        assert_eq!((m.expected, m.done(), m.missing), (3, 0, 2));
        assert_eq!(m.failed(), vec![("a.obj", "nglod", "no triangles")]);
        assert_eq!(m.corrupt.len(), 1);
        assert!(matches!(
            state.read("b.obj", ModelKind::Nglod),
            Record::Corrupt(_)
        ));
        let table = m.markdown();
        assert!(
            table.contains("0 of 3 done, 1 failed, 2 not yet run"),
            "{table}"
        );
        assert!(table.contains("| a.obj | failed: no triangles"), "{table}");
        assert!(!table.contains("b.obj"), "{table}");
        // A result that cannot be read (here a folder in its place) is not taken for a corrupt
        // one, which the next run would redo over it.
        std::fs::create_dir(state.record("c.obj", ModelKind::Nglod)).unwrap();
        assert!(matches!(
            state.read("c.obj", ModelKind::Nglod),
            Record::Unreadable(_)
        ));
        let m = merge(&state, &all, &[ModelKind::Nglod]);
        assert_eq!((m.missing, m.corrupt.len(), m.unreadable.len()), (2, 1, 1));
        std::fs::remove_dir_all(&root).unwrap();
    }
}
