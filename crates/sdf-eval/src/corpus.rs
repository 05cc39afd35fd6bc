//! Corpus runs: which meshes a corpus holds, which of them one shard takes, where each mesh's
//! result lives in the shared `<out>.d/` folder, and the table merged from those results.
//!
//! Scale-out rides on the engines people already run (Slurm job arrays, Kubernetes Indexed
//! Jobs): the engine hands every task its index, [`Shard`] turns the index into a fixed subset of
//! the meshes, every task writes one file per mesh and model into the same folder (atomically,
//! under a name no other mesh shares), and [`merge`] builds the table from that folder alone.
//! There is no queue, lock or protocol of our own: a shard that is run again skips what is done.
//!
//! ```
//! use sdf_eval::corpus::{CorpusMesh, Shard};
//!
//! let meshes: Vec<CorpusMesh> = ["a.obj", "sub/b.glb", "c.gltf"]
//!     .iter()
//!     .map(|rel| CorpusMesh::new(std::path::Path::new("/data"), rel))
//!     .collect();
//! // Every mesh lands in exactly one of three shards, by a hash of its relative path.
//! let total: usize = (0..3)
//!     .map(|k| Shard::new(k, 3).unwrap().select(&meshes).len())
//!     .sum();
//! assert_eq!(total, meshes.len());
//! ```

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::run::{ModelKind, Report, RunSettings};

/// File extensions a corpus walk picks up (case-insensitive).
pub const MESH_EXTENSIONS: [&str; 3] = ["obj", "gltf", "glb"];

/// Errors of corpus bookkeeping. Every one is raised before any training starts.
#[derive(Debug, thiserror::Error)]
pub enum CorpusError {
    /// A folder or list could not be read.
    #[error("{path}: {source}")]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The corpus holds no mesh.
    #[error("{0} holds no .obj, .gltf or .glb file")]
    Empty(PathBuf),
    /// A shard specification that cannot be used.
    #[error("bad shard {value:?} (from {source_name}): {reason}")]
    BadShard {
        /// The value as given.
        value: String,
        /// Where it came from (`--shard`, `SLURM_ARRAY_TASK_ID`, ...).
        source_name: String,
        /// Why it is refused.
        reason: String,
    },
    /// The results folder holds results of other settings; one table never mixes them.
    #[error(
        "{} holds results of other settings ({}); give another --out, or delete that folder to start over",
        .dir.display(), .differences.join("; ")
    )]
    OtherSettings {
        /// The results folder.
        dir: PathBuf,
        /// `name asked, not recorded` for each setting that differs.
        differences: Vec<String>,
    },
    /// The results folder's settings record does not parse.
    #[error(
        "{}: not a settings record ({reason}); delete it only if every result in its folder was made with this run's settings",
        .path.display()
    )]
    BadSettings {
        /// The record.
        path: PathBuf,
        /// The parse error.
        reason: String,
    },
}

/// What a corpus run asks for: the evaluation's size and each model's [`RunSettings`]. The first
/// run or shard writes them into `<out>.d/settings.json` and every later one must ask for the
/// same ([`StateDir::claim`]), so that a table never mixes results of different settings and a
/// rerun with other flags cannot silently skip meshes as done.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct CorpusSettings {
    /// Points in each evaluation set.
    pub eval_points: usize,
    /// Each model's settings, by model name.
    pub models: BTreeMap<String, RunSettings>,
}

impl CorpusSettings {
    /// How these settings differ from `recorded`, as `name asked, not recorded` lines: the
    /// evaluation, and each model both have (a model only one side has is no conflict: its
    /// results are kept apart by name).
    pub fn differences(&self, recorded: &CorpusSettings) -> Vec<String> {
        let mut out = Vec::new();
        if self.eval_points != recorded.eval_points {
            out.push(format!(
                "eval points {}, not {}",
                self.eval_points, recorded.eval_points
            ));
        }
        for (model, settings) in &self.models {
            if let Some(theirs) = recorded.models.get(model) {
                out.extend(
                    settings
                        .differences(theirs)
                        .into_iter()
                        .map(|d| format!("{model} {d}")),
                );
            }
        }
        out
    }
}

/// One mesh of a corpus: where it is, and its path relative to the corpus root, which names it
/// in the table, in the result files and in the shard hash.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct CorpusMesh {
    /// Relative path with `/` separators (the key of everything else).
    pub rel: String,
    /// The file to load.
    pub path: PathBuf,
}

impl CorpusMesh {
    /// The mesh at `rel` under `root` (`rel` may also be absolute; it is then its own key).
    pub fn new(root: &Path, rel: &str) -> Self {
        let rel = rel.trim().replace('\\', "/");
        let rel = rel.trim_start_matches("./").to_owned();
        CorpusMesh {
            path: root.join(&rel),
            rel,
        }
    }
}

