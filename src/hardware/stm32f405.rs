//! The real drive controller: STM32F405RG, 8 MHz crystal.
//!
//! | function                         | peripheral          | pins                      |
//! |----------------------------------|---------------------|---------------------------|
//! | motor encoder A/B (x4)           | TIM3 encoder mode 3 | PA6 = CH1, PA7 = CH2 (AF2)|
//! | linear scale A/B (x4, 0.5 um)    | TIM4 encoder mode 3 | PB6 = CH1, PB7 = CH2 (AF2)|
//! | current command (analog)         | DAC channel 1       | PA4                       |
//! | amplifier enable (high = on)     | GPIO                | PB0                       |
//! | control tick                     | TIM7 update IRQ     | -                         |
//! | host link, 460800 8N1            | USART2              | PA2 = TX, PA3 = RX (AF7)  |
//! | defmt log                        | RTT (probe-rs)      | SWD                       |
//!
//! The motor is driven by a transconductance (current-mode) amplifier with a +-1.65 V analog
//! input around mid-rail: DAC code 2048 (1.65 V) is 0 A and each step of the 12-bit DAC is
//! [`AMP_FULL_SCALE_MA`] / 2047 of current, so codes 1..=4095 span +-3 A. The amplifier's
//! enable input is held low (motor unpowered) until `init` finishes, whenever the drive reports
//! a fault, and on panic / HardFault.

use estimator_core::fixed::types::I16F16;
use stm32f4xx_hal::{
    gpio::{Output, Pin, PushPull},
    pac,
    prelude::*,
    qei::Qei,
    rcc::{Config, RccExt},
    serial::{self, Serial},
    timer::{CounterHz, Event, Flag},
};

use super::{link_usart, Board, Mono};
use crate::drive::{Output as DriveOutput, Sample};

/// Board name for the boot log.
pub const NAME: &str = "STM32F405RG drive controller (HSE 8 MHz, PLL 168 MHz)";
/// Link baud rate.
pub const BAUD: u32 = 460_800;
/// Amplifier current at DAC full scale (code 4095, +1.65 V from mid-rail), milliamperes.
pub const AMP_FULL_SCALE_MA: i64 = 3_000;
/// DAC code for zero current.
const DAC_ZERO: u16 = 2048;
/// DAC counts per ampere in 32.32 fixed point, so that `(current_bits * K) >> 48` are counts
/// (current bits are I16F16: one more shift by 16).
const DAC_COUNTS_PER_A_Q32: i64 = (2047i64 << 32) * 1000 / AMP_FULL_SCALE_MA;

/// Sampling and output of the control task.
pub struct ControlIo {
    tick: CounterHz<pac::TIM7>,
    motor: Qei<pac::TIM3>,
    scale: Qei<pac::TIM4>,
    dac: pac::DAC,
    amp_enable: Pin<'B', 0, Output<PushPull>>,
}

/// `Shutdown` requests are refused: there is nothing to exit to.
pub const ALLOW_SHUTDOWN: bool = false;

/// What `begin_tick` hands to the control task.
pub struct Tick {
    /// The counters, read before anything else in the tick.
    pub sample: Sample,
    /// Sequence number to answer with (PIL only).
    pub reply_seq: Option<u8>,
}

impl ControlIo {
    /// Acknowledges the tick interrupt and samples both encoder counters.
    #[inline(always)]
    pub fn begin_tick(&mut self) -> Option<Tick> {
        self.tick.clear_flags(Flag::Update);
        use stm32f4xx_hal::hal_02::Qei as _;
        Some(Tick {
            sample: Sample {
                motor_counter: self.motor.count(),
                scale_counter: self.scale.count(),
            },
            reply_seq: None,
        })
    }

    /// Runs `step`; the instruction count is not measured on the real board (0): DWT counts
    /// cycles, not instructions, and the budget is checked under QEMU.
    #[inline(always)]
    pub fn measure<R>(&mut self, step: impl FnOnce() -> R) -> (R, u32) {
        (step(), 0)
    }

