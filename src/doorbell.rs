//! Wakes an async software task from an interrupt without losing a ring.
//!
//! RTIC 2's `spawn()` fails while the task is still running, so an interrupt that spawns on
//! every byte could lose the last wake-up (the task has seen an empty queue but not yet
//! returned). Instead the task runs forever and awaits this bell between batches: a ring that
//! lands at any point, even just before the task registers, is kept in `rung`.

use core::future::poll_fn;
use core::sync::atomic::{AtomicBool, Ordering};
use core::task::Poll;

use rtic_common::waker_registration::CriticalSectionWakerRegistration;

/// A one-bit "something is waiting" flag with a waker.
pub struct Doorbell {
    rung: AtomicBool,
    waker: CriticalSectionWakerRegistration,
}

impl Doorbell {
    /// A bell that has not rung.
    pub const fn new() -> Self {
        Doorbell {
            rung: AtomicBool::new(false),
            waker: CriticalSectionWakerRegistration::new(),
        }
    }

    /// Rings (any context): the waiting task runs when its priority allows. Not inlined: the
    /// waker's critical section once, not at every ring (flash).
    #[inline(never)]
    pub fn ring(&self) {
        self.rung.store(true, Ordering::Release);
        self.waker.wake();
    }

    /// Waits for the next ring (or returns at once if it rang since the last wait).
    pub async fn wait(&self) {
        poll_fn(|cx| {
            if self.rung.swap(false, Ordering::Acquire) {
                return Poll::Ready(());
            }
            self.waker.register(cx.waker());
            // A ring between the check above and the registration is not lost.
            if self.rung.swap(false, Ordering::Acquire) {
                Poll::Ready(())
            } else {
                Poll::Pending
            }
        })
        .await
    }
}

impl Default for Doorbell {
    fn default() -> Self {
        Self::new()
    }
}
