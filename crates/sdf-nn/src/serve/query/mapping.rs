//! The state of a buffer's mapping, shared with wgpu's map callback.

use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

/// The state of the staging buffer's mapping.
#[derive(Debug, Default)]
pub(super) enum MapState {
    /// Not mapped, nothing in flight.
    #[default]
    Idle,
    /// `map_async` was called; its callback has not run yet.
    Pending,
    /// Mapped and readable.
    Mapped,
    /// The mapping failed.
    Failed(String),
}

/// The staging buffer's [`MapState`], and a condition variable its `map_async` callback
/// notifies: the callback may run on another thread's `poll` after ours has returned (devices
/// are shared), so a waiter waits for the callback itself, not only for the submission.
#[derive(Debug, Default)]
pub(super) struct MapSlot {
    state: Mutex<MapState>,
    changed: Condvar,
}

impl MapSlot {
    pub(super) fn lock(&self) -> MutexGuard<'_, MapState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    pub(super) fn set(&self, state: MapState) {
        *self.lock() = state;
        self.changed.notify_all();
    }

    /// Whether the requested mapping's callback has not run yet.
    pub(super) fn is_pending(&self) -> bool {
        matches!(*self.lock(), MapState::Pending)
    }

    /// Asks for `slice` to be mapped for `mode`, the callback settling this slot.
    pub(super) fn request(self: &Arc<Self>, slice: wgpu::BufferSlice<'_>, mode: wgpu::MapMode) {
        self.set(MapState::Pending);
        let map = Arc::clone(self);
        slice.map_async(mode, move |r| {
            map.set(match r {
                Ok(()) => MapState::Mapped,
                Err(e) => MapState::Failed(e.to_string()),
            });
        });
    }

    /// Waits (up to 10 s, polling `device`) for the requested mapping: `Ok` once mapped, the
    /// reason otherwise. The slot is left idle.
    pub(super) fn settle(&self, device: &wgpu::Device) -> Result<(), String> {
        match self.take_settled(device, Duration::from_secs(10)) {
            MapState::Mapped => Ok(()),
            MapState::Failed(reason) => Err(reason),
            MapState::Idle | MapState::Pending => Err("the mapping did not complete".into()),
        }
    }

    /// Takes the state once it is no longer [`MapState::Pending`], polling `device` between
    /// waits; [`MapState::Pending`] if that takes longer than `timeout`.
    pub(super) fn take_settled(&self, device: &wgpu::Device, timeout: Duration) -> MapState {
        let deadline = Instant::now() + timeout;
        let mut state = self.lock();
        while matches!(*state, MapState::Pending) {
            let now = Instant::now();
            if now >= deadline {
                break;
            }
            drop(state);
            let _ = device.poll(wgpu::PollType::Poll);
            state = self.lock();
            if matches!(*state, MapState::Pending) {
                let wait = (deadline - now).min(Duration::from_millis(1));
                state = self
                    .changed
                    .wait_timeout(state, wait)
                    .unwrap_or_else(|e| e.into_inner())
                    .0;
            }
        }
        std::mem::take(&mut *state)
    }
}
