//! The QEMU board: `qemu-system-arm -M netduinoplus2` (an STM32F405RGT6), see
//! `shared/QEMU-NOTES.md`.
//!
//! - Clocks: HSI, no PLL (QEMU does not model RCC: the PLL's ready bit never sets). The CPU and
//!   SysTick run at 168 MHz whatever RCC says, so the monotonic is started at 168 MHz.
//! - Time: SysTick only; QEMU's TIM2-5 do not keep time.
//! - The plant: `hil-sim` on USART2 (QEMU's second `-serial`), in lockstep: each
//!   [`Request::Sample`](estimator_core::link::Request::Sample) is handed to `control` by pending
//!   TIM7, and `control` answers with the current and telemetry. No sample, no tick.
//! - TIM2 with PSC = 0 and ARR = 0 counts executed instructions under `-icount shift=0`: read
//!   before and after `Drive::step` it gives the step's exact instruction count (+5 for the reads).
//! - defmt over semihosting (QEMU's stdout); `halt(code)` is a semihosting exit with `code`.

use core::sync::atomic::{AtomicBool, AtomicU32, Ordering};

use stm32f4xx_hal::pac;

use super::{link_usart, Board, Mono};
use crate::drive::{Output as DriveOutput, Sample};

/// Board name for the boot log.
pub const NAME: &str = "QEMU netduinoplus2 (STM32F405RG model, HSI, 168 MHz virtual)";
/// QEMU's CPU and SysTick clock.
const QEMU_CORE_HZ: u32 = 168_000_000;
/// Fixed cost of the two counter reads around the measured region.
pub const COUNTER_OVERHEAD: u32 = 5;
/// Link baud rate (QEMU ignores BRR; kept equal to the board's).
const BAUD: u32 = 460_800;
/// The real board's limit (see `stm32f405.rs`), so that a configuration accepted in PIL is
/// accepted on the board.
pub const MAX_LINEAR_CURRENT_MA: i32 = 8_787;

/// The mailbox from the link task (a PIL sample arrived) to the control task; `PENDING` is
/// released last and taken first.
static SAMPLE: AtomicU32 = AtomicU32::new(0);
static SEQ: AtomicU32 = AtomicU32::new(0);
static PENDING: AtomicBool = AtomicBool::new(false);

/// Sampling and output of the control task.
pub struct ControlIo {
    counter: pac::TIM2,
}

/// `Shutdown` ends the emulator (end of a PIL run).
pub const ALLOW_SHUTDOWN: bool = true;

/// What `begin_tick` hands to the control task.
pub struct Tick {
    /// The plant's counters for this tick.
    pub sample: Sample,
    /// Sequence number of the PIL sample, echoed in the answer.
    pub reply_seq: Option<u8>,
    /// Late or skipped ticks: none, the plant paces the ticks.
    pub missed: u32,
    /// Tick latency: not measured (QEMU's TIM7 is not modelled).
    pub latency_us: u16,
}

impl ControlIo {
    /// Takes the PIL sample that pended this tick; `None` if there is none (a spurious pend).
    #[inline(always)]
    pub fn begin_tick(&mut self) -> Option<Tick> {
        if !PENDING.swap(false, Ordering::Acquire) {
            return None;
        }
        let raw = SAMPLE.load(Ordering::Relaxed);
        Some(Tick {
            sample: Sample {
                motor_counter: raw as u16,
                scale_counter: (raw >> 16) as u16,
            },
            reply_seq: Some(SEQ.load(Ordering::Relaxed) as u8),
            missed: 0,
            latency_us: 0,
        })
    }

    /// Runs `step` with interrupts masked and returns the instructions it executed (TIM2 CNT
    /// before and after, less the reads' own cost). Masking keeps SysTick out of the count.
    #[inline(always)]
    pub fn measure<R>(&mut self, step: impl FnOnce() -> R) -> (R, u32) {
        cortex_m::interrupt::free(|_| {
            let t0 = self.counter.cnt().read().bits();
            let r = step();
            let t1 = self.counter.cnt().read().bits();
            (r, t1.wrapping_sub(t0).wrapping_sub(COUNTER_OVERHEAD))
        })
    }

    /// No amplifier under QEMU: the current travels back in the PIL answer.
    #[inline(always)]
    pub fn write_current(&mut self, _out: &DriveOutput, _amplifier_on: bool) {}

    /// No overrun: the plant waits for every answer.
    #[inline(always)]
    pub fn overran(&self) -> bool {
        false
    }

    /// No watchdog (QEMU does not model the IWDG).
    #[inline(always)]
    pub fn feed_watchdog(&mut self) {}

    /// Nothing to start: the plant paces the ticks, and QEMU models no IWDG.
    pub fn start(&mut self) {}
}

/// QEMU's clock cannot fail.
#[inline(always)]
pub fn clock_failed() -> bool {
    false
}

/// Hands a PIL sample to the control task and pends its interrupt; true (always, here).
pub fn pil_deliver(seq: u8, sample: Sample) -> bool {
    SAMPLE.store(
        sample.motor_counter as u32 | (sample.scale_counter as u32) << 16,
        Ordering::Relaxed,
    );
    SEQ.store(seq as u32, Ordering::Relaxed);
    PENDING.store(true, Ordering::Release);
    rtic::pend(pac::Interrupt::TIM7);
    true
}

/// Reset clocks (HSI: QEMU ignores RCC), SysTick monotonic at 168 MHz, TIM2 instruction
/// counter, USART2.
pub fn init(dp: pac::Peripherals, core: cortex_m::Peripherals, _control_rate_hz: u32) -> Board {
    Mono::start(core.SYST, QEMU_CORE_HZ);

    // TIM2 as an instruction counter: PSC = 0, ARR = 0, no interrupt.
    // SAFETY: one RCC bit during init (QEMU ignores it; kept for honesty).
    unsafe {
        (*pac::RCC::ptr())
            .apb1enr()
            .modify(|_, w| w.tim2en().set_bit())
    };
    let counter = dp.TIM2;
    counter.psc().write(|w| unsafe { w.bits(0) });
    counter.arr().write(|w| unsafe { w.bits(0) });
    counter.cr1().write(|w| w.cen().set_bit());

    // The HSI frequency: what the board's BRR would be without the PLL.
    let (rx, tx) = link_usart(dp.USART2, 16_000_000, BAUD);

    Board {
        control: ControlIo { counter },
        rx,
        tx,
        sysclk_hz: QEMU_CORE_HZ,
        clock_fallback: false,
        // QEMU reads RCC as 0: unknown.
        reset_cause: 0,
    }
}

/// No motor under QEMU.
pub fn emergency_stop() {}

/// Ends QEMU with exit status `code`.
pub fn halt(code: i32) -> ! {
    semihosting::process::exit(code)
}
