//! The wire tap: a transport that copies every byte it sends and receives, with the time on the
//! common clock, into [`WireFrame`]s the loop publishes after each cycle for the black box. A
//! copy into buffers allocated once: no I/O, allocation or logging on the control path, and
//! nothing here waits for the reader (the plane's queue overwrites its oldest frame). A cycle
//! fills one frame; the servos' set-up before the loop, or a bus reopened, fills several.

use crate::transport::{Transport, TransportError};
use std::time::Duration;
use telemetry::clock::monotonic_ns;
use telemetry::wire::{Direction, WireFrame};

/// Frames a tap holds between two cycles' hand-overs (32 kB, 1024 chunks): twice what the
/// set-up of a whole bus moves before the loop's first cycle (about 520 chunks with its
/// transactions' discard marks; 8 frames lost 577 bytes of it). Beyond them bytes are counted
/// lost.
pub const TAP_FRAMES: usize = 16;

/// `inner` with its traffic recorded.
pub struct Tapped<T> {
    inner: T,
    frames: Box<[WireFrame; TAP_FRAMES]>,
    /// The frame being filled.
    current: usize,
}

impl<T> Tapped<T> {
    /// Taps `inner`.
    pub fn new(inner: T) -> Self {
        Tapped {
            inner,
            frames: Box::new([WireFrame::default(); TAP_FRAMES]),
            current: 0,
        }
    }

    /// Records one chunk, in the next frame when the current one cannot take it.
    fn record(&mut self, direction: Direction, bytes: &[u8]) {
        let now = monotonic_ns();
        if !self.frames[self.current].fits(bytes.len()) && self.current + 1 < TAP_FRAMES {
            self.current += 1;
        }
        self.frames[self.current].record(direction, now, bytes);
    }

    /// The link under the tap.
    pub fn inner(&self) -> &T {
        &self.inner
    }
}

impl<T: Transport> Transport for Tapped<T> {
    fn baud(&self) -> u32 {
        self.inner.baud()
    }

    fn send(&mut self, bytes: &[u8]) -> Result<(), TransportError> {
        let sent = self.inner.send(bytes);
        let direction = match sent {
            Ok(()) => Direction::Sent,
            Err(_) => Direction::SendFailed,
        };
        self.record(direction, bytes);
        sent
    }

    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, TransportError> {
        let n = self.inner.receive(buf, timeout)?;
        if let Some(got) = buf.get(..n) {
            self.record(Direction::Received, got);
        }
        Ok(n)
    }

    fn discard_input(&mut self) -> Result<(), TransportError> {
        self.record(Direction::Discarded, &[]);
        self.inner.discard_input()
    }

    fn reopen(&mut self) -> Result<(), TransportError> {
        self.inner.reopen()?;
        self.record(Direction::Reopened, &[]);
        Ok(())
    }

    fn set_baud(&mut self, baud: u32) -> Result<(), TransportError> {
        self.inner.set_baud(baud)?;
        self.record(Direction::BaudChanged, &baud.to_le_bytes());
        Ok(())
    }

