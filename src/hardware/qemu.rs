//! The QEMU board: `qemu-system-arm -M netduinoplus2` (an STM32F405RGT6), see
//! `shared/QEMU-NOTES.md`.
//!
//! - Clocks: HSI, no PLL (QEMU does not model RCC: the PLL's ready bit never sets). The CPU and
//!   SysTick run at 168 MHz whatever RCC says, so the monotonic is started at 168 MHz.
//! - Time: SysTick only; QEMU's TIM2-5 do not keep time.
//! - The plant: `hil-sim`, in lockstep: each
//!   [`Request::Sample`](belt_link::Request::Sample) is handed to `control` by pending
//!   TIM7, and `control` answers with the current and telemetry. No sample, no tick.
//! - The link: USART2 (QEMU's second `-serial`), or, when QEMU's semihosting command line holds
//!   `--pipe IN OUT`, two host FIFOs read and written through semihosting ([`IdleIo`]): one call
//!   per burst of bytes instead of one emulated interrupt and host round trip per byte (QEMU's
//!   USART takes about 19 us a byte). The frames, the decoder and every task are the same.
//! - Time: the defmt timestamp is plant time, control ticks over the configured rate, so that a
//!   log line lines up with the simulator's figures (QEMU's virtual clock runs at another pace).
//! - TIM2 with PSC = 0 and ARR = 0 counts executed instructions under `-icount shift=0`: read
//!   before and after `Drive::step` it gives the step's exact instruction count (+5 for the reads).
//! - defmt over semihosting (QEMU's stdout); `halt(code)` is a semihosting exit with `code`.

use core::ffi::CStr;
use core::sync::atomic::{AtomicBool, AtomicU32, Ordering};

use estimator_core::fixed::types::I16F16;
use heapless::spsc::{Consumer, Producer, Queue};
use semihosting::fd::{AsFd, OwnedFd};
use semihosting::sys::arm_compat::{sys_get_cmdline_uninit, sys_open, OpenMode};
use stm32f4xx_hal::pac;

use super::{link_usart, Board, Mono, UsartRx, UsartTx};
use crate::drive::Sample;

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
/// Control ticks run (PIL samples taken) and the control rate: the log's clock.
static TICKS: AtomicU32 = AtomicU32::new(0);
static RATE_HZ: AtomicU32 = AtomicU32::new(1);

/// Bytes read from the pipe and not yet taken by the `usart2` task: one read's worth.
const PIPE_CHUNK: usize = 64;
type PipeQueue = Queue<u8, { PIPE_CHUNK + 1 }>;

/// Plant time in microseconds: ticks run over the control rate.
pub fn timestamp_us() -> u64 {
    let ticks = TICKS.load(Ordering::Relaxed);
    let rate = RATE_HZ.load(Ordering::Relaxed).max(1);
    // Whole seconds, then the rest in two 32-bit steps of 1000 (exact for rates below 4 MHz):
    // no `u64` division, whose routine costs ~0.9 KB of flash.
    let (secs, rest) = (ticks / rate, ticks % rate);
    let (ms, ms_rest) = ((rest * 1000) / rate, (rest * 1000) % rate);
    secs as u64 * 1_000_000 + (ms * 1000 + ms_rest * 1000 / rate) as u64
}

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
        TICKS.fetch_add(1, Ordering::Relaxed);
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
    pub fn write_current(&mut self, _current_a: I16F16, _amplifier_on: bool) {}

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

/// Receive half of the link: the pipe's bytes (handed over by `idle`) or USART2.
pub struct LinkRx {
    usart: UsartRx,
    pipe: Option<Consumer<'static, u8>>,
}

impl LinkRx {
    /// The next received byte, if any.
    #[inline]
    pub fn read(&mut self) -> Option<u8> {
        match &mut self.pipe {
            Some(c) => c.dequeue(),
            None => self.usart.read(),
        }
    }
}

/// Transmit half of the link: whole frames into the pipe, or bytes into USART2.
pub struct LinkTx {
    usart: UsartTx,
    pipe: Option<OwnedFd>,
}

impl LinkTx {
    /// True when the USART can take a byte (always under QEMU).
    #[inline]
    pub fn can_write(&self) -> bool {
        self.usart.can_write()
    }

    /// Writes a whole frame into the pipe; false on USART2 (the outbox queues it).
    pub fn write_frame(&mut self, frame: &[u8]) -> bool {
        let Some(fd) = &self.pipe else { return false };
        let mut rest = frame;
        while !rest.is_empty() {
            match semihosting::sys::write(fd.as_fd(), rest) {
                Ok(n) if n > 0 => rest = &rest[n.min(rest.len())..],
                // The host is gone: nothing to report to.
                _ => halt(EXIT_HOST_GONE),
            }
        }
        true
    }

    /// Writes one byte to USART2.
    #[inline]
    pub fn write(&mut self, byte: u8) {
        self.usart.write(byte)
    }