    /// Sends the tick's current command to the amplifier; the enable line is high only while
    /// the drive is enabled with no fault latched.
    #[inline(always)]
    pub fn write_current(&mut self, out: &DriveOutput) {
        self.dac
            .dhr12r1()
            .write(|w| unsafe { w.daccdhr().bits(dac_code(out.current_a)) });
        if out.telemetry.amplifier_enabled {
            self.amp_enable.set_high();
        } else {
            self.amp_enable.set_low();
        }
    }
}

/// DAC code for a current command, saturated to the DAC's range.
fn dac_code(current_a: I16F16) -> u16 {
    let counts = (current_a.to_bits() as i64 * DAC_COUNTS_PER_A_Q32) >> 48;
    (DAC_ZERO as i64 + counts.clamp(-2047, 2047)) as u16
}

/// Clocks, encoder timers, DAC, control timer, link USART and the monotonic.
pub fn init(dp: pac::Peripherals, syst: cortex_m::peripheral::SYST, control_rate_hz: u32) -> Board {
    let mut rcc = dp.RCC.freeze(
        Config::hse(8.MHz())
            .sysclk(168.MHz())
            .hclk(168.MHz())
            .pclk1(42.MHz())
            .pclk2(84.MHz()),
    );
    let sysclk_hz = rcc.clocks.sysclk().raw();
    Mono::start(syst, sysclk_hz);

    let gpioa = dp.GPIOA.split(&mut rcc);
    let gpiob = dp.GPIOB.split(&mut rcc);

    // The amplifier stays off until the first tick says otherwise.
    let amp_enable = gpiob
        .pb0
        .into_push_pull_output_in_state(stm32f4xx_hal::gpio::PinState::Low);

    // DAC channel 1 on PA4, output buffer on, mid-scale (0 A) before it is enabled.
    let _pa4 = gpioa.pa4.into_analog();
    // SAFETY: a single read-modify-write of RCC during init, before any task runs.
    unsafe {
        (*pac::RCC::ptr())
            .apb1enr()
            .modify(|_, w| w.dacen().set_bit())
    };
    dp.DAC
        .dhr12r1()
        .write(|w| unsafe { w.daccdhr().bits(DAC_ZERO) });
    dp.DAC.cr().modify(|_, w| w.en1().set_bit());

    let motor = Qei::new(dp.TIM3, (gpioa.pa6, gpioa.pa7), &mut rcc);
    let scale = Qei::new(dp.TIM4, (gpiob.pb6, gpiob.pb7), &mut rcc);

    let usart = Serial::<_, u8>::new(
        dp.USART2,
        (gpioa.pa2, gpioa.pa3),
        serial::Config::default().baudrate(BAUD.bps()),
        &mut rcc,
    )
    .unwrap_or_else(|_| defmt::panic!("USART2 config"))
    .release()
    .0;
    let (rx, tx) = link_usart(usart);

    let mut tick = dp.TIM7.counter_hz(&mut rcc);
    tick.start(control_rate_hz.Hz())
        .unwrap_or_else(|_| defmt::panic!("TIM7 rate"));
    tick.listen(Event::Update);

    Board {
        control: ControlIo {
            tick,
            motor,
            scale,
            dac: dp.DAC,
            amp_enable,
        },
        rx,
        tx,
        sysclk_hz,
    }
}

/// PIL samples exist only under QEMU: refused (false).
pub fn pil_deliver(_seq: u8, _sample: Sample) -> bool {
    false
}

/// Mid-scale current and amplifier off, from any context (panic, HardFault, exit).
pub fn emergency_stop() {
    // SAFETY: two single-register writes that cannot conflict with an interrupted writer in a
    // harmful way: whatever it wrote, zero current and a low enable line win.
    unsafe {
        (*pac::DAC::ptr())
            .dhr12r1()
            .write(|w| w.daccdhr().bits(DAC_ZERO));
        (*pac::GPIOB::ptr()).bsrr().write(|w| w.br0().set_bit());
    }
}

/// Stops here for good: interrupts off, motor off; the log stays readable over RTT.
pub fn halt(_code: i32) -> ! {
    cortex_m::interrupt::disable();
    emergency_stop();
    loop {
        cortex_m::asm::wfi();
    }
}
