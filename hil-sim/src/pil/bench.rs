//! PIL runs that check and measure the firmware: the same plant, samples and commands drive the
//! core in-process and the firmware under QEMU; every tick's output must be identical, and the
//! firmware reports how many instructions each `Drive::control` took.

use std::path::{Path, PathBuf};

use estimator_core::drive::{Command, Drive, DriveConfig, Output, Sample};
use estimator_core::model::{ModelKind, ModelParams};

use super::{PilController, PilError, PilOptions, StepCounts};
use crate::run::keepalive_ticks;
use crate::{Plant, PlantParams};

/// One move of a bench run: target (mm), speed (mm/s), acceleration (mm/s^2).
pub type Move = (f64, f64, f64);

/// The bench's moves: out, back past the start (a reversal), and a short reversal.
pub const MOVES: [Move; 3] = [
    (80.0, 200.0, 4000.0),
    (40.0, 150.0, 3000.0),
    (42.0, 20.0, 1000.0),
];
/// Where the carriage starts, mm.
pub const START_MM: f64 = 50.0;

/// Result of one PIL run.
#[derive(Clone, Debug)]
pub struct RunReport {
    /// Model in use.
    pub model: ModelKind,
    /// Ticks run.
    pub ticks: u64,
    /// `Drive::control` instruction counts.
    pub counts: StepCounts,
    /// First tick whose firmware output differed from the in-process core's, if any.
    pub first_mismatch: Option<u64>,
    /// The firmware's stack high-water mark after the run, bytes.
    pub stack_peak_bytes: u32,
    /// Frames the firmware accepted / rejected.
    pub frames: (u32, u32),
    /// QEMU's exit status after the shutdown request.
    pub exit_status: i32,
    /// Final carriage position of the plant, mm.
    pub final_mm: f64,
}

/// The calibration image both sides load before a run with a model: the paper's parameters
/// (Model 3 sampled from Model 1), and Model 4 with the belt observer of the paper rig's
/// physics (its guide profile in every point, a unit weight), as a calibration by `hil-sim
/// calibrate` has it; built exactly as for a calibration it writes.
pub fn paper_image() -> Result<Vec<u8>, PilError> {
    use estimator_core::model::belt::{BeltParams, MAX_GUIDE_BINS};
    let cfg = DriveConfig::paper_rig();
    let mut physics = BeltParams::PAPER;
    physics.guide_bins = MAX_GUIDE_BINS;
    for (k, d) in physics.guide_delta_n.iter_mut().enumerate() {
        *d = 0.8 * (k as f64 * 0.6).sin();
    }
    let mut params = ModelParams::PAPER;
    params.model4.belt = Some(estimator_core::model::BeltTerm {
        physics,
        tick_s: 1.0 / cfg.settings.rate_hz,
        step_ticks: crate::calibrate::BELT_STEP_TICKS,
        weight: -1.0,
        rest_um: [-130.0, 140.0],
        half_travel_mm: [0.3, 10.0],
        fast_share: 0.6,
    });
    Ok(estimator_core::image::of_params(
        &params,
        &cfg.settings.rig,
    )?)
}

/// The in-process core, the firmware and the plant, stepped together.
struct Lockstep {
    host: Drive,
    fw: PilController,
    plant: Plant,
    dt: f64,
    /// Ticks between two of the host's keep-alives ([`keepalive_ticks`]).
    keepalive: u64,
    ticks: u64,
    first_mismatch: Option<u64>,
}

impl Lockstep {
    /// One tick: both controllers see the same sample; the firmware's current drives the plant.
    fn step(&mut self) -> Result<Output, PilError> {
        let s = Sample {
            motor_counter: self.plant.motor_counter(),
            scale_counter: self.plant.scale_counter(),
        };
        // A host keeps both link watchdogs fed, as a run's does.
        if self.ticks.is_multiple_of(self.keepalive) {
            self.host.link_alive();
            self.fw.status()?;
        }
        let a = self.host.step(s);
        let b = self.fw.step_sample(s)?;
        if a != b && self.first_mismatch.is_none() {
            self.first_mismatch = Some(self.ticks);
        }
        self.plant.step(b.current_a.to_num::<f64>(), self.dt);
        self.ticks += 1;
        Ok(b)
    }

    /// The same command to both; the bench needs both to accept it.
    fn command(&mut self, c: Command) -> Result<(), PilError> {
        let core = self.host.command(c);
        let firmware = match self.fw.send_command(c) {
            Ok(()) => Ok(()),
            Err(PilError::Refused(e)) => Err(e),
            Err(link) => return Err(link),
        };
        if core.is_ok() && firmware.is_ok() {
            return Ok(());
        }
        Err(PilError::NotAccepted {
            command: c,
            core,
            firmware,
        })
    }
}

