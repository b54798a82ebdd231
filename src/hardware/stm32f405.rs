//! The real drive controller: STM32F405RG, 8 MHz crystal (or oscillator module: `hse-bypass`).
//!
//! | function                         | peripheral          | pins                          |
//! |----------------------------------|---------------------|-------------------------------|
//! | motor encoder A/B (x4)           | TIM3 encoder mode 3 | PA6 = CH1, PA7 = CH2 (AF2, PU)|
//! | linear scale A/B (x4, 0.5 um)    | TIM4 encoder mode 3 | PB6 = CH1, PB7 = CH2 (AF2, PU)|
//! | current command (analog)         | DAC channel 1       | PA4                           |
//! | amplifier enable (high = on)     | GPIO                | PB0 (external pull-down)      |
//! | control tick                     | TIM7 update IRQ     | -                             |
//! | host link, 460800 8N1            | USART2              | PA2 = TX, PA3 = RX (AF7, PU)  |
//! | defmt log                        | RTT (probe-rs)      | SWD                           |
//!
//! The motor is driven by a transconductance (current-mode) amplifier with a +-10 A input range
//! around mid-rail: DAC code 2048 (VREF+ / 2) is 0 A and each step of the 12-bit DAC is
//! [`AMP_FULL_SCALE_MA`] / 2047 of current.
//!
//! Safe state: `__pre_init` (below) drives PB0 low and puts PA4 in analog mode before RAM is
//! initialised; no code ever resets GPIOA/GPIOB afterwards. The enable goes high only while the
//! drive is enabled with no fault latched; panic, HardFault, an unexpected interrupt or a clock
//! failure drop it at once. The independent watchdog, fed only at the end of a completed control
//! tick, resets a board that stops ticking into that safe state.

mod clocks;
/// The configuration storage: flash sectors 10-11.
pub mod flash;
pub use flash::{
    open_staging, open_storage, with_long_watchdog as during_save, BoardFlash as StorageFlash,
};
/// The calibration staging area: sector 9, erased with the watchdog lengthened.
pub type StagingFlash = flash::LongErase<flash::BoardFlash>;

use core::sync::atomic::{AtomicBool, Ordering};

use cortex_m::peripheral::{scb::SystemHandler, DWT};
use estimator_core::fixed::types::I16F16;
use stm32f4xx_hal::pac;

use super::gpio::{self, Pull};
use super::{link_usart, Board, Mono};
pub use super::{UsartRx as LinkRx, UsartTx as LinkTx};
use crate::drive::Sample;
use crate::postmortem::reset_cause;

use clocks::Source as ClockSource;

/// Board name for the boot log.
pub const NAME: &str = "STM32F405RG drive controller";
/// Link baud rate.
pub const BAUD: u32 = 460_800;
/// Amplifier current at DAC full scale (code 4095, VREF+ / 2 above mid-rail), milliamperes:
/// a 150 W / 48 V class brushed-motor amplifier with a +-10 A input range.
pub const AMP_FULL_SCALE_MA: i64 = 10_000;
/// Largest current the DAC reaches linearly, milliamperes: with its output buffer on, the DAC
/// is linear only from 0.2 V to VDDA - 0.2 V, i.e. +-1.45 V of the +-1.65 V around mid-rail at
/// 3.3 V, so +-8.79 A of the +-10 A scale. A drive whose current limit exceeds it would wind its
/// integrator up against the buffer's rail: `init` refuses it.
pub const MAX_LINEAR_CURRENT_MA: i32 = (AMP_FULL_SCALE_MA * (1650 - 200) / 1650) as i32;
/// DAC code for zero current.
const DAC_ZERO: u16 = 2048;
/// DAC counts per ampere in 32.32 fixed point, so that `(current_bits * K) >> 48` are counts
/// (current bits are I16F16: one more shift by 16).
const DAC_COUNTS_PER_A_Q32: i64 = (2047i64 << 32) * 1000 / AMP_FULL_SCALE_MA;
/// Amplifier enable pin: PB0.
const AMP_ENABLE_PIN: u8 = 0;

/// TIM7 counts microseconds.
const TICK_TIMER_HZ: u32 = 1_000_000;
/// Encoder inputs: digital filter fCK_INT, N = 8 (IC1F = IC2F = 0b0011: ~95 ns at 84 MHz, far
/// below the 2.1 us edge spacing at 467 k counts/s), CC1S = TI1, CC2S = TI2.
const ENCODER_CCMR1: u32 = 0b01 | (0b0011 << 4) | (0b01 << 8) | (0b0011 << 12);
/// SMCR.SMS = 0b011: encoder mode 3 (count on both edges of both inputs, x4).
const ENCODER_SMS: u32 = 0b011;

