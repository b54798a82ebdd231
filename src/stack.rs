//! Stack high-water mark: paint the free stack at boot, find the deepest overwritten word later.
//!
//! RTIC runs `init`, every task and every handler on the one main stack (MSP), which grows down
//! from `_stack_start` (end of RAM) towards `_stack_end` (end of `.bss`/`.uninit`, from
//! cortex-m-rt's linker script).

use core::ptr;

const PAINT: u32 = 0xDEAD_C0DE;
/// Words just below the live stack pointer left untouched while painting: `paint` itself and
/// anything an interrupt pushes meanwhile live there.
const GUARD_BYTES: usize = 256;

extern "C" {
    static _stack_start: u32;
    static _stack_end: u32;
}

fn bounds() -> (usize, usize) {
    // Only the addresses of the linker symbols are taken, never their contents.
    (
        ptr::addr_of!(_stack_end) as usize,
        ptr::addr_of!(_stack_start) as usize,
    )
}

/// Fills the unused part of the stack with a pattern. Call once, early in `init`.
pub fn paint() {
    let (bottom, _) = bounds();
    let sp = cortex_m::register::msp::read() as usize;
    let mut at = bottom;
    while at + 4 <= sp.saturating_sub(GUARD_BYTES) {
        // SAFETY: [bottom, sp - guard) is RAM that no live frame uses: the stack grows down from
        // `_stack_start` and the current frame lies above `sp`.
        unsafe { ptr::write_volatile(at as *mut u32, PAINT) };
        at += 4;
    }
}

/// Deepest stack use since `paint`, in bytes from the top of RAM.
pub fn peak_bytes() -> u32 {
    let (bottom, top) = bounds();
    let mut at = bottom;
    // SAFETY: reads of RAM between the end of statics and the top of the stack.
    while at < top && unsafe { ptr::read_volatile(at as *const u32) } == PAINT {
        at += 4;
    }
    (top - at) as u32
}