/// Runs the bench moves with `model`, in lockstep: in-process core and firmware side by side on
/// one plant (driven by the firmware's current). Stops at the first mismatch.
pub fn run_model(opts: &PilOptions, model: ModelKind) -> Result<RunReport, PilError> {
    // The firmware boots uncalibrated; so does its host twin.
    let cfg = DriveConfig {
        model: estimator_core::drive::Models::Image(&[]),
        ..DriveConfig::paper_rig()
    };
    let host = Drive::new(&cfg)?;
    let fw = PilController::start(opts)?;
    let plant = Plant::new(&PlantParams::paper_rig(), START_MM, 1)
        .map_err(|e| PilError::Sim(Box::new(e)))?;
    let mut ls = Lockstep {
        host,
        fw,
        plant,
        dt: 1.0 / cfg.settings.rate_hz,
        keepalive: keepalive_ticks(1.0 / cfg.settings.rate_hz),
        ticks: 0,
        first_mismatch: None,
    };

    ls.step()?;
    let start_um = (START_MM * 1000.0).round() as i32;
    let scale_um = (ls.plant.scale_counts() as f64 * 0.5).round() as i32;
    ls.command(Command::Home {
        position_um: start_um,
        scale_um,
    })?;
    if model != ModelKind::None {
        let image = paper_image()?;
        ls.host.load_calibration(&image)?;
        ls.fw.load_calibration(&image)?;
    }
    ls.command(Command::SelectModel(model))?;
    ls.command(Command::Enable)?;
    'moves: for &(to_mm, v, a) in &MOVES {
        ls.command(Command::MoveMotorTo {
            target_um: (to_mm * 1000.0).round() as i32,
            velocity_um_s: (v * 1000.0).round() as u32,
            accel_um_s2: (a * 1000.0).round() as u32,
        })?;
        // Until the move ends, then 50 ms at rest; bounded.
        let mut rest = 0;
        for _ in 0..40_000 {
            let out = ls.step()?;
            if !out.telemetry.faults.is_clear() {
                return Err(PilError::Fault(out.telemetry.faults));
            }
            if ls.first_mismatch.is_some() {
                break 'moves;
            }
            rest = if out.telemetry.moving { 0 } else { rest + 1 };
            if rest >= 100 {
                break;
            }
        }
    }
    let status = ls.fw.status()?;
    let counts = ls.fw.counts;
    let final_mm = ls.plant.carriage_mm();
    let (ticks, first_mismatch) = (ls.ticks, ls.first_mismatch);
    let exit_status = ls.fw.shutdown(0)?;
    Ok(RunReport {
        model,
        ticks,
        counts,
        first_mismatch,
        stack_peak_bytes: status.stack_peak_bytes,
        frames: (status.frames_ok, status.frames_bad),
        exit_status,
        final_mm,
    })
}

/// Flash and static RAM of a firmware ELF, from its section headers.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Footprint {
    /// Bytes in flash: vector table, code, read-only data and `.data`'s initial values.
    pub flash_bytes: u64,
    /// Bytes of static RAM: `.data`, `.bss` and `.uninit`.
    pub static_ram_bytes: u64,
}

/// Reads the footprint of `elf` (32-bit little-endian ELF).
pub fn footprint(elf: &Path) -> Result<Footprint, crate::error::Error> {
    use crate::error::Error;
    let b = crate::input::read_file(elf).map_err(|e| Error::io(elf, e))?;
    let u16_at = |o: usize| {
        b.get(o..o + 2)
            .map(|s| u16::from_le_bytes([s[0], s[1]]) as u64)
    };
    let u32_at = |o: usize| {
        b.get(o..o + 4)
            .map(|s| u32::from_le_bytes([s[0], s[1], s[2], s[3]]) as u64)
    };
    if b.get(..5) != Some(&[0x7f, b'E', b'L', b'F', 1][..]) {
        return Err(Error::NotElf32(elf.to_path_buf()));
    }
    let bad = || Error::TruncatedElf(elf.to_path_buf());
    let shoff = u32_at(0x20).ok_or_else(bad)? as usize;
    let shentsize = u16_at(0x2e).ok_or_else(bad)? as usize;
    let shnum = u16_at(0x30).ok_or_else(bad)? as usize;
    const SHF_ALLOC: u64 = 2;
    const SHT_NOBITS: u64 = 8;
    let mut fp = Footprint::default();
    for i in 0..shnum {
        let o = shoff + i * shentsize;
        let ty = u32_at(o + 4).ok_or_else(bad)?;
        let flags = u32_at(o + 8).ok_or_else(bad)?;
        let addr = u32_at(o + 12).ok_or_else(bad)?;
        let size = u32_at(o + 20).ok_or_else(bad)?;
        if flags & SHF_ALLOC == 0 || size == 0 {
            continue;
        }
        let in_ram = (0x2000_0000..0x2002_0000).contains(&addr);
        if in_ram {
            fp.static_ram_bytes += size;
        }
        // Loaded bytes live in flash, including `.data`'s initial values.
        if ty != SHT_NOBITS {
            fp.flash_bytes += size;
        }
    }
    Ok(fp)
}

/// Everything `qemu-run --bench` reports.
#[derive(Clone, Debug)]
pub struct BenchReport {
    /// The ELF measured.
    pub elf: PathBuf,
    /// One PIL run per model.
    pub runs: Vec<RunReport>,
    /// Its footprint.
    pub footprint: Footprint,
}

/// Runs the bench for every model.
pub fn bench(opts: &PilOptions) -> Result<BenchReport, PilError> {
    let footprint = footprint(&opts.elf).map_err(|e| PilError::Sim(Box::new(e)))?;
    let mut runs = Vec::new();
    for model in ModelKind::ALL {
        runs.push(run_model(opts, model)?);
    }
    Ok(BenchReport {
        elf: opts.elf.clone(),
        runs,
        footprint,
    })
}
