//! Checkpoints: what an interrupted run saves besides the weights, and how it resumes.

use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use super::NglodTrainer;
use crate::nglod::NglodError;

impl NglodTrainer<'_> {
    /// The optimiser's moments and step counter.
    pub fn optimizer_state(&self) -> Result<crate::AdamState, NglodError> {
        Ok(self.adam.export_state(self.gpu)?)
    }

    /// Continues a run: restores the optimiser state and the progress: `epochs_done` whole
    /// epochs plus `epoch_steps_done` steps of the next one, which [`NglodTrainer::train`]
    /// finishes first, drawing the same points in the same order (each epoch's points are
    /// rebuilt from the seed and the epoch). The weights come with the [`crate::Nglod`] the trainer was
    /// built from.
    pub fn resume(
        &mut self,
        state: &crate::AdamState,
        epochs_done: usize,
        epoch_steps_done: usize,
    ) -> Result<(), NglodError> {
        let n = self.config.points_per_epoch() as u32;
        let steps_per_epoch = n.div_ceil(self.config.batch_size.min(n)) as usize;
        if epoch_steps_done >= steps_per_epoch {
            return Err(NglodError::InvalidConfig(format!(
                "{epoch_steps_done} steps done within an epoch of {steps_per_epoch} steps"
            )));
        }
        self.adam.import_state(self.gpu, state)?;
        self.epochs_done = epochs_done;
        self.epoch_steps_done = epoch_steps_done;
        self.steps_done = state.step as usize;
        Ok(())
    }

    /// A flag polled at every loss read-back: once set, training stops as `max_seconds` does
    /// (the epoch in progress stays unfinished: see [`NglodTrainer::epoch_steps_done`]), e.g. on
    /// Ctrl-C.
    pub fn set_stop_flag(&mut self, flag: Arc<AtomicBool>) {
        self.stop = Some(flag);
    }

    /// Whole epochs done so far.
    pub fn epochs_done(&self) -> usize {
        self.epochs_done
    }

    /// Steps done within the unfinished epoch `epochs_done()` (0 unless stopped part-way).
    pub fn epoch_steps_done(&self) -> usize {
        self.epoch_steps_done
    }
}
