//! Properties of the incremental decoder on hostile input.

use feetech::frame::write_packet;
use feetech::{Decoder, Frame};
use proptest::prelude::*;

/// Feeds `bytes` in chunks of `chunk` and drains everything, including at the end of input.
fn decode_chunked(bytes: &[u8], chunk: usize) -> Vec<Frame> {
    let mut decoder = Decoder::new();
    let mut frames = Vec::new();
    for piece in bytes.chunks(chunk.max(1)) {
        let mut rest = piece;
        while !rest.is_empty() {
            let taken = decoder.push(rest);
            rest = &rest[taken..];
            while let Some(result) = decoder.next_frame() {
                if let Ok(frame) = result {
                    frames.push(frame);
                }
            }
        }
    }
    while let Some(result) = decoder.finish() {
        if let Ok(frame) = result {
            frames.push(frame);
        }
    }
    frames
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 600, .. ProptestConfig::default() })]

    /// Random bytes in random chunks never panic, and everything that comes out is checksum-valid.
    #[test]
    fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..2048), chunk in 1usize..64) {
        for frame in decode_chunked(&bytes, chunk) {
            let mut out = [0u8; 300];
            let n = frame.encode(&mut out).unwrap();
            prop_assert!(n >= 6);
        }
    }

    /// Bytes biased towards headers (many 0xFF) stress the resync paths.
    #[test]
    fn header_heavy_bytes_never_panic(bytes in proptest::collection::vec(prop_oneof![Just(0xFFu8), Just(0x01), Just(0x02), any::<u8>()], 0..1024)) {
        decode_chunked(&bytes, 7);
    }

    /// A valid packet surrounded by garbage is always recovered, whatever the garbage and however
    /// the bytes are split.
    #[test]
    fn packet_in_garbage_is_recovered(
        before in proptest::collection::vec(any::<u8>(), 0..300),
        after in proptest::collection::vec(any::<u8>(), 0..300),
        id in 0u8..=0xFD,
        code in 0u8..=0x7F,
        params in proptest::collection::vec(any::<u8>(), 0..40),
        chunk in 1usize..40,
    ) {
        let mut packet = [0u8; 300];
        let n = write_packet(&mut packet, id, code, &params).unwrap();
        let mut stream = before.clone();
        stream.extend_from_slice(&packet[..n]);
        stream.extend_from_slice(&after);
        let frames = decode_chunked(&stream, chunk);
        let wanted = Frame::new(id, code, &params).unwrap();
        prop_assert!(frames.contains(&wanted), "lost {:?} in {} garbage bytes before", wanted, before.len());
    }
}