/// Independent watchdog: LSI / 4 and 80 counts: 10 ms at the nominal 32 kHz, but the LSI is
/// anywhere from 17 to 47 kHz, so 6.8 to 18.8 ms; a control tick is 0.5 ms.
const IWDG_PRESCALER: u8 = 0; // /4
const IWDG_RELOAD: u16 = 80;
const IWDG_KEY_START: u16 = 0xCCCC;
const IWDG_KEY_UNLOCK: u16 = 0x5555;
const IWDG_KEY_FEED: u16 = 0xAAAA;

/// `Shutdown` requests are refused: there is nothing to exit to.
pub const ALLOW_SHUTDOWN: bool = false;

/// Set by the clock-security NMI; `control` latches `CLOCK_FAILURE` and writes no current.
static CLOCK_FAILED: AtomicBool = AtomicBool::new(false);

// First code after reset, before .bss/.data initialisation and everything in `init` (stack
// painting, clock start-up): the amplifier enable PB0 is driven low and the DAC pin PA4 is put
// in analog mode, so neither floats while the board boots. Plain assembly (only r0-r1, no stack,
// no RAM): cortex-m-rt calls `__pre_init` before RAM is valid, where Rust code is unsound.
// RCC_AHB1ENR |= GPIOAEN | GPIOBEN, read back + DSB (erratum ES0182 2.1.13); GPIOB_BSRR = BR0
// (low first), GPIOB_OTYPER.OT0 = 0, GPIOB_MODER.MODER0 = 01 (output); GPIOA_MODER.MODER4 = 11.
// No port reset (RCC_AHB1RSTR) is ever pulsed, here or later.
core::arch::global_asm!(
    ".section .text.__pre_init, \"ax\"",
    ".global __pre_init",
    ".type __pre_init, %function",
    ".thumb_func",
    "__pre_init:",
    "ldr r0, ={ahb1enr}",
    "ldr r1, [r0]",
    "orr r1, r1, #3",
    "str r1, [r0]",
    "ldr r1, [r0]",
    "dsb",
    "ldr r0, ={gpiob}",
    "mov r1, #0x10000",
    "str r1, [r0, #0x18]",
    "ldr r1, [r0, #0x04]",
    "bic r1, r1, #1",
    "str r1, [r0, #0x04]",
    "ldr r1, [r0]",
    "bic r1, r1, #3",
    "orr r1, r1, #1",
    "str r1, [r0]",
    "ldr r0, ={gpioa}",
    "ldr r1, [r0]",
    "orr r1, r1, #0x300",
    "str r1, [r0]",
    "bx lr",
    ".size __pre_init, . - __pre_init",
    ahb1enr = const 0x4002_3830u32,
    gpiob = const 0x4002_0400u32,
    gpioa = const 0x4002_0000u32,
);

/// Sampling and output of the control task.
pub struct ControlIo {
    tick: pac::TIM7,
    motor: pac::TIM3,
    scale: pac::TIM4,
    dac: pac::DAC,
    iwdg: pac::IWDG,
    /// TIM7 counts at tick entry beyond which the tick is late (half a period).
    late_after_us: u16,
    /// Core cycles per tick, and the cycle counter at the previous tick's entry.
    period_cycles: u32,
    last_entry: Option<u32>,
}

/// What `begin_tick` hands to the control task.
pub struct Tick {
    /// The counters, read before anything else in the tick.
    pub sample: Sample,
    /// Sequence number to answer with (PIL only).
    pub reply_seq: Option<u8>,
    /// Ticks found late or skipped at entry (0 = on time).
    pub missed: u32,
    /// Microseconds from the timer's update to this tick's entry.
    pub latency_us: u16,
}

