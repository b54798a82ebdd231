//! What the previous run left behind: the reset cause (RCC_CSR, read once at boot) and a small
//! record of how it ended (panic location, HardFault PC, unexpected interrupt), kept in RAM that
//! the start-up code does not initialise (`.uninit`), so that it survives the watchdog reset
//! that follows a halt and the next boot can log it.

use core::mem::MaybeUninit;
use core::ptr;

/// Reset-cause bits, as reported in the status reply.
pub use belt_link::reset_cause;

/// Logs the reset cause by name, one line ("unknown" when no flag is set, e.g. under QEMU).
pub fn log_reset_cause(bits: u8) {
    if bits == 0 {
        defmt::info!("reset cause: unknown");
        return;
    }
    for (bit, name) in reset_cause::NAMES {
        if bits & bit != 0 {
            defmt::info!("reset cause: {=str}", name);
        }
    }
}

/// How the previous run ended.
#[derive(Clone, Copy, PartialEq, Eq)]
#[repr(u32)]
enum Kind {
    Panic = 1,
    HardFault = 2,
    UnexpectedInterrupt = 3,
}

const MAGIC: u32 = 0x4245_4C54; // "BELT"
/// Tail of the panicking file's path kept (the end names the file).
const FILE_BYTES: usize = 40;

#[repr(C)]
struct Record {
    magic: u32,
    kind: u32,
    /// Line (panic), PC (HardFault) or IRQ number.
    value: u32,
    file_len: u32,
    file: [u8; FILE_BYTES],
    /// Guards against RAM that merely happens to hold the magic (power-on contents).
    check: u32,
}

#[link_section = ".uninit.belt_drive.postmortem"]
static mut RECORD: MaybeUninit<Record> = MaybeUninit::uninit();

fn checksum(kind: u32, value: u32, file_len: u32, file: &[u8; FILE_BYTES]) -> u32 {
    let mut h = 0x811C_9DC5u32 ^ kind;
    for w in [value, file_len] {
        h = (h ^ w).wrapping_mul(0x0100_0193);
    }
    for &b in file {
        h = (h ^ b as u32).wrapping_mul(0x0100_0193);
    }
    h
}

fn write(kind: Kind, value: u32, path: &str) {
    let bytes = path.as_bytes();
    // The last FILE_BYTES bytes, starting on a character boundary.
    let mut start = bytes.len().saturating_sub(FILE_BYTES);
    while !path.is_char_boundary(start) {
        start += 1;
    }
    let tail = &bytes[start..];
    let mut file = [0u8; FILE_BYTES];
    file[..tail.len()].copy_from_slice(tail);
    let rec = Record {
        magic: MAGIC,
        kind: kind as u32,
        value,
        file_len: tail.len() as u32,
        file,
        check: checksum(kind as u32, value, tail.len() as u32, &file),
    };
    // SAFETY: called with interrupts masked from the panic / fault handlers only, once.
    unsafe { ptr::write_volatile(ptr::addr_of_mut!(RECORD).cast::<Record>(), rec) };
}

/// Records a panic (file and line). Call with interrupts masked, motor already off.
pub fn record_panic(file: &str, line: u32) {
    write(Kind::Panic, line, file);
}

/// Records a HardFault at `pc`.
pub fn record_hardfault(pc: u32) {
    write(Kind::HardFault, pc, "");
}

/// Records an unexpected interrupt (the `DefaultHandler`'s IRQ number).
pub fn record_interrupt(irqn: i16) {
    write(Kind::UnexpectedInterrupt, irqn as u16 as u32, "");
}

/// Reads and erases the previous run's record; logs it and returns true if there was one.
/// Call once, early in `init`.
pub fn take_and_log() -> bool {
    // SAFETY: `init` runs alone; the memory is plain words (any bit pattern is a valid
    // `Record`), read volatile because the compiler cannot know what a previous run left there.
    let rec = unsafe { ptr::read_volatile(ptr::addr_of!(RECORD).cast::<Record>()) };
    // SAFETY: as above; erased so that the record is reported once.
    unsafe { ptr::write_volatile(ptr::addr_of_mut!(RECORD).cast::<u32>(), 0) };
    if rec.magic != MAGIC
        || rec.file_len as usize > FILE_BYTES
        || rec.check != checksum(rec.kind, rec.value, rec.file_len, &rec.file)
    {
        return false;
    }
    let file = core::str::from_utf8(&rec.file[..rec.file_len as usize]).unwrap_or("?");
    match rec.kind {
        k if k == Kind::Panic as u32 => defmt::error!(
            "previous run ended in panic at {=str}:{=u32}",
            file,
            rec.value
        ),
        k if k == Kind::HardFault as u32 => defmt::error!(
            "previous run ended in HardFault at pc={=u32:#010x}",
            rec.value
        ),
        _ => defmt::error!(
            "previous run ended in unexpected interrupt {=u32}",
            rec.value
        ),
    }
    true
}
