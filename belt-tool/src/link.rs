//! The host's end of belt-link: requests with retries and reply matching, and the collection of
//! the drive's recording stream.
//!
//! The port is anything `Read + Write`: the serial adapter, a pseudo-terminal in the tests, or an
//! in-memory fake. A read that finds nothing returns `Ok(0)` or fails with `TimedOut` or
//! `WouldBlock`; the link keeps its own deadlines.
//!
//! Matching: a reply belongs to a request when it carries the request's seq and is a plausible
//! answer to that kind of request ([`answers`]). Seq 0 is the drive's own (boot status, records,
//! telemetry) and is never used for a request, so unsolicited frames cannot be taken for a reply.
//! A frame the drive could not read is answered with `Error { of: UNKNOWN }` and seq 0 (it could
//! not read the seq either): while a request is outstanding, that is taken as the request's
//! damage, and the request is sent again.

use std::io::{self, Read, Write};
use std::time::{Duration, Instant};

use belt_link::{
    cobs_decode_in_place, decode_raw, encode, kind, Command, Frame, LinkError, Message, Receiver,
    RecordSample, Rejected, Reply, Request, WireStatus, MAX_FRAME,
};

use crate::error::{is_damage, link_error_name, refusal, ToolError};

/// A byte stream to a drive.
pub trait Port: Read + Write + Send {}
impl<T: Read + Write + Send> Port for T {}

/// How long to wait and how often to try.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LinkOptions {
    /// Time allowed for one try's reply.
    pub timeout: Duration,
    /// Tries per request (at least 1).
    pub tries: u32,
}

impl Default for LinkOptions {
    /// 300 ms per try, 3 tries.
    fn default() -> Self {
        LinkOptions {
            timeout: Duration::from_millis(300),
            tries: 3,
        }
    }
}

/// What the link has seen, for diagnostics.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LinkStats {
    /// Valid frames received.
    pub frames: u64,
    /// Bytes that belonged to no valid frame.
    pub garbage_bytes: u64,
    /// Frames that failed to decode.
    pub bad_frames: u64,
    /// Replies to earlier tries that came too late.
    pub stale: u64,
    /// Frames the drive sent on its own (seq 0) that nothing waited for.
    pub unsolicited: u64,
    /// Boot status frames: the drive (re)started while we listened.
    pub boots: u64,
    /// Requests sent again after a timeout or a damaged frame.
    pub resent: u64,
    /// Our own requests that came back (a loopback).
    pub echoes: u64,
}

/// A short name of a request for messages (`status`, `move to 12.500 mm`,
/// `config get rig.gear_ratio`).
pub fn describe(req: &Request) -> String {
    let mm = |um: i32| format!("{:.3} mm", um as f64 / 1000.0);
    let field = |key: u8| {
        estimator_core::settings::field(key).map_or(format!("key {key}"), |f| f.name().to_string())
    };
    match *req {
        Request::Command(c) => match c {
            Command::MoveMotorTo { target_um, .. } => format!("move-motor to {}", mm(target_um)),
            Command::MoveTo { target_um, .. } => format!("move to {}", mm(target_um)),
            Command::Stop => "stop".into(),
            Command::Enable => "enable".into(),
            Command::Disable => "disable".into(),
            Command::ClearFaults => "clear-faults".into(),
            Command::SelectModel(m) => format!("model {m}"),
            Command::Homing => "home".into(),
            Command::Home { .. } => "home (declared position)".into(),
        },
        Request::CalBegin { total_len, .. } => format!("calibration upload ({total_len} bytes)"),
        Request::CalChunk { offset, .. } => format!("calibration chunk at byte {offset}"),
        Request::CalCommit => "calibration commit".into(),
        Request::Status => "status".into(),
        Request::Telemetry { .. } => "telemetry".into(),
        Request::Sample { .. } => "sample".into(),
        Request::Shutdown { .. } => "shutdown".into(),
        Request::ConfigSet { key, .. } => format!("config set {}", field(key)),
        Request::ConfigGet { key } => format!("config get {}", field(key)),
        Request::ConfigParts { offset, .. } => format!("configuration image at byte {offset}"),
        Request::ConfigApply => "config apply".into(),
        Request::Save => "save".into(),
        Request::Record { every_n_ticks: 0 } => "record stop".into(),
        Request::Record { .. } => "record".into(),
        Request::CalRead { offset } => format!("calibration read-back at byte {offset}"),
    }
}

