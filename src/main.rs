//! belt-drive firmware: the RTIC 2 application.
//!
//! Thin on purpose: every decision lives in `estimator-core` (tested on the host and on the
//! target); the tasks here only move bytes and samples between the hardware and the core.
//!
//! | task      | trigger                       | priority | does                                  |
//! |-----------|-------------------------------|----------|---------------------------------------|
//! | `control` | TIM7 (board: timer at the control rate; QEMU: pended per PIL sample) | 3 | sample, `Drive::step`, current out |
//! | `link`    | USART2 (RXNE / TXE)           | 2        | frame decoding, commands, replies     |
//! | `idle`    | -                             | 0        | `wfi`                                 |
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!("belt-drive is firmware: build it with `cargo fw` or `cargo fw-qemu`");
}

#[cfg(target_os = "none")]
use belt_drive as _;

#[cfg(target_os = "none")]
#[rtic::app(device = stm32f4xx_hal::pac, peripherals = true)]
mod app {
    use core::sync::atomic::{AtomicU16, Ordering};

    use belt_drive::drive::{Command, CommandError, Drive, DriveConfig, Faults, Models, Telemetry};
    use belt_drive::hardware::{self, ControlIo, LinkRx};
    use belt_drive::outbox::Outbox;
    use belt_drive::stack;
    use estimator_core::blob::{self, BlobError};
    use estimator_core::link::{answer, Effect, Endpoint, Event};
    use estimator_core::link::{LinkError, Message, Receiver, Reply, Request, WireTelemetry};

    /// Telemetry stream decimation, 0 = off.
    static STREAM_EVERY: AtomicU16 = AtomicU16::new(0);

    #[shared]
    struct Shared {
        drive: Drive,
        outbox: Outbox,
    }

    #[local]
    struct Local {
        io: ControlIo,
        rx: LinkRx,
        receiver: Receiver,
        endpoint: &'static mut Endpoint,
        /// The previous tick's telemetry (for move start/end and fault logs).
        prev: Telemetry,
    }

    #[init(local = [endpoint_storage: Endpoint = Endpoint::new()])]
    fn init(cx: init::Context) -> (Shared, Local) {
        stack::paint();
        // Table 2 as an embedded blob (made by build.rs): built straight into fixed point.
        static PAPER_BLOB: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/paper_blob.bin"));
        let config = DriveConfig {
            model: Models::Blob(PAPER_BLOB),
            ..DriveConfig::paper_rig()
        };
        // The configured rate is a whole number of hertz (the paper rig: 2 kHz).
        let rate_hz = config.rate_hz as u32;
        let board = hardware::init(cx.device, cx.core.SYST, rate_hz);
        defmt::info!(
            "belt-drive {=str} on {=str}: sysclk {=u32} Hz, control tick {=u32} Hz",
            env!("CARGO_PKG_VERSION"),
            hardware::NAME,
            board.sysclk_hz,
            rate_hz
        );
        let drive = match Drive::new(&config) {
            Ok(d) => d,
            // The built-in configuration is tested on the host: this cannot happen in a release.
            Err(e) => defmt::panic!("drive configuration refused: {=str}", e.field()),
        };
        defmt::info!(
            "drive disabled, model {=str} (paper Table 2 parameters), no calibration blob loaded: waiting for the link",
            drive.telemetry().model.as_str()
        );
        // The boot announcement: an unsolicited status (sequence 0) tells the host that the
        // link is up (QEMU drops bytes sent before the USART is enabled) and that the drive
        // (re)started, disabled.
        let receiver = Receiver::new();
        let endpoint: &'static mut Endpoint = cx.local.endpoint_storage;
        let mut outbox = Outbox::new(board.tx);
        outbox.send(0, &Reply::Status(endpoint.status(&drive, &receiver, 0, 0)));
        (
            Shared { drive, outbox },
            Local {
                io: board.control,
                rx: board.rx,
                receiver,
                endpoint,
                prev: Telemetry::default(),
            },
        )
    }

    #[idle]
    fn idle(_: idle::Context) -> ! {
        loop {
            // Sleep until the next interrupt; under QEMU with -icount this also skips idle time.
            cortex_m::asm::wfi();
        }
    }