fn is_mesh_name(name: &str) -> bool {
    Path::new(name)
        .extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| MESH_EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
}

/// Every OBJ, glTF and GLB file under `root`, recursively, sorted by relative path.
///
/// Hidden entries (names starting with `.`) are skipped, and so are symbolic links to folders,
/// so that a link cycle cannot make the walk endless; links to files are followed.
pub fn walk(root: &Path) -> Result<Vec<CorpusMesh>, CorpusError> {
    let io = |path: &Path| {
        let path = path.to_owned();
        move |source| CorpusError::Io { path, source }
    };
    let mut out = Vec::new();
    let mut stack = vec![(root.to_owned(), String::new())];
    while let Some((dir, prefix)) = stack.pop() {
        for entry in std::fs::read_dir(&dir).map_err(io(&dir))? {
            let entry = entry.map_err(io(&dir))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            if name.starts_with('.') {
                continue;
            }
            let rel = format!("{prefix}{name}");
            let kind = entry.file_type().map_err(io(&entry.path()))?;
            if kind.is_dir() {
                stack.push((entry.path(), format!("{rel}/")));
            } else if is_mesh_name(&name)
                && std::fs::metadata(entry.path()).is_ok_and(|m| m.is_file())
            {
                out.push(CorpusMesh {
                    path: entry.path(),
                    rel,
                });
            }
        }
    }
    out.sort();
    if out.is_empty() {
        return Err(CorpusError::Empty(root.to_owned()));
    }
    Ok(out)
}

/// The largest mesh list [`read_list`] reads (about a million paths).
pub const MAX_LIST_BYTES: u64 = 64 << 20;

/// The meshes named in a list file: one path a line, relative to the list's folder (or
/// absolute); blank lines and lines starting with `#` are skipped, repeats are dropped.
pub fn read_list(list: &Path) -> Result<Vec<CorpusMesh>, CorpusError> {
    // A regular file of at most 64 MiB: a FIFO would block, /dev/zero would fill the memory.
    let io = |source| CorpusError::Io {
        path: list.to_owned(),
        source,
    };
    let bytes = sdf_geom::io::read_regular_file(list, MAX_LIST_BYTES).map_err(io)?;
    let text = String::from_utf8(bytes).map_err(|e| {
        io(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("not UTF-8 text: {e}"),
        ))
    })?;
    let root = list.parent().unwrap_or(Path::new("."));
    let set: BTreeSet<CorpusMesh> = text
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .map(|l| CorpusMesh::new(root, l))
        .collect();
    if set.is_empty() {
        return Err(CorpusError::Empty(list.to_owned()));
    }
    Ok(set.into_iter().collect())
}

/// FNV-1a, 64 bits: a hash that never changes between versions, platforms or runs (unlike
/// `std`'s), so a mesh stays in its shard for as long as its relative path does.
pub fn stable_hash(s: &str) -> u64 {
    s.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

/// Shard `index` of `count`: the meshes whose [`stable_hash`] of the relative path is `index`
/// modulo `count`. Adding meshes to a corpus never moves the others between shards.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shard {
    /// 0-based shard index.
    pub index: u32,
    /// Number of shards.
    pub count: u32,
}

impl Shard {
    /// Everything in one shard.
    pub const ALL: Shard = Shard { index: 0, count: 1 };

    /// Shard `index` of `count`, checked.
    pub fn new(index: u32, count: u32) -> Result<Self, CorpusError> {
        Self::checked(index, count, &format!("{index}/{count}"), "arguments")
    }

    fn checked(index: u32, count: u32, value: &str, source: &str) -> Result<Self, CorpusError> {
        let reason = if count == 0 {
            Some("the shard count must be at least 1".to_owned())
        } else if index >= count {
            Some(format!(
                "shard index {index} is not below the count {count} (indices are 0..{count})"
            ))
        } else {
            None
        };
        match reason {
            Some(reason) => Err(CorpusError::BadShard {
                value: value.to_owned(),
                source_name: source.to_owned(),
                reason,
            }),
            None => Ok(Shard { index, count }),
        }
    }

    /// Parses `K/N` (as `--shard` takes it).
    pub fn parse(value: &str) -> Result<Self, CorpusError> {
        let bad = |reason: &str| CorpusError::BadShard {
            value: value.to_owned(),
            source_name: "--shard".into(),
            reason: reason.to_owned(),
        };
        let (k, n) = value
            .split_once('/')
            .ok_or_else(|| bad("expected K/N, e.g. 0/8"))?;
        // u32's own parse error says whether the number is not one or too large.
        let whole = |x: &str, name: &str| {
            x.trim().parse::<u32>().map_err(|e| match e.kind() {
                std::num::IntErrorKind::PosOverflow => {
                    bad(&format!("{name} is larger than {}", u32::MAX))
                }
                _ => bad(&format!("{name} is not a whole number")),
            })
        };
        let (k, n) = (whole(k, "K")?, whole(n, "N")?);
        Self::checked(k, n, value, "--shard")
    }

