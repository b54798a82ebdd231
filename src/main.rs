//! belt-drive firmware: the RTIC 2 application.
//!
//! Thin on purpose: every decision lives in `estimator-core` (tested on the host and on the
//! target); the tasks here only move bytes and samples between the hardware and the core.
//!
//! | task      | trigger                       | priority | does                                  |
//! |-----------|-------------------------------|----------|---------------------------------------|
//! | `control` | TIM7 (board: timer at the control rate; QEMU: pended per PIL sample) | 3 | sample, `Drive::step`, current out, events queued |
//! | `usart2`  | USART2 (RXNE / TXE)           | 2        | received bytes into a queue, transmit queue drained |
//! | `link`    | software (bytes queued)       | 1        | frame decoding, commands, replies, calibration decode |
//! | `logger`  | software (events queued)      | 1        | defmt lines for the control task's events |
//! | `idle`    | -                             | 0        | `wfi` (QEMU PIL pipe: waits for the host's bytes) |
//!
//! Nothing in `control` formats or logs, and nothing in `usart2` decodes: each hands small
//! records to a lock-free queue (heapless spsc) for a priority-1 task.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!("belt-drive is firmware: build it with `cargo fw` or `cargo fw-qemu`");
}

#[cfg(target_os = "none")]
use belt_drive as _;

#[cfg(target_os = "none")]
#[rtic::app(device = stm32f4xx_hal::pac, peripherals = true, dispatchers = [SDIO])]
mod app {
    use core::mem::MaybeUninit;
    use core::sync::atomic::{AtomicBool, AtomicU16, Ordering};

    use heapless::spsc;

    use belt_drive::doorbell::Doorbell;
    use belt_drive::drive::{
        Command, CommandError, Drive, Faults, Output as DriveOutput, Parts, Telemetry,
    };
    use belt_drive::events::{self, Event};
    use belt_drive::hardware::{self, ControlIo, IdleIo, LinkRx};
    use belt_drive::outbox::Outbox;
    use belt_drive::persist::{self, Boot, Persist};
    use belt_drive::postmortem::{self, reset_cause};
    use belt_drive::stack;
    use belt_link::{
        LinkError, Message, ModelKind, MotorCounts, Receiver, RecordSample, Reply, Request,
        ScaleCounts, RECORD_BATCH,
    };
    use estimator_core::blob::BlobError;
    use estimator_core::endpoint::{answer, Effect, Endpoint, Event as LinkEvent};
    use estimator_core::fixed::types::I16F16;
    use estimator_core::image;
    use estimator_core::staging::FlashStaging;

    /// The link's endpoint: calibration images are staged in flash (sector 9; QEMU: the
    /// `--staging` file), not in RAM.
    type LinkEndpoint = Endpoint<FlashStaging<hardware::StagingFlash>>;
    use estimator_core::settings::{self, RawSettings, SettingsError};
    use estimator_core::{ConfigError, ConfigField};

    /// Received bytes waiting for `link` (one slot stays free): more than one largest frame
    /// (77 bytes) plus a status request, 2.7 ms of a saturated 460800 Bd line. Hosts wait for
    /// each reply, so the only long wait, a calibration decode, sees no traffic; QEMU holds bytes
    /// back when the queue is full. Sized for the 8 KiB static RAM budget.
    const RX_QUEUE: usize = 128;

    /// Telemetry stream decimation, 0 = off.
    static STREAM_EVERY: AtomicU16 = AtomicU16::new(0);
    /// Recording decimation, 0 = off.
    static RECORD_EVERY: AtomicU16 = AtomicU16::new(0);
    /// A recording (re)started: the control task restarts its batch and sequence.
    static RECORD_RESTART: AtomicBool = AtomicBool::new(false);
    /// The paper rig's configuration image (built by build.rs): the drive before any stored
    /// configuration.
    static PAPER_PARTS: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/paper_parts.bin"));
    /// The paper rig's settings record (built by build.rs): what an unconfigured drive reports
    /// and stages first.
    static PAPER_SETTINGS: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/paper_settings.bin"));
    /// The board accepts the drive's current limit (set once in `init`); otherwise the drive is
    /// kept disabled and the amplifier off.
    static AMP_PERMITTED: AtomicBool = AtomicBool::new(false);
    /// Rung by `usart2` when bytes were queued.
    static RX_BELL: Doorbell = Doorbell::new();
    /// `usart2` found the byte queue full and turned RXNE off; `link` turns it back on.
    static RX_PAUSED: AtomicBool = AtomicBool::new(false);

