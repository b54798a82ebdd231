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
pub const FILE_BYTES: usize = 40;

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

/// The record's size in words.
const WORDS: usize = core::mem::size_of::<Record>() / 4;
const _: () = assert!(core::mem::size_of::<Record>() == WORDS * 4);

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
    // `get` and `zip`, not indexing: no slice panic inside the panic handler.
    let tail = bytes.get(start..).unwrap_or_default();
    let mut file = [0u8; FILE_BYTES];
    file.iter_mut().zip(tail).for_each(|(d, s)| *d = *s);
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

/// How the previous run ended, as its record says.
#[derive(Clone, Copy, Debug, PartialEq, Eq, defmt::Format)]
pub enum Ended {
    /// A panic at `line` of the file whose path ends in `file` (its last bytes, up to 40).
    Panic {
        /// The tail of the path, as the panic location gave it.
        file: [u8; FILE_BYTES],
        /// How many bytes of `file` hold it.
        file_len: usize,
        /// Line of the panic.
        line: u32,
    },
    /// A HardFault at `pc`.
    HardFault {
        /// Program counter of the faulting instruction.
        pc: u32,
    },
    /// An interrupt without a handler.
    UnexpectedInterrupt {
        /// Its number (`DefaultHandler`'s `irqn`, as 16 bits).
        irqn: u32,
    },
}

impl Ended {
    /// The file of a panic (empty for the others).
    pub fn file(&self) -> &[u8] {
        match self {
            Ended::Panic { file, file_len, .. } => file.get(..*file_len).unwrap_or_default(),
            _ => &[],
        }
    }
}

/// Reads and erases the previous run's record: `None` when there is none (or RAM that merely
/// looks like one fails its check). Call once, early in `init` (or from a test).
pub fn take() -> Option<Ended> {
    // SAFETY: `init` runs alone; the memory is plain words, read volatile because the compiler
    // cannot know what a previous run left there. Word by word in a loop: one volatile read of
    // the whole struct is unrolled into ~460 B of byte and word loads.
    let mut words = [0u32; WORDS];
    for (i, w) in words.iter_mut().enumerate() {
        // SAFETY: `i < WORDS` words of the `Record` (its size is `WORDS` words), word-aligned.
        *w = unsafe { ptr::read_volatile(ptr::addr_of!(RECORD).cast::<u32>().add(i)) };
    }
    // SAFETY: `Record` is `repr(C)` words and bytes of exactly `WORDS` words (checked at
    // compile time); every bit pattern is a valid `Record`.
    let rec = unsafe { core::mem::transmute::<[u32; WORDS], Record>(words) };
    // SAFETY: as above; erased so that the record is reported once.
    unsafe { ptr::write_volatile(ptr::addr_of_mut!(RECORD).cast::<u32>(), 0) };
    if rec.magic != MAGIC
        || rec.file_len as usize > FILE_BYTES
        || rec.check != checksum(rec.kind, rec.value, rec.file_len, &rec.file)
    {
        return None;
    }
    Some(match rec.kind {
        k if k == Kind::Panic as u32 => Ended::Panic {
            file: rec.file,
            file_len: rec.file_len as usize,
            line: rec.value,
        },
        k if k == Kind::HardFault as u32 => Ended::HardFault { pc: rec.value },
        _ => Ended::UnexpectedInterrupt { irqn: rec.value },
    })
}

/// [`take`], and logs the record; returns true if there was one.
pub fn take_and_log() -> bool {
    let Some(ended) = take() else {
        return false;
    };
    match ended {
        // Bytes shown as text by the host (`:a`): no UTF-8 validation (~370 B) on the drive.
        Ended::Panic { line, .. } => defmt::error!(
            "previous run ended in panic at {=[u8]:a}:{=u32}",
            ended.file(),
            line
        ),
        Ended::HardFault { pc } => {
            defmt::error!("previous run ended in HardFault at pc={=u32:#010x}", pc)
        }
        Ended::UnexpectedInterrupt { irqn } => {
            defmt::error!("previous run ended in unexpected interrupt {=u32}", irqn)
        }
    }
    true
}