    /// The shard the engine assigned, from its variables (`var` reads one; pass
    /// `|k| std::env::var(k).ok()`), and a description of where it came from:
    ///
    /// - Slurm job arrays: `SLURM_ARRAY_TASK_ID`. With a count from `shards` (the `--shards`
    ///   flag) or `HWSDF_SHARDS`, the task id is the 0-based shard index, which keeps a task
    ///   resubmitted on its own (`sbatch --array=5`) in its shard; the recipe sets it. Without
    ///   one, the index and count come from the array itself (`SLURM_ARRAY_TASK_MIN`,
    ///   `SLURM_ARRAY_TASK_STEP`, `SLURM_ARRAY_TASK_COUNT` or `SLURM_ARRAY_TASK_MAX`), so
    ///   `--array=1-8` and `--array=0-14:2` work too;
    /// - Kubernetes Indexed Jobs: `JOB_COMPLETION_INDEX`, with the count from `shards` (the
    ///   `--shards` flag) or `HWSDF_SHARDS`.
    ///
    /// `None` when no engine variable is set: the run takes every mesh.
    pub fn from_env(
        var: impl Fn(&str) -> Option<String>,
        shards: Option<u32>,
    ) -> Result<Option<(Self, String)>, CorpusError> {
        let num = |name: &str| -> Result<Option<u32>, CorpusError> {
            match var(name).filter(|v| !v.trim().is_empty()) {
                None => Ok(None),
                Some(v) => v
                    .trim()
                    .parse()
                    .map(Some)
                    .map_err(|_| CorpusError::BadShard {
                        value: v.clone(),
                        source_name: name.to_owned(),
                        reason: "not a whole number".into(),
                    }),
            }
        };
        let count = match shards {
            Some(n) => Some(n),
            None => num("HWSDF_SHARDS")?,
        };
        if let Some(id) = num("SLURM_ARRAY_TASK_ID")? {
            if let Some(count) = count {
                // A stated count makes the task id the shard index itself, so one task
                // resubmitted alone (`sbatch --array=5`) is still shard 5 of the whole run.
                let value = format!("task {id} of {count} (HWSDF_SHARDS or --shards)");
                let shard = Self::checked(id, count, &value, "SLURM_ARRAY_TASK_ID")?;
                return Ok(Some((shard, format!("Slurm array task {id}"))));
            }
            let min = num("SLURM_ARRAY_TASK_MIN")?.unwrap_or(0);
            let step = num("SLURM_ARRAY_TASK_STEP")?.unwrap_or(1).max(1);
            let count = match (num("SLURM_ARRAY_TASK_COUNT")?, num("SLURM_ARRAY_TASK_MAX")?) {
                (Some(c), _) => c,
                (None, Some(max)) if max >= min => (max - min) / step + 1,
                _ => {
                    return Err(CorpusError::BadShard {
                        value: id.to_string(),
                        source_name: "SLURM_ARRAY_TASK_ID".into(),
                        reason: "neither HWSDF_SHARDS, SLURM_ARRAY_TASK_COUNT nor a usable SLURM_ARRAY_TASK_MAX is set".into(),
                    });
                }
            };
            let value = format!("task {id} of {count} (min {min}, step {step})");
            if id < min || (id - min) % step != 0 {
                return Err(CorpusError::BadShard {
                    value,
                    source_name: "SLURM_ARRAY_TASK_ID".into(),
                    reason: "the task id is not on the array's range".into(),
                });
            }
            let shard = Self::checked((id - min) / step, count, &value, "SLURM_ARRAY_TASK_ID")?;
            return Ok(Some((shard, format!("Slurm array task {id}"))));
        }
        if let Some(index) = num("JOB_COMPLETION_INDEX")? {
            let count = count.ok_or_else(|| CorpusError::BadShard {
                value: index.to_string(),
                source_name: "JOB_COMPLETION_INDEX".into(),
                reason: "the shard count is unknown: pass --shards N or set HWSDF_SHARDS (the Job's completions)".into(),
            })?;
            let value = format!("{index}/{count}");
            let shard = Self::checked(index, count, &value, "JOB_COMPLETION_INDEX")?;
            return Ok(Some((
                shard,
                format!("Kubernetes completion index {index}"),
            )));
        }
        Ok(None)
    }