    /// The USART's TXE interrupt (QEMU raises none; kept for the shared outbox).
    #[inline]
    pub fn set_tx_interrupt(&mut self, on: bool) {
        self.usart.set_tx_interrupt(on)
    }

    /// Receive interrupt on or off. With the pipe, "on" pends `usart2` to take the bytes it
    /// left when its queue was full.
    #[inline]
    pub fn set_rx_interrupt(&mut self, on: bool) {
        if self.pipe.is_some() {
            if on {
                rtic::pend(pac::Interrupt::USART2);
            }
        } else {
            self.usart.set_rx_interrupt(on)
        }
    }
}

/// QEMU exit status when the host closed the pipe.
pub const EXIT_HOST_GONE: i32 = 3;

/// What `idle` does: `wfi` with USART2; with the pipe, waits (inside QEMU, in the host's
/// `read`) for the host's next bytes and hands them to `usart2`. Virtual time stands still
/// while it waits, as the plant paces the firmware anyway.
pub struct IdleIo {
    pipe: Option<(OwnedFd, Producer<'static, u8>)>,
}

impl IdleIo {
    /// One idle round.
    pub fn wait(&mut self) {
        let Some((fd, queue)) = &mut self.pipe else {
            cortex_m::asm::wfi();
            return;
        };
        if !queue.is_empty() {
            // `usart2` paused on a full queue; `link` pends it again once drained.
            cortex_m::asm::wfi();
            return;
        }
        let mut buf = [0u8; PIPE_CHUNK];
        match semihosting::sys::read(fd.as_fd(), &mut buf) {
            Ok(n) if n > 0 => {
                for &b in &buf[..n.min(PIPE_CHUNK)] {
                    let _ = queue.enqueue(b);
                }
                rtic::pend(pac::Interrupt::USART2);
            }
            // End of file or an error: the host closed the pipe.
            _ => {
                defmt::info!("link pipe closed by the host: exit");
                halt(EXIT_HOST_GONE)
            }
        }
    }
}

/// The pipe's paths from QEMU's semihosting command line (`... --pipe IN OUT`), opened.
fn open_pipe() -> Option<(OwnedFd, OwnedFd)> {
    let mut line = [core::mem::MaybeUninit::<u8>::uninit(); 768];
    let line = sys_get_cmdline_uninit(&mut line).ok()?;
    let mut words = line.split(|&b| b == b' ').filter(|w| !w.is_empty());
    words.find(|w| *w == b"--pipe")?;
    let (Some(input), Some(output)) = (words.next(), words.next()) else {
        defmt::error!("--pipe needs two paths: exit");
        halt(EXIT_HOST_GONE)
    };
    let open = |path: &[u8], mode| {
        let mut z = [0u8; 128];
        let n = path.len().min(z.len() - 1);
        z[..n].copy_from_slice(&path[..n]);
        let p = CStr::from_bytes_until_nul(&z).ok()?;
        sys_open(p, mode).ok()
    };
    match (
        open(input, OpenMode::RDONLY_BINARY),
        open(output, OpenMode::WRONLY_TRUNC_BINARY),
    ) {
        (Some(i), Some(o)) => Some((i, o)),
        // The host waits on the pipe, not on USART2: say why and end at once.
        _ => {
            defmt::error!("--pipe given but its FIFOs cannot be opened: exit");
            halt(EXIT_HOST_GONE)
        }
    }
}

/// Reset clocks (HSI: QEMU ignores RCC), SysTick monotonic at 168 MHz, TIM2 instruction
/// counter, the link (the pipe if the command line names one, else USART2).
pub fn init(dp: pac::Peripherals, core: cortex_m::Peripherals, control_rate_hz: u32) -> Board {
    Mono::start(core.SYST, QEMU_CORE_HZ);
    RATE_HZ.store(control_rate_hz.max(1), Ordering::Relaxed);

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
    let (usart_rx, usart_tx) = link_usart(dp.USART2, 16_000_000, BAUD);
    // `singleton!` is `None` only on a second call; init runs once.
    let pipe = open_pipe()
        .and_then(|(i, o)| cortex_m::singleton!(: PipeQueue = Queue::new()).map(|q| (i, o, q)));
    let (rx, tx, idle) = match pipe {
        Some((input, output, queue)) => {
            let (producer, consumer) = queue.split();
            (
                LinkRx {
                    usart: usart_rx,
                    pipe: Some(consumer),
                },
                LinkTx {
                    usart: usart_tx,
                    pipe: Some(output),
                },
                IdleIo {
                    pipe: Some((input, producer)),
                },
            )
        }
        None => (
            LinkRx {
                usart: usart_rx,
                pipe: None,
            },
            LinkTx {
                usart: usart_tx,
                pipe: None,
            },
            IdleIo { pipe: None },
        ),
    };

    Board {
        control: ControlIo { counter },
        rx,
        tx,
        idle,
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
