//! An in-memory fake drive for the library's tests.

use std::collections::VecDeque;
use std::io::{self, Read, Write};
use std::time::Duration;

use belt_link::{encode, Receiver, Reply, Request, MAX_FRAME};

use crate::link::{Link, LinkOptions};

/// One frame on the wire.
pub fn wire(seq: u8, reply: &Reply) -> Vec<u8> {
    let mut buf = [0u8; MAX_FRAME];
    let n = encode(seq, reply, &mut buf);
    buf[..n].to_vec()
}

type Answer = Box<dyn FnMut(u8, Request) -> Vec<u8> + Send>;

/// A port whose other end is a closure: every request written is decoded and answered with the
/// bytes the closure returns, readable at once.
pub struct Fake {
    rx: Receiver,
    input: VecDeque<u8>,
    answer: Answer,
}

impl Fake {
    pub fn link(answer: impl FnMut(u8, Request) -> Vec<u8> + Send + 'static) -> Link {
        let fake = Fake {
            rx: Receiver::new(),
            input: VecDeque::new(),
            answer: Box::new(answer),
        };
        Link::new(Box::new(fake), "fake", OPTS)
    }
}

pub const OPTS: LinkOptions = LinkOptions {
    timeout: Duration::from_millis(30),
    tries: 3,
};

impl Write for Fake {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        for &b in buf {
            if let Some(Ok(f)) = self.rx.push::<Request>(b) {
                let out = (self.answer)(f.seq, f.msg);
                self.input.extend(out);
            }
        }
        Ok(buf.len())
    }
    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

impl Read for Fake {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        if self.input.is_empty() {
            return Err(io::ErrorKind::WouldBlock.into());
        }
        let n = buf.len().min(self.input.len());
        for (d, s) in buf.iter_mut().zip(self.input.drain(..n)) {
            *d = s;
        }
        Ok(n)
    }
}

/// The drive's own endpoint and core (the paper rig's configuration), answering in line as the
/// firmware does; `lose_reply` drops the replies it picks (a reply lost on the way).
pub fn endpoint_drive(mut lose_reply: impl FnMut(&Request) -> bool + Send + 'static) -> Link {
    use belt_link::Receiver;
    use estimator_core::drive::{Drive, DriveConfig};
    use estimator_core::endpoint::{Effect, Endpoint};
    let mut ep = Box::new(Endpoint::new());
    let mut drive = Drive::new(&DriveConfig::paper_rig()).unwrap();
    Fake::link(move |seq, req| {
        let reply = match ep.handle_inline(&req, &mut drive).0 {
            Effect::Reply(r) => r,
            Effect::Status => Reply::Status(ep.status(&drive, &Receiver::new(), 0, 0)),
            // As the firmware applies it (without the board's current limit).
            Effect::Configure => {
                let result = ep
                    .staged_parts()
                    .map_err(Ok)
                    .and_then(|p| drive.reconfigure(p).map_err(Err));
                ep.configure_done(result).0
            }
            other => panic!("{req:?}: {other:?}"),
        };
        if lose_reply(&req) {
            return Vec::new();
        }
        wire(seq, &reply)
    })
}