    /// Whether the mesh with relative path `rel` is in this shard.
    pub fn contains(&self, rel: &str) -> bool {
        stable_hash(rel) % u64::from(self.count) == u64::from(self.index)
    }

    /// This shard's meshes, in order.
    pub fn select<'a>(&self, meshes: &'a [CorpusMesh]) -> Vec<&'a CorpusMesh> {
        meshes.iter().filter(|m| self.contains(&m.rel)).collect()
    }
}

impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

/// One mesh × model outcome, as kept on disk.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Entry {
    /// Trained and evaluated.
    Done(Box<Report>),
    /// Failed with this error (retried by the next run).
    Failed {
        /// The mesh file.
        mesh: String,
        /// `"siren"` or `"nglod"`.
        model: String,
        /// The error.
        error: String,
    },
}

/// What a mesh's result file holds.
#[derive(Debug)]
pub enum Record {
    /// No file yet.
    Missing,
    /// A finished or failed run.
    Entry(Entry),
    /// A file that does not parse (a writer killed by hand, a disk error): it is never merged,
    /// and the next run redoes the mesh.
    Corrupt(String),
}

/// The folder of per-mesh results, `<out>.d/`, shared by every shard.
#[derive(Clone, Debug)]
pub struct StateDir {
    dir: PathBuf,
}

impl StateDir {
    /// The folder that belongs to the table `out`.
    pub fn for_table(out: &Path) -> Self {
        StateDir {
            dir: PathBuf::from(format!("{}.d", out.display())),
        }
    }

    /// Its path.
    pub fn path(&self) -> &Path {
        &self.dir
    }

    /// Creates the folder (and its parents) if needed.
    pub fn create(&self) -> Result<(), CorpusError> {
        // "File exists (os error 17)" alone does not say that the state folder's name is taken.
        if self.dir.exists() && !self.dir.is_dir() {
            return Err(CorpusError::Io {
                path: self.dir.clone(),
                source: std::io::Error::new(
                    std::io::ErrorKind::AlreadyExists,
                    "a file has the name of the results' state folder (the table's name + .d); \
                     move it or choose another --out",
                ),
            });
        }
        std::fs::create_dir_all(&self.dir).map_err(|source| CorpusError::Io {
            path: self.dir.clone(),
            source,
        })
    }

    /// The stem of every file of `mesh` × `model`: the relative path itself where it is a
    /// plain file name, otherwise the path with unsafe characters replaced and a hash of the
    /// whole relative path appended, so that no two meshes share a name.
    pub fn stem(rel: &str, model: ModelKind) -> String {
        let plain = !rel.is_empty()
            && !rel.starts_with('.')
            && rel
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'));
        let base = if plain {
            rel.to_owned()
        } else {
            let cleaned: String = rel
                .chars()
                .map(|c| {
                    if c.is_ascii_alphanumeric() || matches!(c, '.' | '-') {
                        c
                    } else {
                        '_'
                    }
                })
                .collect();
            let cleaned = cleaned.trim_start_matches(['.', '_']);
            let tail: String = cleaned
                .chars()
                .rev()
                .take(80)
                .collect::<Vec<_>>()
                .into_iter()
                .rev()
                .collect();
            format!("{tail}-{:08x}", stable_hash(rel) as u32)
        };
        format!("{base}.{}", model.name())
    }

    /// The record of the settings every result in the folder was made with.
    pub fn settings_path(&self) -> PathBuf {
        self.dir.join("settings.json")
    }

    /// The recorded settings, if any run has recorded them yet.
    pub fn read_settings(&self) -> Result<Option<CorpusSettings>, CorpusError> {
        let path = self.settings_path();
        match std::fs::read(&path) {
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(source) => Err(CorpusError::Io { path, source }),
            Ok(bytes) => {
                serde_json::from_slice(&bytes)
                    .map(Some)
                    .map_err(|e| CorpusError::BadSettings {
                        path,
                        reason: e.to_string(),
                    })
            }
        }
    }

    /// Records `settings` as the folder's, or checks them against those recorded: any
    /// difference is [`CorpusError::OtherSettings`], and a model the record lacks is added to
    /// it. Shards starting together agree on one record: the first is created without ever
    /// replacing another's, and the rest are checked against it. A folder from before the
    /// record existed takes the first settings claimed.
    pub fn claim(&self, settings: &CorpusSettings) -> Result<(), CorpusError> {
        let path = self.settings_path();
        let io = |source| CorpusError::Io {
            path: path.clone(),
            source,
        };
        let json = |s: &CorpusSettings| serde_json::to_vec_pretty(s).expect("settings serialise");
        // Twice at most: a shard that loses the race to create the record reads the winner's.
        for _ in 0..2 {
            let Some(recorded) = self.read_settings()? else {
                match sdf_geom::io::create_atomic(&path, &json(settings)) {
                    Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
                    other => return other.map_err(io),
                }
            };
            let differences = settings.differences(&recorded);
            if !differences.is_empty() {
                return Err(CorpusError::OtherSettings {
                    dir: self.dir.clone(),
                    differences,
                });
            }
            let mut merged = recorded.clone();
            for (model, s) in &settings.models {
                merged
                    .models
                    .entry(model.clone())
                    .or_insert_with(|| s.clone());
            }
            if merged != recorded {
                sdf_geom::io::write_atomic(&path, &json(&merged)).map_err(io)?;
            }
            return Ok(());
        }
        Err(io(std::io::Error::other(
            "the settings record was created and removed while being read",
        )))
    }