/// True when `reply` is a plausible answer to `req` (its seq aside).
pub fn answers(req: &Request, reply: &Reply) -> bool {
    let k = req.kind();
    match *reply {
        Reply::Ack { of } => {
            of == k
                && !matches!(
                    req,
                    Request::Status
                        | Request::ConfigGet { .. }
                        | Request::Save
                        | Request::CalRead { .. }
                        | Request::Sample { .. }
                )
        }
        Reply::Error { of, .. } => of == k || of == kind::UNKNOWN,
        Reply::Status(_) => matches!(req, Request::Status),
        Reply::ConfigValue { key, .. } => matches!(*req, Request::ConfigGet { key: k } if k == key),
        Reply::Saved { .. } => matches!(req, Request::Save),
        Reply::CalData { offset, .. } => {
            matches!(*req, Request::CalRead { offset: o } if o == offset)
        }
        Reply::Answer { .. } => matches!(req, Request::Sample { .. }),
        Reply::Telemetry(_) | Reply::Records { .. } => false,
    }
}

/// One recorded sample with its control tick.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TickSample {
    /// Control tick.
    pub tick: u32,
    /// The sample.
    pub sample: RecordSample,
}

/// What a recording lost, and how much came.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct RecordingStats {
    /// Frames received and kept.
    pub frames: u64,
    /// Samples received and kept.
    pub samples: u64,
    /// Frames missing by sequence number.
    pub lost_frames: u64,
    /// Where they went missing: (first missing seq, count), the first few.
    pub gaps: Vec<(u32, u32)>,
    /// Samples missing by tick although the frame sequence was whole (the drive skipped them).
    pub missing_samples: u64,
    /// Frames that arrived with a seq already passed (duplicated or reordered); dropped.
    pub out_of_order: u64,
    /// Frames of another (earlier) recording that arrived after ours was asked for; dropped.
    pub foreign: u64,
}

impl RecordingStats {
    /// `Err(LostRecords)` when anything went missing.
    pub fn check(&self) -> Result<(), ToolError> {
        if self.lost_frames == 0 && self.missing_samples == 0 && self.out_of_order == 0 {
            return Ok(());
        }
        let mut parts: Vec<String> = self
            .gaps
            .iter()
            .map(|(seq, n)| format!("{n} at seq {seq}"))
            .collect();
        if self.gaps.len() as u64 > GAPS_KEPT as u64 - 1 {
            parts.push("...".into());
        }
        if self.missing_samples > 0 {
            parts.push(format!("{} samples missing by tick", self.missing_samples));
        }
        if self.out_of_order > 0 {
            parts.push(format!("{} frames out of order", self.out_of_order));
        }
        Err(ToolError::LostRecords {
            lost_frames: self.lost_frames,
            expected_frames: self.frames + self.lost_frames,
            detail: parts.join(", "),
        })
    }
}

/// Gaps listed in [`RecordingStats::gaps`].
const GAPS_KEPT: usize = 8;

/// Frames in flight when a recording starts: a first frame with a larger seq belongs to an
/// earlier recording that was never stopped.
const START_SEQ_MAX: u32 = 64;

/// Collects [`Reply::Records`] frames: sequence-gap and tick-continuity checks.
#[derive(Debug)]
struct Collector {
    every: u16,
    /// In `u64`: after the last `u32` a drive can send, the next is beyond every frame.
    next_seq: Option<u64>,
    next_tick: Option<u32>,
    samples: Vec<TickSample>,
    stats: RecordingStats,
}

impl Collector {
    fn new(every: u16) -> Collector {
        Collector {
            every,
            next_seq: None,
            next_tick: None,
            samples: Vec::new(),
            stats: RecordingStats::default(),
        }
    }

    fn push(&mut self, seq: u32, first_tick: u32, every: u16, samples: &[RecordSample]) {
        let expected = match self.next_seq {
            None => {
                // The recording counts frames from 0: a first frame at seq k means k were lost,
                // unless it is far along, i.e. from a recording that was never stopped.
                if every != self.every || seq > START_SEQ_MAX {
                    self.stats.foreign += 1;
                    return;
                }
                0
            }
            Some(s) => s,
        };
        let seq64 = u64::from(seq);
        if seq64 < expected {
            self.stats.out_of_order += 1;
            return;
        }
        if seq64 > expected {
            let n = seq64 - expected;
            self.stats.lost_frames += n;
            if self.stats.gaps.len() < GAPS_KEPT {
                // Both fit: expected < seq, a u32.
                self.stats.gaps.push((expected as u32, n as u32));
            }
        } else if let Some(t) = self.next_tick {
            // A whole sequence whose ticks jump: the drive skipped samples.
            let skipped = first_tick.wrapping_sub(t) as i32;
            if skipped > 0 && every > 0 {
                self.stats.missing_samples += (skipped as u64).div_ceil(every as u64);
            }
        }
        self.next_seq = Some(seq64 + 1);
        let every32 = every as u32;
        self.next_tick = Some(first_tick.wrapping_add(every32 * samples.len() as u32));
        self.stats.frames += 1;
        self.stats.samples += samples.len() as u64;
        self.samples
            .extend(samples.iter().enumerate().map(|(i, s)| TickSample {
                tick: first_tick.wrapping_add(every32 * i as u32),
                sample: *s,
            }));
    }
}

