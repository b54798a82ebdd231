//! Clock start-up with bounded waits: HSE 8 MHz (crystal, or an oscillator module with the
//! `hse-bypass` feature) -> PLL 168 MHz, falling back to HSI 16 MHz -> PLL 168 MHz when the HSE
//! does not start. The HAL's `rcc.freeze()` waits on HSERDY and PLLRDY forever: a missing or
//! broken crystal would hang the board silently before the first log line.
//!
//! Both sources give VCO input 1 MHz, VCO 336 MHz, SYSCLK = VCO / 2 = 168 MHz, 48 MHz clock =
//! VCO / 7; AHB 168 MHz, APB1 42 MHz (timers 84 MHz), APB2 84 MHz.

use stm32f4xx_hal::pac;

/// HSE crystal / oscillator frequency.
pub const HSE_HZ: u32 = 8_000_000;
/// HSI frequency (factory-trimmed RC, +-1 % at 25 C).
pub const HSI_HZ: u32 = 16_000_000;
const SYSCLK_HZ: u32 = 168_000_000;

/// Polls of HSERDY before giving up. A poll (peripheral read, test, branch, count) takes at
/// least ~5 cycles at 16 MHz HSI: >= 100 ms, against a crystal start-up of about 2 ms.
const HSE_POLLS: u32 = 320_000;
/// Polls of PLLRDY / SWS (lock takes well under 1 ms): >= 30 ms.
const PLL_POLLS: u32 = 100_000;

/// What the clock tree runs from.
#[derive(Clone, Copy, PartialEq, Eq, defmt::Format)]
pub enum Source {
    /// HSE -> PLL 168 MHz: the intended configuration; the clock security system is on.
    Hse,
    /// HSE did not start in time: HSI -> PLL 168 MHz (less accurate; no clock security).
    HsiFallback,
    /// The PLL did not lock: HSI 16 MHz, no PLL, everything slow (the drive is faulted).
    HsiNoPll,
}

/// Bus frequencies after start-up.
#[derive(Clone, Copy)]
pub struct Clocks {
    pub source: Source,
    pub sysclk_hz: u32,
    /// APB1 peripheral clock (USART2, DAC).
    pub pclk1_hz: u32,
    /// Clock of the APB1 timers (TIM3, TIM4, TIM7): twice PCLK1 when APB1 is divided.
    pub tim1_hz: u32,
}

/// Polls `ready` up to `polls` times; true as soon as it holds.
fn wait(polls: u32, mut ready: impl FnMut() -> bool) -> bool {
    for _ in 0..polls {
        if ready() {
            return true;
        }
    }
    ready()
}

/// Starts the clocks. Never blocks for more than a few hundred milliseconds.
pub fn start(rcc: &pac::RCC, flash: &pac::FLASH, pwr: &pac::PWR) -> Clocks {
    // Voltage scale 1 (the reset value on the F405; set anyway: 168 MHz needs it).
    rcc.apb1enr().modify(|_, w| w.pwren().set_bit());
    let _ = rcc.apb1enr().read();
    cortex_m::asm::dsb();
    pwr.cr().modify(|_, w| w.vos().set_bit());

    // HSEBYP may only change while HSE is off.
    rcc.cr().modify(|_, w| w.hseon().clear_bit());
    rcc.cr()
        .modify(|_, w| w.hsebyp().bit(cfg!(feature = "hse-bypass")));
    rcc.cr().modify(|_, w| w.hseon().set_bit());
    let hse = wait(HSE_POLLS, || rcc.cr().read().hserdy().bit_is_set());
    if !hse {
        rcc.cr()
            .modify(|_, w| w.hseon().clear_bit().hsebyp().clear_bit());
    }

    // 5 wait states for 168 MHz at 2.7-3.6 V, prefetch and caches on; set before the speed-up.
    flash.acr().modify(|_, w| unsafe {
        w.latency()
            .bits(5)
            .prften()
            .set_bit()
            .icen()
            .set_bit()
            .dcen()
            .set_bit()
    });

    // PLL: M makes 1 MHz from either source; N 336, P /2 (168 MHz), Q /7 (48 MHz).
    let (m, src_hse) = if hse {
        (HSE_HZ / 1_000_000, true)
    } else {
        (HSI_HZ / 1_000_000, false)
    };
    rcc.pllcfgr().modify(|_, w| unsafe {
        w.pllm()
            .bits(m as u8)
            .plln()
            .bits(336)
            .pllp()
            .bits(0b00)
            .pllq()
            .bits(7)
            .pllsrc()
            .bit(src_hse)
    });
    // AHB /1, APB1 /4 (42 MHz), APB2 /2 (84 MHz), set while still on HSI.
    rcc.cfgr().modify(|_, w| unsafe {
        w.hpre()
            .bits(0b0000)
            .ppre1()
            .bits(0b101)
            .ppre2()
            .bits(0b100)
    });
    rcc.cr().modify(|_, w| w.pllon().set_bit());
    let locked = wait(PLL_POLLS, || rcc.cr().read().pllrdy().bit_is_set()) && {
        rcc.cfgr().modify(|_, w| unsafe { w.sw().bits(0b10) });
        wait(PLL_POLLS, || rcc.cfgr().read().sws().bits() == 0b10)
    };

    if !locked {
        // Stay on (or return to) HSI with undivided buses: slow but consistent.
        rcc.cfgr().modify(|_, w| unsafe {
            w.sw()
                .bits(0b00)
                .hpre()
                .bits(0)
                .ppre1()
                .bits(0)
                .ppre2()
                .bits(0)
        });
        let _ = wait(PLL_POLLS, || rcc.cfgr().read().sws().bits() == 0b00);
        rcc.cr().modify(|_, w| w.pllon().clear_bit());
        return Clocks {
            source: Source::HsiNoPll,
            sysclk_hz: HSI_HZ,
            pclk1_hz: HSI_HZ,
            tim1_hz: HSI_HZ,
        };
    }
    if hse {
        // Clock security: an HSE failure now switches to HSI and raises the NMI.
        rcc.cr().modify(|_, w| w.csson().set_bit());
    }
    Clocks {
        source: if hse {
            Source::Hse
        } else {
            Source::HsiFallback
        },
        sysclk_hz: SYSCLK_HZ,
        pclk1_hz: SYSCLK_HZ / 4,
        tim1_hz: SYSCLK_HZ / 2,
    }
}
