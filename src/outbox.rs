//! Outgoing link frames: a byte ring drained by the USART's TXE interrupt, so that no task ever
//! waits for the wire (at 460800 baud a telemetry frame takes about 1 ms to send).

use belt_link::{encode, Message, MAX_FRAME};

use crate::hardware::LinkTx;

/// Ring size: several replies plus a telemetry frame.
const CAPACITY: usize = 512;

/// The link's transmit queue and the USART's transmit half.
pub struct Outbox {
    tx: LinkTx,
    ring: [u8; CAPACITY],
    head: usize,
    len: usize,
    /// Frames dropped because the ring was full.
    pub dropped: u32,
}

impl Outbox {
    /// An empty outbox.
    pub fn new(tx: LinkTx) -> Self {
        Outbox {
            tx,
            ring: [0; CAPACITY],
            head: 0,
            len: 0,
            dropped: 0,
        }
    }

    /// Queues one frame whole, or drops it whole (and counts it) if it does not fit.
    pub fn send<M: Message>(&mut self, seq: u8, msg: &M) -> bool {
        let mut frame = [0u8; MAX_FRAME];
        // `encode` returns at most `MAX_FRAME`; `get` keeps the slice panic (and `core::fmt`)
        // out of the image.
        let n = encode(seq, msg, &mut frame);
        let bytes = frame.get(..n).unwrap_or_default();
        // A link that takes whole frames (QEMU's PIL pipe) gets it at once, in order.
        if self.len == 0 && self.tx.write_frame(bytes) {
            return true;
        }
        if CAPACITY - self.len < n {
            self.dropped = self.dropped.wrapping_add(1);
            return false;
        }
        for &b in bytes {
            self.ring[(self.head + self.len) % CAPACITY] = b;
            self.len += 1;
        }
        // Start at once: the hardware takes a byte now and asks for the rest with TXE
        // interrupts; QEMU (whose USART is synchronous and raises no TXE interrupt) takes all.
        self.tx.set_tx_interrupt(true);
        self.pump();
        true
    }

    /// Moves queued bytes to the USART while it takes them; the TXE interrupt goes off when the
    /// ring is empty.
    pub fn pump(&mut self) {
        while self.len > 0 && self.tx.can_write() {
            // `head < CAPACITY` always; the `%` lets the compiler see it (no panic path).
            self.tx.write(self.ring[self.head % CAPACITY]);
            self.head = (self.head + 1) % CAPACITY;
            self.len -= 1;
        }
        if self.len == 0 {
            self.tx.set_tx_interrupt(false);
        }
    }

    /// Turns the link's receive interrupt on or off (the transmit half owns CR1).
    pub fn set_rx_interrupt(&mut self, on: bool) {
        self.tx.set_rx_interrupt(on);
    }

    /// Sends everything now, waiting for the USART (shutdown only).
    pub fn flush(&mut self) {
        while self.len > 0 {
            self.pump();
        }
    }
}