    /// One control tick: sample the counters, `Drive::step`, write the current.
    ///
    /// Budget: `Drive::step` at most 400 instructions per tick with Model 3, counted exactly
    /// under QEMU by `tools/bench-target.sh` (which prints the current figures); the whole task,
    /// sampling and reporting included, well under a tenth of a 2 kHz tick (84,000 cycles at
    /// 168 MHz).
    #[task(binds = TIM7, priority = 3, local = [io, prev, since_stream: u16 = 0], shared = [drive, outbox])]
    fn control(cx: control::Context) {
        let control::LocalResources {
            io,
            since_stream,
            prev,
            ..
        } = cx.local;
        let control::SharedResources {
            mut drive,
            mut outbox,
            ..
        } = cx.shared;
        let Some(tick) = io.begin_tick() else { return };

        let (out, instructions) = drive.lock(|d| io.measure(|| d.step(tick.sample)));
        io.write_current(&out);

        // Everything below is reporting; the motor already has its current.
        let t = out.telemetry;
        if let Some(seq) = tick.reply_seq {
            outbox.lock(|o| o.send(seq, &answer(&out, instructions)));
        }
        let every = STREAM_EVERY.load(Ordering::Relaxed);
        *since_stream += 1;
        if every != 0 && *since_stream >= every {
            *since_stream = 0;
            outbox.lock(|o| o.send(0, &Reply::Telemetry(WireTelemetry::from(&t))));
        }
        defmt::trace!(
            "tick {=u32}: x_PE {=i32} set {=i32} I {=i32} (I16F16 bits), {=u32} instr",
            t.tick,
            t.motor_counts,
            t.setpoint_counts,
            t.current_a.to_bits(),
            instructions
        );
        log_transitions(prev, &t);
        *prev = t;
    }

    /// Logs a move's start and end and every change of the fault bits.
    fn log_transitions(prev: &Telemetry, t: &Telemetry) {
        if t.moving && !prev.moving {
            defmt::info!(
                "move start at {=i32} counts (tick {=u32})",
                t.motor_counts,
                t.tick
            );
        }
        if !t.moving && prev.moving {
            defmt::info!(
                "move end at {=i32} counts, following error {=i32} counts (tick {=u32})",
                t.motor_counts,
                t.following_error_counts,
                t.tick
            );
        }
        let new = t.faults.0 & !prev.faults.0;
        for (bit, name) in Faults::NAMES {
            if new & bit != 0 {
                defmt::error!(
                    "fault {=str} at {=i32} counts: zero current, amplifier disabled",
                    name,
                    t.motor_counts
                );
            }
        }
    }

    /// The link: bytes in, frames decoded, commands applied, replies queued; also drains the
    /// transmit queue on TXE.
    #[task(binds = USART2, priority = 2, local = [rx, receiver, endpoint], shared = [drive, outbox])]
    fn link(cx: link::Context) {
        let link::LocalResources {
            rx,
            receiver,
            endpoint,
            ..
        } = cx.local;
        let link::SharedResources {
            mut drive,
            mut outbox,
            ..
        } = cx.shared;
        while let Some(byte) = rx.read() {
            let frame = match receiver.push::<Request>(byte) {
                None => continue,
                Some(Err(r)) => {
                    // Every rejection is counted and answered; the log keeps the first few and
                    // then one line per thousand, so that a flood cannot starve the log.
                    let bad = receiver.frames_bad;
                    if bad <= 10 || bad % 1000 == 0 {
                        defmt::warn!(
                            "link: frame rejected: {=str} (kind {=u8:#04x}), {=u32} bad so far",
                            error_name(r.error),
                            r.kind,
                            bad
                        );
                    } else {
                        defmt::debug!("link: frame rejected: {=str}", error_name(r.error));
                    }
                    let reply = Reply::Error {
                        of: r.kind,
                        reason: r.error,
                        detail: 0,
                    };
                    outbox.lock(|o| o.send(r.seq, &reply));
                    continue;
                }
                Some(Ok(f)) => f,
            };
            let (effect, event) = drive.lock(|d| endpoint.handle(&frame.msg, d));
            log_event(&event);
            let reply = match effect {
                Effect::Reply(r) => r,
                Effect::Tick(sample) => {
                    if hardware::pil_deliver(frame.seq, sample) {
                        continue; // `control` answers.
                    }
                    not_supported(&frame.msg)
                }
                Effect::Status => {
                    let peak = stack::peak_bytes();
                    Reply::Status(drive.lock(|d| endpoint.status(d, receiver, peak, 0)))
                }
                Effect::Stream(n) => {
                    defmt::info!("telemetry stream every {=u16} ticks (0 = off)", n);
                    STREAM_EVERY.store(n, Ordering::Relaxed);
                    Reply::Ack {
                        of: frame.msg.kind(),
                    }
                }
                Effect::Calibrate(len) => {
                    // Milliseconds of soft-float: decoded here, outside the drive's lock, so the
                    // control task keeps its ticks; only the swap below holds the lock.
                    let rig = drive.lock(|d| *d.rig());
                    let result = blob::decode_coeffs(endpoint.calibration(len), &rig)
                        .and_then(|c| drive.lock(|d| d.set_models(c)));
                    let (reply, event) = endpoint.calibration_done(len, result);
                    log_event(&event);
                    reply
                }
                Effect::Shutdown(code) => {
                    if !hardware::ALLOW_SHUTDOWN {
                        not_supported(&frame.msg)
                    } else {
                        let t = drive.lock(|d| d.telemetry());
                        defmt::info!(
                            "shutdown {=u8}: {=u32} ticks, frames ok {=u32} bad {=u32}, stack peak {=u32} bytes",
                            code,
                            t.tick,
                            receiver.frames_ok,
                            receiver.frames_bad,
                            stack::peak_bytes()
                        );
                        outbox.lock(|o| {
                            o.send(
                                frame.seq,
                                &Reply::Ack {
                                    of: frame.msg.kind(),
                                },
                            );
                            o.flush()
                        });
                        hardware::halt(code as i32)
                    }
                }
            };
            outbox.lock(|o| o.send(frame.seq, &reply));
        }
        outbox.lock(|o| o.pump());
    }

