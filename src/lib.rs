//! belt-drive firmware support (knurling app-template style): the global defmt logger, the panic
//! and HardFault behaviour, `exit()`, and the two boards under [`hardware`].
//!
//! Binaries and on-target tests start with `use belt_drive as _;` so that all of this is linked.
//!
//! | build                | board                | logger            | panic / HardFault           |
//! |----------------------|----------------------|-------------------|-----------------------------|
//! | default (or `board`) | STM32F405 controller | defmt over RTT    | motor current zero, halt    |
//! | `--features qemu`    | QEMU netduinoplus2   | defmt-semihosting | semihosting exit 101 / 102  |
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

#[cfg(target_os = "none")]
pub mod hardware;
#[cfg(target_os = "none")]
pub mod outbox;
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
            match info.location() {
                Some(l) => defmt::error!("panic at {=str}:{=u32}", l.file(), l.line()),
                None => defmt::error!("panic"),
            }
        }
        crate::hardware::halt(crate::EXIT_PANIC)
    }

    #[cortex_m_rt::exception]
    unsafe fn HardFault(frame: &cortex_m_rt::ExceptionFrame) -> ! {
        crate::hardware::emergency_stop();
        defmt::error!(
            "HardFault at pc={=u32:#010x} lr={=u32:#010x}",
            frame.pc(),
            frame.lr()
        );
        crate::hardware::halt(crate::EXIT_HARDFAULT)
    }

    defmt::timestamp!("{=u32:ms}", crate::hardware::timestamp_ms());
}

/// Ends the program successfully: QEMU exits with status 0; the real board halts with the motor
/// at zero current (there is nothing to return to).
#[cfg(target_os = "none")]
pub fn exit() -> ! {
    hardware::emergency_stop();
    hardware::halt(0)
}