    /// The result file of `rel` × `model`.
    pub fn record(&self, rel: &str, model: ModelKind) -> PathBuf {
        self.dir.join(format!("{}.json", Self::stem(rel, model)))
    }

    /// The model file of `rel` × `model`.
    pub fn model_file(&self, rel: &str, model: ModelKind) -> PathBuf {
        self.dir
            .join(format!("{}.safetensors", Self::stem(rel, model)))
    }

    /// The checkpoint an interrupted fit of `rel` × `model` leaves.
    pub fn checkpoint(&self, rel: &str, model: ModelKind) -> PathBuf {
        self.dir
            .join(format!("{}.checkpoint.safetensors", Self::stem(rel, model)))
    }

    /// Reads the result of `rel` × `model`.
    pub fn read(&self, rel: &str, model: ModelKind) -> Record {
        let path = self.record(rel, model);
        match std::fs::read(&path) {
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Record::Missing,
            Err(e) => Record::Corrupt(format!("{}: {e}", path.display())),
            Ok(bytes) => match serde_json::from_slice::<Entry>(&bytes) {
                Ok(entry) => Record::Entry(entry),
                Err(e) => Record::Corrupt(format!("{}: {e}", path.display())),
            },
        }
    }

    /// Writes the result of `rel` × `model`, atomically.
    pub fn write(&self, rel: &str, model: ModelKind, entry: &Entry) -> Result<(), CorpusError> {
        let path = self.record(rel, model);
        let json = serde_json::to_vec_pretty(entry).expect("entries serialise");
        sdf_geom::io::write_atomic(&path, &json).map_err(|source| CorpusError::Io { path, source })
    }
}

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