    fn not_supported(req: &Request) -> Reply {
        defmt::warn!(
            "link: request kind {=u8:#04x} not supported on this board",
            req.kind()
        );
        Reply::Error {
            of: req.kind(),
            reason: LinkError::NotSupported,
            detail: 0,
        }
    }

    fn log_event(e: &Event) {
        match *e {
            Event::None => {}
            Event::Applied(Command::MoveTo {
                target_um,
                velocity_um_s,
                accel_um_s2,
            }) => defmt::info!(
                "move to {=i32} um at {=u32} um/s, {=u32} um/s^2",
                target_um,
                velocity_um_s,
                accel_um_s2
            ),
            Event::Applied(Command::SelectModel(m)) => {
                defmt::info!("model selected: {=str}", m.as_str())
            }
            Event::Applied(Command::Home {
                position_um,
                scale_um,
            }) => {
                defmt::info!(
                    "homed: motor at {=i32} um, scale at {=i32} um",
                    position_um,
                    scale_um
                )
            }
            Event::Applied(c) => defmt::info!("command: {=str}", command_name(&c)),
            Event::Refused(c, why) => defmt::warn!(
                "command {=str} refused: {=str}",
                command_name(&c),
                command_error_name(why)
            ),
            Event::CalibrationBegun { total_len } => {
                defmt::info!("calibration transfer: {=u32} bytes announced", total_len)
            }
            Event::CalibrationRefused(detail) => {
                defmt::warn!("calibration transfer step refused (detail {=u8})", detail)
            }
            Event::CalibrationLoaded { len } => {
                defmt::info!("calibration loaded ({=u32} bytes): Model 3 available", len)
            }
            Event::CalibrationRejected(e) => {
                defmt::error!(
                    "calibration rejected: {=str}; previous tables kept",
                    blob_error_name(e)
                )
            }
        }
    }

    fn command_name(c: &Command) -> &'static str {
        match c {
            Command::MoveTo { .. } => "move",
            Command::Stop => "stop",
            Command::Enable => "enable",
            Command::Disable => "disable",
            Command::ClearFaults => "clear faults",
            Command::SelectModel(_) => "select model",
            Command::Home { .. } => "home",
        }
    }

    fn command_error_name(e: CommandError) -> &'static str {
        match e {
            CommandError::TargetOutOfTravel => "target outside the travel",
            CommandError::VelocityOutOfRange => "velocity out of range",
            CommandError::AccelOutOfRange => "acceleration out of range",
            CommandError::NotEnabled => "drive not enabled (or faulted)",
            CommandError::Busy => "busy (moving)",
            CommandError::NotHomed => "not homed",
        }
    }

    fn blob_error_name(e: BlobError) -> &'static str {
        match e {
            BlobError::Truncated => "truncated",
            BlobError::TooLong => "too long",
            BlobError::BadMagic => "bad magic",
            BlobError::UnsupportedVersion(_) => "unsupported version",
            BlobError::BadChecksum => "checksum mismatch",
            BlobError::RigMismatch => "calibrated on another rig",
            BlobError::BadCount(_) => "table count out of bounds",
            BlobError::Invalid(_) => "a value failed the model checks",
            BlobError::Busy => "drive moving",
            BlobError::BufferTooSmall | BlobError::Unrepresentable(_) => "encoder error",
        }
    }

    fn error_name(e: LinkError) -> &'static str {
        match e {
            LinkError::Framing => "COBS framing",
            LinkError::Oversize => "oversize",
            LinkError::TooShort => "too short",
            LinkError::Crc => "CRC",
            LinkError::UnknownKind => "unknown kind",
            LinkError::BadLength => "bad length",
            LinkError::OutOfRange => "value out of range",
            LinkError::Refused => "refused",
            LinkError::Calibration => "calibration",
            LinkError::NotSupported => "not supported",
        }
    }
}