impl ControlIo {
    /// Measures how late this tick starts, acknowledges the tick interrupt and samples both
    /// encoder counters.
    #[inline(always)]
    pub fn begin_tick(&mut self) -> Option<Tick> {
        let latency_us = self.tick.cnt().read().bits() as u16;
        // SR.UIF is rc_w0 and the only flag of a basic timer.
        self.tick.sr().write(|w| unsafe { w.bits(0) });
        let sample = Sample {
            motor_counter: self.motor.cnt().read().bits() as u16,
            scale_counter: self.scale.cnt().read().bits() as u16,
        };
        // Late: the entry came more than half a period after the update. Skipped: more than
        // 1.5 periods since the previous entry (a blocked interrupt across whole periods leaves
        // TIM7 CNT small again and UIF merged, so the counter alone cannot see it).
        let now = DWT::cycle_count();
        let mut missed = (latency_us > self.late_after_us) as u32;
        if let Some(last) = self.last_entry {
            let gap = now.wrapping_sub(last);
            if gap > self.period_cycles + self.period_cycles / 2 {
                // `checked_div`: no division panic in the tick (a period is never 0 cycles).
                let periods = gap.checked_div(self.period_cycles).unwrap_or(1);
                missed = missed.max(periods.saturating_sub(1)).max(1);
            }
        }
        self.last_entry = Some(now);
        Some(Tick {
            sample,
            reply_seq: None,
            missed,
            latency_us,
        })
    }

    /// Runs `step`; the instruction count is not measured on the real board (0): DWT counts
    /// cycles, not instructions, and the budget is checked under QEMU.
    #[inline(always)]
    pub fn measure<R>(&mut self, step: impl FnOnce() -> R) -> (R, u32) {
        (step(), 0)
    }

    /// Sends the tick's current to the amplifier, or zero current and a low enable when
    /// `amplifier_on` is false or the clock has failed meanwhile.
    #[inline(always)]
    pub fn write_current(&mut self, current_a: I16F16, amplifier_on: bool) {
        if amplifier_on && !CLOCK_FAILED.load(Ordering::Relaxed) {
            // Current first, then the enable: the amplifier never sees a stale command.
            self.dac
                .dhr12r1()
                .write(|w| unsafe { w.daccdhr().bits(dac_code(current_a)) });
            gpio::GPIOB.set_high(AMP_ENABLE_PIN);
        } else {
            // Enable first, then zero.
            gpio::GPIOB.set_low(AMP_ENABLE_PIN);
            self.dac
                .dhr12r1()
                .write(|w| unsafe { w.daccdhr().bits(DAC_ZERO) });
        }
    }

    /// True when the next update came while this tick ran (an overrun).
    #[inline(always)]
    pub fn overran(&self) -> bool {
        self.tick.sr().read().uif().bit_is_set()
    }

    /// Feeds the independent watchdog: the last thing of a completed tick, and nowhere else.
    #[inline(always)]
    pub fn feed_watchdog(&mut self) {
        self.iwdg
            .kr()
            .write(|w| unsafe { w.key().bits(IWDG_KEY_FEED) });
    }

    /// Starts the control tick from a clean count, then the independent watchdog: the last
    /// thing `init` does, so that the boot's own duration is neither a late tick nor a
    /// watchdog reset. From now on a board that stops completing control ticks resets into its
    /// safe state within 7-19 ms.
    pub fn start(&mut self) {
        self.tick.cnt().write(|w| unsafe { w.bits(0) });
        self.tick.sr().write(|w| unsafe { w.bits(0) });
        self.tick.cr1().modify(|_, w| w.cen().set_bit());

        let iwdg = &self.iwdg;
        iwdg.kr().write(|w| unsafe { w.key().bits(IWDG_KEY_START) });
        iwdg.kr()
            .write(|w| unsafe { w.key().bits(IWDG_KEY_UNLOCK) });
        iwdg.pr().write(|w| unsafe { w.pr().bits(IWDG_PRESCALER) });
        iwdg.rlr().write(|w| unsafe { w.rl().bits(IWDG_RELOAD) });
        // The new values cross into the LSI domain in a few LSI cycles (~200 us at worst); a
        // bounded wait: if it never completes, the reset values (~0.5 s) stay in force.
        for _ in 0..100_000 {
            if iwdg.sr().read().bits() == 0 {
                break;
            }
        }
        self.feed_watchdog();
    }
}

/// DAC code for a current command, saturated to the DAC's range.
fn dac_code(current_a: I16F16) -> u16 {
    let counts = (current_a.to_bits() as i64 * DAC_COUNTS_PER_A_Q32) >> 48;
    (DAC_ZERO as i64 + counts.clamp(-2047, 2047)) as u16
}

