//! What the control task reports, as small records through a lock-free queue: the control task
//! never formats or logs (defmt's RTT logger masks interrupts while it writes, and a slow probe
//! must never stretch a tick); the `logger` software task (priority 1) does the logging.

use core::sync::atomic::{AtomicU32, Ordering};

use heapless::spsc;

use crate::doorbell::Doorbell;
use crate::drive::{Faults, Telemetry};

/// Queue slots (one stays free): records are rare (a busy tick queues up to 4), and the logger
/// runs within a tick or two unless `link` is decoding a calibration; drops are counted.
pub const CAPACITY: usize = 8;
/// Ticks between two trace records (10 Hz at 2 kHz); `trace` level only.
pub const TRACE_EVERY: u16 = 200;

/// Records dropped because the queue was full (the logger reports the count).
static DROPPED: AtomicU32 = AtomicU32::new(0);
/// Rung by the control task after a push.
pub static BELL: Doorbell = Doorbell::new();

/// The queue's storage (in `init`'s locals) and its two ends.
pub type Queue = spsc::Queue<Event, CAPACITY>;
pub type Producer = spsc::Producer<'static, Event>;
pub type Consumer = spsc::Consumer<'static, Event>;

/// One thing the control task saw.
#[derive(Clone, Copy)]
pub enum Event {
    MoveStart {
        tick: u32,
        motor_counts: i32,
    },
    MoveEnd {
        tick: u32,
        motor_counts: i32,
        following_error_counts: i32,
    },
    /// Fault bits newly set this tick.
    FaultRaised {
        tick: u32,
        motor_counts: i32,
        new: u16,
    },
    FaultsCleared {
        tick: u32,
    },
    /// Late or skipped ticks found at a tick's entry, or an overrun at its end.
    Deadline {
        tick: u32,
        latency_us: u16,
        missed: u32,
        overrun: bool,
        total: u32,
    },
    /// The host enabled the drive but the board refuses its current limit.
    EnableRefused {
        tick: u32,
    },
    /// Decimated per-tick values (I16F16 bits for the current).
    Trace {
        tick: u32,
        motor_counts: i32,
        setpoint_counts: i32,
        current_bits: i32,
    },
}

/// Queues a record (never blocks: a full queue drops it and counts) and wakes the logger. Not
/// inlined: one copy of the queue's enqueue for every kind of record (flash).
#[inline(never)]
pub fn push(p: &mut Producer, e: Event) {
    if p.enqueue(e).is_err() {
        DROPPED.fetch_add(1, Ordering::Relaxed);
    }
    BELL.ring();
}

/// Records for the changes between two ticks' telemetry: move start/end, faults raised and
/// cleared.
#[inline]
pub fn transitions(p: &mut Producer, prev: &Telemetry, t: &Telemetry) {
    if t.moving != prev.moving {
        push(
            p,
            if t.moving {
                Event::MoveStart {
                    tick: t.tick,
                    motor_counts: t.motor_counts.0,
                }
            } else {
                Event::MoveEnd {
                    tick: t.tick,
                    motor_counts: t.motor_counts.0,
                    following_error_counts: t.following_error_counts.0,
                }
            },
        );
    }
    if t.faults != prev.faults {
        let (now, before) = (bits(t.faults), bits(prev.faults));
        if now & !before != 0 {
            push(
                p,
                Event::FaultRaised {
                    tick: t.tick,
                    motor_counts: t.motor_counts.0,
                    new: now & !before,
                },
            );
        } else if now == 0 {
            push(p, Event::FaultsCleared { tick: t.tick });
        }
    }
}

#[inline(always)]
fn bits(f: Faults) -> u16 {
    f.0
}

/// Logs every set bit of `set` by name (never as a number), one line each.
fn log_fault_names(set: u16, tick: u32, motor_counts: i32) {
    for i in 0..16 {
        let bit = 1u16 << i;
        if set & bit != 0 {
            defmt::error!(
                "fault raised: {=str} at {=i32} counts (tick {=u32}): amplifier off, zero current",
                Faults::name(bit),
                motor_counts,
                tick
            );
        }
    }
}

/// Logs everything queued, then the drop count if any. Runs in the `logger` task.
pub fn drain(c: &mut Consumer) {
    while let Some(e) = c.dequeue() {
        log(&e);
    }
    let dropped = DROPPED.swap(0, Ordering::Relaxed);
    if dropped != 0 {
        defmt::warn!("{=u32} control events dropped (log queue full)", dropped);
    }
}

fn log(e: &Event) {
    match *e {
        Event::MoveStart { tick, motor_counts } => {
            defmt::info!("move start at {=i32} counts (tick {=u32})", motor_counts, tick)
        }
        Event::MoveEnd {
            tick,
            motor_counts,
            following_error_counts,
        } => defmt::info!(
            "move end at {=i32} counts, following error {=i32} counts (tick {=u32})",
            motor_counts,
            following_error_counts,
            tick
        ),
        Event::FaultRaised {
            tick,
            motor_counts,
            new,
        } => log_fault_names(new, tick, motor_counts),
        Event::FaultsCleared { tick } => defmt::info!("faults cleared (tick {=u32})", tick),
        Event::Deadline {
            tick,
            latency_us,
            missed,
            overrun,
            total,
        } => defmt::error!(
            "control deadline missed at tick {=u32}: entry {=u16} us late, {=u32} ticks skipped, overrun {=bool} ({=u32} so far)",
            tick,
            latency_us,
            missed,
            overrun,
            total
        ),
        Event::EnableRefused { tick } => defmt::error!(
            "enable refused (tick {=u32}): the drive's current limit exceeds the amplifier's linear range",
            tick
        ),
        Event::Trace {
            tick,
            motor_counts,
            setpoint_counts,
            current_bits,
        } => defmt::trace!(
            "tick {=u32}: x_PE {=i32} set {=i32} I {=i32} (I16F16 bits)",
            tick,
            motor_counts,
            setpoint_counts,
            current_bits
        ),
    }
}