/// The design document's averages (F1 in the box, F1 near the surface).
fn reference(model: &str) -> (f64, f64) {
    match model {
        "siren" => (0.90, 0.89),
        _ => (0.98, 0.94),
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
        let presets: BTreeSet<&str> = reports.iter().map(|r| r.preset.as_str()).collect();
        let adapters: BTreeSet<&str> = reports.iter().map(|r| r.adapter.as_str()).collect();
        let list = |set: &BTreeSet<&str>| {
            if set.is_empty() {
                "none yet".to_owned()
            } else {
                set.iter().copied().collect::<Vec<_>>().join("; ")
            }
        };
        let _ = writeln!(
            s,
            "Preset `{}`, adapter {}. {}.\n",
            list(&presets),
            list(&adapters),
            self.status()
        );
        for model in ["siren", "nglod"] {
            let rows: Vec<_> = self
                .entries
                .iter()
                .filter(|((m, _), _)| *m == model)
                .collect();
            if rows.is_empty() {
                continue;
            }
            let _ = writeln!(s, "### {}\n", model.to_uppercase());
            if let Ok(Some(settings)) = &self.settings {
                if let Some(m) = settings.models.get(model) {
                    let _ = writeln!(s, "Settings: {m}; eval points {}.\n", settings.eval_points);
                }
            }
            let _ = writeln!(
                s,
                "| mesh | F1 in bounding box | F1 near surface | mean | train s | ns/point | µs/3000 | params | file bytes |"
            );
            let _ = writeln!(s, "| --- | --- | --- | --- | --- | --- | --- | --- | --- |");
            let (mut fb, mut fnr, mut n, mut left_out) = (0.0, 0.0, 0usize, 0usize);
            let mut done: Vec<(&str, &Report)> = Vec::new();
            for ((_, mesh), e) in &rows {
                match e {
                    Entry::Done(r) => {
                        done.push((mesh.as_str(), r.as_ref()));
                        let _ = writeln!(
                            s,
                            "| {mesh} | {} | {} | {} | {:.0} | {:.0} | {:.0} | {} | {} |",
                            f1_cell(r.f1_bbox),
                            f1_cell(r.f1_near_surface),
                            f1_cell(r.f1_mean),
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
                            "| {mesh} | failed: {} | | | | | | | |",
                            error.replace('|', "/").replace('\n', " ")
                        );
                    }
                }
            }
            if left_out > 0 {
                let _ = writeln!(
                    s,
                    "| n/a: {left_out} mesh(es) without an inside (F1 undefined), left out of the average | | | | | | | | |"
                );
            }
            if n > 0 {
                let (rb, rn) = reference(model);
                let _ = writeln!(
                    s,
                    "| **average ({n} meshes)** | **{:.3}** | **{:.3}** | **{:.3}** | | | | | |",
                    fb / n as f64,
                    fnr / n as f64,
                    0.5 * (fb + fnr) / n as f64
                );
                let _ = writeln!(
                    s,
                    "| design document (50 meshes) | {rb:.2} | {rn:.2} | {:.3} | | | | | |",
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

#[cfg(test)]
mod tests {
    use super::*;

    fn meshes(n: usize) -> Vec<CorpusMesh> {
        (0..n)
            .map(|i| CorpusMesh::new(Path::new("/c"), &format!("set{}/mesh{i}.obj", i % 7)))
            .collect()
    }

    fn env(vars: &[(&str, &str)]) -> impl Fn(&str) -> Option<String> {
        let vars: Vec<(String, String)> = vars
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect();
        move |k| vars.iter().find(|(n, _)| n == k).map(|(_, v)| v.clone())
    }

    #[test]
    fn the_hash_is_fixed_forever() {
        // FNV-1a test vectors: changing them would move every mesh to another shard.
        assert_eq!(stable_hash(""), 0xcbf2_9ce4_8422_2325);
        assert_eq!(stable_hash("a"), 0xaf63_dc4c_8601_ec8c);
        assert_eq!(stable_hash("foobar"), 0x8594_4171_f739_67e8);
    }

    #[test]
    fn shards_partition_the_corpus_and_are_balanced() {
        let all = meshes(1000);
        for count in [1u32, 2, 3, 8, 64] {
            let mut seen = BTreeSet::new();
            for index in 0..count {
                let part = Shard::new(index, count).unwrap().select(&all);
                if count <= 8 {
                    let ideal = all.len() as f64 / f64::from(count);
                    assert!(
                        (part.len() as f64 - ideal).abs() < 0.25 * ideal,
                        "shard {index}/{count} has {} meshes",
                        part.len()
                    );
                }
                for m in part {
                    assert!(seen.insert(m.rel.clone()), "{} in two shards", m.rel);
                }
            }
            assert_eq!(seen.len(), all.len());
        }
    }

    #[test]
    fn adding_meshes_moves_none_of_the_others() {
        let before = meshes(200);
        let mut after = before.clone();
        after.extend((0..50).map(|i| CorpusMesh::new(Path::new("/c"), &format!("new/{i}.glb"))));
        after.sort();
        for k in 0..5 {
            let shard = Shard::new(k, 5).unwrap();
            for m in &before {
                let later = after.iter().find(|a| a.rel == m.rel).unwrap();
                assert_eq!(shard.contains(&m.rel), shard.contains(&later.rel));
            }
        }
    }

    #[test]
    fn bad_shards_are_refused_with_the_reason() {
        for (value, needle) in [
            ("3/3", "not below"),
            ("0/0", "at least 1"),
            ("x/2", "whole number"),
            ("1", "K/N"),
            ("-1/4", "whole number"),
            ("0/99999999999", "N is larger than 4294967295"),
        ] {
            let e = Shard::parse(value).unwrap_err().to_string();
            assert!(e.contains(needle), "{value}: {e}");
        }
        assert_eq!(Shard::parse(" 2/8 ").unwrap(), Shard { index: 2, count: 8 });
    }

    #[test]
    fn a_file_in_the_state_folders_place_is_named() {
        let dir = std::env::temp_dir().join(format!("hwsdf-statefile-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let out = dir.join("r.md");
        std::fs::write(dir.join("r.md.d"), "not a folder").unwrap();
        let e = StateDir::for_table(&out).create().unwrap_err().to_string();
        assert!(e.contains("r.md.d"), "{e}");
        assert!(
            e.contains("a file has the name of the results' state folder"),
            "{e}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn engines_variables_give_the_shard() {
        let none = Shard::from_env(env(&[]), None).unwrap();
        assert!(none.is_none());
        let slurm = env(&[
            ("SLURM_ARRAY_TASK_ID", "2"),
            ("SLURM_ARRAY_TASK_COUNT", "3"),
            ("SLURM_ARRAY_TASK_MIN", "0"),
            ("SLURM_ARRAY_TASK_MAX", "2"),
        ]);
        let (s, from) = Shard::from_env(slurm, None).unwrap().unwrap();
        assert_eq!(s, Shard { index: 2, count: 3 });
        assert!(from.contains("Slurm"));
        // --array=1-8: ids start at 1.
        let one_based = env(&[
            ("SLURM_ARRAY_TASK_ID", "8"),
            ("SLURM_ARRAY_TASK_MIN", "1"),
            ("SLURM_ARRAY_TASK_MAX", "8"),
        ]);
        assert_eq!(
            Shard::from_env(one_based, None).unwrap().unwrap().0,
            Shard { index: 7, count: 8 }
        );
        // --array=0-14:2 gives ids 0, 2, ..., 14: eight tasks.
        let stepped = env(&[
            ("SLURM_ARRAY_TASK_ID", "6"),
            ("SLURM_ARRAY_TASK_MIN", "0"),
            ("SLURM_ARRAY_TASK_MAX", "14"),
            ("SLURM_ARRAY_TASK_STEP", "2"),
        ]);
        assert_eq!(
            Shard::from_env(stepped, None).unwrap().unwrap().0,
            Shard { index: 3, count: 8 }
        );
        // A stated count keeps a task resubmitted alone (`--array=5`) in shard 5 of 8.
        let alone = env(&[
            ("SLURM_ARRAY_TASK_ID", "5"),
            ("SLURM_ARRAY_TASK_COUNT", "1"),
            ("SLURM_ARRAY_TASK_MIN", "5"),
            ("SLURM_ARRAY_TASK_MAX", "5"),
            ("HWSDF_SHARDS", "8"),
        ]);
        assert_eq!(
            Shard::from_env(alone, None).unwrap().unwrap().0,
            Shard { index: 5, count: 8 }
        );
        let k8s = env(&[("JOB_COMPLETION_INDEX", "4"), ("HWSDF_SHARDS", "5")]);
        assert_eq!(
            Shard::from_env(&k8s, None).unwrap().unwrap().0,
            Shard { index: 4, count: 5 }
        );
        // --shards wins over HWSDF_SHARDS.
        assert_eq!(
            Shard::from_env(&k8s, Some(10)).unwrap().unwrap().0,
            Shard {
                index: 4,
                count: 10
            }
        );
        for (vars, needle) in [
            (vec![("JOB_COMPLETION_INDEX", "4")], "--shards"),
            (
                vec![("JOB_COMPLETION_INDEX", "5"), ("HWSDF_SHARDS", "5")],
                "not below",
            ),
            (vec![("SLURM_ARRAY_TASK_ID", "x")], "whole number"),
            (vec![("SLURM_ARRAY_TASK_ID", "1")], "SLURM_ARRAY_TASK_COUNT"),
            (
                vec![("SLURM_ARRAY_TASK_ID", "8"), ("HWSDF_SHARDS", "8")],
                "not below",
            ),
        ] {
            let e = Shard::from_env(env(&vars), None).unwrap_err().to_string();
            assert!(e.contains(needle), "{vars:?}: {e}");
        }
    }

    #[test]
    fn names_are_unique_per_mesh_and_model() {
        let rels = [
            "a.obj",
            "x/a.obj",
            "x_a.obj",
            "y/x/a.obj",
            "a b.obj",
            "a_b.obj",
            "ünï.obj",
            "../up.obj",
        ];
        let mut stems = BTreeSet::new();
        for rel in rels {
            for model in [ModelKind::Siren, ModelKind::Nglod] {
                let stem = StateDir::stem(rel, model);
                assert!(!stem.contains('/') && !stem.starts_with('.'), "{stem}");
                assert!(
                    stems.insert(stem.clone()),
                    "{rel} {model:?} -> {stem} twice"
                );
            }
        }
        // Flat corpora keep the names earlier versions wrote, so old runs resume.
        assert_eq!(
            StateDir::stem("spot.obj", ModelKind::Nglod),
            "spot.obj.nglod"
        );
    }

    #[test]
    fn walk_recurses_and_a_list_is_relative_to_itself() {
        let root = std::env::temp_dir().join(format!("hwsdf-corpus-walk-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        for f in [
            "a.obj",
            "sub/b.GLB",
            "sub/deep/c.gltf",
            "sub/notes.txt",
            ".hidden/d.obj",
        ] {
            let p = root.join(f);
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            std::fs::write(&p, "").unwrap();
        }
        let rels: Vec<String> = walk(&root).unwrap().into_iter().map(|m| m.rel).collect();
        assert_eq!(rels, ["a.obj", "sub/b.GLB", "sub/deep/c.gltf"]);
        std::fs::write(
            root.join("sub/list.txt"),
            "# meshes\nb.GLB\n\n./deep/c.gltf\nb.GLB\n",
        )
        .unwrap();
        let listed = read_list(&root.join("sub/list.txt")).unwrap();
        assert_eq!(listed.len(), 2);
        assert_eq!(listed[0].rel, "b.GLB");
        assert_eq!(listed[0].path, root.join("sub/b.GLB"));
        assert_eq!(listed[1].rel, "deep/c.gltf");
        // Special files are refused unread (a FIFO would block, /dev/zero fill the memory).
        #[cfg(unix)]
        {
            let fifo = root.join("list.fifo");
            let made = std::process::Command::new("mkfifo")
                .arg(&fifo)
                .status()
                .unwrap()
                .success();
            assert!(made);
            for special in [fifo.as_path(), Path::new("/dev/zero")] {
                match read_list(special) {
                    Err(e @ CorpusError::Io { .. }) => {
                        assert!(e.to_string().contains("not a regular file"), "{e}")
                    }
                    other => panic!("{special:?}: {other:?}"),
                }
            }
        }
        assert!(matches!(
            walk(&root.join("sub/deep/nothing")),
            Err(CorpusError::Io { .. })
        ));
        std::fs::create_dir_all(root.join("empty")).unwrap();
        assert!(matches!(
            walk(&root.join("empty")),
            Err(CorpusError::Empty(_))
        ));
        std::fs::remove_dir_all(&root).unwrap();
    }

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

    #[test]
    fn a_corrupt_record_is_never_merged() {
        let root = std::env::temp_dir().join(format!("hwsdf-corpus-merge-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let state = StateDir::for_table(&root.join("results.md"));
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
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn a_results_folder_keeps_one_set_of_settings() {
        use crate::run::{Preset, TrainOptions};
        let root =
            std::env::temp_dir().join(format!("hwsdf-corpus-settings-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let state = StateDir::for_table(&root.join("results.md"));
        state.create().unwrap();
        let nglod = |epochs: Option<usize>, cpu: bool| {
            TrainOptions {
                epochs,
                ..TrainOptions::new(ModelKind::Nglod, Preset::Default)
            }
            .settings(cpu)
            .unwrap()
        };
        let siren = TrainOptions {
            steps: Some(50),
            ..TrainOptions::new(ModelKind::Siren, Preset::Small)
        };
        let with = |models: &[(&str, RunSettings)], points: usize| CorpusSettings {
            eval_points: points,
            models: models
                .iter()
                .map(|(m, s)| (m.to_string(), s.clone()))
                .collect(),
        };
        let first = with(&[("nglod", nglod(Some(12), false))], 1000);
        assert_eq!(state.read_settings().unwrap(), None);
        state.claim(&first).unwrap();
        assert_eq!(state.read_settings().unwrap().as_ref(), Some(&first));
        // The same settings, however spelt, are welcome again: 100 epochs is a GPU's default.
        state.claim(&first).unwrap();
        let gpu_default = with(&[("nglod", nglod(None, false))], 1000);
        let explicit = with(&[("nglod", nglod(Some(100), false))], 1000);
        assert!(gpu_default.differences(&explicit).is_empty());
        // Other settings are refused with what differs, and the record stays.
        for (other, says) in [
            (
                with(&[("nglod", nglod(Some(30), false))], 1000),
                "nglod epochs 30, not 12",
            ),
            (
                with(&[("nglod", nglod(Some(12), false))], 999),
                "eval points 999, not 1000",
            ),
            (gpu_default, "nglod epochs 100, not 12"),
            (
                with(&[("nglod", nglod(None, true))], 1000),
                "nglod epochs about 55 s of training (12 to 100), not 12",
            ),
        ] {
            let e = state.claim(&other).unwrap_err();
            assert!(matches!(&e, CorpusError::OtherSettings { .. }), "{e}");
            assert!(e.to_string().contains(says), "{e}");
        }
        assert_eq!(state.read_settings().unwrap().as_ref(), Some(&first));
        // A model the record lacks is added to it; the merged table states each model's.
        let siren_settings = siren.settings(true).unwrap();
        state
            .claim(&with(&[("siren", siren_settings.clone())], 1000))
            .unwrap();
        let both = with(
            &[("nglod", nglod(Some(12), false)), ("siren", siren_settings)],
            1000,
        );
        assert_eq!(state.read_settings().unwrap().as_ref(), Some(&both));
        let table = merge(&state, &[], &[ModelKind::Siren]).settings.unwrap();
        assert_eq!(table.as_ref(), Some(&both));
        // An unreadable record stops every run instead of being replaced.
        std::fs::write(state.settings_path(), "{\"eval_poi").unwrap();
        let e = state.claim(&first).unwrap_err();
        assert!(matches!(e, CorpusError::BadSettings { .. }), "{e}");
        assert!(merge(&state, &[], &[ModelKind::Nglod]).settings.is_err());
        std::fs::remove_dir_all(&root).unwrap();
    }
}