/// Clocks, encoder timers, DAC, control timer, link USART, the monotonic, debug settings.
pub fn init(dp: pac::Peripherals, mut core: cortex_m::Peripherals, control_rate_hz: u32) -> Board {
    // PB0 and PA4 are already safe (`__pre_init`). RTT needs no clock: say where we are before
    // anything can hang.
    defmt::info!("starting clocks");
    let reset_cause = read_reset_cause(&dp.RCC);
    let clocks = clocks::start(&dp.RCC, &dp.FLASH, &dp.PWR);
    match clocks.source {
        ClockSource::Hse => defmt::info!(
            "clocks: HSE {=u32} Hz{=str} -> PLL {=u32} Hz, clock security on",
            clocks::HSE_HZ,
            if cfg!(feature = "hse-bypass") { " (bypass)" } else { "" },
            clocks.sysclk_hz
        ),
        ClockSource::HsiFallback => defmt::error!(
            "clocks: HSE did not start within 100 ms: running from HSI -> PLL {=u32} Hz (+-1 %, no clock security)",
            clocks.sysclk_hz
        ),
        ClockSource::HsiNoPll => defmt::error!(
            "clocks: PLL did not lock: running from HSI {=u32} Hz; drive held faulted",
            clocks.sysclk_hz
        ),
    }
    // The PLL failure is a clock failure too: the drive latches it on the first tick.
    if clocks.source == ClockSource::HsiNoPll {
        CLOCK_FAILED.store(true, Ordering::Relaxed);
    }
    Mono::start(core.SYST, clocks.sysclk_hz);
    // SysTick's priority is never set by the monotonic (it would stay at 0, above `control`):
    // logical 2, below the control tick.
    // SAFETY: priorities change before interrupts are enabled (RTIC's init).
    unsafe { core.SCB.set_priority(SystemHandler::SysTick, 0xE0) };
    // Tick gap measurement (cycle counter).
    core.DCB.enable_trace();
    core.DWT.enable_cycle_counter();

    // Debug: a probe can attach while the core sleeps in `wfi`; IWDG and TIM7 stop while the
    // core is halted, so a breakpoint neither resets the board nor counts as a missed tick.
    dp.DBGMCU.cr().modify(|_, w| w.dbg_sleep().set_bit());
    dp.DBGMCU
        .apb1_fz()
        .modify(|_, w| w.dbg_iwdg_stop().set_bit().dbg_tim7_stop().set_bit());

    let rcc = &dp.RCC;
    rcc.apb1enr().modify(|_, w| {
        w.tim3en()
            .set_bit()
            .tim4en()
            .set_bit()
            .tim7en()
            .set_bit()
            .dacen()
            .set_bit()
    });
    // Erratum ES0182 2.1.13: read back and DSB before touching the newly clocked peripherals.
    let _ = rcc.apb1enr().read();
    cortex_m::asm::dsb();

    // DAC channel 1 on PA4 (analog since `__pre_init`), output buffer on, 0 A before enabling.
    dp.DAC
        .dhr12r1()
        .write(|w| unsafe { w.daccdhr().bits(DAC_ZERO) });
    dp.DAC.cr().modify(|_, w| w.en1().set_bit());

    // Encoders: pull-ups so an unplugged cable reads a steady high, not noise.
    gpio::GPIOA.alternate(6, 2, Pull::Up);
    gpio::GPIOA.alternate(7, 2, Pull::Up);
    gpio::GPIOB.alternate(6, 2, Pull::Up);
    gpio::GPIOB.alternate(7, 2, Pull::Up);
    encoder(&dp.TIM3);
    encoder(&dp.TIM4);

    let (rx, tx) = link_usart(dp.USART2, clocks.pclk1_hz, BAUD);

    // TIM7 counts microseconds; the update is the control tick. URS: only overflow sets UIF.
    // Counting starts at the end of `init` (`ControlIo::start`).
    let period_us = (TICK_TIMER_HZ / control_rate_hz.max(16)).clamp(2, 65_536);
    let tim7 = dp.TIM7;
    tim7.psc()
        .write(|w| unsafe { w.bits(clocks.tim1_hz / TICK_TIMER_HZ - 1) });
    tim7.arr().write(|w| unsafe { w.bits(period_us - 1) });
    tim7.cr1().write(|w| w.urs().set_bit());
    tim7.egr().write(|w| w.ug().set_bit());
    tim7.sr().write(|w| unsafe { w.bits(0) });
    tim7.dier().write(|w| w.uie().set_bit());

    let tick_rate = TICK_TIMER_HZ / period_us;
    Board {
        control: ControlIo {
            tick: tim7,
            motor: dp.TIM3,
            scale: dp.TIM4,
            dac: dp.DAC,
            iwdg: dp.IWDG,
            late_after_us: (period_us / 2) as u16,
            period_cycles: clocks.sysclk_hz / tick_rate,
            last_entry: None,
        },
        rx,
        tx,
        idle: IdleIo,
        sysclk_hz: clocks.sysclk_hz,
        clock_fallback: clocks.source != ClockSource::Hse,
        reset_cause,
    }
}

