//! Shards: which meshes of a corpus one task takes, by a hash of their relative paths that never
//! changes, from `--shard K/N` or the variables a job engine (Slurm, Kubernetes) sets.

use super::{CorpusError, CorpusMesh};

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
            let (stated, max) = (num("SLURM_ARRAY_TASK_COUNT")?, num("SLURM_ARRAY_TASK_MAX")?);
            let spanned = max
                .filter(|&max| max >= min)
                .map(|max| (max - min) / step + 1);
            // The array must be the whole run: a task resubmitted alone (`--array=17`: one task,
            // its own min) or a partial list (`--array=3,5`: two tasks spanning three) would
            // read as a smaller run and take meshes of other shards.
            let partial = match (stated, spanned) {
                (Some(c), Some(s)) => c != s || (c == 1 && id != 0),
                (Some(1), None) => id != 0,
                _ => false,
            };
            if partial {
                return Err(CorpusError::BadShard {
                    value: format!(
                        "task {id} of an array of {} (min {min}, max {}, step {step})",
                        stated.map_or("?".into(), |c| c.to_string()),
                        max.map_or("?".into(), |m| m.to_string())
                    ),
                    source_name: "SLURM_ARRAY_TASK_ID".into(),
                    reason: "the array is not the whole run (a task resubmitted alone or a \
                             partial list): set HWSDF_SHARDS or pass --shards with the run's \
                             shard count, and the task id is taken as the shard index"
                        .into(),
                });
            }
            let count = match (stated, spanned) {
                (Some(c), _) => c,
                (None, Some(s)) => s,
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeSet;
    use std::path::Path;

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
            // Without a stated count, a task resubmitted alone (`--array=17`) or a partial
            // list (`--array=3,5`) would read as a run of 1 or 2 shards: every mesh, or half.
            (
                vec![
                    ("SLURM_ARRAY_TASK_ID", "17"),
                    ("SLURM_ARRAY_TASK_COUNT", "1"),
                    ("SLURM_ARRAY_TASK_MIN", "17"),
                    ("SLURM_ARRAY_TASK_MAX", "17"),
                ],
                "not the whole run",
            ),
            (
                vec![
                    ("SLURM_ARRAY_TASK_ID", "3"),
                    ("SLURM_ARRAY_TASK_COUNT", "2"),
                    ("SLURM_ARRAY_TASK_MIN", "3"),
                    ("SLURM_ARRAY_TASK_MAX", "5"),
                ],
                "HWSDF_SHARDS",
            ),
        ] {
            let e = Shard::from_env(env(&vars), None).unwrap_err().to_string();
            assert!(e.contains(needle), "{vars:?}: {e}");
        }
    }
}