    fn take_wire(&mut self, publish: &mut dyn FnMut(&mut WireFrame)) {
        for frame in &mut self.frames[..=self.current] {
            if !frame.is_empty() {
                publish(frame);
            }
            frame.clear();
        }
        self.current = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::VecDeque;

    /// A link that answers each send with the bytes queued for it.
    struct Echo(VecDeque<u8>);

    impl Transport for Echo {
        fn baud(&self) -> u32 {
            1_000_000
        }
        fn send(&mut self, bytes: &[u8]) -> Result<(), TransportError> {
            self.0.extend(bytes.iter().map(|b| b ^ 0xFF));
            Ok(())
        }
        fn receive(&mut self, buf: &mut [u8], _: Duration) -> Result<usize, TransportError> {
            let n = buf.len().min(self.0.len()).min(3);
            for b in buf.iter_mut().take(n) {
                *b = self.0.pop_front().unwrap_or(0);
            }
            Ok(n)
        }
        fn discard_input(&mut self) -> Result<(), TransportError> {
            self.0.clear();
            Ok(())
        }
    }

    #[test]
    fn every_byte_sent_and_received_is_in_the_frame_in_order_with_rising_times() {
        let mut t = Tapped::new(Echo(VecDeque::new()));
        t.send(&[1, 2, 3, 4]).unwrap();
        let mut buf = [0u8; 8];
        let mut got = Vec::new();
        loop {
            let n = t.receive(&mut buf, Duration::ZERO).unwrap();
            if n == 0 {
                break;
            }
            got.extend_from_slice(&buf[..n]);
        }
        assert_eq!(got, [0xFE, 0xFD, 0xFC, 0xFB]);
        let chunks = taken(&mut t);
        assert_eq!(
            chunks.len(),
            3,
            "one send, two non-empty receives: {chunks:?}"
        );
        assert_eq!(chunks[0].0, Direction::Sent);
        assert_eq!(chunks[0].2, [1, 2, 3, 4]);
        let received: Vec<u8> = chunks[1..].iter().flat_map(|c| c.2.clone()).collect();
        assert_eq!(received, got);
        assert!(chunks.windows(2).all(|w| w[0].1 <= w[1].1));
        assert!(taken(&mut t).is_empty(), "taken once");
    }

    fn taken(t: &mut Tapped<Echo>) -> Vec<(Direction, u64, Vec<u8>)> {
        let mut out = Vec::new();
        t.take_wire(&mut |f| {
            assert_eq!(f.lost_bytes, 0);
            out.extend(f.chunks().map(|(d, t, b)| (d, t, b.to_vec())))
        });
        out
    }

    /// A link whose writes fail.
    struct Broken;

    impl Transport for Broken {
        fn baud(&self) -> u32 {
            1_000_000
        }
        fn send(&mut self, _: &[u8]) -> Result<(), TransportError> {
            Err(TransportError::Io {
                device: "/dev/gone".into(),
                source: std::io::Error::other("unplugged"),
            })
        }
        fn receive(&mut self, _: &mut [u8], _: Duration) -> Result<usize, TransportError> {
            Ok(0)
        }
        fn discard_input(&mut self) -> Result<(), TransportError> {
            Ok(())
        }
    }

    #[test]
    fn a_failed_write_a_discard_and_a_reopen_are_marked_and_the_error_passes_through() {
        let mut t = Tapped::new(Broken);
        t.discard_input().unwrap();
        assert!(t.send(&[1, 2]).is_err(), "the link's error reaches the bus");
        t.reopen().unwrap();
        let mut marks = Vec::new();
        t.take_wire(&mut |f| marks.extend(f.chunks().map(|(d, _, b)| (d, b.to_vec()))));
        assert_eq!(
            marks,
            vec![
                (Direction::Discarded, vec![]),
                (Direction::SendFailed, vec![1, 2]),
                (Direction::Reopened, vec![]),
            ]
        );
        assert!(
            t.set_baud(500_000).is_err(),
            "a link with one rate refuses, unmarked"
        );
        let mut n = 0;
        t.take_wire(&mut |f| n += f.chunks().count());
        assert_eq!(n, 0);
    }

    #[test]
    fn a_set_up_s_many_chunks_go_on_in_the_next_frames_and_only_beyond_them_are_lost() {
        let mut t = Tapped::new(Echo(VecDeque::new()));
        // Found by the black box's test: a bus's set-up before the first cycle is ~150
        // chunks, beyond one frame's 64.
        let per_frame = telemetry::wire::MAX_WIRE_CHUNKS;
        for k in 0..(per_frame * 3) {
            t.send(&[k as u8, 0xAA]).unwrap();
        }
        let sent: Vec<u8> = taken(&mut t).into_iter().flat_map(|c| c.2).collect();
        let want: Vec<u8> = (0..per_frame * 3).flat_map(|k| [k as u8, 0xAA]).collect();
        assert_eq!(sent, want);
        for _ in 0..(per_frame * TAP_FRAMES + 5) {
            t.send(&[1]).unwrap();
        }
        let mut lost = 0;
        t.take_wire(&mut |f| lost += f.lost_bytes);
        assert_eq!(lost, 5);
    }
}