/// What `idle` does: sleep until the next interrupt.
pub struct IdleIo;

impl IdleIo {
    /// One idle round.
    #[inline(always)]
    pub fn wait(&mut self) {
        cortex_m::asm::wfi();
    }
}

/// Encoder mode 3 with input filters, full 16-bit range, counting.
fn encoder(tim: &pac::tim3::RegisterBlock) {
    tim.cr1().write(|w| unsafe { w.bits(0) });
    tim.ccmr1_input()
        .write(|w| unsafe { w.bits(ENCODER_CCMR1) });
    // Both inputs non-inverted (CCxP = 0); capture outputs are not needed for counting.
    tim.ccer().write(|w| unsafe { w.bits(0) });
    tim.smcr().write(|w| unsafe { w.bits(ENCODER_SMS) });
    tim.arr().write(|w| unsafe { w.bits(0xFFFF) });
    tim.cr1().write(|w| w.cen().set_bit());
}

/// RCC_CSR's reset flags as [`reset_cause`] bits, then cleared (RMVF) so that the next boot sees
/// only its own cause.
fn read_reset_cause(rcc: &pac::RCC) -> u8 {
    let csr = rcc.csr().read();
    let flags = [
        (csr.lpwrrstf().bit_is_set(), reset_cause::LOW_POWER),
        (csr.wwdgrstf().bit_is_set(), reset_cause::WINDOW_WATCHDOG),
        (
            csr.wdgrstf().bit_is_set(),
            reset_cause::INDEPENDENT_WATCHDOG,
        ),
        (csr.sftrstf().bit_is_set(), reset_cause::SOFTWARE),
        (csr.porrstf().bit_is_set(), reset_cause::POWER_ON),
        (csr.padrstf().bit_is_set(), reset_cause::PIN),
        (csr.borrstf().bit_is_set(), reset_cause::BROWNOUT),
    ];
    rcc.csr().modify(|_, w| w.rmvf().set_bit());
    flags
        .iter()
        .filter(|(set, _)| *set)
        .fold(0, |acc, (_, bit)| acc | bit)
}

/// Whether the clock security system fired (or the PLL never locked).
#[inline(always)]
pub fn clock_failed() -> bool {
    CLOCK_FAILED.load(Ordering::Relaxed)
}

/// PIL samples exist only under QEMU: refused (false).
pub fn pil_deliver(_seq: u8, _sample: Sample) -> bool {
    false
}

/// Enable low and zero current, from any context (panic, HardFault, NMI, exit).
pub fn emergency_stop() {
    // Two single-register writes; whatever an interrupted writer did, these win.
    gpio::GPIOB.set_low(AMP_ENABLE_PIN);
    // SAFETY: one write of the DAC's data register.
    unsafe {
        (*pac::DAC::ptr())
            .dhr12r1()
            .write(|w| w.daccdhr().bits(DAC_ZERO));
    }
}

/// Stops here with the motor off. The independent watchdog (started here if `init` never got
/// that far) then resets the board into its safe state; under a debugger the halt is kept.
pub fn halt(_code: i32) -> ! {
    cortex_m::interrupt::disable();
    emergency_stop();
    // SAFETY: the start key only; a running watchdog is unaffected, a stopped one starts with
    // its reset timeout (~0.5 s).
    unsafe {
        (*pac::IWDG::ptr())
            .kr()
            .write(|w| w.key().bits(IWDG_KEY_START))
    };
    loop {
        cortex_m::asm::wfi();
    }
}

/// Clock security: the HSE failed and the hardware switched the system clock to HSI. The motor
/// goes off here, at once; the control task then latches `CLOCK_FAILURE`.
#[cortex_m_rt::exception]
unsafe fn NonMaskableInt() {
    emergency_stop();
    CLOCK_FAILED.store(true, Ordering::Relaxed);
    // SAFETY: CSSC is write-1-to-clear; the other CIR bits are interrupt enables (all off).
    let rcc = &*pac::RCC::ptr();
    rcc.cir().modify(|_, w| w.cssc().set_bit());
}