/// The link to one drive.
pub struct Link {
    port: Box<dyn Port>,
    name: String,
    opts: LinkOptions,
    rx: Receiver,
    /// Bytes read but not yet decoded.
    inbuf: Vec<u8>,
    inpos: usize,
    inlen: usize,
    /// The current frame's bytes so far (for the garbage count and echo detection).
    pending: Vec<u8>,
    pending_len: u64,
    next_seq: u8,
    stats: LinkStats,
    recording: Option<Collector>,
    /// The last request frame sent (to recognise an echo).
    last_sent: Vec<u8>,
}

/// What [`Link::next_frame`] found.
enum Next {
    /// A valid frame.
    Frame(Frame<Reply>),
    /// The deadline passed first.
    Deadline,
    /// The awaited answer arrived intact (its CRC holds) but could not be read.
    Unreadable(Rejected),
}

impl Link {
    /// A link over `port`, named `name` in messages.
    pub fn new(port: Box<dyn Port>, name: &str, opts: LinkOptions) -> Link {
        Link {
            port,
            name: name.to_string(),
            opts: LinkOptions {
                tries: opts.tries.max(1),
                ..opts
            },
            rx: Receiver::new(),
            inbuf: vec![0; 4096],
            inpos: 0,
            inlen: 0,
            pending: Vec::new(),
            pending_len: 0,
            next_seq: 1,
            stats: LinkStats::default(),
            recording: None,
            last_sent: Vec::new(),
        }
    }

    /// The port's name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The link's counters.
    pub fn stats(&self) -> LinkStats {
        self.stats
    }

    /// The options in force.
    pub fn options(&self) -> LinkOptions {
        self.opts
    }

    fn seq(&mut self) -> u8 {
        let s = self.next_seq;
        // 1..=255: seq 0 is the drive's own.
        self.next_seq = if s == 255 { 1 } else { s + 1 };
        s
    }

    fn send(&mut self, seq: u8, req: &Request) -> Result<(), ToolError> {
        let mut buf = [0u8; MAX_FRAME];
        let n = encode(seq, req, &mut buf);
        self.last_sent.clear();
        self.last_sent.extend_from_slice(&buf[..n - 1]);
        self.port
            .write_all(&buf[..n])
            .and_then(|_| self.port.flush())
            .map_err(|source| ToolError::Io {
                port: self.name.clone(),
                op: "write",
                source,
            })
    }

    /// The next valid frame, the deadline, or the answer with sequence number `awaited` arriving
    /// unreadable. Frames that fail to decode are counted as garbage.
    fn next_frame(&mut self, deadline: Instant, awaited: Option<u8>) -> Result<Next, ToolError> {
        loop {
            while self.inpos < self.inlen {
                let b = self.inbuf[self.inpos];
                self.inpos += 1;
                if b != 0 {
                    self.pending_len += 1;
                    if self.pending.len() < MAX_FRAME {
                        self.pending.push(b);
                    }
                }
                match self.rx.push::<Reply>(b) {
                    None => {}
                    Some(Ok(f)) => {
                        self.pending.clear();
                        self.pending_len = 0;
                        self.stats.frames += 1;
                        return Ok(Next::Frame(f));
                    }
                    Some(Err(r)) => {
                        if self.is_echo() {
                            self.stats.echoes += 1;
                        } else {
                            self.stats.bad_frames += 1;
                            self.stats.garbage_bytes += self.pending_len + 1;
                        }
                        self.pending.clear();
                        self.pending_len = 0;
                        // The answer came through intact (its CRC holds) but says something
                        // this beltctl cannot read: no use waiting or asking again.
                        if is_reply_unreadable(&r) && awaited == Some(r.seq) {
                            return Ok(Next::Unreadable(r));
                        }
                    }
                }
            }
            let now = Instant::now();
            if now >= deadline {
                return Ok(Next::Deadline);
            }
            let idle = Duration::from_millis(1).min(deadline - now);
            match self.port.read(&mut self.inbuf) {
                Ok(0) => std::thread::sleep(idle),
                Ok(n) => (self.inpos, self.inlen) = (0, n),
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => std::thread::sleep(idle),
                Err(e)
                    if matches!(
                        e.kind(),
                        io::ErrorKind::TimedOut | io::ErrorKind::Interrupted
                    ) => {}
                Err(source) => {
                    return Err(ToolError::Io {
                        port: self.name.clone(),
                        op: "read",
                        source,
                    })
                }
            }
        }
    }

