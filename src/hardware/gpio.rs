//! Pin set-up at register level, one pin at a time.
//!
//! The HAL's `GPIOx.split()` pulses the port's reset in RCC_AHB1RSTR, which would return the
//! amplifier enable (PB0, driven low since `__pre_init`) to a floating input for a moment. This
//! module only read-modify-writes the configuration fields of the pins it is given, so the other
//! pins of a port keep their state. Port clocks are enabled once, in `__pre_init` (board) or in
//! [`enable_ports`] (both), never reset.

use core::ptr;

/// GPIOA register block (RM0090 2.3).
pub const GPIOA: Port = Port(0x4002_0000);
/// GPIOB register block.
pub const GPIOB: Port = Port(0x4002_0400);

const MODER: usize = 0x00;
const OTYPER: usize = 0x04;
const OSPEEDR: usize = 0x08;
const PUPDR: usize = 0x0C;
const BSRR: usize = 0x18;
const AFRL: usize = 0x20;

/// MODER values.
#[derive(Clone, Copy)]
#[repr(u32)]
pub enum Mode {
    Output = 0b01,
    Alternate = 0b10,
    Analog = 0b11,
}

/// PUPDR values.
#[derive(Clone, Copy)]
#[repr(u32)]
pub enum Pull {
    None = 0b00,
    Up = 0b01,
}

/// One GPIO port, by base address.
#[derive(Clone, Copy)]
pub struct Port(usize);

impl Port {
    // Not inlined: `init` configures a dozen pins (flash).
    #[inline(never)]
    fn modify(self, offset: usize, pin: u8, width: u32, value: u32) {
        let reg = (self.0 + offset) as *mut u32;
        let shift = pin as u32 * width;
        let mask = ((1u32 << width) - 1) << shift;
        // SAFETY: a GPIO configuration register of this port; callers run in `init` (interrupts
        // off) or own the pin, so no other read-modify-write of the register is in flight.
        unsafe {
            let v = ptr::read_volatile(reg);
            ptr::write_volatile(reg, (v & !mask) | ((value << shift) & mask));
        }
    }

    /// Alternate function `af` on a pin 0..=7 (AFRL), push-pull, medium speed.
    pub fn alternate(self, pin: u8, af: u32, pull: Pull) {
        debug_assert!(pin < 8);
        self.modify(AFRL, pin, 4, af);
        self.modify(OTYPER, pin, 1, 0);
        self.modify(OSPEEDR, pin, 2, 0b01);
        self.modify(PUPDR, pin, 2, pull as u32);
        self.modify(MODER, pin, 2, Mode::Alternate as u32);
    }

    /// Analog mode (no digital input buffer, no pull).
    pub fn analog(self, pin: u8) {
        self.modify(PUPDR, pin, 2, Pull::None as u32);
        self.modify(MODER, pin, 2, Mode::Analog as u32);
    }

    /// Push-pull output, driven low before the output stage is switched on.
    pub fn output_low(self, pin: u8) {
        self.set_low(pin);
        self.modify(OTYPER, pin, 1, 0);
        self.modify(MODER, pin, 2, Mode::Output as u32);
    }

    /// Drives `pin` high (one atomic BSRR write: safe from any context).
    #[inline(always)]
    pub fn set_high(self, pin: u8) {
        // SAFETY: BSRR is write-only and set/reset per bit: no read-modify-write.
        unsafe { ptr::write_volatile((self.0 + BSRR) as *mut u32, 1 << pin) };
    }

    /// Drives `pin` low (one atomic BSRR write: safe from any context).
    #[inline(always)]
    pub fn set_low(self, pin: u8) {
        // SAFETY: as `set_high`.
        unsafe { ptr::write_volatile((self.0 + BSRR) as *mut u32, 1 << (pin as u32 + 16)) };
    }
}

/// Clocks GPIOA and GPIOB (RCC_AHB1ENR) without resetting them, with the read-back the
/// clock-enable erratum (ES0182 2.1.13) asks for before the first access.
pub fn enable_ports() {
    // SAFETY: a read-modify-write of RCC_AHB1ENR during init, before any task runs.
    let rcc = unsafe { &*stm32f4xx_hal::pac::RCC::ptr() };
    rcc.ahb1enr()
        .modify(|_, w| w.gpioaen().set_bit().gpioben().set_bit());
    let _ = rcc.ahb1enr().read();
    cortex_m::asm::dsb();
}
