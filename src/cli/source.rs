//! What `render`, `extract` and `query` draw from: one trained model, or a scene of models and
//! primitives (`--scene S.toml`), and the level `c` they draw at.

use std::path::{Path, PathBuf};

use glam::DVec3;
use sdf_nn::serve::scene::Scene;
use sdf_nn::{NeuralSdf, Normalization};

/// The positional model and `--scene`: exactly one of them.
#[derive(clap::Args, Clone, Debug, Default)]
#[group(required = true, multiple = false)]
pub struct SourceFlags {
    /// Model file written by `train` (.safetensors).
    #[arg(value_name = "MODEL")]
    pub model: Option<PathBuf>,
    /// A scene file (TOML): models placed and combined with primitives (docs/scenes.md).
    #[arg(long, value_name = "S.toml")]
    pub scene: Option<PathBuf>,
}

/// A loaded model or scene.
#[derive(Debug)]
pub enum Source {
    /// One trained model.
    Model(Box<NeuralSdf>),
    /// A scene.
    Scene(Scene),
}

impl SourceFlags {
    /// The input file (for `check_outputs`).
    pub fn path(&self) -> &Path {
        self.model
            .as_deref()
            .or(self.scene.as_deref())
            .expect("clap requires one of them")
    }

    /// [`sdf_geom::io::check_outputs`] of `outputs` against every input: the model, or the
    /// scene file and the model files it names (an output must not replace a scene's model
    /// either), and `more` (a query's points).
    pub fn check_outputs(
        &self,
        more: &[&Path],
        outputs: &[&Path],
    ) -> Result<(), sdf_geom::io::OutputPathError> {
        let models = self
            .scene
            .as_ref()
            .map_or_else(Vec::new, Scene::model_paths);
        let mut inputs = vec![self.path()];
        inputs.extend(models.iter().map(PathBuf::as_path));
        inputs.extend(more);
        sdf_geom::io::check_outputs(&inputs, outputs)
    }

    /// Loads the model or the scene (and the models it names).
    pub fn load(&self) -> Result<Source, String> {
        match (&self.model, &self.scene) {
            (Some(model), _) => NeuralSdf::load(model)
                .map(|m| Source::Model(Box::new(m)))
                .map_err(|e| format!("cannot load the model {}: {e}", model.display())),
            (None, Some(scene)) => Scene::load(scene)
                .map(Source::Scene)
                .map_err(|e| format!("scene {}: {e}", scene.display())),
            (None, None) => Err("give a model file or --scene S.toml".into()),
        }
    }
}

impl Source {
    /// The box drawn from: a model's normalised cube (mesh coordinates), a scene's
    /// [`Scene::frame`] at level 0.
    pub fn frame(&self) -> Normalization {
        match self {
            Source::Model(m) => m.normalization(),
            Source::Scene(s) => s.frame(0.0),
        }
    }

    /// The source in coordinates relative to a model's centre where the model lies far from
    /// the origin for its size ([`Normalization::is_far`]: a mesh trained from georeferenced or
    /// CAD coordinates), and that centre; else the source as it is and zero. Queried, traced
    /// and extracted in f32 at 10⁷ a model would collapse onto a one-unit grid; relative to
    /// its centre it keeps its shape, and outputs in mesh coordinates add the centre back in
    /// f64. A scene's coordinates are its own (f32 placements): it stays as it is. Call it on a
    /// source just loaded: a recentred model keeps its level of detail, not other settings
    /// (SIREN kernels).
    pub fn recentred(self) -> Result<(Source, DVec3), String> {
        match self {
            Source::Model(m) if m.normalization().is_far() => {
                let (normalization, centre) = m.normalization().recentred();
                let mut file = m.model_file().clone();
                file.metadata.normalization = normalization;
                let mut moved = NeuralSdf::from_model_file(file).map_err(|e| e.to_string())?;
                moved.set_lod(m.lod()).map_err(|e| e.to_string())?;
                Ok((Source::Model(Box::new(moved)), centre))
            }
            other => Ok((other, DVec3::ZERO)),
        }
    }

    /// A model as a scene of one leaf, a scene as it is: the queries of rays and closest
    /// points are the scene's.
    pub fn into_scene(self) -> Result<Scene, String> {
        match self {
            Source::Scene(s) => Ok(s),
            Source::Model(m) => Scene::new(sdf_nn::serve::scene::SceneNode::model(
                std::sync::Arc::new(*m),
                sdf_nn::serve::scene::Transform::IDENTITY,
            ))
            .map_err(|e| e.to_string()),
        }
    }
}

/// Checks `--level c` against the box it is drawn in: `|c|` below the box's half side, since
/// beyond it the level set leaves the box a model was trained in (and outside a model's box its
/// distance is only the box's). `what` names the box ("the model's", "the scene's").
///
/// ```
/// use hwsdf::nn::Normalization;
/// let frame = Normalization { center: glam::DVec3::ZERO, scale: 0.5 }; // half side 2
/// assert!(hwsdf::cli::check_level(1.5, frame, "the model's").is_ok());
/// assert!(hwsdf::cli::check_level(-2.5, frame, "the model's").is_err());
/// ```
pub fn check_level(level: f32, frame: Normalization, what: &str) -> Result<(), String> {
    let half = 1.0 / frame.scale;
    if !level.is_finite() {
        return Err(format!("--level {level} is not finite"));
    }
    if level.abs() >= half {
        return Err(format!(
            "--level {level} is beyond {what} box (half side {half} units around {}): the level \
             set would leave the box; use |c| < {half}",
            frame.center
        ));
    }
    Ok(())
}