    /// True when the bytes of the frame just rejected are our last request.
    fn is_echo(&self) -> bool {
        if self.pending.is_empty() || self.pending != self.last_sent {
            return false;
        }
        let mut raw = self.pending.clone();
        cobs_decode_in_place(&mut raw)
            .ok()
            .and_then(|n| decode_raw::<Request>(&raw[..n]).ok())
            .is_some()
    }

    /// Handles a frame that answers nothing we wait for.
    fn other(&mut self, f: Frame<Reply>) {
        match f.msg {
            Reply::Records {
                seq,
                first_tick,
                every,
                count,
                ref samples,
            } if f.seq == 0 => match &mut self.recording {
                Some(c) => c.push(
                    seq,
                    first_tick,
                    every,
                    &samples[..(count as usize).min(samples.len())],
                ),
                None => self.stats.unsolicited += 1,
            },
            Reply::Status(_) if f.seq == 0 => self.stats.boots += 1,
            _ if f.seq == 0 => self.stats.unsolicited += 1,
            _ => self.stats.stale += 1,
        }
    }

    /// Sends `req` and returns the drive's answer, an error reply included; retries on a
    /// timeout and on a reply saying the request arrived damaged.
    pub fn call_raw(&mut self, req: &Request) -> Result<Reply, ToolError> {
        let garbage_before = self.stats.garbage_bytes;
        let (frames_before, echoes_before) = (self.stats.frames, self.stats.echoes);
        let mut damage: Option<LinkError> = None;
        for attempt in 0..self.opts.tries {
            if attempt > 0 {
                self.stats.resent += 1;
            }
            let seq = self.seq();
            self.send(seq, req)?;
            let deadline = Instant::now() + self.opts.timeout;
            damage = None;
            loop {
                let f = match self.next_frame(deadline, Some(seq))? {
                    Next::Frame(f) => f,
                    Next::Deadline => break,
                    Next::Unreadable(r) => {
                        return Err(ToolError::Unreadable {
                            port: self.name.clone(),
                            request: describe(req),
                            kind: r.kind,
                            reason: match r.error {
                                LinkError::UnknownKind => "a kind this beltctl does not know",
                                e => link_error_name(e),
                            },
                        })
                    }
                };
                let ours = f.seq == seq && answers(req, &f.msg);
                // The drive could not read the seq of a damaged frame: it answers with 0.
                let damaged_unread = f.seq == 0
                    && matches!(f.msg, Reply::Error { of: kind::UNKNOWN, reason, .. }
                        if is_damage(reason));
                if !(ours || damaged_unread) {
                    self.other(f);
                    continue;
                }
                match f.msg {
                    Reply::Error { reason, .. } if is_damage(reason) => {
                        damage = Some(reason);
                        break;
                    }
                    reply => return Ok(reply),
                }
            }
        }
        let request = describe(req);
        if let Some(reason) = damage {
            return Err(ToolError::Damaged {
                port: self.name.clone(),
                request,
                tries: self.opts.tries,
                reason: link_error_name(reason),
            });
        }
        let garbage = self.stats.garbage_bytes - garbage_before;
        let valid = self.stats.frames - frames_before;
        if self.stats.echoes > echoes_before && valid == 0 {
            return Err(ToolError::Echo {
                port: self.name.clone(),
            });
        }
        // Bytes with no delimiter at all (text, a wrong baud rate) are garbage too.
        let junk = garbage + self.pending_len;
        if junk > 0 && valid == 0 && self.stats.frames == 0 {
            return Err(ToolError::WrongDevice {
                port: self.name.clone(),
                request,
                bytes: junk,
            });
        }
        let mut got = Vec::new();
        if junk > 0 {
            got.push(format!("{junk} bytes of garbage"));
        }
        if valid > 0 {
            got.push(format!("{valid} frames that answer nothing asked"));
        }
        let note = if !got.is_empty() {
            format!(" (received {})", got.join(" and "))
        } else if self.stats.frames == 0 {
            " (nothing received at all: is the drive powered and connected?)".to_string()
        } else {
            String::new()
        };
        Err(ToolError::Timeout {
            port: self.name.clone(),
            request,
            timeout_ms: self.opts.timeout.as_millis() as u64,
            tries: self.opts.tries,
            note,
        })
    }

