//! belt-drive firmware support (knurling app-template style): the global defmt logger, the panic
//! and HardFault behaviour, `exit()`, and the two boards under [`hardware`].
//!
//! Binaries and on-target tests start with `use belt_drive as _;` so that all of this is linked.
//!
//! | build                | board                | logger            | panic / HardFault           |
//! |----------------------|----------------------|-------------------|-----------------------------|
//! | default (or `board`) | STM32F405 controller | defmt over RTT    | motor off, record, log, halt; the IWDG resets |
//! | `--features qemu`    | QEMU netduinoplus2   | defmt-semihosting | semihosting exit 101 / 102 / 103 |
//!
//! Panic, HardFault and an unexpected interrupt all do the same, in this order: motor off
//! (enable low, zero current) first, then a record in `.uninit` RAM ([`postmortem`]), then the
//! log line, then the halt. On the real board the independent watchdog then resets the halted
//! chip into its safe state, and the next boot logs the record.
//!
//! On the host this crate is empty: the firmware only builds for `thumbv7em-none-eabihf`.
#![no_std]

#[cfg(all(feature = "qemu", feature = "board"))]
compile_error!(
    "features `qemu` and `board` both enabled: they select different boards and defmt back-ends \
     (semihosting vs RTT), and only one global logger can be linked"
);

/// QEMU exit status of a panic.
pub const EXIT_PANIC: i32 = 101;
/// QEMU exit status of a HardFault.
pub const EXIT_HARDFAULT: i32 = 102;
/// QEMU exit status of an unexpected interrupt.
pub const EXIT_UNEXPECTED_IRQ: i32 = 103;

#[cfg(target_os = "none")]
pub mod doorbell;
#[cfg(target_os = "none")]
pub mod events;
#[cfg(target_os = "none")]
pub mod hardware;
#[cfg(target_os = "none")]
pub mod outbox;
pub mod persist;
#[cfg(target_os = "none")]
pub mod postmortem;
#[cfg(target_os = "none")]
pub mod stack;

pub use estimator_core::drive;

#[cfg(target_os = "none")]
mod runtime {
    // Exactly one global logger: the cfgs are exclusive.
    #[cfg(not(feature = "qemu"))]
    use defmt_rtt as _;
    #[cfg(feature = "qemu")]
    use defmt_semihosting as _;

    use core::sync::atomic::{AtomicBool, Ordering};

    static PANICKED: AtomicBool = AtomicBool::new(false);

    #[panic_handler]
    fn panic(info: &core::panic::PanicInfo) -> ! {
        cortex_m::interrupt::disable();
        // The motor first: nothing below may run with current flowing.
        crate::hardware::emergency_stop();
        // A panic while logging a panic must not recurse.
        if !PANICKED.swap(true, Ordering::Relaxed) {
            // The location only: the message would pull in `core::fmt` (several KiB of flash).
            let (file, line) = info.location().map_or(("?", 0), |l| (l.file(), l.line()));
            crate::postmortem::record_panic(file, line);
            defmt::error!("panic at {=str}:{=u32}", file, line);
        }
        crate::hardware::halt(crate::EXIT_PANIC)
    }

    #[cortex_m_rt::exception]
    unsafe fn HardFault(frame: &cortex_m_rt::ExceptionFrame) -> ! {
        crate::hardware::emergency_stop();
        crate::postmortem::record_hardfault(frame.pc());
        defmt::error!(
            "HardFault at pc={=u32:#010x} lr={=u32:#010x}",
            frame.pc(),
            frame.lr()
        );
        crate::hardware::halt(crate::EXIT_HARDFAULT)
    }

    /// An interrupt that nothing handles: with no handler it would loop here for good with
    /// whatever current was last written.
    #[cortex_m_rt::exception]
    unsafe fn DefaultHandler(irqn: i16) -> ! {
        cortex_m::interrupt::disable();
        crate::hardware::emergency_stop();
        crate::postmortem::record_interrupt(irqn);
        defmt::error!("unexpected interrupt {=i16}: motor off, halted", irqn);
        crate::hardware::halt(crate::EXIT_UNEXPECTED_IRQ)
    }

    // The board: milliseconds since boot. QEMU: plant time (control ticks over the rate).
    #[cfg(not(feature = "qemu"))]
    defmt::timestamp!("{=u32:ms}", crate::hardware::timestamp_ms());
    #[cfg(feature = "qemu")]
    defmt::timestamp!("{=u64:us}", crate::hardware::timestamp_us());
}

/// Ends the program successfully: QEMU exits with status 0; the real board halts with the motor
/// off (there is nothing to return to) until the watchdog resets it.
#[cfg(target_os = "none")]
pub fn exit() -> ! {
    hardware::emergency_stop();
    hardware::halt(0)
}
