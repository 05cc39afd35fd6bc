//! The results folder `<out>.d/` every shard shares: the settings it was made with, one result
//! file (and model, and checkpoint) per mesh and model under a name no other pair shares, each
//! written atomically.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::{CorpusError, CorpusMesh, stable_hash};
use crate::run::{ModelKind, Report, RunSettings};

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
        /// `"siren"`, `"nglod"` or `"hashgrid"`.
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
    /// A file that could not be read (permissions, a network file system's error): left out
    /// of the table and not redone, since the result may be there.
    Unreadable(String),
}

/// A settings record at `path`, if there is one.
fn read_settings_file(path: PathBuf) -> Result<Option<CorpusSettings>, CorpusError> {
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

/// The folder of per-mesh results, `<out>.d/`, shared by every shard.
#[derive(Clone, Debug)]
pub struct StateDir {
    dir: PathBuf,
    /// The meshes whose short name another mesh of the corpus shares: they are named by a
    /// 64-bit hash instead ([`StateDir::stem`]).
    long_names: BTreeSet<String>,
}

impl StateDir {
    /// The folder that belongs to the table `out`, for the corpus `meshes` (the whole corpus,
    /// not one shard's part: every shard must name a mesh alike). A name ends in a 32-bit hash
    /// of the relative path where the path is not a plain file name; the few meshes whose
    /// names would still coincide (a chance of about 26 % at 51 000 paths that share their
    /// last 80 characters) are found here and named by a 64-bit hash, so that no two meshes
    /// ever share a result, while every other name stays what earlier versions wrote.
    pub fn for_table(out: &Path, meshes: &[CorpusMesh]) -> Self {
        let mut by_name: BTreeMap<String, Vec<&str>> = BTreeMap::new();
        for m in meshes {
            by_name
                .entry(Self::base(&m.rel, false))
                .or_default()
                .push(&m.rel);
        }
        let long_names = by_name
            .into_values()
            .filter(|rels| rels.len() > 1)
            .flatten()
            .map(str::to_owned)
            .collect();
        StateDir {
            dir: PathBuf::from(format!("{}.d", out.display())),
            long_names,
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

    /// The stem of every file of `rel` × `model`: the relative path itself where it is a
    /// plain file name, otherwise its last 80 characters with unsafe ones replaced and a
    /// 32-bit hash of the whole relative path appended; for a mesh whose name another mesh of
    /// the corpus shares ([`StateDir::for_table`]), a 64-bit hash, so that no two meshes share
    /// a name.
    pub fn stem(&self, rel: &str, model: ModelKind) -> String {
        let base = Self::base(rel, self.long_names.contains(rel));
        format!("{base}.{}", model.name())
    }

    /// The model-independent part of [`StateDir::stem`], with the 64-bit hash if `long`.
    fn base(rel: &str, long: bool) -> String {
        let plain = !long
            && !rel.is_empty()
            && !rel.starts_with('.')
            && rel
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'));
        if plain {
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
            let hash = stable_hash(rel);
            if long {
                format!("{tail}-{hash:016x}")
            } else {
                format!("{tail}-{:08x}", hash as u32)
            }
        }
    }

    /// The record of the settings every result in the folder was made with.
    pub fn settings_path(&self) -> PathBuf {
        self.dir.join("settings.json")
    }

    /// The record of a model that a later run added to the folder: `settings.<model>.json`
    /// (the first run's models are in [`StateDir::settings_path`]).
    fn model_settings_path(&self, model: &str) -> PathBuf {
        self.dir.join(format!("settings.{model}.json"))
    }

    /// The recorded settings, if any run has recorded them yet: the first run's record with
    /// the models later runs added beside it.
    pub fn read_settings(&self) -> Result<Option<CorpusSettings>, CorpusError> {
        let Some(mut settings) = read_settings_file(self.settings_path())? else {
            return Ok(None);
        };
        for model in ModelKind::ALL.map(ModelKind::name) {
            if settings.models.contains_key(model) {
                continue;
            }
            if let Some(added) = read_settings_file(self.model_settings_path(model))? {
                settings.models.extend(added.models);
            }
        }
        Ok(Some(settings))
    }

    /// Records `settings` as the folder's, or checks them against those recorded: any
    /// difference is [`CorpusError::OtherSettings`]. Shards starting together agree on one
    /// record: the first run's is created without ever replacing another's, and the rest are
    /// checked against it. A model the record lacks gets a record of its own, created the same
    /// way, so that runs of different models starting at once never lose one another's (a
    /// shared record rewritten by each lost one now and then). A folder from before the
    /// record existed takes the first settings claimed.
    pub fn claim(&self, settings: &CorpusSettings) -> Result<(), CorpusError> {
        let json = |s: &CorpusSettings| serde_json::to_vec_pretty(s).expect("settings serialise");
        let path = self.settings_path();
        match sdf_geom::io::create_atomic(&path, &json(settings)) {
            Ok(()) => return Ok(()),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
            Err(source) => return Err(CorpusError::Io { path, source }),
        }
        let recorded = self.read_settings()?.ok_or_else(|| CorpusError::Io {
            path: path.clone(),
            source: std::io::Error::other("the settings record was removed while being read"),
        })?;
        let conflict = |differences: Vec<String>| CorpusError::OtherSettings {
            dir: self.dir.clone(),
            differences,
        };
        let differences = settings.differences(&recorded);
        if !differences.is_empty() {
            return Err(conflict(differences));
        }
        for (model, s) in &settings.models {
            if recorded.models.contains_key(model) {
                continue;
            }
            let own = CorpusSettings {
                eval_points: settings.eval_points,
                models: [(model.clone(), s.clone())].into(),
            };
            let path = self.model_settings_path(model);
            match sdf_geom::io::create_atomic(&path, &json(&own)) {
                Ok(()) => {}
                // Another run of this model recorded it first: its settings must be these.
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    let theirs = read_settings_file(path)?.unwrap_or_default();
                    let differences = own.differences(&theirs);
                    if !differences.is_empty() {
                        return Err(conflict(differences));
                    }
                }
                Err(source) => return Err(CorpusError::Io { path, source }),
            }
        }
        Ok(())
    }

    /// The result file of `rel` × `model`.
    pub fn record(&self, rel: &str, model: ModelKind) -> PathBuf {
        self.dir.join(format!("{}.json", self.stem(rel, model)))
    }

    /// The model file of `rel` × `model`.
    pub fn model_file(&self, rel: &str, model: ModelKind) -> PathBuf {
        self.dir
            .join(format!("{}.safetensors", self.stem(rel, model)))
    }

    /// The checkpoint an interrupted fit of `rel` × `model` leaves.
    pub fn checkpoint(&self, rel: &str, model: ModelKind) -> PathBuf {
        self.dir
            .join(format!("{}.checkpoint.safetensors", self.stem(rel, model)))
    }

    /// Reads the result of `rel` × `model`.
    pub fn read(&self, rel: &str, model: ModelKind) -> Record {
        let path = self.record(rel, model);
        match std::fs::read(&path) {
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Record::Missing,
            Err(e) => Record::Unreadable(format!("{}: {e}", path.display())),
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::corpus::merge;

    #[test]
    fn a_file_in_the_state_folders_place_is_named() {
        let dir = std::env::temp_dir().join(format!("hwsdf-statefile-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let out = dir.join("r.md");
        std::fs::write(dir.join("r.md.d"), "not a folder").unwrap();
        let e = StateDir::for_table(&out, &[])
            .create()
            .unwrap_err()
            .to_string();
        assert!(e.contains("r.md.d"), "{e}");
        assert!(
            e.contains("a file has the name of the results' state folder"),
            "{e}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
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
        let meshes: Vec<_> = rels.map(|r| CorpusMesh::new(Path::new("c"), r)).to_vec();
        let state = StateDir::for_table(Path::new("r.md"), &meshes);
        let mut stems = BTreeSet::new();
        for rel in rels {
            for model in ModelKind::ALL {
                let stem = state.stem(rel, model);
                assert!(!stem.contains('/') && !stem.starts_with('.'), "{stem}");
                assert!(
                    stems.insert(stem.clone()),
                    "{rel} {model:?} -> {stem} twice"
                );
            }
        }
        // Flat corpora keep the names earlier versions wrote, so old runs resume.
        assert_eq!(state.stem("spot.obj", ModelKind::Nglod), "spot.obj.nglod");
        assert_eq!(
            state.stem("x/a.obj", ModelKind::Nglod),
            "x_a.obj-dd19d684.nglod"
        );
    }

    /// Two paths that share their last 80 characters and their 32-bit hash (found by a
    /// birthday search) are told apart by a 64-bit hash, in every shard; every other mesh of
    /// the corpus keeps its short name.
    #[test]
    fn meshes_whose_short_names_coincide_get_long_ones() {
        let tail =
            "/exports/cad/released/final/assembly-with-a-long-descriptive-name/part-00/model.obj";
        let (a, b) = (format!("batch305081{tail}"), format!("batch951190{tail}"));
        let blind = StateDir::for_table(Path::new("r.md"), &[]);
        assert_eq!(
            blind.stem(&a, ModelKind::Nglod),
            blind.stem(&b, ModelKind::Nglod),
            "not a collision of the short names"
        );
        let meshes: Vec<_> = [a.as_str(), b.as_str(), "x/a.obj"]
            .map(|r| CorpusMesh::new(Path::new("c"), r))
            .to_vec();
        let state = StateDir::for_table(Path::new("r.md"), &meshes);
        let (sa, sb) = (
            state.stem(&a, ModelKind::Nglod),
            state.stem(&b, ModelKind::Nglod),
        );
        assert_ne!(sa, sb);
        for stem in [&sa, &sb] {
            let hash = stem.trim_end_matches(".nglod").rsplit('-').next().unwrap();
            assert_eq!(hash.len(), 16, "{stem}");
        }
        assert_eq!(
            state.record(&a, ModelKind::Siren),
            state
                .path()
                .join(format!("{}.json", state.stem(&a, ModelKind::Siren)))
        );
        assert_ne!(
            state.record(&a, ModelKind::Siren),
            state.record(&b, ModelKind::Siren)
        );
        assert_eq!(
            state.stem("x/a.obj", ModelKind::Nglod),
            blind.stem("x/a.obj", ModelKind::Nglod)
        );
    }

    #[test]
    fn a_results_folder_keeps_one_set_of_settings() {
        use crate::run::{Preset, TrainOptions};
        let root =
            std::env::temp_dir().join(format!("hwsdf-corpus-settings-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let state = StateDir::for_table(&root.join("results.md"), &[]);
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

    /// Runs of different models sharing one folder, started at once (a SIREN array and a
    /// hash-grid array): every model ends up in the record, none replaced by another's
    /// addition.
    #[test]
    fn models_claimed_at_once_are_all_recorded() {
        use crate::run::{Preset, TrainOptions};
        let root = std::env::temp_dir().join(format!("hwsdf-claims-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        for round in 0..4 {
            let state = StateDir::for_table(&root.join(format!("r{round}.md")), &[]);
            state.create().unwrap();
            let claims: Vec<_> = ModelKind::ALL
                .into_iter()
                .map(|model| {
                    let state = state.clone();
                    std::thread::spawn(move || {
                        let options = TrainOptions::new(model, Preset::Small);
                        let settings = CorpusSettings {
                            eval_points: 1000,
                            models: [(model.name().to_owned(), options.settings(true).unwrap())]
                                .into(),
                        };
                        state.claim(&settings)
                    })
                })
                .collect();
            for claim in claims {
                claim.join().unwrap().unwrap();
            }
            let recorded = state.read_settings().unwrap().unwrap();
            let names: Vec<&str> = recorded.models.keys().map(String::as_str).collect();
            assert_eq!(names, ["hashgrid", "nglod", "siren"], "round {round}");
        }
        std::fs::remove_dir_all(&root).unwrap();
    }
}