    /// [`Link::call_raw`], with an error reply turned into [`ToolError::Refused`].
    pub fn call(&mut self, req: &Request) -> Result<Reply, ToolError> {
        match self.call_raw(req)? {
            Reply::Error { reason, detail, .. } => Err(ToolError::Refused {
                request: describe(req),
                why: refusal(reason, detail),
                reason,
                detail,
            }),
            reply => Ok(reply),
        }
    }

    /// A request answered with an `Ack`.
    pub fn acked(&mut self, req: &Request) -> Result<(), ToolError> {
        match self.call(req)? {
            Reply::Ack { .. } => Ok(()),
            other => Err(self.unexpected(req, &other)),
        }
    }

    /// A drive command.
    pub fn command(&mut self, cmd: Command) -> Result<(), ToolError> {
        self.acked(&Request::Command(cmd))
    }

    /// The drive's status.
    pub fn status(&mut self) -> Result<WireStatus, ToolError> {
        match self.call(&Request::Status)? {
            Reply::Status(s) => Ok(s),
            other => Err(self.unexpected(&Request::Status, &other)),
        }
    }

    /// The error for a reply that answers `req` but not as it should.
    pub fn unexpected(&self, req: &Request, got: &Reply) -> ToolError {
        ToolError::Unexpected {
            port: self.name.clone(),
            request: describe(req),
            got: format!("{got:?}"),
        }
    }

    /// Starts the drive's recording stream, one sample every `every` ticks, and collects it
    /// from now on (also while other requests wait for their replies).
    pub fn start_recording(&mut self, every: u16) -> Result<(), ToolError> {
        if every == 0 {
            return Err(ToolError::Usage("--every must be at least 1".into()));
        }
        self.recording = Some(Collector::new(every));
        let r = self.acked(&Request::Record {
            every_n_ticks: every,
        });
        if r.is_err() {
            self.recording = None;
        }
        r
    }

    /// Listens for `duration`, collecting records (and dropping anything else).
    pub fn pump(&mut self, duration: Duration) -> Result<(), ToolError> {
        let deadline = later(duration);
        // No request awaits its answer while listening.
        while let Next::Frame(f) = self.next_frame(deadline, None)? {
            self.other(f);
        }
        Ok(())
    }

    /// The samples collected since the last call.
    pub fn take_samples(&mut self) -> Vec<TickSample> {
        self.recording
            .as_mut()
            .map_or_else(Vec::new, |c| std::mem::take(&mut c.samples))
    }

    /// The recording's counters so far.
    pub fn recording_stats(&self) -> Option<&RecordingStats> {
        self.recording.as_ref().map(|c| &c.stats)
    }

    /// Stops the stream (`Record { 0 }`), collects the frames still in flight, and returns the
    /// remaining samples and the recording's counters. Losses are reported by
    /// [`RecordingStats::check`], not here: the caller may keep what arrived.
    pub fn stop_recording(&mut self) -> Result<(Vec<TickSample>, RecordingStats), ToolError> {
        let r = self.acked(&Request::Record { every_n_ticks: 0 });
        // Frames already queued in the drive or the adapter still arrive after the ack.
        if r.is_ok() {
            self.pump(Duration::from_millis(50))?;
        }
        let c = self.recording.take();
        r?;
        Ok(c.map_or_else(Default::default, |c| (c.samples, c.stats)))
    }
}

#[cfg(test)]
mod tests;

/// A reply whose frame arrived intact (the CRC holds) but whose content this side refuses: a
/// field out of range, a length or a kind it does not know. A drive and a `beltctl` of
/// different protocol versions; asking again cannot help.
fn is_reply_unreadable(r: &Rejected) -> bool {
    r.kind >= 0x80
        && matches!(
            r.error,
            LinkError::OutOfRange | LinkError::BadLength | LinkError::UnknownKind
        )
}

/// `now + d`, a year at most (no overflow panic on any duration).
pub fn later(d: Duration) -> Instant {
    Instant::now() + d.min(Duration::from_secs(365 * 86_400))
}
