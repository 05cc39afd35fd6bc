//! [`PendingRead`]: a small read-back that waits only for the submission that holds its copy,
//! so that the host records and submits the next work before it waits, and the GPU does not
//! sit idle while the host records (a training loop's loss, read every few steps).

use std::sync::mpsc;

use bytemuck::Pod;

use super::{GpuContext, GpuError, copy_out_mapped};

/// A copy of a few bytes of a buffer, recorded into an encoder ([`GpuContext::record_read`])
/// and not yet submitted.
#[derive(Debug)]
pub(crate) struct ReadCopy {
    staging: wgpu::Buffer,
    label: String,
}

/// A [`ReadCopy`] whose submission is under way ([`GpuContext::submit_with_read`]).
#[derive(Debug)]
pub(crate) struct PendingRead {
    staging: wgpu::Buffer,
    label: String,
    submission: wgpu::SubmissionIndex,
    mapped: mpsc::Receiver<Result<(), wgpu::BufferAsyncError>>,
}

impl GpuContext {
    /// Records into `enc` a copy of `bytes` bytes of `buffer` from `offset` (both multiples
    /// of 4), to be read once the encoder's submission is done.
    pub(crate) fn record_read(
        &self,
        enc: &mut wgpu::CommandEncoder,
        buffer: &wgpu::Buffer,
        offset: u64,
        bytes: u64,
    ) -> ReadCopy {
        let staging = self.device().create_buffer(&wgpu::BufferDescriptor {
            label: Some("pending read staging"),
            size: bytes.max(4),
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        enc.copy_buffer_to_buffer(buffer, offset, &staging, 0, bytes);
        ReadCopy {
            staging,
            label: format!("{buffer:?}"),
        }
    }

    /// Submits `enc`, which holds `read`'s copy, and returns the read, to be waited for after
    /// the host has submitted more work.
    pub(crate) fn submit_with_read(
        &self,
        enc: wgpu::CommandEncoder,
        read: ReadCopy,
    ) -> PendingRead {
        let submission = self.queue().submit([enc.finish()]);
        let (tx, mapped) = mpsc::channel();
        read.staging
            .slice(..)
            .map_async(wgpu::MapMode::Read, move |r| {
                let _ = tx.send(r);
            });
        PendingRead {
            staging: read.staging,
            label: read.label,
            submission,
            mapped,
        }
    }
}

impl PendingRead {
    /// Waits for the read's submission (not for any submitted after it) and returns the bytes
    /// as `T`s.
    pub(crate) fn wait<T: Pod>(self, gpu: &GpuContext) -> Result<Vec<T>, GpuError> {
        let error = |reason: String| GpuError::Readback {
            label: self.label.clone(),
            reason,
        };
        let mut result = None;
        let spun = gpu
            .spin_until(|_| {
                result = self.mapped.try_recv().ok();
                result.is_some()
            })
            .map_err(|e| error(e.to_string()))?;
        if !spun {
            gpu.device()
                .poll(wgpu::PollType::Wait {
                    submission_index: Some(self.submission.clone()),
                    timeout: None,
                })
                .map_err(|e| error(e.to_string()))?;
            result = Some(self.mapped.recv().map_err(|e| error(e.to_string()))?);
        }
        if let Some(Err(e)) = result {
            return Err(error(e.to_string()));
        }
        copy_out_mapped(&self.staging, &self.label)
    }
}

#[cfg(test)]
mod tests {
    use crate::GpuContext;

    /// A read waited for after a later submission has overwritten its buffer returns the value
    /// of its own submission.
    #[test]
    fn a_pending_read_sees_its_own_submission() {
        let gpu = GpuContext::shared().expect("a GPU adapter (lavapipe in CI)");
        let buffer = gpu.storage_from_slice("value", &[1.0f32, 2.0]).unwrap();
        let mut enc = gpu.device().create_command_encoder(&Default::default());
        let copy = gpu.record_read(&mut enc, &buffer, 4, 4);
        enc.clear_buffer(&buffer, 0, None);
        let pending = gpu.submit_with_read(enc, copy);
        gpu.write(&buffer, &[3.0f32, 4.0]).unwrap();
        let later = gpu.device().create_command_encoder(&Default::default());
        gpu.queue().submit([later.finish()]);
        assert_eq!(pending.wait::<f32>(gpu).unwrap(), vec![2.0]);
        assert_eq!(gpu.read_back::<f32>(&buffer).unwrap(), vec![3.0, 4.0]);
    }
}