    #[shared]
    struct Shared {
        /// In a static of `init` (built there in place): not moved through the stack.
        drive: &'static mut Drive,
        outbox: Outbox,
    }

    #[local]
    struct Local {
        io: ControlIo,
        events_in: events::Producer,
        events_out: events::Consumer,
        rx: LinkRx,
        idle_io: IdleIo,
        bytes_in: spsc::Producer<'static, u8>,
        bytes_out: spsc::Consumer<'static, u8>,
        receiver: Receiver,
        endpoint: &'static mut LinkEndpoint,
        persist: Persist,
        /// The previous tick's telemetry (for move start/end and fault events).
        prev: Telemetry,
        /// Reset-cause bits for the status reply.
        reset_cause: u8,
    }

    #[init(local = [
        endpoint_storage: MaybeUninit<LinkEndpoint> = MaybeUninit::uninit(),
        drive_storage: MaybeUninit<Drive> = MaybeUninit::uninit(),
        event_queue: events::Queue = events::Queue::new(),
        rx_queue: spsc::Queue<u8, RX_QUEUE> = spsc::Queue::new(),
    ])]
    fn init(cx: init::Context) -> (Shared, Local) {
        // The amplifier enable and the DAC pin are already safe (board: `__pre_init`).
        stack::paint();
        // Built on the host (build.rs) and checked by the host tests: refused only by a broken
        // build.
        let defaults = match RawSettings::decode(PAPER_SETTINGS) {
            Ok(s) => s,
            Err(_) => defmt::panic!("built-in settings record refused"),
        };
        let endpoint = cx.local.endpoint_storage.write(Endpoint::with_staging(
            FlashStaging::new(hardware::open_staging()),
            defaults,
        ));
        // The stored configuration and calibration, read before the clocks and timers start
        // (the control rate comes from it).
        let mut persist = Persist::open();
        let mut settings_buf = [0u8; settings::STORED_LEN];
        let boot = persist.load(&mut settings_buf);
        // The paper rig's configuration image, built on the host (build.rs) and checked by the
        // host tests: refused only by a broken build.
        let (paper, _) = match Parts::decode(PAPER_PARTS) {
            Ok(p) => p,
            Err(e) => defmt::panic!("built-in configuration refused: {=istr}", e.field().istr()),
        };
        let (stored, stored_record, record_crc) = match boot {
            Boot::Loaded(r) => {
                match settings::decode_stored(
                    &settings_buf[..r.settings_len.min(settings_buf.len())],
                ) {
                    Ok(s) => (Some(s), Some(r), r.crc32),
                    Err(e) => {
                        log_settings_error(&e);
                        (None, None, 0)
                    }
                }
            }
            _ => (None, None, 0),
        };
        let rate_hz = match &stored {
            Some((_, p)) => p.rate_hz(),
            None => paper.rate_hz(),
        };
        let mut board = hardware::init(cx.device, cx.core, rate_hz);
        defmt::info!(
            "belt-drive {=str} on {=str}: sysclk {=u32} Hz{=str}, control tick {=u32} Hz",
            env!("CARGO_PKG_VERSION"),
            hardware::NAME,
            board.sysclk_hz,
            if board.clock_fallback {
                " (internal RC fallback)"
            } else {
                ""
            },
            rate_hz
        );
        let mut cause = board.reset_cause;
        if postmortem::take_and_log() {
            cause |= reset_cause::PANIC_RECORD;
        }
        postmortem::log_reset_cause(cause);
        persist::log_boot(&boot);

        // Assembled from the paper rig's image first, then the stored one installed over it
        // with the link's own checks.
        let mut current_limit = paper.max_current_a();
        // No calibration built in: a calibration belongs to one machine (the paper's Table 2
        // fits no other), so the drive runs uncompensated until its own loads (2.5 KB of flash).
        let drive = match Drive::from_parts_in(cx.local.drive_storage, paper, &[]) {
            Ok(_) => {
                // SAFETY: `from_parts_in` returned Ok, so it wrote the drive into the slot.
                // Taken from the static itself, not from the returned reference: the control
                // tick then addresses the static directly (9 instructions per tick fewer,
                // measured).
                unsafe { cx.local.drive_storage.assume_init_mut() }
            }
            // Cannot happen: an empty image is no calibration, not a bad one.
            Err(e) => defmt::panic!("drive not assembled: {=istr}", blob_error_name(e)),
        };
        // The timer runs at the stored configuration's rate from here to the next boot.
        drive.set_tick_rate_hz(rate_hz);
        let mut configured = false;
        let mut initial_model = ModelKind::None;
        if let Some((active, parts)) = stored {
            let limit = parts.max_current_a();
            initial_model = parts.initial_model();
            match board_limit(&parts)
                .map_err(Ok)
                .and_then(|()| drive.reconfigure(parts).map_err(Err))
            {
                Ok(()) => {
                    configured = true;
                    current_limit = limit;
                    // The image is the tail of the stored configuration (`decode_stored`).
                    if let Ok(image) = settings_buf[settings::ENCODED_LEN..].try_into() {
                        endpoint.boot_with(active, image, record_crc);
                    }
                }
                Err(Ok(e)) => defmt::error!(
                    "stored configuration refused: {=istr}: the drive boots unconfigured",
                    e.field().istr()
                ),
                Err(Err(_)) => defmt::error!("stored configuration not installed"),
            }
        }
        if configured {
            if let Some(r) = stored_record.filter(|r| r.blob_len > 0) {
                let len = r.blob_len;
                // Staged (copied into the staging area unless it already holds it), then
                // read from there like a transferred one.
                let loaded = persist
                    .stage_blob(&r, endpoint.staging())
                    .map_err(|code| {
                        defmt::error!(
                            "stored calibration not staged: {=istr}; no compensation until one loads",
                            persist::detail_name(code)
                        )
                    })
                    .ok()
                    .map(|_| drive.load_calibration_from(&mut endpoint.calibration(len)));
                match loaded {
                    None => {}
                    Some(Ok(())) => {
                        endpoint.boot_calibration(len);
                        // The geometry changed from the paper rig's: the configured model
                        // comes back with its calibration.
                        let model = initial_model;
                        let _ = drive.command(Command::SelectModel(model));
                        defmt::info!(
                            "stored calibration loaded ({=usize} bytes): model {=str}",
                            len,
                            model.as_str()
                        );
                    }
                    Some(Err(e)) => log_blob_refused(
                        defmt::intern!(
                            "stored calibration refused (no compensation until one loads)"
                        ),
                        e,
                    ),
                }
            }
            defmt::info!(
                "configured from storage (record crc {=u32:#010x}): {=u32} encoder lines, gear {=f64}:1, {=u32}-tooth pulley, {=f64} mm pitch",
                record_crc,
                drive.rig().encoder_lines,
                drive.rig().gear_ratio,
                drive.rig().pulley_teeth,
                drive.rig().belt_pitch_mm
            );
        } else {
            drive.forget_configuration();
            defmt::warn!(
                "no valid configuration stored: the drive is UNCONFIGURED and refuses to enable; set one over the link (beltctl config set, which applies it) and save it"
            );
        }
        // A current limit beyond the amplifier's linear range would wind the integrator up
        // against the DAC buffer's rail: refused (the drive stays disabled), never a panic.
        let permitted = within_amplifier(current_limit);
        AMP_PERMITTED.store(permitted, Ordering::Relaxed);
        if !permitted {
            defmt::error!(
                "drive current limit {=i32} mA exceeds the amplifier's linear range +-{=i32} mA: the drive stays disabled",
                milliamperes(current_limit),
                hardware::MAX_LINEAR_CURRENT_MA
            );
        }
        defmt::info!(
            "drive disabled, model {=str}: waiting for the link",
            drive.telemetry().model.as_str()
        );
        // The boot announcement: an unsolicited status (sequence 0) tells the host that the
        // link is up (QEMU drops bytes sent before the USART is enabled) and that the drive
        // (re)started, disabled.
        let receiver = Receiver::new();
        let mut outbox = Outbox::new(board.tx);
        outbox.send(
            0,
            &Reply::Status(endpoint.status(drive, &receiver, 0, cause)),
        );

        let (events_in, events_out) = cx.local.event_queue.split();
        let (bytes_in, bytes_out) = cx.local.rx_queue.split();
        if link::spawn().is_err() || logger::spawn().is_err() {
            defmt::error!("software tasks already running");
        }
        // Last: the control tick starts from a clean count and the watchdog starts guarding it.
        board.control.start();
        (
            Shared { drive, outbox },
            Local {
                io: board.control,
                events_in,
                events_out,
                rx: board.rx,
                idle_io: board.idle,
                bytes_in,
                bytes_out,
                receiver,
                endpoint,
                persist,
                prev: Telemetry::default(),
                reset_cause: cause,
            },
        )
    }

    /// Board: `wfi` (under QEMU with -icount this also skips idle time). QEMU with the PIL pipe:
    /// waits on the host for the next bytes of the link (see `hardware::qemu`).
    #[idle(local = [idle_io])]
    fn idle(cx: idle::Context) -> ! {
        loop {
            cx.local.idle_io.wait();
        }
    }

    /// One control tick: sample the counters, `Drive::step`, write the current, queue events.
    ///
    /// Budget: `Drive::step` at most 400 instructions per tick with Model 3, counted exactly
    /// under QEMU by `tools/bench-target.sh` (which prints the current figures); the whole task,
    /// sampling and reporting included, well under a tenth of a 2 kHz tick (84,000 cycles at
    /// 168 MHz). No logging here: events go to the `logger` task through a lock-free queue.
    #[task(
        binds = TIM7,
        priority = 3,
        local = [io, prev, events_in, since_stream: u16 = 0, since_trace: u16 = 0, deadline_misses: u32 = 0, since_record: u16 = 0, batch: Batch = Batch::EMPTY],
        shared = [drive, outbox]
    )]
    fn control(cx: control::Context) {
        let control::LocalResources {
            io,
            prev,
            events_in,
            since_stream,
            since_trace,
            deadline_misses,
            since_record,
            batch,
            ..
        } = cx.local;
        let control::SharedResources {
            mut drive,
            mut outbox,
            ..
        } = cx.shared;
        let Some(tick) = io.begin_tick() else { return };
        let clock_failed = hardware::clock_failed();
        let permitted = AMP_PERMITTED.load(Ordering::Relaxed);
        let mut refused = false;

        let (current_a, amplifier_on, instructions) = drive.lock(|d| {
            // Faults found before the step latch now: this tick already writes zero current.
            d.missed_ticks(tick.missed);
            if clock_failed {
                d.raise_fault(Faults::CLOCK_FAILURE);
            }
            if !permitted && d.is_enabled() {
                refused = true;
                let _ = d.command(Command::Disable);
            }
            let (current_a, n) = io.measure(|| d.control(tick.sample));
            (current_a, permitted && d.amplifier_enabled(), n)
        });
        io.write_current(current_a, amplifier_on);

        // Everything below is reporting; the motor already has its current.
        let t = drive.lock(|d| d.telemetry());
        let out = DriveOutput {
            current_a,
            telemetry: t,
        };
        if let Some(seq) = tick.reply_seq {
            outbox.lock(|o| o.send(seq, &answer(&out, instructions)));
        }
        let every = STREAM_EVERY.load(Ordering::Relaxed);
        *since_stream += 1;
        if every != 0 && *since_stream >= every {
            *since_stream = 0;
            outbox.lock(|o| o.send(0, &Reply::Telemetry(t)));
        }
        let record_every = RECORD_EVERY.load(Ordering::Relaxed);
        if RECORD_RESTART.swap(false, Ordering::Relaxed) {
            *batch = Batch::EMPTY;
            *since_record = record_every;
        }
        if record_every != 0 {
            *since_record = since_record.saturating_add(1);
            if *since_record >= record_every {
                *since_record = 0;
                if let Some(frame) = batch.push(&t, record_every) {
                    outbox.lock(|o| o.send(0, &frame));
                }
            }
        }
        events::transitions(events_in, prev, &t);
        if refused {
            events::push(events_in, Event::EnableRefused { tick: t.tick });
        }
        *since_trace += 1;
        if *since_trace >= events::TRACE_EVERY {
            *since_trace = 0;
            events::push(
                events_in,
                Event::Trace {
                    tick: t.tick,
                    motor_counts: t.motor_counts.0,
                    setpoint_counts: t.setpoint_counts.0,
                    current_bits: t.current_a.to_bits(),
                },
            );
        }
        *prev = t;

        // The next update came while this tick ran: an overrun, latched from the next tick.
        let overrun = io.overran();
        if overrun {
            drive.lock(|d| d.missed_ticks(1));
        }
        if tick.missed != 0 || overrun {
            *deadline_misses = deadline_misses.saturating_add(tick.missed + overrun as u32);
            events::push(
                events_in,
                Event::Deadline {
                    tick: t.tick,
                    latency_us: tick.latency_us,
                    missed: tick.missed,
                    overrun,
                    total: *deadline_misses,
                },
            );
        }
        // Only a completed tick feeds the watchdog.
        io.feed_watchdog();
    }

    /// Recorded samples waiting for a full [`Reply::Records`] frame.
    pub struct Batch {
        seq: u32,
        first_tick: u32,
        count: u8,
        samples: [RecordSample; RECORD_BATCH],
    }

    impl Batch {
        const EMPTY: Batch = Batch {
            seq: 0,
            first_tick: 0,
            count: 0,
            samples: [RecordSample {
                motor_counts: MotorCounts(0),
                scale_counts: ScaleCounts(0),
                setpoint_counts: MotorCounts(0),
                current_ma: 0,
            }; RECORD_BATCH],
        };

        /// Adds one tick; returns the frame to send when the batch is full.
        fn push(&mut self, t: &Telemetry, every: u16) -> Option<Reply> {
            if self.count == 0 {
                self.first_tick = t.tick;
            }
            let ma = (t.current_a.to_bits() as i64 * 1000) >> 16;
            self.samples[self.count as usize % RECORD_BATCH] = RecordSample {
                motor_counts: t.motor_counts,
                scale_counts: t.scale_counts,
                setpoint_counts: t.setpoint_counts,
                current_ma: ma.clamp(i16::MIN as i64, i16::MAX as i64) as i16,
            };
            self.count += 1;
            if (self.count as usize) < RECORD_BATCH {
                return None;
            }
            let frame = Reply::Records {
                seq: self.seq,
                first_tick: self.first_tick,
                every,
                count: self.count,
                samples: self.samples,
            };
            self.seq = self.seq.wrapping_add(1);
            self.count = 0;
            Some(frame)
        }
    }

    /// Defmt lines for the control task's events, outside every interrupt handler.
    #[task(priority = 1, local = [events_out])]
    async fn logger(cx: logger::Context) {
        loop {
            events::drain(cx.local.events_out);
            events::BELL.wait().await;
        }
    }

    /// USART2: moves received bytes into the queue for `link` (a byte arrives every 21.7 us at
    /// 460800 Bd: nothing slower may run here) and drains the transmit queue on TXE.
    #[task(binds = USART2, priority = 2, local = [rx, bytes_in, held: Option<u8> = None], shared = [outbox])]
    fn usart2(cx: usart2::Context) {
        let usart2::LocalResources {
            rx, bytes_in, held, ..
        } = cx.local;
        let mut outbox = cx.shared.outbox;
        let mut queued = false;
        while bytes_in.ready() {
            // The byte held back at the last pause goes first.
            let Some(b) = held.take().or_else(|| rx.read()) else {
                break;
            };
            let _ = bytes_in.enqueue(b);
            queued = true;
        }
        if !bytes_in.ready() {
            // Full: RXNE's interrupt stays off until `link` has drained the queue (on the
            // board a TXE run may still take bytes when there is room). It goes off first,
            // then the waiting byte is held here: reading DR is what drops the line (QEMU 7.2
            // keeps it high on RXNEIE = 0 while RXNE is set, and this task would run again and
            // again, starving `link`). In that order no byte can arrive between the two with
            // the interrupt still on.
            RX_PAUSED.store(true, Ordering::Relaxed);
            outbox.lock(|o| o.set_rx_interrupt(false));
            if held.is_none() {
                *held = rx.read();
            }
            queued = true;
        }
        if queued {
            RX_BELL.ring();
        }
        outbox.lock(|o| o.pump());
    }

    /// The link: frames decoded from the byte queue, commands applied, replies queued.
    #[task(priority = 1, local = [bytes_out, receiver, endpoint, persist, reset_cause], shared = [drive, outbox])]
    async fn link(cx: link::Context) {
        let link::LocalResources {
            bytes_out,
            receiver,
            endpoint,
            persist,
            reset_cause,
            ..
        } = cx.local;
        let link::SharedResources {
            mut drive,
            mut outbox,
            ..
        } = cx.shared;
        loop {
            while let Some(byte) = bytes_out.dequeue() {
                let frame = match receiver.push::<Request>(byte) {
                    None => continue,
                    Some(Err(r)) => {
                        // Every rejection is counted and answered; the log keeps the first few
                        // and then one line per thousand, so that a flood cannot starve the log.
                        let bad = receiver.frames_bad;
                        if bad <= 10 || bad % 1000 == 0 {
                            defmt::warn!(
                                "link: frame rejected: {=istr} (kind {=u8:#04x}), {=u32} bad so far",
                                error_name(r.error),
                                r.kind,
                                bad
                            );
                        } else {
                            defmt::debug!("link: frame rejected: {=istr}", error_name(r.error));
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
                // `handle` also feeds the core's link watchdog (`Drive::link_alive`), on every
                // frame but a PIL sample.
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
                        Reply::Status(
                            drive.lock(|d| endpoint.status(d, receiver, peak, *reset_cause)),
                        )
                    }
                    Effect::Stream(n) => {
                        defmt::info!("telemetry stream every {=u16} ticks (0 = off)", n);
                        STREAM_EVERY.store(n, Ordering::Relaxed);
                        Reply::Ack {
                            of: frame.msg.kind(),
                        }
                    }
                    Effect::Calibrate(len) => {
                        // Checked here, outside the drive's lock; the lock is held only while
                        // the checked image is read into the coefficients (no staging copy).
                        let (rig, rate_hz) = drive.lock(|d| (*d.rig(), d.rate_hz()));
                        let mut staged = endpoint.calibration(len);
                        let result = image::check_from(&mut staged, &rig, rate_hz).and_then(|()| {
                            drive.lock(|d| d.load_checked_calibration_from(&mut staged))
                        });
                        let (reply, event) = endpoint.calibration_done(len, result);
                        log_event(&event);
                        reply
                    }
                    Effect::Record(n) => {
                        defmt::info!("recording every {=u16} ticks (0 = off)", n);
                        RECORD_EVERY.store(n, Ordering::Relaxed);
                        RECORD_RESTART.store(true, Ordering::Relaxed);
                        Reply::Ack {
                            of: frame.msg.kind(),
                        }
                    }
                    Effect::Configure => {
                        // The image is read and checked outside the lock; only the install
                        // holds it.
                        let result = endpoint
                            .staged_parts()
                            .and_then(|p| board_limit(&p).map(|()| p))
                            .map_err(Ok)
                            .and_then(|p| {
                                let limit = p.max_current_a();
                                // Another control rate is installed but not run: enabling
                                // is refused, by name, until the restart.
                                drive.lock(|d| d.reconfigure(p)).map_err(Err)?;
                                Ok(limit)
                            });
                        if let Ok(limit) = result {
                            AMP_PERMITTED.store(within_amplifier(limit), Ordering::Relaxed);
                        }
                        let result = result.map(|_| ());
                        let (reply, event) = endpoint.configure_done(result);
                        log_event(&event);
                        reply
                    }
                    Effect::Save => {
                        let result = match endpoint.active_parts() {
                            Some(parts) => {
                                let buf = settings::encode_stored(endpoint.active(), parts);
                                match endpoint.installed_calibration() {
                                    Some(mut blob) => persist.save(&buf, &mut blob),
                                    None => persist.save(&buf, &mut &[][..]),
                                }
                            }
                            // Refused by the endpoint before: nothing applied to save.
                            None => Err(persist::detail::ENCODE),
                        };
                        let (reply, event) = endpoint.save_done(result);
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
            // `usart2` may have filled the queue and paused after the last `dequeue`.
            // Resumed then, it finds the queue full and a byte held, so it cannot read DR;
            // QEMU 7.2 keeps the line high with RXNEIE off while RXNE is set, and it ran
            // forever (a livelock the PIL fuzz caught). So the receiver is resumed only on an
            // empty queue; otherwise the bell, rung with those bytes, sends `link` round again.
            if RX_PAUSED.load(Ordering::Relaxed) && !bytes_out.ready() {
                RX_PAUSED.store(false, Ordering::Relaxed);
                // Take bytes again, starting with the held one (the pend: no new byte may come
                // to raise the interrupt); `usart2` runs at once and rings for what it queues.
                outbox.lock(|o| o.set_rx_interrupt(true));
                rtic::pend(hardware::LINK_INTERRUPT);
            }
            RX_BELL.wait().await;
        }
    }

    /// The board's own limit on the current (the DAC's linear range), checked like any other
    /// field of a configuration image.
    fn board_limit(p: &Parts) -> Result<(), ConfigError> {
        if within_amplifier(p.max_current_a()) {
            Ok(())
        } else {
            Err(ConfigError::OutOfRange(ConfigField::PidMaxCurrentA))
        }
    }

    /// A current limit within the amplifier's linear range.
    fn within_amplifier(limit: I16F16) -> bool {
        milliamperes(limit) <= hardware::MAX_LINEAR_CURRENT_MA
    }

    /// Whole milliamperes, rounded down (|limit| <= 127 A: no overflow in i64).
    fn milliamperes(a: I16F16) -> i32 {
        ((a.to_bits() as i64 * 1000) >> 16) as i32
    }

    fn log_settings_error(e: &SettingsError) {
        match *e {
            SettingsError::Invalid(c) => {
                defmt::error!("stored configuration refused: {=istr}", c.field().istr())
            }
            SettingsError::UnknownKey(k) => {
                defmt::error!("stored configuration refused: unknown field key {=u8}", k)
            }
            SettingsError::Truncated => defmt::error!(
                "stored configuration refused: truncated or too long (a record of an older firmware?)"
            ),
            SettingsError::BadMagic => {
                defmt::error!("stored configuration refused: not a settings record")
            }
            SettingsError::UnsupportedVersion(v) => {
                defmt::error!("stored configuration refused: settings version {=u16}", v)
            }
        }
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

    fn log_event(e: &LinkEvent) {
        match *e {
            LinkEvent::None => {}
            LinkEvent::Applied(Command::MoveMotorTo {
                target_um,
                velocity_um_s,
                accel_um_s2,
            }) => defmt::info!(
                "move to {=i32} um at {=u32} um/s, {=u32} um/s^2",
                target_um,
                velocity_um_s,
                accel_um_s2
            ),
            LinkEvent::Applied(Command::MoveTo {
                target_um,
                velocity_um_s,
                accel_um_s2,
            }) => defmt::info!(
                "move carriage to {=i32} um at {=u32} um/s, {=u32} um/s^2",
                target_um,
                velocity_um_s,
                accel_um_s2
            ),
            LinkEvent::Applied(Command::SelectModel(m)) => {
                defmt::info!("model selected: {=str}", m.as_str())
            }
            LinkEvent::Applied(Command::Home {
                position_um,
                scale_um,
            }) => {
                defmt::info!(
                    "homed: motor at {=i32} um, scale at {=i32} um",
                    position_um,
                    scale_um
                )
            }
            LinkEvent::Applied(c) => defmt::info!("command: {=istr}", command_name(&c)),
            LinkEvent::Refused(c, why) => defmt::warn!(
                "command {=istr} refused: {=istr}",
                command_name(&c),
                command_error_name(why)
            ),
            LinkEvent::CalibrationBegun { total_len } => {
                defmt::info!("calibration transfer: {=u32} bytes announced", total_len)
            }
            LinkEvent::CalibrationRefused(detail) => {
                defmt::warn!("calibration transfer step refused (detail {=u8})", detail)
            }
            LinkEvent::CalibrationLoaded { len } => {
                defmt::info!("calibration loaded ({=u32} bytes): Model 3 available", len)
            }
            LinkEvent::CalibrationRejected(e) => log_blob_refused(
                defmt::intern!("calibration rejected (previous tables kept)"),
                e,
            ),
            LinkEvent::ConfigRefused(e) => {
                defmt::warn!("configuration refused: {=istr}", e.field().istr())
            }
            LinkEvent::Configured => {
                defmt::info!("new configuration in force: home the drive again")
            }
            LinkEvent::Saved { seq, crc32 } => {
                defmt::info!(
                    "configuration and calibration stored: record {=u32}, crc {=u32:#010x}",
                    seq,
                    crc32
                )
            }
            LinkEvent::SaveFailed(d) => {
                defmt::error!("save failed: {=istr}", persist::detail_name(d))
            }
        }
    }

    fn command_name(c: &Command) -> defmt::Str {
        match c {
            Command::MoveMotorTo { .. } => defmt::intern!("move"),
            Command::MoveTo { .. } => defmt::intern!("move carriage"),
            Command::Stop => defmt::intern!("stop"),
            Command::Enable => defmt::intern!("enable"),
            Command::Disable => defmt::intern!("disable"),
            Command::ClearFaults => defmt::intern!("clear faults"),
            Command::SelectModel(_) => defmt::intern!("select model"),
            Command::Home { .. } => defmt::intern!("home"),
            Command::Homing => defmt::intern!("homing"),
        }
    }

    fn command_error_name(e: CommandError) -> defmt::Str {
        match e {
            CommandError::TargetOutOfTravel => defmt::intern!("target outside the travel"),
            CommandError::VelocityOutOfRange => defmt::intern!("velocity out of range"),
            CommandError::AccelOutOfRange => defmt::intern!("acceleration out of range"),
            CommandError::NotEnabled => defmt::intern!("drive not enabled (or faulted)"),
            CommandError::Busy => defmt::intern!("busy (moving)"),
            CommandError::NotHomed => defmt::intern!("not homed"),
            CommandError::Unconfigured => defmt::intern!("not configured"),
            CommandError::NotCalibrated => defmt::intern!("no calibration for this geometry"),
            CommandError::RestartNeeded => {
                defmt::intern!("control rate changed: save and restart")
            }
        }
    }

    /// Logs a refused calibration, naming the field at fault when there is one.
    fn log_blob_refused(context: defmt::Str, e: BlobError) {
        match e {
            BlobError::BadCount(f) => {
                defmt::error!("{=istr}: {=istr}: count out of bounds", context, f.istr())
            }
            BlobError::Invalid(c) => defmt::error!(
                "{=istr}: {=istr}: failed the model checks",
                context,
                c.field().istr()
            ),
            _ => defmt::error!("{=istr}: {=istr}", context, blob_error_name(e)),
        }
    }

    fn blob_error_name(e: BlobError) -> defmt::Str {
        match e {
            BlobError::Truncated => defmt::intern!("truncated"),
            BlobError::TooLong => defmt::intern!("too long"),
            BlobError::BadMagic => defmt::intern!("bad magic"),
            BlobError::UnsupportedVersion(_) => defmt::intern!("unsupported version"),
            BlobError::BadChecksum => defmt::intern!("checksum mismatch"),
            BlobError::RigMismatch => defmt::intern!("calibrated on another rig"),
            BlobError::RateMismatch => defmt::intern!("belt observer for another control rate"),
            BlobError::BadCount(_) => defmt::intern!("table count out of bounds"),
            BlobError::Invalid(_) => defmt::intern!("a value failed the model checks"),
            BlobError::Busy => defmt::intern!("drive moving"),
            BlobError::BufferTooSmall | BlobError::Unrepresentable(_) => {
                defmt::intern!("encoder error")
            }
            BlobError::Unreadable => defmt::intern!("staging flash unreadable"),
        }
    }

    fn error_name(e: LinkError) -> defmt::Str {
        match e {
            LinkError::Framing => defmt::intern!("COBS framing"),
            LinkError::Oversize => defmt::intern!("oversize"),
            LinkError::TooShort => defmt::intern!("too short"),
            LinkError::Crc => defmt::intern!("CRC"),
            LinkError::UnknownKind => defmt::intern!("unknown kind"),
            LinkError::BadLength => defmt::intern!("bad length"),
            LinkError::OutOfRange => defmt::intern!("value out of range"),
            LinkError::Refused => defmt::intern!("refused"),
            LinkError::Calibration => defmt::intern!("calibration"),
            LinkError::NotSupported => defmt::intern!("not supported"),
            LinkError::Config => defmt::intern!("configuration refused"),
            LinkError::Storage => defmt::intern!("storage"),
        }
    }
}
