//! The two boards the firmware runs on, behind one interface (embassy's driver split).
//!
//! Each board module provides:
//! - `NAME`, `MAX_LINEAR_CURRENT_MA`, `init(device, core, control_rate_hz) -> Board`;
//! - `ControlIo` (owned by the `control` task): `begin_tick()` samples the counters and
//!   measures the tick's lateness (board) or takes the PIL sample (QEMU), `measure()`,
//!   `write_current()` drives the amplifier (board only), `overran()`, `feed_watchdog()` and
//!   `start()` (tick timer and watchdog; board only);
//! - `pil_deliver()` (QEMU: hand a PIL sample to `control`; board: refused), `clock_failed()`,
//! - `LinkRx`, `LinkTx` (the link; board: the USART halves; QEMU: also the PIL pipe) and
//!   `IdleIo` (what `idle` does);
//! - the configuration storage (`estimator_core::storage`'s A/B slots): `StorageFlash` (board:
//!   flash sectors 10-11, `stm32f405/flash.rs`; QEMU: a host file, `qemu_storage.rs`),
//!   `open_storage()` and `during_save(f)` (board: the watchdog lengthened around the erase).
//! - `emergency_stop()`, `halt(code)`; here: `timestamp_ms()` and the link USART halves.
//!
//! The control-tick interrupt is `TIM7` on both: on the board TIM7 (a basic timer) fires at the
//! control rate; under QEMU, whose TIM7 is not modelled, the link task pends it when a PIL sample
//! arrives, so the plant paces the firmware.

pub mod gpio;

#[cfg(not(feature = "qemu"))]
mod stm32f405;
#[cfg(not(feature = "qemu"))]
pub use stm32f405::*;

#[cfg(feature = "qemu")]
mod qemu;
#[cfg(feature = "qemu")]
pub use qemu::*;
/// The configuration storage under QEMU: a host file through semihosting (`--storage PATH`).
#[cfg(feature = "qemu")]
pub mod qemu_storage;
#[cfg(feature = "qemu")]
pub use qemu_storage::{
    during_save, open_staging, open_storage, FileFlash as StorageFlash, FileFlash as StagingFlash,
};

use stm32f4xx_hal::pac;

rtic_monotonics::systick_monotonic!(Mono, 1_000);

/// The link USART's interrupt (the `usart2` task), pended by `link` when it resumes reception.
pub const LINK_INTERRUPT: pac::Interrupt = pac::Interrupt::USART2;

/// Milliseconds since the monotonic started (the board's defmt timestamps).
#[cfg(not(feature = "qemu"))]
pub fn timestamp_ms() -> u32 {
    use rtic_monotonics::systick::prelude::*;
    Mono::now().as_ticks()
}

/// Everything `init` hands to the RTIC app.
pub struct Board {
    /// Sampling and output, owned by the `control` task.
    pub control: ControlIo,
    /// Receive side of the link, owned by the `usart2` task.
    pub rx: LinkRx,
    /// Transmit side of the link, shared by the tasks that send.
    pub tx: LinkTx,
    /// What `idle` does between interrupts.
    pub idle: IdleIo,
    /// Core clock, Hz.
    pub sysclk_hz: u32,
    /// The crystal did not start (or the PLL did not lock): running from the internal RC.
    pub clock_fallback: bool,
    /// Why the chip last reset: `belt_link::reset_cause` bits, 0 = unknown.
    pub reset_cause: u8,
}

/// Sets up the link USART (USART2 on both boards) at register level: clock, PA2 (TX) and PA3
/// (RX, pulled up so an unplugged cable idles instead of framing noise) on AF7, 8N1 at `baud`
/// from `pclk1_hz`, receive interrupt on; split into its receive and transmit halves.
fn link_usart(usart: pac::USART2, pclk1_hz: u32, baud: u32) -> (UsartRx, UsartTx) {
    // SAFETY: a read-modify-write of RCC during init, before any task runs.
    let rcc = unsafe { &*pac::RCC::ptr() };
    rcc.apb1enr().modify(|_, w| w.usart2en().set_bit());
    // Erratum ES0182 2.1.13: read back before the first access to the USART.
    let _ = rcc.apb1enr().read();
    cortex_m::asm::dsb();
    gpio::enable_ports();
    gpio::GPIOA.alternate(2, 7, gpio::Pull::None);
    gpio::GPIOA.alternate(3, 7, gpio::Pull::Up);
    // Oversampling by 16: BRR = PCLK / baud (mantissa and fraction together), rounded.
    let brr = ((pclk1_hz + baud / 2) / baud.max(1)).clamp(16, 0xFFFF) as u16;
    usart.brr().write(|w| unsafe { w.bits(brr) });
    usart.cr2().write(|w| unsafe { w.bits(0) });
    usart.cr3().write(|w| unsafe { w.bits(0) });
    usart.cr1().write(|w| {
        w.ue()
            .set_bit()
            .te()
            .set_bit()
            .re()
            .set_bit()
            .rxneie()
            .set_bit()
    });
    (UsartRx { _owned: () }, UsartTx { usart })
}

/// Receive half of the link USART: reads SR and DR only.
pub struct UsartRx {
    _owned: (),
}

impl UsartRx {
    /// The next received byte, if any. Overrun, noise and framing errors are cleared (the lost
    /// byte then shows up as a frame that fails its CRC).
    #[inline]
    pub fn read(&mut self) -> Option<u8> {
        // SAFETY: this half only reads SR and DR (a DR read pops the receive register); the
        // transmit half writes DR's transmit side and CR1, never touching receive state.
        let usart = unsafe { &*pac::USART2::ptr() };
        let sr = usart.sr().read();
        if sr.rxne().bit_is_set() {
            Some(usart.dr().read().dr().bits() as u8)
        } else {
            if sr.ore().bit_is_set() || sr.fe().bit_is_set() || sr.nf().bit_is_set() {
                // SR then DR read clears the error flags.
                let _ = usart.dr().read();
            }
            None
        }
    }
}

/// Transmit half of the link USART: the only writer of CR1 after init.
pub struct UsartTx {
    usart: pac::USART2,
}

impl UsartTx {
    /// True when the transmit register can take a byte.
    #[inline]
    pub fn can_write(&self) -> bool {
        self.usart.sr().read().txe().bit_is_set()
    }

    /// A whole frame in one go: not on a USART (the outbox queues it byte by byte).
    #[inline(always)]
    pub fn write_frame(&mut self, _frame: &[u8]) -> bool {
        false
    }

    /// Writes one byte; call only when `can_write()`.
    #[inline]
    pub fn write(&mut self, byte: u8) {
        self.usart
            .dr()
            .write(|w| unsafe { w.dr().bits(byte as u16) });
    }

    /// Turns the TXE interrupt on (bytes queued) or off (queue empty).
    #[inline]
    pub fn set_tx_interrupt(&mut self, on: bool) {
        self.usart.cr1().modify(|_, w| w.txeie().bit(on));
    }

    /// Turns the RXNE interrupt on or off (off while the receive queue is full: QEMU then holds
    /// the next byte back; the real board loses it to an overrun, seen as a bad frame).
    #[inline]
    pub fn set_rx_interrupt(&mut self, on: bool) {
        self.usart.cr1().modify(|_, w| w.rxneie().bit(on));
    }
}
