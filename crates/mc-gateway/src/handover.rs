//! A hand-over from the threads that produce (the core task, the loggers) to one writer thread
//! that takes everything waiting at once: the log writers and the audit writer. The writer runs on
//! its own period and is never woken per item; once nothing comes it sleeps until the next item,
//! so an idle gateway's writers never wake.

use std::sync::Mutex;
use std::thread::Thread;

use crate::lock;

/// What waits (`B`: the writer's buffer) and the state of both ends, behind one lock.
#[derive(Debug, Default)]
pub(crate) struct Handover<B>(Mutex<Slot<B>>);

#[derive(Debug, Default)]
struct Slot<B> {
    waiting: B,
    /// The writer's thread, known from its first take.
    writer: Option<Thread>,
    /// The writer sleeps until something is put.
    asleep: bool,
    /// The producers' end is gone: the writer takes what is left and stops.
    closed: bool,
    /// The writer's end is gone: nothing is taken any more.
    writer_gone: bool,
}

impl<B> Handover<B> {
    /// Adds to what waits with `put`, which returns its result and whether the writer must take
    /// it now (it is woken then, and whenever it sleeps). `None` once the writer is gone.
    pub fn put<R>(&self, put: impl FnOnce(&mut B) -> (R, bool)) -> Option<R> {
        let mut slot = lock(&self.0);
        if slot.writer_gone {
            return None;
        }
        let (r, urgent) = put(&mut slot.waiting);
        let wake = std::mem::take(&mut slot.asleep) || urgent;
        let writer = if wake { slot.writer.clone() } else { None };
        drop(slot);
        if let Some(writer) = writer {
            writer.unpark();
        }
        Some(r)
    }

    /// Exchanges what waits for `taken` (emptied by the writer); false once closed, and then
    /// everything put before the close is in `taken`. The calling thread is the writer.
    pub fn take(&self, taken: &mut B) -> bool {
        let mut slot = self.writers_slot();
        std::mem::swap(&mut slot.waiting, taken);
        !slot.closed
    }

    /// The writer sleeps until something is put or the producers' end closes, unless something
    /// waits already (`is_empty` says) or it is closed: false when closed.
    pub fn sleep(&self, is_empty: impl FnOnce(&B) -> bool) -> bool {
        {
            let mut slot = self.writers_slot();
            if slot.closed {
                return false;
            }
            if !is_empty(&slot.waiting) {
                return true;
            }
            slot.asleep = true;
        }
        // A put or close between the unlock and here leaves its unpark for this park.
        std::thread::park();
        !lock(&self.0).closed
    }

    /// The slot, locked by the writer: its thread is known from then on, to be woken.
    fn writers_slot(&self) -> std::sync::MutexGuard<'_, Slot<B>> {
        let mut slot = lock(&self.0);
        if slot.writer.is_none() {
            slot.writer = Some(std::thread::current());
        }
        slot
    }

    /// The producers' end is gone: wakes the writer to take what is left.
    pub fn close(&self) {
        let writer = {
            let mut slot = lock(&self.0);
            slot.closed = true;
            slot.writer.clone()
        };
        if let Some(writer) = writer {
            writer.unpark();
        }
    }

    /// The writer's end is gone: later puts are refused.
    pub fn writer_gone(&self) {
        lock(&self.0).writer_gone = true;
    }

    /// Reads what waits.
    #[cfg(test)]
    pub fn with<R>(&self, read: impl FnOnce(&B) -> R) -> R {
        read(&lock(&self.0).waiting)
    }

    /// The writer sleeps until something is put.
    #[cfg(test)]
    pub fn asleep(&self) -> bool {
        lock(&self.0).asleep
    }
}
