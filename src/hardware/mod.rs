//! The two boards the firmware runs on, behind one interface (embassy's driver split).
//!
//! Each board module provides:
//! - `NAME`, `init(device, syst, control_rate_hz) -> Board`;
//! - `ControlIo` (owned by the `control` task): `begin_tick()` samples the counters (board) or
//!   takes the PIL sample (QEMU), `write_current()` drives the amplifier (board only),
//!   `step_counter()` reads the instruction counter (QEMU only);
//! - `Uart` (shared by the tasks that send): byte-level access to the link's USART;
//! - `pil_deliver()` (QEMU: hand a PIL sample to `control`; board: refused),
//! - `emergency_stop()`, `halt(code)`, `timestamp_ms()`.
//!
//! The control-tick interrupt is `TIM7` on both: on the board TIM7 (a basic timer) fires at the
//! control rate; under QEMU, whose TIM7 is not modelled, the link task pends it when a PIL sample
//! arrives, so the plant paces the firmware.

#[cfg(not(feature = "qemu"))]
mod stm32f405;
#[cfg(not(feature = "qemu"))]
pub use stm32f405::*;

#[cfg(feature = "qemu")]
mod qemu;
#[cfg(feature = "qemu")]
pub use qemu::*;

use stm32f4xx_hal::pac;

rtic_monotonics::systick_monotonic!(Mono, 1_000);

/// Milliseconds since the monotonic started (defmt timestamps).
pub fn timestamp_ms() -> u32 {
    use rtic_monotonics::systick::prelude::*;
    Mono::now().as_ticks()
}

/// Everything `init` hands to the RTIC app.
pub struct Board {
    /// Sampling and output, owned by the `control` task.
    pub control: ControlIo,
    /// Receive side of the link USART, owned by the `link` task.
    pub rx: LinkRx,
    /// Transmit side of the link USART, shared by the tasks that send.
    pub tx: LinkTx,
    /// Core clock, Hz.
    pub sysclk_hz: u32,
}

/// Splits the link USART (USART2 on both boards) into its receive and transmit halves and
/// turns on the receive interrupt.
fn link_usart(usart: pac::USART2) -> (LinkRx, LinkTx) {
    usart.cr1().modify(|_, w| w.rxneie().set_bit());
    (LinkRx { _owned: () }, LinkTx { usart })
}

/// Receive half of the link USART: reads SR and DR only.
pub struct LinkRx {
    _owned: (),
}

impl LinkRx {
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
pub struct LinkTx {
    usart: pac::USART2,
}

impl LinkTx {
    /// True when the transmit register can take a byte.
    #[inline]
    pub fn can_write(&self) -> bool {
        self.usart.sr().read().txe().bit_is_set()
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
}
