//! Processor-in-the-loop: the real firmware under QEMU, paced by the simulated plant.
//!
//! [`qemu`] starts and supervises QEMU and decodes the firmware's defmt log.

pub mod qemu;
